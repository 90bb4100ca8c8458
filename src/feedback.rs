//! Sensor feedback around the feedforward compensator: the position sensor's reading, a PI(D)
//! controller on the error with anti-windup and an output limit, an optional notch at the stage
//! resonance, and the drift check of the observer against the sensor.
//!
//! Per closed-loop tick ([`Feedback::correction`]):
//!
//! 1. `e = reference − measured` (Q2.30, saturating), where the reference is the target of
//!    [`SENSOR_DELAY_TICKS`] ticks ago: the reading is that old, and comparing it with the
//!    target of now would feed the feedback a phantom error `ẋ · delay` (7 % of the stroke
//!    for a 750 Hz sine at 50 kHz) that it would then "correct" into the output. The
//!    feedforward acts on the present target; the feedback corrects what the model got wrong;
//! 2. with a notch, `e` passes through it ([`crate::notch`]): the loop no longer sees the
//!    resonance, so it can neither excite nor sustain it;
//! 3. integral: `i += ki · e` (Q0.32 gain, one `SMMUL`), limited to ±`limit` — and **held**
//!    (anti-windup by conditional integration) while the previous tick's command was cut by the
//!    drive's range or slew limit in the direction `e` pushes;
//! 4. proportional: `kp · e` with `e` first limited to ±`limit / kp`, so the Q4.28 product
//!    fits 32 bits without a 64-bit saturation;
//! 5. derivative (optional): `kd · d` on the low-passed change of `e` per tick;
//! 6. the sum, limited to ±`limit`, is the correction added to the feedforward.
//!
//! The drift check ([`Feedback::drifted`]) compares the measurement with the observer's
//! estimate of the same instant (the sensor reading is [`SENSOR_DELAY_TICKS`] ticks old), low
//! passes the difference over 2^[`DRIFT_FILTER_SHIFT`] ticks and flags it when it exceeds the
//! drift limit: the model no longer describes the stage.
//!
//! Configuration ([`Feedback`]) and memory ([`FeedbackState`]) are kept apart; nothing here
//! allocates, panics or loops.

use crate::board::AdcCode;
use crate::fixed_point::{limit, mul_high, saturate_i64, SIGNAL_ONE};
use crate::notch::{Notch, NotchState};

/// How many ticks old the sensor reading is, relative to the observer's estimate of the same
/// tick: the conversion starts at the tick's trigger (the stage after the previous tick's
/// write) and the ADC returns the previous conversion (one sample of latency), as on the board
/// and in `hal-sim`'s `SimBoard`.
pub const SENSOR_DELAY_TICKS: usize = 2;

/// The drift check low-passes the model-vs-sensor difference over `2^DRIFT_FILTER_SHIFT`
/// ticks, so sensor noise and the stage's own fast dynamics do not trip it.
pub const DRIFT_FILTER_SHIFT: u32 = 4;

