//! The analog setpoint input: the board as a linearising front-end. A second ADC input,
//! converted on the same timer trigger as the sensor, is the setpoint source — scaled (gain,
//! offset), optionally low-passed, checked against a valid window — and the setpoint goes
//! through the compensator, the feedback and the drive's range and slew limits like any
//! other source's. An existing controller (or Micro-Manager's "DA Z Stage") that drives a
//! piezo amplifier with a voltage drives twinstack instead, and the stage comes out linear.
//!
//! # One tick
//!
//! The board hands the tick the input's latest conversion as a fraction of the ADC's span,
//! UQ0.16 (`0` = 0 V at the pin, `65535` = full scale; `None` when the board has no such
//! input or the conversion failed, which counts as lost: [`crate::board::SensorAdc::setpoint_input`]).
//!
//! 1. **Window**: a reading below `lost_below` is a **lost** input (an open input pulled
//!    down, a live-zero signal gone), one above `over_above` **over-range**. Either is a fault.
//! 2. **Scale**: `x = offset + gain · r`, `r` the reading as a fraction of the span: Q2.30
//!    normalised displacement, saturating.
//! 3. **Low-pass** (optional): one pole, `y ← y + k (x − y)`, `k = 1 − exp(−2π f_c / f_s)`,
//!    Q1.31. Not fed while in fault (a fault's readings are not the signal).
//! 4. **Output**: with a valid input the setpoint *tracks* `y`. On a fault it **holds** where
//!    it is or **ramps to the rest position** (the drive at rest, the configuration's
//!    [`crate::control::Controller::rest_setpoint`]) by at most `step` a tick, as the settings
//!    say. When the input comes back, the setpoint walks to the live value by at most `step`
//!    a tick and tracks it again once it is there: no jump either way.
//!
//! The step's DAC value is written by the tick that reads the new conversion (the sensor's and
//! the input's conversions start together on the control timer's trigger, before the tick),
//! so the analog input reaches the DAC within one tick. O(1): no division, no loop; one
//! compare when the input is not running.
//!
//! The drive's own range and slew limits still apply after the compensator: a step on the
//! input moves the stacks as fast as the slew limit lets them, and never faster.

use serde::{Deserialize, Serialize};

use crate::fixed_point::signal_from_f64;
use crate::refusal::{Field, Refusal, Rule};

/// Largest `|gain|`, normalised displacement per input span (the gain is Q3.28).
pub const MAX_GAIN: f32 = 7.9;
/// Largest `|offset|`, normalised displacement.
pub const MAX_OFFSET: f32 = 2.0;

/// What the setpoint does while the input is lost or over-range.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum OnFault {
    /// Holds where the last valid reading left it.
    Hold,
    /// Ramps to the rest position (the drive at rest) at the configured rate.
    RampToRest,
}

/// The analog input's settings (protocol `Analog(Start)`), in physical units.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AnalogInputConfig {
    /// Normalised displacement per full input span (0 V to the ADC's full scale at the pin);
    /// |gain| ≤ [`MAX_GAIN`]. A 0–10 V source through a divider onto the full span, driving
    /// the whole stroke (−1 … +1): gain 2.0, offset −1.0.
    pub gain: f32,
    /// Normalised displacement at 0 V on the pin; |offset| ≤ [`MAX_OFFSET`].
    pub offset: f32,
    /// The one-pole low-pass's corner, Hz (above 0, below a sixth of the control rate), or
    /// `None`: no filter.
    pub corner_hz: Option<f32>,
    /// Readings below this fraction of the span (0 ≤ … < `over_above`) are a lost input.
    pub lost_below: f32,
    /// Readings above this fraction of the span (… ≤ 1) are over-range.
    pub over_above: f32,
    /// What the setpoint does on a fault.
    pub on_fault: OnFault,
    /// The ramp's rate on a fault (ramp to rest) and on recovery, normalised displacement
    /// per second (above 0; the drive's slew limit still applies after it).
    pub rate: f32,
    /// Stored with the settings (`StoreParams`), the board starts the input at power-up
    /// from the stored record, with no host connected.
    pub start_at_boot: bool,
}

