//! Scan patterns generated on the board — raster, Lissajous, spiral — and the trigger I/O
//! that goes with them: pixel, line and frame clocks on GPIO outputs, and an external trigger
//! input that starts a stream, a scan or a capture.
//!
//! # Patterns
//!
//! Every pattern drives **x** (this board's axis: the setpoint of the tick, Q2.30 normalised
//! displacement) and defines **y** (the second axis, Q2.30: not driven here — the board has
//! one differential pair — and for the raster stepped once per line, the line clock being its
//! step signal). Since nothing on the board uses y, the tick does not compute it: it keeps
//! what the sample's y is made from (the phase, for the Lissajous figure and the spiral, whose
//! y costs a table sine and a multiply), and [`ScanGenerator::y`] computes it for the host.
//!
//! * **Raster**: `lines` lines per frame, each a trace of `pixels × ticks_per_pixel` ticks at
//!   constant speed from `offset − amplitude` to `offset + amplitude` (or back: the raster is
//!   bidirectional), then a turnaround of `turn_ticks` ticks at constant deceleration (a
//!   parabola: the velocity reverses continuously, the position overshoots the trace by
//!   `v · turn_ticks / 4`, `v` the trace's speed per tick). `turn_ticks = 0` is the plain
//!   triangle. Pixel clocks only on the trace; y steps from `y_offset − y_amplitude` to
//!   `y_offset + y_amplitude` in `lines − 1` equal steps, at each line's start.
//! * **Lissajous**: `x = offset + amplitude · sin(2π · x_cycles · f · t + π/2)`,
//!   `y = y_offset + y_amplitude · sin(2π · y_cycles · f · t + φ_y)`, one frame per `1/f` (the pattern
//!   repeats exactly: both phases are integer multiples of one `u32` accumulator). A line is
//!   one period of x. x starts at its peak, where its velocity is zero.
//! * **Spiral** (Archimedean, out and back in): `x = offset + r · sin θ`, `y = y_offset + r ·
//!   cos θ`, θ turning at `turn_hz`, `r` rising linearly from 0 to `amplitude` over `turns`
//!   turns and back to 0 over as many. A line is one turn; a frame one spiral out and in,
//!   `2 · turns` turns counted (the envelope's step is rounded down and saturates, and
//!   restarts at each frame, so frames and lines never drift apart).
//!
//! # Fixed point, cost
//!
//! Positions are Q2.30 (`SIGNAL_ONE` = 1.0). The raster's speed is Q2.30 · 2^16 per tick
//! (`i64`) and its deceleration Q2.30 · 2^16 per tick²: one or two `i64` multiplies a tick.
//! Lissajous and spiral phases are `u32` accumulators (2^32 per cycle), their sines the
//! waveform generator's interpolated quarter-wave table ([`crate::sources::waveform::unit_sine`]).
//! [`ScanGenerator::next_sample`] is O(1): no loop, no division, no allocation, no panic path;
//! every division is in [`ScanGenerator::new`] (off the tick, where the request is
//! validated). Host and board run this same code: bit for bit the same samples.
//!
//! # Start and stop
//!
//! [`ScanGenerator::start`] begins with an **approach**: the setpoint walks from where it is
//! to the pattern's first point at a quarter of the drive's slew limit (no step), and each
//! pattern's first point is one where x's velocity is zero (the raster's turnaround apex,
//! Lissajous' x peak, the spiral's centre). A scan of `frames` frames ends at such a point
//! too (the raster completes half a turnaround) and holds there; a scan stopped by the host
//! holds where it is. The drive's range and slew limits apply to these setpoints as to any
//! other (they pass through [`crate::control::Controller::tick`]).
//!
//! # Triggers
//!
//! [`ScanSample::events`] marks the ticks a pixel, line or frame starts ([`PIXEL`], [`LINE`],
//! [`FRAME`]); [`TriggerOutputs`] stretches them to pulses of `pulse_ticks` ticks (the output
//! is high on the event's tick and the `pulse_ticks − 1` after it), whose levels the board
//! writes to its GPIO pins in one BSRR store each tick (`hardware::trigger_pins`, in the board build).
//! [`ExternalTrigger`] watches the trigger input, sampled once a tick (latency at most one
//! tick), for a chosen edge while armed.

use serde::{Deserialize, Serialize};

use crate::fixed_point::{saturate_i64, signal_from_f64, SIGNAL_ONE};
use crate::refusal::{Field, Refusal, Rule};
use crate::sources::waveform::unit_sine;

/// Event / output bit: a pixel starts (pixel clock).
pub const PIXEL: u8 = 1 << 0;
/// Event / output bit: a line starts (line clock; the raster's slow-axis step).
pub const LINE: u8 = 1 << 1;
/// Event / output bit: a frame starts (frame clock).
pub const FRAME: u8 = 1 << 2;
/// The trigger input's level, in the capture's trigger channel (bit 3).
pub const INPUT: u8 = 1 << 3;

/// GPIOA pin of the pixel clock output (PA1).
pub const PIXEL_PIN: u32 = 1;
/// GPIOA pin of the line clock output (PA2).
pub const LINE_PIN: u32 = 2;
/// GPIOA pin of the frame clock output (PA3).
pub const FRAME_PIN: u32 = 3;
/// GPIOA pin of the external trigger input (PA6).
pub const INPUT_PIN: u32 = 6;
/// GPIOA pin of a sequence's settled output (PA7, [`crate::sources::sequence::SETTLED`]).
pub const SETTLED_PIN: u32 = 7;

/// The GPIOA `BSRR` word that puts the four outputs at `levels` ([`PIXEL`], [`LINE`],
/// [`FRAME`] bits, and a sequence's [`crate::sources::sequence::SETTLED`]): a set bit for each high
/// output, a reset bit (bit + 16) for each low one, so one store writes all four whatever
/// they were. A few shifts and masks.
///
/// ```
/// use twinstack::sources::scan::{bsrr_word, LINE};
/// use twinstack::sources::sequence::SETTLED;
/// assert_eq!(bsrr_word(LINE), 1 << 2 | (1 << 1 | 1 << 3 | 1 << 7) << 16);
/// assert_eq!(bsrr_word(SETTLED), 1 << 7 | (1 << 1 | 1 << 2 | 1 << 3) << 16);
/// ```
#[inline(always)]
pub const fn bsrr_word(levels: u8) -> u32 {
    let high = (levels & 0b111) as u32 | (((levels >> 4) & 1) as u32) << (SETTLED_PIN - PIXEL_PIN);
    let all = 0b111 | 1 << (SETTLED_PIN - PIXEL_PIN);
    let low = !high & all;
    (high << PIXEL_PIN) | (low << (PIXEL_PIN + 16))
}

/// The largest setpoint step per tick (Q2.30 normalised) a drive slewing at `slew_rate`
/// (V/s) over `min_voltage … max_voltage` follows at `rate_hz`, taking the normalised stroke
/// (2.0) to span the voltage range, as in bypass: the `max_step` a board validates scans
/// with (the host computes it the same way to replay a scan).
///
/// ```
/// // 1 V/µs over 0–140 V at 50 kHz: 20 V a tick, 2 · 20 / 140 of the stroke.
/// let step = twinstack::sources::scan::slew_step(1e6, 0.0, 140.0, 50_000.0);
/// assert_eq!(step, twinstack::fixed_point::signal_from_f64(40.0 / 140.0));
/// ```
pub fn slew_step(slew_rate: f64, min_voltage: f64, max_voltage: f64, rate_hz: f64) -> i32 {
    let step = 2.0 * slew_rate / (rate_hz * (max_voltage - min_voltage));
    // NaN (a zero span, refused by the settings anyway) maps to 0, then 1 LSB in `new`.
    signal_from_f64(step.min(2.0))
}

