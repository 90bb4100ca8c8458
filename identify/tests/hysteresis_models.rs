//! Host checks of the fixed-point hysteresis models against their `f64` reference and against
//! the properties the theory promises (see the book, docs/src/reference/models.md).
//!
//! Bounds are stated in LSB of a 16-bit output spanning the configured output range
//! (`LSB16 = 2 / 65536` in normalised units).

use proptest::prelude::*;
use twinstack::fixed_point::{signal_from_f64 as q, signal_to_f64 as f};
use twinstack::models::duhem::{Duhem, InverseDuhem};
use twinstack::models::prandtl_ishlinskii::{InversePrandtlIshlinskii, PrandtlIshlinskii};
use twinstack::{DuhemParams, ParamError, PiParams, Scaling, Thresholds};
use twinstack_identify::reference;

/// One LSB of a 16-bit converter over the normalised range [-1, 1].
const LSB16: f64 = 2.0 / 65536.0;

/// A random invertible P–I model in volts/µm over the input range `[u_min, u_max]`, with an
/// output range wide enough for every state the play operators can reach.
/// A bank's error bound in LSB16: its gain `Σ|w_i|` (Q8.24 weights) times 1.5 LSB16, how far
/// each operator may run from the `f64` one (the input rounded to the Q1.15 grid, half a
/// step, a whole one at +1, which the lane's top `1 − 2^-15` misses; half a step of
/// threshold).
fn gain(bank: &twinstack::models::prandtl_ishlinskii::PlayOperatorBank) -> f64 {
    1.5 * (0..bank.operators())
        .map(|i| (bank.weight(i) as f64).abs() / (1u64 << 24) as f64)
        .sum::<f64>()
}

/// The weights' Q8.24 rounding and the output's floor, LSB16.
const SLACK: f64 = 0.05;

fn pi_model() -> impl Strategy<Value = (PiParams, Scaling)> {
    (
        1usize..=32,
        prop::bool::ANY,
        prop::collection::vec(-0.45f64..1.0, 32),
        0.0f64..0.5,
        prop::bool::ANY,
        -5.0f64..5.0,
    )
        .prop_map(|(n, geometric, raw, a0, unipolar, offset)| {
            let (u_min, u_max) = if unipolar {
                (0.0, 150.0)
            } else {
                (-100.0, 100.0)
            };
            let amplitude = u_max - u_min;
            let kind = if geometric {
                Thresholds::Geometric { ratio: 1.15 }
            } else {
                Thresholds::Uniform
            };
            let thresholds = kind.generate(n, amplitude).unwrap();
            // Weights (µm/V): w_1 > 0, later ones may be negative while every partial sum
            // stays at least 20 % of the largest it has been (invertible, well conditioned).
            let mut weights = Vec::new();
            let mut sum = 0.0;
            let mut peak: f64 = 0.0;
            for (i, &r) in raw.iter().take(n).enumerate() {
                let mut w = if i == 0 { 0.05 + r.abs() } else { r } * 0.1;
                if sum + w < 0.2 * peak.max(sum) {
                    w = w.abs();
                }
                sum += w;
                peak = peak.max(sum);
                weights.push(w);
            }
            let params = PiParams::new(a0 * 0.1, offset, &thresholds, &weights).unwrap();
            let reach = (a0 * 0.1 + weights.iter().map(|w| w.abs()).sum::<f64>())
                * u_max.abs().max(u_min.abs());
            let scaling = Scaling::new(u_min, u_max, offset - reach, offset + reach).unwrap();
            (params, scaling)
        })
}

