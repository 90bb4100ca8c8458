//! Scan patterns and trigger I/O on the in-process board (`SimDevice`: the library's command
//! handler and control loop, the simulated stage): the captured setpoint and trigger levels
//! equal the library's replay tick for tick, the clocks fall on the pattern's ticks, a scan
//! starts and stops without a step, and the external trigger input starts a capture and a
//! scan on the tick its edge arrives.

use std::time::Duration;

use hal_sim::sim_device::{SimDevice, SimDeviceConfig};
use twinstack::protocol::messages::{
    CaptureRequest, CaptureState, Request, ScanRequest, StatusReport, StreamControl, Trigger,
    TriggerConfig, TriggerEdge,
};
use twinstack::services::recorder::Channel;
use twinstack::sources::scan::{slew_step, FRAME, INPUT, LINE};
use twinstack_link::capture::wait_and_read;
use twinstack_link::client::Client;
use twinstack_link::scan_timing::{analyse, parse_pattern};

const RATE: f64 = 50_000.0;

fn board() -> Client<SimDevice> {
    Client::new(SimDevice::new(SimDeviceConfig::paper()).unwrap())
}

fn max_step(client: &mut Client<SimDevice>) -> i32 {
    let d = client.read_params().unwrap().drive;
    slew_step(d.slew_rate, d.min_voltage, d.max_voltage, RATE)
}

/// Runs `request` with pulses of `pulse` ticks and captures setpoint and triggers for
/// `samples` ticks from its start.
fn run_scan(
    client: &mut Client<SimDevice>,
    request: ScanRequest,
    pulse: u16,
    samples: u32,
    pre: u32,
) -> (Vec<i16>, Vec<i16>) {
    client
        .expect_ack(&Request::Trigger(TriggerConfig {
            pulse_ticks: pulse,
            input: TriggerEdge::Off,
            start_stream: false,
        }))
        .unwrap();
    client
        .arm_capture(CaptureRequest {
            signals: Channel::Setpoint.bit() | Channel::Triggers.bit(),
            samples,
            pre_trigger: pre,
            trigger: Trigger::ScanStart,
            decimation: 1,
        })
        .unwrap();
    client.expect_ack(&Request::Scan(request)).unwrap();
    let (_, w) = wait_and_read(client, Duration::from_secs(5), |_, _| {}).unwrap();
    (
        w.iter().step_by(2).copied().collect(),
        w.iter().skip(1).step_by(2).copied().collect(),
    )
}

#[test]
fn each_pattern_on_the_board_is_the_library_s_tick_for_tick_with_its_clocks() {
    for (spec, tpp, frames, samples) in [
        (
            "raster:lines=6,pixels=50,turn=40,amplitude=0.6,offset=0.1",
            4u16,
            1u16,
            2000u32,
        ),
        ("lissajous:hz=40,x=3,y=2,amplitude=0.7", 10, 2, 2700),
        (
            "spiral:hz=500,turns=4,amplitude=0.6,y-offset=0.2",
            5,
            1,
            1000,
        ),
    ] {
        let mut client = board();
        let step = max_step(&mut client);
        let request = ScanRequest {
            pattern: parse_pattern(spec).unwrap(),
            ticks_per_pixel: tpp,
            frames,
            on_trigger: false,
        };
        let (x, t) = run_scan(&mut client, request, 2, samples, 0);
        let (f, _) = analyse(&request, RATE, step, 2, &x, &t).unwrap();
        assert_eq!(f.x_mismatches, 0, "{spec}: {f:?}");
        assert_eq!(f.trigger_mismatches, 0, "{spec}: {f:?}");
        assert!(f.x_compared > samples as usize / 2, "{spec}: {f:?}");
        assert_eq!(f.line.error_max_ticks, 0, "{spec}");
        assert_eq!(f.frame.pulses, frames as usize, "{spec}");
        // Each clock within a tick of the pattern's ideal times; pulses 2 ticks wide.
        assert!(f.line.ideal_error_max_ticks < 1.0, "{spec}: {f:?}");
        assert_eq!(f.line.width_ticks, (2, 2), "{spec}");
        match request.pattern {
            twinstack::sources::scan::ScanPattern::Raster(r) => {
                assert_eq!(f.line.pulses, r.lines as usize);
                assert_eq!(f.line.period_ticks, (240, 240));
                assert_eq!(f.line.jitter_ticks, 0);
                assert_eq!(f.pixel.pulses, (r.lines * r.pixels) as usize);
                // The line pulse comes T/2 ticks after the turnaround's apex, as measured
                // in the captured setpoint.
                let (lo, hi, want) = f.turnaround_to_line.unwrap();
                assert!(
                    (lo - want).abs() <= 0.5 && (hi - want).abs() <= 0.5,
                    "{lo} {hi}"
                );
            }
            twinstack::sources::scan::ScanPattern::Lissajous(_) => {
                assert_eq!(f.line.pulses, 6);
                let (lo, hi, _) = f.turnaround_to_line.unwrap();
                assert!(lo.abs() <= 1.0 && hi.abs() <= 1.0, "{lo} {hi}");
            }
            twinstack::sources::scan::ScanPattern::Spiral(_) => assert_eq!(f.line.pulses, 8),
        }
    }
}

