//! The services beside the control law: they watch the tick's signals and serve the host.
//!
//! * [`recorder`] — the data recorder (triggered capture with pre-trigger and decimation).
//! * [`telemetry`] — continuous telemetry: the tick's tap, the queue, the frame packer.
//! * [`learning`] — learning feedforward for periodic motion (a phase-indexed correction table,
//!   updated from the tracking error).

pub mod learning;
pub mod recorder;
pub mod telemetry;
