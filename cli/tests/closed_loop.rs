//! End to end: the library's control tick (`Controller::tick`, the code the interrupt runs)
//! drives the simulated board through `SimBoard::split`, with the internal converters and with
//! the SPI drivers on the emulated chips, and closes the loop on the emulated sensor.
//!
//! The setpoint ramps over 10 ms to 20 µm, steps in one tick to −12 µm (a step that would make the
//! inverse Duhem limit-cycle were its drive step not capped at `1/α`), and ramps to 3.5 µm.

use core::fmt::Debug;
use hal_sim::converters::{AnalogDualDac, AnalogSensorAdc};
use hal_sim::plant::{Configuration as PlantConfiguration, StageParams};
use hal_sim::sim_board::{BoardConfig, ExternalBoard, InternalBoard, SimBoard};
use twinstack::board::{DualDac, Hardware};
use twinstack::config::settings::{FeedbackSettings, Mode, Model, SensorSettings, Settings};
use twinstack::control::drive::{Configuration, DriveSettings, SafeState};
use twinstack::control::{ControlConfig, Controller};
use twinstack::fixed_point::signal_from_f64;
use twinstack::services::observer::Observed;
use twinstack::{DuhemParams, Scaling};

/// Output range of the controller's model, µm (normalised setpoint 1.0 = 40 µm).
const OUTPUT_UM: (f64, f64) = (-40.0, 40.0);

/// The board as the settings are validated against: 150 V amplifiers on the board's DAC, the
/// sensor on an ADC of `adc_bits`, 50 kHz.
fn hardware<D: AnalogDualDac, A: AnalogSensorAdc>(
    board: &SimBoard<D, A>,
    adc_bits: u8,
) -> Hardware {
    Hardware {
        amplifier_full_scale: 150.0,
        dac_full_scale: DualDac::full_scale(board).0,
        sensor_adc_bits: Some(adc_bits),
        control_rate_hz: 50_000.0,
    }
}

/// Closed-loop settings for a board whose ADC spans `adc_volts`.
fn settings<D: AnalogDualDac, A: AnalogSensorAdc>(
    board: &SimBoard<D, A>,
    adc_volts: (f64, f64),
) -> Settings {
    // The controller's model: the stage's differential gain on u_l = ū + v, with the default
    // truth hysteresis's Duhem shape (β the gain, γ = 0.75 β, α = 0.03 /V); the compensator
    // inverts it, the observer runs it.
    let gain = StageParams::paper()
        .second_order(PlantConfiguration::Differential)
        .a0_um_per_volt;
    let model = Model::Duhem(DuhemParams {
        alpha: 0.03,
        beta: gain,
        gamma: 0.75 * gain,
        offset: -70.0 * gain,
    });
    let sensor = board.sensor();
    let um_at = |volts: f64| (volts - sensor.offset_volts()) / sensor.volts_per_um();
    Settings {
        ranges: Scaling::new(0.0, 140.0, OUTPUT_UM.0, OUTPUT_UM.1).unwrap(),
        compensator: Some(model.clone()),
        observer: Some(model),
        drive: DriveSettings {
            configuration: Configuration::Differential,
            bias: 70.0,
            min_voltage: 0.0,
            max_voltage: 140.0,
            slew_rate: 1.0e6,
            safe_state: SafeState::Bias,
        },
        sensor: Some(SensorSettings {
            displacement_at_zero: um_at(adc_volts.0),
            displacement_at_full_scale: um_at(adc_volts.1),
            drift_limit: None,
        }),
        feedback: Some(FeedbackSettings::pi(0.0, 500.0, 1.0)),
        mode: Mode::ClosedLoop,
        creep: None,
        shaping: None,
        preview: None,
        output_map: None,
    }
}

/// Runs `controller` on `board`: a setpoint ramp of `ramp` ticks from `from_um` to `to_um`,
/// then a hold for the rest of `seconds`; returns the final displacement.
fn ramp_and_hold<D, A>(
    controller: &mut Controller,
    board: &mut SimBoard<D, A>,
    (from_um, to_um): (f64, f64),
    ramp: usize,
    seconds: f64,
) -> f64
where
    D: AnalogDualDac<Error: Debug>,
    A: AnalogSensorAdc<Error: Debug>,
{
    for k in 0..(seconds * 50_000.0) as usize {
        let f = (k as f64 / ramp as f64).min(1.0);
        let setpoint = signal_from_f64((from_um + f * (to_um - from_um)) / OUTPUT_UM.1);
        let (mut dac, mut adc) = board.split();
        controller.tick(Some(setpoint), &mut adc, &mut dac);
    }
    board.plant().stage_um()
}

