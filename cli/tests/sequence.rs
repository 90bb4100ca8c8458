//! TTL-stepped sequences on the in-process board (`SimDevice`: the library's command handler
//! and control loop, the simulated stage, a simulated camera on the trigger input): 10 000
//! positions stepped without a miss, edges faster than the settle time counted early, the
//! edge's own tick writing the first moved DAC sample, the slew limit held on a full-stroke
//! step, and the `sequence` command refusing a hostile positions file by its line.

use std::ops::ControlFlow;
use std::process::Command;
use std::time::Duration;

use hal_sim::sim_camera::CameraConfig;
use hal_sim::sim_device::{SimDevice, SimDeviceConfig};
use twinstack::control::TickFlags;
use twinstack::protocol::messages::{
    Mode, Request, SequenceConfig, SequenceRequest, StatusReport, TriggerEdge,
};
use twinstack::sources::sequence::SETTLED;
use twinstack_link::client::Client;
use twinstack_link::sequence_run::{run_sequence, SequenceOptions};

const TICK: Duration = Duration::from_micros(20);

fn board(camera: Option<CameraConfig>, mode: Mode) -> Client<SimDevice> {
    let config = SimDeviceConfig {
        camera,
        ..SimDeviceConfig::paper()
    };
    let mut client = Client::new(SimDevice::new(config).unwrap());
    client.set_mode(mode).unwrap();
    client
}

/// The paper's stage in open loop without a sensor: the settle window is checked against
/// the setpoint in force (the observer's estimate is computed below the tick).
fn board_without_sensor(camera: Option<CameraConfig>) -> Client<SimDevice> {
    let mut settings = SimDeviceConfig::paper_settings(Mode::OpenLoop);
    settings.sensor = None;
    settings.feedback = None;
    let config = SimDeviceConfig {
        camera,
        stored: Some(settings),
        ..SimDeviceConfig::paper()
    };
    Client::new(SimDevice::new(config).unwrap())
}

fn options(window: f32, settle_ticks: u16) -> SequenceOptions {
    SequenceOptions {
        config: SequenceConfig {
            edge: TriggerEdge::Rising,
            window,
            settle_ticks,
        },
        idle: Duration::from_millis(200),
        poll: Duration::from_millis(5),
        timing: true,
    }
}

/// A Z stack: `n` positions stepping by `step` (wire LSB) up from −0.1 and back.
fn z_stack(n: usize, step: i16) -> Vec<i16> {
    let half = (n / 2) as i32;
    (0..n as i32)
        .map(|k| (-3277 + step as i32 * if k < half { k } else { 2 * half - k }) as i16)
        .collect()
}

#[test]
fn ten_thousand_positions_on_a_camera_s_edges_without_a_miss() {
    // The camera's exposures (10 ticks) start on the settled output.
    let camera = CameraConfig {
        period_ticks: 10,
        frames: 10_000,
        on_settled: true,
    };
    let mut client = board_without_sensor(Some(camera));
    let positions = z_stack(10_000, 1);
    let report = run_sequence(&mut client, &positions, &options(0.002, 10), |_| {
        ControlFlow::Continue(())
    })
    .unwrap();
    let s = report.status;
    assert!(report.complete, "{report:?}");
    assert_eq!((s.steps, s.missed, s.early), (10_000, 0, 0), "{s:?}");
    assert_eq!(client.transport().camera().unwrap().frames_sent(), 10_000);
    assert_eq!(report.timing.map(|t| t.ticks_to_motion), Some(0));
    // Where the last edge sent it, within the window.
    let last = *positions.last().unwrap() as i32;
    assert_eq!(s.target, last << 15);
    let status = client.status().unwrap();
    assert!(!status.has(StatusReport::SEQUENCE), "disarmed at the end");
}

/// The caller stops the wait (Python's Ctrl-C): the sequence is disarmed and the error says
/// how far it got.
#[test]
fn a_stopped_wait_disarms_the_sequence() {
    let camera = CameraConfig {
        period_ticks: 10,
        frames: 100,
        on_settled: true,
    };
    let mut client = board_without_sensor(Some(camera));
    let positions = z_stack(1_000, 1);
    let mut polls = 0;
    let e = run_sequence(&mut client, &positions, &options(0.002, 10), |_| {
        polls += 1;
        if polls > 3 {
            ControlFlow::Break(())
        } else {
            ControlFlow::Continue(())
        }
    })
    .unwrap_err();
    assert!(
        matches!(e, twinstack_link::sequence_run::SequenceError::Stopped { steps } if steps < 1_000),
        "{e}"
    );
    let status = client.status().unwrap();
    assert!(!status.has(StatusReport::SEQUENCE), "disarmed when stopped");
}

