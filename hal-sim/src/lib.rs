//! `hal-sim`: the host twin of the twinstack board and the PC-side tools.
//!
//! * [`plant`] — the dual-stack piezo stage (coupled and `K_0 → ∞` models, exact
//!   discretisation) with "truth" hysteresis per stack.
//! * [`converters`] — emulated DACs, amplifiers, sensor and ADCs, including the external SPI
//!   chips (DAC8562/3, ADS8689) at the wire level.
//! * [`sim_board`] — [`sim_board::SimBoard`]: all of it behind the library's board traits.
//! * [`sim_device`] — [`sim_device::SimDevice`]: the board, the library's control loop and
//!   command handler in-process, on a modelled UART, behind [`link::Transport`].
//! * [`identification`], [`measured_data`], [`param_file`] — fitting models to measured data,
//!   the CSV reader and the versioned parameter file.
//! * [`stage_model`] — an identified model as the board runs it (scaling, sensor sign and
//!   lag), run over whole records in fixed point and in the `f64` reference; [`plot`] — the
//!   identification figure; [`output_file`] — outputs written only when complete.
//! * [`mod@reference`] — the `f64` reference of every model, the specification the library's
//!   fixed-point code is checked against; [`accuracy`] — the fixed-point vs `f64` error table.
//! * [`closed_loop`] — sensor feedback around the compensator: the tracking table and the
//!   notch's step.
//! * [`golden`] — golden vectors: generating them, and checking them against the `f64` tick.
//! * [`link`] — the host end of the board link: [`link::Transport`] and the protocol client;
//!   [`port`] — `--port` values and opening them (the simulated board too); [`board_link`] —
//!   connecting to a board from `--port` / `--baud` / `--timeout-ms`.
//! * [`dual_stage_sim`] — the piezo stage on a ball-screw coarse stage ([`plant::ball_screw`]),
//!   with the emulated step/dir output and encoders ([`coarse_stage`]): the dual-stage controller
//!   end to end; [`coarse_rig`] — the same stage as a board on the wire (a [`sim_device::SimDevice`]
//!   whose coarse axis runs the library's supervisor, with fault injection).
//! * [`tracking`] — open-loop tracking on [`plant::lab_stage`], a stage outside the model
//!   family: excite, identify, compensate, score (`twinstack lab-stage`).
//! * [`virtual_board`] — a [`sim_device::SimDevice`] served over TCP in real time, keeping its
//!   state from one client to the next (`twinstack virtual-board`).
//! * [`calibrate`] — one-command calibration over the board link: excite with the board's
//!   waveform generator, record, identify, load, store, verify (`twinstack calibrate`).
//! * [`board_requests`] — what the board commands and the Python package share: the settings a load
//!   sends and its checks, waveform and capture requests, the status as JSON.
//! * [`cli`] — the `hal-sim` subcommands.

pub mod analog_source;
pub mod coarse_rig;
pub mod coarse_stage;
pub mod converters;
pub mod dual_stage_sim;
pub mod plant;
pub mod port;
pub mod sim_board;
pub mod sim_camera;
pub mod sim_device;
pub mod virtual_board;