/// Most ticks one raster trace may take (`pixels × ticks_per_pixel`): 2^20, 21 s at 50 kHz.
pub const MAX_TRACE_TICKS: u32 = 1 << 20;

/// Extra fractional bits of the raster's speed and deceleration (Q2.30 · 2^16).
const FINE: u32 = 16;

/// A raster: bidirectional lines with parabolic turnarounds (normalised units, −1…1).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RasterScan {
    /// Lines per frame, ≥ 1.
    pub lines: u16,
    /// Pixels per line, ≥ 1 (a trace takes `pixels × ticks_per_pixel` ticks).
    pub pixels: u16,
    /// Ticks of each turnaround (0: a plain triangle, with a velocity step at each corner).
    pub turn_ticks: u16,
    /// Centre of the fast axis (x), normalised.
    pub offset: f64,
    /// Half the trace's span, normalised (> 0); the turnarounds overshoot it by `v·T/4`.
    pub amplitude: f64,
    /// Centre of the slow axis (y), normalised.
    pub y_offset: f64,
    /// Half the slow axis' span, normalised (≥ 0).
    pub y_amplitude: f64,
}

impl RasterScan {
    /// A square raster centred on the middle of the range: `lines` lines of `pixels` pixels
    /// over ±`amplitude` (normalised) on both axes, `turn_ticks` per turnaround.
    ///
    /// ```
    /// use twinstack::sources::scan::RasterScan;
    /// let r = RasterScan::centred(4, 16, 20, 0.5);
    /// assert_eq!((r.offset, r.amplitude, r.y_offset, r.y_amplitude), (0.0, 0.5, 0.0, 0.5));
    /// ```
    pub const fn centred(lines: u16, pixels: u16, turn_ticks: u16, amplitude: f64) -> Self {
        Self {
            lines,
            pixels,
            turn_ticks,
            offset: 0.0,
            amplitude,
            y_offset: 0.0,
            y_amplitude: amplitude,
        }
    }
}

/// A Lissajous figure: x and y sines at `x_cycles` and `y_cycles` times `frame_hz`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LissajousScan {
    /// Frames per second (the figure's repeat rate), Hz.
    pub frame_hz: f64,
    /// Periods of x per frame, ≥ 1.
    pub x_cycles: u16,
    /// Periods of y per frame, ≥ 1.
    pub y_cycles: u16,
    /// y's phase at the start, degrees (x starts at its peak, +90°).
    pub y_phase_deg: f64,
    /// Centre of x, normalised.
    pub offset: f64,
    /// Amplitude of x, normalised (> 0).
    pub amplitude: f64,
    /// Centre of y, normalised.
    pub y_offset: f64,
    /// Amplitude of y, normalised (≥ 0).
    pub y_amplitude: f64,
}

/// An Archimedean spiral out and back in.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SpiralScan {
    /// Turns per second, Hz.
    pub turn_hz: f64,
    /// Turns from the centre out (as many back in), ≥ 1.
    pub turns: u16,
    /// Centre of x, normalised.
    pub offset: f64,
    /// Outer radius, normalised (> 0; x and y both reach it).
    pub amplitude: f64,
    /// Centre of y, normalised.
    pub y_offset: f64,
}

/// Which pattern.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum ScanPattern {
    /// Raster lines with turnarounds.
    Raster(RasterScan),
    /// Lissajous figure.
    Lissajous(LissajousScan),
    /// Spiral out and in.
    Spiral(SpiralScan),
}

/// A scan as the host asks for it (protocol v6 `Scan`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScanRequest {
    /// The pattern.
    pub pattern: ScanPattern,
    /// Ticks per pixel (the pixel clock's period), more than the trigger pulse's ticks.
    pub ticks_per_pixel: u16,
    /// Frames to scan, then hold; 0: until stopped.
    pub frames: u16,
    /// Wait for the external trigger input (armed by `Trigger`) instead of starting now.
    pub on_trigger: bool,
}

/// Which edge of the trigger input fires it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum TriggerEdge {
    /// The input is ignored.
    Off,
    /// Low to high.
    Rising,
    /// High to low.
    Falling,
}

/// Trigger I/O settings (protocol v6 `Trigger`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TriggerConfig {
    /// Width of the pixel, line and frame pulses, ticks (0: the outputs stay low).
    pub pulse_ticks: u16,
    /// The input's edge; any but `Off` arms the input (one shot: send again to re-arm).
    pub input: TriggerEdge,
    /// The edge also starts the setpoint stream (besides a scan waiting for it and a capture
    /// armed on [`crate::services::recorder::Trigger::External`]).
    pub start_stream: bool,
}

/// One tick of a scan. The second axis is not in it: the board does not drive y, so the tick
/// does not compute it; [`ScanGenerator::y`] does, on demand, for the host.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ScanSample {
    /// Fast axis, this board's setpoint, Q2.30 normalised displacement.
    pub x: i32,
    /// [`PIXEL`], [`LINE`], [`FRAME`]: what starts on this tick.
    pub events: u8,
}

/// What the last sample's y is made from: the phase the sample was taken at for the two
/// patterns whose y is a sine (one table sine and a multiply each, left out of the tick), y
/// itself otherwise.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum LastY {
    /// y itself, Q2.30 (the approach, the raster).
    Held(i32),
    /// The Lissajous figure's frame phase.
    Lissajous(u32),
    /// The spiral's angle and envelope phase.
    Spiral(u32, u32),
}

/// Where the generator is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Phase {
    /// Walking to the pattern's first point.
    Approach,
    /// Running the pattern.
    Pattern,
    /// The last frame is done: holding.
    Done,
}

/// The raster's state and constants.
#[derive(Clone, Copy, Debug)]
struct Raster {
    /// Centre, Q2.30.
    offset: i32,
    /// Half the trace, Q2.30.
    half: i32,
    /// Trace speed, Q2.30 · 2^16 per tick.
    v_fine: i64,
    /// Turnaround deceleration `v / T`, Q2.30 · 2^16 per tick².
    a_fine: i64,
    /// Ticks of a trace.
    trace: u32,
    /// Ticks of a turnaround.
    turn: u32,
    /// Tick within the trace or turnaround.
    t: u32,
    /// In a turnaround.
    turning: bool,
    /// +1 forward (rising x), −1 backward.
    dir: i32,
    /// The line the next (or current) trace is.
    line: u16,
    /// Lines per frame.
    lines: u16,
    /// The last frame's last trace is done: the turnaround stops at its apex.
    closing: bool,
    /// y of line 0, Q2.30.
    y0: i32,
    /// y step per line, Q2.30.
    y_step: i32,
}

/// The Lissajous figure's state and constants.
#[derive(Clone, Copy, Debug)]
struct Lissajous {
    offset: i32,
    amplitude: i32,
    y_offset: i32,
    y_amplitude: i32,
    /// Frame phase, 2^32 per frame.
    r: u32,
    /// Frame phase step per tick.
    step: u32,
    x_cycles: u32,
    y_cycles: u32,
    /// x's phase at r = 0 (a quarter cycle: its peak).
    x0: u32,
    /// y's phase at r = 0.
    y0: u32,
}

