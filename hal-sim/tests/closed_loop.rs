//! End to end: the library's control tick (`Controller::tick`, the code the interrupt runs)
//! drives the simulated board through `SimBoard::split`, with the internal converters and with
//! the SPI drivers on the emulated chips, and closes the loop on the emulated sensor.
//!
//! The setpoint ramps over 10 ms to 20 µm, steps in one tick to −12 µm (the step that made the
//! inverse Duhem limit-cycle before its drive step was capped at `1/α`), and ramps to 3.5 µm.

use core::fmt::Debug;
use hal_sim::converters::{AnalogDualDac, AnalogSensorAdc};
use hal_sim::plant::{Configuration as PlantConfiguration, StageParams};
use hal_sim::sim_board::{BoardConfig, ExternalBoard, InternalBoard, SimBoard};
use twinstack::board::DualDac;
use twinstack::control::Controller;
use twinstack::drive::{Configuration, DriveSettings, SafeState};
use twinstack::fixed_point::signal_from_f64;
use twinstack::settings::{FeedbackSettings, Mode, Model, SensorSettings, Settings};
use twinstack::{DuhemParams, Scaling};

/// Output range of the controller's model, µm (normalised setpoint 1.0 = 40 µm).
const OUTPUT_UM: (f64, f64) = (-40.0, 40.0);

/// Closed-loop settings for a board whose ADC spans `adc_volts` with `adc_bits`.
fn settings<D: AnalogDualDac, A: AnalogSensorAdc>(
    board: &SimBoard<D, A>,
    adc_volts: (f64, f64),
    adc_bits: u32,
) -> Settings {
    // The controller's model: the stage's differential gain on u_l = ū + v, with the default
    // truth hysteresis's Duhem shape (β the gain, γ = 0.75 β, α = 0.03 /V).
    let gain = StageParams::paper()
        .second_order(PlantConfiguration::Differential)
        .a0_um_per_volt;
    let model = DuhemParams {
        alpha: 0.03,
        beta: gain,
        gamma: 0.75 * gain,
        offset: -70.0 * gain,
    };
    let sensor = board.sensor();
    let um_at = |volts: f64| (volts - sensor.offset_volts()) / sensor.volts_per_um();
    Settings {
        model: Some(Model::Duhem(model)),
        scaling: Scaling::new(0.0, 140.0, OUTPUT_UM.0, OUTPUT_UM.1).unwrap(),
        drive: DriveSettings {
            configuration: Configuration::Differential,
            amplifier_full_scale: 150.0,
            bias: 70.0,
            right_idle: 0.0,
            min_voltage: 0.0,
            max_voltage: 140.0,
            slew_rate: 1.0e6,
            control_rate: 50_000.0,
            dac_full_scale: DualDac::full_scale(board).0,
            safe_state: SafeState::Bias,
        },
        feedback: Some(FeedbackSettings::pi(
            SensorSettings {
                adc_bits,
                displacement_at_zero: um_at(adc_volts.0),
                displacement_at_full_scale: um_at(adc_volts.1),
            },
            0.0,
            500.0,
            1.0,
        )),
        mode: Mode::ClosedLoop,
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

fn track<D, A>(mut board: SimBoard<D, A>, adc_volts: (f64, f64), adc_bits: u32, tol_um: f64)
where
    D: AnalogDualDac<Error: Debug>,
    A: AnalogSensorAdc<Error: Debug>,
{
    let config = settings(&board, adc_volts, adc_bits).build().unwrap();
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
