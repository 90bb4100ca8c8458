//! `twinstack tune`: the measured response and its fit, the design's margins
//! on the true plant, the step's ringing and the bandwidth at 50 and 100 kHz, the refusal of
//! an unstable gain set, a second stage, the load, and the command over the link (simulated
//! and virtual boards).

use hal_sim::plant::{true_plant, Configuration, StageParams};
use hal_sim::sim_device::{SimDevice, SimDeviceConfig};
use std::ops::ControlFlow;
use std::process::{Command, Output};
use twinstack::control::feedback::FeedbackSettings;
use twinstack::protocol::messages::{Mode, StatusReport};
use twinstack_cli::closed_loop::{self, ClosedLoopOptions};
use twinstack_identify::tune::design::{check, Goals, Refused};
use twinstack_identify::tune::{tune, SweepEvent, TuneError, TuneOptions, TuneReport};
use twinstack_link::Client;

#[path = "support/virtual_board_process.rs"]
mod virtual_board_process;

/// The simulated board (the paper's stage, or `stage`) at `rate`, through the protocol client.
fn board(rate: f64, stage: Option<StageParams>) -> Client<SimDevice> {
    let mut config = SimDeviceConfig::paper();
    config.board.plant.dt = 1.0 / rate;
    if let Some(s) = stage {
        config.board.plant.stage = s;
    }
    Client::new(SimDevice::new(config).unwrap())
}

/// A `progress` that lets the sweep run to its end.
fn run_on(_: SweepEvent<'_>) -> ControlFlow<()> {
    ControlFlow::Continue(())
}

fn tuned(rate: f64, stage: Option<StageParams>) -> TuneReport {
    tune(&mut board(rate, stage), &TuneOptions::default(), run_on).unwrap()
}

/// The simulated device's ranges: 0…140 V on the left stack (70 V half span) onto ±45 µm.
const SPANS: (f64, f64) = (70.0, 45.0);

/// A second stage: a stage mass 1.8 times the paper's (resonance about 16.5 kHz, less damped
/// relative to its frequency).
fn heavier_stage() -> StageParams {
    let mut s = StageParams::paper();
    s.stage_mass *= 1.8;
    s
}

fn resonance_of(stage: &StageParams) -> (f64, f64) {
    let s = stage.second_order(Configuration::Differential);
    (s.omega_n / (2.0 * std::f64::consts::PI), s.zeta)
}

/// The fit recovers the simulated stage's resonance within 0.5 % and its damping within 10 %,
/// with the tick's delay (one tick after the zero-order hold), on both stages and both rates.
#[test]
fn the_fit_recovers_the_resonance_and_damping_of_the_simulated_stages() {
    for (stage, rates) in [
        (StageParams::paper(), &[50_000.0, 100_000.0][..]),
        (heavier_stage(), &[50_000.0][..]),
    ] {
        let (f_true, zeta_true) = resonance_of(&stage);
        for &rate in rates {
            let r = tuned(rate, Some(stage));
            let p = &r.fit.plant;
            assert!(
                (p.resonance_hz / f_true - 1.0).abs() < 0.005,
                "{rate}: {} Hz vs {f_true} Hz",
                p.resonance_hz
            );
            assert!(
                (p.zeta / zeta_true - 1.0).abs() < 0.10,
                "{rate}: ζ {} vs {zeta_true}",
                p.zeta
            );
            assert_eq!(p.delay, 1, "{rate}");
            assert!(r.fit.rms_db < 0.5 && r.fit.rms_deg < 3.0, "{:?}", r.fit);
        }
    }
    // The second stage is another stage: its resonance is well away from the first's.
    assert!(resonance_of(&heavier_stage()).0 < 0.8 * resonance_of(&StageParams::paper()).0);
}

