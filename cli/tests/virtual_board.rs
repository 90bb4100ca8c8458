//! `twinstack virtual-board`: one simulated board served over TCP on 127.0.0.1, its state kept
//! from one client to the next — through the library's `serve` on a thread, and through the
//! binary as a user runs it. Every wait is bounded.

use hal_sim::sim_device::SimDeviceConfig;
use hal_sim::virtual_board::{serve, ServeReport};
use std::io::{BufRead, BufReader};
use std::net::{SocketAddr, TcpListener};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use twinstack::config::settings::Mode;
use twinstack::protocol::messages::{
    RecordRequest, Request, Response, SetpointBatch, Signal, StatusReport, StreamControl,
    UnderrunPolicy, MAX_BATCH,
};
use twinstack_link::client::Client;
use twinstack_link::socket::SocketTransport;
use twinstack_link::streamer::{stream_setpoints, StreamOptions};

#[path = "support/virtual_board_process.rs"]
mod virtual_board_process;

/// `serve` on a thread, on an OS-picked port of 127.0.0.1.
struct Server {
    address: SocketAddr,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<ServeReport>>,
}

impl Server {
    fn start(speed: f64) -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind 127.0.0.1:0");
        let address = listener.local_addr().unwrap();
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let thread = std::thread::spawn(move || {
            // Behind a USB–serial adapter's latency, as a lab's board is.
            let config = SimDeviceConfig {
                link: hal_sim::sim_device::LinkDelay::ADAPTER,
                ..SimDeviceConfig::paper()
            };
            serve(listener, config, speed, &flag).expect("serve")
        });
        Self {
            address,
            stop,
            thread: Some(thread),
        }
    }

    fn client(&self) -> Client<SocketTransport> {
        let transport = SocketTransport::tcp(&self.address.to_string()).expect("connect");
        let mut client = Client::new(transport);
        client.set_timeout(Duration::from_secs(5));
        client.resync(Duration::from_millis(20)).expect("resync");
        client
    }

    /// Stops the server (bounded: it checks the flag every turn) and returns its report.
    fn stop(mut self) -> ServeReport {
        self.stop.store(true, Ordering::Relaxed);
        let thread = self.thread.take().unwrap();
        let deadline = Instant::now() + Duration::from_secs(10);
        while !thread.is_finished() {
            assert!(Instant::now() < deadline, "the server did not stop");
            std::thread::sleep(Duration::from_millis(5));
        }
        thread.join().expect("the server thread")
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

/// Values captured by the recorder in the first test (ticks, 50 kHz).
const CAPTURE: u32 = 15_000;

/// `n` setpoints of a ±0.9 sine, Q1.15.
fn sine(n: usize) -> Vec<i16> {
    (0..n)
        .map(|i| {
            let phase = 2.0 * std::f64::consts::PI * i as f64 / 100.0;
            (0.9 * phase.sin() * 32768.0).round() as i16
        })
        .collect()
}

#[test]
fn the_board_keeps_its_state_from_one_client_to_the_next() {
    // Twice real time: fast, yet a record of 0.3 s of board time spans ~150 ms of wall time
    // between the requests that arm it and start the stream, even on a loaded host (at four
    // times, 75 ms, a host busy with a build beside it missed the start).
    let server = Server::start(2.0);

    // First client: loads open-loop settings, then leaves.
    let loaded = SimDeviceConfig::paper_settings(Mode::OpenLoop);
    let (first, read_back) = {
        let mut client = server.client();
        let first = client.status().expect("status");
        assert_eq!(first.tick_rate_hz, 50_000);
        assert_eq!(first.mode(), Mode::Bypass, "the board boots in bypass");
        client.load_params(&loaded).expect("loaded");
        let read_back = client.read_params().expect("read back");
        assert_eq!(read_back.mode, Mode::OpenLoop);
        (first, read_back)
    };

    // Second client: the same board, the settings still loaded, its clock still running.
    let mut client = server.client();
    assert_eq!(client.read_params().expect("read"), read_back);
    assert_eq!(read_back, loaded, "read back as loaded");
    let second = client.status().expect("status");
    assert_eq!(second.mode(), Mode::OpenLoop);
    assert!(
        second.ticks.wrapping_sub(first.ticks) > 0,
        "{} → {}",
        first.ticks,
        second.ticks
    );

    // While it is connected, a second connection is closed at once (one client at a time).
    {
        let mut other =
            Client::new(SocketTransport::tcp(&server.address.to_string()).expect("connect"));
        other.set_timeout(Duration::from_secs(5));
        assert!(other.status().is_err(), "two clients at once");
    }

    // A short record queued while the stream is stopped, the recorder armed, the stream
    // started: the capture holds every setpoint, in order.
    let samples = sine(400);
    let s = client.status().unwrap();
    assert_eq!(s.queue_fill, 0);
    let mut seq = s.next_seq;
    for chunk in samples.chunks(MAX_BATCH) {
        let batch = SetpointBatch {
            seq,
            samples: chunk.iter().copied().collect(),
        };
        assert!(matches!(
            client.request(&Request::Setpoints(batch)).unwrap(),
            Response::Ack { .. }
        ));
        seq = seq.wrapping_add(1);
    }
    assert_eq!(client.status().unwrap().queue_fill as usize, samples.len());
    client
        .stream(StreamControl::Underrun(UnderrunPolicy::Hold))
        .unwrap();
    client
        .arm_recorder(RecordRequest {
            signal: Signal::Setpoint,
            count: CAPTURE,
            decimation: 1,
        })
        .expect("armed");
    client.stream(StreamControl::Start).expect("started");
    let deadline = Instant::now() + Duration::from_secs(20);
    while client.status().unwrap().recorded < CAPTURE {
        assert!(Instant::now() < deadline, "the capture did not finish");
        client.wait(Duration::from_millis(5)).unwrap();
    }
    client.stream(StreamControl::Stop).unwrap();
    assert_eq!(client.status().unwrap().queue_fill, 0, "played out");

    // The streamer, through credits (a record longer than the queue).
    let long = sine(twinstack::control_loop::SETPOINT_CAPACITY + 3000);
    let options = StreamOptions {
        underrun: Some(UnderrunPolicy::Hold),
        ..StreamOptions::default()
    };
    let r = stream_setpoints(&mut client, &long, &options, |_| {}).expect("stream");
    assert_eq!(r.accepted, long.len());
    assert!(r.nacks.is_empty(), "{:?}", r.nacks);
    assert!(r.capacity < long.len(), "{r:?}");
    assert_eq!(r.drained.expect("drained").queue_fill, 0);
    drop(client);

    // Third client: reads the capture the second one made.
    let mut client = server.client();
    let values = client.read_recording(CAPTURE, |_| {}).expect("read back");
    let want: Vec<i32> = samples.iter().map(|&s| (s as i32) << 15).collect();
    assert!(
        values.windows(want.len()).any(|w| w == want.as_slice()),
        "the streamed setpoints are not in the capture in order"
    );
    let last = client.status().unwrap();
    assert!(!last.has(StatusReport::STREAMING));
    drop(client);

    let report = server.stop();
    assert_eq!(report.clients, 3, "{report:?}");
    assert_eq!(report.refused, 1, "{report:?}");
    assert!(report.ticks >= last.ticks as u64, "{report:?}");
}

#[test]
fn real_time_pacing_runs_the_board_at_the_wall_clock() {
    let server = Server::start(1.0);
    let mut client = server.client();
    let a = client.status().unwrap();
    let t0 = Instant::now();
    std::thread::sleep(Duration::from_millis(300));
    let b = client.status().unwrap();
    let wall = t0.elapsed().as_secs_f64();
    drop(client);
    server.stop();
    let board = b.ticks.wrapping_sub(a.ticks) as f64 / 50_000.0;
    // Never faster than the wall clock (+ one step and a status round trip); not stalled.
    assert!(board <= wall + 0.05, "board {board} s in {wall} s");
    assert!(board >= 0.05, "board {board} s in {wall} s");
}

#[test]
fn a_new_client_never_gets_the_answers_meant_for_the_last() {
    let server = Server::start(1.0);
    // A client asks five times and leaves before any answer is back (the adapter's 16 ms each
    // way): its requests and answers are still on the line when the next client connects.
    {
        let mut client = server.client();
        client
            .send_together(&vec![Request::Status; 5])
            .expect("sent");
    }
    for _ in 0..3 {
        let mut client = server.client();
        let status = client.status().expect("the answer to this status");
        assert_eq!(status.tick_rate_hz, 50_000);
        // The next answer is this request's own (an Ack), not a late Status.
        client
            .stream(StreamControl::Stop)
            .expect("the answer to this stop");
        client
            .send_together(&vec![Request::Status; 5])
            .expect("sent");
    }
    server.stop();
}

/// The binary: prints the address it listens on; killed when dropped.
struct Binary(Child);

impl Drop for Binary {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn twinstack_bin(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args(args)
        .output()
        .expect("twinstack runs")
}

/// `twinstack args`, which must succeed: its standard output (the failure shows both).
fn twinstack_ok(args: &[&str]) -> String {
    let o = twinstack_bin(args);
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        o.status.success(),
        "{args:?}: {out}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    out
}

fn status_field(out: &str, name: &str) -> String {
    out.lines()
        .find_map(|l| l.strip_prefix(&format!("{name} ")))
        .unwrap_or_else(|| panic!("no {name} in {out}"))
        .to_string()
}

#[test]
fn the_cli_serves_one_board_to_successive_commands() {
    let mut child = Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args([
            "virtual-board",
            "--listen",
            "tcp:127.0.0.1:0",
            "--speed",
            "0",
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("twinstack virtual-board starts");
    let stdout = child.stdout.take().unwrap();
    let _server = Binary(child);
    // The first line names the address (read on a thread: the wait is bounded).
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut line = String::new();
        let _ = BufReader::new(stdout).read_line(&mut line);
        let _ = tx.send(line);
    });
    let line = rx
        .recv_timeout(Duration::from_secs(20))
        .expect("the server printed its address");
    let port = line
        .split_whitespace()
        .find(|w| w.starts_with("tcp:127.0.0.1:"))
        .unwrap_or_else(|| panic!("no address in {line:?}"));
    assert!(!port.ends_with(":0"), "{line}");

    let o = twinstack_bin(&["status", "--port", port]);
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        o.status.success(),
        "{out}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert_eq!(status_field(&out, "mode"), "Bypass");
    let ticks: u64 = status_field(&out, "ticks").parse().unwrap();

    let o = twinstack_bin(&["mode", "open-loop", "--port", port]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    // The next command finds the mode the last one set, on a board that kept running.
    let o = twinstack_bin(&["status", "--port", port]);
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        o.status.success(),
        "{out}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert_eq!(status_field(&out, "mode"), "OpenLoop");
    let later: u64 = status_field(&out, "ticks").parse().unwrap();
    assert!(later > ticks, "{ticks} → {later}");
}

#[test]
fn the_cli_refuses_a_listen_address_that_is_not_tcp() {
    for (args, needle) in [
        (&["virtual-board", "--listen", "sim"][..], "tcp:HOST:PORT"),
        (
            &["virtual-board", "--listen", "tcp:127.0.0.1:0", "--speed=-1"][..],
            "--speed",
        ),
    ] {
        let o = twinstack_bin(args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{args:?}: {err}");
        assert!(err.contains(needle), "{args:?}: {err}");
    }
}

/// Starts `twinstack virtual-board` as fast as it runs; returns it and its address.
fn start_virtual_board() -> (virtual_board_process::VirtualBoard, String) {
    virtual_board_process::start(&["--speed", "0"])
}

/// The streamed run recorded: stream a 100-sample file and record the streamed run with four
/// signals over the same connection (`stream --record`); the CSV's setpoint is the file, in
/// µm through the board's settings, and the drive and the sensor are in volts and µm
/// consistent with them.
#[test]
fn a_streamed_run_is_recorded_with_four_signals_in_physical_units() {
    let (_server, port) = start_virtual_board();
    let dir = tempfile::tempdir().unwrap();
    // 100 setpoints of a ±0.5 sine, each an exact Q1.15 value.
    let q: Vec<i16> = (0..100)
        .map(|i| {
            (0.5 * (2.0 * std::f64::consts::PI * i as f64 / 100.0).sin() * 32768.0).round() as i16
        })
        .collect();
    let mut text = String::from("setpoint\n");
    for &v in &q {
        text.push_str(&format!("{}\n", v as f64 / 32768.0));
    }
    let data = dir.path().join("sine.csv");
    std::fs::write(&data, text).unwrap();
    let out = dir.path().join("run.csv");
    let stdout = twinstack_ok(&[
        "stream",
        "--port",
        &port,
        "--data",
        data.to_str().unwrap(),
        "--record",
        "setpoint,left,sensor,estimate",
        "--record-out",
        out.to_str().unwrap(),
        "--record-samples",
        "150",
        "--record-pre",
        "10",
    ]);
    assert!(
        stdout.contains("150 frames of setpoint, left, sensor, estimate"),
        "{stdout}"
    );
    let png = std::fs::read(dir.path().join("run.png")).expect("the PNG is written");
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");

    // The settings the board converts with.
    let settings = {
        let transport = SocketTransport::tcp(&port["tcp:".len()..]).expect("connect");
        let mut client = Client::new(transport);
        client.set_timeout(Duration::from_secs(5));
        client.resync(Duration::from_millis(20)).expect("resync");
        client.read_params().expect("params")
    };
    let r = &settings.ranges;

    let csv = std::fs::read_to_string(&out).unwrap();
    let mut lines = csv.lines();
    assert_eq!(
        lines.next(),
        Some("t [s],setpoint [um],left [V],sensor [um],estimate [um]")
    );
    let rows: Vec<Vec<f64>> = lines
        .map(|l| l.split(',').map(|c| c.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 150);
    // 10 frames before the stream's start, one per tick at 50 kHz.
    assert!((rows[10][0]).abs() < 1e-12 && (rows[9][0] + 20e-6).abs() < 1e-12);
    for (row, &v) in rows[10..110].iter().zip(&q) {
        let want = r.norm_to_output(v as f64 / 32768.0);
        assert!(
            (row[1] - want).abs() < 1e-9,
            "setpoint {} µm, file {want} µm",
            row[1]
        );
    }
    // After the file, the output holds its last setpoint.
    let last = r.norm_to_output(q[99] as f64 / 32768.0);
    assert!(rows[110..].iter().all(|row| (row[1] - last).abs() < 1e-9));
    // Bypass: the left stack follows the setpoint across the input range (volts), within a
    // DAC step (150 V / 4095).
    let lsb = 150.0 / 4095.0;
    for row in &rows[10..] {
        let norm = r.output_to_norm(row[1]);
        let want = r.norm_to_input(norm);
        assert!(
            (row[2] - want).abs() <= lsb,
            "left {} V, want {want} V",
            row[2]
        );
    }
    // The sensor and the estimate: in µm on the output range, Q1.15 steps of it, following
    // the drive (correlation with the left stack's volts).
    let corr = |a: &[f64], b: &[f64]| {
        let (ma, mb) = (
            a.iter().sum::<f64>() / a.len() as f64,
            b.iter().sum::<f64>() / b.len() as f64,
        );
        let cov: f64 = a.iter().zip(b).map(|(x, y)| (x - ma) * (y - mb)).sum();
        let va: f64 = a.iter().map(|x| (x - ma).powi(2)).sum();
        let vb: f64 = b.iter().map(|y| (y - mb).powi(2)).sum();
        cov / (va * vb).sqrt()
    };
    let left: Vec<f64> = rows[10..110].iter().map(|row| row[2]).collect();
    for col in [3, 4] {
        let x: Vec<f64> = rows[10..110].iter().map(|row| row[col]).collect();
        for &v in &x {
            assert!(
                v >= r.output_min - 1e-9 && v <= r.output_max + 1e-9,
                "{v} µm"
            );
            let steps = r.output_to_norm(v) * 32768.0;
            assert!(
                (steps - steps.round()).abs() < 1e-6,
                "{v} µm is no Q1.15 step"
            );
        }
        let c = corr(&left, &x);
        assert!(c > 0.9, "column {col}: correlation {c} with the drive");
    }
}

/// `record --arm-only` leaves the port free for the command that triggers the capture (here
/// the waveform generator), and `record --fetch` reads it back with its pre-trigger frames;
/// bad capture requests are refused with what is wrong.
#[test]
fn a_capture_armed_on_the_waveform_start_is_fetched_by_a_later_command() {
    let (_server, port) = start_virtual_board();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("wave.csv");
    let ok = |o: std::process::Output| {
        let stdout = String::from_utf8_lossy(&o.stdout).into_owned();
        assert!(
            o.status.success(),
            "{stdout}{}",
            String::from_utf8_lossy(&o.stderr)
        );
        stdout
    };
    let armed = ok(twinstack_bin(&[
        "record",
        "--port",
        &port,
        "--signals",
        "setpoint,right",
        "--samples",
        "200",
        "--pre",
        "50",
        "--trigger",
        "waveform",
        "--arm-only",
    ]));
    assert!(armed.contains("--fetch"), "{armed}");
    ok(twinstack_bin(&[
        "waveform",
        "--port",
        &port,
        "--shape",
        "sine",
        "--offset",
        "0",
        "--amplitude",
        "0.5",
        "--frequency",
        "1000",
    ]));
    let fetched = ok(twinstack_bin(&[
        "record",
        "--port",
        &port,
        "--fetch",
        "--out",
        out.to_str().unwrap(),
    ]));
    assert!(
        fetched.contains("200 frames of setpoint, right, 50 before the trigger"),
        "{fetched}"
    );
    let csv = std::fs::read_to_string(&out).unwrap();
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some("t [s],setpoint [um],right [V]"));
    let rows: Vec<Vec<f64>> = lines
        .map(|l| l.split(',').map(|c| c.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 200);
    assert!(rows[50][0].abs() < 1e-12);
    // Before the start the output held still; after it, three periods of the sine (0.5 of
    // the half range: ±22.5 µm about the middle of ±45 µm) — the right stack in antiphase.
    assert!(rows[..50]
        .windows(2)
        .all(|w| w[0][1] == w[1][1] && w[0][2] == w[1][2]));
    let after: Vec<f64> = rows[50..].iter().map(|r| r[1]).collect();
    let (lo, hi) = after
        .iter()
        .fold((f64::MAX, f64::MIN), |(lo, hi), &x| (lo.min(x), hi.max(x)));
    assert!(
        (hi - 22.5).abs() < 0.1 && (lo + 22.5).abs() < 0.1,
        "{lo} … {hi}"
    );
    let i_hi = after.iter().position(|&x| x == hi).unwrap();
    let right_hi = rows[50 + i_hi][2];
    assert!(
        right_hi < 40.0,
        "right stack at the setpoint's peak: {right_hi} V"
    );

    // Six signals share the board's capture buffer.
    let six_signals = format!(
        "at most {}",
        twinstack::services::recorder::CAPTURE_SLOTS / 6
    );
    for (args, needle) in [
        (
            &["--signals", "setpoint,volts", "--samples", "10"][..],
            "unknown signal \"volts\"",
        ),
        (
            &["--signals", "setpoint", "--samples", "10", "--pre", "3"][..],
            "--trigger now",
        ),
        (
            &[
                "--signals",
                "setpoint,left,right,sensor,estimate,error",
                "--samples",
                "20000",
            ][..],
            six_signals.as_str(),
        ),
    ] {
        let mut all = vec!["record", "--port", &port, "--out", out.to_str().unwrap()];
        all.extend_from_slice(args);
        let o = twinstack_bin(&all);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{args:?}: {err}");
        assert!(err.contains(needle), "{args:?}: {err}");
    }
}

/// Ten seconds of a full-range triangle streamed by `twinstack stream` to a virtual board in
/// real time, through its default link (an adapter's 16 ms ± 4 ms each way): the board's
/// counter, which the streamer prints, says no tick ran dry.
fn ten_seconds_in_real_time(rate: u32) {
    let (_board, port) = virtual_board_process::start(&["--tick-rate", &rate.to_string()]);
    let dir = tempfile::tempdir().unwrap();
    let n = 10 * rate as usize;
    let mut text = String::with_capacity(10 * n);
    text.push_str("setpoint\n");
    for i in 0..n {
        // ±0.95, 5 000 ticks a ramp.
        let phase = (i % 10_000) as f64 / 5_000.0;
        let v = if phase < 1.0 { phase } else { 2.0 - phase };
        text.push_str(&format!("{:.5}\n", 0.95 * (2.0 * v - 1.0)));
    }
    let data = dir.path().join("triangle.csv");
    std::fs::write(&data, text).unwrap();
    let o = twinstack_bin(&[
        "stream",
        "--port",
        &port,
        "--data",
        data.to_str().unwrap(),
        "--tick-rate",
        &rate.to_string(),
        "--underrun",
        "hold",
    ]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{rate} Hz: {stdout}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(
        stdout.contains(&format!("streamed {n} setpoints")),
        "{rate} Hz: {stdout}"
    );
    assert!(
        stdout.contains("underruns during the stream: 0\n"),
        "{rate} Hz: {stdout}"
    );
}

#[test]
fn ten_seconds_at_50_khz_stream_in_real_time_without_an_underrun() {
    ten_seconds_in_real_time(50_000);
}

#[test]
fn ten_seconds_at_100_khz_stream_in_real_time_without_an_underrun() {
    ten_seconds_in_real_time(100_000);
}

/// `stream --start-on rising`: the queue primed, the input armed, and the stream (and its
/// recording) starts on the simulated camera's frame; with no camera on the input
/// (`--port sim`), the wait ends with exit 1, saying the input is disarmed and the setpoints
/// stay queued.
#[test]
fn a_stream_started_by_the_camera_s_edge_plays_and_without_one_waits_then_says_so() {
    let (_server, port) = virtual_board_process::start(&["--speed", "0", "--camera-hz", "200"]);
    let dir = tempfile::tempdir().unwrap();
    let mut text = String::from("setpoint\n");
    for i in 0..100 {
        text.push_str(&format!("{}\n", 0.4 * (i as f64 / 100.0)));
    }
    let data = dir.path().join("ramp.csv");
    std::fs::write(&data, text).unwrap();
    let out = dir.path().join("run.csv");
    let stdout = twinstack_ok(&[
        "stream",
        "--port",
        &port,
        "--data",
        data.to_str().unwrap(),
        "--start-on",
        "rising",
        "--edge-wait-s",
        "5",
        "--record",
        "setpoint",
        "--record-out",
        out.to_str().unwrap(),
        "--record-samples",
        "120",
        "--record-pre",
        "10",
    ]);
    assert!(
        stdout.contains("underruns during the stream: 0"),
        "{stdout}"
    );
    // The recording starts with the stream, on the edge: before it the setpoint held at the
    // board's rest, from it the ramp.
    let csv = std::fs::read_to_string(&out).unwrap();
    let rows: Vec<Vec<f64>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').map(|c| c.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 120);
    assert!(rows[10][0].abs() < 1e-12, "t = 0 at the stream's start");
    assert!(rows[..10].windows(2).all(|w| w[0][1] == w[1][1]), "held");
    assert!(
        rows[12][1] > rows[11][1] && rows[11][1] > rows[10][1],
        "the ramp plays"
    );

    let o = twinstack_bin(&[
        "stream",
        "--port",
        "sim",
        "--data",
        data.to_str().unwrap(),
        "--start-on",
        "rising",
        "--edge-wait-s",
        "0.05",
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("rising edge did not come within 50ms: the input is disarmed"),
        "{err}"
    );
    let o = twinstack_bin(&[
        "stream",
        "--port",
        "sim",
        "--data",
        "x.csv",
        "--edge-wait-s",
        "nan",
    ]);
    assert_eq!(o.status.code(), Some(2));
}
