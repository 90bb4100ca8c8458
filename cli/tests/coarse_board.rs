//! The dual-actuated stage as a board on the wire: the simulated dual-stage board
//! ([`hal_sim::coarse_rig`]: the library's command handler, control loop and coarse
//! supervisor on the piezo stage and the ball screw) driven through the host's protocol
//! client — homing, a 5 mm move, refusals, and the three faults.

use std::time::Duration;

use hal_sim::coarse_rig::{DualStageDevice, DualStageDeviceConfig, InjectedFaults};
use twinstack::dual_stage::{CoarseState, CoarseStatus};
use twinstack::protocol::messages::{
    CoarseMove, NackReason, Request, Response, StatusReport, StreamControl, WaveShape, Waveform,
};
use twinstack::refusal::{Field, Refusal, Rule};
use twinstack_link::client::{Client, LinkError};

const TICK: Duration = Duration::from_micros(20);

fn board() -> Client<DualStageDevice> {
    let device = DualStageDevice::dual_stage(&DualStageDeviceConfig::paper()).unwrap();
    let mut client = Client::new(device);
    // Wall-clock bound on each answer (the simulated board answers in simulated time, but
    // computing it takes wall-clock time on a loaded machine).
    client.set_timeout(Duration::from_secs(10));
    client
}

fn move_to(mm: f64) -> Request {
    Request::CoarseMove(CoarseMove {
        target_mm: mm,
        velocity_mm_s: 10.0,
        acceleration_mm_s2: 200.0,
    })
}

/// Polls (every 5 ms of simulated time) until `done`, at most `seconds`.
fn until(
    c: &mut Client<DualStageDevice>,
    seconds: f64,
    done: impl Fn(&CoarseStatus) -> bool,
) -> CoarseStatus {
    let mut t = 0.0;
    loop {
        let s = c.coarse_status().unwrap();
        if done(&s) {
            return s;
        }
        assert!(t < seconds, "still {s:?} after {seconds} s");
        c.wait(Duration::from_millis(5)).unwrap();
        t += 0.005;
    }
}

fn home(c: &mut Client<DualStageDevice>) {
    c.coarse(&Request::CoarseHome).unwrap();
    c.wait(Duration::from_millis(1)).unwrap();
    let s = until(c, 5.0, |s| s.state != CoarseState::Homing);
    assert_eq!(
        (s.state, s.homed, s.faults),
        (CoarseState::Idle, true, 0),
        "{s:?}"
    );
}

fn refusal(e: LinkError) -> Refusal {
    match e {
        LinkError::Nack {
            reason: NackReason::Refused(r),
            ..
        } => r,
        e => panic!("not a refusal: {e}"),
    }
}

