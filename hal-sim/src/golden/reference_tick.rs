//! The whole tick in `f64`, and the check that stored vectors agree with it.
//!
//! The reference composes the `f64` models (`crate::reference`) with the tick's
//! other steps written out in real arithmetic from their documented semantics (`src/control.rs`,
//! `src/feedback.rs`, `src/drive.rs`, the README's "Closed loop"): setpoint clamp and hold,
//! feedforward, the sensor reading, the drift check, the PI feedback, range and slew limits,
//! the differential split, the observer. It runs on the stored inputs alone, so it checks the
//! stored outputs independently of the fixed-point code. The feedback, per tick with a reading:
//!
//! * the reading `measured = at_zero + gain · code / 2^bits` (code masked to the ADC's bits) is
//!   [`SENSOR_DELAY_TICKS`] ticks old, so it is compared with the **target of as many ticks
//!   ago** — whether or not the reads in between succeeded (the delay is the converter's);
//! * integral: `i ← clamp(i + ki/f_s · e, ±limit)`, **held** while the previous tick's command
//!   (feedforward + correction) was cut by the range or slew limit in the direction `e`
//!   pushes (`clip = command − applied` of that tick, `clip · e > 0`);
//! * proportional: `kp · clamp(e, ±limit / kp)` — the P term alone is limited to ±limit;
//! * correction `clamp(P + i, ±limit)`, added to the feedforward; on a failed read the
//!   integrator alone (held);
//! * drift: `δ ← δ + (measured − estimate of SENSOR_DELAY_TICKS ago − δ) / 2^DRIFT_FILTER_SHIFT`,
//!   flagged when `|δ|` exceeds the drift limit.
//!
//! Signals that the tick holds in Q2.30 (error, reading, command) saturate at ±2 here too.
//! The golden sets have no derivative or notch (the recipe carries neither) and start in their
//! mode with no mode switch, so the bumpless-transfer offset is always 0 in them: the check
//! refuses a recipe with a derivative or a notch rather than ignore it. Bounds:
//!
//! * **drive** (applied, model-normalised): within [`DRIVE_BOUND_LSB16`] of the reference
//!   chain — the inverse models' documented bound (README, "Fixed point");
//! * **estimate**: within [`ESTIMATE_BOUND_LSB16`] of the reference observer fed the stored
//!   drive — the forward models' documented bound;
//! * **DAC codes**: each the stored drive's exact code rounded to nearest (within
//!   [`CODE_BOUND`] code, clamped to the converter's range);
//! * **flags**: equal to the reference's, except a range or slew flag where the reference's
//!   command lies within the drive bound of the limit, or a drift flag where the reference's
//!   low-passed difference lies within [`DRIFT_BOUND_LSB16`] of the drift limit (counted as
//!   ambiguous).
//!
//! LSB16 = one LSB of a 16-bit converter over the normalised range: `2 / 65536`.

use crate::accuracy::LSB16;
use crate::reference;
use twinstack::control::TickFlags;
use twinstack::drive::Configuration;
use twinstack::feedback::{DRIFT_FILTER_SHIFT, SENSOR_DELAY_TICKS};
use twinstack::fixed_point::signal_to_f64;
use twinstack::golden::{CompensatorChoice, ObserverChoice, Recipe, VectorSet};
use twinstack::Scaling;

/// Largest |stored drive − reference drive|, LSB16.
pub const DRIVE_BOUND_LSB16: f64 = 0.5;
/// Largest |stored estimate − reference observer|, LSB16.
pub const ESTIMATE_BOUND_LSB16: f64 = 0.1;
/// Largest |stored code − exact code|, codes (half a code for rounding, plus the split's
/// Q17.15 arithmetic).
pub const CODE_BOUND: f64 = 0.5 + 1e-3;
/// How far the stored drift filter may be from the reference's, LSB16: the estimate's bound
/// (the filter has gain 1) plus the sensor scaling's and the filter's rounding (< 0.01).
pub const DRIFT_BOUND_LSB16: f64 = ESTIMATE_BOUND_LSB16 + 0.01;

