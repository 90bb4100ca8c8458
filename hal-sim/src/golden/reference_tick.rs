//! The whole tick in `f64`, and the check that stored vectors agree with it.
//!
//! The reference composes the library's `f64` models (`twinstack::reference`) with the tick's
//! other steps written out in real arithmetic from their specification (`src/control.rs`,
//! `src/drive.rs`): setpoint clamp and hold, feedforward, PI feedback with clamped integrator
//! and anti-windup, range and slew limits, the differential split, the observer. It runs on the
//! stored inputs alone, so it checks the stored outputs independently of the fixed-point code:
//!
//! * **drive** (applied, model-normalised): within [`DRIVE_BOUND_LSB16`] of the reference
//!   chain — the inverse models' documented bound (README, "Fixed point");
//! * **estimate**: within [`ESTIMATE_BOUND_LSB16`] of the reference observer fed the stored
//!   drive — the forward models' documented bound;
//! * **DAC codes**: each the stored drive's exact code rounded to nearest (within
//!   [`CODE_BOUND`] code, clamped to the converter's range);
//! * **flags**: equal to the reference's, except a range or slew flag where the reference's
//!   command lies within the drive bound of the limit (counted as ambiguous).
//!
//! LSB16 = one LSB of a 16-bit converter over the normalised range: `2 / 65536`.

use crate::accuracy::LSB16;
use twinstack::control::TickFlags;
use twinstack::drive::Configuration;
use twinstack::fixed_point::signal_to_f64;
use twinstack::golden::{CompensatorChoice, ObserverChoice, Recipe, VectorSet};
use twinstack::{reference, Scaling};

/// Largest |stored drive − reference drive|, LSB16.
pub const DRIVE_BOUND_LSB16: f64 = 0.5;
/// Largest |stored estimate − reference observer|, LSB16.
pub const ESTIMATE_BOUND_LSB16: f64 = 0.1;
/// Largest |stored code − exact code|, codes (half a code for rounding, plus the split's
/// Q17.15 arithmetic).
pub const CODE_BOUND: f64 = 0.5 + 1e-3;

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
    /// Ticks where a range or slew decision lies within the drive bound of its limit.
    pub ambiguous: usize,
    /// First tick whose drive, estimate or code exceeds its bound.
    pub first_violation: Option<usize>,
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
    let fb = recipe.feedback.map(|fb| {
        let at_zero = s.output_to_norm(fb.sensor.displacement_at_zero);
        let gain = s.output_to_norm(fb.sensor.displacement_at_full_scale) - at_zero;
        let bits = fb.sensor.adc_bits.min(30);
        (
            at_zero,
            gain,
            bits,
            fb.kp,
            fb.ki / d.control_rate,
            2.0 * fb.limit,
        )
    });

    let mut target = y_rest_norm;
    let mut previous = rest;
    let mut integrator = 0.0f64;
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
        if let Some((at_zero, gain, bits, kp, ki, bound)) = fb {
            if input.adc_fails {
                flags |= TickFlags::ADC_ERROR;
                command = ff + integrator;
            } else {
                let mask = (1u32 << bits) - 1;
                let code = (input.adc_code as u32 & mask) as f64;
                let measured = at_zero + gain * code / (1u64 << bits) as f64;
                let error = target - measured;
                let held = (previous >= dmax && error > 0.0) || (previous <= dmin && error < 0.0);
                if !held {
                    integrator = (integrator + ki * error).clamp(-bound, bound);
                }
                command = ff + (kp * error + integrator).clamp(-bound, bound);
            }
        }
        let ranged = command.clamp(dmin, dmax);
        let applied = ranged.clamp(previous - slew, previous + slew);
        let mut ambiguous = false;
        if ranged != command {
            flags |= TickFlags::RANGE_LIMIT;
        }
        if (command - dmin).abs() < drive_tol || (command - dmax).abs() < drive_tol {
            ambiguous = true;
        }
        if applied != ranged {
            flags |= TickFlags::SLEW_LIMIT;
        }
        if (ranged - (previous - slew)).abs() < drive_tol
            || (ranged - (previous + slew)).abs() < drive_tol
        {
            ambiguous = true;
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
        let limit_bits = TickFlags::RANGE_LIMIT | TickFlags::SLEW_LIMIT;
        if ambiguous {
            a.ambiguous += 1;
        }
        let differs = if ambiguous {
            (flags ^ out.flags) & !limit_bits != 0
        } else {
            flags != out.flags
        };
        if differs {
            a.flag_mismatches += 1;
            a.first_flag_mismatch.get_or_insert((k, out.flags, flags));
        }
    }
    Ok(a)
}
