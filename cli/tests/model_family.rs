//! The model family against the textbook P–I (17 uniform play operators, NNLS), the way a
//! user runs it: `identify` with its defaults (`--model auto`).
//!
//! * on both measured records, the held-out forward and inverse errors of what `auto` picks;
//! * on the lab stage (a simulated stage built from none of our models), open-loop tracking of
//!   a triangle, nested minor loops and a multisine with what `auto` picks.
//!
//! Each test holds the figure reached (see the book, results/identification.md and
//! results/lab-stage.md) and fails when the pick is replaced by the textbook P–I. `auto` picks
//! by the compensator: held out, the bipolar record's pick (Bouc–Wen with its output map +
//! creep) predicts within 0.88 % and inverts within 1.11 %, the micromanipulator's (the
//! generalised P–I) 1.49 % and 1.20 %; tracking on the lab stage is held within 1 %.
//! `stage_variants` holds `auto` on 21 other stages.

use hal_sim::plant::{LabStage, LabStageConfig};
use std::path::Path;
use twinstack_cli::tracking::{
    evaluate_methods, evaluate_methods_with_triangles, excite, Method, EXCITATION, FIT_UNTIL_S,
    SAMPLE_RATE_HZ,
};
use twinstack_identify::identification::auto::identify_auto;
use twinstack_identify::identification::score::score;
use twinstack_identify::identification::{identify, IdentifyOptions, ModelKind};
use twinstack_link::measured_data::{Columns, MeasuredData};

fn record(name: &str) -> MeasuredData {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../data")
        .join(name);
    MeasuredData::read(&path, Columns::TimeDriveOutput).unwrap()
}

/// Held-out figures (max %, of span) of a fit: forward (`predict` against the measured
/// reading) and inverse (`compensate` against the measured drive, the last `lag` samples, with
/// no later reading to aim at, left out).
fn figures(
    data: &MeasuredData,
    id: &twinstack_identify::identification::Identification,
) -> (f64, f64) {
    let (u, x) = (data.u.as_deref().unwrap(), data.x.as_deref().unwrap());
    let n = x.len();
    let predicted = id.model.predict(&data.t, u).unwrap();
    let forward = score(x, &predicted, id.held_out_from..n).unwrap();
    let drive = id.model.compensate_measured(&data.t, x).unwrap();
    let aimed = n - id.model.lag_samples(&data.t);
    let inverse = score(u, &drive, id.held_out_from..aimed).unwrap();
    (forward.max_pct, inverse.max_pct)
}

/// What the stage sees is the inverse: on both measured records the compensator of the model
/// `auto` picks beats the textbook P–I's on the held-out part, and its forward error stays
/// within 1.5 %. (Ranked by the forward error alone, auto picked models whose forward error
/// was lower — 0.83 % and 0.87 % — but whose compensators were not the best: on the
/// micromanipulator the generalised P–I + creep's inverse is 1.70 % on the validation part
/// against the generalised P–I's 0.97 %.)
#[test]
fn auto_beats_the_textbook_pi_on_both_measured_records() {
    for (name, fit_until) in [
        ("piezo-bipolar-150v-1hz.csv", 5.95),
        ("micromanipulator-unipolar-3v6-1hz.csv", 16.0),
    ] {
        let data = record(name);
        let base = IdentifyOptions::new(ModelKind::Pi, fit_until);
        let auto = identify_auto(&data, &base.candidates()).unwrap();
        let picked = auto.options.model_label();
        let (forward, inverse) = figures(&data, &auto.identification);
        let (p_forward, p_inverse) = figures(&data, &identify(&data, &base).unwrap());
        eprintln!(
            "{name}: auto picked {picked}: held-out forward {forward:.2} %, inverse {inverse:.2} %; textbook P-I {p_forward:.2} %, {p_inverse:.2} %"
        );
        assert!(forward <= 1.5, "{name}: {forward} % > 1.5 %");
        assert!(
            inverse < p_inverse && forward.max(inverse) < p_forward.max(p_inverse),
            "{name}: auto {forward} / {inverse} % against the textbook P-I's {p_forward} / {p_inverse} %"
        );
    }
}

