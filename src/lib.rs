//! # twinstack — hysteresis compensation for dual-stack piezo nanopositioners
//!
//! This `no_std` library holds every algorithm the twinstack board runs, so that the
//! firmware interrupt and the host simulator (`hal-sim`) call the very same code.
//!
//! * [`fixed_point`] — the Q-formats every signal and coefficient of the tick uses.
//! * [`scaling`] — the affine map between physical units (volts, micrometres) and the
//!   normalised fixed-point signals.
//! * [`play_operator`] — the play (backlash) operator, the building block of P–I.
//! * [`prandtl_ishlinskii`] — forward and analytic-inverse Prandtl–Ishlinskii models.
//! * [`duhem`] — Duhem forward observer and inverse Duhem compensator.
//! * [`generalised_pi`] — the generalised (asymmetric) P–I: a P–I followed by a monotone
//!   dead-zone map, and its analytic inverse.
//! * [`creep`] — the creep operator (log-spaced first-order modes) in series with a
//!   hysteresis model, and its exact inverse.
//! * [`bouc_wen`] — generalised (asymmetric) Bouc–Wen observer and its inverse-multiplicative
//!   compensator.
//! * [`feedback`] — sensor feedback: PI(D) with anti-windup, the drift check; [`notch`] — the
//!   resonance notch (fixed-point biquad designed for the control rate); [`mode_switch`] —
//!   bumpless switching between bypass, open loop and closed loop.
//! * [`settings`] — the one settings type (physical units, serde): what the wire, the flash
//!   record, parameter files and golden vectors carry; [`refusal`] — why a setting was refused
//!   (field and rule), as the wire reports it; [`sensor`] — the position sensor.
//! * [`params`] — the models' physical (`f64`) parameters and their own checks ([`ParamError`]).
//! * [`param_store`] — the CRC-protected settings record in flash.
//! * `hardware` (firmware build only) — STM32F405 registers behind the [`board`] traits.
//! * [`control_loop`] — the tick side of the board: setpoint queue and stream or waveform,
//!   the control tick, the data recorder; [`recorder`] — the recorder itself;
//!   [`telemetry`] — continuous telemetry (the tick's tap, the queue, the frame packer).
//! * [`protocol`] — the UART protocol: frames and messages; [`command_handler`] — the board's
//!   command handler (requests in, responses out, over the tick side).
//! * [`converters`] — SPI drivers of the external DAC (DAC8562/3) and sensor ADC (ADS8689).
//! * [`dual_stage`] — the dual-actuated stage: ball-screw coarse stage + piezo fine stage under
//!   one controller (setpoint split, trapezoidal moves, centring, hand-over); [`coarse_axis`] —
//!   its step generation and quadrature counting.
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

pub mod analog_input;
pub mod board;
pub mod bouc_wen;
pub mod coarse_axis;
pub mod command_handler;
pub mod control;
pub mod control_loop;
pub mod converters;
pub mod creep;
pub mod drive;
pub mod dual_stage;
pub mod duhem;
pub mod feedback;
pub mod fixed_point;
pub mod generalised_pi;
#[cfg(target_os = "none")]
pub mod hardware;
pub mod learning;
pub mod mode_switch;
pub mod notch;
pub mod param_store;
pub mod params;
pub mod play_operator;
pub mod prandtl_ishlinskii;
pub mod protocol;
pub mod recorder;
pub mod refusal;
pub mod scaling;
pub mod scan;
pub mod sensor;
pub mod sequence;
pub mod setpoint_stream;
pub mod settings;
pub mod telemetry;
pub mod tick_budget;
pub mod waveform;

/// The `heapless` the protocol's messages are built from (`Vec` of setpoints, chunks), so
/// host code builds them without naming the crate itself.
pub use heapless;
pub use params::{BoucWenParams, DuhemParams, ParamError, PiParams, Thresholds, MAX_OPERATORS};
pub use scaling::Scaling;