#[test]
fn a_scan_starts_and_stops_without_a_step() {
    let mut client = board();
    let step = max_step(&mut client) as f64 / (1u64 << 30) as f64;
    // Off-centre first: a waveform leaves the setpoint somewhere, then it is stopped.
    client
        .expect_ack(&Request::Stream(StreamControl::Stop))
        .unwrap();
    let request = ScanRequest {
        pattern: parse_pattern("lissajous:hz=25,x=2,y=3,amplitude=0.8,offset=-0.1").unwrap(),
        ticks_per_pixel: 10,
        frames: 0,
        on_trigger: false,
    };
    // 50 frames from before the start: the setpoint held there.
    client.wait(Duration::from_millis(2)).unwrap();
    let (x, _) = run_scan(&mut client, request, 1, 3000, 50);
    let worst = x
        .windows(2)
        .map(|w| (w[1] as f64 - w[0] as f64).abs() / 32768.0)
        .fold(0.0, f64::max);
    // The approach walks at a quarter of the slew step; the pattern stays under it.
    assert!(worst <= step / 4.0 + 1.0 / 32768.0, "{worst} vs {step}");
    // The window opens on the held setpoint (the frames before the start the ring had), and
    // the first move from it is an approach step.
    let first_move = x.iter().position(|&v| v != x[0]).unwrap();
    assert!(first_move > 0 && first_move <= 50, "{first_move}");
    // Stop: the setpoint holds where the scan left it.
    client.wait(Duration::from_millis(7)).unwrap();
    client
        .expect_ack(&Request::Stream(StreamControl::Stop))
        .unwrap();
    client
        .arm_capture(CaptureRequest {
            signals: Channel::Setpoint.bit(),
            samples: 200,
            pre_trigger: 0,
            trigger: Trigger::Now,
            decimation: 1,
        })
        .unwrap();
    let (_, held) = wait_and_read(&mut client, Duration::from_secs(2), |_, _| {}).unwrap();
    assert!(held.iter().all(|&v| v == held[0]), "holds after the stop");
    let s = client.status().unwrap();
    assert!(!s.has(StatusReport::SCANNING));
}

/// Arms the trigger input on its rising edge (pulses of one tick, the stream not started by it).
fn arm_rising_input(client: &mut Client<SimDevice>) {
    client
        .expect_ack(&Request::Trigger(TriggerConfig {
            pulse_ticks: 1,
            input: TriggerEdge::Rising,
            start_stream: false,
        }))
        .unwrap();
}

#[test]
fn the_external_trigger_starts_a_capture_and_a_waiting_scan_on_its_edge() {
    let mut client = board();
    let step = max_step(&mut client);
    arm_rising_input(&mut client);
    assert!(client.status().unwrap().has(StatusReport::TRIGGER_ARMED));
    // A capture armed on the external trigger, with 100 frames from before it.
    client
        .arm_capture(CaptureRequest {
            signals: Channel::Setpoint.bit() | Channel::Triggers.bit(),
            samples: 1200,
            pre_trigger: 100,
            trigger: Trigger::External,
            decimation: 1,
        })
        .unwrap();
    let request = ScanRequest {
        pattern: parse_pattern("raster:lines=3,pixels=40,turn=20,amplitude=0.5").unwrap(),
        ticks_per_pixel: 3,
        frames: 1,
        on_trigger: true,
    };
    client.expect_ack(&Request::Scan(request)).unwrap();
    client.wait(Duration::from_millis(5)).unwrap();
    // Waiting: not scanning, nothing captured beyond the ring.
    let s = client.status().unwrap();
    assert!(!s.has(StatusReport::SCANNING) && s.has(StatusReport::TRIGGER_ARMED));
    assert_eq!(client.capture_status().unwrap().state, CaptureState::Armed);
    client.transport_mut().set_trigger_input(true);
    let (status, w) = wait_and_read(&mut client, Duration::from_secs(2), |_, _| {}).unwrap();
    assert_eq!(status.pre_available, 100);
    let x: Vec<i16> = w.iter().step_by(2).copied().collect();
    let t: Vec<i16> = w.iter().skip(1).step_by(2).copied().collect();
    // The input's level is in the capture: low before the trigger frame, high from it on;
    // the scan starts moving on that very tick (its approach), and the clocks follow.
    let high = t.iter().position(|&v| v & INPUT as i16 != 0).unwrap();
    assert_eq!(high, 100);
    assert!(x[..100].iter().all(|&v| v == x[0]), "held until the edge");
    let (f, _) = analyse(&request, RATE, step, 1, &x[100..], &t[100..]).unwrap();
    assert_eq!((f.x_mismatches, f.trigger_mismatches), (0, 0), "{f:?}");
    assert_eq!(f.line.pulses, 3);
    assert!(t[100..].iter().any(|&v| v & FRAME as i16 != 0));
    assert!(t[..100].iter().all(|&v| v & LINE as i16 == 0));
    // One shot: disarmed now.
    let s = client.status().unwrap();
    assert!(!s.has(StatusReport::TRIGGER_ARMED));
}