/// An output map after the Bouc–Wen is fitted where the model's state no longer carries its
/// guessed start (after the drive has seen both extremes), so that it follows the stage's
/// curve, not the record's start: on the bipolar record, without creep, the model with its
/// map holds the held-out part as well as the model without it, forward (1.36 % both) and
/// inverse (1.42 % against 2.01 %). Fitted on every fit row, the map bent to the start-up
/// transient: its fit RMS fell 1.17 → 0.99 % of span and its held-out max rose to 2.02 %.
#[test]
fn an_output_map_fitted_after_the_bouc_wen_holds_the_held_out_part() {
    let data = record("piezo-bipolar-150v-1hz.csv");
    let plain = IdentifyOptions::new(ModelKind::BoucWen, 5.95);
    let mapped = IdentifyOptions {
        output_map: true,
        ..plain.clone()
    };
    let without = identify(&data, &plain).unwrap();
    let with = identify(&data, &mapped).unwrap();
    assert!(with.model.output_map.is_some(), "{:?}", with.notes);
    let (f0, i0) = figures(&data, &without);
    let (f1, i1) = figures(&data, &with);
    eprintln!("Bouc-Wen held out {f0:.2} / {i0:.2} %, with its map {f1:.2} / {i1:.2} %");
    assert!(
        f1 <= f0 + 0.05 && i1 <= i0,
        "with the map {f1} / {i1} %, without {f0} / {i0} %"
    );
}

/// The worst max over the three trajectories (% of span) of no compensation, `auto`'s pick
/// and the textbook P–I on the stage `config` builds, each identified as a user would.
fn none_auto_textbook(config: LabStageConfig, stage: &str) -> (f64, f64, f64) {
    let base = IdentifyOptions::new(ModelKind::Pi, twinstack_cli::tracking::FIT_UNTIL_S);
    let table = evaluate_methods(
        &config,
        &[Method::Auto(base.candidates()), Method::One(base.clone())],
    )
    .unwrap();
    let worst = |i: usize| {
        let row = &table.rows[i];
        assert!(row.error.is_none(), "{}: {:?}", row.method, row.error);
        assert_eq!(row.scores.len(), 3, "{}", row.method);
        row.worst_max_pct().unwrap()
    };
    // rows[0] is the uncompensated line.
    let (none, auto, pi) = (worst(0), worst(1), worst(2));
    eprintln!(
        "{stage}, worst max over the three trajectories: none {none:.2} %, {} {auto:.2} %, textbook P-I {pi:.2} %",
        table.rows[1].method
    );
    (none, auto, pi)
}

#[test]
fn auto_tracks_the_lab_stage_far_better_than_the_textbook_pi() {
    let (none, auto, pi) = none_auto_textbook(LabStageConfig::new(SAMPLE_RATE_HZ, 1), "lab stage");
    assert!(auto <= 1.0, "the goal: {auto} %");
    assert!(
        auto < 0.5 * pi,
        "auto {auto} % against the textbook P-I's {pi} %"
    );
    assert!(pi < none);
}

/// On the Bouc–Wen-class stage (outside the family: exponent 1.5, a rising branch that
/// saturates sooner, minor loops that are not congruent, a flexure that stiffens after it)
/// what `auto` picks tracks better than the textbook P–I and within 1 % (0.82 % measured);
/// among the candidates with creep (as `--creep` ranks them) it picks the family's Bouc–Wen
/// with its output map + creep, which tracks within 1 % (0.82 % measured; the Bouc–Wen +
/// creep without the map, 1.21 %: a Bouc–Wen's output is linear in its state, and the
/// flexure's curve after it is what the map takes). Its compensator tracks a single-ended stage only when it starts where
/// the stage rests, on its loop's ascending branch (`twinstack::models::Rest`): started
/// relaxed it tracked worse than the P–I (6.0 % against 2.9 %). Without the output map among
/// the candidates, the default ranking picked the Bouc–Wen without creep (2.10 %).
#[test]
fn auto_tracks_the_bouc_wen_class_stage_better_than_the_textbook_pi() {
    let config = LabStageConfig {
        hysteresis: hal_sim::plant::StageHysteresis::BoucWen,
        ..LabStageConfig::new(SAMPLE_RATE_HZ, 1)
    };
    let (none, auto, pi) = none_auto_textbook(config.clone(), "Bouc-Wen-class stage");
    assert!(auto < pi, "auto {auto} % against the textbook P-I's {pi} %");
    assert!(auto <= 1.0, "the goal: {auto} % (none {none} %)");
    let base = IdentifyOptions {
        creep: true,
        ..IdentifyOptions::new(ModelKind::Pi, twinstack_cli::tracking::FIT_UNTIL_S)
    };
    let table = evaluate_methods(&config, &[Method::Auto(base.candidates())]).unwrap();
    let row = &table.rows[1];
    assert!(row.error.is_none(), "{}: {:?}", row.method, row.error);
    let with_creep = row.worst_max_pct().unwrap();
    eprintln!("{}: worst max {with_creep:.2} %", row.method);
    assert!(row.method.contains("bouc-wen+map+creep"), "{}", row.method);
    assert!(with_creep <= 1.0, "the goal: {with_creep} %");
}

