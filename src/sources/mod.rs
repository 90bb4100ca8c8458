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
//!
//! [`SetpointSource`] names which one is in force; the dual-stage images add the coarse axis's
//! ramp ([`crate::dual_stage::link`]).

pub mod analog_input;
pub mod scan;
pub mod sequence;
pub mod setpoint_stream;
pub mod waveform;

/// Where the tick's setpoint comes from. One at a time: starting one stops the others (the
/// control loop's command methods switch it, between two ticks, so the tick dispatches once),
/// and the tick budget charges each by what it costs above the stream
/// ([`crate::config::tick_budget::source_cycles`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum SetpointSource {
    /// The stream: the setpoint queue or the board's waveform generator, or, stopped, the
    /// setpoint it holds (also while a scan waits for its trigger).
    #[default]
    Stream,
    /// A scan generated on the board ([`scan`]).
    Scan,
    /// A TTL-stepped sequence, armed ([`sequence`]).
    Sequence,
    /// The analog setpoint input, running ([`analog_input`]).
    Analog,
    /// The coarse axis's ramp (the dual-stage images, once the coarse task has posted one):
    /// from then on the coarse axis owns the piezo's setpoint.
    Coarse,
}
