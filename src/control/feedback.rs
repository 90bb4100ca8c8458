//! Sensor feedback around the feedforward compensator: the position sensor's reading, a PI(D)
//! controller on the error with anti-windup and an output limit, an optional notch at the stage
//! resonance, and the constants of the drift check of the observer against the sensor.
//!
//! Per closed-loop tick ([`Feedback::correction`]):
//!
//! 1. `e = reference − measured` (Q2.30, saturating), where the reference is the target of
//!    the reading's instant: the reading is of the end of the hold of the drive of
//!    [`SENSOR_DELAY_TICKS`] ticks ago, between the instants that drive and the next were
//!    aimed at (the middles of their holds), so the targets around it interpolated there
//!    ([`crate::control::instant`]). Comparing it with the target of now would feed the
//!    feedback a phantom error `ẋ · delay` (7 % of the stroke for a 750 Hz sine at 50 kHz)
//!    that it would then "correct" into the output. The feedforward acts on the present
//!    target; the feedback corrects what the model got wrong;
//! 2. with a notch, `e` passes through it ([`crate::control::notch`]): the loop no longer sees the
//!    resonance, so it can neither excite nor sustain it;
//! 3. integral: `i += ki · e` (Q0.32 gain, one `SMMUL`), limited to ±`limit` — and **held**
//!    (anti-windup by conditional integration) while the previous tick's command was cut by the
//!    drive's range or slew limit in the direction `e` pushes;
//! 4. proportional: `kp · e` with `e` first limited to ±`limit / kp`, so the Q4.28 product
//!    fits 32 bits without a 64-bit saturation;
//! 5. derivative (optional): `kd · d` on the low-passed change of `e` per tick;
//! 6. the sum, limited to ±`limit`, is the correction added to the feedforward.
//!
//! The drift check ([`crate::services::observer::ObserverBelow::observe`], below the tick)
//! compares the measurement with the observer's estimate of the same instant (the sensor
//! reading is [`SENSOR_DELAY_TICKS`] ticks old), low passes the difference over
//! 2^[`DRIFT_FILTER_SHIFT`] ticks and flags it when it exceeds the drift limit: the model no
//! longer describes the stage.
//!
//! Configuration ([`Feedback`]) and memory ([`FeedbackState`]) are kept apart; nothing here
//! allocates, panics or loops.

use crate::control::instant::ReadingInstant;
use crate::control::notch::{Notch, NotchDesign, NotchError, NotchState};
use crate::fixed_point::{
    limit, mul_high, q0_32_from_f64, q1_31_from_f64, q4_28_from_f64, saturate_i64, signal_from_f64,
    SIGNAL_ONE,
};
use crate::refusal::{finite, Field, Refusal, Rule};

/// PI(D) feedback on the sensor's error and the resonance notch, in physical terms. Gains are
/// normalised: drive as a fraction of the model's input range per displacement error as a
/// fraction of its output range (kp = 1: an error of the whole stroke asks for the whole
/// drive range).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FeedbackSettings {
    /// Proportional gain, 0 ≤ kp < 7.5.
    pub kp: f64,
    /// Integral gain, per second; per tick (`ki / control rate`) it must be below 1/2.
    pub ki: f64,
    /// Derivative gain, seconds (0: no derivative term); per tick (`kd · control rate`)
    /// below 7.5.
    pub kd: f64,
    /// Corner of the derivative's low pass, Hz (0 < f < control rate / 2; unused when kd = 0,
    /// but it must still be a finite number).
    pub derivative_cutoff_hz: f64,
    /// Largest correction, as a fraction of the drive range (0…1]: 0.1 lets the feedback
    /// move the drive by a tenth of the model's input range either way.
    pub limit: f64,
    /// Notch on the error at the stage's resonance, if any.
    pub notch: Option<NotchDesign>,
}

impl FeedbackSettings {
    /// The feedback the tools ship as a default (the simulated and virtual boards' settings,
    /// `twinstack load --kp/--ki` on a board without feedback): integral only, 1000 /s, within
    /// ±10 % of the drive range, no notch. Stable with at least 45° and 6 dB of margin at
    /// every control rate the board allows (10–100 kHz), whatever the delay does to the
    /// resonance's phase: its gain at a resonance 30 times the stage's DC gain is under
    /// −14 dB. A notch cannot be a default: below 2.04 × the resonance the rate has no room
    /// for it. Slow (about 140 Hz closed-loop bandwidth on the paper's stage): `twinstack tune`
    /// measures the stage and chooses faster gains for its rate.
    ///
    /// ```
    /// use twinstack::control::feedback::FeedbackSettings;
    /// for rate in [10_000.0, 50_000.0, 100_000.0] {
    ///     assert!(FeedbackSettings::DEFAULT.build(rate).is_ok());
    /// }
    /// ```
    pub const DEFAULT: Self = Self {
        kp: 0.0,
        ki: 1000.0,
        kd: 0.0,
        derivative_cutoff_hz: 1.0,
        limit: 0.1,
        notch: None,
    };

