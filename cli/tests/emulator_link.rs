//! The host tools drive the firmware's emulator image in QEMU over its UART: the same
//! `Client`, streamer, parameter load and recorder read-back as with a real board (USART1 on a
//! Unix socket, `--port unix:SOCK`): status, a parameter load from an `identify` file, a
//! deliberately corrupted frame NACKed with nothing lost, a streamed record played in full,
//! and a recorder capture that holds what was streamed; then the `twinstack` binary itself.
//!
//! Builds the `emulator` image into `target/firmware` and installs the Rust target and
//! `qemu-system-arm` if they are missing (the root crate's `tests/support`).

#[path = "../../tests/support/mod.rs"]
mod support;
#[path = "support/view_client.rs"]
mod view_client;

use hal_sim::port::{self, PortSpec};
use std::path::PathBuf;
use std::process::Child;
use std::time::{Duration, Instant};
use twinstack_identify::param_file::ParamFile;
use twinstack_identify::stage_model::{Hysteresis, StageModel};
use twinstack_link::client::{Client, LinkError};
use twinstack_link::streamer::{stream_setpoints, StreamOptions};
use twinstack_link::Transport;

/// Values the stream's capture records: the emulator's whole recorder (its 19 456 SRAM slots,
/// two per value; QEMU models no CCM RAM, the board's other 32 768).
const RECORD_VALUES: u32 = 9_728;
use twinstack::protocol::frame::{self, FrameError, MAX_ENCODED};
use twinstack::protocol::messages::{
    Image, Mode, NackReason, RecordRequest, Request, Response, SetpointBatch, Signal, StatusReport,
    StreamControl, UnderrunPolicy, WaveShape, Waveform,
};

/// QEMU running the emulator image with USART1 on a Unix socket; killed on drop.
struct Qemu {
    child: Child,
    elf: PathBuf,
    scratch: PathBuf,
    socket: PathBuf,
}

impl Drop for Qemu {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.scratch);
    }
}

fn boot() -> Qemu {
    boot_image(support::build_image(
        support::FIRMWARE,
        "twinstack-emu",
        &["emulator"],
    ))
}

fn boot_image(elf: PathBuf) -> Qemu {
    // One directory per boot: the tests of this file run in parallel threads of one process,
    // and a directory named after the process alone would be removed under the other's QEMU.
    static BOOTS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let boot = BOOTS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let scratch =
        std::env::temp_dir().join(format!("twinstack-host-link-{}-{boot}", std::process::id()));
    let _ = std::fs::remove_dir_all(&scratch);
    std::fs::create_dir_all(&scratch).expect("scratch directory");
    let socket = scratch.join("uart.sock");
    let mut cmd = support::emulator_command(&elf);
    cmd.arg("-chardev")
        .arg(format!(
            "socket,id=u1,path={},server=on,wait=on",
            socket.display()
        ))
        .args(["-serial", "chardev:u1"]);
    let child = cmd.spawn().expect("qemu-system-arm starts");
    Qemu {
        child,
        elf,
        scratch,
        socket,
    }
}

/// Opens QEMU's UART socket, waiting up to 20 s for QEMU to create it.
fn open_socket(qemu: &Qemu) -> Box<dyn Transport> {
    let spec = PortSpec::Unix(qemu.socket.clone());
    let start = Instant::now();
    let transport = loop {
        match port::open(&spec, 0) {
            Ok(t) => break t,
            Err(e) if start.elapsed() > Duration::from_secs(20) => {
                panic!("QEMU's UART socket never accepted: {e}")
            }
            Err(_) => std::thread::sleep(Duration::from_millis(50)),
        }
    };
    transport
}