#[test]
fn a_5_mm_move_over_the_wire_settles_within_the_encoder_resolution() {
    let mut c = board();
    // Refused before homing, with the reason.
    assert_eq!(
        refusal(c.coarse(&move_to(-19.0)).unwrap_err()),
        Refusal::new(Field::CoarseAxis, Rule::NotHomed)
    );
    home(&mut c);
    assert_eq!(
        refusal(c.coarse(&move_to(30.0)).unwrap_err()),
        Refusal::new(Field::CoarseTarget, Rule::AtMost(25.0))
    );
    c.wait(Duration::from_millis(100)).unwrap();
    // The move: −24 mm (the home reference, braked a little past) to −19 mm.
    let target_mm = -19.0;
    let rig = c.transport_mut().coarse_rig_mut().unwrap();
    rig.reset_stats();
    let offset = rig.offset_um();
    let start = c.coarse_status().unwrap();
    c.coarse(&move_to(target_mm)).unwrap();
    // Tick by tick from here: the error (board frame) every tick.
    let target_um = target_mm * 1e3;
    let dev = c.transport_mut();
    let mut errors_nm = Vec::new();
    let mut done_at = None;
    for k in 0..60_000 {
        dev.run_for(TICK);
        let rig = dev.coarse_rig().unwrap();
        errors_nm.push((rig.total_um() + offset - target_um) * 1e3);
        if done_at.is_none() && k > 100 && rig.status().state == CoarseState::Idle {
            done_at = Some(k);
        }
    }
    let done_at = done_at.expect("the move ended");
    let per_ms = 50;
    let averaged: Vec<f64> = errors_nm
        .windows(per_ms)
        .map(|w| w.iter().sum::<f64>() / per_ms as f64)
        .collect();
    let last_outside = averaged.iter().rposition(|e| e.abs() > 5.0).unwrap_or(0) + per_ms;
    let tail = &errors_nm[errors_nm.len() - 1000..];
    let mean = tail.iter().sum::<f64>() / tail.len() as f64;
    let rms = (tail.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / tail.len() as f64).sqrt();
    let status = c.coarse_status().unwrap();
    let rig = c.transport().coarse_rig().unwrap();
    println!(
        "5 mm move over the wire: from {:.6} mm, planned move {:.3} s, settled (1 ms mean within 5 nm) {:.1} ms after it, final error {mean:.2} nm (noise {rms:.2} nm rms), board reports {:.6} mm, peak piezo {:.2} µm, range-limit ticks {}, largest DAC step {} LSB",
        start.position_pm as f64 / 1e9,
        done_at as f64 * 20e-6,
        (last_outside.saturating_sub(done_at)) as f64 * 0.02,
        status.position_pm as f64 / 1e9,
        rig.peak_piezo_um(),
        rig.range_limited_ticks(),
        rig.largest_dac_step(),
    );
    assert!(mean.abs() <= 5.0, "final error {mean} nm");
    assert!(
        last_outside < done_at + 5_000,
        "settled 0.1 s after the plan"
    );
    assert_eq!(rig.range_limited_ticks(), 0);
    assert!(rig.peak_piezo_um() < 25.0 / 2.0, "{}", rig.peak_piezo_um());
    assert!(rig.peak_piezo_um() > 0.05, "the piezo takes part");
    assert_eq!((status.state, status.faults), (CoarseState::Idle, 0));
    assert!(
        (status.position_pm - -19_000_000_000).abs() <= 10_000,
        "{status:?}"
    );
}

fn busy(e: LinkError) {
    assert!(
        matches!(
            e,
            LinkError::Nack {
                reason: NackReason::Busy,
                ..
            }
        ),
        "not busy: {e}"
    );
}