    /// PI feedback with the given gains (`ki` per second) and limit; no derivative or notch.
    pub fn pi(kp: f64, ki: f64, limit: f64) -> Self {
        Self {
            kp,
            ki,
            kd: 0.0,
            derivative_cutoff_hz: 1.0,
            limit,
            notch: None,
        }
    }

    /// Validates the gains at `control_rate` (Hz) and builds the tick's feedback.
    ///
    /// ```
    /// use twinstack::control::feedback::FeedbackSettings;
    /// let fb = FeedbackSettings::pi(0.2, 500.0, 0.1).build(50_000.0).unwrap();
    /// assert!(fb.derivative.is_none() && fb.notch.is_none());
    /// assert!(FeedbackSettings::pi(0.2, 30_000.0, 0.1).build(50_000.0).is_err()); // ki ≥ rate/2
    /// ```
    pub fn build(&self, control_rate: f64) -> Result<Feedback, Refusal> {
        finite(Field::Kp, self.kp)?;
        finite(Field::Ki, self.ki)?;
        finite(Field::Kd, self.kd)?;
        finite(Field::DerivativeCutoff, self.derivative_cutoff_hz)?;
        finite(Field::FeedbackLimit, self.limit)?;
        let below = |field, x: f64, lo: f64, hi: f64| {
            if x < lo {
                Err(Refusal::new(field, Rule::AtLeast(lo)))
            } else if x >= hi {
                Err(Refusal::new(field, Rule::Below(hi)))
            } else {
                Ok(())
            }
        };
        below(Field::Kp, self.kp, 0.0, 7.5)?;
        below(Field::Ki, self.ki, 0.0, 0.5 * control_rate)?;
        below(Field::Kd, self.kd, 0.0, 7.5 / control_rate)?;
        if self.kd > 0.0 {
            if self.derivative_cutoff_hz <= 0.0 {
                return Err(Refusal::new(Field::DerivativeCutoff, Rule::Above(0.0)));
            }
            below(
                Field::DerivativeCutoff,
                self.derivative_cutoff_hz,
                0.0,
                control_rate / 2.0,
            )?;
        }
        if self.limit <= 0.0 {
            return Err(Refusal::new(Field::FeedbackLimit, Rule::Above(0.0)));
        }
        if self.limit > 1.0 {
            return Err(Refusal::new(Field::FeedbackLimit, Rule::AtMost(1.0)));
        }
        let notch = match &self.notch {
            Some(d) => Some(Notch::new(d, control_rate).map_err(|e| notch_refusal(d, e))?),
            None => None,
        };
        let derivative = (self.kd > 0.0).then(|| Derivative {
            kd: q4_28_from_f64(self.kd * control_rate),
            smoothing: q1_31_from_f64(
                1.0 - libm::exp(
                    -2.0 * core::f64::consts::PI * self.derivative_cutoff_hz / control_rate,
                ),
            ),
        });
        // Q2.30; the whole drive range is 2 normalised units (saturates just below 2).
        let limit = signal_from_f64(self.limit * 2.0);
        let kp = q4_28_from_f64(self.kp);
        Ok(Feedback {
            kp,
            error_bound: Feedback::error_bound(limit, kp),
            ki: q0_32_from_f64(self.ki / control_rate),
            derivative,
            limit,
            notch,
        })
    }
}

/// The notch's refusal, on the field it names.
fn notch_refusal(d: &NotchDesign, e: NotchError) -> Refusal {
    crate::control::notch::refusal(
        d,
        e,
        [Field::NotchFrequency, Field::NotchQ, Field::NotchDepth],
    )
}

