//! The `hal-sim` subcommands, one module each: `run(&Args) -> anyhow::Result<()>`.

pub mod compensate;
pub mod demo;
pub mod dual_stage;
pub mod identify;
pub mod predict;
