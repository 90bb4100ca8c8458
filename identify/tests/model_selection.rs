//! `identify --model auto` and the lag estimate, on data from known models.
//!
//! * the candidate that generated the data wins the ranking;
//! * the held-out part (after `fit_until`) is never looked at: garbage there changes nothing;
//! * a lag is estimated only where the data has one: noisy data without lag gets lag 0, a
//!   3-sample delay is found.

use std::path::PathBuf;
use twinstack::models::params::{DuhemParams, PiParams, Thresholds};
use twinstack::Scaling;
use twinstack_identify::identification::auto::{identify_auto, InverseBound};
use twinstack_identify::identification::{identify, IdentifyOptions, ModelKind};
use twinstack_identify::reference;
use twinstack_identify::stage_model::between;
use twinstack_link::measured_data::MeasuredData;

/// Deterministic Gaussian-ish noise (sum of 4 uniforms from an xorshift), unit variance.
struct Noise(u64);

impl Noise {
    fn next(&mut self) -> f64 {
        let mut s = 0.0;
        for _ in 0..4 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            s += (self.0 >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
        }
        s * 3f64.sqrt()
    }
}

/// 6 s at 1 kHz of a 1 Hz sine with a slowly decaying amplitude (minor loops), from rest.
fn drive() -> (Vec<f64>, Vec<f64>) {
    let t: Vec<f64> = (0..6000).map(|k| k as f64 * 1e-3).collect();
    let u = t
        .iter()
        .map(|&t| {
            let a = 100.0 * (1.0 - 0.05 * t);
            a * (2.0 * std::f64::consts::PI * t).sin()
        })
        .collect();
    (t, u)
}

fn record(t: Vec<f64>, u: Vec<f64>, x: Vec<f64>) -> MeasuredData {
    MeasuredData {
        path: PathBuf::from("synthetic.csv"),
        t,
        u: Some(u),
        x: Some(x),
    }
}

fn scaling() -> Scaling {
    Scaling::new(-110.0, 110.0, -30.0, 30.0).unwrap()
}

/// A P–I stage with `noise_rms` output noise, the reading delayed by `lag` samples.
fn pi_record(noise_rms: f64, lag: usize) -> MeasuredData {
    let (t, u) = drive();
    let thresholds = Thresholds::Uniform.generate(12, 100.0).unwrap();
    let weights: Vec<f64> = (0..12).map(|i| 0.1 / (1.0 + 0.4 * i as f64)).collect();
    let p = PiParams::new(0.0, 1.0, &thresholds, &weights).unwrap();
    let mut m = reference::PrandtlIshlinskii::new(&p, &scaling(), 0.0).unwrap();
    let clean: Vec<f64> = u.iter().map(|&v| m.step(v)).collect();
    let mut n = Noise(7);
    let x = (0..clean.len())
        .map(|k| clean[k.saturating_sub(lag)] + noise_rms * n.next())
        .collect();
    record(t, u, x)
}

/// [`pi_record`] read `lag + ½` samples late: each reading lies between two outputs (a drive
/// held for a sample, read at the end of its hold), interpolated as `identify` pairs them.
fn pi_record_half(noise_rms: f64, lag: usize) -> MeasuredData {
    let clean = pi_record(0.0, 0).x.unwrap();
    let at = |k: isize| clean[k.clamp(0, clean.len() as isize - 1) as usize];
    let mut n = Noise(7);
    let x = (0..clean.len() as isize)
        .map(|k| {
            let j = k - lag as isize;
            between(at(j - 2), at(j - 1), at(j), at(j + 1)) + noise_rms * n.next()
        })
        .collect();
    let (t, u) = drive();
    record(t, u, x)
}

fn duhem_record() -> MeasuredData {
    let (t, u) = drive();
    let p = DuhemParams {
        alpha: 0.03,
        beta: 0.2,
        gamma: 0.12,
        offset: 0.5,
    };
    let mut m = reference::Duhem::new(&p, &scaling(), 0.0, 0.5).unwrap();
    let mut n = Noise(11);
    let x = u.iter().map(|&v| m.step(v) + 0.005 * n.next()).collect();
    record(t, u, x)
}

fn candidates() -> Vec<IdentifyOptions> {
    IdentifyOptions::new(ModelKind::Pi, 4.0).candidates()
}