/// How many ticks old the sensor reading is, relative to the observer's estimate of the same
/// tick: the conversion starts at the tick's trigger (the stage after the previous tick's
/// write) and the ADC returns the previous conversion (one sample of latency), as on the board
/// and in `hal-sim`'s `SimBoard`.
pub const SENSOR_DELAY_TICKS: usize = 2;
// The target of a reading's instant (`instant::ReadingInstant`) is laid out for this delay:
// the end of the hold of two ticks ago, between the targets of two and one tick ago, the cubic
// taking those of three ticks ago and of the present tick beside them.
const _: () = assert!(SENSOR_DELAY_TICKS == 2);

/// The drift check low-passes the model-vs-sensor difference over `2^DRIFT_FILTER_SHIFT`
/// ticks, so sensor noise and the stage's own fast dynamics do not trip it.
pub const DRIFT_FILTER_SHIFT: u32 = 4;

/// The controller on the sensor's error, in fixed point (built by [`FeedbackSettings::build`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Feedback {
    /// Proportional gain, Q4.28 (normalised drive per normalised displacement error).
    pub kp: i32,
    /// Error limit of the proportional term, Q2.30: `⌊limit / kp⌋`, so `|kp · e| ≤ limit`.
    pub error_bound: i32,
    /// Integral gain per tick, Q0.32 in a signed word (in [0, 0.5)): `ki · e` is the high word
    /// of the product, one `SMMUL`.
    pub ki: i32,
    /// Derivative term, if any.
    pub derivative: Option<Derivative>,
    /// Largest correction (and integrator) magnitude, Q2.30 normalised drive.
    pub limit: i32,
    /// Notch on the error, if any.
    pub notch: Option<Notch>,
}

/// The derivative term: `kd · d`, `d` the change of the error per tick, low-passed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Derivative {
    /// Gain, Q4.28 (normalised drive per normalised error change per tick).
    pub kd: i32,
    /// Pole of the one-pole low pass, Q1.31: `d += smoothing · (Δe − d)`
    /// (`1 − e^{−2π f_c / f_s}`).
    pub smoothing: i32,
}

/// The feedback's memory.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FeedbackState {
    /// Integrator, Q2.30 normalised drive (within ±limit).
    integrator: i32,
    /// The previous tick's command minus the drive applied (non-zero when a limit cut it).
    clip: i32,
    /// The previous error, Q2.30 (after the notch), for the derivative.
    previous_error: i32,
    /// Low-passed error change per tick, Q2.30.
    derivative: i32,
    /// The notch's memory.
    notch: NotchState,
    /// The last targets, and from them the target of the present reading's instant.
    targets: ReadingInstant,
    /// The last measurement, Q2.30.
    pub(crate) measured: i32,
}

/// `(a · b) >> shift` with a 64-bit product, for products that provably fit 32 bits.
#[inline(always)]
fn mul_shift(a: i32, b: i32, shift: u32) -> i32 {
    ((a as i64 * b as i64) >> shift) as i32
}

impl Feedback {
    /// The proportional term's error bound for `limit` (Q2.30) and `kp` (Q4.28):
    /// `⌊limit · 2^28 / kp⌋`, so that `kp · e >> 28` never exceeds the limit (`i32::MAX` when
    /// `kp ≤ 0`).
    pub fn error_bound(limit: i32, kp: i32) -> i32 {
        if kp > 0 {
            (((limit as i64) << 28) / kp as i64).min(i32::MAX as i64) as i32
        } else {
            i32::MAX
        }
    }

    /// The closed-loop correction for `target` against `measured` (both Q2.30): see the
    /// module doc. Returns a Q2.30 normalised drive within ±`limit`.
    #[inline(always)]
    pub fn correction(&self, s: &mut FeedbackState, target: i32, measured: i32) -> i32 {
        self.correction_with::<true>(s, target, measured)
    }

    /// [`Feedback::correction`], with the notch and the derivative looked at only when `FULL`:
    /// the tick runs a PI-only feedback (neither configured) with `FULL = false`, without
    /// their checks. With `FULL = false` and either configured, it would be left out.
    #[inline(always)]
    pub fn correction_with<const FULL: bool>(
        &self,
        s: &mut FeedbackState,
        target: i32,
        measured: i32,
    ) -> i32 {
        let reference = s.delayed_target(target);
        let mut error = reference.saturating_sub(measured);
        if let (true, Some(n)) = (FULL, &self.notch) {
            error = n.step(&mut s.notch, error);
        }
        // Anti-windup: hold while the last command was cut in the direction the error pushes
        // (the clip and the error have the same sign).
        if s.clip == 0 || (s.clip ^ error) < 0 {
            // Q0.32 × Q2.30 >> 32 = Q2.30; |ki| < 1/2, so it fits.
            let i = s.integrator.saturating_add(mul_high(self.ki, error));
            s.integrator = limit(i, -self.limit, self.limit);
        }
        // Q4.28 × Q2.30 >> 28 = Q2.30; |e| ≤ limit / kp, so |kp · e| ≤ limit fits.
        let e = limit(error, -self.error_bound, self.error_bound);
        let mut c = mul_shift(self.kp, e, 28).saturating_add(s.integrator);
        if let (true, Some(d)) = (FULL, &self.derivative) {
            c = c.saturating_add(d.step(s, error));
        }
        limit(c, -self.limit, self.limit)
    }

