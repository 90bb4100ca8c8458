//! The dual-actuated stage end to end in simulation: the library's `DualStage` coarse tick on
//! the emulated step/dir output and encoders of the simulated ball screw, the library's piezo
//! `Controller::tick` on the simulated piezo stage riding on it.

use hal_sim::coarse_stage::{EmulatedEncoder, EmulatedStepDir, StepDirError};
use hal_sim::dual_stage_sim::{
    five_mm_move, largest_jump_nm, track_large_trajectory, DualStageSim, DualStageSimConfig,
    Sample, Trajectory,
};
use hal_sim::plant::ball_screw::{BallScrew, BallScrewParams};
use twinstack::board::fakes::FixedEncoder;
use twinstack::board::{QuadratureEncoder, StepBurst, StepDir, StepDirection};
use twinstack::dual_stage::{DualMode, PM_PER_UM};

/// Largest change of the tracking error from one 20 µs tick to the next during a hand-over
/// between the stages (an abrupt one, in one coarse tick, moves it by ≈ 300 nm).
const HANDOVER_JUMP_BOUND_NM: f64 = 40.0;
/// The same over a whole move: a third of a microstep (312.5 nm). The carriage breaking away
/// from its sticking friction at the start of the move is the largest event (≈ 60 nm).
const MOVE_JUMP_BOUND_NM: f64 = 100.0;

#[test]
fn the_piezo_never_saturates_on_the_5_mm_move() {
    let config = DualStageSimConfig::paper();
    let m = five_mm_move(&config, 5000.0).unwrap();
    assert_eq!(
        m.range_limited_ticks, 0,
        "the piezo's drive hit its range limit"
    );
    assert_eq!(m.fine_clamps, 0, "the residual left the piezo's window");
    assert!(
        m.peak_piezo_um < 0.5 * m.window_um,
        "peak piezo {} µm of a ±{} µm window",
        m.peak_piezo_um,
        m.window_um
    );
    // The piezo did take part: it absorbed the carriage's following error.
    assert!(m.peak_piezo_um > 0.2, "peak piezo {} µm", m.peak_piezo_um);
}

#[test]
fn the_5_mm_move_settles_within_the_linear_encoders_resolution() {
    let config = DualStageSimConfig::paper();
    let m = five_mm_move(&config, 5000.0).unwrap();
    assert!(m.settled, "did not settle");
    assert!(m.settling_time_s < 0.1, "settling {} s", m.settling_time_s);
    assert!(
        m.final_error_nm.abs() <= m.resolution_nm,
        "final error {} nm vs resolution {} nm",
        m.final_error_nm,
        m.resolution_nm
    );
    // The move took the planned time of a trapezoid: 5 mm / 10 mm/s + 10 mm/s / 200 mm/s².
    assert!((m.move_time_s - 0.55).abs() < 0.002, "{} s", m.move_time_s);
    let last = m.samples.last().unwrap();
    assert!((last.total_um - last.setpoint_um).abs() < 0.01);
    assert!(last.carriage_um > 4990.0, "the carriage carried the move");
}

#[test]
fn the_5_mm_move_has_no_jump_in_the_combined_output() {
    let m = five_mm_move(&DualStageSimConfig::paper(), 5000.0).unwrap();
    assert!(
        m.largest_jump_nm <= MOVE_JUMP_BOUND_NM,
        "largest per-tick change of the error {} nm",
        m.largest_jump_nm
    );
}

/// A 2 mm move in dual mode; 100 ms into it (cruising at 10 mm/s, the piezo holding the
/// carriage's following error) the hand-over to coarse only, 100 ms later back to dual.
/// Returns the samples after each hand-over and the piezo's share before the first.
fn handover_run(handover_s: f64) -> (Vec<Sample>, Vec<Sample>, f64) {
    let mut config = DualStageSimConfig::paper();
    config.dual.handover_s = handover_s;
    let mut sim = DualStageSim::new(&config).unwrap();
    let mut samples = Vec::new();
    sim.dual().set_mode(DualMode::Dual);
    sim.run(0.1, |_, _| {}, &mut samples);
    let target = sim.total_um() + 2000.0;
    sim.dual().move_to((target * PM_PER_UM).round() as i64);
    samples.clear();
    sim.run(0.1, |_, _| {}, &mut samples);
    let held = samples.last().unwrap().piezo_um;
    let mut out = Vec::new();
    sim.dual().set_mode(DualMode::CoarseOnly);
    sim.run(0.1, |_, _| {}, &mut out);
    let mut back = Vec::new();
    sim.dual().set_mode(DualMode::Dual);
    sim.run(0.3, |_, _| {}, &mut back);
    (out, back, held)
}