/// The gains chosen on the fit meet the margins on the TRUE plant (the stage's mechanics, with
/// the hysteresis-free gain, which is above the small-signal gain the sweep measures through
/// the hysteresis), and on the fit.
#[test]
fn the_tuned_gains_meet_the_margins_on_the_true_plant() {
    for (stage, rates) in [
        (StageParams::paper(), &[50_000.0, 100_000.0][..]),
        (heavier_stage(), &[50_000.0][..]),
    ] {
        for &rate in rates {
            let r = tuned(rate, Some(stage));
            let goals = Goals::at(rate);
            let truth = true_plant(&stage, SPANS.0, SPANS.1, rate);
            assert!(
                truth.gain > r.fit.plant.gain,
                "the hysteresis lowers the gain"
            );
            let f = check(&truth, &r.design.settings, &goals)
                .unwrap_or_else(|e| panic!("{rate}: {:?} on the true plant: {e}", r.design));
            assert!(
                f.phase_margin_deg >= 45.0 && f.gain_margin_db >= 6.0,
                "{f:?}"
            );
            let on_fit = &r.design.figures;
            assert!(
                on_fit.phase_margin_deg >= 45.0 && on_fit.gain_margin_db >= 6.0,
                "{on_fit:?}"
            );
        }
    }
}

/// The tuning's goals on the simulated stage (the closed-loop study's board: external
/// converters, hysteresis, sensor and amplifier noise, slew limit): after tuning, a 30 → 70 %
/// step rings at most 1 % of the step 1–3 ms after it, at 50 and at 100 kHz, where the study's
/// gains without the notch ring at the correction limit at 100 kHz; and the closed-loop
/// bandwidth is at least 2 kHz, on the fit and on the true plant.
#[test]
fn after_tuning_the_step_rings_below_1_percent_and_the_bandwidth_exceeds_2_khz() {
    let options = ClosedLoopOptions {
        out_dir: None,
        ..ClosedLoopOptions::default()
    };
    for rate in [50_000.0, 100_000.0] {
        let r = tuned(rate, None);
        let model = closed_loop::identify_model(rate, &options).unwrap();
        // Gains are per normalised unit: from the tuned board's spans to the study model's.
        let s = model.scaling;
        let k = (s.input_half_span() / s.output_half_span()) / (SPANS.0 / SPANS.1);
        let feedback = FeedbackSettings {
            kp: r.design.settings.kp / k,
            ki: r.design.settings.ki / k,
            ..r.design.settings
        };
        let tuned_step = closed_loop::step_with(rate, &options, &model, &feedback).unwrap();
        assert!(
            tuned_step.ringing_pct <= 1.0,
            "{rate}: ringing {} % with {feedback:?}",
            tuned_step.ringing_pct
        );
        let truth = true_plant(&StageParams::paper(), SPANS.0, SPANS.1, rate);
        let on_truth = check(&truth, &r.design.settings, &Goals::at(rate)).unwrap();
        for f in [&r.design.figures, &on_truth] {
            assert!(f.closed_loop_bandwidth_hz >= 2000.0, "{rate}: {f:?}");
        }
    }
    // Today's gains without the notch, at 100 kHz, for contrast: unstable.
    let model = closed_loop::identify_model(100_000.0, &options).unwrap();
    let study = closed_loop::step(100_000.0, &options, &model, false).unwrap();
    assert!(study.ringing_pct > 50.0, "{}", study.ringing_pct);
}

/// A gain set the fitted model says is unstable is refused (the closed-loop study's gains
/// without the notch at 100 kHz), and nothing is loaded.
#[test]
fn an_unstable_gain_set_is_refused_and_not_loaded() {
    let mut client = board(100_000.0, None);
    let before = client.read_params().unwrap();
    let options = TuneOptions {
        check: Some(FeedbackSettings::pi(0.1, 20_000.0, 0.25)),
        load: true,
        ..TuneOptions::default()
    };
    match tune(&mut client, &options, run_on) {
        Err(TuneError::Refused(Refused::Unstable { radius, .. })) => assert!(radius > 1.0),
        other => panic!("{:?}", other.map(|r| r.design)),
    }
    assert_eq!(client.read_params().unwrap(), before);
    // The same gains with the study's notch are stable: the check is not a blanket refusal.
    let options = TuneOptions {
        check: Some(closed_loop::feedback_settings(100_000.0, true)),
        ..TuneOptions::default()
    };
    let r = tune(&mut client, &options, run_on);
    assert!(
        !matches!(r, Err(TuneError::Refused(Refused::Unstable { .. }))),
        "{:?}",
        r.map(|r| r.design)
    );
}