    /// The correction when the sensor could not be read: the integrator alone, held.
    /// `target` (Q2.30) still enters the history: the next reading is as old as ever (the
    /// delay is the converter's), so it must meet the target of [`SENSOR_DELAY_TICKS`] ticks
    /// ago, not one from before the failed read.
    #[inline(always)]
    pub fn held_correction(&self, s: &mut FeedbackState, target: i32) -> i32 {
        s.delayed_target(target);
        s.integrator
    }
}

impl Derivative {
    /// `kd` times the low-passed change of `error` since the last tick, Q2.30 (saturated).
    #[inline(always)]
    fn step(&self, s: &mut FeedbackState, error: i32) -> i32 {
        let change = error.saturating_sub(s.previous_error);
        s.previous_error = error;
        let d = s.derivative.saturating_add(mul_shift(
            self.smoothing,
            change.saturating_sub(s.derivative),
            31,
        ));
        s.derivative = d;
        saturate_i64((self.kd as i64 * d as i64) >> 28)
    }
}

impl FeedbackState {
    /// Puts this tick's `target` into the history and returns what the present reading is to
    /// be compared with: the target of the reading's instant, the end of the hold of the
    /// drive of [`SENSOR_DELAY_TICKS`] ticks ago ([`crate::control::instant`]).
    #[inline(always)]
    fn delayed_target(&mut self, target: i32) -> i32 {
        self.targets.push(target)
    }

    /// The state at rest: integrator empty, the stage at `position` (where the observer puts
    /// it).
    pub fn at_rest(position: i32) -> Self {
        Self {
            targets: ReadingInstant::at(position),
            measured: position,
            ..Self::default()
        }
    }

    /// Prepares a bumpless entry into closed loop at `target` (O(1), between two ticks): the
    /// target history restarts at `target`, the integrator, the anti-windup clip and the
    /// derivative are empty, and the notch starts settled at the present error, so the first
    /// correction is the proportional term alone; the tick's transfer offset takes up the
    /// rest (see [`crate::control::mode_switch`]).
    pub fn enter_closed_loop(&mut self, target: i32) {
        self.targets = ReadingInstant::at(target);
        let error = limit(
            target.saturating_sub(self.measured),
            -SIGNAL_ONE,
            SIGNAL_ONE,
        );
        self.notch = Notch::state_at(error);
        self.previous_error = error;
        self.derivative = 0;
        self.clip = 0;
        self.integrator = 0;
    }

    /// What the limits cut from this tick's command (for the next tick's anti-windup).
    #[inline(always)]
    pub fn limited(&mut self, command: i32, applied: i32) {
        self.clip = command.saturating_sub(applied);
    }

    /// The integrator, Q2.30 normalised drive.
    pub fn integrator(&self) -> i32 {
        self.integrator
    }