impl AnalogInputConfig {
    /// Checks the settings against the control rate; the refusal names the field and its
    /// limit.
    ///
    /// ```
    /// use twinstack::sources::analog_input::{AnalogInputConfig, OnFault};
    /// let ok = AnalogInputConfig {
    ///     gain: 2.0, offset: -1.0, corner_hz: Some(500.0), lost_below: 0.02,
    ///     over_above: 0.99, on_fault: OnFault::Hold, rate: 10.0, start_at_boot: false,
    /// };
    /// assert!(ok.check(50_000.0).is_ok());
    /// assert!(AnalogInputConfig { gain: f32::NAN, ..ok }.check(50_000.0).is_err());
    /// assert!(AnalogInputConfig { lost_below: 0.5, over_above: 0.4, ..ok }.check(50_000.0).is_err());
    /// ```
    pub fn check(&self, control_rate_hz: f64) -> Result<(), Refusal> {
        let finite = |field, v: f32| {
            if v.is_finite() {
                Ok(())
            } else {
                Err(Refusal::new(field, Rule::NotFinite))
            }
        };
        finite(Field::AnalogGain, self.gain)?;
        finite(Field::AnalogOffset, self.offset)?;
        finite(Field::AnalogLostBelow, self.lost_below)?;
        finite(Field::AnalogOverAbove, self.over_above)?;
        finite(Field::AnalogRate, self.rate)?;
        if self.gain.abs() > MAX_GAIN {
            return Err(Refusal::new(
                Field::AnalogGain,
                Rule::AtMost(MAX_GAIN as f64),
            ));
        }
        if self.offset.abs() > MAX_OFFSET {
            return Err(Refusal::new(
                Field::AnalogOffset,
                Rule::AtMost(MAX_OFFSET as f64),
            ));
        }
        if let Some(c) = self.corner_hz {
            finite(Field::AnalogCorner, c)?;
            if c <= 0.0 {
                return Err(Refusal::new(Field::AnalogCorner, Rule::Above(0.0)));
            }
            let most = control_rate_hz / 6.0;
            if c as f64 > most {
                return Err(Refusal::new(Field::AnalogCorner, Rule::AtMost(most)));
            }
        }
        if self.lost_below < 0.0 {
            return Err(Refusal::new(Field::AnalogLostBelow, Rule::AtLeast(0.0)));
        }
        if self.over_above > 1.0 {
            return Err(Refusal::new(Field::AnalogOverAbove, Rule::AtMost(1.0)));
        }
        if self.over_above <= self.lost_below {
            return Err(Refusal::new(Field::AnalogOverAbove, Rule::NotIncreasing));
        }
        if self.rate <= 0.0 {
            return Err(Refusal::new(Field::AnalogRate, Rule::Above(0.0)));
        }
        // At least one Q2.30 LSB a tick, at most the whole ±2 range a tick.
        let most = 2.0 * control_rate_hz;
        if self.rate as f64 > most {
            return Err(Refusal::new(Field::AnalogRate, Rule::AtMost(most)));
        }
        Ok(())
    }

    /// The fixed-point coefficients at `control_rate_hz` (checked first: [`Self::check`]).
    /// Off the interrupt path: `exp`, division and rounding happen here, once.
    pub fn prepare(&self, control_rate_hz: f64) -> Result<PreparedInput, Refusal> {
        self.check(control_rate_hz)?;
        let k = match self.corner_hz {
            None => None,
            Some(c) => {
                let k = 1.0 - libm::exp(-2.0 * core::f64::consts::PI * c as f64 / control_rate_hz);
                Some((libm::round(k * (1u64 << 31) as f64) as u32).clamp(1, 1 << 31))
            }
        };
        let span = |f: f32| -> u32 { libm::round(f as f64 * 65536.0).clamp(0.0, 65536.0) as u32 };
        let step = signal_from_f64(self.rate as f64 / control_rate_hz).max(1);
        Ok(PreparedInput {
            gain: libm::round(self.gain as f64 * (1u64 << 28) as f64) as i32,
            offset: signal_from_f64(self.offset as f64),
            k,
            lost_below: span(self.lost_below),
            over_above: span(self.over_above),
            ramp: self.on_fault == OnFault::RampToRest,
            step,
        })
    }
}

/// [`AnalogInputConfig`] in the tick's formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PreparedInput {
    /// Gain, Q3.28 normalised displacement per span.
    gain: i32,
    /// Offset, Q2.30.
    offset: i32,
    /// The low-pass's `k`, Q1.31 (1 … 2^31), or `None`.
    k: Option<u32>,
    /// The valid window's bounds, in the reading's UQ0.16 (0 … 65536).
    lost_below: u32,
    over_above: u32,
    /// Ramp to rest on a fault (else hold).
    ramp: bool,
    /// Largest setpoint change a tick while ramping, Q2.30, ≥ 1.
    step: i32,
}