/// `load` puts the tuned feedback on the board through the normal settings path, its other
/// settings kept, and the board's mode restored.
#[test]
fn load_puts_the_tuned_feedback_on_the_board() {
    let mut client = board(50_000.0, None);
    let before = client.read_params().unwrap();
    let mode = client.status().unwrap().mode();
    let options = TuneOptions {
        load: true,
        ..TuneOptions::default()
    };
    let r = tune(&mut client, &options, run_on).unwrap();
    assert!(r.loaded);
    let after = client.read_params().unwrap();
    assert_eq!(after.feedback, Some(r.design.settings));
    assert_eq!(after.ranges, before.ranges);
    assert_eq!(after.compensator, before.compensator);
    assert_eq!(client.status().unwrap().mode(), mode);
}

/// A sweep its `progress` stops — after the 2nd point, or while it waits on the board for the
/// 3rd point's capture — ends with `Stopped` there, even with `load`: the board's mode is the
/// one before (closed loop), its generator stopped, its settings unchanged, and the board
/// takes the next tune.
#[test]
fn a_stopped_sweep_leaves_the_board_as_it_was_and_loads_nothing() {
    let mut client = board(50_000.0, None);
    client.set_mode(Mode::ClosedLoop).unwrap();
    let before = client.read_params().unwrap();
    let options = TuneOptions {
        load: true,
        ..TuneOptions::default()
    };
    for stop_while_waiting in [false, true] {
        let (mut points, mut waits) = (Vec::new(), 0);
        let r = tune(&mut client, &options, |event| {
            match event {
                SweepEvent::Point(p) => points.push(p.frequency_hz),
                SweepEvent::Waiting { .. } => waits += 1,
            }
            let stop = match (stop_while_waiting, event) {
                (false, SweepEvent::Point(_)) => points.len() == 2,
                (true, SweepEvent::Waiting { .. }) => points.len() == 2,
                _ => false,
            };
            if stop {
                ControlFlow::Break(())
            } else {
                ControlFlow::Continue(())
            }
        });
        match r {
            Err(e @ TuneError::Stopped { measured: 2, .. }) => {
                let message = e.to_string();
                assert!(
                    message.contains("stopped") && message.contains("nothing was loaded"),
                    "{message}"
                );
            }
            other => panic!(
                "stop while waiting {stop_while_waiting}: {:?}",
                other.map(|r| r.points.len())
            ),
        }
        assert_eq!(points.len(), 2, "no point measured after the stop");
        assert!(waits > 0, "the sweep waits on the board for each capture");
        let status = client.status().unwrap();
        assert_eq!(status.mode(), Mode::ClosedLoop, "{stop_while_waiting}");
        assert!(!status.has(StatusReport::WAVEFORM), "{stop_while_waiting}");
        assert_eq!(client.read_params().unwrap(), before, "nothing was loaded");
    }
    // The board takes the next tune, which loads.
    let r = tune(&mut client, &options, run_on).unwrap();
    assert!(r.loaded);
    assert_eq!(
        client.read_params().unwrap().feedback,
        Some(r.design.settings)
    );
    assert_eq!(client.status().unwrap().mode(), Mode::ClosedLoop);
}

fn twinstack_bin(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .env_remove("TWINSTACK_PORT")
        .args(args)
        .output()
        .expect("twinstack runs")
}

fn json(o: Output) -> serde_json::Value {
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        o.status.success(),
        "exit {:?}\n{out}{}",
        o.status.code(),
        String::from_utf8_lossy(&o.stderr)
    );
    assert_eq!(out.lines().count(), 1, "{out}");
    serde_json::from_str(&out).expect("one JSON object")
}

