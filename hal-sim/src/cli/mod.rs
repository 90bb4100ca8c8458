//! The `hal-sim` subcommands, one module each: `run(&Args) -> anyhow::Result<()>`.
//!
//! Board commands (`stream`, `load`, `params`, `mode`, `recall`, `status`, `waveform`, `stop`,
//! `record`) share
//! [`board_link`]'s `--port` / `--baud` / `--timeout-ms`.

pub mod board_link;
pub mod closed_loop;
pub mod compensate;
pub mod demo;
pub mod dual_stage;
pub mod golden;
pub mod identify;
pub mod lab_stage;
pub mod load;
pub mod params;
pub mod predict;
pub mod record;
pub mod status;
pub mod stop;
pub mod stream;
pub mod virtual_board;
pub mod waveform;