#[test]
fn a_sequence_longer_than_the_queue_is_topped_up_as_edges_consume_it() {
    // The queue's capacity, from a board without a camera.
    let capacity = {
        let s = board(None, Mode::Bypass).status().unwrap();
        s.credits as usize + s.queue_fill as usize
    };
    let positions = z_stack(capacity + 5_000, 1);
    let camera = CameraConfig {
        period_ticks: 4,
        frames: positions.len() as u32,
        on_settled: false,
    };
    let mut client = board(Some(camera), Mode::Bypass);
    let report = run_sequence(&mut client, &positions, &options(0.5, 1), |_| {
        ControlFlow::Continue(())
    })
    .unwrap();
    assert!(report.complete, "{report:?}");
    assert_eq!(report.sent, positions.len());
    assert_eq!(report.status.missed, 0, "{:?}", report.status);
}

#[test]
fn edges_faster_than_the_settle_time_are_counted_early_and_edges_past_the_end_missed() {
    // Free-running at 8 ticks a frame; settling takes 40 ticks within the window.
    let camera = CameraConfig {
        period_ticks: 8,
        frames: 20,
        on_settled: false,
    };
    let mut client = board_without_sensor(Some(camera));
    let positions = z_stack(20, 100);
    let mut opts = options(0.002, 40);
    opts.idle = Duration::from_millis(50);
    let report = run_sequence(
        &mut client,
        &positions,
        &opts,
        |_| ControlFlow::Continue(()),
    )
    .unwrap();
    let s = report.status;
    assert_eq!(s.steps, 20);
    // The first edge comes 8 ticks after the arming, every other 8 ticks after the one
    // before: never 40 ticks settled.
    assert_eq!(s.early, 20, "{s:?}");
    assert_eq!(s.missed, 0);
    // Ten frames more than positions: ten edges missed (the stage holds the last one).
    let camera = CameraConfig {
        frames: 30,
        ..camera
    };
    let mut client2 = board_without_sensor(Some(camera));
    let seq = client2.status().unwrap().next_seq;
    client2
        .expect_ack(&Request::PackedSetpoints(
            twinstack::protocol::messages::PackedBatch {
                seq,
                samples: heapless::Vec::from_slice(&positions).unwrap(),
            },
        ))
        .unwrap();
    client2
        .expect_ack(&Request::Sequence(SequenceRequest::Arm(opts.config)))
        .unwrap();
    client2.wait(TICK * 8 * 32).unwrap();
    let s2 = client2.sequence_status().unwrap();
    assert_eq!((s2.steps, s2.missed), (20, 10), "{s2:?}");
    assert_eq!(s2.target, (*positions.last().unwrap() as i32) << 15);
}

#[test]
fn the_edge_s_own_tick_writes_the_first_moved_dac_sample() {
    let mut client = board(None, Mode::OpenLoop);
    let seq = client.status().unwrap().next_seq;
    client
        .expect_ack(&Request::PackedSetpoints(
            twinstack::protocol::messages::PackedBatch {
                seq,
                samples: heapless::Vec::from_slice(&[8000, -8000]).unwrap(),
            },
        ))
        .unwrap();
    client
        .expect_ack(&Request::Sequence(SequenceRequest::Arm(
            options(0.01, 5).config,
        )))
        .unwrap();
    let device = client.transport_mut();
    device.run_for(TICK * 100);
    for _ in 0..2 {
        let held = device.last_report().unwrap();
        device.run_for(TICK);
        assert_eq!(
            device.last_report().unwrap().left,
            held.left,
            "no edge, no move"
        );
        device.set_trigger_input(true);
        device.run_for(TICK);
        let moved = device.last_report().unwrap();
        assert_ne!(
            moved.left, held.left,
            "the tick that sampled the edge moved the DAC"
        );
        assert_eq!(device.control().trigger_levels() & SETTLED, 0);
        device.run_for(TICK * 200);
        device.set_trigger_input(false);
        device.run_for(TICK * 10);
    }
    assert_eq!(device.control().sequence_status().steps, 2);
}