/// On a Bouc–Wen-class stage with `n = 1`, and nothing else in the way (no creep, a linear
/// flexure, no noise), the family's Bouc–Wen can be the stage's own hysteresis: its four rates
/// (rising and falling, from a positive and from a negative state: 2, 14, 4 and 2 per unit
/// input) are each a coefficient of its own (`χ` beside `ψ`), and its compensator refuses
/// only a model whose output's slope does bend back to zero (the stage's never bends back
/// beyond 0.45 of `k`). Identified as a user would, it tracks to its class's floor: 0.15 %
/// measured, held at 0.3 %. With `ψ` alone the four rates were tied and the former bound
/// held (1.04 %); with `χ` but the compensator's former bound `|A|·(1 + c_max/c_min)`, 2.4
/// for this stage, the fit could not reach it (0.63 %).
#[test]
fn the_family_s_bouc_wen_reaches_its_own_class_on_a_bouc_wen_class_stage() {
    let mut config = LabStageConfig {
        hysteresis: hal_sim::plant::StageHysteresis::BoucWen,
        creep_per_decade: 0.0,
        flexure_saturation_um: f64::INFINITY,
        noise_rms_nm: 0.0,
        sensor_lsb_nm: 0.0,
        ..LabStageConfig::new(SAMPLE_RATE_HZ, 1)
    };
    config.bouc_wen.exponent = 1.0;
    let base = IdentifyOptions::new(ModelKind::BoucWen, twinstack_cli::tracking::FIT_UNTIL_S);
    let table = evaluate_methods(&config, &[Method::One(base)]).unwrap();
    let row = &table.rows[1];
    assert!(row.error.is_none(), "{}: {:?}", row.method, row.error);
    let worst = row.worst_max_pct().unwrap();
    eprintln!("{}: worst max {worst:.2} %", row.method);
    assert!(worst <= 0.3, "the class's floor: {worst} %");
}