/// Connects to the socket and asks for the status until the firmware answers (it enables
/// USART1 a moment after boot; bytes before that are lost).
fn connect(qemu: &Qemu) -> Client<Box<dyn Transport>> {
    let start = Instant::now();
    let transport = open_socket(qemu);
    let mut client = Client::new(transport);
    client.set_timeout(Duration::from_millis(300));
    loop {
        client.resync(Duration::from_millis(50)).expect("resync");
        if let Ok(s) = client.status() {
            // The wrong image answers too (the emulator image on a board would): it says
            // which it is.
            assert_eq!(
                s.image(),
                Image::Emulator,
                "QEMU runs {}, which reports itself as the {} image, not the emulator image \
                 (twinstack-emu, `cargo build-emu`)",
                qemu.elf.display(),
                s.image().name()
            );
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "{} never answered a status request in 20 s: a board image (twinstack-fw) booted \
             in QEMU never does (it waits for a crystal QEMU does not model); QEMU needs the \
             emulator image (twinstack-emu, `cargo build-emu`)",
            qemu.elf.display()
        );
    }
    client.set_timeout(Duration::from_secs(5));
    client
}

/// `twinstack load`'s arguments with nothing overridden.
fn load_args() -> twinstack_cli::commands::load::Args {
    use clap::Parser;
    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        load: twinstack_cli::commands::load::Args,
    }
    Cli::try_parse_from(["load", "--port", "unused", "--params", "p.json"])
        .expect("arguments parse")
        .load
}

fn sine(n: usize, hz: f64, rate: f64) -> Vec<i16> {
    (0..n)
        .map(|i| {
            let t = i as f64 / rate;
            (0.9 * (std::f64::consts::TAU * hz * t).sin() * 32768.0).round() as i16
        })
        .collect()
}

