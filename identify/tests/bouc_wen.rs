//! The generalised Bouc–Wen model in fixed point: against its `f64` reference, and its
//! compensator against the forward model (tracking, boundedness, no
//! ratchet on a noisy desired trajectory), and in the tick.

use proptest::prelude::*;
use std::path::PathBuf;
use twinstack::board::fakes::{FixedAdc, RecordingDac};
use twinstack::config::settings::{Hardware, Mode, Model, Settings};
use twinstack::fixed_point::{signal_from_f64 as q, signal_to_f64 as f};
use twinstack::models::bouc_wen::{BoucWen, InverseBoucWen};
use twinstack::services::observer::Observed;
use twinstack::{BoucWenParams, Scaling};
use twinstack_identify::identification::auto::identify_auto;
use twinstack_identify::identification::score::score;
use twinstack_identify::identification::{identify, IdentifyOptions, ModelKind};
use twinstack_identify::reference;
use twinstack_identify::stage_model::Hysteresis;
use twinstack_link::measured_data::MeasuredData;

/// One LSB of a 16-bit converter over the normalised range [-1, 1].
const LSB16: f64 = 2.0 / 65536.0;

fn params() -> BoucWenParams {
    BoucWenParams {
        k: 0.42,
        offset: 1.0,
        a: 0.1,
        beta: 0.04,
        gamma: 0.008,
        psi: 0.006,
        chi: 0.002,
    }
}

fn scaling() -> Scaling {
    Scaling::new(0.0, 140.0, -5.0, 75.0).unwrap()
}

/// A small deterministic generator (LCG), uniform in [-1, 1).
struct Noise(u32);
impl Noise {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        (self.0 >> 8) as f64 / (1u32 << 23) as f64 - 1.0
    }
}

/// A random bounded model (`|γ| < β`, `|ψ| < β − |γ|`, `|χ| < β − |γ| − |ψ|`, either sign of
/// `A`, the compensator's loop gain below 0.85) with an output range holding `k·u + δ` and
/// the state bound.
fn bouc_wen_model() -> impl Strategy<Value = (BoucWenParams, Scaling)> {
    (
        0.05f64..0.5,
        -1.0f64..1.0,
        0.002f64..0.08,
        -0.45f64..0.45,
        -0.7f64..0.7,
        -3.0f64..3.0,
        -0.7f64..0.7,
    )
        .prop_map(|(k, a, beta, g, psi, offset, chi)| {
            let gamma = g * beta;
            let mut p = BoucWenParams {
                k,
                offset,
                a: 0.0,
                beta,
                gamma,
                psi: psi * (beta - gamma.abs()),
                chi: 0.0,
            };
            p.chi = chi * (beta - gamma.abs() - p.psi.abs());
            p.a = a * 0.85 * k / (1.0 + p.max_factor() / p.min_factor());
            let h = p.a.abs() * (1.0 / p.min_factor()).max(150.0);
            let reach = k * 150.0 + offset.abs() + h + 1.0;
            (p, Scaling::new(0.0, 150.0, -reach, reach).unwrap())
        })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// Forward and inverse fixed point stay within 0.1 and 0.5 LSB16 of the `f64` reference
    /// for any bounded model: the forward model on a random walk with full-range jumps, the
    /// compensator on the reference model's output along the walk without the jumps (a jump
    /// in one sample makes `f = 1`, where its loop needs a gain below ½: the drive's slew
    /// limit rules that out on the board, see the module doc of `twinstack::models::bouc_wen`).
    #[test]
    fn fixed_point_tracks_the_f64_reference(
        (p, s) in bouc_wen_model(),
        steps in prop::collection::vec((-1.0f64..1.0, 0.0f64..1.0), 300..1500),
    ) {
        let fwd = BoucWen::new(&p, &s).unwrap();
        let inv = InverseBoucWen::new(&p, &s).unwrap();
        let mut fs = fwd.relaxed(q(-1.0));
        let mut is = fwd.relaxed(q(-1.0));
        let mut fr = reference::BoucWen::new(&p, &s, 0.0).unwrap();
        let mut ir = reference::InverseBoucWen::new(&p, &s, 0.0).unwrap();
        let mut truth = reference::BoucWen::new(&p, &s, 0.0).unwrap();
        let (mut u, mut walk) = (-1.0f64, -1.0f64);
        for (step, jump) in steps {
            walk = (walk + 0.005 * step).clamp(-1.0, 1.0);
            u = if jump > 0.98 { step.signum() } else { (u + 0.005 * step).clamp(-1.0, 1.0) };
            let y_ref = s.output_to_norm(fr.step(s.norm_to_input(u)));
            let y_fix = f(fwd.step(&mut fs, q(u)));
            prop_assert!((y_fix - y_ref).abs() <= 0.1 * LSB16, "forward {} vs {}", y_fix, y_ref);
            let y_d = truth.step(s.norm_to_input(walk));
            let u_ref = s.input_to_norm(ir.step(y_d));
            let u_fix = f(inv.step(&mut is, q(s.output_to_norm(y_d))));
            prop_assert!((u_fix - u_ref).abs() <= 0.5 * LSB16, "inverse {} vs {}", u_fix, u_ref);
        }
    }
}

