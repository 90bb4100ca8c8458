//! `twinstack calibrate`: the whole lab workflow against the virtual board run as a
//! process (calibrate → stream a 100-sample file → record the streamed run with four signals →
//! read the parameters back), with the virtual stage's tracking error below 1 % max after
//! calibration; and each way a calibration can fail, on the in-process board, with the error
//! that says why and nothing loaded.

use hal_sim::sim_device::{SimDevice, SimDeviceConfig};
use std::process::{Command, Output};
use std::time::Duration;
use twinstack::board::Hardware;
use twinstack::config::settings::{Mode, Settings};
use twinstack_identify::calibrate::{
    calibrate, CalibrateError, CalibrateOptions, ResonanceOutcome,
};
use twinstack_identify::excitation::SWEEP_CYCLES;
use twinstack_identify::identification::auto::{identify_auto_admitting, Admission};
use twinstack_identify::identification::{IdentifyError, IdentifyOptions, ModelKind};
use twinstack_link::client::Client;

#[path = "support/virtual_board_process.rs"]
mod virtual_board_process;

fn twinstack_bin(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .env_remove("TWINSTACK_PORT")
        .args(args)
        .output()
        .expect("twinstack runs")
}

fn ok(o: Output) -> String {
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        o.status.success(),
        "exit {:?}\n{out}{}",
        o.status.code(),
        String::from_utf8_lossy(&o.stderr)
    );
    out
}

/// `twinstack virtual-board` as fast as it runs; returns it and its `--port`.
fn start_virtual_board() -> (virtual_board_process::VirtualBoard, String) {
    virtual_board_process::start(&["--speed", "0"])
}