#[test]
fn the_host_tools_drive_the_emulated_firmware_over_its_uart() {
    let t0 = Instant::now();
    let qemu = boot();
    let mut client = connect(&qemu);
    eprintln!("booted in {:?}", t0.elapsed());

    // Status: the tick runs.
    let a = client.status().expect("status");
    client.wait(Duration::from_millis(200)).unwrap();
    let b = client.status().expect("status");
    assert!(
        b.ticks > a.ticks,
        "tick counter did not advance: {a:?} {b:?}"
    );
    assert!(b.tick_rate_hz > 0);
    let rate = b.tick_rate_hz as f64;

    // A parameter load from the file `identify` writes (a representative P–I model on the
    // firmware's default ranges), open loop.
    let twinstack::config::settings::Model::PrandtlIshlinskii(pi) =
        twinstack::config::settings::representative_pi(16).unwrap()
    else {
        unreachable!()
    };
    let model = StageModel {
        hysteresis: Hysteresis::Pi(pi),
        scaling: twinstack::config::settings::Settings::default().ranges,
        output_sign: 1.0,
        sensor_lag_s: 0.0,
        creep: None,
        output_map: None,
    };
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("params.json");
    std::fs::write(&path, ParamFile::from_model(&model, "um", None).to_json()).unwrap();
    let (file, _) = ParamFile::load(&path).expect("the file reads back");
    // As `twinstack load` sends it: the file's settings, the board's sensor and gains kept.
    let board = client.read_params().expect("the firmware's settings");
    let set =
        twinstack_cli::commands::load::settings_for(&load_args(), &file.settings, Some(&board));
    client
        .load_params(&set)
        .expect("the firmware takes the load");
    client.wait(Duration::from_millis(20)).unwrap();
    assert_eq!(client.status().unwrap().mode(), Mode::OpenLoop);
    assert_eq!(client.read_params().unwrap(), set, "read back as sent");

    // A batch queued (the stream is stopped), then a corrupted frame: NACKed for its CRC,
    // nothing applied, nothing queued lost, the next frame decodes.
    let s = client.status().unwrap();
    let queued = SetpointBatch {
        seq: s.next_seq,
        samples: (0..30).collect(),
    };
    assert!(matches!(
        client.request(&Request::Setpoints(queued)).unwrap(),
        Response::Ack { .. }
    ));
    let damaged = Request::Setpoints(SetpointBatch {
        seq: s.next_seq.wrapping_add(1),
        samples: (0..50).collect(),
    });
    let mut wire = [0u8; MAX_ENCODED + 1];
    let n = frame::encode(&damaged, &mut wire).unwrap();
    wire[n / 2] ^= 0x20;
    client.send_raw(&wire[..n]).unwrap();
    let nack = client
        .receive(client.timeout())
        .unwrap()
        .expect("an answer");
    assert_eq!(
        nack,
        Response::Nack {
            reason: NackReason::Frame(FrameError::BadCrc)
        }
    );
    let after = client.status().unwrap();
    assert_eq!(after.queue_fill, s.queue_fill + 30);
    assert_eq!(after.crc_errors, s.crc_errors + 1);
    assert_eq!(after.next_seq, s.next_seq.wrapping_add(1));
    // A load the firmware refuses (not invertible) changes nothing.
    let mut bad = set.clone();
    if let Some(twinstack::config::settings::Model::PrandtlIshlinskii(p)) = &mut bad.compensator {
        p.weights[0] = -1.0;
    }
    assert!(matches!(
        client.load_params(&bad),
        Err(LinkError::Nack {
            reason: NackReason::Refused(twinstack::refusal::Refusal {
                field: twinstack::refusal::Field::Compensator(
                    twinstack::refusal::ModelField::Weight(1)
                ),
                rule: twinstack::refusal::Rule::NotInvertible,
            }),
            ..
        })
    ));
    assert_eq!(client.read_params().unwrap(), set, "nothing changed");
    assert_eq!(client.status().unwrap().queue_fill, after.queue_fill);

    // Arm the recorder, then stream 0.03 s of a sine through the streamer (the 30 queued
    // setpoints play first). Every setpoint is accepted and played; the capture holds them
    // in order (an underrun would only repeat a value, so repeats are collapsed first —
    // QEMU's speed is not the board's).
    client
        .arm_recorder(RecordRequest {
            signal: Signal::Setpoint,
            count: RECORD_VALUES,
            decimation: 1,
        })
        .unwrap();
    // 0.03 s (1 500 setpoints, three times the queue): with QEMU's underruns it fits the
    // emulator's recorder.
    let samples = sine((0.03 * rate) as usize, 100.0, rate);
    let options = StreamOptions {
        underrun: Some(UnderrunPolicy::Hold),
        ..StreamOptions::default()
    };
    let r = stream_setpoints(&mut client, &samples, &options, |_| {}).expect("stream");
    assert_eq!(r.accepted, samples.len());
    assert!(r.nacks.is_empty(), "{:?}", r.nacks);
    assert_eq!(r.drained.map(|s| s.queue_fill), Some(0));
    let deadline = Instant::now() + Duration::from_secs(30);
    while client.status().unwrap().recorded < RECORD_VALUES {
        assert!(Instant::now() < deadline, "the capture never completed");
        client.wait(Duration::from_millis(50)).unwrap();
    }
    let values = client
        .read_recording(RECORD_VALUES, |_| {})
        .expect("read back");
    let mut played: Vec<i32> = Vec::new();
    for v in values {
        if played.last() != Some(&v) {
            played.push(v);
        }
    }
    let want: Vec<i32> = samples.iter().map(|&s| (s as i32) << 15).collect();
    let first = played.iter().position(|&v| v == want[0]);
    assert!(
        played.windows(want.len()).any(|w| w == want.as_slice()),
        "the streamed setpoints are not in the capture in order: {} distinct values captured, \
         the first streamed one at {first:?}, last captured {:?}, last streamed {:?}; {r:?}",
        played.len(),
        played.last(),
        want.last()
    );
    drop(client);

    // The command-line tool on the same UART.
    let port = format!("unix:{}", qemu.socket.display());
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args(["status", "--port", &port])
        .output()
        .expect("twinstack runs");
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{out}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(out.contains("mode OpenLoop\n"), "{out}");
    assert!(out.contains("image emulator\n"), "{out}");
}

/// The wrong image in QEMU must not hang silently: the board image waits for a crystal
/// QEMU does not model and never answers; the host's error names the emulator image.
#[test]
fn the_board_image_in_qemu_is_named_in_the_no_response_error() {
    let qemu = boot_image(support::build_image(support::FIRMWARE, "twinstack-fw", &[]));
    let transport = open_socket(&qemu);
    let mut client = Client::new(transport);
    // Longer than the emulator image takes to answer on a loaded machine.
    client.set_timeout(Duration::from_secs(3));
    let e = client
        .status()
        .expect_err("the board image answered in QEMU");
    assert!(matches!(e, LinkError::Timeout { .. }), "{e}");
    let text = e.to_string();
    assert!(
        text.contains("twinstack-emu") && text.contains("cargo build-emu"),
        "{text}"
    );
}