/// The spiral's state and constants.
#[derive(Clone, Copy, Debug)]
struct Spiral {
    offset: i32,
    amplitude: i32,
    y_offset: i32,
    /// Angle, 2^32 per turn.
    theta: u32,
    /// Angle step per tick.
    step: u32,
    /// Envelope phase, 2^32 per frame (out and in).
    e: u32,
    /// Envelope step per tick (`step / (2 · turns)`, rounded down).
    e_step: u32,
    /// Turns since the frame started.
    turns_done: u32,
    /// Turns per frame (`2 · turns`: out and back in).
    turns_per_frame: u32,
}

#[derive(Clone, Copy, Debug)]
enum Motion {
    Raster(Raster),
    Lissajous(Lissajous),
    Spiral(Spiral),
}

/// A validated scan and its progress. Build with [`ScanGenerator::new`] (off the tick), start
/// with [`ScanGenerator::start`], then one [`ScanGenerator::next_sample`] per tick.
#[derive(Clone, Debug)]
pub struct ScanGenerator {
    motion: Motion,
    phase: Phase,
    /// x now, Q2.30.
    x: i32,
    /// The last sample's y, as the tick leaves it ([`ScanGenerator::y`] computes it).
    last_y: LastY,
    /// The pattern's first point (x), Q2.30.
    start_x: i32,
    /// The pattern's first y, Q2.30.
    start_y: i32,
    /// The approach's step per tick, Q2.30, > 0.
    approach_step: i32,
    ticks_per_pixel: u16,
    /// Ticks to the next pixel clock.
    pixel_left: u16,
    /// Frames still to scan (0 with `endless`).
    frames_left: u16,
    endless: bool,
    /// Lissajous / spiral: the frame or line wrapped at the last advance (the events of the
    /// next sample).
    pending: u8,
    /// Lissajous / spiral: the last frame wrapped; the next sample is the end point.
    last: bool,
    /// Ticks a line takes (the line clock's period), as the pattern defines it.
    line_ticks: f64,
}

fn refuse(field: Field, rule: Rule) -> Refusal {
    Refusal::new(field, rule)
}

/// `|x| ≤ limit`, finite, else a refusal of `field`.
fn check_within(field: Field, x: f64, lo: f64, hi: f64) -> Result<(), Refusal> {
    crate::refusal::within(field, x, lo, hi)
}

impl ScanGenerator {
    /// Validates `request` for a board ticking at `rate_hz` whose drive slews at most
    /// `max_step` (Q2.30 normalised per tick, > 0), with trigger pulses of `pulse_ticks`
    /// ticks; every refusal names the field and the limit it broke.
    ///
    /// ```
    /// use twinstack::sources::scan::*;
    /// let raster = ScanPattern::Raster(RasterScan {
    ///     lines: 8, pixels: 16, turn_ticks: 20, offset: 0.0, amplitude: 0.5,
    ///     y_offset: 0.0, y_amplitude: 0.5,
    /// });
    /// let request = ScanRequest { pattern: raster, ticks_per_pixel: 4, frames: 1, on_trigger: false };
    /// let mut scan = ScanGenerator::new(&request, 50_000.0, 1 << 26, 1).unwrap();
    /// scan.start(0);
    /// // The approach, then 8 lines of 64 + 20 ticks: the first line clock comes with a frame clock.
    /// let first = (0..1000).map(|_| scan.next_sample()).find(|s| s.events & LINE != 0).unwrap();
    /// assert_eq!(first.events & FRAME, FRAME);
    /// assert_eq!(scan.line_ticks(), 84.0);
    /// ```
    pub fn new(
        request: &ScanRequest,
        rate_hz: f64,
        max_step: i32,
        pulse_ticks: u16,
    ) -> Result<Self, Refusal> {
        let tpp = request.ticks_per_pixel;
        if tpp == 0 || (pulse_ticks > 0 && tpp <= pulse_ticks) {
            return Err(refuse(
                Field::ScanTicksPerPixel,
                Rule::AtLeast(pulse_ticks as f64 + 1.0),
            ));
        }
        let max_step = max_step.max(1);
        let step_norm = max_step as f64 / SIGNAL_ONE as f64;
        let nyquist = 0.5 * rate_hz;
        let (motion, start_x, start_y, line_ticks) = match request.pattern {
            ScanPattern::Raster(r) => Self::raster(&r, tpp, rate_hz, step_norm)?,
            ScanPattern::Lissajous(l) => {
                if l.x_cycles == 0 || l.y_cycles == 0 {
                    return Err(refuse(Field::ScanCycles, Rule::AtLeast(1.0)));
                }
                let top = l.x_cycles.max(l.y_cycles) as f64;
                crate::refusal::finite(Field::ScanFrequency, l.frame_hz)?;
                if l.frame_hz <= 0.0 {
                    return Err(refuse(Field::ScanFrequency, Rule::Above(0.0)));
                }
                if l.frame_hz * top >= nyquist {
                    return Err(refuse(Field::ScanFrequency, Rule::Below(nyquist / top)));
                }
                amplitudes(l.offset, l.amplitude)?;
                check_within(Field::ScanAmplitude, l.y_amplitude, 0.0, 1.0)?;
                check_within(Field::ScanOffset, l.y_offset, -1.0, 1.0)?;
                if l.y_offset.abs() + l.y_amplitude > 1.0 {
                    return Err(refuse(
                        Field::ScanAmplitude,
                        Rule::AtMost(1.0 - l.y_offset.abs()),
                    ));
                }
                crate::refusal::finite(Field::ScanOffset, l.y_phase_deg)?;
                // x's fastest step: 2π · f_x · A / rate.
                let fastest =
                    core::f64::consts::TAU * l.frame_hz * l.x_cycles as f64 / rate_hz * l.amplitude;
                if fastest > step_norm {
                    let limit = l.frame_hz * step_norm / fastest;
                    return Err(refuse(Field::ScanFrequency, Rule::AtMost(limit)));
                }
                let step = libm::round(l.frame_hz / rate_hz * 4_294_967_296.0) as u32;
                let x0 = (1u32 << 30) / l.x_cycles as u32;
                let phase = libm::round(l.y_phase_deg / 360.0 * 4_294_967_296.0);
                let phase = (libm::fmod(phase, 4_294_967_296.0) + 4_294_967_296.0) as u64 as u32;
                let m = Lissajous {
                    offset: signal_from_f64(l.offset),
                    amplitude: signal_from_f64(l.amplitude),
                    y_offset: signal_from_f64(l.y_offset),
                    y_amplitude: signal_from_f64(l.y_amplitude),
                    r: 0,
                    step,
                    x_cycles: l.x_cycles as u32,
                    y_cycles: l.y_cycles as u32,
                    x0: x0.wrapping_mul(l.x_cycles as u32),
                    y0: x0.wrapping_mul(l.y_cycles as u32).wrapping_add(phase),
                };
                let (sx, sy) = (m.x_at(), m.y_at(0));
                let line = rate_hz / (l.frame_hz * l.x_cycles as f64);
                (Motion::Lissajous(m), sx, sy, line)
            }
            ScanPattern::Spiral(s) => {
                if s.turns == 0 {
                    return Err(refuse(Field::ScanLines, Rule::AtLeast(1.0)));
                }
                crate::refusal::finite(Field::ScanFrequency, s.turn_hz)?;
                if s.turn_hz <= 0.0 {
                    return Err(refuse(Field::ScanFrequency, Rule::Above(0.0)));
                }
                if s.turn_hz >= nyquist {
                    return Err(refuse(Field::ScanFrequency, Rule::Below(nyquist)));
                }
                amplitudes(s.offset, s.amplitude)?;
                check_within(Field::ScanOffset, s.y_offset, -1.0, 1.0)?;
                if s.y_offset.abs() + s.amplitude > 1.0 {
                    return Err(refuse(
                        Field::ScanAmplitude,
                        Rule::AtMost(1.0 - s.y_offset.abs()),
                    ));
                }
                let fastest = core::f64::consts::TAU * s.turn_hz / rate_hz * s.amplitude;
                if fastest > step_norm {
                    let limit = s.turn_hz * step_norm / fastest;
                    return Err(refuse(Field::ScanFrequency, Rule::AtMost(limit)));
                }
                let step = libm::round(s.turn_hz / rate_hz * 4_294_967_296.0) as u32;
                let e_step = step / (2 * s.turns as u32);
                if e_step == 0 {
                    // The envelope would never move: fewer turns, or a faster turn rate. A
                    // turn rate so slow that no number of turns moves it is named itself.
                    if step / 2 == 0 {
                        let least = 2.0 * s.turns as f64 * rate_hz / 4_294_967_296.0;
                        return Err(refuse(Field::ScanFrequency, Rule::AtLeast(least)));
                    }
                    return Err(refuse(Field::ScanLines, Rule::AtMost((step / 2) as f64)));
                }
                let m = Spiral {
                    offset: signal_from_f64(s.offset),
                    amplitude: signal_from_f64(s.amplitude),
                    y_offset: signal_from_f64(s.y_offset),
                    theta: 0,
                    step,
                    e: 0,
                    e_step,
                    turns_done: 0,
                    turns_per_frame: 2 * s.turns as u32,
                };
                let line = rate_hz / s.turn_hz;
                (Motion::Spiral(m), m.offset, m.y_offset, line)
            }
        };
        Ok(Self {
            motion,
            phase: Phase::Done,
            x: start_x,
            last_y: LastY::Held(start_y),
            start_x,
            start_y,
            approach_step: (max_step / 4).max(1),
            ticks_per_pixel: tpp,
            pixel_left: 0,
            frames_left: request.frames,
            endless: request.frames == 0,
            pending: LINE | FRAME,
            last: false,
            line_ticks,
        })
    }

