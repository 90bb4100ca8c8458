//! The parameter file `identify` writes → what `twinstack load` sends: the file carries the
//! board's own settings type, what the board could not run is refused (naming the field)
//! before anything is sent, the board keeps its sensor and gains when the file has none, and
//! a board's refusal reaches the user as one line.

use clap::Parser;
use hal_sim::sim_device::{SimDevice, SimDeviceConfig};
use twinstack::config::settings::PreviewDesign;
use twinstack::config::settings::{representative_duhem, representative_pi, Mode, Model};
use twinstack::control::drive::DriveSettings;
use twinstack::Scaling;
use twinstack_cli::commands::load::{settings_for, with_preview, Args};
use twinstack_identify::param_file::{ParamFile, ParamFileError};
use twinstack_identify::preview::Resonance;
use twinstack_identify::stage_model::{Hysteresis, StageModel};
use twinstack_link::client::Client;

#[path = "../../link/tests/support/mod.rs"]
mod support;

fn pi_model() -> StageModel {
    let Model::PrandtlIshlinskii(p) = representative_pi(16).unwrap() else {
        unreachable!()
    };
    StageModel {
        hysteresis: Hysteresis::Pi(p),
        scaling: Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap(),
        output_sign: 1.0,
        sensor_lag_s: 0.0,
        creep: None,
        output_map: None,
    }
}

/// `twinstack load`'s arguments, parsed as the command line gives them.
fn load_args(extra: &[&str]) -> Args {
    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        load: Args,
    }
    let mut argv = vec!["load", "--port", "sim", "--params", "p.json"];
    argv.extend_from_slice(extra);
    Cli::try_parse_from(argv).expect("arguments parse").load
}

#[test]
fn a_pi_file_carries_the_model_as_compensator_and_observer_with_the_default_drive() {
    let m = pi_model();
    let file = ParamFile::from_model(&m, "um", None);
    let Hysteresis::Pi(p) = &m.hysteresis else {
        unreachable!()
    };
    let s = &file.settings;
    // f64 throughout: the model is carried exactly, not rounded.
    assert_eq!(s.compensator, Some(Model::PrandtlIshlinskii(p.clone())));
    assert_eq!(s.observer, s.compensator);
    assert_eq!(s.ranges, m.scaling);
    assert_eq!(s.drive, DriveSettings::DEFAULT);
    assert_eq!(s.mode, Mode::OpenLoop);
    assert_eq!((s.sensor, s.feedback), (None, None));
    let (back, loaded) = ParamFile::parse(std::path::Path::new("p.json"), &file.to_json())
        .expect("a written file loads");
    assert_eq!(back, file);
    assert_eq!(loaded, m);
}

#[test]
fn a_duhem_file_carries_the_duhem_model() {
    let Model::Duhem(d) = representative_duhem() else {
        unreachable!()
    };
    let m = StageModel {
        hysteresis: Hysteresis::Duhem(d),
        ..pi_model()
    };
    let file = ParamFile::from_model(&m, "um", None);
    assert!(
        matches!(file.settings.compensator, Some(Model::Duhem(p)) if p.alpha == 0.02),
        "{:?}",
        file.settings.compensator
    );
}

/// The file of [`pi_model`] with one edit, parsed: its error.
fn refused(edit: impl Fn(&mut serde_json::Value)) -> ParamFileError {
    let mut v: serde_json::Value =
        serde_json::from_str(&ParamFile::from_model(&pi_model(), "um", None).to_json()).unwrap();
    edit(&mut v);
    ParamFile::parse(std::path::Path::new("p.json"), &v.to_string()).unwrap_err()
}

