//! `twinstack telemetry` and `twinstack stream --telemetry` as a user runs them: against the
//! virtual board over TCP (paced in real time), and on a line too slow for the rate asked,
//! where samples are lost and the command must say so and exit 1. Every wait is bounded.

use std::path::Path;
use std::process::{Command, Output};

#[path = "support/virtual_board_process.rs"]
mod virtual_board_process;

fn twinstack_bin(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .env_remove("TWINSTACK_PORT")
        .args(args)
        .output()
        .expect("twinstack runs")
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// Starts `twinstack virtual-board` on an OS-picked port; returns it and its `tcp:` address.
fn virtual_board() -> (virtual_board_process::VirtualBoard, String) {
    virtual_board_process::start(&[])
}

/// The CSV's rows (header first), each split at the commas.
fn rows(path: &Path) -> Vec<Vec<String>> {
    std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .lines()
        .map(|l| l.split(',').map(str::to_string).collect())
        .collect()
}

#[test]
fn telemetry_and_a_watched_stream_on_the_virtual_board() {
    let dir = tempfile::tempdir().unwrap();
    let (_board, port) = virtual_board();

    // Two signals at 10 kHz for 0.3 s: every sample, in physical units, 100 µs apart.
    let csv = dir.path().join("t.csv");
    let o = twinstack_bin(&[
        "telemetry",
        "--port",
        &port,
        "--signals",
        "sensor,setpoint",
        "--rate",
        "10000",
        "--duration",
        "0.3",
        "--out",
        csv.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(
        text(&o).contains("samples of setpoint, sensor at 10000 Hz"),
        "{}",
        text(&o)
    );
    assert!(dir.path().join("t.png").is_file());
    let r = rows(&csv);
    assert_eq!(r[0], ["t [s]", "setpoint [um]", "sensor [um]"]);
    assert!(r.len() > 3000, "{} rows", r.len());
    let t: Vec<f64> = r[1..].iter().map(|row| row[0].parse().unwrap()).collect();
    assert!(
        t.windows(2).all(|w| (w[1] - w[0] - 1e-4).abs() < 1e-9),
        "samples 100 µs apart, none missing"
    );

    // A streamed run, watched over the same connection: the setpoints the file holds show up
    // in the telemetry's setpoint column (µm on the paper settings' ±45 µm).
    let data = dir.path().join("ramp.csv");
    let mut file = String::from("setpoint\n");
    for k in 0..2000 {
        file.push_str(&format!("{}\n", -0.5 + k as f64 / 2000.0));
    }
    std::fs::write(&data, file).unwrap();
    let watched = dir.path().join("s.csv");
    let o = twinstack_bin(&[
        "stream",
        "--port",
        &port,
        "--data",
        data.to_str().unwrap(),
        "--telemetry",
        "setpoint,left:5000",
        "--telemetry-out",
        watched.to_str().unwrap(),
    ]);
    // 0, or 3 if the stream underran: a real-time board on a loaded machine may run dry,
    // which is the stream's matter; a telemetry failure would be 1.
    assert!(
        matches!(o.status.code(), Some(0 | 3)),
        "{:?}: {}",
        o.status,
        text(&o)
    );
    assert!(
        text(&o).contains("samples of setpoint, left at 5000 Hz"),
        "{}",
        text(&o)
    );
    let r = rows(&watched);
    assert_eq!(r[0], ["t [s]", "setpoint [um]", "left [V]"]);
    let setpoint: Vec<f64> = r[1..].iter().map(|row| row[1].parse().unwrap()).collect();
    // The ramp from −22.5 µm to +22.5 µm passes through the telemetry, rising (the board
    // rests at 0 µm before it).
    let start = setpoint
        .iter()
        .position(|&x| x < -22.0)
        .expect("the ramp's first setpoint");
    let during: Vec<f64> = setpoint[start..]
        .iter()
        .copied()
        .skip_while(|&x| x < -22.0)
        .take_while(|&x| x < 22.0)
        .collect();
    assert!(during.len() > 150, "{} samples of the ramp", during.len());
    assert!(during.windows(2).all(|w| w[1] >= w[0]), "{during:?}");
}

#[test]
fn lost_samples_are_reported_and_exit_1() {
    // 115 200 baud carries 11 520 bytes/s: two signals at 10 kHz (about 55 000 bytes/s) do
    // not fit, the board's queue overflows and the frames announce the gaps.
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("t.csv");
    let o = twinstack_bin(&[
        "telemetry",
        "--port",
        "sim",
        "--baud",
        "115200",
        "--signals",
        "setpoint,estimate",
        "--rate",
        "10000",
        "--duration",
        "0.2",
        "--out",
        csv.to_str().unwrap(),
    ]);
    let out = text(&o);
    assert_eq!(o.status.code(), Some(1), "{out}");
    assert!(out.contains("did not arrive"), "{out}");
    assert!(out.contains("dropped on the board"), "{out}");
    // The rest is written, the gaps showing in t.
    let r = rows(&csv);
    assert!(r.len() > 100, "{} rows", r.len());
    let t: Vec<f64> = r[1..].iter().map(|row| row[0].parse().unwrap()).collect();
    assert!(t.windows(2).any(|w| w[1] - w[0] > 2e-4), "no gap in t");
}