    /// The raster's constants, checked.
    fn raster(
        r: &RasterScan,
        tpp: u16,
        rate_hz: f64,
        step_norm: f64,
    ) -> Result<(Motion, i32, i32, f64), Refusal> {
        if r.lines == 0 {
            return Err(refuse(Field::ScanLines, Rule::AtLeast(1.0)));
        }
        if r.pixels == 0 {
            return Err(refuse(Field::ScanPixels, Rule::AtLeast(1.0)));
        }
        let trace = r.pixels as u32 * tpp as u32;
        if trace > MAX_TRACE_TICKS {
            return Err(refuse(
                Field::ScanPixels,
                Rule::AtMost((MAX_TRACE_TICKS / tpp as u32) as f64),
            ));
        }
        amplitudes(r.offset, r.amplitude)?;
        check_within(Field::ScanAmplitude, r.y_amplitude, 0.0, 1.0)?;
        check_within(Field::ScanOffset, r.y_offset, -1.0, 1.0)?;
        if r.y_offset.abs() + r.y_amplitude > 1.0 {
            return Err(refuse(
                Field::ScanAmplitude,
                Rule::AtMost(1.0 - r.y_offset.abs()),
            ));
        }
        // Trace speed per tick, and the line rate the slew limit allows.
        let v = 2.0 * r.amplitude / trace as f64;
        if v > step_norm {
            let line_ticks = trace as f64 + r.turn_ticks as f64;
            let limit = rate_hz / line_ticks * step_norm / v;
            return Err(refuse(Field::ScanFrequency, Rule::AtMost(limit)));
        }
        // The turnaround overshoots by v·T/4 on each side.
        let room = 1.0 - r.offset.abs() - r.amplitude;
        if v * r.turn_ticks as f64 / 4.0 > room {
            let most = libm::floor(4.0 * room / v);
            return Err(refuse(Field::ScanTurnaround, Rule::AtMost(most.max(0.0))));
        }
        let half = signal_from_f64(r.amplitude);
        let v_fine = ((2 * half as i64) << FINE) / trace as i64;
        let turn = r.turn_ticks as u32;
        let a_fine = if turn == 0 { 0 } else { v_fine / turn as i64 };
        let y_amp = signal_from_f64(r.y_amplitude);
        let y0 = signal_from_f64(r.y_offset) - y_amp;
        let y_step = if r.lines > 1 {
            ((2 * y_amp as i64) / (r.lines as i64 - 1)) as i32
        } else {
            0
        };
        let y0 = if r.lines > 1 {
            y0
        } else {
            signal_from_f64(r.y_offset)
        };
        let m = Raster {
            offset: signal_from_f64(r.offset),
            half,
            v_fine,
            a_fine,
            trace,
            turn,
            // Start at the apex of the turnaround before the first (forward) line.
            t: turn / 2,
            turning: turn > 0,
            dir: if turn > 0 { -1 } else { 1 },
            line: 0,
            lines: r.lines,
            closing: false,
            y0,
            y_step,
        };
        let (x, _) = m.rel();
        let start = saturate_i64(m.offset as i64 + m.dir as i64 * x as i64);
        let line_ticks = trace as f64 + turn as f64;
        Ok((Motion::Raster(m), start, y0, line_ticks))
    }

    /// Starts from `from` (the setpoint in force, Q2.30): the approach walks to the pattern's
    /// first point, then the pattern runs. Restarts a generator already run. O(1).
    pub fn start(&mut self, from: i32) {
        self.x = from;
        self.last_y = LastY::Held(self.start_y);
        self.phase = Phase::Approach;
    }

    /// The second axis at the last sample (the pattern's first y before any), Q2.30. The
    /// board does not drive y, so the tick keeps only what it is made from and this computes
    /// it: the host's replay ([`ScanSample`] has no y) and the tests call it.
    pub fn y(&self) -> i32 {
        match (self.last_y, &self.motion) {
            (LastY::Lissajous(r), Motion::Lissajous(m)) => m.y_at(r),
            (LastY::Spiral(theta, e), Motion::Spiral(m)) => m.y_at(theta, e),
            (LastY::Held(y), _) => y,
            // A phase of another pattern cannot be stored: the motion never changes.
            _ => self.start_y,
        }
    }

    /// Whether the last frame is done (the generator holds its end point).
    pub fn is_done(&self) -> bool {
        self.phase == Phase::Done
    }

    /// Whether the approach is over (the pattern runs, or has run).
    pub fn is_scanning(&self) -> bool {
        self.phase != Phase::Approach
    }

    /// Ticks per line (the line clock's period) the pattern defines: the raster's
    /// `pixels × ticks_per_pixel + turn_ticks`, one period of x for Lissajous, one turn for
    /// the spiral (the last two need not be whole ticks).
    pub fn line_ticks(&self) -> f64 {
        self.line_ticks
    }

    /// The pattern's first point (x, y), Q2.30: where the approach ends.
    pub fn start_point(&self) -> (i32, i32) {
        (self.start_x, self.start_y)
    }