/// The command end to end: on the simulated board at 100 kHz (with the Bode PNG), and on the
/// virtual board over TCP with `--load` (then `params` reads the tuned gains back); a check
/// of unstable gains exits 1 naming why.
#[test]
fn the_command_tunes_the_simulated_and_the_virtual_board() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("bode.png");
    let v = json(twinstack_bin(&[
        "tune",
        "--port",
        "sim",
        "--rate",
        "100k",
        "--json",
        "--png",
        png.to_str().unwrap(),
    ]));
    assert_eq!(v["rate_hz"], 100_000.0);
    assert!(
        v["figures"]["phase_margin_deg"].as_f64().unwrap() >= 45.0,
        "{v}"
    );
    assert!(
        v["figures"]["gain_margin_db"].as_f64().unwrap() >= 6.0,
        "{v}"
    );
    assert!((v["fit"]["resonance_hz"].as_f64().unwrap() / 21_804.0 - 1.0).abs() < 0.005);
    assert!(std::fs::metadata(&png).unwrap().len() > 10_000);
    // The board's timing: one period (the DAC latched by the timer) plus the 2 µs lead, whose
    // phase at the crossover is what the whole-tick model leaves out.
    let timing = &v["board_timing"];
    assert!((timing["sample_to_output_s"].as_f64().unwrap() - 12e-6).abs() < 1e-12);
    let crossover = v["figures"]["crossover_hz"].as_f64().unwrap();
    let lead = timing["lead_phase_deg"].as_f64().unwrap();
    assert!(
        crossover > 0.0 && (lead - 360.0 * crossover * 2e-6).abs() < 1e-9,
        "{v}"
    );

    // The text output gives the fitted resonance as the preview's flags, for `compensate`.
    let text = twinstack_bin(&["tune", "--port", "sim", "--rate", "100k"]);
    let out = String::from_utf8_lossy(&text.stdout);
    let fitted = format!(
        "`compensate --resonance-hz {:.0} --resonance-damping {:.4}`",
        v["fit"]["resonance_hz"].as_f64().unwrap(),
        v["fit"]["zeta"].as_f64().unwrap()
    );
    assert!(text.status.success() && out.contains(&fitted), "{out}");

    // `--params` writes the fitted resonance into a parameter file, the rest kept; a file
    // that does not load is refused before the sweep, and one whose check fails is unchanged.
    let params = dir.path().join("stage.json");
    let identified = twinstack_identify::param_file::ParamFile::from_model(
        &twinstack_identify::stage_model::StageModel {
            hysteresis: twinstack_identify::stage_model::Hysteresis::Pi(
                twinstack::PiParams::new(0.0, 0.5, &[0.0, 30.0, 60.0], &[0.08, 0.03, 0.02])
                    .unwrap(),
            ),
            scaling: twinstack::Scaling::new(0.0, 140.0, -20.0, 21.0).unwrap(),
            output_sign: 1.0,
            sensor_lag_s: 0.0,
            creep: None,
            output_map: None,
        },
        "um",
        None,
    );
    std::fs::write(&params, identified.to_json()).unwrap();
    let with_file = |extra: &[&str]| {
        let mut args = vec!["tune", "--port", "sim", "--rate", "100k"];
        args.extend_from_slice(extra);
        twinstack_bin(&args)
    };
    let written = with_file(&["--params", params.to_str().unwrap()]);
    assert!(written.status.success(), "{written:?}");
    let (file, _) = twinstack_identify::param_file::ParamFile::load(&params).unwrap();
    let resonance = file.resonance.expect("the resonance written");
    assert_eq!(
        resonance.frequency_hz,
        v["fit"]["resonance_hz"].as_f64().unwrap()
    );
    assert_eq!(resonance.damping, v["fit"]["zeta"].as_f64().unwrap());
    assert_eq!(
        twinstack_identify::param_file::ParamFile {
            resonance: None,
            ..file
        },
        identified
    );
    let broken = dir.path().join("broken.json");
    std::fs::write(&broken, "{ \"format\": \"other\" }").unwrap();
    let refused = with_file(&["--params", broken.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success() && err.contains("format"), "{err}");
    std::fs::write(&params, identified.to_json()).unwrap();
    let refused = with_file(&[
        "--kp",
        "0.1",
        "--ki",
        "20000",
        "--params",
        params.to_str().unwrap(),
    ]);
    assert_eq!(refused.status.code(), Some(1));
    assert_eq!(
        std::fs::read_to_string(&params).unwrap(),
        identified.to_json()
    );

    let bad = twinstack_bin(&[
        "tune", "--port", "sim", "--rate", "100k", "--kp", "0.1", "--ki", "20000",
    ]);
    assert_eq!(bad.status.code(), Some(1));
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("unstable"), "{err}");

    let (_board, port) = virtual_board_process::start(&["--speed", "0"]);
    let v = json(twinstack_bin(&[
        "tune", "--port", &port, "--load", "--json",
    ]));
    assert_eq!(v["loaded"], true);
    let params = twinstack_bin(&["params", "--port", &port]);
    let settings: serde_json::Value =
        serde_json::from_slice(&params.stdout).expect("params prints JSON");
    assert_eq!(
        settings["feedback"]["ki"], v["feedback"]["ki"],
        "{settings}"
    );
}