/// What the compensator may miss its own model's output by, normalised: some tens of LSB of
/// Q2.30 (the step's f32 quotient and the roundings). An inverse that lagged one sample would
/// miss by that sample's change of the state, `A·Δu − f·h`.
const EXACT: f64 = 32.0 / (1u64 << 30) as f64;

/// The compensator's drive, fed to the forward model, gives the desired output on every
/// sample, on a smooth trajectory and on one with white noise of 1 % of the span over
/// 100 000 samples: the drive stays inside the range, the error within the rounding, and
/// neither drifts (no ratchet).
#[test]
fn compensation_lands_on_its_model_and_does_not_ratchet_on_noise() {
    // A < 0: the output's slope falls to 0.29 of k just after a reversal.
    let (p, s) = (
        BoucWenParams {
            a: -0.1,
            ..params()
        },
        scaling(),
    );
    let inv = InverseBoucWen::new(&p, &s).unwrap();
    let fwd = BoucWen::new(&p, &s).unwrap();
    let period = 2000;
    assert!(p.inverse_loop_gain() > 0.7, "a demanding model");
    for noise_peak in [0.0, 0.01 * 2.0] {
        let mut is = inv.model().relaxed(0);
        let mut plant = fwd.relaxed(0);
        let mut noise = Noise(17);
        let mut worst_error = 0.0f64;
        let mut mean_u = Vec::new();
        let mut sum_u = 0.0;
        let mut worst_drive = 0.0f64;
        for k in 0..100_000 {
            let phase = 2.0 * std::f64::consts::PI * k as f64 / period as f64;
            let y_d = 0.5 * phase.sin() + noise_peak * noise.next();
            let u = inv.step(&mut is, q(y_d));
            let y = f(fwd.step(&mut plant, u));
            assert_eq!(
                is, plant,
                "tick {k}: the compensator's observer is the model"
            );
            let u = f(u);
            worst_drive = worst_drive.max(u.abs());
            if k > 0 {
                worst_error = worst_error.max((y - y_d).abs());
            }
            sum_u += u;
            if (k + 1) % period == 0 {
                mean_u.push(sum_u / period as f64);
                sum_u = 0.0;
            }
        }
        assert!(
            worst_drive < 0.99,
            "noise {noise_peak}: drive reached {worst_drive}"
        );
        // On noise, steps of up to 2 % of the span, some just after a reversal where the slope
        // falls to 0.29 k: the Newton step's O((c·m)²) of such a step, below 1e-7 (a
        // three-hundredth of a 16-bit code). Smooth, the rounding alone.
        let bound = if noise_peak > 0.0 { 1e-7 } else { EXACT };
        assert!(
            worst_error <= bound,
            "noise {noise_peak}: missed its model by {worst_error}"
        );
        // No ratchet: the mean drive over a period is the same at the end as after the first.
        let drift = (mean_u[mean_u.len() - 1] - mean_u[1]).abs();
        assert!(
            drift < 0.002,
            "noise {noise_peak}: mean drive drifted by {drift}"
        );
    }
}