/// Runs the `twinstack` binary with `args`; returns its exit code, stdout and stderr.
fn twinstack_bin(args: &[&str]) -> (Option<i32>, String, String) {
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .env_remove("TWINSTACK_PORT")
        .args(args)
        .output()
        .expect("twinstack runs");
    (
        o.status.code(),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

/// The lab workflow over the real firmware in QEMU, command by command as a user types it
/// (each a new connection to the UART): load → stream (recorded with four signals) → record →
/// params → status, then calibrate. QEMU's ADC is not a stage, so calibrate cannot succeed on
/// it; it must stop cleanly (exit 1, no panic) and say why, with the settings left as loaded.
#[test]
fn the_lab_workflow_runs_command_by_command_on_the_emulated_firmware() {
    let qemu = boot();
    drop(connect(&qemu)); // the firmware answers
    let port = format!("unix:{}", qemu.socket.display());
    let dir = tempfile::tempdir().unwrap();
    let ok = |args: &[&str]| {
        let (code, out, err) = twinstack_bin(args);
        assert_eq!(code, Some(0), "twinstack {args:?}:\n{out}{err}");
        out
    };

    // load: a P–I model on the firmware's default ranges (0…140 V onto 0…70 µm), open loop.
    let twinstack::config::settings::Model::PrandtlIshlinskii(pi) =
        twinstack::config::settings::representative_pi(16).unwrap()
    else {
        unreachable!()
    };
    let model = StageModel {
        hysteresis: Hysteresis::Pi(pi),
        scaling: twinstack::config::settings::Settings::default().ranges,
        output_sign: 1.0,
        sensor_lag_s: 0.0,
        creep: None,
        output_map: None,
    };
    let params = dir.path().join("stage.json");
    std::fs::write(&params, ParamFile::from_model(&model, "um", None).to_json()).unwrap();
    let params = params.to_str().unwrap();
    let out = ok(&["load", "--port", &port, "--params", params]);
    assert!(out.starts_with("loaded "), "{out}");

    // stream 100 setpoints, recorded over the same connection with four signals.
    let mut text = String::from("setpoint\n");
    for i in 0..100 {
        text.push_str(&format!(
            "{}\n",
            0.5 * (std::f64::consts::TAU * i as f64 / 100.0).sin()
        ));
    }
    let data = dir.path().join("sine.csv");
    std::fs::write(&data, text).unwrap();
    let run = dir.path().join("run.csv");
    let out = ok(&[
        "stream",
        "--port",
        &port,
        "--data",
        data.to_str().unwrap(),
        "--record",
        "setpoint,left,sensor,estimate",
        "--record-out",
        run.to_str().unwrap(),
    ]);
    assert!(out.contains("streamed 100 setpoints"), "{out}");
    let csv = std::fs::read_to_string(&run).unwrap();
    assert!(
        csv.starts_with("t [s],setpoint [um],left [V],sensor [um],estimate [um]\n"),
        "{csv}"
    );
    assert_eq!(csv.lines().count(), 101, "100 frames and the header");

    // record: four signals now.
    let now = dir.path().join("now.csv");
    let out = ok(&[
        "record",
        "--port",
        &port,
        "--signals",
        "setpoint,left,right,sensor",
        "--samples",
        "500",
        "--out",
        now.to_str().unwrap(),
    ]);
    assert!(
        out.contains("500 frames of setpoint, left, right, sensor"),
        "{out}"
    );

    // params: what was loaded; status: the emulator image, open loop.
    let loaded: twinstack::config::settings::Settings =
        serde_json::from_str(&ok(&["params", "--port", &port])).expect("params JSON");
    assert_eq!(loaded.mode, Mode::OpenLoop);
    assert_eq!(
        loaded.compensator,
        ParamFile::load(std::path::Path::new(params))
            .unwrap()
            .0
            .settings
            .compensator
    );
    let status: serde_json::Value =
        serde_json::from_str(&ok(&["status", "--port", &port, "--json"])).unwrap();
    assert_eq!(status["image"], "emulator");
    assert_eq!(status["mode"], "open-loop");

    // calibrate: a short excitation; QEMU's ADC does not measure a stage.
    let out_file = dir.path().join("calibrated.json");
    let (code, out, err) = twinstack_bin(&[
        "calibrate",
        "--port",
        &port,
        "--out",
        out_file.to_str().unwrap(),
        "--model",
        "duhem",
        "--frequency",
        "20",
        "--full-cycles",
        "2",
        "--decay-cycles",
        "4",
        "--no-store",
        "--json",
    ]);
    eprintln!("calibrate on the emulator: exit {code:?}\n{out}{err}");
    assert!(!err.contains("panicked"), "{err}");
    match code {
        Some(1) => {
            assert!(
                err.starts_with("error: ")
                    && (err.contains("sensor") || err.contains("does not fit")),
                "the error says why: {err}"
            );
            assert!(!out_file.exists(), "no parameter file after a failure");
            // Nothing was loaded, and the mode calibrate switched to bypass is restored.
            let after: twinstack::config::settings::Settings =
                serde_json::from_str(&ok(&["params", "--port", &port])).unwrap();
            assert_eq!(after, loaded);
        }
        Some(0) => {
            let v: serde_json::Value = serde_json::from_str(&out).expect("JSON");
            assert!(v["tracking_after"]["max_pct"].as_f64().is_some(), "{v}");
        }
        other => panic!("calibrate exited {other:?}: {err}"),
    }
}

/// The dual-stage emulator image (`cargo build-emu-dual`: the firmware's coarse task and
/// supervisor on the library's model of step/dir, encoders and switches, QEMU modelling
/// none of them): home, move, status and the refusals over the UART, then `twinstack coarse`.
#[test]
fn the_coarse_axis_of_the_emulated_firmware_homes_and_moves_over_its_uart() {
    use twinstack::dual_stage::{CoarseState, CoarseStatus};
    use twinstack::protocol::messages::CoarseMove;
    use twinstack::refusal::{Field, Refusal, Rule};
    let qemu = boot_image(support::build_image(
        support::FIRMWARE,
        "twinstack-emu-dual",
        &["emulator", "dual-stage"],
    ));
    let mut client = connect(&qemu);
    let refused = |e: LinkError| match e {
        LinkError::Nack {
            reason: NackReason::Refused(r),
            ..
        } => r,
        e => panic!("not a refusal: {e}"),
    };
    let move_to = |mm: f64| {
        Request::CoarseMove(CoarseMove {
            target_mm: mm,
            velocity_mm_s: 10.0,
            acceleration_mm_s2: 200.0,
        })
    };
    let s = client.coarse_status().expect("coarse status");
    assert_eq!((s.state, s.homed), (CoarseState::Unhomed, false), "{s:?}");
    assert_eq!(
        refused(client.coarse(&move_to(-20.0)).unwrap_err()),
        Refusal::new(Field::CoarseAxis, Rule::NotHomed)
    );
    let settle = |client: &mut Client<Box<dyn Transport>>| -> CoarseStatus {
        let deadline = Instant::now() + Duration::from_secs(60);
        client.wait(Duration::from_millis(20)).unwrap();
        loop {
            let s = client.coarse_status().unwrap();
            if !matches!(
                s.state,
                CoarseState::Homing | CoarseState::Moving | CoarseState::Stopping
            ) {
                return s;
            }
            assert!(Instant::now() < deadline, "still {s:?}");
            client.wait(Duration::from_millis(50)).unwrap();
        }
    };
    client.coarse(&Request::CoarseHome).expect("home");
    let s = settle(&mut client);
    eprintln!("homed: {s:?}");
    assert_eq!(
        (s.state, s.homed, s.faults),
        (CoarseState::Idle, true, 0),
        "{s:?}"
    );
    // The model's home switch is at carriage −1 mm, the reference −24 mm: the axis braked a
    // little past it (5 mm/s at 100 mm/s²: 125 µm).
    assert!(
        (s.position_pm - -24_125_000_000).abs() < 20_000_000,
        "{s:?}"
    );
    assert!(s.switches & CoarseStatus::HOME != 0);
    assert_eq!(
        refused(client.coarse(&move_to(26.0)).unwrap_err()),
        Refusal::new(Field::CoarseTarget, Rule::AtMost(25.0))
    );
    assert_eq!(
        refused(
            client
                .coarse(&Request::CoarseMove(CoarseMove {
                    target_mm: -20.0,
                    velocity_mm_s: 100.0,
                    acceleration_mm_s2: 200.0,
                }))
                .unwrap_err()
        ),
        Refusal::new(Field::CoarseVelocity, Rule::AtMost(15.0))
    );
    client.coarse(&move_to(-20.0)).expect("move");
    let s = settle(&mut client);
    eprintln!("moved: {s:?}");
    assert_eq!((s.state, s.faults), (CoarseState::Idle, 0), "{s:?}");
    // The model's carriage moves in whole microsteps (0.3125 µm) and nothing else moves it.
    assert!((s.position_pm - -20_000_000_000).abs() <= 320_000, "{s:?}");
    // The piezo handed back: its own waveform plays, a move is refused while it does, and the
    // carriage holds.
    assert!(client.status().unwrap().has(StatusReport::COARSE));
    client.coarse(&Request::CoarseRelease).expect("release");
    assert!(!client.status().unwrap().has(StatusReport::COARSE));
    client
        .waveform(Waveform {
            shape: WaveShape::Triangle,
            offset: 0,
            amplitude: 8192,
            frequency_mhz: 20_000,
            decay: None,
        })
        .expect("the piezo's own waveform");
    client.wait(Duration::from_millis(50)).unwrap();
    assert!(client.status().unwrap().has(StatusReport::WAVEFORM));
    assert!(matches!(
        client.coarse(&move_to(-21.0)),
        Err(LinkError::Nack {
            reason: NackReason::Busy,
            ..
        })
    ));
    client.stream(StreamControl::Stop).unwrap();
    let held = client.coarse_status().unwrap();
    assert_eq!(held.state, CoarseState::Idle);
    assert!(
        (held.position_pm - s.position_pm).abs() <= 320_000,
        "{held:?}"
    );
    drop(client);

    // The command-line tool on the same UART.
    let port = format!("unix:{}", qemu.socket.display());
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args([
            "coarse", "move", "--to-mm", "-22.5", "--wait", "--port", &port,
        ])
        .output()
        .expect("twinstack runs");
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{out}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(out.contains("state idle\nhomed yes\n"), "{out}");
    // Within a microstep of the target, as above (the carriage can stop a few nm short).
    let position: f64 = out
        .lines()
        .find_map(|l| l.strip_prefix("position_mm "))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no position_mm line: {out}"));
    assert!((position - -22.5).abs() <= 0.000_32, "{out}");
    // The move took the piezo back.
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args(["coarse", "status", "--port", &port])
        .output()
        .expect("twinstack runs");
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success() && out.contains("piezo coarse\n"),
        "{out}"
    );
}

/// `twinstack tune` on the emulated firmware: the whole protocol path runs (bypass, a sine from
/// the generator, a capture of drive and sensor armed on its start, read back), but QEMU's ADC
/// does not measure a stage, so the sweep must stop at its first frequency with exit 1 saying
/// the sensor did not move, nothing loaded and the board's mode restored.
#[test]
fn tune_runs_its_sweep_on_the_emulated_firmware_and_stops_cleanly_without_a_stage() {
    let qemu = boot();
    drop(connect(&qemu));
    let port = format!("unix:{}", qemu.socket.display());
    let (_, before, _) = twinstack_bin(&["params", "--port", &port]);
    let (code, out, err) = twinstack_bin(&["tune", "--port", &port, "--load", "--json"]);
    eprintln!("tune on the emulator: exit {code:?}\n{out}{err}");
    assert_eq!(code, Some(1), "{out}{err}");
    assert!(!err.contains("panicked"), "{err}");
    assert!(
        err.starts_with("error: ") && err.contains("sensor did not move"),
        "the error says why: {err}"
    );
    let (_, after, _) = twinstack_bin(&["params", "--port", &port]);
    assert_eq!(after, before, "nothing was loaded");
    let (_, status, _) = twinstack_bin(&["status", "--port", &port, "--json"]);
    assert!(status.contains("\"mode\":\"bypass\""), "{status}");
}

/// The largest settings the protocol carries (two generalised P–I models of 32 operators and
/// 8 dead zones, the feedback's notch, the input shaping): the largest frame there is.
fn largest_settings() -> twinstack::config::settings::Settings {
    use twinstack::config::settings::{representative_gpi, Model};
    use twinstack::control::notch::NotchDesign;
    let Model::GeneralisedPi(mut g) = representative_gpi(32).unwrap() else {
        unreachable!()
    };
    g.dead_zones = twinstack::models::generalised_pi::DeadZoneParams::new(
        35.0,
        1.0,
        &[-32.0, -24.0, -16.0, -8.0, 8.0, 16.0, 24.0, 32.0],
        &[-0.1, -0.1, -0.1, -0.05, 0.05, 0.1, 0.15, 0.1],
    )
    .unwrap();
    let mut s = hal_sim::sim_device::SimDeviceConfig::paper_settings(Mode::OpenLoop);
    s.compensator = Some(Model::GeneralisedPi(g.clone()));
    s.observer = Some(Model::GeneralisedPi(g));
    if let Some(f) = s.feedback.as_mut() {
        f.notch = Some(NotchDesign {
            frequency_hz: 1000.0,
            q: 2.0,
            depth: 0.1,
        });
    }
    if let Some(sensor) = s.sensor.as_mut() {
        sensor.drift_limit = Some(0.1);
    }
    s.shaping = Some(NotchDesign {
        frequency_hz: 2_000.0,
        q: 0.5,
        depth: 0.0173,
    });
    s
}

/// A frame as large as the protocol allows, sent in one write at the link's full rate (no
/// pacing), is received whole: the board answers it (accepted or refused on its fields, never
/// a damaged or lost frame), five times in a row, each followed at once by a status request.
#[test]
fn the_largest_load_sent_unpaced_is_received_whole() {
    let qemu = boot();
    let mut client = connect(&qemu);
    let load = Request::LoadParams(largest_settings());
    let mut out = [0u8; MAX_ENCODED + 1];
    let n = frame::encode(&load, &mut out).expect("fits a frame");
    assert!(n > 1_500, "{n} bytes: not the largest frame");
    let mut status = [0u8; 64];
    let m = frame::encode(&Request::Status, &mut status).unwrap();
    let before = client.status().unwrap();
    for attempt in 0..5 {
        // The load and a status request back to back, one write.
        let mut bytes = out[..n].to_vec();
        bytes.extend_from_slice(&status[..m]);
        client.send_raw(&bytes).unwrap();
        let answer = client
            .receive(Duration::from_secs(10))
            .unwrap()
            .unwrap_or_else(|| panic!("attempt {attempt}: the load got no answer"));
        assert!(
            !matches!(
                answer,
                Response::Nack {
                    reason: NackReason::Frame(_)
                }
            ),
            "attempt {attempt}: {answer:?}"
        );
        assert!(
            matches!(
                client.receive(Duration::from_secs(10)).unwrap(),
                Some(Response::Status(_))
            ),
            "attempt {attempt}: the status behind the load was lost"
        );
    }
    let after = client.status().unwrap();
    assert_eq!(after.crc_errors, before.crc_errors);
    assert_eq!(after.frame_errors, before.frame_errors);
}

/// `twinstack view` on the emulated firmware's UART: the page's events carry its telemetry
/// with every sample counted, its status says it is the emulator, a mode the board refuses
/// comes back with the board's reason and a waveform started from the HTTP interface runs.
#[test]
fn the_live_view_shows_the_emulated_firmware() {
    let qemu = boot();
    drop(connect(&qemu)); // it answers; the view takes the UART next
    let port = format!("unix:{}", qemu.socket.display());
    let view = view_client::start_on(&port, &["--signals", "setpoint,sensor", "--rate", "1000"]);
    let addr = view.addr.clone();
    let mut received = 0u64;
    let mut start: Option<u64> = None;
    let (mut switched, mut refused, mut paused) = (false, false, false);
    let evs = view_client::events(&view.addr, |event, v| {
        match event {
            "samples" => {
                start.get_or_insert(v["first"].as_u64().unwrap());
                received += v["n"].as_u64().unwrap();
            }
            "status" if !refused && received > 100 => {
                assert_eq!(v["image"], "emulator", "{v}");
                // No sensor in the emulator's defaults: closed loop is refused with why.
                let (code, answer) =
                    view_client::post(&addr, "/api/mode", r#"{"mode": "closed-loop"}"#);
                assert_eq!(code, 422, "{answer}");
                assert!(
                    answer["error"].as_str().unwrap().contains("feedback"),
                    "{answer}"
                );
                refused = true;
                // The waveform generator, started from the same interface, runs on the board.
                let (code, answer) = view_client::post(
                    &addr,
                    "/api/waveform",
                    r#"{"amplitude": 0.3, "frequency": 20, "shape": "sine", "offset": 0}"#,
                );
                assert_eq!(code, 200, "{answer}");
                switched = true;
            }
            "status"
                if switched
                    && !paused
                    && v["flags"]
                        .as_array()
                        .is_some_and(|f| f.iter().any(|f| f == "waveform")) =>
            {
                view_client::pause(&addr);
                paused = true;
            }
            _ => {}
        }
        paused && v["counts"]["produced"].is_u64()
    });
    view_client::assert_every_sample_arrived(&evs, received, start);
}

/// `twinstack selftest` on the emulator image: the link's echoes pass through QEMU's UART and
/// the safe state is read (overruns there are the host's emulation speed, not a fault); the
/// checks QEMU cannot answer say why they skip — the tick rate (QEMU's timer has no crystal
/// behind it), the loopback (no DAC or ADC modelled), the flash (the image has no parameter
/// storage in QEMU, and says so) and the watchdog (QEMU models none: the image refuses the
/// drill).
#[test]
fn selftest_passes_on_the_emulator_image_and_skips_what_qemu_does_not_model() {
    let qemu = boot();
    drop(connect(&qemu)); // the firmware answers
    let port = format!("unix:{}", qemu.socket.display());
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args(["selftest", "--port", &port, "--echoes", "50", "--json"])
        .output()
        .expect("twinstack runs");
    let out = String::from_utf8_lossy(&o.stdout);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{out}{err}");
    let report: serde_json::Value = serde_json::from_str(out.trim()).expect("one JSON object");
    assert_eq!(report["image"], "emulator");
    let outcome = |name: &str| -> (String, String) {
        let c = report["checks"]
            .as_array()
            .unwrap()
            .iter()
            .find(|c| c["check"] == name)
            .unwrap_or_else(|| panic!("no {name} in {report}"));
        (
            c["outcome"].as_str().unwrap().to_string(),
            c["detail"].as_str().unwrap().to_string(),
        )
    };
    assert_eq!(outcome("link").0, "PASS", "{report}");
    assert_eq!(report["checks"][1]["figures"]["intact"], 50);
    assert_eq!(outcome("safe-state").0, "PASS", "{report}");
    let (tick, why) = outcome("tick-rate");
    assert_eq!(tick, "SKIP");
    assert!(why.contains("no crystal"), "{why}");
    let (loopback, why) = outcome("loopback");
    assert_eq!(loopback, "SKIP");
    assert!(why.contains("no DAC"), "{why}");
    let (flash, why) = outcome("flash");
    assert_eq!(flash, "SKIP");
    assert!(why.contains("no parameter storage"), "{why}");
    let (watchdog, why) = outcome("watchdog");
    assert_eq!(watchdog, "SKIP");
    assert!(
        why.contains("no watchdog to drill, and says so (QEMU models none)"),
        "{why}"
    );
    // It said so, and it runs on: the drill was refused, not started.
    let mut client = connect(&qemu);
    let s = client
        .status()
        .expect("the board answers after the selftest");
    assert!(!s.has(StatusReport::WATCHDOG_RESET));
}
