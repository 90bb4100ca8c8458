//! The laboratory stage (`hal_sim::plant::lab_stage`): its physics does what its documentation
//! says (creep across decades, asymmetric loops, the noise asked for, the resonance), and the
//! tracking table on it (`twinstack_cli::tracking`), printed with `--nocapture`.

use hal_sim::plant::{LabStage, LabStageConfig, StageHysteresis};
use twinstack_cli::tracking::{
    evaluate, evaluate_variants, excite, print_variants, Method, StageVariant, VariantError,
    EXCITATION, FIT_UNTIL_S, SAMPLE_RATE_HZ,
};
use twinstack_identify::identification::score::score;
use twinstack_identify::identification::{identify, IdentifyOptions, ModelKind};

/// The default stage at `rate` without noise or sensor rounding.
fn quiet(rate: f64) -> LabStageConfig {
    LabStageConfig {
        noise_rms_nm: 0.0,
        sensor_lsb_nm: 0.0,
        ..LabStageConfig::new(rate, 1)
    }
}

#[test]
fn creep_after_a_step_keeps_growing_decade_after_decade() {
    let config = quiet(1000.0);
    let gamma = config.creep_per_decade;
    let mut stage = LabStage::new(&config).unwrap();
    stage.rest(30.0);
    let before = stage.position_um();
    // Sample times 1 ms, 10 ms, …, 100 s after a step to 90 V.
    // (From 10 ms: the resonance has rung down by then.)
    let marks = [10usize, 100, 1000, 10_000, 100_000];
    let mut at = Vec::new();
    for k in 1..=*marks.last().unwrap() {
        stage.step(90.0);
        if marks.contains(&k) {
            at.push(stage.position_um());
        }
    }
    let step = at[0] - before;
    println!(
        "step {step:.3} µm; position at 10 ms … 100 s: {:?}",
        at.iter().map(|x| format!("{x:.3}")).collect::<Vec<_>>()
    );
    for (decade, w) in at.windows(2).enumerate() {
        let per_decade = (w[1] - w[0]) / step;
        assert!(
            per_decade > 0.6 * gamma && per_decade < 1.6 * gamma,
            "decade {decade} (from {} ms): creep {:.4} of the step, expected about {gamma}",
            10f64.powi(decade as i32 + 1),
            per_decade
        );
    }
}

/// `(rising, falling)` branches of the second cycle of a quasi-static 0 → 150 → 0 V sweep,
/// sampled every 0.5 V: `rising[i]` at `u = 0.5 i`, `falling[i]` at `u = 150 − 0.5 i`.
fn branches(config: &LabStageConfig) -> (Vec<f64>, Vec<f64>) {
    let mut stage = LabStage::new(config).unwrap();
    let mut sweep = |from: f64, to: f64| -> Vec<f64> {
        (0..=300)
            .map(|i| {
                let u = from + (to - from) * i as f64 / 300.0;
                // Settle the resonance at each level.
                for _ in 0..40 {
                    stage.step(u);
                }
                stage.position_um()
            })
            .collect()
    };
    sweep(0.0, 150.0);
    sweep(150.0, 0.0);
    (sweep(0.0, 150.0), sweep(150.0, 0.0))
}

/// Largest difference, % of the loop's span, between the rise from the bottom and the fall
/// from the top by the same drive change: 0 for a point-symmetric loop (any P–I's).
fn asymmetry_pct(rising: &[f64], falling: &[f64]) -> f64 {
    let span = rising.last().unwrap() - rising[0];
    rising
        .iter()
        .zip(falling)
        .map(|(r, f)| ((r - rising[0]) - (falling[0] - f)).abs())
        .fold(0.0, f64::max)
        / span
        * 100.0
}