/// The piezo handed back from the homed axis at rest plays its own source (a waveform) while
/// the carriage holds; a move is refused while it plays (it would be cut off), and once it
/// is stopped the move takes the piezo back: its setpoint leaves from where the waveform left
/// it at the dual stage's slope limit, with no jump, and the move settles as before.
#[test]
fn the_piezo_handed_back_plays_its_own_source_and_the_next_move_takes_it_back_without_a_jump() {
    let mut c = board();
    home(&mut c);
    c.wait(Duration::from_millis(50)).unwrap();
    assert!(c.status().unwrap().has(StatusReport::COARSE));
    let wave = Waveform {
        shape: WaveShape::Triangle,
        offset: 0,
        amplitude: (0.6 * 32768.0) as i16,
        frequency_mhz: 2_000,
        decay: None,
    };
    assert!(matches!(
        c.waveform(wave),
        Err(LinkError::Nack {
            reason: NackReason::Unsupported,
            ..
        })
    ));
    c.coarse(&Request::CoarseRelease).unwrap();
    assert!(!c.status().unwrap().has(StatusReport::COARSE));
    let carriage = c.transport().coarse_rig().unwrap().screw().carriage_um();
    c.waveform(wave).unwrap();
    // Until the piezo is far out (the triangle's crest, 0.6 of the half stroke).
    let dev = c.transport_mut();
    let mut far = 0.0f64;
    for _ in 0..20_000 {
        dev.run_for(TICK);
        far = dev.coarse_rig().unwrap().piezo_um();
        if far.abs() > 15.0 {
            break;
        }
    }
    assert!(far.abs() > 15.0, "the piezo plays its waveform: {far} µm");
    let rig = c.transport().coarse_rig().unwrap();
    let held = (rig.screw().carriage_um() - carriage).abs();
    assert!(held < 0.5, "the carriage holds: moved {held} µm");
    assert_eq!(rig.status().state, CoarseState::Idle);
    busy(c.coarse(&move_to(-23.0)).unwrap_err());
    c.expect_ack(&Request::Stream(StreamControl::Stop)).unwrap();
    // The move sent, then tick by tick: the piezo's setpoint (Q2.30) every tick.
    let setpoint = |c: &Client<DualStageDevice>| c.transport().control().controller().setpoint();
    let from = setpoint(&c);
    c.send(&move_to(-23.0)).unwrap();
    let mut last = from;
    let mut largest = 0i64;
    for _ in 0..5_000 {
        c.transport_mut().run_for(TICK);
        let now = setpoint(&c);
        largest = largest.max((now as i64 - last as i64).abs());
        last = now;
    }
    assert!(matches!(
        c.receive(Duration::from_secs(1)).unwrap(),
        Some(Response::Ack { .. })
    ));
    // The dual stage's slope limit on the piezo: `fine_step_pm` a coarse period, spread over
    // its fine ticks (0.6 µm a tick of the ±40 µm range: about 16·10⁶ in Q2.30). A ramp from
    // the piezo's last coarse ramp, not from where the waveform left it, would have covered
    // the whole way (15 µm) within one coarse period.
    let config = *c
        .transport()
        .coarse_rig()
        .unwrap()
        .supervisor()
        .dual()
        .config();
    let per_tick = config.fine_step_pm as f64 / config.fine_ticks as f64;
    // In Q2.30, with room for the roundings (the fine setpoint's to Q2.30, and the ramp's last
    // tick taking its division's remainder, less than a tick's count of LSBs).
    let bound = (per_tick / config.fine_half_span_pm as f64 * (1u64 << 30) as f64).ceil() as i64
        + config.fine_ticks as i64
        + 2;
    println!(
        "piezo taken back from {:.3} (normalised): largest step {largest} a tick (slope limit {bound}), now {:.3}",
        from as f64 / (1u64 << 30) as f64,
        last as f64 / (1u64 << 30) as f64,
    );
    assert!(
        from > 1 << 28,
        "the waveform left the piezo far out: {from}"
    );
    assert!(
        largest <= bound,
        "{largest} in one tick, the slope limit {bound}"
    );
    assert!(
        last.abs() < 1 << 28,
        "back within the dual stage's share: {last}"
    );
    assert!(c.status().unwrap().has(StatusReport::COARSE));
    busy(c.coarse(&Request::CoarseRelease).unwrap_err());
    assert!(matches!(
        c.waveform(wave),
        Err(LinkError::Nack {
            reason: NackReason::Unsupported,
            ..
        })
    ));
    let s = until(&mut c, 5.0, |s| s.state == CoarseState::Idle);
    assert_eq!(s.faults, 0);
    assert!((s.position_pm - -23_000_000_000).abs() <= 10_000, "{s:?}");
}

/// Home, start a 5 mm move up, inject a fault 0.1 s in; checks what every fault must do,
/// prints one line of what `what` (the fault, and the flag it must raise) did, and returns
/// the fault's status and the largest DAC step after its detection.
fn fault(what: &str, inject: InjectedFaults, flag: u16) -> (CoarseStatus, u16) {
    let mut c = board();
    home(&mut c);
    c.wait(Duration::from_millis(50)).unwrap();
    c.coarse(&move_to(-19.0)).unwrap();
    c.wait(Duration::from_millis(100)).unwrap();
    let dev = c.transport_mut();
    let rig = dev.coarse_rig_mut().unwrap();
    rig.inject(inject);
    let mut ticks = 0;
    while dev.coarse_rig().unwrap().status().state != CoarseState::Fault {
        dev.run_for(TICK);
        ticks += 1;
        assert!(ticks < 5_000, "not detected in 0.1 s");
    }
    let detected_ms = ticks as f64 * 0.02;
    // From the detection on: the DAC codes' largest change per tick, and where the piezo is.
    let rig = dev.coarse_rig_mut().unwrap();
    let piezo_at_fault = rig.piezo_um();
    rig.reset_stats();
    // One more coarse period for the burst under way, then not one more pulse.
    dev.run_for(Duration::from_micros(400));
    let pulses = dev.coarse_rig().unwrap().pulses();
    let held = dev.coarse_rig().unwrap().status().fine_setpoint;
    dev.run_for(Duration::from_millis(20));
    let piezo_20ms = dev.coarse_rig().unwrap().piezo_um();
    dev.run_for(Duration::from_millis(30));
    let rig = dev.coarse_rig().unwrap();
    assert_eq!(rig.pulses(), pulses, "steps after the fault");
    let s = c.coarse_status().unwrap();
    assert_eq!(
        (s.state, s.faults, s.homed),
        (CoarseState::Fault, flag, false)
    );
    assert_eq!(s.fine_setpoint, held, "the piezo's setpoint holds");
    let dac_step = c.transport().coarse_rig().unwrap().largest_dac_step();
    // Refused until homed again.
    assert_eq!(
        refusal(c.coarse(&move_to(-20.0)).unwrap_err()),
        Refusal::new(Field::CoarseAxis, Rule::NotHomed)
    );
    let piezo_after = c.transport().coarse_rig().unwrap().piezo_um();
    println!(
        "{what}: detected after {detected_ms:.2} ms; piezo {piezo_at_fault:.2} µm at detection, {piezo_20ms:.2} µm 20 ms later, {piezo_after:.2} µm 50 ms later; largest DAC step after detection {dac_step} LSB; no step after the fault"
    );
    // It settles on its held setpoint (its own loop lagged the last ramp) and stays there.
    assert!((piezo_after - piezo_20ms).abs() < 0.1, "the piezo holds");
    (s, dac_step)
}

