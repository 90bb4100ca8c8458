//! `hal-sim`: the simulated twinstack board and stage — the emulated converters, the plant,
//! and the library's own control loop and command handler driving them, behind the host link.
//!
//! * [`plant`] — the dual-stack piezo stage (coupled and `K_0 → ∞` models, exact
//!   discretisation) with "truth" hysteresis per stack (the `f64` reference models of
//!   `twinstack-identify`); [`plant::lab_stage`], a stage outside the model family;
//!   [`plant::ball_screw`], the coarse stage.
//! * [`converters`] — emulated DACs, amplifiers, sensor and ADCs, including the external SPI
//!   chips (DAC8562/3, ADS8689) at the wire level.
//! * [`sim_board`] — [`sim_board::SimBoard`]: all of it behind the library's board traits.
//! * [`sim_device`] — [`sim_device::SimDevice`]: the board, the library's control loop and
//!   command handler in-process, on a modelled UART, behind the link's `Transport`;
//!   [`sim_camera`] — a camera on its trigger input; [`analog_source`] — the voltage on its
//!   analog setpoint input.
//! * [`dual_stage_sim`] — the piezo stage on a ball-screw coarse stage, with the emulated
//!   step/dir output and encoders ([`coarse_stage`]): the dual-stage controller end to end;
//!   [`coarse_rig`] — the same stage as a board on the wire (a [`sim_device::SimDevice`] whose
//!   coarse axis runs the library's supervisor, with fault injection).
//! * [`virtual_board`] — a [`sim_device::SimDevice`] served over TCP in real time, keeping its
//!   state from one client to the next (`twinstack virtual-board`).
//! * [`port`] — `--port` values and opening them: serial ports, sockets and the simulated board.

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