    /// The next tick's sample. O(1): no loop, no division, no panic path.
    // Inlined into the tick, where its source is the rarer branch (`crate::rare`), which the
    // compiler would otherwise leave a call.
    #[inline(always)]
    pub fn next_sample(&mut self) -> ScanSample {
        match self.phase {
            Phase::Done => ScanSample {
                x: self.x,
                events: 0,
            },
            Phase::Approach => {
                let d = self.start_x as i64 - self.x as i64;
                let s = self.approach_step as i64;
                if d.abs() <= s {
                    self.x = self.start_x;
                    self.phase = Phase::Pattern;
                } else {
                    // |d| > s: a full step toward the start. (Not `d.clamp(-s, s)`, whose
                    // check of its bounds links a panic path into the tick.)
                    let step = if d > 0 { s } else { -s };
                    self.x = (self.x as i64 + step) as i32;
                }
                ScanSample {
                    x: self.x,
                    events: 0,
                }
            }
            Phase::Pattern => self.pattern(),
        }
    }

    #[inline(always)]
    fn pattern(&mut self) -> ScanSample {
        let (x, y, mut events, trace_start, in_trace, done) = match &mut self.motion {
            Motion::Raster(m) => {
                let (x, y, events, trace_start, in_trace, done) =
                    m.next(&mut self.frames_left, self.endless);
                (x, LastY::Held(y), events, trace_start, in_trace, done)
            }
            Motion::Lissajous(m) => {
                let (x, y) = (m.x_at(), LastY::Lissajous(m.r));
                let events = self.pending;
                let (r, wrapped) = m.r.overflowing_add(m.step);
                let line = m.x_cycles.wrapping_mul(r) < m.x_cycles.wrapping_mul(m.r);
                m.r = r;
                let (events, done) = frame_end(
                    events,
                    self.last,
                    wrapped,
                    line,
                    &mut self.frames_left,
                    self.endless,
                    &mut self.pending,
                    &mut self.last,
                );
                (x, y, events, false, true, done)
            }
            Motion::Spiral(m) => {
                let (x, y) = (m.x_at(), LastY::Spiral(m.theta, m.e));
                let events = self.pending;
                let (theta, line) = m.theta.overflowing_add(m.step);
                m.theta = theta;
                // The envelope saturates rather than wrap (its step is rounded down): the
                // frame ends on the turn count, where the envelope restarts from 0.
                m.e = m.e.saturating_add(m.e_step);
                let mut wrapped = false;
                if line {
                    m.turns_done += 1;
                    if m.turns_done >= m.turns_per_frame {
                        m.turns_done = 0;
                        m.e = 0;
                        wrapped = true;
                    }
                }
                let (events, done) = frame_end(
                    events,
                    self.last,
                    wrapped,
                    line,
                    &mut self.frames_left,
                    self.endless,
                    &mut self.pending,
                    &mut self.last,
                );
                (x, y, events, false, true, done)
            }
        };
        // The pixel clock: every `ticks_per_pixel` ticks from a trace's start (the raster)
        // or from the pattern's start (the others); none in turnarounds or at the end.
        if trace_start {
            self.pixel_left = 0;
        }
        if in_trace && !done {
            if self.pixel_left == 0 {
                events |= PIXEL;
                self.pixel_left = self.ticks_per_pixel;
            }
            self.pixel_left = self.pixel_left.saturating_sub(1);
        }
        if done {
            self.phase = Phase::Done;
        }
        self.x = x;
        self.last_y = y;
        ScanSample { x, events }
    }
}

/// Lissajous and spiral: the events of this sample (`events`, computed at the last advance)
/// and whether it ends the scan, given what the advance just did (`wrapped`: a frame ended,
/// `line`: a line ended). The events of the next sample go to `pending`.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn frame_end(
    events: u8,
    last: bool,
    wrapped: bool,
    line: bool,
    frames_left: &mut u16,
    endless: bool,
    pending: &mut u8,
    next_last: &mut bool,
) -> (u8, bool) {
    if last {
        // The end point: no new line or frame starts.
        return (0, true);
    }
    let mut next = if line { LINE } else { 0 };
    if wrapped {
        next |= FRAME | LINE;
        if !endless {
            *frames_left = frames_left.saturating_sub(1);
            *next_last = *frames_left == 0;
        }
    }
    *pending = next;
    (events, false)
}

/// The x offset and amplitude: amplitude in (0, 1], `|offset| + amplitude ≤ 1`.
fn amplitudes(offset: f64, amplitude: f64) -> Result<(), Refusal> {
    check_within(Field::ScanOffset, offset, -1.0, 1.0)?;
    crate::refusal::finite(Field::ScanAmplitude, amplitude)?;
    if amplitude <= 0.0 {
        return Err(refuse(Field::ScanAmplitude, Rule::Above(0.0)));
    }
    if offset.abs() + amplitude > 1.0 {
        return Err(refuse(
            Field::ScanAmplitude,
            Rule::AtMost(1.0 - offset.abs()),
        ));
    }
    Ok(())
}

impl Raster {
    /// x relative to the centre in the forward sense (Q2.30), and whether this is a trace.
    #[inline(always)]
    fn rel(&self) -> (i32, bool) {
        let t = self.t as i64;
        if self.turning {
            // From +A at +v to +A at −v: A + v·t − (v/T)·t².
            let fine = t
                .wrapping_mul(self.v_fine)
                .wrapping_sub(t.wrapping_mul(t).wrapping_mul(self.a_fine));
            (saturate_i64(self.half as i64 + (fine >> FINE)), false)
        } else {
            let fine = t.wrapping_mul(self.v_fine);
            (saturate_i64(-(self.half as i64) + (fine >> FINE)), true)
        }
    }

    /// One tick: (x, y, events, a trace starts, in a trace, the scan ends here).
    #[inline(always)]
    fn next(&mut self, frames_left: &mut u16, endless: bool) -> (i32, i32, u8, bool, bool, bool) {
        let (rel, in_trace) = self.rel();
        let x = saturate_i64(self.offset as i64 + self.dir as i64 * rel as i64);
        let y = self
            .y0
            .saturating_add((self.line as i32).wrapping_mul(self.y_step));
        let mut events = 0;
        let trace_start = in_trace && self.t == 0;
        if trace_start {
            events = if self.line == 0 { LINE | FRAME } else { LINE };
        }
        let mut done = false;
        self.t += 1;
        if in_trace {
            if self.t >= self.trace {
                self.t = 0;
                self.line += 1;
                if self.line >= self.lines {
                    self.line = 0;
                    if !endless {
                        *frames_left = frames_left.saturating_sub(1);
                        self.closing = *frames_left == 0;
                    }
                }
                if self.turn > 0 {
                    self.turning = true;
                } else {
                    self.dir = -self.dir;
                    // A plain triangle ends at the trace's end.
                    done = self.closing;
                }
            }
        } else if self.closing && self.t > self.turn / 2 {
            // The apex of the last turnaround (x's velocity zero): the end point.
            self.t = self.turn / 2;
            done = true;
        } else if self.t >= self.turn {
            self.t = 0;
            self.turning = false;
            self.dir = -self.dir;
        }
        (x, y, events, trace_start, in_trace, done)
    }
}

impl Lissajous {
    /// x at the frame phase `r` (the tick's).
    #[inline(always)]
    fn x_at(&self) -> i32 {
        let px = self.x0.wrapping_add(self.x_cycles.wrapping_mul(self.r));
        saturate_i64(self.offset as i64 + ((self.amplitude as i64 * unit_sine(px) as i64) >> 30))
    }

    /// y at the frame phase `r` (off the tick: [`ScanGenerator::y`]).
    fn y_at(&self, r: u32) -> i32 {
        let py = self.y0.wrapping_add(self.y_cycles.wrapping_mul(r));
        saturate_i64(
            self.y_offset as i64 + ((self.y_amplitude as i64 * unit_sine(py) as i64) >> 30),
        )
    }
}