#[test]
fn a_large_step_stays_within_the_slew_limit_without_the_drive_clipping_it() {
    let mut client = board(None, Mode::OpenLoop);
    let seq = client.status().unwrap().next_seq;
    client
        .expect_ack(&Request::PackedSetpoints(
            twinstack::protocol::messages::PackedBatch {
                seq,
                samples: heapless::Vec::from_slice(&[-24000, 24000, -24000]).unwrap(),
            },
        ))
        .unwrap();
    client
        .expect_ack(&Request::Sequence(SequenceRequest::Arm(
            options(0.01, 5).config,
        )))
        .unwrap();
    let device = client.transport_mut();
    // Codes per tick the drive's slew limit allows (Q17.15 codes per tick).
    let slew_codes = (device.control().controller().slew() as f64 / 32768.0).ceil() as i32;
    let mut level = false;
    let mut last = device.last_report().map(|r| r.left.0 as i32);
    let mut largest = 0;
    let mut slew_limited = 0;
    for k in 0..3000 {
        if k % 1000 == 10 {
            level = !level;
            device.set_trigger_input(level);
        }
        device.run_for(TICK);
        let report = device.last_report().unwrap();
        if report.flags.contains(TickFlags::SLEW_LIMIT) {
            slew_limited += 1;
        }
        let left = report.left.0 as i32;
        if let Some(l) = last {
            largest = largest.max((left - l).abs());
        }
        last = Some(left);
    }
    assert_eq!(device.control().sequence_status().steps, 2);
    assert!(
        largest > 0 && largest <= slew_codes,
        "{largest} > {slew_codes}"
    );
    // The move is shaped below the slew limit: the drive never has to clip it.
    assert_eq!(slew_limited, 0);
}

fn twinstack(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args(args)
        .output()
        .expect("twinstack runs")
}

#[test]
fn the_sequence_command_refuses_a_hostile_file_by_its_line_and_runs_a_good_one() {
    let dir = std::env::temp_dir().join(format!("twinstack-sequence-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for (body, needle) in [
        ("setpoint\n0.1\nabc\n", ":3:"),
        ("setpoint\n0.1\n0.2\nNaN\n", ":4:"),
        ("setpoint\n1.5\n", ":2:"),
        ("# a comment\nsetpoint\n0.1\n-1.0001\n", ":4:"),
        ("position\n0.1\n", ":1:"),
        ("setpoint\n", "no setpoints"),
    ] {
        let path = dir.join("bad.csv");
        std::fs::write(&path, body).unwrap();
        let o = twinstack(&[
            "sequence",
            "--port",
            "sim",
            "--data",
            path.to_str().unwrap(),
            "--sim-camera-hz",
            "1000",
        ]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{body:?}: {err}");
        assert!(!err.contains("panicked"), "{err}");
        assert!(err.contains(needle), "{body:?}: {needle} not in {err}");
    }
    let path = dir.join("good.csv");
    // The first position away from the rest, so that the first edge moves the stage.
    let rows: String = (1..=50).map(|k| format!("{}\n", k as f64 * 0.01)).collect();
    std::fs::write(&path, format!("setpoint\n{rows}")).unwrap();
    let o = twinstack(&[
        "sequence",
        "--port",
        "sim",
        "--link-latency-ms",
        "0",
        "--link-jitter-ms",
        "0",
        "--data",
        path.to_str().unwrap(),
        "--sim-camera-hz",
        "1000",
        "--window",
        "0.5",
        "--settle-ticks",
        "1",
        "--json",
    ]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{out}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let v: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(v["steps"], 50);
    assert_eq!(v["missed"], 0);
    assert_eq!(v["early"], 0);
    assert_eq!(v["ticks_to_motion"], 0);
    // A bad setting is refused by name before anything is sent.
    let o = twinstack(&[
        "sequence",
        "--port",
        "sim",
        "--data",
        path.to_str().unwrap(),
        "--window",
        "NaN",
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("sequence window"));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_served_virtual_board_steps_a_sequence_on_its_simulated_camera() {
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;
    use twinstack_link::socket::SocketTransport;
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let address = listener.local_addr().unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    let positions = z_stack(300, 2);
    let frames = positions.len() as u32;
    let server = std::thread::spawn(move || {
        let mut settings = SimDeviceConfig::paper_settings(Mode::OpenLoop);
        settings.sensor = None;
        settings.feedback = None;
        let config = SimDeviceConfig {
            stored: Some(settings),
            camera: Some(CameraConfig {
                period_ticks: 20,
                frames,
                on_settled: true,
            }),
            ..SimDeviceConfig::paper()
        };
        // As fast as the host goes: the board's time is its own.
        hal_sim::virtual_board::serve(listener, config, 0.0, &flag).unwrap()
    });
    let mut client = Client::new(SocketTransport::tcp(&address.to_string()).unwrap());
    client.set_timeout(Duration::from_secs(5));
    client.resync(Duration::from_millis(20)).unwrap();
    let mut opts = options(0.002, 10);
    opts.idle = Duration::from_secs(5);
    let report = run_sequence(
        &mut client,
        &positions,
        &opts,
        |_| ControlFlow::Continue(()),
    )
    .unwrap();
    stop.store(true, Ordering::Relaxed);
    let s = report.status;
    assert_eq!((s.steps, s.early, s.missed), (300, 0, 0), "{s:?}");
    assert_eq!(report.timing.map(|t| t.ticks_to_motion), Some(0));
    server.join().unwrap();
}
