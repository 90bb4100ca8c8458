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
//! * [`params`] — physical (`f64`) parameter sets and their validation ([`ParamError`]).
//! * [`reference`] — `f64` reference implementations the fixed-point code is checked against.
//! * [`converters`] — SPI drivers of the external DAC (DAC8562/3) and sensor ADC (ADS8689).
//!
//! Everything here is allocation-free; the per-sample `step` functions have no panic path
//! and no unbounded loop.
#![no_std]
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod board;
pub mod control;
pub mod converters;
pub mod drive;
pub mod duhem;
pub mod fixed_point;
pub mod params;
pub mod play_operator;
pub mod prandtl_ishlinskii;
pub mod protocol;
pub mod reference;
pub mod scaling;
pub mod setpoint_stream;
pub mod settings;
pub mod waveform;

pub use params::{DuhemParams, ParamError, PiParams, Thresholds, MAX_OPERATORS};
pub use scaling::Scaling;
