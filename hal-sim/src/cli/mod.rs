//! The `hal-sim` subcommands, one module each: `run(&Args) -> anyhow::Result<()>`.

pub mod closed_loop;
pub mod compensate;
pub mod demo;
pub mod identify;
pub mod predict;
