//! `twinstack-cli`: the `twinstack` command-line tool's subcommands ([`commands`]) and the
//! studies it runs on the simulated board.
//!
//! * [`demo`] — the first paper's study on the simulated board and stage: identification
//!   tables, tracking with each compensator, figures (`twinstack demo`).
//! * [`closed_loop`] — sensor feedback around the compensator: the tracking table and the
//!   notch's step (`twinstack closed-loop`).
//! * [`learn`] — learning feedforward for periodic motion on the simulated stage;
//!   [`learn_link`] — the same on a board over its link (`twinstack learn`).
//! * [`tracking`] — open-loop tracking on the laboratory stage, a stage outside the model
//!   family: excite, identify, compensate, score (`twinstack lab-stage`).
//! * [`board_link`] — what every board command shares: `--port`, `--baud`, `--timeout-ms`,
//!   and connecting.

pub mod board_link;
pub mod closed_loop;
pub mod commands;
pub mod demo;
pub mod learn;
pub mod learn_link;
pub mod plot;
pub mod tracking;