/// In the tick, open loop on a Bouc–Wen compensator and the same model as observer (run below
/// the tick, on its report: [`Observed`]): the observer's estimate follows the setpoint (the compensator shares the observer's state from
/// the start, and both see the same drive while the drive limits do not act).
#[test]
fn the_tick_runs_the_bouc_wen_compensator_and_observer() {
    let s = Settings {
        ranges: scaling(),
        compensator: Some(Model::BoucWen(params())),
        observer: Some(Model::BoucWen(params())),
        sensor: None,
        mode: Mode::OpenLoop,
        ..Settings::default()
    };
    let hw = Hardware::driver_board(50_000.0);
    let mut c = Observed::new(s.build(&hw).unwrap());
    let mut dac = RecordingDac::default();
    let start = c.controller.setpoint();
    let mut worst = 0.0f64;
    for k in 0..20_000 {
        let sp = f(start) + 0.3 * (k as f64 * 1e-3).sin();
        let r = c.tick(Some(q(sp)), &mut FixedAdc(None), &mut dac);
        if k > 100 {
            worst = worst.max((f(r.estimate) - sp).abs());
        }
    }
    assert!(worst < 4.0 * LSB16, "{:.2} LSB16", worst / LSB16);
}

/// A stage that follows a known asymmetric Bouc–Wen (ψ, χ ≠ 0), with a little sensor noise: 6 s
/// at 1 kHz of a 1 Hz sine with a decaying amplitude, from rest.
fn bouc_wen_record() -> (MeasuredData, BoucWenParams) {
    let truth = BoucWenParams {
        k: 0.15,
        offset: 0.5,
        a: 0.02,
        beta: 0.03,
        gamma: 0.004,
        psi: 0.008,
        chi: 0.004,
    };
    assert!(
        truth.inverse_loop_gain() < 0.8,
        "a model the compensator accepts"
    );
    let s = Scaling::new(-110.0, 110.0, -30.0, 30.0).unwrap();
    let t: Vec<f64> = (0..6000).map(|k| k as f64 * 1e-3).collect();
    let u: Vec<f64> = t
        .iter()
        .map(|&t| 100.0 * (1.0 - 0.05 * t) * (2.0 * std::f64::consts::PI * t).sin())
        .collect();
    let mut m = reference::BoucWen::new(&truth, &s, 0.0).unwrap();
    let mut noise = Noise(23);
    let x = u
        .iter()
        .map(|&v| m.step(v) + 0.005 * noise.next())
        .collect();
    let data = MeasuredData {
        path: PathBuf::from("bouc-wen.csv"),
        t,
        u: Some(u),
        x: Some(x),
    };
    (data, truth)
}

/// `identify --model bouc-wen` recovers a known asymmetric model from synthetic data and
/// predicts the held-out part better than the Duhem fit (which has no asymmetric term); the
/// ranking of `--model auto` picks it.
#[test]
fn identification_recovers_a_known_asymmetric_bouc_wen_and_beats_duhem() {
    let (data, truth) = bouc_wen_record();
    let (u, x) = (data.u.as_ref().unwrap(), data.x.as_ref().unwrap());
    let held = |kind| {
        let id = identify(&data, &IdentifyOptions::new(kind, 4.0)).unwrap();
        let predicted = id.model.predict(&data.t, u).unwrap();
        (id, score(x, &predicted, 4000..6000).unwrap())
    };
    let (bw, bw_score) = held(ModelKind::BoucWen);
    let (_, duhem_score) = held(ModelKind::Duhem);
    eprintln!(
        "Bouc-Wen {bw_score:?}\nDuhem    {duhem_score:?}\n{:?}",
        bw.notes
    );
    let Hysteresis::BoucWen(p) = bw.model.hysteresis else {
        panic!("a Bouc-Wen model")
    };
    assert!(
        bw_score.max_pct < 0.5 * duhem_score.max_pct,
        "{bw_score:?} vs {duhem_score:?}"
    );
    assert!(bw_score.rms_pct < 0.1, "{bw_score:?}");
    for (name, got, want) in [("k", p.k, truth.k), ("a", p.a, truth.a)] {
        assert!((got / want - 1.0).abs() < 0.1, "{name}: {got} vs {want}");
    }
    for (name, got, want) in [("psi", p.psi, truth.psi), ("chi", p.chi, truth.chi)] {
        assert!((got / want - 1.0).abs() < 0.3, "{name}: {got} vs {want}");
    }
    let auto = identify_auto(
        &data,
        &IdentifyOptions::new(ModelKind::Pi, 4.0).candidates(),
    )
    .unwrap();
    assert_eq!(
        auto.ranking[0].options.model,
        ModelKind::BoucWen,
        "{}",
        auto.reason
    );
}