/// A running scan replaced by one that waits for the trigger: the first stops where it is and
/// the stage holds there, without a step (the waiting scan is not the setpoint's source yet),
/// until the edge starts the second from that point.
#[test]
fn a_scan_replaced_by_one_waiting_for_its_trigger_holds_until_the_edge() {
    let mut client = board();
    arm_rising_input(&mut client);
    let scan = |on_trigger: bool| ScanRequest {
        pattern: parse_pattern("raster:lines=4,pixels=40,turn=20,amplitude=0.5").unwrap(),
        ticks_per_pixel: 3,
        frames: 0,
        on_trigger,
    };
    client.expect_ack(&Request::Scan(scan(false))).unwrap();
    client.wait(Duration::from_millis(3)).unwrap();
    assert!(client.status().unwrap().has(StatusReport::SCANNING));
    // The setpoint from before the replacement to well after it.
    client
        .arm_capture(CaptureRequest {
            signals: Channel::Setpoint.bit(),
            samples: 400,
            pre_trigger: 0,
            trigger: Trigger::Now,
            decimation: 1,
        })
        .unwrap();
    client.wait(Duration::from_millis(2)).unwrap();
    client.expect_ack(&Request::Scan(scan(true))).unwrap();
    let (_, x) = wait_and_read(&mut client, Duration::from_secs(2), |_, _| {}).unwrap();
    assert!(!client.status().unwrap().has(StatusReport::SCANNING));
    // No step at the replacement: no move larger than the first scan's own moves.
    let moves = |x: &[i16]| {
        x.windows(2)
            .map(|w| (w[1] as i32 - w[0] as i32).abs())
            .max()
            .unwrap_or(0)
    };
    let (scanning, all) = (moves(&x[..50]), moves(&x));
    assert!(
        scanning > 0 && all <= scanning,
        "a step of {all} where the scan moved by {scanning}"
    );
    let last = *x.last().unwrap();
    assert!(x[x.len() - 100..].iter().all(|&v| v == last), "held");
    assert!(
        x[..50].iter().any(|&v| v != last),
        "the first scan moved before"
    );
    // The edge starts the waiting scan from where the stage holds.
    client
        .arm_capture(CaptureRequest {
            signals: Channel::Setpoint.bit(),
            samples: 300,
            pre_trigger: 100,
            trigger: Trigger::External,
            decimation: 1,
        })
        .unwrap();
    client.wait(Duration::from_millis(3)).unwrap();
    client.transport_mut().set_trigger_input(true);
    let (_, y) = wait_and_read(&mut client, Duration::from_secs(2), |_, _| {}).unwrap();
    assert!(y[..100].iter().all(|&v| v == last), "held until the edge");
    assert!(y[100..].iter().any(|&v| v != last), "the edge starts it");
}

#[test]
fn the_board_refuses_a_bad_scan_by_field_and_keeps_what_it_was_doing() {
    use twinstack::protocol::messages::{NackReason, Response};
    use twinstack::refusal::{Field, Refusal, Rule};
    let mut client = board();
    let good = ScanRequest {
        pattern: parse_pattern("raster:lines=4,pixels=20,turn=10").unwrap(),
        ticks_per_pixel: 4,
        frames: 0,
        on_trigger: false,
    };
    client.expect_ack(&Request::Scan(good)).unwrap();
    client.wait(Duration::from_millis(2)).unwrap();
    assert!(client.status().unwrap().has(StatusReport::SCANNING));
    for (spec, tpp, refusal) in [
        (
            "raster:lines=0",
            4,
            Refusal::new(Field::ScanLines, Rule::AtLeast(1.0)),
        ),
        (
            "raster:pixels=100",
            1,
            // The pulse is 1 tick (the default): a pixel must last longer.
            Refusal::new(Field::ScanTicksPerPixel, Rule::AtLeast(2.0)),
        ),
        (
            "lissajous:hz=9000,x=3",
            4,
            Refusal::new(Field::ScanFrequency, Rule::Below(25_000.0 / 3.0)),
        ),
        (
            "spiral:amplitude=1.2",
            4,
            Refusal::new(Field::ScanAmplitude, Rule::AtMost(1.0)),
        ),
    ] {
        let bad = ScanRequest {
            pattern: parse_pattern(spec).unwrap(),
            ticks_per_pixel: tpp,
            frames: 1,
            on_trigger: false,
        };
        match client.request(&Request::Scan(bad)).unwrap() {
            Response::Nack {
                reason: NackReason::Refused(r),
            } => assert_eq!(r, refusal, "{spec}"),
            other => panic!("{spec}: {other:?}"),
        }
        // The running scan goes on.
        assert!(
            client.status().unwrap().has(StatusReport::SCANNING),
            "{spec}"
        );
    }
}