#[test]
fn the_loop_is_asymmetric_and_its_branches_saturate_differently() {
    // The hysteresis alone: no creep, a linear flexure.
    let mut config = quiet(SAMPLE_RATE_HZ);
    config.creep_per_decade = 0.0;
    config.flexure_saturation_um = f64::INFINITY;
    let (rising, falling) = branches(&config);
    let asymmetry = asymmetry_pct(&rising, &falling);
    let span = rising.last().unwrap() - rising[0];
    let n = rising.len() - 1;
    let width = (0..=n)
        .map(|i| falling[n - i] - rising[i])
        .fold(0.0, f64::max)
        / span
        * 100.0;
    println!("loop width {width:.2} % of span {span:.2} µm");
    assert!(width > 5.0 && width < 25.0, "{width} %");
    // Slopes over the last 5 % of each branch (15 V): rising into the top, falling into the
    // bottom. Equal for a point-symmetric loop.
    let top = (rising[n] - rising[n - 30]) / 15.0;
    let bottom = (falling[n - 30] - falling[n]) / 15.0;
    println!(
        "asymmetry {asymmetry:.2} % of span; end slopes: rising at the top {top:.4} µm/V, falling at the bottom {bottom:.4} µm/V"
    );
    assert!(asymmetry > 2.0, "{asymmetry} %");
    assert!(bottom > 1.3 * top, "{bottom} vs {top}");

    // Control: with equal saturation at both ends the density is point-symmetric and so is
    // the loop (the measure sees nothing but rounding).
    config.preisach.bottom_saturation = config.preisach.top_saturation;
    let (rising, falling) = branches(&config);
    let control = asymmetry_pct(&rising, &falling);
    assert!(control < 0.05, "symmetric density: {control} %");
}

#[test]
fn the_sensor_noise_has_the_rms_asked_for_and_follows_the_seed() {
    let config = LabStageConfig::new(SAMPLE_RATE_HZ, 42);
    let mut stage = LabStage::new(&config).unwrap();
    stage.rest(75.0);
    let x: Vec<f64> = (0..20_000).map(|_| stage.step(75.0)).collect();
    let mean = x.iter().sum::<f64>() / x.len() as f64;
    let rms_nm = 1e3 * (x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / x.len() as f64).sqrt();
    let lsb = config.sensor_lsb_nm;
    let expected = (config.noise_rms_nm.powi(2) + lsb * lsb / 12.0).sqrt();
    println!("noise {rms_nm:.3} nm RMS, expected {expected:.3} nm (2 nm + 2 nm rounding)");
    assert!((rms_nm / expected - 1.0).abs() < 0.05, "{rms_nm} nm");
    assert!(x
        .iter()
        .all(|v| ((v / (lsb * 1e-3)).round() * lsb * 1e-3 - v).abs() < 1e-9));

    // The same seed gives the same record bit for bit, after a rest too; another does not.
    let record =
        |seed: u64| excite(&mut LabStage::new(&LabStageConfig::new(2000.0, seed)).unwrap());
    let a = record(3);
    assert_eq!(a, record(3));
    assert_ne!(a.x, record(4).x);
}

