//! `hal-sim`: the host twin of the twinstack board and the PC-side tools.
pub mod accuracy;
pub mod cli;
pub mod identification;
pub mod measured_data;
pub mod output_file;
pub mod param_file;
pub mod plot;
pub mod stage_model;