fn track<D, A>(mut board: SimBoard<D, A>, adc_volts: (f64, f64), adc_bits: u8, tol_um: f64)
where
    D: AnalogDualDac<Error: Debug>,
    A: AnalogSensorAdc<Error: Debug>,
{
    let config = settings(&board, adc_volts)
        .build(&hardware(&board, adc_bits))
        .unwrap();
    let mut controller = Controller::new(config);
    let mut from = 0.0;
    for (target, ramp) in [(20.0, 500), (-12.0, 1), (3.5, 500)] {
        let x = ramp_and_hold(&mut controller, &mut board, (from, target), ramp, 0.1);
        from = target;
        assert!(
            (x - target).abs() < tol_um,
            "target {target} µm, stage at {x} µm"
        );
    }
    let c = controller.counters();
    assert_eq!((c.adc_errors, c.dac_errors), (0, 0));
    assert_eq!(board.periods(), 15_000);
}

#[test]
fn control_tick_holds_setpoints_on_the_board_with_internal_converters() {
    let board = InternalBoard::internal(&BoardConfig::paper(PlantConfiguration::Differential));
    // 12-bit ADC over 90 µm: 22 nm per code.
    track(board.unwrap(), (0.0, 3.3), 12, 0.06);
}

#[test]
fn control_tick_holds_setpoints_on_the_board_with_spi_converters() {
    let board = ExternalBoard::external(&BoardConfig::paper(PlantConfiguration::Differential));
    let board = board.unwrap();
    // 16-bit ADC over ±10.24 V = ±46 µm: 1.4 nm per code, plus 2 nm rms sensor noise. The
    // Duhem truth creeps under the amplifier's 1 mV noise (α Σ|Δu| relaxes it toward its
    // anhysteretic curve), which the integrator follows with a lag of some 10 nm.
    track(board, (-10.24, 10.24), 16, 0.03);
}

// ---- The closed-loop study, anti-windup, bumpless mode switch, notch, drift. ----

use twinstack::control::TickFlags;
use twinstack_cli::closed_loop::{
    self, identify_model, sensor_settings, ClosedLoopOptions, Configuration4,
};
use twinstack_identify::stage_model::StageModel;

fn study_options() -> ClosedLoopOptions {
    ClosedLoopOptions {
        out_dir: None,
        ..ClosedLoopOptions::default()
    }
}

/// The study's table, on the gains `twinstack tune` picks at each rate: feedforward + feedback
/// tracks the 750 Hz sine within 0.25 % of the stroke (max) at both rates, and beats feedback
/// alone on max and on RMS on every row; every compensated configuration beats none. (It
/// need not beat the feedforward alone where that is already this close: at 750 Hz the
/// feedback runs near its crossover, where it amplifies what it sees.)
///
/// The triangle's worst sample is its reversal: the setpoint's velocity turns by `Δv = 4·f·span`
/// in one tick, and the stage's lightly damped 21.8 kHz resonance answers with an overshoot of
/// `Δv/ω_n` — 0.29 % of the span at 100 Hz, whatever the rate or the loop (neither sees the
/// reversal coming). Its max is held within 0.1 % of that, and its RMS within 0.05 %.
#[test]
fn feedforward_plus_feedback_holds_a_quarter_percent_on_every_row() {
    let report = closed_loop::run(&study_options()).unwrap();
    assert_eq!(report.tracking.len(), 16);
    let mut text = Vec::new();
    closed_loop::print(&report, &mut text).unwrap();
    let text = String::from_utf8(text).unwrap();
    let resonance_hz = 21_807.0;
    let reversal_pct = 100.0 * 4.0 * 100.0 / (2.0 * std::f64::consts::PI * resonance_hz);
    for b in report
        .tracking
        .iter()
        .filter(|r| r.configuration == Configuration4::Both)
    {
        if b.waveform.contains("sine") {
            assert!(b.max_pct <= 0.25, "{text}");
        } else {
            assert!(b.max_pct <= reversal_pct + 0.1, "{reversal_pct} {text}");
            assert!(b.rms_pct <= 0.05, "{text}");
        }
        let fb = report
            .row(b.rate, b.waveform, Configuration4::Feedback)
            .unwrap();
        assert!(b.max_pct < fb.max_pct && b.rms_pct < fb.rms_pct, "{text}");
    }
    // The gains are what tune picked, one set per rate, not the fixed PI.
    assert_eq!(report.feedback.len(), 2, "{text}");
    for (rate, f) in &report.feedback {
        assert_ne!(*f, closed_loop::feedback_settings(*rate, true), "{text}");
    }
    for r in &report.tracking {
        let none = report
            .row(r.rate, r.waveform, Configuration4::None)
            .unwrap();
        if r.configuration != Configuration4::None {
            assert!(r.rms_pct < none.rms_pct, "{text}");
        }
        // The identified model agrees with the stage: no drift flag in the scored cycles of
        // any run (after boot's first cycles, which the score leaves out too), where the rate
        // leaves the observer time (at 50 kHz it always does).
        assert!(r.drift_ticks_after_start.unwrap_or(0) == 0, "{text}");
        if r.rate < 60e3 {
            assert_eq!(r.drift_ticks_after_start, Some(0), "{text}");
        }
    }
}