/// Least-squares fit of `x_{k+1} = c1 x_k + c2 x_{k−1} + c0` (exact for a sampled
/// second-order mode with a held input); returns `(f_n Hz, ζ)`.
fn second_order(x: &[f64], dt: f64) -> (f64, f64) {
    let mut a = [[0.0f64; 3]; 3];
    let mut b = [0.0f64; 3];
    for k in 1..x.len() - 1 {
        let row = [x[k], x[k - 1], 1.0];
        for i in 0..3 {
            for j in 0..3 {
                a[i][j] += row[i] * row[j];
            }
            b[i] += row[i] * x[k + 1];
        }
    }
    // Cramer's rule on the 3×3 normal equations.
    let det = |m: [[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(a);
    let c: Vec<f64> = (0..3)
        .map(|col| {
            let mut m = a;
            for r in 0..3 {
                m[r][col] = b[r];
            }
            det(m) / d
        })
        .collect();
    let r = (-c[1]).sqrt();
    let theta = (c[0] / (2.0 * r)).acos();
    let (sigma, omega_d) = (-r.ln() / dt, theta / dt);
    let omega_n = (sigma * sigma + omega_d * omega_d).sqrt();
    (omega_n / std::f64::consts::TAU, sigma / omega_n)
}

#[test]
fn a_step_rings_at_the_resonance_with_its_damping() {
    let rate = 200_000.0;
    let mut config = quiet(rate);
    config.creep_per_decade = 0.0;
    let mut stage = LabStage::new(&config).unwrap();
    stage.rest(50.0);
    // 3 ms of ringing after a 2 V step.
    let x: Vec<f64> = (0..600)
        .map(|_| {
            stage.step(52.0);
            stage.position_um()
        })
        .collect();
    let (f_n, zeta) = second_order(&x, 1.0 / rate);
    println!("ringing: f_n {f_n:.1} Hz, ζ {zeta:.4}");
    assert!((f_n / config.resonance_hz - 1.0).abs() < 0.01, "{f_n} Hz");
    assert!((zeta / config.damping_ratio - 1.0).abs() < 0.02, "ζ {zeta}");
    let overshoot = x.iter().copied().fold(f64::MIN, f64::max) - x.last().unwrap();
    assert!(
        overshoot > 0.5 * (x.last().unwrap() - x[0]),
        "lightly damped: it overshoots"
    );
}

#[test]
fn bad_configurations_are_refused_naming_the_field() {
    let base = LabStageConfig::new(SAMPLE_RATE_HZ, 1);
    type Spoil = fn(&mut LabStageConfig);
    let cases: [(&str, Spoil); 10] = [
        ("sample_period_s", |c| c.sample_period_s = f64::NAN),
        // A creep span of countless modes (it used to overflow their count).
        ("creep_fastest_s", |c| c.creep_fastest_s = 1e-310),
        ("creep_slowest_s", |c| c.creep_slowest_s = 1e308),
        ("creep_slowest_s", |c| {
            c.creep_slowest_s = 2e12 * c.creep_fastest_s
        }),
        ("preisach.levels", |c| c.preisach.levels = 1),
        ("preisach.top_saturation", |c| {
            c.preisach.top_saturation = 1.0
        }),
        ("creep_slowest_s", |c| c.creep_slowest_s = 1e-6),
        ("noise_rms_nm", |c| c.noise_rms_nm = -1.0),
        // γ > β: on a reversal the state would run away instead of relaxing.
        ("bouc_wen.gamma", |c| {
            c.bouc_wen.gamma = c.bouc_wen.beta + 1.0
        }),
        ("bouc_wen.exponent", |c| c.bouc_wen.exponent = 0.5),
    ];
    for (field, spoil) in cases {
        let mut c = base.clone();
        spoil(&mut c);
        let e = LabStage::new(&c).unwrap_err();
        assert_eq!(e.field, field);
        assert!(e.to_string().contains(field), "{e}");
    }
}

#[test]
fn tracking_table_compensated_pi_beats_no_compensation_on_every_trajectory() {
    let config = LabStageConfig::new(SAMPLE_RATE_HZ, 1);
    let options = [
        IdentifyOptions::new(ModelKind::Pi, FIT_UNTIL_S),
        IdentifyOptions::new(ModelKind::Duhem, FIT_UNTIL_S),
    ];
    let table = evaluate(&config, &options).unwrap();
    table.print(&mut std::io::stdout()).unwrap();
    let none = table.row("none").unwrap();
    let pi = table.row("pi").unwrap();
    assert!(pi.error.is_none(), "{:?}", pi.error);
    assert_eq!(none.scores.len(), 3);
    for (k, name) in table.trajectories.iter().enumerate() {
        let (p, n) = (pi.scores[k], none.scores[k]);
        assert!(
            p.max_pct < n.max_pct && p.rms_pct < n.rms_pct,
            "{name}: P–I {p:?} against none {n:?}"
        );
    }
    assert!(table.row("duhem").is_some());

    // The figures are a function of the seed: the same evaluation again gives the same rows.
    let again = evaluate(&config, &options[..1]).unwrap();
    assert_eq!(again.rows[..], table.rows[..2]);
}

/// The stage variants are excited with the excitation asked for: with a sweep up to the
/// fastest motion, each variant's table says so and its fit window is the swept
/// excitation's; one the stage's rate does not resolve is refused before any stage runs,
/// naming the limit.
#[test]
fn the_variants_are_identified_from_the_excitation_asked_for() {
    let rate = 2_000.0;
    let base = LabStageConfig::new(rate, 1);
    let variants: [StageVariant; 2] = [
        ("default", &[]),
        (
            "linear flexure",
            &[("flexure_saturation_um", f64::INFINITY)],
        ),
    ];
    let swept = EXCITATION.reaching(50.0);
    let method = [Method::One(IdentifyOptions::new(
        ModelKind::Pi,
        swept.held_out_from_s(),
    ))];
    let tables = evaluate_variants(&base, &variants, &method, None, &swept).unwrap();
    assert_eq!(tables.len(), 2);
    for v in &tables {
        assert_eq!(v.table.fastest_hz, Some(50.0), "{}", v.variant);
        assert_eq!(v.table.excitation_s, swept.duration_s(), "{}", v.variant);
        assert!(v.table.excitation_s > EXCITATION.duration_s());
        let pi = v.table.row("pi").unwrap();
        assert!(pi.error.is_none(), "{}: {:?}", v.variant, pi.error);
    }
    let mut text = Vec::new();
    print_variants(&tables, &mut text).unwrap();
    let text = String::from_utf8(text).unwrap();
    assert!(text.contains("sweep up to 50 Hz"), "{text}");

    // 200 Hz at 2 kHz is 10 samples a cycle: refused, naming the limit.
    let e = evaluate_variants(&base, &variants, &method, None, &EXCITATION.reaching(200.0))
        .unwrap_err();
    assert!(matches!(e, VariantError::Excitation(_)), "{e}");
    assert!(e.to_string().contains("at most 100 Hz"), "{e}");

    // The CLI takes `--fastest-hz` with `--variants` and refuses it the same way.
    let bad = std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args([
            "lab-stage",
            "--variants",
            "--rate",
            "2000",
            "--fastest-hz",
            "200",
        ])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(
        err.contains("200 Hz") && err.contains("at most 100 Hz"),
        "{err}"
    );
    assert!(bad.stdout.is_empty(), "nothing printed");
}

/// The Bouc–Wen-class stage (`--hysteresis bouc-wen`): a P–I's and a generalised P–I's
/// compensators, identified from the same excitation, at least halve no compensation's error
/// on every trajectory.
#[test]
fn on_the_bouc_wen_class_stage_compensation_halves_the_error() {
    let config = LabStageConfig {
        hysteresis: StageHysteresis::BoucWen,
        ..LabStageConfig::new(SAMPLE_RATE_HZ, 1)
    };
    let options = [
        IdentifyOptions::new(ModelKind::Pi, FIT_UNTIL_S),
        IdentifyOptions::new(ModelKind::Gpi, FIT_UNTIL_S),
    ];
    let table = evaluate(&config, &options).unwrap();
    table.print(&mut std::io::stdout()).unwrap();
    let none = table.row("none").unwrap();
    for name in ["pi", "gpi"] {
        let row = table.row(name).unwrap();
        assert!(row.error.is_none(), "{name}: {:?}", row.error);
        for (k, trajectory) in table.trajectories.iter().enumerate() {
            let (m, n) = (row.scores[k], none.scores[k]);
            assert!(
                m.max_pct < 0.5 * n.max_pct,
                "{name}, {trajectory}: {m:?} against none {n:?}"
            );
        }
    }
}

/// Duhem and Bouc–Wen are not this stage's physics, but a model of their class describes its
/// loops to a few % of span: the fits on the excitation must be models that simulate bounded
/// and close to the record, not the equation-error fit's runaway (`β = 1.3e5`, RMS 10⁶ % of
/// span, where the constrained refit pinned `α` at zero).
#[test]
fn duhem_and_bouc_wen_fits_on_the_excitation_simulate_within_a_few_percent() {
    let mut stage = LabStage::new(&LabStageConfig::new(SAMPLE_RATE_HZ, 1)).unwrap();
    let data = excite(&mut stage);
    let n_fit = data.t.iter().take_while(|&&t| t < FIT_UNTIL_S).count();
    let (u, x) = (data.u.as_ref().unwrap(), data.x.as_ref().unwrap());
    for kind in [ModelKind::Duhem, ModelKind::BoucWen] {
        let fit = identify(&data, &IdentifyOptions::new(kind, FIT_UNTIL_S))
            .unwrap_or_else(|e| panic!("{kind:?}: {e}"));
        let predicted = fit.model.predict(&data.t[..n_fit], &u[..n_fit]).unwrap();
        assert!(predicted.iter().all(|v| v.is_finite()), "{kind:?}");
        let first = fit.motion.first_fitted;
        let e = score(&x[..n_fit], &predicted, first..n_fit).unwrap();
        println!("{kind:?}: {e:?}; {:?}", fit.notes);
        assert!(e.rms_pct < 4.0 && e.max_pct < 15.0, "{kind:?}: {e:?}");
    }
}

#[test]
fn the_cli_prints_the_table_as_json_and_refuses_bad_flags() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("excitation.csv");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args([
            "lab-stage",
            "--model",
            "pi",
            "--seed",
            "5",
            "--rate",
            "2000",
            "--json",
        ])
        .arg("--write-excitation")
        .arg(&csv)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let table: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(table["seed"], 5);
    let rows = table["rows"].as_array().unwrap();
    let methods: Vec<&str> = rows.iter().map(|r| r["method"].as_str().unwrap()).collect();
    assert_eq!(methods, ["none", "pi"]);
    assert_eq!(rows[1]["scores"].as_array().unwrap().len(), 3);
    let text = std::fs::read_to_string(&csv).unwrap();
    assert!(text.starts_with("t,u,x\n"));
    assert_eq!(text.lines().count(), 1 + 4000, "2 s at 2 kHz");

    let bad = std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args(["lab-stage", "--fit-until", "3"])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--fit-until"));
    // A control rate the board does not run, or not a number: refused naming the flag.
    for rate in ["5000", "200000", "NaN"] {
        let bad = std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
            .args(["lab-stage", "--model", "pi", "--tick-rate", rate])
            .output()
            .unwrap();
        assert!(!bad.status.success(), "{rate}");
        let err = String::from_utf8_lossy(&bad.stderr);
        assert!(err.contains("--tick-rate"), "{rate}: {err}");
        assert!(bad.stdout.is_empty(), "{rate}: nothing printed");
    }

    // A field of the hysteresis not chosen: refused naming it and the one chosen.
    for (hysteresis, set) in [
        ("bouc-wen", "preisach.width=0.3"),
        ("preisach", "bouc_wen.alpha=0.2"),
    ] {
        let bad = std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
            .args(["lab-stage", "--model", "pi", "--hysteresis", hysteresis])
            .args(["--set", set])
            .output()
            .unwrap();
        assert!(!bad.status.success(), "{set}");
        let err = String::from_utf8_lossy(&bad.stderr);
        let field = set.split('=').next().unwrap();
        assert!(
            err.contains(field) && err.contains(hysteresis),
            "{set}: {err}"
        );
        assert!(bad.stdout.is_empty(), "{set}: nothing printed");
    }

    // `--set`: an unknown field, a value out of range and a count that is not whole are
    // refused naming the field, before anything runs.
    for (set, names) in [
        ("stiffness=3", "stiffness"),
        ("preisach.width=-1", "preisach.width"),
        ("preisach.levels=3.5", "preisach.levels"),
        ("resonance_hz=fast", "fast"),
    ] {
        let bad = std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
            .args(["lab-stage", "--model", "pi", "--set", set])
            .output()
            .unwrap();
        assert_eq!(
            bad.status.code(),
            Some(if set.starts_with("preisach") { 1 } else { 2 }),
            "{set}"
        );
        let err = String::from_utf8_lossy(&bad.stderr);
        assert!(err.contains(names), "{set}: {err}");
        assert!(bad.stdout.is_empty(), "{set}: nothing printed");
    }
}

/// `SETTABLE_FIELDS` (what `--set` offers) and `LabStageConfig::set` (what it applies) name the
/// same fields: every listed field is taken, and one not listed is refused.
#[test]
fn every_settable_field_is_set() {
    for field in hal_sim::plant::SETTABLE_FIELDS {
        let mut c = LabStageConfig::new(SAMPLE_RATE_HZ, 1);
        c.set(field, 7.0).unwrap_or_else(|e| panic!("{field}: {e}"));
        assert_ne!(
            c,
            LabStageConfig::new(SAMPLE_RATE_HZ, 1),
            "{field}: changed nothing"
        );
    }
    assert!(LabStageConfig::new(SAMPLE_RATE_HZ, 1)
        .set("sample_period_s", 1.0)
        .is_err());
}
