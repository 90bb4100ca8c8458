//! Where each tick's setpoint comes from: the sources that can drive the outputs, one at a
//! time.
//!
//! * [`setpoint_stream`] — the queue the host streams into (interpolated when the stream is
//!   slower than the control rate), and the choice between it and the built-in generator.
//! * [`waveform`] — the built-in sine and triangle generator.
//! * [`scan`] — raster, Lissajous and spiral scans with their pixel, line and frame clocks, and
//!   the external trigger input.
//! * [`sequence`] — TTL-stepped position lists with a "settled" output.
//! * [`analog_input`] — the analog setpoint input (the board as a linearising front-end).

pub mod analog_input;
pub mod scan;
pub mod sequence;
pub mod setpoint_stream;
pub mod waveform;