/// With the board's preview (`twinstack closed-loop --preview`: the settings' preview for the
/// resonance `tune` measures, every setpoint shaped before the compensator, the feedback
/// aiming at the setpoint itself). The triangle's reversal (`Δv/ω_n`, 0.29 % of the span,
/// above), which neither the feedforward nor the feedback sees coming, is taken out: under half
/// its unshaped error. And feedforward + tuned feedback with the preview is one configuration
/// that tracks every row of the study within 0.25 % (max) at both rates, the triangle's
/// reversal and the 750 Hz sine alike: the feedback corrects what the model misses, not the
/// shaping's standoff.
#[test]
fn a_preview_takes_the_triangle_s_reversal_out_in_closed_loop() {
    let report = closed_loop::run(&ClosedLoopOptions {
        preview: true,
        ..study_options()
    })
    .unwrap();
    let mut text = Vec::new();
    closed_loop::print(&report, &mut text).unwrap();
    let text = String::from_utf8(text).unwrap();
    assert_eq!(report.tracking.len(), 24, "{text}");
    assert_eq!(report.resonance.len(), 2, "{text}");
    for (_, hz, _) in &report.resonance {
        assert!((hz / 21_807.0 - 1.0).abs() < 0.01, "{text}");
    }
    for r in report.tracking.iter().filter(|r| r.preview) {
        let unshaped = report.row(r.rate, r.waveform, r.configuration).unwrap();
        if r.waveform.contains("triangle") {
            assert!(r.max_pct < 0.5 * unshaped.max_pct, "{text}");
        } else {
            assert!(r.max_pct <= 0.5, "{text}");
        }
        if r.configuration == Configuration4::Both {
            assert!(r.max_pct <= 0.25 && r.rms_pct <= 0.1, "{text}");
        }
    }
    // The rows without it are the study's own.
    let plain = closed_loop::run(&study_options()).unwrap();
    for p in &plain.tracking {
        let r = report.row(p.rate, p.waveform, p.configuration).unwrap();
        assert_eq!((r.max_pct, r.rms_pct), (p.max_pct, p.rms_pct), "{text}");
    }
}

/// The step: at 100 kHz the loop's gains excite the 21.8 kHz resonance without the notch
/// (it rings up to the correction limit); with the notch the ringing left 1–3 ms after the step
/// is the stage's own decay, at least 20 times smaller.
#[test]
fn the_notch_keeps_the_resonance_from_ringing() {
    let options = study_options();
    let model = identify_model(100_000.0, &options).unwrap();
    let without = closed_loop::step(100_000.0, &options, &model, false).unwrap();
    let with = closed_loop::step(100_000.0, &options, &model, true).unwrap();
    assert!(
        with.ringing_pct * 20.0 < without.ringing_pct,
        "ringing with notch {} %, without {} %",
        with.ringing_pct,
        without.ringing_pct
    );
    assert!(with.ringing_pct < 5.0, "{}", with.ringing_pct);
}

/// The study's control rate in these tests, Hz.
const RATE: f64 = 50_000.0;

