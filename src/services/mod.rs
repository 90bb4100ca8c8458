//! The services beside the control law: they watch the tick's signals and serve the host.
//!
//! * [`snapshot`] — the ring the tick pushes one snapshot a tick onto: the services' only
//!   input from the tick.
//! * [`consumer`] — the services that consume it below the tick: the recorder and telemetry's
//!   tap, one resource apart from the tick's.
//! * [`observer`] — the forward observer and the drift check, where the stage has a sensor:
//!   fed each tick's applied drive and measurement from the snapshots.
//! * [`recorder`] — the data recorder (triggered capture with pre-trigger and decimation).
//! * [`decimation`] — one tick in every `n`: the recorder's and telemetry's countdown.
//! * [`telemetry`] — continuous telemetry: the tap, the queue, the frame packer.
//! * [`learning`] — learning feedforward for periodic motion (a phase-indexed correction table,
//!   updated from the tracking error).

pub mod consumer;
pub mod decimation;
pub mod learning;
pub mod observer;
pub mod recorder;
pub mod snapshot;
pub mod telemetry;