/// A piecewise-monotone input: turning points in [-1, 1] (normalised), joined by ramps of a
/// random number of samples, plus some jumps straight to the range ends.
fn piecewise_monotone() -> impl Strategy<Value = Vec<f64>> {
    prop::collection::vec((-1.0f64..=1.0, 1usize..40), 2..24).prop_map(|turns| {
        let mut out = vec![0.0];
        for (i, (target, steps)) in turns.into_iter().enumerate() {
            let target = match i % 9 {
                7 => 1.0,
                8 => -1.0,
                _ => target,
            };
            let from = *out.last().unwrap();
            for k in 1..=steps {
                out.push(from + (target - from) * k as f64 / steps as f64);
            }
        }
        out
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    /// The compensator's promise: driving the (fixed-point) model with the inverse's output
    /// reproduces the desired displacement, within what the banks' Q1.15 grid allows: the
    /// inverse's drive is within `G_i = 1.5·Σ|w'|` LSB16 of the exact inverse ([`gain`]), the
    /// forward model (slope at most `Σ|w| ≤ G_f`) turns that into at most `G_f·G_i`, plus its
    /// own `G_f` (see `twinstack_identify::accuracy`).
    #[test]
    fn inverse_then_forward_returns_the_setpoint((params, scaling) in pi_model(), u in piecewise_monotone()) {
        let forward = PrandtlIshlinskii::new(&params, &scaling).unwrap();
        let inverse = match InversePrandtlIshlinskii::new(&params, &scaling) {
            Ok(inv) => inv,
            // Some random models need inverse weights beyond Q8.24: refused, not wrong.
            Err(ParamError::WeightOutOfRange { .. } | ParamError::GainSumTooLarge) => return Ok(()),
            Err(e) => panic!("valid model refused: {e}"),
        };
        // Reachable setpoints: the reference model's response to a random input.
        let mut truth = reference::PrandtlIshlinskii::new(&params, &scaling, scaling.norm_to_input(0.0)).unwrap();
        let mut fwd_state = forward.state_at_rest(0);
        let y0 = forward.step(&mut fwd_state, 0);
        let mut inv_state = inverse.state_at_rest(y0);
        let mut worst = 0.0f64;
        for &un in &u {
            let y_desired = scaling.output_to_norm(truth.step(scaling.norm_to_input(un)));
            let drive = inverse.step(&mut inv_state, q(y_desired));
            let y = f(forward.step(&mut fwd_state, drive));
            worst = worst.max((y - y_desired).abs());
        }
        let (gf, gi) = (gain(forward.bank()), gain(inverse.bank()));
        let bound = gf * (1.0 + gi) + SLACK;
        prop_assert!(worst <= bound * LSB16, "inverse∘forward error {:.3} LSB16 (bound {bound:.2})", worst / LSB16);
    }

    /// Fixed point agrees with the f64 reference within its bank's bound `1.5·Σ|w|` LSB16
    /// (the operators' Q1.15 grid, [`gain`]) — including inputs at the range limits
    /// and full-range steps (the input strategy jumps to ±1).
    #[test]
    fn fixed_point_pi_matches_the_f64_reference((params, scaling) in pi_model(), u in piecewise_monotone()) {
        let fixed = PrandtlIshlinskii::new(&params, &scaling).unwrap();
        let mut reference = reference::PrandtlIshlinskii::new(&params, &scaling, scaling.norm_to_input(0.0)).unwrap();
        let mut state = fixed.state_at_rest(0);
        let bound = gain(fixed.bank()) + SLACK;
        for &un in &u {
            let want = scaling.output_to_norm(reference.step(scaling.norm_to_input(un)));
            let got = f(fixed.step(&mut state, q(un)));
            prop_assert!((got - want).abs() <= bound * LSB16, "{got} vs {want}");
        }
    }

    #[test]
    fn fixed_point_inverse_pi_matches_the_f64_reference((params, scaling) in pi_model(), u in piecewise_monotone()) {
        let Ok(fixed) = InversePrandtlIshlinskii::new(&params, &scaling) else { return Ok(()) };
        let mut reference = reference::InversePrandtlIshlinskii::new(&params, &scaling, scaling.norm_to_input(0.0)).unwrap();
        let mut fwd = reference::PrandtlIshlinskii::new(&params, &scaling, scaling.norm_to_input(0.0)).unwrap();
        let y0 = scaling.output_to_norm(fwd.clone().step(scaling.norm_to_input(0.0)));
        let mut state = fixed.state_at_rest(q(y0));
        // The inverse's bank bound `1.5·Σ|w'|` LSB16 (its operators' Q1.15 grid, [`gain`]).
        let bound = gain(fixed.bank()) + SLACK;
        for &un in &u {
            let y = fwd.step(scaling.norm_to_input(un));
            let want = scaling.input_to_norm(reference.step(y));
            let got = f(fixed.step(&mut state, q(scaling.output_to_norm(y))));
            prop_assert!((got - want).abs() <= bound * LSB16, "{got} vs {want}");
        }
    }

    /// Rate independence: resampling the monotone segments (more or fewer samples per ramp)
    /// leaves the output at every turning point unchanged, bit for bit.
    #[test]
    fn play_operator_is_rate_independent(
        (params, scaling) in pi_model(),
        turns in prop::collection::vec(-1.0f64..=1.0, 2..12),
        coarse in 1usize..5, fine in 5usize..60,
    ) {
        let model = PrandtlIshlinskii::new(&params, &scaling).unwrap();
        let outputs_at_turns = |steps: usize| {
            let mut s = model.state_at_rest(0);
            let mut from = 0.0;
            let mut at_turns = Vec::new();
            for &t in &turns {
                for k in 1..=steps {
                    let u = if k == steps { t } else { from + (t - from) * k as f64 / steps as f64 };
                    model.step(&mut s, q(u));
                }
                at_turns.push(s);
                from = t;
            }
            at_turns
        };
        prop_assert_eq!(outputs_at_turns(coarse), outputs_at_turns(fine));
    }

    /// Wiping-out: an inner minor loop that returns to its starting turning point leaves no
    /// trace — the operator outputs equal those before the loop, bit for bit.
    #[test]
    fn inner_minor_loops_are_wiped_out(
        (params, scaling) in pi_model(),
        high in 0.2f64..1.0, low in -1.0f64..-0.2, inner in 0.05f64..0.95,
    ) {
        let model = PrandtlIshlinskii::new(&params, &scaling).unwrap();
        let ramp = |s: &mut _, from: f64, to: f64| {
            for k in 1..=50 {
                model.step(s, q(from + (to - from) * k as f64 / 50.0));
            }
        };
        let mut s = model.state_at_rest(0);
        ramp(&mut s, 0.0, high);
        ramp(&mut s, high, low);
        let before = s;
        // Inner loop inside [low, high]: up to a point between them and back to `low`.
        let peak = low + inner * (high - low);
        ramp(&mut s, low, peak);
        ramp(&mut s, peak, low);
        prop_assert_eq!(model.bank().outputs(&before), model.bank().outputs(&s));
        // …and the two states behave the same from here on.
        let mut before = before;
        for k in 0..=50 {
            let u = q(low + (1.0 - low) * k as f64 / 50.0);
            prop_assert_eq!(model.step(&mut before, u), model.step(&mut s, u));
        }
    }

    /// Inverse Duhem then Duhem returns the setpoint. Setpoints are made reachable by
    /// construction: they are the reference model's response to a smooth drive.
    #[test]
    fn inverse_duhem_then_duhem_returns_the_setpoint(
        alpha in 0.005f64..0.05, beta in 0.05f64..0.2, gamma_ratio in 0.6f64..1.5,
        amplitude in 0.2f64..0.95, cycles in 1usize..4,
    ) {
        let params = DuhemParams { alpha, beta, gamma: beta * gamma_ratio, offset: 1.0 };
        let reach = beta * 100.0 + (beta * gamma_ratio - beta).abs() / alpha + 2.0;
        let scaling = Scaling::new(-100.0, 100.0, 1.0 - reach, 1.0 + reach).unwrap();
        let inverse = InverseDuhem::new(&params, &scaling).unwrap();
        let forward = Duhem::new(&params, &scaling).unwrap();
        let y0 = forward.anhysteretic(0);
        let mut truth = reference::Duhem::new(&params, &scaling, 0.0, scaling.norm_to_output(f(y0))).unwrap();
        let mut inv_state = inverse.model().state_at(0, y0);
        let mut fwd_state = forward.state_at(0, y0);
        let n = 2000;
        let mut worst = 0.0f64;
        for k in 0..cycles * n {
            let phase = k as f64 / n as f64 * core::f64::consts::TAU;
            let y_desired = scaling.output_to_norm(truth.step(100.0 * amplitude * phase.sin()));
            let u = inverse.step(&mut inv_state, q(y_desired));
            let y = f(forward.step(&mut fwd_state, u));
            worst = worst.max((y - y_desired).abs());
        }
        prop_assert!(worst <= LSB16, "inverse Duhem∘Duhem error {:.3} LSB16", worst / LSB16);
    }
}

/// Discrete Duhem converges to the closed-form solution of the continuous model on a monotone
/// input; the fixed-point observer tracks the f64 discrete form to well under an LSB.
#[test]
fn duhem_matches_its_closed_form_on_a_monotone_ramp() {
    let params = DuhemParams {
        alpha: 0.02,
        beta: 0.12,
        gamma: 0.08,
        offset: 0.5,
    };
    let scaling = Scaling::new(-150.0, 150.0, -20.0, 20.0).unwrap();
    let (u0, y0) = (-150.0, -17.0);
    let fixed = Duhem::new(&params, &scaling).unwrap();
    let mut fs = fixed.state_at(q(-1.0), q(scaling.output_to_norm(y0)));
    let mut reference = reference::Duhem::new(&params, &scaling, u0, y0).unwrap();
    let steps = 100_000;
    let mut worst_closed: f64 = 0.0;
    let mut worst_fixed: f64 = 0.0;
    for k in 1..=steps {
        let u = u0 + 300.0 * k as f64 / steps as f64;
        let discrete = reference.step(u);
        let closed = reference::Duhem::closed_form_monotone(&params, u0, y0, u);
        let got = scaling.norm_to_output(f(fixed.step(&mut fs, q(scaling.input_to_norm(u)))));
        worst_closed = worst_closed.max((discrete - closed).abs());
        worst_fixed = worst_fixed.max((got - discrete).abs());
    }
    // Euler error of the discrete form: O(α Δu) relative = 0.02 · 0.003 V → ≈ 1e-4 of the span.
    let span = 40.0;
    assert!(
        worst_closed / span < 2e-4,
        "discrete vs closed form: {worst_closed}"
    );
    assert!(
        worst_fixed / span * 2.0 < 0.5 * LSB16,
        "fixed vs f64: {worst_fixed}"
    );
    // And the end point really is on the ascending anhysteretic branch, not at y0.
    assert!(reference.y > 10.0, "end point {}", reference.y);
}

/// Fixed-point Duhem follows the f64 discrete form over repeated full-range cycles and large
/// steps, without drifting.
#[test]
fn fixed_point_duhem_matches_the_f64_reference_over_many_cycles() {
    let params = DuhemParams {
        alpha: 0.03,
        beta: 0.1,
        gamma: 0.07,
        offset: 0.0,
    };
    let scaling = Scaling::new(0.0, 150.0, -2.0, 18.0).unwrap();
    let fixed = Duhem::new(&params, &scaling).unwrap();
    let mut fs = fixed.state_at(q(-1.0), q(scaling.output_to_norm(0.0)));
    let mut reference = reference::Duhem::new(&params, &scaling, 0.0, 0.0).unwrap();
    let mut worst: f64 = 0.0;
    for k in 0..50_000 {
        // 10 cycles of a full-range triangle, then steps between the range ends.
        let u = if k < 40_000 {
            let ph = (k % 4000) as f64 / 4000.0;
            150.0 * if ph < 0.5 { 2.0 * ph } else { 2.0 - 2.0 * ph }
        } else if (k / 100) % 2 == 0 {
            150.0
        } else {
            0.0
        };
        let want = scaling.output_to_norm(reference.step(u));
        let got = f(fixed.step(&mut fs, q(scaling.input_to_norm(u))));
        worst = worst.max((got - want).abs());
    }
    assert!(
        worst <= 0.5 * LSB16,
        "fixed vs f64 Duhem: {:.3} LSB16",
        worst / LSB16
    );
}

#[test]
fn non_invertible_models_are_refused_naming_the_first_failing_operator() {
    let scaling = Scaling::new(0.0, 150.0, -10.0, 10.0).unwrap();
    let r = Thresholds::Uniform.generate(4, 150.0).unwrap();
    let p = PiParams::new(0.0, 0.0, &r, &[0.1, -0.05, -0.04, -0.02]).unwrap();
    assert_eq!(
        InversePrandtlIshlinskii::new(&p, &scaling),
        Err(ParamError::PartialSumNotPositive { operator: 4 })
    );
    // The forward model of the same parameters is still a valid observer.
    assert!(PrandtlIshlinskii::new(&p, &scaling).is_ok());
    let p = PiParams::new(0.0, 0.0, &r, &[-0.1, 0.2, 0.1, 0.1]).unwrap();
    assert_eq!(
        InversePrandtlIshlinskii::new(&p, &scaling),
        Err(ParamError::FirstWeightNotPositive)
    );
}

/// Switching the compensator on mid-run: the inverse state derived from the forward state
/// (`p'_i = S_i p_i + Σ_{j>i} w_j p_j`) makes the inverse agree with the present drive.
#[test]
fn inverse_state_from_forward_state_continues_without_a_jump() {
    let scaling = Scaling::new(-100.0, 100.0, -30.0, 30.0).unwrap();
    let r = Thresholds::Uniform.generate(9, 200.0).unwrap();
    let p = PiParams::new(
        0.0,
        0.0,
        &r,
        &[0.1, 0.02, 0.01, 0.01, 0.005, 0.004, 0.003, 0.002, 0.001],
    )
    .unwrap();
    let fwd = PrandtlIshlinskii::new(&p, &scaling).unwrap();
    let inv = InversePrandtlIshlinskii::new(&p, &scaling).unwrap();
    let mut s = fwd.state_at_rest(0);
    let mut u = 0.0;
    for k in 0..300 {
        u = (k as f64 * 0.05).sin() * (1.0 - k as f64 / 400.0);
        fwd.step(&mut s, q(u));
    }
    let y = fwd.step(&mut s, q(u));
    let mut inv_state = inv.state_from_forward(&fwd.bank().outputs(&s));
    let drive = f(inv.step(&mut inv_state, y));
    assert!(
        (drive - u).abs() < 4.0 * LSB16,
        "drive {drive} vs applied {u}"
    );
}

/// A setpoint step across most of the range, with `α` large enough that one sample's drive
/// step would clamp the discrete model's `a = α|Δu|` at 1: the inverse reaches the new setpoint
/// in a few samples and stays there, instead of ping-ponging between the range ends.
#[test]
fn inverse_duhem_settles_after_a_large_setpoint_step() {
    let gain = 0.5285;
    let params = DuhemParams {
        alpha: 0.03,
        beta: gain,
        gamma: 0.75 * gain,
        offset: -70.0 * gain,
    };
    let scaling = Scaling::new(0.0, 140.0, -40.0, 40.0).unwrap();
    let inverse = InverseDuhem::new(&params, &scaling).unwrap();
    let forward = Duhem::new(&params, &scaling).unwrap();
    let mut inv_state = inverse.model().state_at(0, forward.anhysteretic(0));
    let mut fwd_state = inv_state;
    let mut reference = reference::InverseDuhem::new(
        &params,
        &scaling,
        70.0,
        scaling.norm_to_output(f(inv_state.y)),
    )
    .unwrap();
    for (target, ticks) in [(0.5, 2000), (-0.3, 30), (0.7, 30)] {
        let mut drives = Vec::new();
        for _ in 0..ticks {
            let u = inverse.step(&mut inv_state, q(target));
            reference.step(scaling.norm_to_output(target));
            forward.step(&mut fwd_state, u);
            drives.push(u);
        }
        // Settled: the last drives agree to well under an LSB16 (the fixed point may still
        // creep by a few Q2.30 LSB while it rounds onto the target).
        let last = &drives[drives.len() - 5..];
        assert!(
            last.iter()
                .all(|&u| (f(u) - f(last[0])).abs() < LSB16 / 16.0),
            "{target}: drive still moving {last:?}"
        );
        assert!(
            (f(fwd_state.y) - target).abs() <= LSB16,
            "{target}: at {}",
            f(fwd_state.y)
        );
        let r = scaling.output_to_norm(reference.model().y);
        assert!((r - target).abs() <= LSB16, "reference {target}: at {r}");
    }
}

/// A gentle model (α below 0.5 per input half-span, so 1/α exceeds the whole range): the
/// per-sample step cap must not overflow and the compensator still tracks.
#[test]
fn inverse_duhem_with_small_alpha_tracks_without_overflowing_its_step_cap() {
    let params = DuhemParams {
        alpha: 0.002,
        beta: 0.1,
        gamma: 0.08,
        offset: 0.0,
    };
    let scaling = Scaling::new(-100.0, 100.0, -25.0, 25.0).unwrap();
    let inverse = InverseDuhem::new(&params, &scaling).unwrap();
    let forward = Duhem::new(&params, &scaling).unwrap();
    let y0 = forward.anhysteretic(0);
    let mut truth =
        reference::Duhem::new(&params, &scaling, 0.0, scaling.norm_to_output(f(y0))).unwrap();
    let mut inv_state = inverse.model().state_at(0, y0);
    let mut fwd_state = forward.state_at(0, y0);
    let mut worst = 0.0f64;
    for k in 0..4000 {
        let y_desired = scaling.output_to_norm(truth.step(80.0 * (k as f64 * 0.003).sin()));
        let u = inverse.step(&mut inv_state, q(y_desired));
        let y = f(forward.step(&mut fwd_state, u));
        worst = worst.max((y - y_desired).abs());
    }
    assert!(worst <= LSB16, "error {:.3} LSB16", worst / LSB16);
}
