//! `twinstack stream --resonance-hz F --resonance-damping Z` on the virtual board (a separate
//! process over TCP, as a lab's board): refused, with nothing sent, where the shaped setpoints
//! would not be what the board does with them (in bypass, setpoints interpolated over several
//! ticks); in open loop and in closed loop the board plays the setpoints shaped
//! (`twinstack_identify::preview::ResonancePreview::shape_stream`, whose own tests hold its
//! refusal of a shaped value outside the range), as its recorder shows.

#[path = "support/tool.rs"]
mod tool;
#[path = "support/virtual_board_process.rs"]
mod virtual_board_process;

use tool::{text, twinstack as twinstack_bin};

/// A 250 Hz triangle of ±0.5 about 0, one setpoint a tick at 50 kHz: 200 a period.
fn triangle(n: usize) -> Vec<f64> {
    (0..n)
        .map(|k| {
            let phase = (k % 200) as f64 / 200.0;
            if phase < 0.5 {
                -0.5 + 2.0 * phase
            } else {
                1.5 - 2.0 * phase
            }
        })
        .collect()
}

#[test]
fn stream_with_a_preview_plays_the_shaped_setpoints_in_open_and_closed_loop_and_refuses_otherwise()
{
    let (_board, port) = virtual_board_process::start(&["--speed", "0"]);
    let dir = tempfile::tempdir().unwrap();
    let x = triangle(2000);
    let rows: String = x.iter().map(|v| format!("{v}\n")).collect();
    let data = dir.path().join("triangle.csv");
    std::fs::write(&data, format!("setpoint\n{rows}")).unwrap();
    let d = data.to_str().unwrap();
    let resonance = ["--resonance-hz", "21800", "--resonance-damping", "0.017"];
    let stream = |extra: &[&str]| {
        let mut args = vec!["stream", "--port", &port, "--data", d];
        args.extend_from_slice(&resonance);
        args.extend_from_slice(extra);
        twinstack_bin(&args)
    };
    // The sequence number the board expects next: unchanged while no setpoint reaches it.
    let next_seq = || {
        let o = twinstack_bin(&["status", "--port", &port, "--json"]);
        let v: serde_json::Value = serde_json::from_slice(&o.stdout).expect("status JSON");
        v["next_seq"].as_u64().expect("next_seq")
    };
    let before = next_seq();

    // The board boots in bypass: the shaped setpoints would be the drive.
    let o = stream(&[]);
    let (out, err) = text(&o);
    assert_eq!(o.status.code(), Some(1), "{out}{err}");
    assert!(
        err.contains("the board is in Bypass") && err.contains("nothing was sent"),
        "{err}"
    );
    // Interpolated over five ticks, shaped setpoints are not what the preview assumes.
    let o = stream(&["--divider", "5"]);
    let (_, err) = text(&o);
    assert!(
        err.contains("one setpoint every 5 ticks") && err.contains("nothing was sent"),
        "{err}"
    );
    assert_eq!(next_seq(), before, "no setpoint reached the board");
    assert!(
        twinstack_bin(&["set", "/mode", "OpenLoop", "--port", &port])
            .status
            .success()
    );

    // A stream with the recorder on its setpoints: what the board printed and what it played.
    let played_stream = |name: &str| {
        let run = dir.path().join(name);
        let o = stream(&[
            "--record",
            "setpoint",
            "--record-out",
            run.to_str().unwrap(),
        ]);
        let (out, err) = text(&o);
        assert_eq!(o.status.code(), Some(0), "{out}{err}");
        let csv = std::fs::read_to_string(&run).unwrap();
        let recorded: Vec<f64> = csv
            .lines()
            .skip(1)
            .map(|l| l.split(',').nth(1).unwrap().parse().unwrap())
            .collect();
        assert!(recorded.len() >= 1000, "{} frames", recorded.len());
        (err, recorded)
    };

    // Open loop: the board plays the shaped setpoints (its recorder's setpoint column).
    let (err, recorded) = played_stream("run.csv");
    assert!(
        err.contains("setpoints shaped for a resonance at 21800 Hz"),
        "{err}"
    );
    let settings: twinstack::config::settings::Settings =
        serde_json::from_slice(&twinstack_bin(&["params", "--port", &port]).stdout)
            .expect("params JSON");
    let r = &settings.ranges;
    let to_um = |q: i16| r.norm_to_output(q as f64 / 32768.0);
    let q: Vec<i16> = x.iter().map(|&v| (v * 32768.0).round() as i16).collect();
    let shaped = twinstack_identify::preview::ResonancePreview::new(21_800.0, 0.017, 50_000.0)
        .unwrap()
        .shape_stream(&q, twinstack::control::mode_switch::Mode::OpenLoop, 1)
        .unwrap();
    let lsb = r.output_half_span() / 32768.0;
    let off = |a: &[f64], b: &[i16]| {
        a.iter()
            .zip(b)
            .map(|(a, &b)| (a - to_um(b)).abs())
            .fold(0.0, f64::max)
    };
    let played = off(&recorded, &shaped);
    assert!(
        played <= 2.0 * lsb,
        "the recorded setpoints are the shaped ones: {played} um"
    );
    // And not the file's: the corners were shaped.
    assert!(off(&recorded, &q) > 100.0 * lsb);

    // Closed loop: the same shaped setpoints, which the feedback follows as the compensator
    // does (what that does to the tracking: `twinstack closed-loop --preview`).
    let o = twinstack_bin(&["set", "/mode", "ClosedLoop", "--port", &port]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}{err}");
    let (_, recorded) = played_stream("closed.csv");
    let played = off(&recorded, &shaped);
    assert!(
        played <= 2.0 * lsb,
        "closed loop, the recorded setpoints are the shaped ones: {played} um"
    );
}