#[test]
fn what_the_board_could_not_run_is_refused_before_sending_naming_the_field() {
    let field = |e: &ParamFileError| match e {
        ParamFileError::Field { field, .. } => field.clone(),
        other => panic!("not a field error: {other}"),
    };
    // Bias outside the voltage limits.
    let e = refused(|v| v["settings"]["drive"]["bias"] = 150.0.into());
    assert_eq!(field(&e), "settings.drive.bias", "{e}");
    assert!(e.to_string().contains("must be at most 140"), "{e}");
    // Closed loop in a file without a sensor calibration (or gains).
    let e = refused(|v| v["settings"]["mode"] = "ClosedLoop".into());
    assert_eq!(field(&e), "settings.sensor", "{e}");
    // Feedback limit beyond the drive range.
    let e = refused(|v| {
        v["settings"]["feedback"] = serde_json::json!({
            "kp": 0.2, "ki": 10.0, "kd": 0.0, "derivative_cutoff_hz": 1.0,
            "limit": 1.5, "notch": null
        })
    });
    assert_eq!(field(&e), "settings.feedback.limit", "{e}");
    assert!(e.to_string().contains("must be at most 1"), "{e}");
}

#[test]
fn closed_loop_on_an_inverted_sensor_is_refused_by_load_before_sending() {
    let dir = tempfile::tempdir().unwrap();
    let file = ParamFile::from_model(
        &StageModel {
            output_sign: -1.0,
            ..pi_model()
        },
        "um",
        None,
    );
    let path = dir.path().join("p.json");
    std::fs::write(&path, file.to_json()).unwrap();
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args(["load", "--port", "sim", "--mode", "closed-loop", "--params"])
        .arg(&path)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("inverted"), "{err}");
    assert!(err.contains("nothing was sent"), "{err}");
}

#[test]
fn an_identified_file_loads_onto_the_board_and_reads_back_with_the_board_s_sensor() {
    // What `identify` writes for the paper's stage (its ranges: 0…140 V onto ±45 µm).
    let Hysteresis::Pi(mut p) = pi_model().hysteresis else {
        unreachable!()
    };
    p.offset = -28.0;
    let m = StageModel {
        hysteresis: Hysteresis::Pi(p),
        scaling: Scaling::new(0.0, 140.0, -45.0, 45.0).unwrap(),
        ..pi_model()
    };
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("p.json");
    ParamFile::from_model(&m, "um", None).save(&path).unwrap();
    let (file, _) = ParamFile::load(&path).expect("the file loads");
    assert!(file.settings.sensor.is_none() && file.settings.feedback.is_none());

    // `twinstack load`'s path: the board's settings read back, the file's on top.
    let mut client = Client::new(SimDevice::new(SimDeviceConfig::paper()).expect("device"));
    let board = client.read_params().expect("the board's settings");
    assert!(board.sensor.is_some() && board.feedback.is_some());
    let sent = settings_for(&load_args(&[]), &file.settings, Some(&board));
    client.load_params(&sent).expect("loaded");
    let back = client.read_params().expect("read back");
    assert_eq!(back, sent);
    assert_eq!(
        back.compensator, file.settings.compensator,
        "the file's model"
    );
    assert_eq!(back.observer, file.settings.observer);
    assert_eq!(back.ranges, file.settings.ranges, "the file's ranges");
    assert_eq!(back.drive, file.settings.drive);
    assert_eq!(back.sensor, board.sensor, "the board's sensor kept");
    assert_eq!(back.feedback, board.feedback, "the board's gains kept");
    assert_eq!(back.mode, Mode::OpenLoop, "the file's mode");
    let s = client.status().unwrap();
    assert_eq!(s.mode(), Mode::OpenLoop);
    assert!(!s.has(twinstack::protocol::messages::StatusReport::DEFAULTS));

    // The command line's overrides go on top; a file with a sensor keeps its own.
    let mut with_sensor = file.settings.clone();
    let mut own = board.sensor.unwrap();
    own.displacement_at_zero = -44.0;
    with_sensor.sensor = Some(own);
    let sent = settings_for(
        &load_args(&["--mode", "closed-loop", "--ki", "800"]),
        &with_sensor,
        Some(&board),
    );
    client.load_params(&sent).expect("loaded");
    let back = client.read_params().expect("read back");
    assert_eq!(back.sensor, Some(own), "the file's sensor, not the board's");
    assert_eq!(back.feedback.unwrap().ki, 800.0);
    assert_eq!(back.feedback.unwrap().kp, board.feedback.unwrap().kp);
    assert_eq!(back.mode, Mode::ClosedLoop);
    assert_eq!(client.status().unwrap().mode(), Mode::ClosedLoop);
}