/// How far one set's stored outputs are from the reference.
#[derive(Clone, Debug, PartialEq)]
pub struct Agreement {
    /// Set name.
    pub name: String,
    /// Ticks compared.
    pub ticks: usize,
    /// Largest drive error, LSB16.
    pub drive_lsb16: f64,
    /// Largest estimate error, LSB16.
    pub estimate_lsb16: f64,
    /// Largest DAC code error, codes (before rounding's half code is subtracted).
    pub code_error: f64,
    /// Ticks whose flags differ from the reference's where the reference is unambiguous.
    pub flag_mismatches: usize,
    /// First tick with a flag mismatch.
    pub first_flag_mismatch: Option<(usize, u8, u8)>,
    /// Ticks where a range or slew decision lies within the drive bound of its limit, or the
    /// drift filter within the drift bound of the drift limit.
    pub ambiguous: usize,
    /// First tick whose drive, estimate or code exceeds its bound.
    pub first_violation: Option<usize>,
    /// Ticks the reference held the integrator (anti-windup) against a non-zero error.
    pub integrator_holds: usize,
}

impl Agreement {
    /// Whether every tick is within its bound.
    pub fn holds(&self) -> bool {
        self.first_violation.is_none() && self.flag_mismatches == 0
    }
}

enum Feedforward {
    None,
    InversePi(Box<reference::InversePrandtlIshlinskii>),
    InverseDuhem(reference::InverseDuhem),
}

enum Estimator {
    None,
    Pi(Box<reference::PrandtlIshlinskii>),
    Duhem(reference::Duhem),
}

/// The sensor feedback in real arithmetic (see the module doc), with its memory.
struct ReferenceFeedback {
    /// Displacement at code 0 and per ADC full scale, normalised.
    at_zero: f64,
    gain: f64,
    /// ADC bits.
    bits: u32,
    /// Proportional gain; integral gain per tick; correction (and integrator) limit,
    /// normalised drive.
    kp: f64,
    ki: f64,
    limit: f64,
    /// Drift limit, normalised displacement (`None`: no check).
    drift_limit: Option<f64>,
    /// Integrator.
    integrator: f64,
    /// The previous tick's command minus the drive applied.
    clip: f64,
    /// Targets and the observer's estimates of the last ticks, newest first.
    targets: [f64; SENSOR_DELAY_TICKS],
    estimates: [f64; SENSOR_DELAY_TICKS],
    /// Low-passed measured − estimate.
    drift: f64,
}

/// What the reference feedback gave one tick.
struct FeedbackTick {
    /// The correction added to the feedforward.
    correction: f64,
    /// The integrator was held against a non-zero error.
    held: bool,
    /// The drift flag, and whether the reference's filter lies within the drift bound of the
    /// limit (the stored flag may go either way).
    drift: bool,
    drift_ambiguous: bool,
}

impl ReferenceFeedback {
    fn new(recipe: &Recipe, at_rest: f64) -> anyhow::Result<Option<Self>> {
        let Some(fb) = recipe.feedback else {
            return Ok(None);
        };
        if fb.kd != 0.0 || fb.notch.is_some() {
            anyhow::bail!("the reference tick models PI feedback without derivative or notch");
        }
        let s = &recipe.scaling;
        let at_zero = s.output_to_norm(fb.sensor.displacement_at_zero);
        // The drift check compares the sensor with the observer: none without one.
        let observed = recipe.observer != ObserverChoice::None;
        Ok(Some(Self {
            at_zero,
            gain: s.output_to_norm(fb.sensor.displacement_at_full_scale) - at_zero,
            bits: fb.sensor.adc_bits.min(30),
            kp: fb.kp,
            ki: fb.ki / recipe.drive.control_rate,
            // Fractions of the range; the normalised range is 2 wide.
            limit: 2.0 * fb.limit,
            drift_limit: fb.drift_limit.filter(|_| observed).map(|d| 2.0 * d),
            integrator: 0.0,
            clip: 0.0,
            targets: [at_rest; SENSOR_DELAY_TICKS],
            estimates: [at_rest; SENSOR_DELAY_TICKS],
            drift: 0.0,
        }))
    }