#[test]
fn handover_between_the_stages_has_no_jump() {
    let (out, back, held) = handover_run(0.02);
    assert!(
        held.abs() > 1.0,
        "the piezo held {held} µm before the hand-over"
    );
    // Out: the piezo hands its share back to the coarse stage and sits at mid-stroke.
    let piezo_after = out.last().unwrap().piezo_um;
    assert!(
        piezo_after.abs() < 0.1,
        "piezo at {piezo_after} µm in coarse only"
    );
    for (name, s) in [("to coarse only", &out), ("back to dual", &back)] {
        let jump = largest_jump_nm(s);
        eprintln!("hand-over {name}: largest per-tick change {jump:.1} nm");
        assert!(
            jump <= HANDOVER_JUMP_BOUND_NM,
            "{name}: {jump} nm in one tick"
        );
    }
    // Back in dual mode, after the move, the error returns within the linear encoder's
    // resolution.
    let tail = &back[back.len() - 1000..];
    let mean = tail.iter().map(|s| s.error_um()).sum::<f64>() / tail.len() as f64;
    assert!(mean.abs() * 1e3 < 5.0, "error {} nm", mean * 1e3);
}

#[test]
fn an_abrupt_handover_would_break_the_bound() {
    // The same hand-over in one coarse tick (the ramp set to 0): the test above would catch it.
    let (out, _, held) = handover_run(0.0);
    assert!(held.abs() > 1.0);
    let jump = largest_jump_nm(&out);
    eprintln!("abrupt hand-over: largest per-tick change {jump:.1} nm");
    assert!(
        jump > 4.0 * HANDOVER_JUMP_BOUND_NM,
        "abrupt hand-over: only {jump} nm"
    );
}

#[test]
fn the_dual_stage_tracks_a_trajectory_larger_than_the_stroke_far_better_than_the_coarse_stage() {
    let config = DualStageSimConfig::paper();
    let trajectory = Trajectory::larger_than_the_stroke();
    let coarse = track_large_trajectory(&config, DualMode::CoarseOnly, trajectory, 1.2, 0.2);
    let dual = track_large_trajectory(&config, DualMode::Dual, trajectory, 1.2, 0.2);
    let (coarse, dual) = (coarse.unwrap(), dual.unwrap());
    assert!(trajectory.amplitude_um > 10.0 * 37.0);
    assert!(dual.rms_um * 10.0 < coarse.rms_um, "{dual:?} vs {coarse:?}");
    assert!(dual.max_um * 5.0 < coarse.max_um, "{dual:?} vs {coarse:?}");
    assert_eq!(dual.range_limited_ticks, 0);
    assert!(dual.peak_piezo_um < config.dual.fine_window_um);
}

#[test]
fn planned_moves_and_step_bursts_respect_their_limits() {
    let config = DualStageSimConfig::paper();
    let m = five_mm_move(&config, 5000.0).unwrap();
    let rate = config.dual.coarse_rate_hz;
    let per_coarse = (config.board.plant.dt.recip() / rate).round() as usize;
    // The setpoint at the end of each coarse period.
    let r: Vec<f64> = m
        .samples
        .iter()
        .skip(per_coarse - 1)
        .step_by(per_coarse)
        .map(|s| s.setpoint_um)
        .collect();
    let v_max = config.dual.move_velocity_um_s / rate;
    let a_max = config.dual.move_acceleration_um_s2 / (rate * rate);
    let mut peak_v = 0f64;
    for w in r.windows(3) {
        let (v0, v1) = (w[1] - w[0], w[2] - w[1]);
        assert!(v1.abs() <= v_max + 1e-6, "{v1} µm per tick");
        assert!((v1 - v0).abs() <= a_max + 1e-6, "{} µm per tick²", v1 - v0);
        peak_v = peak_v.max(v1.abs());
    }
    assert!(
        peak_v > 0.999 * v_max,
        "the move cruises at its speed limit"
    );
    // Steps: at most the coarse speed's worth per coarse period (plus the take-up).
    let mut sim = DualStageSim::new(&config).unwrap();
    let mut samples = Vec::new();
    sim.dual().set_mode(DualMode::Dual);
    sim.dual().move_to(2_000_000_000);
    let mut last = 0;
    let step_um = config.screw.step_um();
    let max_per_tick = (config.dual.coarse_velocity_um_s / rate / step_um).ceil() as u64 + 7;
    for _ in 0..3000 {
        sim.coarse_period(&mut samples);
        let pulses = sim.step_dir().pulses();
        assert!(pulses - last <= max_per_tick, "{} steps", pulses - last);
        last = pulses;
    }
    assert!((sim.screw().commanded_microsteps() as f64 * step_um - 2000.0).abs() < 3.0);
}

