//! # twinstack — hysteresis compensation for dual-stack piezo nanopositioners
//!
//! This `no_std` library holds every algorithm the twinstack board runs, so that the
//! firmware interrupt and the host simulator (`hal-sim`) call the very same code.
//!
//! The folders say where each part runs:
//!
//! * In the control interrupt: [`control`] — the control law (the tick, the sensor, feedback,
//!   notch, bumpless mode switching, the differential drive and its limits) — and the
//!   [`models`] it runs (P–I, generalised P–I, Duhem, Bouc–Wen, creep), over the Q-formats of
//!   [`fixed_point`] and the physical-to-normalised map of [`scaling`]. Every part checks its
//!   own settings and says why it refuses one in the words of [`refusal`] (the field and the
//!   rule it broke, as the wire reports it).
//! * Feeding it and watching it, on the board: [`sources`] — where each tick's setpoint comes
//!   from (the host's stream, the waveform generator, scans, TTL sequences, the analog input);
//!   [`services`] — the recorder, telemetry and the learning feedforward; [`control_loop`] —
//!   the tick side that puts sources, control law and services together for one interrupt.
//! * Off the interrupt, on the board: [`command_handler`] — requests in, responses out;
//!   [`protocol`] — the UART's frames and messages; [`config`] — the settings type, its
//!   validation, the flash record and the tick budget that admits a configuration.
//! * The board itself: [`board`] — the traits the converters sit behind and the hardware's
//!   facts; `hardware` (firmware build only) — STM32F405 registers; [`converters`] — SPI
//!   drivers of the external DAC (DAC8562/3) and sensor ADC (ADS8689); [`dual_stage`] — the
//!   ball-screw coarse stage carrying the piezo, under one controller.
//!
//! Everything here is allocation-free; the per-sample `step` functions have no panic path
//! and no unbounded loop.
#![no_std]
// Host builds forbid `unsafe` outright; the firmware build only denies it, so that the
// register-level `hardware` module can opt in with `#[allow(unsafe_code)]`, and so can the
// five dual-16-bit DSP instructions of `play_operator` (one `asm!` each, registers only).
#![cfg_attr(not(target_os = "none"), forbid(unsafe_code))]
#![cfg_attr(target_os = "none", deny(unsafe_code))]
#![warn(missing_docs)]

pub mod board;
pub mod command_handler;
pub mod config;
pub mod control;
pub mod control_loop;
pub mod converters;
pub mod divisor;
pub mod dual_stage;
pub mod fixed_point;
#[cfg(target_os = "none")]
pub mod hardware;
pub mod models;
pub mod protocol;
pub mod refusal;
pub mod scaling;
pub mod services;
pub mod sources;

/// The `heapless` the protocol's messages are built from (`Vec` of setpoints, chunks), so
/// host code builds them without naming the crate itself.
pub use heapless;
pub use models::params::{
    BoucWenParams, DuhemParams, ParamError, PiParams, Thresholds, MAX_OPERATORS,
};
pub use scaling::Scaling;

/// Marks the branch that calls it as the rare one, so that the compiler lays that branch out
/// of line and the common path runs straight on: on the board every taken branch refills the
/// pipeline from flash (up to 5 wait states), so a tick that skips what is off must not jump
/// over it. The tick calls it where what follows is charged apart in the tick budget (a
/// source other than the stream, the learning, the trigger's armed edge, a trigger pulse) —
/// never on a path of the tick's own worst case (a limit, a reload), which it would lengthen.
/// A `#[cold]` call in an arm is what gives the branch its weights (`core::hint::cold_path`
/// loses them across crates in the toolchain this builds with); the optimiser then removes
/// the call to the empty function.
#[cold]
#[inline(never)]
pub(crate) fn rare() {}