/// Start, stop or read the analog input (protocol `Request::Analog`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum AnalogRequest {
    /// Makes the analog input the setpoint source (refused while another source runs):
    /// its output starts where the setpoint is and walks to the input's value at the rate.
    Start(AnalogInputConfig),
    /// Stops it: the setpoint holds where it is.
    Stop,
    /// Reads its state (answered with `Response::Analog`).
    Status,
}

/// The analog input's state (the answer to `Analog(Status)`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct AnalogStatus {
    /// Whether the input is the setpoint source.
    pub running: bool,
    /// The input is lost (below the window, or no conversion).
    pub lost: bool,
    /// The input is over-range (above the window).
    pub over_range: bool,
    /// Faults (valid → lost or over-range) since the input was started.
    pub faults: u32,
    /// The last reading, UQ0.16 of the span (0 when there was none).
    pub reading: u16,
    /// The setpoint the input gives now, Q2.30 normalised displacement.
    pub setpoint: i32,
}

/// The tick half of the analog input (see the module doc).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AnalogInput {
    running: bool,
    p: PreparedInput,
    /// The low-pass's output (or the scaled reading without one), Q2.30.
    filtered: i32,
    /// The setpoint given, Q2.30.
    out: i32,
    /// The setpoint tracks `filtered` (no fault, caught up since the last).
    tracking: bool,
    /// The filter has seen a valid reading since the start.
    primed: bool,
    lost: bool,
    over: bool,
    faults: u32,
    reading: u16,
}

impl Default for AnalogInput {
    fn default() -> Self {
        Self::new()
    }
}

impl AnalogInput {
    /// Not running.
    pub const fn new() -> Self {
        Self {
            running: false,
            p: PreparedInput {
                gain: 0,
                offset: 0,
                k: None,
                lost_below: 0,
                over_above: 65536,
                ramp: false,
                step: 1,
            },
            filtered: 0,
            out: 0,
            tracking: false,
            primed: false,
            lost: false,
            over: false,
            faults: 0,
            reading: 0,
        }
    }

    /// Starts with `prepared` and the setpoint at `from` (Q2.30): the first valid reading
    /// primes the filter, and the setpoint walks there at the rate. Counts restart at zero.
    ///
    /// ```
    /// use twinstack::sources::analog_input::{AnalogInput, AnalogInputConfig, OnFault};
    /// let config = AnalogInputConfig {
    ///     gain: 2.0, offset: -1.0, corner_hz: None, lost_below: 0.0,
    ///     over_above: 1.0, on_fault: OnFault::Hold, rate: 50_000.0, start_at_boot: false,
    /// };
    /// let mut a = AnalogInput::new();
    /// a.start(config.prepare(50_000.0).unwrap(), 0);
    /// // Three quarters of the span: 2 × 0.75 − 1 = +0.5, reached at once at this rate.
    /// assert_eq!(a.next(Some(49152), 0), 1 << 29);
    /// ```
    pub fn start(&mut self, prepared: PreparedInput, from: i32) {
        *self = Self {
            running: true,
            p: prepared,
            filtered: from,
            out: from,
            ..Self::new()
        };
    }

    /// Stops (the setpoint holds where it is; the counts stay readable).
    pub fn stop(&mut self) {
        self.running = false;
    }

    /// Whether it is the setpoint source.
    #[inline(always)]
    pub fn is_running(&self) -> bool {
        self.running
    }

    /// The state and counts.
    pub fn status(&self) -> AnalogStatus {
        AnalogStatus {
            running: self.running,
            lost: self.lost,
            over_range: self.over,
            faults: self.faults,
            reading: self.reading,
            setpoint: self.out,
        }
    }

    /// One tick (running): `reading` the input's conversion (UQ0.16 of the span, `None`:
    /// none), `rest` the rest position (Q2.30); returns this tick's setpoint (Q2.30). O(1).
    // Inlined into the tick, where its source is the rarer branch (`crate::rare`), which the
    // compiler would otherwise leave a call.
    #[inline(always)]
    pub fn next(&mut self, reading: Option<u16>, rest: i32) -> i32 {
        let p = self.p;
        let r = reading.unwrap_or(0);
        self.reading = r;
        let r32 = r as u32;
        let lost = reading.is_none() | (r32 < p.lost_below);
        let over = r32 > p.over_above;
        if lost | over {
            if !(self.lost | self.over) {
                self.faults = self.faults.wrapping_add(1);
            }
            self.lost = lost;
            self.over = over;
            self.tracking = false;
            if p.ramp {
                self.out = toward(self.out, rest, p.step);
            }
            return self.out;
        }
        self.lost = false;
        self.over = false;
        // Scale: Q3.28 × UQ0.16 = Q3.44, >> 14 → Q2.30; plus the offset, saturating.
        let scaled = (p.offset as i64 + ((p.gain as i64 * r as i64) >> 14))
            .clamp(i32::MIN as i64, i32::MAX as i64) as i32;
        // Low-pass: Q2.30 difference × Q1.31 k, >> 31 → Q2.30 (|result| ≤ |d|: no overflow).
        self.filtered = match p.k {
            Some(k) if self.primed => {
                let d = scaled as i64 - self.filtered as i64;
                (self.filtered as i64 + ((d * k as i64) >> 31)) as i32
            }
            _ => scaled,
        };
        self.primed = true;
        if self.tracking {
            self.out = self.filtered;
        } else {
            self.out = toward(self.out, self.filtered, p.step);
            self.tracking = self.out == self.filtered;
        }
        self.out
    }
}