    /// One tick: `code` the sensor's reading (`None`: the read failed), `target` this tick's.
    fn tick(
        &mut self,
        target: f64,
        code: Option<u16>,
        closed: bool,
        drift_tol: f64,
    ) -> FeedbackTick {
        // The target of SENSOR_DELAY_TICKS ago, then this tick's into the history.
        let reference = self.targets[SENSOR_DELAY_TICKS - 1];
        self.targets.rotate_right(1);
        self.targets[0] = target;
        let Some(code) = code else {
            return FeedbackTick {
                correction: if closed { self.integrator } else { 0.0 },
                held: false,
                drift: false,
                drift_ambiguous: false,
            };
        };
        let mask = (1u32 << self.bits) - 1;
        let fraction = (code as u32 & mask) as f64 / (1u64 << self.bits) as f64;
        let measured = saturate(self.at_zero + self.gain * fraction);

        let difference = saturate(measured - self.estimates[SENSOR_DELAY_TICKS - 1]);
        self.drift += (difference - self.drift) / (1u32 << DRIFT_FILTER_SHIFT) as f64;
        let (drift, drift_ambiguous) = match self.drift_limit {
            Some(l) => (
                self.drift.abs() > l,
                (self.drift.abs() - l).abs() < drift_tol,
            ),
            None => (false, false),
        };

        let mut correction = 0.0;
        let mut held = false;
        if closed {
            let error = saturate(reference - measured);
            held = self.clip * error > 0.0;
            if !held {
                self.integrator =
                    (self.integrator + self.ki * error).clamp(-self.limit, self.limit);
            }
            let p = if self.kp > 0.0 {
                self.kp * error.clamp(-self.limit / self.kp, self.limit / self.kp)
            } else {
                0.0
            };
            correction = (p + self.integrator).clamp(-self.limit, self.limit);
        }
        FeedbackTick {
            correction,
            held,
            drift,
            drift_ambiguous,
        }
    }

    /// End of a tick: what the limits cut from the command, and the observer's estimate.
    fn end_tick(&mut self, command: f64, applied: f64, estimate: f64) {
        self.clip = command - applied;
        self.estimates.rotate_right(1);
        self.estimates[0] = estimate;
    }
}

/// A Q2.30 quantity's range: the tick saturates at ±2.
fn saturate(x: f64) -> f64 {
    x.clamp(-2.0, 2.0)
}

/// Initial output of the reference observer at rest at `u0` volts (the controller's start).
fn observer_at_rest(recipe: &Recipe, u0: f64) -> anyhow::Result<(Estimator, Option<f64>)> {
    let s = &recipe.scaling;
    Ok(match recipe.observer {
        ObserverChoice::None => (Estimator::None, None),
        ObserverChoice::Pi => {
            let p = recipe
                .pi
                .as_ref()
                .ok_or_else(|| anyhow::anyhow!("no P–I model"))?;
            let m = reference::PrandtlIshlinskii::new(p, s, u0)?;
            let y = m.clone().step(u0);
            (Estimator::Pi(Box::new(m)), Some(y))
        }
        ObserverChoice::Duhem => {
            let d = recipe
                .duhem
                .as_ref()
                .ok_or_else(|| anyhow::anyhow!("no Duhem model"))?;
            let y = d.beta * u0 + d.offset;
            (
                Estimator::Duhem(reference::Duhem::new(d, s, u0, y)?),
                Some(y),
            )
        }
    })
}