/// `load --preview` takes the resonance the file holds (what `calibrate` measured) into the
/// board's preview, which the board then runs; a file without one is refused by name, a later
/// file without a preview keeps the board's, and `--no-preview` turns it off.
#[test]
fn load_preview_runs_the_file_s_resonance_on_the_board_and_no_preview_turns_it_off() {
    let m = pi_model();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("p.json");
    let mut file = ParamFile::from_model(&m, "um", None);
    file.save(&path).unwrap();
    let (plain, _) = ParamFile::load(&path).unwrap();
    let args = load_args(&["--preview"]);
    let e = with_preview(&args, &plain).unwrap_err().to_string();
    assert!(
        e.contains("p.json") && e.contains("--preview needs the stage's resonance"),
        "{e}"
    );
    file.resonance = Some(Resonance::new(21_807.0, 0.0172).unwrap());
    file.save(&path).unwrap();
    let (measured, _) = ParamFile::load(&path).unwrap();
    let with = with_preview(&args, &measured).unwrap();
    assert_eq!(
        with.preview,
        Some(PreviewDesign {
            frequency_hz: 21_807.0,
            damping: 0.0172
        })
    );
    // Without the flag the file's settings are as they are.
    assert_eq!(
        with_preview(&load_args(&[]), &measured).unwrap().preview,
        None
    );

    let mut client = Client::new(SimDevice::new(SimDeviceConfig::paper()).expect("device"));
    let board = client.read_params().unwrap();
    let sent = settings_for(&args, &with, Some(&board));
    client.load_params(&sent).expect("loaded");
    let back = client.read_params().unwrap();
    assert_eq!(back.preview, with.preview, "the board runs it");
    // A file without a preview keeps the board's; --no-preview takes it away.
    let kept = settings_for(&load_args(&[]), &plain.settings, Some(&back));
    assert_eq!(kept.preview, with.preview);
    let off = settings_for(&load_args(&["--no-preview"]), &plain.settings, Some(&back));
    client.load_params(&off).expect("loaded");
    assert_eq!(client.read_params().unwrap().preview, None);
    // One at half the board's rate is refused by the board, on its field.
    let mut fast = with.clone();
    fast.preview = Some(PreviewDesign {
        frequency_hz: 1.0e6,
        damping: 0.0172,
    });
    let e = client.load_params(&settings_for(&load_args(&[]), &fast, Some(&back)));
    assert!(format!("{e:?}").contains("PreviewFrequency"), "{e:?}");
}

#[test]
fn the_board_s_refusal_reaches_the_user_as_one_clear_line() {
    // A valid file the (fake) board refuses: the NACK's reason is printed, exit code 1.
    let dir = tempfile::tempdir().unwrap();
    let file = ParamFile::from_model(&pi_model(), "um", None);
    let path = dir.path().join("p.json");
    std::fs::write(&path, file.to_json()).unwrap();
    let board = hal_sim_fake::start();
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args(["load", "--port", &board.0, "--params"])
        .arg(&path)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains(
            "the board refused LoadParams: refused: compensator.weights[0] makes the model \
             non-invertible; nothing was applied"
        ),
        "{err}"
    );
    assert_eq!(err.lines().count(), 1, "{err}");
}

/// The fake board on a pty, answering in a thread for the rest of the test process.
mod hal_sim_fake {
    use serialport::{SerialPort, TTYPort};
    use std::io::{Read, Write};
    use std::time::Duration;

    use crate::support::fake_board;

    pub struct Pty(pub String);

    pub fn start() -> Pty {
        let (mut master, slave) = TTYPort::pair().unwrap();
        let path = slave.name().unwrap();
        drop(slave);
        master.set_timeout(Duration::from_millis(5)).unwrap();
        std::thread::spawn(move || {
            let mut board = fake_board::FakeBoard::new(100, 1000.0);
            let mut buf = [0u8; 1024];
            loop {
                if let Ok(n) = master.read(&mut buf) {
                    fake_board::Transport::send(&mut board, &buf[..n]).unwrap();
                }
                let out: Vec<u8> = board.out.drain(..).collect();
                if !out.is_empty() && master.write_all(&out).is_err() {
                    return;
                }
            }
        });
        Pty(path)
    }
}