/// `from` moved toward `to` by at most `step` (> 0).
#[inline(always)]
fn toward(from: i32, to: i32, step: i32) -> i32 {
    if to > from {
        to.min(from.saturating_add(step))
    } else {
        to.max(from.saturating_sub(step))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed_point::SIGNAL_ONE;

    const RATE: f64 = 50_000.0;

    fn config() -> AnalogInputConfig {
        AnalogInputConfig {
            gain: 2.0,
            offset: -1.0,
            corner_hz: None,
            lost_below: 0.05,
            over_above: 0.95,
            on_fault: OnFault::Hold,
            rate: 50.0,
            start_at_boot: false,
        }
    }

    fn q30(x: i32) -> f64 {
        x as f64 / SIGNAL_ONE as f64
    }

    /// The f64 reference of the valid path: scale, then the one-pole low-pass.
    struct Reference {
        gain: f64,
        offset: f64,
        k: Option<f64>,
        y: Option<f64>,
    }

    impl Reference {
        fn new(c: &AnalogInputConfig) -> Self {
            Self {
                gain: c.gain as f64,
                offset: c.offset as f64,
                k: c.corner_hz
                    .map(|f| 1.0 - (-2.0 * core::f64::consts::PI * f as f64 / RATE).exp()),
                y: None,
            }
        }
        fn next(&mut self, r: u16) -> f64 {
            let x = self.offset + self.gain * r as f64 / 65536.0;
            let y = match (self.y, self.k) {
                (Some(y), Some(k)) => y + k * (x - y),
                _ => x,
            };
            self.y = Some(y);
            y
        }
    }

    fn started(c: AnalogInputConfig, from: i32) -> AnalogInput {
        let mut a = AnalogInput::new();
        a.start(c.prepare(RATE).unwrap(), from);
        a
    }

    #[test]
    fn gain_and_offset_match_the_reference() {
        for (gain, offset) in [(2.0, -1.0), (-1.5, 0.75), (7.5, -2.0), (0.25, 0.0)] {
            let c = AnalogInputConfig {
                gain,
                offset,
                lost_below: 0.0,
                over_above: 1.0,
                rate: 2.0 * RATE as f32,
                ..config()
            };
            let mut a = started(c, 0);
            let mut reference = Reference::new(&c);
            for r in (0..=65535u32).step_by(997) {
                let got = a.next(Some(r as u16), 0);
                let want = reference.next(r as u16).clamp(-2.0, 2.0 - 1e-9);
                // One LSB of the gain's Q3.28 times the span, and the scaling's truncation.
                assert!(
                    (q30(got) - want).abs() < 3e-8,
                    "{gain} {offset} {r}: {got} vs {want}"
                );
            }
        }
    }

    #[test]
    fn the_low_pass_matches_the_reference() {
        for corner in [10.0, 200.0, 3000.0] {
            let c = AnalogInputConfig {
                corner_hz: Some(corner),
                lost_below: 0.0,
                over_above: 1.0,
                rate: 2.0 * RATE as f32,
                ..config()
            };
            let mut a = started(c, 0);
            let mut reference = Reference::new(&c);
            let mut worst: f64 = 0.0;
            for i in 0..20_000u32 {
                // A step, then a sine at the corner.
                let r = if i < 5_000 {
                    60_000
                } else {
                    let t = i as f64 / RATE;
                    (32768.0 + 30000.0 * (2.0 * core::f64::consts::PI * corner as f64 * t).sin())
                        as u16
                };
                let got = q30(a.next(Some(r), 0));
                let want = reference.next(r);
                worst = worst.max((got - want).abs());
            }
            // Truncation stalls the Q2.30 state within 1/k LSBs of the input.
            let k = 1.0 - (-2.0 * core::f64::consts::PI * corner as f64 / RATE).exp();
            let bound = (2.0 / k + 4.0) / SIGNAL_ONE as f64;
            assert!(worst < bound, "{corner} Hz: {worst} > {bound}");
        }
    }

    #[test]
    fn a_loss_holds_and_recovery_ramps_without_a_jump() {
        let mut a = started(config(), 0);
        let step = config().prepare(RATE).unwrap().step;
        // Walk to 0.5 (r = 0.75 of the span) and track it.
        let mut last = 0;
        for _ in 0..2_000 {
            let s = a.next(Some(49152), 0);
            assert!((s - last).abs() <= step);
            last = s;
        }
        assert_eq!(last, SIGNAL_ONE / 2);
        // Lost: holds, counted once.
        for _ in 0..100 {
            assert_eq!(a.next(Some(100), 0), last);
        }
        assert!(a.status().lost && !a.status().over_range);
        assert_eq!(a.status().faults, 1);
        // No conversion at all: still lost, not counted again.
        assert_eq!(a.next(None, 0), last);
        assert_eq!(a.status().faults, 1);
        // Back, at −0.5: walks there at the rate, no jump.
        let mut ticks = 0;
        loop {
            let s = a.next(Some(16384), 0);
            assert!((s - last).abs() <= step, "{s} after {last}");
            last = s;
            ticks += 1;
            if s == -SIGNAL_ONE / 2 {
                break;
            }
            assert!(ticks < 10_000);
        }
        // A whole unit at 50 /s: 20 ms, 1000 ticks.
        assert!((999..=1001).contains(&ticks), "{ticks}");
        assert!(!a.status().lost);
    }

    #[test]
    fn over_range_ramps_to_rest() {
        let c = AnalogInputConfig {
            on_fault: OnFault::RampToRest,
            ..config()
        };
        let step = c.prepare(RATE).unwrap().step;
        let rest = -SIGNAL_ONE / 4;
        let mut a = started(c, 0);
        let mut last = 0;
        for _ in 0..2_000 {
            last = a.next(Some(49152), rest);
        }
        for _ in 0..2_000 {
            let s = a.next(Some(65535), rest);
            assert!((s - last).abs() <= step);
            last = s;
        }
        assert_eq!(last, rest);
        assert!(a.status().over_range && !a.status().lost);
        assert_eq!(a.status().faults, 1);
        // Lost after over-range: the same fault, not a second one.
        a.next(Some(0), rest);
        assert_eq!(a.status().faults, 1);
        assert!(a.status().lost);
    }

    #[test]
    fn hostile_settings_are_refused_by_name() {
        let ok = config();
        let cases = [
            (
                AnalogInputConfig {
                    gain: f32::NAN,
                    ..ok
                },
                Field::AnalogGain,
            ),
            (AnalogInputConfig { gain: 9.0, ..ok }, Field::AnalogGain),
            (
                AnalogInputConfig {
                    offset: f32::INFINITY,
                    ..ok
                },
                Field::AnalogOffset,
            ),
            (
                AnalogInputConfig { offset: -3.0, ..ok },
                Field::AnalogOffset,
            ),
            (
                AnalogInputConfig {
                    corner_hz: Some(f32::NAN),
                    ..ok
                },
                Field::AnalogCorner,
            ),
            (
                AnalogInputConfig {
                    corner_hz: Some(0.0),
                    ..ok
                },
                Field::AnalogCorner,
            ),
            (
                AnalogInputConfig {
                    corner_hz: Some(20_000.0),
                    ..ok
                },
                Field::AnalogCorner,
            ),
            (
                AnalogInputConfig {
                    lost_below: -0.1,
                    ..ok
                },
                Field::AnalogLostBelow,
            ),
            (
                AnalogInputConfig {
                    over_above: 1.5,
                    ..ok
                },
                Field::AnalogOverAbove,
            ),
            (
                AnalogInputConfig {
                    lost_below: 0.6,
                    over_above: 0.4,
                    ..ok
                },
                Field::AnalogOverAbove,
            ),
            (AnalogInputConfig { rate: 0.0, ..ok }, Field::AnalogRate),
            (AnalogInputConfig { rate: -1.0, ..ok }, Field::AnalogRate),
            (
                AnalogInputConfig {
                    rate: f32::NAN,
                    ..ok
                },
                Field::AnalogRate,
            ),
        ];
        for (c, field) in cases {
            assert_eq!(c.check(RATE).unwrap_err().field, field, "{c:?}");
            assert!(c.prepare(RATE).is_err());
        }
    }
}