/// The reference drive window (model-normalised) and slew per tick, from the drive settings
/// as `DifferentialDrive::new` specifies them.
fn limits(recipe: &Recipe) -> (f64, f64, f64) {
    let d = &recipe.drive;
    let s = &recipe.scaling;
    let (lo, hi) = match d.configuration {
        Configuration::Differential => (
            d.min_voltage.max(2.0 * d.bias - d.max_voltage),
            d.max_voltage.min(2.0 * d.bias - d.min_voltage),
        ),
        Configuration::Unidirectional => (d.min_voltage, d.max_voltage),
    };
    let slew = (d.slew_rate / d.control_rate / s.input_half_span()).min(2.0);
    (
        s.input_to_norm(lo).max(-1.0),
        s.input_to_norm(hi).min(1.0),
        slew,
    )
}

fn exact_code(volts: f64, full_scale_volts: f64, full_scale_code: u16) -> f64 {
    (volts * full_scale_code as f64 / full_scale_volts).clamp(0.0, full_scale_code as f64)
}

fn norm(s: &Scaling, y_phys: f64) -> f64 {
    s.output_to_norm(y_phys)
}

/// Checks one stored set against the `f64` reference tick.
pub fn check(set: &VectorSet<'_>) -> anyhow::Result<Agreement> {
    let recipe = set
        .recipe()
        .map_err(|e| anyhow::anyhow!("set {}: {e:?}", set.name()))?;
    let s = recipe.scaling;
    let d = recipe.drive;
    let (dmin, dmax, slew) = limits(&recipe);
    let rest = s.input_to_norm(d.bias).max(dmin).min(dmax);
    let u_rest = s.norm_to_input(rest);

    // The controller's start: models relaxed at the rest drive, setpoint at the estimate.
    let (mut estimator, y_rest) = observer_at_rest(&recipe, u_rest)?;
    let y_rest_norm = y_rest.map(|y| norm(&s, y)).unwrap_or(rest);
    let mut feedforward = match recipe.compensator {
        CompensatorChoice::None => Feedforward::None,
        CompensatorChoice::InversePi => {
            let p = recipe
                .pi
                .as_ref()
                .ok_or_else(|| anyhow::anyhow!("no P–I model"))?;
            // Relaxed at the desired output the observer gives: the forward model at rest at
            // u0 outputs c + Σw·u0, so u0 = (y − c) / Σw.
            let c = p.canonical()?;
            let total: f64 = c.weights.iter().sum();
            let u0 = (s.norm_to_output(y_rest_norm) - c.offset) / total;
            Feedforward::InversePi(Box::new(reference::InversePrandtlIshlinskii::new(
                p, &s, u0,
            )?))
        }
        CompensatorChoice::InverseDuhem => {
            let m = recipe
                .duhem
                .as_ref()
                .ok_or_else(|| anyhow::anyhow!("no Duhem model"))?;
            Feedforward::InverseDuhem(reference::InverseDuhem::new(
                m,
                &s,
                u_rest,
                m.beta * u_rest + m.offset,
            )?)
        }
    };
    let mut feedback = ReferenceFeedback::new(&recipe, y_rest_norm)?;
    // The golden recipes start closed loop whenever they have feedback (`Recipe::build`).
    let closed = feedback.is_some();
    let drift_tol = DRIFT_BOUND_LSB16 * LSB16;

    let mut target = y_rest_norm;
    let mut previous = rest;
    let drive_tol = DRIVE_BOUND_LSB16 * LSB16;
    let mut a = Agreement {
        name: set.name().to_string(),
        ticks: 0,
        drive_lsb16: 0.0,
        estimate_lsb16: 0.0,
        code_error: 0.0,
        flag_mismatches: 0,
        first_flag_mismatch: None,
        ambiguous: 0,
        first_violation: None,
        integrator_holds: 0,
    };
    for (k, (input, out)) in set.inputs().zip(set.outputs()).enumerate() {
        let mut flags = 0u8;
        match input.setpoint {
            Some(sp) => target = signal_to_f64(sp).clamp(-1.0, 1.0),
            None => flags |= TickFlags::UNDERRUN,
        }
        let ff = match &mut feedforward {
            Feedforward::None => target,
            Feedforward::InversePi(m) => s.input_to_norm(m.step(s.norm_to_output(target))),
            Feedforward::InverseDuhem(m) => s.input_to_norm(m.step(s.norm_to_output(target))),
        };
        let mut command = ff;
        // Flags the stored tick may set either way (its decision lies within its bound).
        let mut loose = 0u8;
        if let Some(fb) = &mut feedback {
            if input.adc_fails {
                flags |= TickFlags::ADC_ERROR;
            }
            let code = (!input.adc_fails).then_some(input.adc_code);
            let t = fb.tick(target, code, closed, drift_tol);
            if t.drift {
                flags |= TickFlags::DRIFT;
            }
            a.integrator_holds += usize::from(t.held);
            if t.drift_ambiguous {
                loose |= TickFlags::DRIFT;
            }
            command = saturate(ff + t.correction);
        }
        let ranged = command.clamp(dmin, dmax);
        let applied = ranged.clamp(previous - slew, previous + slew);
        if ranged != command {
            flags |= TickFlags::RANGE_LIMIT;
        }
        let limit_bits = TickFlags::RANGE_LIMIT | TickFlags::SLEW_LIMIT;
        if (command - dmin).abs() < drive_tol || (command - dmax).abs() < drive_tol {
            loose |= limit_bits;
        }
        if applied != ranged {
            flags |= TickFlags::SLEW_LIMIT;
        }
        if (ranged - (previous - slew)).abs() < drive_tol
            || (ranged - (previous + slew)).abs() < drive_tol
        {
            loose |= limit_bits;
        }
        if input.dac_fails {
            flags |= TickFlags::DAC_ERROR;
        }
        previous = applied;

        // Drive against the reference chain.
        let stored_drive = signal_to_f64(out.drive);
        let drive_err = (stored_drive - applied).abs() / LSB16;
        // Observer and codes against the stored drive.
        let u_volts = s.norm_to_input(stored_drive);
        let estimate_ref = match &mut estimator {
            Estimator::None => 0.0,
            Estimator::Pi(m) => norm(&s, m.step(u_volts)),
            Estimator::Duhem(m) => norm(&s, m.step(u_volts)),
        };
        if let Some(fb) = &mut feedback {
            fb.end_tick(command, applied, estimate_ref);
        }
        let estimate_err = (signal_to_f64(out.estimate) - estimate_ref).abs() / LSB16;
        let right_volts = match d.configuration {
            Configuration::Differential => 2.0 * d.bias - u_volts,
            Configuration::Unidirectional => d.right_idle,
        };
        let code_err = [(out.left, u_volts), (out.right, right_volts)]
            .iter()
            .map(|&(code, v)| {
                (code as f64 - exact_code(v, d.amplifier_full_scale, d.dac_full_scale)).abs()
            })
            .fold(0.0, f64::max);

        a.ticks += 1;
        a.drive_lsb16 = a.drive_lsb16.max(drive_err);
        a.estimate_lsb16 = a.estimate_lsb16.max(estimate_err);
        a.code_error = a.code_error.max(code_err);
        if (drive_err > DRIVE_BOUND_LSB16
            || estimate_err > ESTIMATE_BOUND_LSB16
            || code_err > CODE_BOUND)
            && a.first_violation.is_none()
        {
            a.first_violation = Some(k);
        }
        if loose != 0 {
            a.ambiguous += 1;
        }
        if (flags ^ out.flags) & !loose != 0 {
            a.flag_mismatches += 1;
            a.first_flag_mismatch.get_or_insert((k, out.flags, flags));
        }
    }
    Ok(a)
}