/// The shipped default feedback is stable, with at least 45° and 6 dB, at every control rate
/// the board allows (10–100 kHz, every kHz), on the paper stage's true plant with its gain
/// raised by the tuner's 1.4 allowance, and on the second stage; the gains it replaced
/// (kp 0.2, ki 500 /s) are not.
#[test]
fn the_shipped_default_feedback_is_stable_at_every_allowed_rate() {
    let (lo, hi) = (
        twinstack::board::Hardware::MIN_CONTROL_RATE_HZ,
        twinstack::board::Hardware::MAX_CONTROL_RATE_HZ,
    );
    let mut old_refused = 0;
    for rate in (lo..=hi).step_by(1000).map(f64::from) {
        for stage in [StageParams::paper(), heavier_stage()] {
            let t = true_plant(&stage, SPANS.0, SPANS.1, rate);
            let raised = twinstack_identify::tune::loop_model::LinearPlant::resonance(
                1.4 * t.gain,
                t.resonance_hz,
                t.zeta,
                t.delay,
                rate,
            );
            for p in [&t, &raised] {
                let f = check(p, &FeedbackSettings::DEFAULT, &Goals::at(rate))
                    .unwrap_or_else(|e| panic!("{rate} Hz: {e}"));
                assert!(f.gain_margin_db >= 6.0 && f.phase_margin_deg >= 45.0);
            }
            old_refused +=
                check(&t, &FeedbackSettings::pi(0.2, 500.0, 0.1), &Goals::at(rate)).is_err() as u32;
        }
    }
    assert!(old_refused > 0);
    // The simulated board at the extreme rates (hysteresis, noise, slew, the identified
    // feedforward): 60 ms after a 30 → 70 % step the stage holds within 0.2 % of the stroke
    // of the setpoint, and its last 10 ms swing less than that (no loop oscillation).
    let options = ClosedLoopOptions {
        out_dir: None,
        ..ClosedLoopOptions::default()
    };
    for rate in [f64::from(lo), f64::from(hi)] {
        let model = closed_loop::identify_model(rate, &options).unwrap();
        let mut board = closed_loop::board(rate, options.sensor_noise_um).unwrap();
        let settings = twinstack::config::settings::Settings {
            feedback: Some(FeedbackSettings::DEFAULT),
            ..closed_loop::settings(
                rate,
                &model,
                closed_loop::sensor_settings(&board),
                closed_loop::Configuration4::Both,
                false,
            )
        };
        let config = settings.build(&closed_loop::hardware(rate)).unwrap();
        let mut c = twinstack::control::Controller::new(config);
        let s = model.scaling;
        let (a, b) = (s.output_min, s.output_max);
        let sp =
            |f: f64| twinstack::fixed_point::signal_from_f64(s.output_to_norm(a + f * (b - a)));
        let ticks = (0.06 * rate) as usize;
        let mut xs = Vec::new();
        for k in 0..2 * ticks {
            c.tick_board(Some(if k < ticks { sp(0.3) } else { sp(0.7) }), &mut board);
            xs.push(board.plant().stage_um());
        }
        let tail = &xs[xs.len() - (0.01 * rate) as usize..];
        let target = a + 0.7 * (b - a);
        let worst = tail.iter().fold(0.0f64, |m, &x| m.max((x - target).abs()));
        assert!(
            worst < 0.002 * (b - a),
            "{rate} Hz: {worst} µm off after 60 ms"
        );
    }
}