#[test]
fn encoders_count_quadrature_through_direction_changes() {
    let mut enc = EmulatedEncoder::new(0.005, 0.0);
    let start = enc.count();
    // Forward 3 µm, back 7 µm, forward 100.0025 µm, in uneven steps; 16-bit wraps on the way.
    let mut x = 0.0;
    let mut wraps = 0;
    let mut last_raw = start;
    for (to, step) in [(3.0, 0.0137), (-4.0, -0.0071), (400.0025, 0.0333)] {
        while (to - x) * step > 0.0 {
            x += step;
            enc.move_to(x);
            let raw = enc.count();
            if (raw as i32 - last_raw as i32).abs() > 30_000 {
                wraps += 1;
            }
            last_raw = raw;
            assert_eq!(enc.counted(), (x / 0.005).floor() as i64, "at {x} µm");
        }
    }
    assert_eq!(enc.missed(), 0);
    assert!(wraps >= 1, "the 16-bit counter wrapped");
    // The library's counter extension recovers the position from the wrapping register.
    let mut ext = twinstack::dual_stage::coarse_axis::EncoderCounter::new(start);
    let mut enc = EmulatedEncoder::new(0.005, 0.0);
    for k in 0..2000 {
        let x = 150.0 * (k as f64 * 0.01).sin();
        enc.move_to(x);
        assert_eq!(ext.update(enc.count()), enc.counted());
    }
}

#[test]
fn step_output_spreads_a_burst_over_the_period_and_refuses_an_overlap() {
    let mut out = EmulatedStepDir::new(10, 255);
    let burst = StepBurst {
        direction: StepDirection::Forward,
        steps: 25,
    };
    out.emit(burst).unwrap();
    assert_eq!(out.emit(burst), Err(StepDirError::Busy));
    let positions: Vec<i64> = (0..10).map(|_| out.advance()).collect();
    assert_eq!(positions, [2, 5, 7, 10, 12, 15, 17, 20, 22, 25]);
    assert_eq!(out.advance(), 25, "the burst ended with the period");
    out.emit(StepBurst {
        direction: StepDirection::Reverse,
        steps: 3,
    })
    .unwrap();
    for _ in 0..10 {
        out.advance();
    }
    assert_eq!((out.position(), out.pulses(), out.reversals()), (22, 28, 1));
    assert_eq!(
        out.emit(StepBurst {
            direction: StepDirection::Forward,
            steps: 256
        }),
        Err(StepDirError::TooManySteps(256))
    );
}

#[test]
fn the_screw_loses_its_backlash_on_a_reversal() {
    let p = BallScrewParams::precision_stage();
    let mut screw = BallScrew::new(&p, 20e-6).unwrap();
    let mut steps = 0i64;
    // One microstep every 50 periods (0.3 mm/s: the carriage coasts a few nm when the nut
    // stops), then 40 ms to settle.
    let mut run = |screw: &mut BallScrew, to: i64| {
        let mut k = 0u64;
        while steps != to || !k.is_multiple_of(2000) {
            if steps != to && k.is_multiple_of(50) {
                steps += (to - steps).signum();
            }
            screw.step(steps);
            k += 1;
        }
        screw.carriage_um()
    };
    let forward = run(&mut screw, 320); // 100 µm
    let back = run(&mut screw, 160); // 50 µm back
    let lost = 50.0 - (forward - back);
    // The nut crosses its 2 µm play before it pushes the carriage back.
    assert!((lost - 2.0).abs() < 0.2, "lost motion {lost} µm");
    // The motor encoder follows the motor, not the carriage.
    let counts = screw.encoder_counts() as f64 * p.encoder_count_um();
    assert!((counts - 50.0).abs() < 0.3, "encoder {counts} µm");
}