/// One calibration (2 s of 10 Hz) across the rates a user runs: what `auto` picks tracks
/// triangles of 1, 5 and 20 Hz within 1 % on the lab stage — the hysteresis and the creep
/// are the same slow or fast — and the error grows above that, where the stage's lightly
/// damped 3.5 kHz resonance, which no hysteresis model inverts, rings at each corner (held
/// as a figure in the book: results/lab-stage.md). With the preview, the resonance measured
/// on the stage as `tune` measures a board's, the fast triangles' error falls by a third at
/// least and the slow ones' stays within 1 %. A frequency the stage's rate cannot sample is
/// refused, naming it.
#[test]
fn one_calibration_tracks_slow_triangles_and_the_resonance_limits_fast_ones() {
    let config = LabStageConfig::new(SAMPLE_RATE_HZ, 1);
    let base = IdentifyOptions::new(ModelKind::Pi, twinstack_cli::tracking::FIT_UNTIL_S);
    let methods = [Method::Auto(base.candidates())];
    let table = evaluate_methods_with_triangles(
        &config,
        &methods,
        &[1.0, 5.0, 20.0, 200.0],
        None,
        true,
        &EXCITATION,
    )
    .unwrap();
    let resonance = table.resonance.expect("the preview's resonance");
    assert!(
        (resonance.frequency_hz / 3_500.0 - 1.0).abs() < 0.01
            && (resonance.zeta / 0.03 - 1.0).abs() < 0.15,
        "measured {resonance:?} on a stage of 3.5 kHz, ζ 0.03"
    );
    assert_eq!(
        &table.trajectories[3..],
        [
            "triangle 1 Hz",
            "triangle 5 Hz",
            "triangle 20 Hz",
            "triangle 200 Hz"
        ]
    );
    let auto = &table.rows[1];
    assert!(auto.error.is_none(), "{:?}", auto.error);
    let max: Vec<f64> = auto.scores[3..].iter().map(|s| s.max_pct).collect();
    eprintln!(
        "{}: triangles 1, 5, 20, 200 Hz: {max:.2?} % max",
        auto.method
    );
    for (hz, m) in [1, 5, 20].iter().zip(&max) {
        assert!(*m <= 1.0, "{hz} Hz: {m} %");
    }
    assert!(max[3] > max[2], "the resonance shows at 200 Hz: {max:?}");
    let previewed = &table.rows[2];
    assert_eq!(previewed.method, format!("{} + preview", auto.method));
    let shaped: Vec<f64> = previewed.scores[3..].iter().map(|s| s.max_pct).collect();
    eprintln!("{}: {shaped:.2?} % max", previewed.method);
    for (hz, m) in [1, 5, 20].iter().zip(&shaped) {
        assert!(*m <= 1.0, "{hz} Hz with the preview: {m} %");
    }
    assert!(
        shaped[3] < 0.67 * max[3],
        "200 Hz: {} % with the preview against {} % without",
        shaped[3],
        max[3]
    );
    let refused =
        evaluate_methods_with_triangles(&config, &methods, &[600.0], None, false, &EXCITATION)
            .unwrap_err();
    assert!(
        refused.to_string().contains("triangle 600 Hz") && refused.to_string().contains("500 Hz"),
        "{refused}"
    );
    // Too slow: refused before anything is allocated (four cycles of 1e-300 Hz used to ask
    // for more memory than there is).
    for hz in [1e-300, 0.05] {
        let refused =
            evaluate_methods_with_triangles(&config, &methods, &[hz], None, false, &EXCITATION)
                .unwrap_err();
        assert!(refused.to_string().contains("from 0.1 Hz"), "{refused}");
    }
}

/// The same stage identified from the same excitation recorded at 10 kHz and at 50 kHz gives
/// the same model: the creep's alternation with the hysteresis fit runs to its best iterate
/// at either rate. (It stopped on the first iterate whose fit RMS changed by less than 1 %:
/// at 50 kHz a plateau four iterates short of the best, held out 1.83 % against 1.20 % at
/// 10 kHz, the slowest creep mode's weight a fifth of the 10 kHz fit's.)
/// At the board's 50 kHz (the record, the identification and the tracking sampled at it),
/// one calibration with the preview tracks every triangle from 1 Hz to 200 Hz within 1 % on
/// the lab stage: the corner's share is a fifth of 10 kHz's and the sharpened preview leaves
/// an eighth of the slope's change over a sample there (the book's figure
/// `lab-stage-triangles-50khz` in results/lab-stage.md, which this test writes).
#[test]
fn at_the_board_s_rate_one_calibration_with_the_preview_tracks_1_to_200_hz_within_1_percent() {
    let config = LabStageConfig::new(50_000.0, 1);
    let base = IdentifyOptions::new(ModelKind::Pi, twinstack_cli::tracking::FIT_UNTIL_S);
    let methods = [Method::Auto(base.candidates())];
    let hz = [1.0, 5.0, 20.0, 50.0, 100.0, 200.0];
    let table =
        evaluate_methods_with_triangles(&config, &methods, &hz, None, true, &EXCITATION).unwrap();
    let previewed = &table.rows[2];
    assert!(
        previewed.method.ends_with(" + preview"),
        "{}",
        previewed.method
    );
    assert!(previewed.error.is_none(), "{:?}", previewed.error);
    let shaped: Vec<f64> = previewed.scores[3..].iter().map(|s| s.max_pct).collect();
    eprintln!("{}: {shaped:.2?} % max", previewed.method);
    assert_eq!(shaped.len(), hz.len());
    for (hz, m) in hz.iter().zip(&shaped) {
        assert!(*m <= 1.0, "{hz} Hz with the preview at 50 kHz: {m} %");
    }
    // The book's figure (`lab-stage-triangles-50khz`) is this table, as `twinstack lab-stage
    // --rate 50000 --model auto --triangles 1,5,20,50,100,200 --preview --json` prints it:
    // written here once every assertion held, read by `cargo xtask figures`, and not computed twice.
    let figure = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/figures");
    std::fs::create_dir_all(&figure).unwrap();
    let json = serde_json::to_string_pretty(&table).unwrap() + "\n";
    std::fs::write(figure.join("lab-stage-triangles-50khz.json"), json).unwrap();
}