impl Spiral {
    /// The radius at the envelope phase `e`, Q2.30: a triangle envelope, Q0.31 (e / 2^31
    /// rising, (2^32 − e) / 2^31 falling), times the amplitude.
    #[inline(always)]
    fn radius(&self, e: u32) -> i64 {
        let tri = if e < 1 << 31 {
            e as i64
        } else {
            (0u32.wrapping_sub(e)) as i64
        };
        (self.amplitude as i64 * tri) >> 31
    }

    /// x at the angle θ and envelope phase `e` (the tick's).
    #[inline(always)]
    fn x_at(&self) -> i32 {
        let r = self.radius(self.e);
        saturate_i64(self.offset as i64 + ((r * unit_sine(self.theta) as i64) >> 30))
    }

    /// y at the angle `theta` and envelope phase `e` (off the tick: [`ScanGenerator::y`]).
    fn y_at(&self, theta: u32, e: u32) -> i32 {
        let r = self.radius(e);
        saturate_i64(
            self.y_offset as i64 + ((r * unit_sine(theta.wrapping_add(1 << 30)) as i64) >> 30),
        )
    }
}

/// The pixel, line and frame outputs: each event starts a pulse of `width` ticks.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TriggerOutputs {
    width: u16,
    /// Ticks each output stays high (pixel, line, frame).
    left: [u16; 3],
}

impl TriggerOutputs {
    /// Outputs with pulses of `width` ticks (0: always low).
    ///
    /// ```
    /// use twinstack::sources::scan::{TriggerOutputs, LINE, PIXEL};
    /// let mut out = TriggerOutputs::new(2);
    /// assert_eq!(out.tick(PIXEL | LINE), PIXEL | LINE);
    /// assert_eq!(out.tick(0), PIXEL | LINE);
    /// assert_eq!(out.tick(0), 0);
    /// ```
    pub const fn new(width: u16) -> Self {
        Self {
            width,
            left: [0; 3],
        }
    }

    /// The pulse width, ticks.
    pub fn width(&self) -> u16 {
        self.width
    }

    /// Sets the pulse width (ticks; pulses under way end at once).
    pub fn set_width(&mut self, width: u16) {
        self.width = width;
        self.left = [0; 3];
    }

    /// One tick: starts the pulses of `events`, returns the outputs' levels ([`PIXEL`],
    /// [`LINE`], [`FRAME`] bits). Straight-line, three compare-and-decrements.
    #[inline(always)]
    pub fn tick(&mut self, events: u8) -> u8 {
        let [p, l, f] = &mut self.left;
        // The common tick (no event, no pulse under way): one test.
        if events == 0 && (*p | *l | *f) == 0 {
            return 0;
        }
        // A pulse starts or runs: the scan's tick, charged with it
        // (`tick_budget::SCAN_CYCLES`), laid out of line.
        crate::rare();
        stretch(events, PIXEL, self.width, p)
            | stretch(events, LINE, self.width, l)
            | stretch(events, FRAME, self.width, f)
    }
}

/// One output of [`TriggerOutputs::tick`]: restarts its pulse on its event, returns `bit`
/// while the pulse lasts.
#[inline(always)]
fn stretch(events: u8, bit: u8, width: u16, left: &mut u16) -> u8 {
    if events & bit != 0 {
        *left = width;
    }
    if *left > 0 {
        *left -= 1;
        bit
    } else {
        0
    }
}

/// The external trigger input: one shot, armed for an edge, fired by it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ExternalTrigger {
    edges: EdgeDetector,
    armed: bool,
    fired: u32,
}

/// The trigger input's edges, one sample a tick: the level compared with the last tick's.
/// What the external trigger and a TTL-stepped sequence ([`crate::sources::sequence`]) both count.
///
/// ```
/// use twinstack::sources::scan::{EdgeDetector, TriggerEdge};
/// let mut e = EdgeDetector::new(TriggerEdge::Falling, true);
/// assert!(!e.poll(true));
/// assert!(e.poll(false)); // high to low
/// assert!(!e.poll(false));
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct EdgeDetector {
    edge: TriggerEdge,
    /// The input's level at the last tick.
    last: bool,
}

impl EdgeDetector {
    /// Counts `edge` (`Off`: none), the input now at `level`: an edge is a change from it.
    pub const fn new(edge: TriggerEdge, level: bool) -> Self {
        Self { edge, last: level }
    }

    /// One tick with the input at `level`: whether it made the edge. O(1).
    #[inline(always)]
    pub fn poll(&mut self, level: bool) -> bool {
        let edge = match self.edge {
            TriggerEdge::Off => false,
            TriggerEdge::Rising => level && !self.last,
            TriggerEdge::Falling => !level && self.last,
        };
        self.last = level;
        edge
    }
}

impl Default for ExternalTrigger {
    fn default() -> Self {
        Self::new()
    }
}

impl ExternalTrigger {
    /// Disarmed, edge off, input low.
    pub const fn new() -> Self {
        Self {
            edges: EdgeDetector::new(TriggerEdge::Off, false),
            armed: false,
            fired: 0,
        }
    }

    /// Arms for `edge` (`Off` disarms), with the input now at `level` (the level the tick
    /// saw last): an edge is a change from it.
    pub fn arm(&mut self, edge: TriggerEdge, level: bool) {
        self.edges = EdgeDetector::new(edge, level);
        self.armed = edge != TriggerEdge::Off;
    }

    /// Whether it waits for its edge.
    pub fn is_armed(&self) -> bool {
        self.armed
    }

    /// Times it fired since power-up.
    pub fn fired(&self) -> u32 {
        self.fired
    }