/// Closed-loop settings of the study at 50 kHz with `model` (compensator and observer), a
/// slow integrator and the upper stack limit lowered to `max_voltage`.
fn study_settings(
    model: &StageModel,
    board: &ExternalBoard,
    ki_per_tick: f64,
    max_voltage: f64,
) -> Settings {
    let mut s = closed_loop::settings(
        RATE,
        model,
        sensor_settings(board),
        Configuration4::Both,
        true,
    );
    s.drive.max_voltage = max_voltage;
    if let Some(f) = s.feedback.as_mut() {
        f.ki = ki_per_tick * RATE;
    }
    s
}

/// [`study_settings`] built on the study's board.
fn build(settings: &Settings) -> ControlConfig {
    settings.build(&closed_loop::hardware(RATE)).unwrap()
}

/// Holds a setpoint the lowered stack limit cannot reach for 20 ms (the drive sits at the
/// limit, the error pushes up), then asks for one inside the range: the stage must be within
/// 2 % of the stroke of it within 100 ticks (2 ms). Without anti-windup the integrator would
/// have wound up to its limit (±50 % of the drive, tens of % of the stroke) and, at 0.005 per
/// tick, need some 400 ticks to unwind. (The band leaves room for the feedforward's own error
/// after the excursion: the model, fitted to a 750 Hz sine, lands the held setpoint about
/// 1.3 % low once the stage has come down from the limit, and this deliberately slow
/// integrator takes a few hundred ticks over that.)
#[test]
fn a_saturated_drive_does_not_wind_the_integrator_up() {
    let options = study_options();
    let model = identify_model(50_000.0, &options).unwrap();
    let mut board = closed_loop::board(50_000.0, options.sensor_noise_um).unwrap();
    let settings = study_settings(&model, &board, 0.005, 110.0);
    let s = settings.ranges;
    let config = build(&settings);
    let limit = config.feedback.unwrap().limit;
    let mut c = Controller::new(config);
    let (lo, hi) = (s.output_min, s.output_max);
    let sp = |um: f64| signal_from_f64(s.output_to_norm(um));
    let mut limited = 0;
    for _ in 0..1000 {
        let r = c.tick_board(Some(sp(lo + 0.95 * (hi - lo))), &mut board);
        limited += r.flags.contains(TickFlags::RANGE_LIMIT) as u32;
    }
    assert!(
        limited > 900,
        "the drive must sit at the limit ({limited} ticks)"
    );
    let wound = c.feedback_state().integrator();
    assert!(
        wound.abs() < limit / 4,
        "integrator {wound} held well inside its limit {limit}"
    );
    let target = lo + 0.5 * (hi - lo);
    let mut recovered = None;
    for k in 0..1000 {
        c.tick_board(Some(sp(target)), &mut board);
        let x = board.plant().stage_um();
        if (x - target).abs() < 0.02 * (hi - lo) {
            recovered.get_or_insert(k);
        } else {
            recovered = None;
        }
    }
    let k = recovered.expect("the stage settles at the new setpoint");
    assert!(k < 100, "recovered after {k} ticks");
}