/// On data from a Duhem model, `auto` picks the Duhem class: Duhem, or Bouc–Wen, of which it
/// is the special case (`γ = ψ = 0`). Both predict the record equally; the pick is by the
/// compensator. The P–I family's compensators track the smooth trajectory worse than the
/// pick's: the hysteresis is not theirs.
#[test]
fn auto_picks_the_model_that_generated_the_data() {
    let auto = identify_auto(&duhem_record(), &candidates()).unwrap();
    for r in &auto.ranking {
        eprintln!("duhem data: {:<30} {}", r.label, r.summary());
    }
    let pick = &auto.ranking[0];
    assert!(
        matches!(pick.options.model, ModelKind::Duhem | ModelKind::BoucWen),
        "{}",
        auto.reason
    );
    let tracking = |r: &twinstack_identify::identification::auto::Ranked| {
        r.tracking
            .as_ref()
            .expect("every candidate is scored on the tracking")
            .max_pct
    };
    for r in &auto.ranking {
        if matches!(r.options.model, ModelKind::Pi | ModelKind::Gpi) {
            assert!(
                tracking(r) > 1.5 * tracking(pick),
                "{}: {} against the pick's {}",
                r.label,
                r.summary(),
                pick.summary()
            );
        }
    }

    let auto = identify_auto(&pi_record(0.005, 0), &candidates()).unwrap();
    for r in &auto.ranking {
        eprintln!("P-I data: {:<30} {}", r.label, r.summary());
    }
    assert_ne!(
        auto.ranking[0].options.model,
        ModelKind::Duhem,
        "{}",
        auto.reason
    );
    // Every candidate was fitted and ranked, best first: by the compensated error, those set
    // aside (their inverse ratchets) last.
    let keys: Vec<(bool, f64)> = auto
        .ranking
        .iter()
        .map(|r| {
            assert!(r.validation.admitted().is_some(), "{}", r.label);
            assert_eq!(
                r.set_aside.is_some(),
                r.bound == Some(InverseBound::Ratchets),
                "{}",
                r.label
            );
            (r.set_aside.is_some(), r.compensated().unwrap())
        })
        .collect();
    assert!(
        keys.windows(2)
            .all(|w| (w[0].0, w[0].1) <= (w[1].0, w[1].1)),
        "{keys:?}"
    );
    assert_eq!(auto.ranking.len(), candidates().len());
}

#[test]
fn auto_never_looks_past_fit_until() {
    let clean = duhem_record();
    let mut spoiled = clean.clone();
    let n_fit = spoiled.t.iter().take_while(|&&t| t < 4.0).count();
    if let Some(x) = spoiled.x.as_mut() {
        for (k, v) in x.iter_mut().enumerate().skip(n_fit) {
            *v = if k % 2 == 0 { 1e3 } else { -1e3 };
        }
    }
    let a = identify_auto(&clean, &candidates()).unwrap();
    let b = identify_auto(&spoiled, &candidates()).unwrap();
    let labels = |r: &twinstack_identify::identification::auto::AutoIdentification| {
        r.ranking
            .iter()
            .map(|c| (c.label.clone(), format!("{:?}", c.validation)))
            .collect::<Vec<_>>()
    };
    assert_eq!(labels(&a), labels(&b));
    assert_eq!(a.validation_from_s, b.validation_from_s);
    assert!(a.validation_from_s < 4.0);
}

#[test]
fn a_lag_is_estimated_only_where_the_data_has_one() {
    let o = IdentifyOptions::new(ModelKind::Pi, 4.0);
    // Sensor noise of 0.3 % of the span and no delay: no lag.
    let id = identify(&pi_record(0.1, 0), &o).unwrap();
    assert!(id.lag_estimated);
    assert_eq!(id.lag_samples, 0.0, "a lag invented on data without one");
    // A 3-sample delay is found.
    let id = identify(&pi_record(0.02, 3), &o).unwrap();
    assert_eq!(id.lag_samples, 3.0);
    // And half samples: a reading of a held drive's end, one and a half samples late.
    let id = identify(&pi_record_half(0.02, 1), &o).unwrap();
    assert_eq!(id.lag_samples, 1.5);
}

/// What `auto` returns is admitted as refitted on the whole window, not only as fitted on its
/// first part: the two fits can differ in size (a creep mode one gives no weight, the other
/// may). An `admit` that takes every fit on the first part and refuses every fit on the whole
/// window leaves nothing to pick.
#[test]
fn auto_checks_the_refit_on_the_whole_window_too() {
    use twinstack_identify::identification::auto::{identify_auto_admitting, Admission};
    use twinstack_identify::identification::IdentifyError;
    let data = duhem_record();
    let candidates = candidates();
    let fit_until = candidates[0].fit_until_s;
    let whole = data.t.iter().take_while(|&&t| t < fit_until).count();
    let admit = |_: &twinstack_identify::identification::IdentifyOptions,
                 id: &twinstack_identify::identification::Identification| {
        if id.held_out_from >= whole {
            Admission::Refused("refitted on the whole window".into())
        } else {
            Admission::Admitted
        }
    };
    match identify_auto_admitting(&data, &candidates, admit) {
        Err(IdentifyError::NoneAdmitted(why)) => {
            assert!(why.contains("refitted on the whole window"), "{why}")
        }
        other => panic!("{other:?}"),
    }
}
