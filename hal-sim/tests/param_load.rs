//! The parameter file `identify` writes → the `LoadParams` request: what converts, what is
//! refused before anything is sent, and a board's refusal at the command line.

use hal_sim::link::param_set::{param_set, DriveOptions, ParamSetError};
use hal_sim::param_file::ParamFile;
use hal_sim::stage_model::{Hysteresis, StageModel};
use twinstack::default_config;
use twinstack::drive::Configuration;
use twinstack::protocol::messages::{Mode, ModelParams};
use twinstack::{DuhemParams, Scaling};

mod support;

fn pi_model() -> StageModel {
    StageModel {
        hysteresis: Hysteresis::Pi(default_config::pi_params(16).unwrap()),
        scaling: default_config::scaling(),
        output_sign: 1.0,
        sensor_lag_s: 0.0,
    }
}

#[test]
fn a_pi_file_converts_with_the_default_drive() {
    let m = pi_model();
    let set = param_set(&m, &DriveOptions::default()).expect("converts");
    let Hysteresis::Pi(p) = &m.hysteresis else {
        unreachable!()
    };
    match &set.model {
        ModelParams::PrandtlIshlinskii {
            thresholds,
            weights,
            ..
        } => {
            assert_eq!(thresholds.len(), 16);
            for (a, b) in weights.iter().zip(p.weights.iter()) {
                assert!((*a as f64 - b).abs() <= 1e-7 * b.abs());
            }
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(set.input_range, [0.0, 140.0]);
    assert_eq!(set.output_range, [0.0, 70.0]);
    assert_eq!(set.voltage_limits, [0.0, 140.0]);
    assert_eq!(set.bias, 70.0);
    assert_eq!(set.mode, Mode::OpenLoop);
    assert_eq!(set.configuration, Configuration::Differential);
}

#[test]
fn a_duhem_file_converts() {
    let m = StageModel {
        hysteresis: Hysteresis::Duhem(default_config::duhem_params()),
        ..pi_model()
    };
    let set = param_set(&m, &DriveOptions::default()).expect("converts");
    assert!(matches!(set.model, ModelParams::Duhem { alpha, .. } if alpha == 0.02));
}

#[test]
fn what_the_board_could_not_run_is_refused_before_sending() {
    // A closed loop on an inverted sensor.
    let inverted = StageModel {
        output_sign: -1.0,
        ..pi_model()
    };
    let closed = DriveOptions {
        mode: Mode::ClosedLoop,
        ..DriveOptions::default()
    };
    assert!(matches!(
        param_set(&inverted, &closed),
        Err(ParamSetError::InvertedSensor)
    ));
    assert!(param_set(&inverted, &DriveOptions::default()).is_ok());
    // Closed loop without feedback gains.
    let no_fb = DriveOptions {
        feedback: None,
        ..closed
    };
    assert!(matches!(
        param_set(&pi_model(), &no_fb),
        Err(ParamSetError::ClosedLoopWithoutFeedback)
    ));
    // Bias outside the voltage limits.
    let bias = DriveOptions {
        bias: 150.0,
        ..DriveOptions::default()
    };
    assert!(matches!(
        param_set(&pi_model(), &bias),
        Err(ParamSetError::Drive(_))
    ));
    // Feedback limit beyond the drive range.
    let fb = DriveOptions {
        feedback: Some([0.2, 0.01, 1.5]),
        ..DriveOptions::default()
    };
    assert!(matches!(
        param_set(&pi_model(), &fb),
        Err(ParamSetError::Feedback(_))
    ));
    // A range f32 cannot hold.
    let huge = StageModel {
        hysteresis: Hysteresis::Duhem(DuhemParams {
            alpha: 1e-40,
            beta: 1e38,
            gamma: 1e38,
            offset: 0.0,
        }),
        scaling: Scaling::new(0.0, 140.0, 0.0, 1e40).unwrap(),
        ..pi_model()
    };
    let e = param_set(&huge, &DriveOptions::default()).unwrap_err();
    assert!(
        matches!(
            e,
            ParamSetError::NotRepresentable {
                field: "output_range",
                ..
            }
        ),
        "{e}"
    );
}

#[test]
fn the_f32_rounding_is_checked_with_the_library_s_own_validation() {
    // Two thresholds 1e-9 V apart survive f64 validation but collapse to one f32.
    let p = twinstack::PiParams::new(0.0, 0.0, &[0.0, 1.0, 1.0 + 1e-9], &[0.3, 0.1, 0.1]).unwrap();
    let m = StageModel {
        hysteresis: Hysteresis::Pi(p),
        ..pi_model()
    };
    m.check().expect("valid in f64");
    let e = param_set(&m, &DriveOptions::default()).unwrap_err();
    assert!(
        e.to_string()
            .contains("threshold of operator 3 does not exceed the one before it"),
        "{e}"
    );
}

#[test]
fn the_board_s_refusal_reaches_the_user_as_one_clear_line() {
    // A valid file the (fake) board refuses: the NACK's reason is printed, exit code 1.
    let dir = tempfile::tempdir().unwrap();
    let file = ParamFile::from_model(&pi_model(), "um", None).unwrap();
    let path = dir.path().join("p.json");
    std::fs::write(&path, file.to_json()).unwrap();
    let board = hal_sim_fake::start();
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_hal-sim"))
        .args(["load", "--port", &board.0, "--params"])
        .arg(&path)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("the board refused LoadParams: parameters refused: not invertible"),
        "{err}"
    );
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