#[test]
fn a_stage_recorded_at_two_rates_identifies_the_same_model() {
    let fit = |rate: f64| {
        let mut stage = LabStage::new(&LabStageConfig::new(rate, 1)).unwrap();
        let data = excite(&mut stage);
        let mut options = IdentifyOptions::new(ModelKind::Gpi, FIT_UNTIL_S);
        options.creep = true;
        let id = identify(&data, &options).unwrap();
        let (u, x) = (data.u.as_deref().unwrap(), data.x.as_deref().unwrap());
        let predicted = id.model.predict(&data.t, u).unwrap();
        let held_out = score(x, &predicted, id.held_out_from..x.len()).unwrap();
        let weights = id.model.creep.expect("a creep kept").weights;
        (held_out.max_pct, weights)
    };
    let (slow, slow_weights) = fit(10_000.0);
    let (fast, fast_weights) = fit(50_000.0);
    eprintln!("held out: {slow:.2} % at 10 kHz, {fast:.2} % at 50 kHz");
    eprintln!("creep weights: {slow_weights:.4?} at 10 kHz, {fast_weights:.4?} at 50 kHz");
    assert!(
        (slow - fast).abs() < 0.15,
        "held out {slow} % at 10 kHz, {fast} % at 50 kHz"
    );
    // The slowest mode is the one held out: what the last cycle extrapolates.
    let (a, b) = (slow_weights.last().unwrap(), fast_weights.last().unwrap());
    assert!(
        (a / b - 1.0).abs() < 0.2,
        "creep weights {slow_weights:?} at 10 kHz, {fast_weights:?} at 50 kHz"
    );
}

/// What `auto` picks where it must run on the board: at 50 kHz the board's tick budget admits
/// the generalised P–I + creep with its observer; at 100 kHz it admits it as the compensator
/// only (the creep's modes taking turns, one a tick, keep its inverse in the interrupt at one
/// cost whatever its modes). Both track the lab stage within the 1 % goal (held as a figure in
/// the book: results/lab-stage.md, "At the board's control rates"). Each row names what the
/// rate took away.
#[test]
fn at_the_boards_rates_auto_picks_what_the_board_runs() {
    use twinstack_identify::identification::run::BoardRate;
    let config = LabStageConfig::new(SAMPLE_RATE_HZ, 1);
    let base = IdentifyOptions::new(ModelKind::Pi, twinstack_cli::tracking::FIT_UNTIL_S);
    let methods = [Method::Auto(base.candidates())];
    let at = |hz: f64| {
        let table = evaluate_methods_with_triangles(
            &config,
            &methods,
            &[],
            Some(&BoardRate::sizing(hz, false)),
            false,
            &EXCITATION,
        )
        .unwrap();
        let (none, auto) = (&table.rows[0], &table.rows[1]);
        assert!(auto.error.is_none(), "{hz} Hz: {:?}", auto.error);
        let worst = |r: &twinstack_cli::tracking::TrackingRow| {
            r.scores.iter().map(|s| s.max_pct).fold(0.0, f64::max)
        };
        eprintln!(
            "board at {hz} Hz: {} worst max {:.2} %",
            auto.method,
            worst(auto)
        );
        (auto.method.clone(), worst(auto), worst(none))
    };
    let (picked, worst, none) = at(50_000.0);
    assert_eq!(picked, "auto: gpi+creep", "everything admitted at 50 kHz");
    assert!(worst <= 1.0, "the goal at 50 kHz: {worst} %");
    let (picked, worst, none_100) = at(100_000.0);
    assert_eq!(none_100, none, "the stage is the same");
    assert_eq!(
        picked, "auto: gpi+creep (no observer)",
        "what the budget admits at 100 kHz"
    );
    assert!(worst <= 1.0, "the goal at 100 kHz: {worst} %");
}