#[test]
fn the_lab_workflow_calibrates_the_virtual_stage_below_one_percent_then_streams_and_records() {
    let (_board, port) = start_virtual_board();
    let dir = tempfile::tempdir().unwrap();
    let params = dir.path().join("stage.json");

    // 1. calibrate: one JSON object with the figures.
    let out = ok(twinstack_bin(&[
        "calibrate",
        "--port",
        &port,
        "--out",
        params.to_str().unwrap(),
        "--json",
    ]));
    assert_eq!(out.lines().count(), 1, "{out}");
    let v: serde_json::Value = serde_json::from_str(&out).expect("JSON");
    eprintln!("{v:#}");
    let after = v["tracking_after"]["max_pct"].as_f64().unwrap();
    let before = v["tracking_before"]["max_pct"].as_f64().unwrap();
    assert!(
        after < 1.0,
        "compensated tracking max {after} % (goal < 1 %)"
    );
    assert!(
        before > 3.0 * after,
        "bypass {before} % against compensated {after} %"
    );
    assert!(
        v["tracking_after"]["rms_pct"].as_f64().unwrap() < 0.5,
        "{v}"
    );
    assert_eq!(v["tracking_after"]["underran"], false);
    // auto ranked the whole family (four models, each with and without creep, and Bouc–Wen
    // with its output map, with and without creep) and picked a model that predicts the
    // held-out cycle.
    assert_eq!(v["ranking"].as_array().unwrap().len(), 10, "{v}");
    // Each with its compensator's figures beside the forward ones: what it was ranked by.
    assert!(
        v["ranking"]
            .as_array()
            .unwrap()
            .iter()
            .all(|c| c["error"].is_string()
                || (c["inverse_max_pct"].is_number() && c["tracking_max_pct"].is_number())),
        "{v}"
    );
    assert!(v["held_out"]["max_pct"].as_f64().unwrap() < 5.0);
    assert_eq!(v["stored"], "Bypass");
    // The parameter file is the one `identify` writes, and `load` reads it back.
    let (file, _) =
        twinstack_identify::param_file::ParamFile::load(&params).expect("a parameter file");
    assert_eq!(file.settings.mode, Mode::OpenLoop);
    // The excitation's fastest motion, as fitted, in the file and the report: the default
    // excitation's nested loops, tens of hertz.
    let seen = file
        .identification
        .as_ref()
        .and_then(|i| i.fastest_motion_hz)
        .expect("the fitted motion in the file");
    assert!((20.0..60.0).contains(&seen), "{seen}");
    assert_eq!(v["fastest_motion_hz"], seen);
    // The stage's resonance measured after the excitation as `tune` measures it (the
    // simulated stage's 21.8 kHz, damping 0.017), in the report and in the file.
    let resonance = file.resonance.expect("the resonance in the parameter file");
    assert!(
        (resonance.frequency_hz / 21_800.0 - 1.0).abs() < 0.01
            && (resonance.damping / 0.017 - 1.0).abs() < 0.15,
        "{resonance:?}"
    );
    assert_eq!(v["resonance"]["frequency_hz"], resonance.frequency_hz);
    assert_eq!(v["resonance"]["damping"], resonance.damping);
    let png = std::fs::read(params.with_extension("png")).expect("the PNG is written");
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");

    // 2. The board runs the calibration: the settings read back are the file's, in open loop.
    let read_back: Settings =
        serde_json::from_str(&ok(twinstack_bin(&["params", "--port", &port])))
            .expect("params JSON");
    assert_eq!(read_back, file.settings);
    let status: serde_json::Value =
        serde_json::from_str(&ok(twinstack_bin(&["status", "--port", &port, "--json"]))).unwrap();
    assert_eq!(status["mode"], "open-loop");

    // 3. stream a 100-sample file (µm, through the file's ranges): one slow cosine cycle over
    // the trajectory's range, from its bottom where the verification left the output; record
    // the streamed run with four signals over the same connection.
    let (lo, hi) = (
        v["trajectory_range"][0].as_f64().unwrap(),
        v["trajectory_range"][1].as_f64().unwrap(),
    );
    let mut text = String::from("x\n");
    for i in 0..100 {
        let f = 0.5 - 0.5 * (std::f64::consts::TAU * i as f64 / 100.0).cos();
        text.push_str(&format!("{}\n", lo + (hi - lo) * f));
    }
    let data = dir.path().join("setpoints.csv");
    std::fs::write(&data, text).unwrap();
    // The file streamed through the parameter file's ranges, one setpoint every 50 ticks.
    let stream = |extra: &[&str]| {
        let mut args = vec![
            "stream",
            "--port",
            &port,
            "--data",
            data.to_str().unwrap(),
            "--params",
            params.to_str().unwrap(),
            "--divider",
            "50",
        ];
        args.extend_from_slice(extra);
        twinstack_bin(&args)
    };
    // `--preview` takes the file's resonance: shaped setpoints are one a tick, and this file
    // plays one every 50 ticks, which it refuses before anything is sent.
    let refused = stream(&["--preview"]);
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(
        !refused.status.success()
            && stderr.contains("--preview: the resonance of")
            && stderr.contains("one setpoint every 50 ticks")
            && stderr.contains("nothing was sent"),
        "{stderr}"
    );
    let run = dir.path().join("run.csv");
    let out = ok(stream(&[
        "--record",
        "setpoint,left,sensor,error",
        "--record-out",
        run.to_str().unwrap(),
    ]));
    assert!(
        out.contains("streamed 100 setpoints")
            && out.contains("frames of setpoint, left, sensor, error"),
        "{out}"
    );
    let csv = std::fs::read_to_string(&run).unwrap();
    let mut lines = csv.lines();
    assert_eq!(
        lines.next(),
        Some("t [s],setpoint [um],left [V],sensor [um],error [um]")
    );
    let rows: Vec<Vec<f64>> = lines
        .map(|l| l.split(',').map(|c| c.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 5000, "100 setpoints × 50 ticks");
    // The compensated stage follows the streamed setpoints (a 10 Hz cosine over the
    // trajectory's range) as it tracked the verification's trajectory, once the rise to the top
    // has wiped the hysteresis memory: between two commands the virtual board runs on (as fast
    // as it can here), and its Duhem stacks creep under the amplifier's noise toward their
    // anhysteretic curve (see the simulator's chapter), a drift the compensator knows nothing
    // of and the first half-cycle undoes. The descending half: within the verification's
    // worst case and half a percent of the span.
    let span = hi - lo;
    let worst = rows[2500..]
        .iter()
        .map(|row| (row[3] - row[1]).abs())
        .fold(0.0, f64::max);
    assert!(
        worst < (after + 0.5) / 100.0 * span,
        "worst {worst} um over a {span} um range (verification {after} %)"
    );
    // The error column is the sensor's difference from the setpoint, as recorded.
    assert!(rows
        .iter()
        .all(|row| (row[4] - (row[1] - row[3])).abs() < 0.01 * span));

    // 4. A later `record` on the same board, four signals, in physical units.
    let now = dir.path().join("now.csv");
    let out = ok(twinstack_bin(&[
        "record",
        "--port",
        &port,
        "--signals",
        "setpoint,left,right,sensor",
        "--samples",
        "1000",
        "--out",
        now.to_str().unwrap(),
    ]));
    assert!(
        out.contains("1000 frames of setpoint, left, right, sensor"),
        "{out}"
    );
}

/// The in-process board (simulated time), and a client on it.
fn sim_client(config: SimDeviceConfig) -> Client<SimDevice> {
    let mut client = Client::new(SimDevice::new(config).expect("the simulated board"));
    client.set_timeout(Duration::from_secs(2));
    client
}

/// A short excitation and one model: the failures below come before or right after the fit.
fn quick() -> CalibrateOptions {
    CalibrateOptions {
        excitation_hz: 20.0,
        full_cycles: 2,
        decay_cycles: 4,
        loop_cycles: 3,
        multisine_cycles: 3,
        model: Some(ModelKind::Duhem),
        store: None,
        ..CalibrateOptions::default()
    }
}

/// Without the resonance's sweep the file holds none, and the report says it was not asked
/// for.
#[test]
fn a_calibration_without_the_resonance_writes_none() {
    let mut client = sim_client(SimDeviceConfig::paper());
    let options = CalibrateOptions {
        resonance: false,
        ..quick()
    };
    let report = calibrate(&mut client, &options, |_| {}).unwrap();
    assert_eq!(report.resonance, ResonanceOutcome::NotAsked);
    assert_eq!(report.file.resonance, None);
    assert!(!report.file.to_json().contains("resonance"));
}

#[test]
fn a_board_without_a_sensor_is_refused_before_anything_moves() {
    let mut client = sim_client(SimDeviceConfig::paper());
    let mut no_sensor = SimDeviceConfig::paper_settings(Mode::Bypass);
    no_sensor.sensor = None;
    no_sensor.feedback = None;
    client.load_params(&no_sensor).unwrap();
    let ticks = client.status().unwrap().ticks;
    let e = calibrate(&mut client, &quick(), |_| {}).unwrap_err();
    assert!(matches!(e, CalibrateError::NoSensor), "{e}");
    assert!(e.to_string().contains("no sensor"), "{e}");
    // Nothing was started or loaded.
    let s = client.status().unwrap();
    assert!(s.ticks > ticks);
    assert_eq!(client.read_params().unwrap(), no_sensor);
}

#[test]
fn a_sensor_that_does_not_see_the_stage_is_named_and_nothing_is_loaded() {
    // A sensor spanning ±50 mm: the stage's ±35 µm are a few steps of its 12-bit ADC.
    let mut config = SimDeviceConfig::paper();
    config.board.sensor_range_um = (-50_000.0, 50_000.0);
    let mut client = sim_client(config);
    let before = client.read_params().unwrap();
    let e = calibrate(&mut client, &quick(), |_| {}).unwrap_err();
    assert!(matches!(e, CalibrateError::SensorFlat { .. }), "{e}");
    let text = e.to_string();
    assert!(
        text.contains("the sensor did not follow the drive") && text.contains("Nothing was loaded"),
        "{text}"
    );
    assert_eq!(
        client.read_params().unwrap().compensator,
        before.compensator
    );
}

#[test]
fn a_sensor_reading_clipped_by_the_output_range_is_named() {
    let mut client = sim_client(SimDeviceConfig::paper());
    // The board's output range ±25 µm: the stage's ±30 µm saturate the normalised reading.
    let mut narrow = SimDeviceConfig::paper_settings(Mode::Bypass);
    narrow.ranges.output_min = -25.0;
    narrow.ranges.output_max = 25.0;
    // (The representative model does not fit so narrow a range; bypass needs none.)
    narrow.compensator = None;
    narrow.observer = None;
    client.load_params(&narrow).unwrap();
    let e = calibrate(&mut client, &quick(), |_| {}).unwrap_err();
    assert!(matches!(e, CalibrateError::SensorSaturated { .. }), "{e}");
    assert!(
        e.to_string().contains("widen settings.ranges.output"),
        "{e}"
    );
}

#[test]
fn a_fit_that_does_not_fit_is_refused_and_the_full_range_needs_no_clamp() {
    // A held-out limit no model meets.
    let mut client = sim_client(SimDeviceConfig::paper());
    let strict = CalibrateOptions {
        max_held_out_pct: 0.01,
        ..quick()
    };
    let e = calibrate(&mut client, &strict, |_| {}).unwrap_err();
    match &e {
        CalibrateError::DoesNotFit {
            model,
            max_pct,
            limit,
        } => {
            assert_eq!(model, "Duhem");
            assert!(*max_pct > 0.01 && *limit == 0.01, "{e}");
        }
        other => panic!("{other}"),
    }
    assert!(e.to_string().contains("nothing was loaded"), "{e}");
    assert_eq!(
        client.read_params().unwrap(),
        SimDeviceConfig::paper_settings(Mode::Bypass)
    );

    // The full drive range: identify's input range is the range swept (no margin since the
    // models rest on the ascending branch of it), which the drive reaches: no clamp needed.
    let full = CalibrateOptions {
        amplitude: 1.0,
        ..quick()
    };
    let r = calibrate(&mut client, &full, |_| {}).expect("full-range calibration");
    assert!(!r.clamped);
    assert_eq!(client.read_params().unwrap(), r.file.settings);
}

/// At 100 kHz the tick budget leaves room for fewer models than at 50 kHz (no generalised
/// P–I of 17 operators, no four-mode creep beside a Duhem): `auto` ranks them all but picks only
/// among those the board runs at its rate, so the calibration loads (a pick the board then
/// refused would fail `calibrate` at the load).
#[test]
fn auto_picks_a_model_the_board_runs_at_its_rate() {
    let rate = 100_000.0;
    let mut config = SimDeviceConfig::paper();
    config.board.plant.dt = 1.0 / rate;
    let mut client = sim_client(config);
    // Three full cycles and six decaying (the quick excitation's two and four leave the
    // 100 kHz pick, a generalised P–I sized to 12 operators, 5.4 % off on its held-out
    // cycle: more than calibrate's 5 %).
    let options = CalibrateOptions {
        model: None,
        full_cycles: 3,
        decay_cycles: 6,
        ..quick()
    };
    let r = calibrate(&mut client, &options, |_| {}).expect("calibration at 100 kHz");
    assert_eq!(r.tick_rate_hz, 100_000);
    // What was loaded runs at the board's rate.
    let loaded = client.read_params().unwrap();
    assert_eq!(loaded, r.file.settings);
    assert!(loaded.build(&Hardware::driver_board(rate)).is_ok());
    // The observer is left out only where the rate leaves the pipeline no time for it beside
    // the compensator (it runs below the tick, in the services).
    let observed = Settings {
        observer: loaded.compensator.clone(),
        ..loaded.clone()
    };
    assert!(
        loaded.observer.is_some() || observed.build(&Hardware::driver_board(rate)).is_err(),
        "{loaded:?}"
    );
    assert!(
        r.ranking[0].validation.admitted().is_some(),
        "{:?}",
        r.ranking
    );
    // Creep beside a Bouc–Wen does not fit 80 % of a 100 kHz period beside the capture even
    // with one mode and no observer: listed with its figures and why, not admitted.
    assert!(
        r.ranking
            .iter()
            .any(|c| c.label.starts_with("Bouc-Wen + creep")
                && c.validation.admitted().is_none()
                && c.summary.contains("not admitted")),
        "{:?}",
        r.ranking
    );
    // Each fitted candidate carries its compensator's figures beside its fit, as `identify`
    // prints them, and the pick's inverse holds where any admitted candidate's does.
    for c in r
        .ranking
        .iter()
        .filter(|c| c.validation.figures().is_some())
    {
        assert!(
            c.inverse.is_some() && c.tracking.is_some() && c.summary.contains("inverse"),
            "{c:?}"
        );
    }
    if r.ranking
        .iter()
        .any(|c| c.validation.admitted().is_some() && c.set_aside.is_none())
    {
        assert!(r.ranking[0].set_aside.is_none(), "{:?}", r.ranking);
    }
    // The model's name says "+ creep" only where the file holds one.
    assert_eq!(
        r.model.contains("+ creep"),
        r.file.settings.creep.is_some(),
        "{}",
        r.model
    );
    // Admitted candidates rank ahead of refused ones, whatever their figures (here the
    // observer's going first leaves none refused for the budget).
    let first_refused = r
        .ranking
        .iter()
        .position(|c| c.validation.admitted().is_none())
        .unwrap_or(r.ranking.len());
    assert!(r.ranking[first_refused..]
        .iter()
        .all(|c| c.validation.admitted().is_none()));

    // Admitting none: an error naming every candidate and why, not a pick.
    let fit_until = options.excitation_s() - 1.0 / options.excitation_hz;
    let candidates = IdentifyOptions::new(ModelKind::Pi, fit_until).candidates();
    let e = identify_auto_admitting(&r.excitation, &candidates, |_, _| {
        Admission::Refused("too dear".into())
    })
    .unwrap_err();
    match &e {
        IdentifyError::NoneAdmitted(why) => {
            assert_eq!(why.matches("too dear").count(), candidates.len(), "{e}")
        }
        other => panic!("{other}"),
    }
}

/// At 100 kHz a P–I of the default 17 operators with its observer, and the calibration's own
/// capture of every other tick beside it, is too dear for the share of the period the tick
/// budget leaves the pipeline: `calibrate --model pi` leaves the observer out (the board has a
/// sensor; the observer only gives the estimate and the drift check) and, where that is not
/// enough, fits fewer operators, says so, and loads what the board runs; with `--operators
/// 17` asked for it keeps them and is refused, naming what they need.
#[test]
fn a_model_is_sized_to_the_boards_rate_unless_its_operators_are_asked_for() {
    let rate = 100_000.0;
    let mut config = SimDeviceConfig::paper();
    config.board.plant.dt = 1.0 / rate;
    let options = CalibrateOptions {
        model: Some(ModelKind::Pi),
        // A capture of every other tick beside the model (the calibration's record at 50 kHz).
        sample_rate_hz: rate / 2.0,
        // The sizing is under test, not the fit: this stage creeps more than a P–I alone
        // follows over the quick excitation (8 % held out).
        max_held_out_pct: 20.0,
        ..quick()
    };
    let mut client = sim_client(config.clone());
    let r = calibrate(&mut client, &options, |_| {}).expect("P-I sized to 100 kHz");
    let operators = r.file.identification.as_ref().unwrap().operators;
    eprintln!("at 100 kHz beside the capture: {} ({})", r.model, r.reason);
    assert!((8..17).contains(&operators), "{operators}");
    assert!(r.reason.contains("no observer"), "{}", r.reason);
    let loaded = client.read_params().unwrap();
    assert!(loaded.observer.is_none() && loaded.compensator.is_some());
    assert!(loaded.build(&Hardware::driver_board(rate)).is_ok());

    let mut client = sim_client(config);
    let e = calibrate(
        &mut client,
        &CalibrateOptions {
            operators: Some(17),
            ..options
        },
        |_| {},
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("17 uniform operators") && e.contains("1344"),
        "{e}"
    );
}

#[test]
fn bad_options_are_refused_naming_the_option() {
    let mut client = sim_client(SimDeviceConfig::paper());
    let e = calibrate(
        &mut client,
        &CalibrateOptions {
            decay_cycles: 1,
            ..quick()
        },
        |_| {},
    )
    .unwrap_err();
    assert!(e.to_string().contains("decay_cycles"), "{e}");
    let o = twinstack_bin(&["calibrate", "--port", "sim", "--out", "x.png"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("must not end in .png"));
}

/// The fastest motion the user names is in what the board streams and records: the
/// excitation's drive, as recorded, sweeps up to it (its half-periods shorten to that
/// motion's); one the recording cannot resolve is refused, naming it, before anything is
/// streamed.
#[test]
fn the_fastest_motion_named_is_swept_on_the_board_and_one_it_cannot_record_is_refused() {
    let mut client = sim_client(SimDeviceConfig::paper());
    let options = CalibrateOptions {
        fastest_hz: Some(200.0),
        resonance: false,
        ..quick()
    };
    let report = calibrate(&mut client, &options, |_| {}).unwrap();
    let (t, u) = (&report.excitation.t, report.excitation.u.as_ref().unwrap());
    // The sweep follows the lead-in, the full and decaying cycles and the nested loops.
    let from = options.lead_in_s() + 9.0 / options.excitation_hz;
    let to = from + f64::from(SWEEP_CYCLES) / options.excitation_hz;
    let (lo, hi) = u
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    let middle = 0.5 * (lo + hi);
    let swept: Vec<(f64, f64)> = t
        .iter()
        .zip(u)
        .filter(|(&t, _)| t >= from && t < to)
        .map(|(&t, &u)| (t, u - middle))
        .collect();
    let crossings: Vec<f64> = swept
        .windows(2)
        .filter(|w| (w[0].1 < 0.0) != (w[1].1 < 0.0))
        .map(|w| w[1].0)
        .collect();
    let shortest = crossings
        .windows(2)
        .map(|w| w[1] - w[0])
        .fold(f64::INFINITY, f64::min);
    assert!(
        (shortest * 2.0 * 200.0 - 1.0).abs() < 0.1,
        "shortest half-period {shortest} s of {} crossings",
        crossings.len()
    );
    // The file records the motion the model was fitted on: the sweep's, not an octave short
    // of the 200 Hz named (its window tapers the top).
    let seen = report
        .file
        .identification
        .as_ref()
        .and_then(|r| r.fastest_motion_hz)
        .unwrap();
    assert!((100.0..=200.0).contains(&seen), "{seen}");

    let mut client = sim_client(SimDeviceConfig::paper());
    let before = client.status().unwrap().next_seq;
    let e = calibrate(
        &mut client,
        &CalibrateOptions {
            fastest_hz: Some(600.0),
            ..quick()
        },
        |_| {},
    )
    .unwrap_err();
    assert!(
        matches!(e, CalibrateError::FastestUnresolved { fastest_hz, .. } if fastest_hz == 600.0),
        "{e}"
    );
    assert_eq!(
        client.status().unwrap().next_seq,
        before,
        "nothing streamed"
    );
}

/// The board's generator decays as the request says (protocol v5): full cycles, then each
/// cycle's peak the previous one's × keep / 65536, bit for bit as the library's generator.
#[test]
fn the_board_plays_the_decaying_waveform_it_is_asked_for() {
    use twinstack::protocol::messages::{CaptureRequest, Trigger};
    use twinstack::services::recorder::Channel;
    let mut client = sim_client(SimDeviceConfig::paper());
    use twinstack::protocol::messages::{WaveDecay, WaveShape, Waveform};
    // Two full cycles of 20 Hz at 0.97, then four decaying to 15 % of it.
    let final_amplitude = 0.15f64;
    let w = Waveform {
        shape: WaveShape::Sine,
        offset: 0,
        amplitude: (0.97f64 * 32768.0).round() as i16,
        frequency_mhz: 20_000,
        decay: Some(WaveDecay {
            hold_cycles: 2,
            keep: (final_amplitude.powf(0.25) * 65536.0).round() as u16,
        }),
    };
    // 6 cycles of 20 Hz at 50 kHz: 2 500 ticks a cycle, every 5th captured.
    client
        .arm_capture(CaptureRequest {
            signals: Channel::Setpoint.bit(),
            samples: 3000,
            pre_trigger: 0,
            trigger: Trigger::WaveformStart,
            decimation: 5,
        })
        .unwrap();
    client.waveform(w).unwrap();
    let (status, window) =
        twinstack_link::capture::wait_and_read(&mut client, Duration::from_secs(5), |_, _| {})
            .expect("the capture completes");
    assert_eq!(status.samples, 3000);
    let peaks: Vec<i16> = window
        .chunks(500)
        .map(|c| *c.iter().max().unwrap())
        .collect();
    // The library's generator, fed the same request, gives the same peaks.
    let decay = w.decay.unwrap();
    let mut g = twinstack::sources::waveform::WaveformGenerator::new(
        twinstack::sources::waveform::Shape::Sine,
        0,
        (w.amplitude as i32) << 15,
        w.frequency_mhz as f64 / 1000.0,
        50_000.0,
    )
    .unwrap()
    .with_decay(decay.hold_cycles, decay.keep);
    let want: Vec<i16> = (0..6)
        .map(|_| {
            (0..2500)
                .map(|k| {
                    let v = g.next_sample();
                    if k % 5 == 0 {
                        (v >> 15).clamp(-32768, 32767) as i16
                    } else {
                        i16::MIN
                    }
                })
                .max()
                .unwrap()
        })
        .collect();
    assert_eq!(peaks, want);
    // Two full cycles, then four shrinking ones down to the final amplitude.
    assert_eq!(peaks[0], peaks[1]);
    assert!(peaks.windows(2).skip(1).all(|p| p[1] < p[0]), "{peaks:?}");
    let last = peaks[5] as f64 / peaks[0] as f64;
    assert!((last - final_amplitude).abs() < 0.01, "{last}");
}

/// The board plays the excitation calibrate streams: in bypass, the setpoint it captured from
/// the stream's start is the one planned, setpoint for setpoint (one every `stream_divider`
/// ticks, captured at that decimation), and the drive follows it over the swept range.
#[test]
fn the_board_plays_the_excitation_calibrate_streams() {
    use twinstack::protocol::messages::{CaptureRequest, Trigger};
    use twinstack::services::recorder::Channel;
    use twinstack_link::streamer::stream_setpoints;
    let mut client = sim_client(SimDeviceConfig::paper());
    client.set_mode(Mode::Bypass).unwrap();
    let options = quick();
    let rate = client.capture_status().unwrap().tick_rate_hz as f64;
    let divider = options.stream_divider;
    let planned = options.excitation_setpoints(rate / divider as f64);
    assert!(planned.len() > 1000, "{}", planned.len());
    client
        .arm_capture(CaptureRequest {
            signals: Channel::Setpoint.bit(),
            samples: planned.len() as u32,
            pre_trigger: 0,
            trigger: Trigger::StreamStart,
            decimation: divider,
        })
        .unwrap();
    let stream = options.stream_options(rate);
    let report = stream_setpoints(&mut client, &planned, &stream, |_| {}).unwrap();
    assert!(!report.underran());
    let (status, window) =
        twinstack_link::capture::wait_and_read(&mut client, Duration::from_secs(10), |_, _| {})
            .expect("the capture completes");
    assert_eq!(status.samples as usize, planned.len());
    // Captured once every `divider` ticks from the stream's start: each is the planned
    // setpoint of its instant, within the stream's interpolation between that setpoint and a
    // neighbour (the capture's tick and the stream's sample need not fall together).
    for (k, &got) in window.iter().enumerate().skip(1) {
        let near = &planned[k - 1..(k + 2).min(planned.len())];
        let (lo, hi) = near
            .iter()
            .fold((i16::MAX, i16::MIN), |(l, h), &v| (l.min(v), h.max(v)));
        assert!(
            got >= lo.saturating_sub(1) && got <= hi.saturating_add(1),
            "sample {k}: {got} outside {lo} … {hi}"
        );
    }
    // It sweeps the amplitude asked for, about the middle.
    let (lo, hi) = window
        .iter()
        .fold((i16::MAX, i16::MIN), |(l, h), &v| (l.min(v), h.max(v)));
    let want = (options.amplitude * 32768.0) as i16;
    assert!(
        (hi - want).abs() < 100 && (lo + want).abs() < 100,
        "{lo} … {hi}"
    );
}

/// Calibrates Bouc–Wen with its observer on a simulated dual-stage board whose piezo runs at
/// `fine_rate_hz`, its piezo handed back (`CoarseRelease`): the steps `calibrate` reported
/// before it identified again beside the board's own load (it must have).
fn calibrate_beside_the_coarse_task(fine_rate_hz: f64) -> Vec<String> {
    use hal_sim::coarse_rig::{DualStageDevice, DualStageDeviceConfig};
    use twinstack::protocol::messages::Request;
    use twinstack_identify::calibrate::Progress;
    let mut config = DualStageDeviceConfig::paper();
    config.sim.board.plant.dt = 1.0 / fine_rate_hz;
    config.sim.dual.fine_rate_hz = fine_rate_hz;
    let device = DualStageDevice::dual_stage(&config).unwrap();
    let mut client = Client::new(device);
    client.set_timeout(Duration::from_secs(10));
    client.coarse(&Request::CoarseRelease).unwrap();
    let options = CalibrateOptions {
        model: Some(ModelKind::BoucWen),
        resonance: false,
        max_held_out_pct: 20.0,
        ..quick()
    };
    let mut steps = Vec::new();
    let r = calibrate(&mut client, &options, |p| {
        if let Progress::Step(s) = p {
            steps.push(s.to_string());
        }
    })
    .expect("sized beside the coarse task");
    eprintln!("beside the coarse task: {} ({})", r.model, r.reason);
    assert_eq!(r.tick_rate_hz as f64, fine_rate_hz);
    let loaded = client.read_params().unwrap();
    assert!(loaded.compensator.is_some() && loaded.observer.is_none());
    assert!(r.reason.contains("no observer"), "{}", r.reason);
    assert!(r.after.max_pct < r.before.max_pct);
    let again = steps
        .iter()
        .position(|s| s.starts_with("identifying again"))
        .unwrap_or_else(|| panic!("{steps:?}"));
    steps.truncate(again);
    steps
}

/// A dual-stage board runs its coarse task beside every model, which the host's tick budget
/// does not see. At 55 kHz Bouc–Wen with its observer fits the period alone, not beside the
/// task's share: the first load is refused for the cycles, and `calibrate` identifies again
/// from the same excitation with the board's own load charged (the observer leaves first),
/// and loads what it runs.
#[test]
fn on_a_dual_stage_board_the_model_is_sized_beside_the_coarse_task() {
    let before = calibrate_beside_the_coarse_task(55_000.0);
    // Before any tracking: the load's refusal.
    assert!(
        !before.iter().any(|s| s.starts_with("tracking")),
        "{before:?}"
    );
}

/// At 50 kHz the same model fits beside the coarse task, and is loaded: only the tracking's
/// capture, beside both, is refused. `calibrate` then takes the board's own load from that
/// refusal, identifies again with it charged and loads what runs with its capture too.
#[test]
fn on_a_dual_stage_board_the_tracking_s_capture_is_sized_for_too() {
    let before = calibrate_beside_the_coarse_task(50_000.0);
    assert!(
        before.iter().any(|s| s.starts_with("tracking in bypass")),
        "{before:?}"
    );
}