/// The largest change of a DAC code per tick from a fault's detection on: the last ramp of
/// the piezo's setpoint (at most its slope limit, 0.6 µm per tick, a few hundred LSB) ends,
/// then it holds. A jump of the piezo back to mid-stroke from the window's edge would be about
/// 25 µm, tens of thousands of LSB.
const NO_JUMP_LSB: u16 = 1000;

#[test]
fn a_stalled_motor_stops_the_axis_and_the_piezo_holds() {
    let (_, dac) = fault(
        "motor stalls (following-error)",
        InjectedFaults {
            stall: true,
            ..Default::default()
        },
        CoarseStatus::FOLLOWING_ERROR,
    );
    assert!(dac <= NO_JUMP_LSB, "{dac}");
}

#[test]
fn a_lost_linear_encoder_stops_the_axis_and_the_piezo_holds() {
    let (_, dac) = fault(
        "linear encoder stops counting (encoder-lost)",
        InjectedFaults {
            linear_lost: true,
            ..Default::default()
        },
        CoarseStatus::ENCODER_LOST,
    );
    assert!(dac <= NO_JUMP_LSB, "{dac}");
}

#[test]
fn a_limit_switch_mid_move_stops_the_axis_and_the_piezo_holds() {
    let (s, dac) = fault(
        "upper limit switch reads active (limit-switch)",
        InjectedFaults {
            upper_limit: true,
            ..Default::default()
        },
        CoarseStatus::LIMIT_SWITCH,
    );
    assert!(dac <= NO_JUMP_LSB, "{dac}");
    assert!(s.switches & CoarseStatus::UPPER_LIMIT != 0);
}

/// The command-line tool against `--port sim` (the simulated dual-stage board).
#[test]
fn hal_sim_coarse_drives_the_simulated_board() {
    let run = |args: &[&str]| {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
            .args(args)
            .output()
            .expect("twinstack runs");
        (
            o.status.code(),
            String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr),
        )
    };
    let (code, out) = run(&["coarse", "move", "--to-mm", "-19", "--port", "sim"]);
    assert_eq!(code, Some(1), "{out}");
    assert!(out.contains("not homed"), "{out}");
    let (code, out) = run(&[
        "coarse", "move", "--to-mm", "-19", "--home", "--wait", "--port", "sim",
    ]);
    assert_eq!(code, Some(0), "{out}");
    assert!(out.contains("state idle\nhomed yes\n"), "{out}");
    let position: f64 = out
        .lines()
        .find_map(|l| l.strip_prefix("position_mm "))
        .and_then(|v| v.parse().ok())
        .expect("a position line");
    // At the plan's end (the settling takes a few ms more).
    assert!((position - -19.0).abs() < 1e-3, "{out}");
    let (code, out) = run(&["coarse", "status", "--port", "sim"]);
    assert_eq!(code, Some(0), "{out}");
    assert!(out.contains("state unhomed"), "{out}");
    let (code, out) = run(&["coarse", "jog", "--speed", "50", "--port", "sim"]);
    assert_eq!(code, Some(1), "{out}");
}