/// The position sensor and the controller on its error (fixed point, validated by
/// [`crate::settings::Settings::build`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Feedback {
    /// ADC resolution, bits (1…30): the code is read as a fraction of full scale.
    pub adc_bits: u32,
    /// Displacement at ADC code 0, Q4.28 normalised displacement.
    pub sensor_offset: i32,
    /// Displacement per ADC full scale, Q4.28 normalised (negative for an inverted sensor).
    pub sensor_gain: i32,
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
    /// Largest low-passed |measured − estimate| before the drift flag, Q2.30 normalised
    /// displacement (`u32::MAX`: no check).
    pub drift_limit: u32,
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
    /// The observer's last estimates, newest first, Q2.30.
    estimates: [i32; SENSOR_DELAY_TICKS],
    /// The last targets, newest first, Q2.30.
    targets: [i32; SENSOR_DELAY_TICKS],
    /// Low-passed measured − estimate, Q2.30.
    drift: i32,
    /// The last measurement, Q2.30.
    measured: i32,
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

    /// ADC code → normalised displacement (Q2.30, saturated): `offset + gain · code / 2^bits`.
    /// The code is masked to `adc_bits` and read as a Q1.31 fraction in [0, 1); the Q4.28
    /// product and sum fit 32 bits, and the final ×4 to Q2.30 saturates.
    #[inline(always)]
    pub fn displacement(&self, code: AdcCode) -> i32 {
        // Shifting the code's top bit to bit 31 drops the stray bits above `adc_bits`; one
        // more shift back down makes it a Q1.31 fraction in [0, 1). Two shifts, no mask.
        // `adc_bits` is validated to 1…30; out of that range the shift amounts wrap (no
        // panic) and the reading is still a fraction in [0, 1).
        let fraction = (code.0.wrapping_shl(32u32.wrapping_sub(self.adc_bits)) >> 1) as i32;
        // Q4.28 × Q1.31 >> 31 = Q4.28; |gain| < 8 and fraction < 1, so it fits.
        let x = self
            .sensor_offset
            .saturating_add(mul_shift(self.sensor_gain, fraction, 31));
        let x = x.saturating_add(x);
        x.saturating_add(x)
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

    /// The drift check on this tick's measurement: updates the low-passed difference from the
    /// observer's estimate of the same instant and says whether it exceeds the limit.
    /// It runs on every tick with a reading, in every mode, and keeps the reading for a later
    /// hand-over into closed loop.
    #[inline(always)]
    pub fn drifted(&self, s: &mut FeedbackState, measured: i32) -> bool {
        s.measured = measured;
        let difference = measured.saturating_sub(s.estimates[SENSOR_DELAY_TICKS - 1]);
        let step = difference.saturating_sub(s.drift) >> DRIFT_FILTER_SHIFT;
        s.drift = s.drift.saturating_add(step);
        s.drift.unsigned_abs() > self.drift_limit
    }

    /// Prepares a bumpless entry into closed loop: the integrator is preloaded so that the
    /// first correction equals `wanted` (the drive now minus the feedforward), as far as the
    /// limit allows, and the notch and the derivative start settled at the present error.
    /// Returns what the integrator could not take (the caller fades it out).
    pub fn hand_over(&self, s: &mut FeedbackState, target: i32, wanted: i32) -> i32 {
        s.targets = [target; SENSOR_DELAY_TICKS];
        let error = target.saturating_sub(s.measured);
        let notch_error = limit(error, -SIGNAL_ONE, SIGNAL_ONE);
        s.notch = Notch::state_at(notch_error);
        let error = if self.notch.is_some() {
            notch_error
        } else {
            error
        };
        s.previous_error = error;
        s.derivative = 0;
        s.clip = 0;
        let e = limit(error, -self.error_bound, self.error_bound);
        let p = mul_shift(self.kp, e, 28);
        // The first tick will add its own integral step: leave room for it.
        let step = mul_high(self.ki, error);
        let i = wanted.saturating_sub(p).saturating_sub(step);
        s.integrator = limit(i, -self.limit, self.limit);
        wanted.saturating_sub(p.saturating_add(s.integrator).saturating_add(step))
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
    /// Puts this tick's `target` into the history and returns the one of
    /// [`SENSOR_DELAY_TICKS`] ticks ago (what the present reading is to be compared with).
    #[inline(always)]
    fn delayed_target(&mut self, target: i32) -> i32 {
        let reference = self.targets[SENSOR_DELAY_TICKS - 1];
        self.targets.copy_within(0..SENSOR_DELAY_TICKS - 1, 1);
        self.targets[0] = target;
        reference
    }

    /// The state at rest: integrator empty, the stage where the observer puts it.
    pub fn at_rest(estimate: i32) -> Self {
        Self {
            estimates: [estimate; SENSOR_DELAY_TICKS],
            targets: [estimate; SENSOR_DELAY_TICKS],
            measured: estimate,
            ..Self::default()
        }
    }

    /// The same state with `measured` as the last measurement (kept across a reconfiguration,
    /// so the hand-over sees where the stage was).
    pub fn with_measurement(mut self, measured: i32) -> Self {
        self.measured = measured;
        self
    }

    /// What the limits cut from this tick's command (for the next tick's anti-windup).
    #[inline(always)]
    pub fn limited(&mut self, command: i32, applied: i32) {
        self.clip = command.saturating_sub(applied);
    }

    /// This tick's observer estimate (for the drift check [`SENSOR_DELAY_TICKS`] ticks on).
    #[inline(always)]
    pub fn observed(&mut self, estimate: i32) {
        self.estimates.copy_within(0..SENSOR_DELAY_TICKS - 1, 1);
        self.estimates[0] = estimate;
    }

    /// The integrator, Q2.30 normalised drive.
    pub fn integrator(&self) -> i32 {
        self.integrator
    }

    /// The low-passed difference measured − estimate, Q2.30 normalised displacement.
    pub fn drift(&self) -> i32 {
        self.drift
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
            adc_bits: 16,
            sensor_offset: q4_28_from_f64(-1.0),
            sensor_gain: q4_28_from_f64(2.0),
            kp,
            error_bound: Feedback::error_bound(limit, kp),
            ki: q0_32_from_f64(ki),
            derivative: None,
            limit,
            notch: None,
            drift_limit: signal_from_f64(0.01) as u32,
        }
    }

    #[test]
    fn sensor_codes_map_onto_the_output_range_and_stray_bits_are_masked() {
        let fb = feedback(0.5, 0.1);
        assert_eq!(fb.displacement(AdcCode(0)), signal_from_f64(-1.0));
        assert_eq!(fb.displacement(AdcCode(32768)), 0);
        let top = signal_to_f64(fb.displacement(AdcCode(65535)));
        assert!((top - (1.0 - 2.0 / 65536.0)).abs() < 1e-8, "{top}");
        // A code with bits above the ADC's 16 reads as its low 16 bits, never beyond range.
        assert_eq!(fb.displacement(AdcCode(0x1_8000)), 0);
        // A sensor spanning beyond ±2 saturates instead of wrapping.
        let wide = Feedback {
            sensor_offset: q4_28_from_f64(-7.0),
            sensor_gain: q4_28_from_f64(7.9),
            ..fb
        };
        assert_eq!(wide.displacement(AdcCode(0)), i32::MIN);
        let top = signal_to_f64(wide.displacement(AdcCode(65535)));
        assert!(
            (top - (-7.0 + 7.9 * 65535.0 / 65536.0)).abs() < 1e-7,
            "{top}"
        );
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
            s.observed(0);
        }
        assert_eq!(s.integrator(), signal_from_f64(0.2));
        // The command is cut from above while the error still pushes up: the integrator holds...
        let mut s = FeedbackState::at_rest(0);
        s.integrator = signal_from_f64(0.05);
        s.limited(signal_from_f64(1.2), signal_from_f64(1.0));
        s.observed(0);
        for _ in 0..100 {
            fb.correction(&mut s, signal_from_f64(0.5), 0);
            s.limited(signal_from_f64(1.2), signal_from_f64(1.0));
            s.observed(0);
        }
        assert_eq!(s.integrator(), signal_from_f64(0.05));
        // ...but unwinds as soon as the error reverses (the reference is the target of
        // SENSOR_DELAY_TICKS ago).
        for _ in 0..=SENSOR_DELAY_TICKS {
            fb.correction(&mut s, signal_from_f64(-0.5), 0);
        }
        assert!(s.integrator() < signal_from_f64(0.05));
    }

    #[test]
    fn the_reading_is_compared_with_the_target_of_as_many_ticks_ago() {
        let fb = feedback(1.0, 0.0);
        let mut s = FeedbackState::at_rest(0);
        // A ramp the stage follows exactly, read SENSOR_DELAY_TICKS late: no error, no
        // correction (comparing with the present target would see a phantom lag).
        let step = signal_from_f64(0.001);
        for k in 0..100i32 {
            let measured = (k - SENSOR_DELAY_TICKS as i32).max(0) * step;
            assert_eq!(fb.correction(&mut s, k * step, measured), 0, "tick {k}");
        }
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
            let measured = (k - SENSOR_DELAY_TICKS as i32).max(0) * step;
            if (20..30).contains(&k) {
                assert_eq!(fb.held_correction(&mut s, k * step), 0, "tick {k}");
            } else {
                assert_eq!(fb.correction(&mut s, k * step, measured), 0, "tick {k}");
            }
        }
    }

    #[test]
    fn drift_is_flagged_when_the_sensor_leaves_the_estimate_and_cleared_when_it_returns() {
        let fb = feedback(0.5, 0.1);
        let mut s = FeedbackState::at_rest(signal_from_f64(0.3));
        // The estimate and the (delayed) measurement agree, with sensor noise: no flag.
        let mut seed = 3u32;
        for _ in 0..500 {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let noise = ((seed >> 16) as i32 - 32768) * 256; // ±0.8 % of full scale
            assert!(!fb.drifted(&mut s, signal_from_f64(0.3) + noise));
            s.limited(0, 0);
            s.observed(signal_from_f64(0.3));
        }
        // The stage sits 2 % away from the model: flagged within a few filter time constants.
        let flagged = (0..100).position(|_| {
            let d = fb.drifted(&mut s, signal_from_f64(0.32));
            s.limited(0, 0);
            s.observed(signal_from_f64(0.3));
            d
        });
        assert!(matches!(flagged, Some(k) if k < 40), "{flagged:?}");
        // Back in agreement: the flag clears.
        let cleared = (0..200).position(|_| {
            let d = fb.drifted(&mut s, signal_from_f64(0.3));
            s.limited(0, 0);
            s.observed(signal_from_f64(0.3));
            !d
        });
        assert!(cleared.is_some());
        // The measurement is compared with the estimate from SENSOR_DELAY_TICKS ago.
        let mut s = FeedbackState::at_rest(0);
        s.limited(0, 0);
        s.observed(signal_from_f64(0.5));
        for _ in 1..SENSOR_DELAY_TICKS {
            s.limited(0, 0);
            s.observed(0);
        }
        let _ = fb.drifted(&mut s, 0);
        assert!(
            s.drift() < 0,
            "the old estimate (0.5) is what the reading is compared to"
        );
    }

    #[test]
    fn hand_over_makes_the_first_correction_what_the_drive_needs() {
        let fb = feedback(0.5, 0.01);
        let mut s = FeedbackState::at_rest(0);
        s.measured = signal_from_f64(0.1);
        let wanted = signal_from_f64(0.07);
        let rest = fb.hand_over(&mut s, signal_from_f64(0.12), wanted);
        assert_eq!(rest, 0);
        let c = fb.correction(&mut s, signal_from_f64(0.12), signal_from_f64(0.1));
        // The first tick's integral step was allowed for: they agree to rounding.
        assert!((c - wanted).abs() <= 2, "{c} vs {wanted}");
        // Beyond the limit, the rest is handed back: error 0 − 0.1 gives p = −0.05 and an
        // integral step of −0.001, the integrator takes 0.2 of the remaining 0.551, 0.351 is
        // left.
        let rest = fb.hand_over(&mut s, 0, signal_from_f64(0.5));
        assert!(
            (signal_to_f64(rest) - 0.351).abs() < 1e-6,
            "{}",
            signal_to_f64(rest)
        );
    }
}