#[test]
fn backlash_after_a_reversal_is_taken_up_and_the_dual_stage_removes_the_rest() {
    // Out 200 µm, back 100 µm: the error when the return move ends (mean of its last ms),
    // and 20 ms later.
    let error_after_return = |mode: DualMode, backlash_um: f64| {
        let mut config = DualStageSimConfig::paper();
        config.dual.backlash_um = backlash_um;
        let mut sim = DualStageSim::new(&config).unwrap();
        let mut s = Vec::new();
        sim.dual().set_mode(mode);
        sim.run(0.05, |_, _| {}, &mut s);
        let x0 = sim.total_um();
        for to in [x0 + 200.0, x0 + 100.0] {
            sim.dual().move_to((to * PM_PER_UM).round() as i64);
            while !sim.dual().move_done() {
                sim.coarse_period(&mut s);
            }
        }
        let mean = |s: &[Sample]| {
            let tail = &s[s.len() - 50..];
            tail.iter().map(|x| x.error_um()).sum::<f64>() / tail.len() as f64
        };
        let at_end = mean(&s);
        s.clear();
        sim.run(0.02, |_, _| {}, &mut s);
        (at_end, mean(&s))
    };
    let without = error_after_return(DualMode::CoarseOnly, 0.0).0.abs();
    let with = error_after_return(DualMode::CoarseOnly, 2.0).0.abs();
    eprintln!(
        "coarse only, at the end of the return move: {without} µm without take-up, {with} µm with"
    );
    assert!(without > 0.4, "no take-up: {without} µm");
    assert!(with < 0.25 * without, "take-up: {with} µm vs {without} µm");
    let dual = error_after_return(DualMode::Dual, 2.0).1.abs();
    assert!(dual * 1e3 < 5.0, "dual: {} nm", dual * 1e3);
}

/// A step output that records the bursts asked of it and refuses them when told to.
struct Fuzzed {
    refuse: bool,
    burst_steps: Vec<u16>,
}
impl StepDir for Fuzzed {
    type Error = ();
    fn max_steps_per_burst(&self) -> u16 {
        255
    }
    fn emit(&mut self, burst: StepBurst) -> Result<(), ()> {
        self.burst_steps.push(burst.steps);
        if self.refuse {
            Err(())
        } else {
            Ok(())
        }
    }
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig::with_cases(64))]

    /// Whatever arrives — setpoints anywhere (beyond the travel too), any encoder readings,
    /// any piezo reading, refused bursts, mode switches — the piezo's setpoint stays inside its
    /// window around mid-stroke, moves by at most its slope limit per coarse tick, continues
    /// where the last period ended, and no burst exceeds the output's limit.
    #[test]
    fn limits_hold_whatever_arrives(
        inputs in proptest::collection::vec(
            (proptest::num::i64::ANY, proptest::num::u16::ANY, proptest::num::u16::ANY,
             proptest::option::of(proptest::num::i32::ANY), 0u8..6),
            1..300,
        )
    ) {
        let settings = twinstack::dual_stage::DualStageSettings::paper_stage();
        let config = settings.build().unwrap();
        let mut dual = twinstack::dual_stage::DualStage::new(config, 0, 0, 0);
        let mut out = Fuzzed { refuse: false, burst_steps: Vec::new() };
        let mut last_to = None;
        let mut last_pm = config.fine_centre_pm;
        for (setpoint, motor, linear, piezo, action) in inputs {
            match action {
                0 => dual.follow(setpoint),
                1 => dual.move_to(setpoint),
                2 => dual.set_mode(DualMode::Dual),
                3 => dual.set_mode(DualMode::CoarseOnly),
                4 => out.refuse = !out.refuse,
                _ => dual.hold(),
            }
            let r = dual.coarse_tick(&mut out, &mut FixedEncoder(motor), &mut FixedEncoder(linear), piezo);
            if let Some(to) = last_to {
                proptest::prop_assert_eq!(r.fine.from, to);
            }
            last_to = Some(r.fine.to);
            let p = dual.fine_to_pm(r.fine.to);
            proptest::prop_assert!((p - config.fine_centre_pm).abs() <= config.fine_window_pm + 1);
            proptest::prop_assert!((p - last_pm).abs() <= config.fine_step_pm + 2);
            last_pm = p;
            let (lo, hi) = config.travel_pm;
            proptest::prop_assert!(r.setpoint_pm >= lo && r.setpoint_pm <= hi);
        }
        proptest::prop_assert!(out.burst_steps.iter().all(|&s| (1..=255).contains(&s)));
    }
}
