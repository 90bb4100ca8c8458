//! The board commands (`status`, `stream`, `load`, `waveform`, `stop`, `record`) as a user
//! runs them: over a pty to a scripted fake board, and with bad input of every kind (a
//! missing or busy port, a bad baud rate, a bad CSV, a bad parameter file, out-of-range
//! flags): a one-line error, a non-zero exit, no panic, and nothing sent.

use serialport::{SerialPort, TTYPort};
use std::io::{Read, Write};
use std::path::Path;
use std::process::{Command, Output};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use support::fake_board::FakeBoard;

#[path = "../../link/tests/support/mod.rs"]
mod support;

fn twinstack_bin(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args(args)
        .output()
        .expect("twinstack runs")
}

fn text(o: &Output) -> (String, String) {
    (
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

/// Asserts a clean refusal: exit code 1 or 2, one `error:` line containing `needle`.
fn refused(args: &[&str], needle: &str) {
    let o = twinstack_bin(args);
    let (out, err) = text(&o);
    assert!(
        matches!(o.status.code(), Some(1) | Some(2)),
        "{args:?}: exit {:?}\n{out}{err}",
        o.status
    );
    assert!(!err.contains("panicked"), "{args:?} panicked: {err}");
    assert_eq!(err.lines().count(), 1, "{args:?}: {err}");
    assert!(
        err.contains(needle),
        "{args:?}: expected {needle:?} in {err:?}"
    );
}

/// A fake board on the master side of a pty; the CLI opens the slave's path.
struct PtyBoard {
    path: String,
    board: Arc<Mutex<FakeBoard>>,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
    /// Bytes the board received.
    received: Arc<Mutex<usize>>,
}

impl PtyBoard {
    fn start(board: FakeBoard) -> Self {
        let (mut master, slave) = TTYPort::pair().expect("pty pair");
        let path = slave.name().expect("pty has a name");
        // Only the path is handed on: the CLI opens it itself.
        drop(slave);
        master
            .set_timeout(Duration::from_millis(5))
            .expect("timeout");
        let board = Arc::new(Mutex::new(board));
        let stop = Arc::new(AtomicBool::new(false));
        let received = Arc::new(Mutex::new(0usize));
        let (b, s, r) = (board.clone(), stop.clone(), received.clone());
        let thread = std::thread::spawn(move || {
            let mut buf = [0u8; 1024];
            let mut clock = std::time::Instant::now();
            while !s.load(Ordering::Relaxed) {
                if let Ok(n) = master.read(&mut buf) {
                    *r.lock().unwrap() += n;
                    let mut board = b.lock().unwrap();
                    support::fake_board::Transport::send(&mut *board, &buf[..n]).unwrap();
                }
                // The board plays in real time.
                let now = std::time::Instant::now();
                b.lock().unwrap().advance(now - clock);
                clock = now;
                let out: Vec<u8> = b.lock().unwrap().out.drain(..).collect();
                if !out.is_empty() {
                    let _ = master.write_all(&out);
                }
            }
        });
        Self {
            path,
            board,
            stop,
            thread: Some(thread),
            received,
        }
    }
}

impl Drop for PtyBoard {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn write(dir: &Path, name: &str, contents: &str) -> String {
    let p = dir.join(name);
    std::fs::write(&p, contents).unwrap();
    p.to_string_lossy().into_owned()
}

#[test]
fn status_and_stream_over_a_pty() {
    // 5 kHz: 1 000 queued setpoints are 200 ms of play, so the host being descheduled on a
    // loaded machine (60 ms was seen) does not run the queue dry; the 2 000-setpoint file
    // still needs the credit flow (a stream that runs dry exits with 3, tested below).
    let pty = PtyBoard::start(FakeBoard::new(1000, 5_000.0));
    let o = twinstack_bin(&["status", "--port", &pty.path]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}{err}");
    assert!(out.contains("queue_fill 0\ncredits 1000\n"), "{out}");

    let dir = tempfile::tempdir().unwrap();
    let n = 2000;
    let mut csv = String::from("# a ramp\nt,setpoint\n");
    let mut want = Vec::new();
    for i in 0..n {
        let v = (i as f64 / n as f64) * 1.8 - 0.9;
        csv.push_str(&format!("{},{v}\n", i as f64 * 2e-4));
        want.push((v * 32768.0).round() as i16);
    }
    let data = write(dir.path(), "sp.csv", &csv);
    let o = twinstack_bin(&[
        "stream",
        "--port",
        &pty.path,
        "--data",
        &data,
        "--tick-rate",
        "5000",
    ]);
    let (out, err) = text(&o);
    assert_eq!(o.status.code(), Some(0), "{out}{err}");
    assert!(out.contains("underruns during the stream: 0\n"), "{out}");
    assert!(out.contains("streamed 2000 setpoints"), "{out}");
    let board = pty.board.lock().unwrap();
    assert_eq!(board.played, want, "the board played the file, in order");
    assert_eq!(board.over_credit, 0);
}

/// A board that plays far faster than the pty can feed it: the stream completes (every
/// setpoint played, in order) but its queue runs dry on the way, and the exit code says so
/// (3, not 0), as `twinstack stream --help` documents.
#[test]
fn a_stream_that_underran_exits_with_code_3() {
    // 2 MHz ticks with room for 100 setpoints: 50 µs of buffer, far less than a round trip.
    let pty = PtyBoard::start(FakeBoard::new(100, 2_000_000.0));
    let dir = tempfile::tempdir().unwrap();
    let n = 3000;
    let mut csv = String::from("setpoint\n");
    let mut want = Vec::new();
    for i in 0..n {
        let v = (i as f64 / n as f64) * 1.8 - 0.9;
        csv.push_str(&format!("{v}\n"));
        want.push((v * 32768.0).round() as i16);
    }
    let data = write(dir.path(), "fast.csv", &csv);
    let o = twinstack_bin(&["stream", "--port", &pty.path, "--data", &data]);
    let (out, err) = text(&o);
    assert_eq!(o.status.code(), Some(3), "{out}{err}");
    assert!(out.contains("streamed 3000 setpoints"), "{out}");
    assert!(!out.contains("underruns during the stream: 0\n"), "{out}");
    assert!(err.starts_with("warning: the stream completed"), "{err}");
    assert!(err.contains("underrun"), "{err}");
    assert_eq!(pty.board.lock().unwrap().played, want);

    let o = twinstack_bin(&["stream", "--help"]);
    let (out, _) = text(&o);
    assert!(o.status.success());
    for line in [
        "Exit codes:",
        "  0  ",
        "  1  error",
        "  2  usage",
        "  3  completed with underruns",
    ] {
        assert!(out.contains(line), "{line:?} missing from\n{out}");
    }
}

#[test]
fn a_bad_csv_is_refused_with_its_line_and_nothing_is_sent() {
    let pty = PtyBoard::start(FakeBoard::new(300, 50_000.0));
    let dir = tempfile::tempdir().unwrap();
    let bad = write(dir.path(), "bad.csv", "setpoint\n0.1\n0.2\nzero\n");
    refused(
        &["stream", "--port", &pty.path, "--data", &bad],
        "bad.csv:4: column `setpoint`: `zero` is not a number",
    );
    let far = write(dir.path(), "far.csv", "setpoint\n0.1\n-1.2\n");
    refused(
        &["stream", "--port", &pty.path, "--data", &far],
        "far.csv:3: setpoint -1.2 is outside -1…1",
    );
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(
        *pty.received.lock().unwrap(),
        0,
        "nothing reached the board"
    );
    assert!(pty.board.lock().unwrap().played.is_empty());
}

#[test]
fn bad_ports_and_baud_rates_are_told_apart() {
    refused(
        &["status", "--port", "/dev/no-such-tty"],
        "/dev/no-such-tty: no such serial device",
    );
    refused(&["status", "--port", ""], "--port is empty");
    refused(
        &["status", "--port", "/dev/null"],
        "/dev/null: cannot open serial device",
    );
    let pty = PtyBoard::start(FakeBoard::new(300, 50_000.0));
    refused(
        &["status", "--port", &pty.path, "--baud", "300"],
        "baud rate 300 is outside",
    );
    refused(
        &["status", "--port", "unix:/nonexistent/uart.sock"],
        "cannot connect: /nonexistent/uart.sock",
    );
    refused(&["status"], "--port");
}

#[test]
fn a_busy_port_is_refused() {
    let pty = PtyBoard::start(FakeBoard::new(300, 50_000.0));
    // Another program holds the port (exclusively, as twinstack opens it).
    let _holder =
        twinstack_link::serial::SerialTransport::open(&pty.path, 115_200).expect("first open");
    refused(
        &["status", "--port", &pty.path],
        &format!("{}: cannot open serial device", pty.path),
    );
}

#[test]
fn bad_parameter_files_and_flags_are_refused_before_anything_is_sent() {
    let pty = PtyBoard::start(FakeBoard::new(300, 50_000.0));
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("none.json");
    refused(
        &[
            "load",
            "--port",
            &pty.path,
            "--params",
            missing.to_str().unwrap(),
        ],
        "none.json: cannot read",
    );
    let broken = write(dir.path(), "broken.json", "{ \"format\": ");
    refused(
        &["load", "--port", &pty.path, "--params", &broken],
        "broken.json:1:",
    );
    refused(
        &[
            "waveform",
            "--port",
            &pty.path,
            "--shape",
            "sine",
            "--amplitude",
            "0.5",
            "--offset",
            "0.6",
            "--frequency",
            "10",
        ],
        "leaves the normalised range",
    );
    refused(
        &[
            "waveform",
            "--port",
            &pty.path,
            "--shape",
            "square",
            "--amplitude",
            "0.5",
            "--frequency",
            "10",
        ],
        "square",
    );
    refused(
        &[
            "record", "--port", &pty.path, "--signal", "drive", "--count", "0", "--out", "x.csv",
        ],
        "--count must be at least 1",
    );
    // A wait beyond a day, or not a number of seconds (a huge one used to panic converting
    // it to a duration): a usage error naming the value.
    for wait in ["1e20", "nan", "-1", "0"] {
        let wait = format!("--wait-s={wait}");
        refused(
            &[
                "record",
                "--port",
                &pty.path,
                "--signals",
                "setpoint",
                "--samples",
                "10",
                &wait,
                "--out",
                "x.csv",
            ],
            "a number of seconds above 0 and at most 86400",
        );
        refused(
            &[
                "scan",
                "--port",
                &pty.path,
                "--pattern",
                "raster:lines=4,pixels=10",
                &wait,
                "--out",
                "x.png",
            ],
            "a number of seconds above 0 and at most 86400",
        );
    }
    refused(
        &[
            "telemetry",
            "--port",
            &pty.path,
            "--signals",
            "sensor",
            "--duration",
            "1e20",
            "--out",
            "x.csv",
        ],
        "86400",
    );
    // A scan's counts are taken as given or refused, never rounded or clamped.
    for (pattern, needle) in [
        ("raster:lines=4.5", "lines=4.5: must be a whole number"),
        ("raster:lines=99999999", "from 0 to 65535"),
        ("raster:turn=-5", "turn=-5"),
        ("raster:lines=4,lines=5", "lines is given twice"),
        ("spiral:turns=1e9", "turns=1000000000"),
    ] {
        refused(
            &[
                "scan",
                "--port",
                &pty.path,
                "--pattern",
                pattern,
                "--out",
                "x.png",
            ],
            needle,
        );
    }
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(
        *pty.received.lock().unwrap(),
        0,
        "nothing reached the board"
    );
}

#[test]
fn every_command_runs_against_the_simulated_board() {
    let dir = tempfile::tempdir().unwrap();
    let o = twinstack_bin(&["status", "--port", "sim"]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}{err}");
    assert!(out.contains("tick_rate_hz 50000\nmode Bypass\n"), "{out}");
    // The simulated board says it is the simulator (a board says board, QEMU emulator).
    assert!(out.starts_with("image simulator\n"), "{out}");

    // 0.2 s of a 20 Hz sine, every 2nd tick (t steps by 40 µs).
    let mut csv = String::from("t,setpoint\n");
    for i in 0..5000 {
        let t = i as f64 * 4e-5;
        csv.push_str(&format!(
            "{t},{}\n",
            0.8 * (2.0 * std::f64::consts::PI * 20.0 * t).sin()
        ));
    }
    let data = write(dir.path(), "sine.csv", &csv);
    let o = twinstack_bin(&["stream", "--port", "sim", "--data", &data]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}{err}");
    assert!(
        out.contains("streamed 5000 setpoints") && out.contains("at divider 2"),
        "{out}"
    );
    assert!(out.contains("underruns during the stream: 0\n"), "{out}");

    let model = twinstack_identify::stage_model::StageModel {
        hysteresis: twinstack_identify::stage_model::Hysteresis::Pi(
            match twinstack::config::settings::representative_pi(16).unwrap() {
                twinstack::config::settings::Model::PrandtlIshlinskii(p) => p,
                other => panic!("{other:?}"),
            },
        ),
        scaling: twinstack::Scaling::new(0.0, 140.0, -10.0, 80.0).unwrap(),
        output_sign: 1.0,
        sensor_lag_s: 0.0,
        creep: None,
        output_map: None,
    };
    let file = twinstack_identify::param_file::ParamFile::from_model(&model, "um", None);
    let params = write(dir.path(), "p.json", &file.to_json());
    let o = twinstack_bin(&[
        "load",
        "--port",
        "sim",
        "--params",
        &params,
        "--store",
        "open-loop",
    ]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}{err}");
    assert!(
        out.contains("(P–I, 16 operators), mode OpenLoop")
            && out.contains("stored to flash (boots in OpenLoop)"),
        "{out}"
    );

    // `params` reads back the settings in force: the simulated board's, as JSON.
    let o = twinstack_bin(&["params", "--port", "sim"]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}{err}");
    let read: twinstack::config::settings::Settings =
        serde_json::from_str(&out).expect("JSON settings");
    assert_eq!(
        read,
        hal_sim::sim_device::SimDeviceConfig::paper_settings(
            twinstack::config::settings::Mode::Bypass
        )
    );
    // `mode` switches; `recall` reloads the stored settings.
    let o = twinstack_bin(&["mode", "--port", "sim", "open-loop"]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}{err}");
    assert!(out.contains("mode OpenLoop"), "{out}");
    let o = twinstack_bin(&["recall", "--port", "sim"]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}{err}");
    assert!(out.contains("recalled the stored settings"), "{out}");

    let rec = dir.path().join("rec.csv");
    let o = twinstack_bin(&[
        "record",
        "--port",
        "sim",
        "--signal",
        "setpoint",
        "--count",
        "300",
        "--decimation",
        "5",
        "--out",
        rec.to_str().unwrap(),
    ]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}{err}");
    let csv = std::fs::read_to_string(&rec).unwrap();
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines.len(), 301);
    assert_eq!(lines[0], "t,setpoint,setpoint_q2_30");
    assert!(lines[2].starts_with("0.0001,"), "{}", lines[2]);

    for args in [
        &[
            "waveform",
            "--port",
            "sim",
            "--shape",
            "triangle",
            "--amplitude",
            "0.5",
            "--offset",
            "-0.2",
            "--frequency",
            "750",
        ][..],
        &["stop", "--port", "sim"][..],
    ] {
        let o = twinstack_bin(args);
        let (out, err) = text(&o);
        assert!(o.status.success(), "{args:?}: {out}{err}");
    }
}