    /// The last measurement, Q2.30 normalised displacement.
    pub fn measured(&self) -> i32 {
        self.measured
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed_point::{q0_32_from_f64, q4_28_from_f64, signal_from_f64, signal_to_f64};

    fn feedback(kp: f64, ki: f64) -> Feedback {
        let limit = signal_from_f64(0.2);
        let kp = q4_28_from_f64(kp);
        Feedback {
            kp,
            error_bound: Feedback::error_bound(limit, kp),
            ki: q0_32_from_f64(ki),
            derivative: None,
            limit,
            notch: None,
        }
    }

    #[test]
    fn correction_is_kp_e_plus_the_integral_and_never_exceeds_the_limit() {
        let fb = feedback(0.5, 0.1);
        let mut s = FeedbackState::at_rest(signal_from_f64(0.1));
        let c = fb.correction(&mut s, signal_from_f64(0.1), 0);
        // 0.5 · 0.1 + 0.1 · 0.1 = 0.06.
        assert!(
            (signal_to_f64(c) - 0.06).abs() < 1e-8,
            "{}",
            signal_to_f64(c)
        );
        // Whatever the error, the correction stays within ±0.2.
        for (t, m) in [
            (i32::MAX, i32::MIN),
            (i32::MIN, i32::MAX),
            (1 << 30, -(1 << 30)),
        ] {
            let mut s = FeedbackState::at_rest(0);
            for _ in 0..100 {
                let c = fb.correction(&mut s, t, m);
                assert!(c.abs() <= signal_from_f64(0.2));
            }
        }
    }

    #[test]
    fn integrator_is_clamped_and_held_while_a_limit_cuts_the_command() {
        let fb = feedback(0.5, 0.1);
        let mut s = FeedbackState::at_rest(0);
        // Drive free: a persistent error winds the integrator up to its limit, no further.
        for _ in 0..1000 {
            fb.correction(&mut s, signal_from_f64(0.5), 0);
            s.limited(0, 0);
        }
        assert_eq!(s.integrator(), signal_from_f64(0.2));
        // The command is cut from above while the error still pushes up: the integrator holds...
        // (the target has been 0.5 all along, the stage at 0)
        let mut s = FeedbackState::at_rest(0);
        s.targets = ReadingInstant::at(signal_from_f64(0.5));
        s.integrator = signal_from_f64(0.05);
        s.limited(signal_from_f64(1.2), signal_from_f64(1.0));
        for _ in 0..100 {
            fb.correction(&mut s, signal_from_f64(0.5), 0);
            s.limited(signal_from_f64(1.2), signal_from_f64(1.0));
        }
        assert_eq!(s.integrator(), signal_from_f64(0.05));
        // ...but unwinds as soon as the error reverses (the reference, the target of the
        // reading's instant, crosses once the new target is SENSOR_DELAY_TICKS + 1 ticks old).
        for _ in 0..=SENSOR_DELAY_TICKS {
            fb.correction(&mut s, signal_from_f64(-0.5), 0);
        }
        assert!(s.integrator() < signal_from_f64(0.05));
    }

    /// A ramp from rest the stage follows exactly, each target at the middle of its drive's
    /// hold, read at the end of the hold of SENSOR_DELAY_TICKS ago: between that target and
    /// the next (half a step past it, once the ramp is under way).
    fn read_at_its_instant(k: i32, step: i32) -> i32 {
        let d = SENSOR_DELAY_TICKS as i32;
        let r = |j: i32| j.max(0) * step;
        let at = crate::control::instant::between_holds([
            r(k - d - 1),
            r(k - d),
            r(k - d + 1),
            r(k - d + 2),
        ]);
        if k > d + 1 {
            assert_eq!(at, r(k - d) + step / 2);
        }
        at
    }

    #[test]
    fn the_reading_is_compared_with_the_target_of_its_instant() {
        let fb = feedback(1.0, 0.0);
        let mut s = FeedbackState::at_rest(0);
        // No error, no correction (comparing with the present target, or with the target of
        // SENSOR_DELAY_TICKS ago alone, would see a phantom lag).
        let step = signal_from_f64(0.001);
        for k in 0..100i32 {
            let measured = read_at_its_instant(k, step);
            assert_eq!(fb.correction(&mut s, k * step, measured), 0, "tick {k}");
        }
        // The target of SENSOR_DELAY_TICKS ago alone is half a step off.
        let mut s = FeedbackState::at_rest(0);
        let mut seen = 0;
        for k in 0..100i32 {
            let measured = (k - SENSOR_DELAY_TICKS as i32).max(0) * step;
            seen = fb.correction(&mut s, k * step, measured);
        }
        assert_eq!(seen, step / 2);
    }

    #[test]
    fn after_a_failed_read_the_reading_still_meets_the_target_of_its_own_instant() {
        let fb = feedback(1.0, 0.0);
        let mut s = FeedbackState::at_rest(0);
        // The same exactly-followed ramp, with reads failing on ticks 20…29: the targets of
        // those ticks still enter the history, so the first readings after the gap see no
        // error (a history frozen at tick 19 would see the ramp's ten ticks of travel).
        let step = signal_from_f64(0.001);
        for k in 0..60i32 {
            let measured = read_at_its_instant(k, step);
            if (20..30).contains(&k) {
                assert_eq!(fb.held_correction(&mut s, k * step), 0, "tick {k}");
            } else {
                assert_eq!(fb.correction(&mut s, k * step, measured), 0, "tick {k}");
            }
        }
    }
}