    /// One tick with the input at `level`: `true` on the tick the armed edge arrives (then
    /// disarmed). O(1).
    #[inline(always)]
    pub fn poll(&mut self, level: bool) -> bool {
        // Disarmed (the common tick): one test; the level is taken again at the arming.
        if !self.armed {
            return false;
        }
        // Armed is the rarer tick, and charged as such (`tick_budget::TRIGGER_CYCLES`): laid
        // out of line, so that the disarmed tick runs straight on without a taken branch.
        crate::rare();
        let edge = self.edges.poll(level);
        if edge {
            self.armed = false;
            self.fired = self.fired.wrapping_add(1);
        }
        edge
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::fixed_point::{signal_from_f64 as q, signal_to_f64 as f};
    use std::vec;
    use std::vec::Vec;

    const RATE: f64 = 50_000.0;
    const FAST: i32 = 1 << 27; // 0.125 per tick

    fn raster(lines: u16, pixels: u16, turn: u16, frames: u16) -> ScanRequest {
        ScanRequest {
            pattern: ScanPattern::Raster(RasterScan {
                lines,
                pixels,
                turn_ticks: turn,
                offset: 0.1,
                amplitude: 0.5,
                y_offset: -0.2,
                y_amplitude: 0.4,
            }),
            ticks_per_pixel: 5,
            frames,
            on_trigger: false,
        }
    }

    /// A sample with its y ([`ScanGenerator::y`] right after it).
    #[derive(Clone, Copy, Debug)]
    struct Sampled {
        x: i32,
        y: i32,
        events: u8,
    }

    /// Runs to the end of the approach; returns the pattern's samples until done (or `most`).
    fn pattern_samples(g: &mut ScanGenerator, from: i32, most: usize) -> Vec<Sampled> {
        g.start(from);
        while !g.is_scanning() {
            g.next_sample();
        }
        let mut out = Vec::new();
        while !g.is_done() && out.len() < most {
            let ScanSample { x, events } = g.next_sample();
            out.push(Sampled {
                x,
                y: g.y(),
                events,
            });
        }
        out
    }

    #[test]
    fn the_raster_matches_its_f64_geometry_and_its_clocks_fall_on_exact_ticks() {
        let (lines, pixels, turn, tpp) = (6u16, 40u16, 30u32, 5u32);
        let mut g =
            ScanGenerator::new(&raster(lines, pixels, turn as u16, 2), RATE, FAST, 1).unwrap();
        let s = pattern_samples(&mut g, 0, 100_000);
        let trace = pixels as u32 * tpp;
        let period = trace + turn;
        let (c, a) = (0.1, 0.5);
        let v = 2.0 * a / trace as f64;
        // The pattern starts half-way through a turnaround: the first trace at tick T/2.
        let first = (turn / 2) as usize;
        let mut worst: f64 = 0.0;
        for (k, smp) in s.iter().enumerate() {
            let want = if k < first {
                // Second half of the turnaround at −A (mirrored).
                let t = (k + first) as f64;
                c - (a + v * t - v / turn as f64 * t * t)
            } else {
                let j = k - first;
                let line = j / period as usize;
                let t = (j % period as usize) as f64;
                let dir = if line % 2 == 0 { 1.0 } else { -1.0 };
                let rel = if t < trace as f64 {
                    -a + v * t
                } else {
                    let t = t - trace as f64;
                    a + v * t - v / turn as f64 * t * t
                };
                c + dir * rel
            };
            worst = worst.max((f(smp.x) - want).abs());
        }
        assert!(worst < 1e-6, "worst {worst}");
        // Line clocks every trace + turn ticks; frame clocks every `lines` lines; pixel clocks
        // every 5 ticks within the traces only.
        let at = |bit: u8| -> Vec<usize> {
            s.iter()
                .enumerate()
                .filter(|(_, x)| x.events & bit != 0)
                .map(|(k, _)| k)
                .collect()
        };
        let line_ticks: Vec<usize> = (0..12).map(|i| first + i * period as usize).collect();
        assert_eq!(at(LINE), line_ticks);
        assert_eq!(at(FRAME), vec![first, first + 6 * period as usize]);
        let pixels_at = at(PIXEL);
        assert_eq!(pixels_at.len(), 12 * pixels as usize);
        for (i, &k) in pixels_at.iter().enumerate() {
            let line = i / pixels as usize;
            let p = i % pixels as usize;
            assert_eq!(k, first + line * period as usize + p * tpp as usize);
        }
        // y steps at each line start: −0.6 … 0.2 in 5 steps.
        for (i, &k) in line_ticks.iter().enumerate() {
            let want = -0.6 + 0.8 * (i % 6) as f64 / 5.0;
            assert!((f(s[k].y) - want).abs() < 1e-8, "line {i}");
        }
        // It ends at the apex of the last turnaround: 2 frames · 6 lines, then T/2 ticks.
        assert_eq!(
            s.len(),
            first + 12 * period as usize - turn as usize / 2 + 1
        );
        let end = f(s.last().unwrap().x);
        assert!(
            (end - (c - a - v * turn as f64 / 4.0)).abs() < 1e-6,
            "{end}"
        );
        assert_eq!(g.line_ticks(), period as f64);
    }

    #[test]
    fn starting_and_stopping_move_continuously() {
        // From far away: the approach walks at a quarter of the slew step; the pattern itself
        // stays under the slew step; velocity changes by at most one turnaround's
        // deceleration per tick (no velocity step at start or end with a turnaround).
        for req in [raster(4, 50, 40, 1), lissajous(3, 2, 1), spiral(3, 1)] {
            let mut g = ScanGenerator::new(&req, RATE, FAST, 1).unwrap();
            g.start(q(-0.9));
            let mut last = q(-0.9) as i64;
            let mut v_last = 0i64;
            let mut k = 0;
            let mut worst_dv = 0i64;
            while !g.is_done() && k < 1_000_000 {
                let x = g.next_sample().x as i64;
                assert!((x - last).abs() <= FAST as i64, "step {} at {k}", x - last);
                if g.is_scanning() {
                    worst_dv = worst_dv.max((x - last - v_last).abs());
                }
                v_last = x - last;
                last = x;
                k += 1;
            }
            assert!(g.is_done());
            // The end holds: no further motion.
            assert_eq!(g.next_sample().x as i64, last);
            // Velocity continuity: small against the trace speeds (≥ 0.001 per tick here)
            // except the approach's end (start of the pattern at zero speed from a walk).
            assert!(worst_dv < (FAST / 4) as i64 + 2, "dv {worst_dv}");
        }
    }

    fn lissajous(nx: u16, ny: u16, frames: u16) -> ScanRequest {
        ScanRequest {
            pattern: ScanPattern::Lissajous(LissajousScan {
                frame_hz: 50.0,
                x_cycles: nx,
                y_cycles: ny,
                y_phase_deg: 30.0,
                offset: -0.1,
                amplitude: 0.6,
                y_offset: 0.2,
                y_amplitude: 0.7,
            }),
            ticks_per_pixel: 10,
            frames,
            on_trigger: false,
        }
    }

    fn spiral(turns: u16, frames: u16) -> ScanRequest {
        ScanRequest {
            pattern: ScanPattern::Spiral(SpiralScan {
                turn_hz: 200.0,
                turns,
                offset: 0.05,
                amplitude: 0.8,
                y_offset: -0.1,
            }),
            ticks_per_pixel: 4,
            frames,
            on_trigger: false,
        }
    }

    #[test]
    fn lissajous_matches_the_f64_sines_and_its_clocks() {
        let mut g = ScanGenerator::new(&lissajous(3, 2, 2), RATE, FAST, 1).unwrap();
        let s = pattern_samples(&mut g, 0, 1_000_000);
        let tau = core::f64::consts::TAU;
        let mut worst: f64 = 0.0;
        for (k, smp) in s.iter().enumerate() {
            let t = k as f64 / RATE;
            let x = -0.1 + 0.6 * libm::sin(tau * 150.0 * t + tau / 4.0);
            let y = 0.2 + 0.7 * libm::sin(tau * 100.0 * t + tau / 12.0 + tau / 4.0 * 2.0 / 3.0);
            worst = worst.max((f(smp.x) - x).abs()).max((f(smp.y) - y).abs());
        }
        // The accumulator's frequency error over 2 frames and the table's interpolation.
        assert!(worst < 1e-4, "worst {worst}");
        // The clocks fall on the first tick at or after each wrap of the u32 accumulators
        // (step = 50 Hz / 50 kHz · 2^32, rounded): frames every 2^32 / step ticks, lines every
        // a third of that; the scan ends on the tick after the second frame's wrap.
        let step = libm::round(50.0 / RATE * 4_294_967_296.0) as u64;
        let wrap = |m: u64, per: u64| (m << 32).div_ceil(per);
        assert_eq!(s.len() as u64, wrap(2, step) + 1);
        let frames: Vec<u64> = (0..s.len())
            .filter(|&k| s[k].events & FRAME != 0)
            .map(|k| k as u64)
            .collect();
        assert_eq!(frames, vec![0, wrap(1, step)]);
        let lines: Vec<u64> = (0..s.len())
            .filter(|&k| s[k].events & LINE != 0)
            .map(|k| k as u64)
            .collect();
        let want: Vec<u64> = core::iter::once(0)
            .chain((1..6).map(|m| wrap(m, 3 * step)))
            .collect();
        assert_eq!(lines, want);
        let pixels = (0..s.len()).filter(|&k| s[k].events & PIXEL != 0).count();
        assert_eq!(pixels, (s.len() - 1).div_ceil(10));
        // It ends where it started: x at its peak.
        assert!((f(s[2000].x) - 0.5).abs() < 1e-4);
    }

    #[test]
    fn the_spiral_matches_its_f64_reference() {
        let mut g = ScanGenerator::new(&spiral(5, 1), RATE, FAST, 1).unwrap();
        let s = pattern_samples(&mut g, 0, 1_000_000);
        let tau = core::f64::consts::TAU;
        // A frame is ten turns of the accumulator (2500.0003 ticks); the envelope restarts
        // on the tick the tenth turn completes (the end sample's).
        let frame = 10.0 * 4_294_967_296.0 / libm::round(200.0 / RATE * 4_294_967_296.0);
        let mut worst: f64 = 0.0;
        for (k, smp) in s.iter().enumerate() {
            let t = k as f64;
            let u = if t >= libm::ceil(frame) {
                t - libm::ceil(frame)
            } else {
                t
            };
            let env = if u < frame / 2.0 {
                u / (frame / 2.0)
            } else {
                (frame - u) / (frame / 2.0)
            };
            let th = tau * 200.0 * t / RATE;
            let x = 0.05 + 0.8 * env * libm::sin(th);
            let y = -0.1 + 0.8 * env * libm::cos(th);
            worst = worst.max((f(smp.x) - x).abs()).max((f(smp.y) - y).abs());
        }
        assert!(worst < 1e-4, "worst {worst}");
        // Ends on the tick after the tenth turn (5 out, 5 in); a line clock at each turn
        // before it.
        let step = libm::round(200.0 / RATE * 4_294_967_296.0) as u64;
        let end = (10u64 << 32).div_ceil(step);
        assert_eq!(s.len() as u64, end + 1);
        let lines: Vec<u64> = (0..s.len())
            .filter(|&k| s[k].events & LINE != 0)
            .map(|k| k as u64)
            .collect();
        let want: Vec<u64> = core::iter::once(0)
            .chain(
                (1..)
                    .map(|m: u64| (m << 32).div_ceil(step))
                    .take_while(|&k| k < end),
            )
            .collect();
        assert_eq!(lines, want);
    }

    #[test]
    fn every_bad_parameter_is_refused_by_name() {
        let bad = |r: ScanRequest, step: i32, pulse: u16| {
            ScanGenerator::new(&r, RATE, step, pulse).err().unwrap()
        };
        let with = |f: &dyn Fn(&mut RasterScan)| {
            let mut r = raster(4, 40, 20, 1);
            if let ScanPattern::Raster(p) = &mut r.pattern {
                f(p);
            }
            r
        };
        assert_eq!(bad(with(&|p| p.lines = 0), FAST, 1).field, Field::ScanLines);
        assert_eq!(
            bad(with(&|p| p.pixels = 0), FAST, 1).field,
            Field::ScanPixels
        );
        assert_eq!(
            bad(with(&|p| p.amplitude = 0.95), FAST, 1),
            Refusal::new(Field::ScanAmplitude, Rule::AtMost(0.9))
        );
        assert_eq!(
            bad(with(&|p| p.amplitude = f64::NAN), FAST, 1).rule,
            Rule::NotFinite
        );
        assert_eq!(
            bad(with(&|p| p.offset = 1.5), FAST, 1).field,
            Field::ScanOffset
        );
        assert_eq!(
            bad(with(&|p| p.turn_ticks = 5000), FAST, 1).field,
            Field::ScanTurnaround
        );
        // Too fast for the slew limit: the line rate it allows.
        let r = bad(raster(4, 40, 20, 1), 1 << 20, 1);
        assert_eq!(r.field, Field::ScanFrequency);
        assert!(matches!(r.rule, Rule::AtMost(x) if x > 0.0 && x < RATE / 220.0));
        // The pixel clock must be longer than the pulse.
        let mut r = raster(4, 40, 20, 1);
        r.ticks_per_pixel = 2;
        assert_eq!(
            bad(r, FAST, 2),
            Refusal::new(Field::ScanTicksPerPixel, Rule::AtLeast(3.0))
        );
        r.ticks_per_pixel = 0;
        assert_eq!(bad(r, FAST, 0).field, Field::ScanTicksPerPixel);
        // Lissajous above Nyquist, zero cycles; spiral zero turns, too fast.
        let mut l = lissajous(3, 2, 1);
        if let ScanPattern::Lissajous(p) = &mut l.pattern {
            p.frame_hz = 9000.0;
        }
        assert_eq!(
            bad(l, FAST, 1),
            Refusal::new(Field::ScanFrequency, Rule::Below(RATE / 2.0 / 3.0))
        );
        let mut l = lissajous(0, 2, 1);
        assert_eq!(bad(l, FAST, 1).field, Field::ScanCycles);
        l = lissajous(3, 2, 1);
        assert_eq!(bad(l, 1 << 16, 1).field, Field::ScanFrequency);
        assert_eq!(bad(spiral(0, 1), FAST, 1).field, Field::ScanLines);
        assert_eq!(bad(spiral(3, 1), 1 << 16, 1).field, Field::ScanFrequency);
        // Too many turns for the turn rate: the turns it holds; a turn rate so slow that no
        // number of turns moves the envelope: the least turn rate for these turns.
        let slow = |hz: f64, turns: u16| {
            let mut r = spiral(turns, 1);
            if let ScanPattern::Spiral(p) = &mut r.pattern {
                p.turn_hz = hz;
            }
            bad(r, FAST, 1)
        };
        let r = slow(1e-4, 10);
        assert!(matches!(r.rule, Rule::AtMost(x) if x >= 1.0), "{r:?}");
        assert_eq!(r.field, Field::ScanLines);
        let r = slow(1e-300, 10);
        assert_eq!(r.field, Field::ScanFrequency);
        assert!(
            matches!(r.rule, Rule::AtLeast(x) if x > 1e-4 && x < 1e-3),
            "{r:?}"
        );
    }

    #[test]
    fn outputs_stretch_events_and_the_input_fires_once_per_arming() {
        let mut o = TriggerOutputs::new(3);
        let levels: Vec<u8> = [LINE, 0, 0, 0, FRAME | PIXEL, PIXEL, 0, 0, 0]
            .iter()
            .map(|&e| o.tick(e))
            .collect();
        assert_eq!(
            levels,
            [
                LINE,
                LINE,
                LINE,
                0,
                FRAME | PIXEL,
                FRAME | PIXEL,
                FRAME | PIXEL,
                PIXEL,
                0
            ]
        );
        let mut off = TriggerOutputs::new(0);
        assert_eq!(off.tick(PIXEL | LINE | FRAME), 0);

        let mut t = ExternalTrigger::new();
        assert!(!t.poll(true)); // not armed
        t.arm(TriggerEdge::Rising, true);
        assert!(!t.poll(true)); // high already: no edge
        assert!(!t.poll(false));
        assert!(t.poll(true));
        assert!(!t.is_armed());
        assert!(!t.poll(false) && !t.poll(true)); // one shot
        t.arm(TriggerEdge::Falling, true);
        assert!(t.poll(false));
        assert_eq!(t.fired(), 2);
    }
}