/// Switches bypass → open loop → closed loop → open loop → bypass → closed loop while the
/// setpoint holds after a sine (so the hysteresis state is far from relaxed and the modes'
/// commands differ by hundreds of codes): the DAC code never jumps by more than 3 LSB at a
/// switch. Into open loop or bypass it then glides to the new mode's value (the transfer fades
/// by 1/256 per tick); into closed loop the loop takes over from the drive as it was and
/// removes the open loop's error at its own pace.
#[test]
fn mode_switches_are_bumpless() {
    let options = study_options();
    let model = identify_model(50_000.0, &options).unwrap();
    let mut board = closed_loop::board(50_000.0, options.sensor_noise_um).unwrap();
    let settings = Settings {
        mode: Mode::Bypass,
        ..study_settings(&model, &board, 0.2, 140.0)
    };
    let s = settings.ranges;
    let mut c = Controller::new(build(&settings));
    let mid = 0.5 * (s.output_min + s.output_max);
    let amp = 0.4 * (s.output_max - s.output_min);
    for k in 0..2000 {
        let um = mid + amp * (2.0 * std::f64::consts::PI * 100.0 * k as f64 / 50_000.0).sin();
        c.tick_board(Some(signal_from_f64(s.output_to_norm(um))), &mut board);
    }
    // Hold a point on the descending branch, away from the loop's tips.
    let hold = signal_from_f64(s.output_to_norm(mid + 0.3 * amp));
    let mut last = c.tick_board(Some(hold), &mut board).left;
    for _ in 0..3000 {
        last = c.tick_board(Some(hold), &mut board).left;
    }
    let mut gaps = Vec::new();
    for mode in [
        Mode::OpenLoop,
        Mode::ClosedLoop,
        Mode::OpenLoop,
        Mode::Bypass,
        Mode::ClosedLoop,
    ] {
        c.set_mode(mode).unwrap();
        assert_eq!(c.mode(), mode);
        let first = c.tick_board(Some(hold), &mut board).left;
        let jump = (first.0 as i32 - last.0 as i32).abs();
        assert!(jump <= 3, "switch to {mode:?}: the code jumped by {jump}");
        // Where this mode goes once the transfer has faded.
        let mut prev = first;
        for _ in 0..4000 {
            let now = c.tick_board(Some(hold), &mut board).left;
            assert!(
                mode == Mode::ClosedLoop || (now.0 as i32 - prev.0 as i32).abs() <= 20,
                "{mode:?}: glide step {prev:?} → {now:?}"
            );
            prev = now;
        }
        gaps.push((prev.0 as i32 - first.0 as i32).abs());
        last = prev;
    }
    // The switches were not trivial: some mode's settled command differs from the previous
    // mode's by hundreds of codes.
    assert!(
        gaps.iter().any(|&g| g > 200),
        "gaps between the modes' commands: {gaps:?}"
    );
}

/// The drift check: the identified model agrees with the stage (no flag); a model whose gain
/// is 10 % off is flagged within milliseconds; swapping the right model back in clears it.
#[test]
fn drift_is_flagged_for_a_wrong_model_and_clears_for_the_right_one() {
    let options = study_options();
    let model = identify_model(50_000.0, &options).unwrap();
    let mut board = closed_loop::board(50_000.0, options.sensor_noise_um).unwrap();
    let right = Settings {
        mode: Mode::OpenLoop,
        ..study_settings(&model, &board, 0.2, 140.0)
    };
    let mut wrong = right.clone();
    for m in [wrong.compensator.as_mut(), wrong.observer.as_mut()] {
        if let Some(Model::PrandtlIshlinskii(p)) = m {
            for w in p.weights.iter_mut() {
                *w *= 1.1;
            }
            p.a0 *= 1.1;
        } else {
            panic!("the study identifies P–I");
        }
    }
    let s = right.ranges;
    let sp = |k: usize| {
        let mid = 0.5 * (s.output_min + s.output_max);
        let amp = 0.3 * (s.output_max - s.output_min);
        let um = mid + amp * (2.0 * std::f64::consts::PI * 100.0 * k as f64 / 50_000.0).sin();
        signal_from_f64(s.output_to_norm(um))
    };
    // The drift check runs below the tick, with the observer: the tick and the services in
    // one call.
    let mut c = Observed::new(build(&right));
    let mut flags = 0;
    for k in 0..5000 {
        // After the first cycle: the observer's state at boot is a guess until the drive has
        // swept its range (the study leaves the same cycles out).
        flags += (c
            .tick_board(Some(sp(k)), &mut board)
            .flags
            .contains(TickFlags::DRIFT)
            && k >= 500) as u32;
    }
    assert_eq!(flags, 0, "the right model is not flagged");
    c.reload(build(&wrong));
    let mut flags = 0;
    for k in 5000..10_000 {
        flags += c
            .tick_board(Some(sp(k)), &mut board)
            .flags
            .contains(TickFlags::DRIFT) as u32;
    }
    assert!(
        flags > 1000,
        "the wrong model is flagged ({flags} of 5000 ticks)"
    );
    c.reload(build(&right));
    let mut last_flag = 0;
    for k in 10_000..15_000 {
        if c.tick_board(Some(sp(k)), &mut board)
            .flags
            .contains(TickFlags::DRIFT)
        {
            last_flag = k;
        }
    }
    assert!(
        last_flag < 10_500,
        "the flag clears (last at tick {last_flag})"
    );
    assert!(!c.observer.as_ref().unwrap().is_drifting());
}
