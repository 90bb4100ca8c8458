//! The emulated board behind the library's `DualDac` / `SensorAdc`: both converter variants
//! drive the plant the same way, the sensor is read with one period of latency, and errors
//! stop the board instead of advancing it.

use core::fmt::Debug;
use hal_sim::converters::{AnalogDualDac, AnalogSensorAdc, InternalDacError};
use hal_sim::plant::{Configuration, PlantError, StageParams};
use hal_sim::sim_board::{BoardConfig, BoardError, ExternalBoard, InternalBoard, SimBoard};
use twinstack::board::{DacCode, DualDac, SensorAdc};

fn quiet_linear() -> BoardConfig {
    let mut c = BoardConfig::paper(Configuration::Differential);
    c.plant = c.plant.without_hysteresis();
    c.sensor_noise_um = 0.0;
    c.amplifier_noise_volts = 0.0;
    c
}

/// The DAC code giving `volts` at the amplifier output (0–150 V over the DAC's full scale).
fn code<B: DualDac>(board: &B, volts: f64) -> DacCode {
    let fs = DualDac::full_scale(board).0 as f64 + 1.0;
    DacCode((volts / 150.0 * fs).round().min(fs - 1.0) as u16)
}

/// Displacement (µm) a sensor reading stands for, on an ADC spanning `adc_volts`.
fn um<D: AnalogDualDac, A: AnalogSensorAdc>(
    board: &SimBoard<D, A>,
    reading: u32,
    adc_volts: (f64, f64),
) -> f64 {
    let fs = SensorAdc::full_scale(board).0 as f64 + 1.0;
    let volts = adc_volts.0 + (reading as f64 + 0.5) / fs * (adc_volts.1 - adc_volts.0);
    (volts - board.sensor().offset_volts()) / board.sensor().volts_per_um()
}

fn settle<D, A>(board: &mut SimBoard<D, A>, ul: f64, ur: f64) -> f64
where
    D: AnalogDualDac<Error: Debug>,
    A: AnalogSensorAdc<Error: Debug>,
{
    let (l, r) = (code(board, ul), code(board, ur));
    for _ in 0..4000 {
        board.read().unwrap();
        board.write_both(l, r).unwrap();
    }
    board.plant().stage_um()
}

#[test]
fn both_variants_settle_where_the_stage_gain_puts_them() {
    let config = quiet_linear();
    let a0 = StageParams::paper()
        .second_order(Configuration::Differential)
        .a0_um_per_volt;
    let expected = a0 * 20.0; // ū = 70 V, v = 20 V
    let mut internal = InternalBoard::internal(&config).unwrap();
    let mut external = ExternalBoard::external(&config).unwrap();
    let xi = settle(&mut internal, 90.0, 50.0);
    let xe = settle(&mut external, 90.0, 50.0);
    // 12-bit codes are 37 mV apart at the stacks, 16-bit ones 2.3 mV.
    assert!(
        (xi - expected).abs() < a0 * 0.04,
        "internal {xi} vs {expected}"
    );
    assert!(
        (xe - expected).abs() < a0 * 0.003,
        "external {xe} vs {expected}"
    );
    assert_eq!(internal.periods(), 4000);
    assert!((internal.time_seconds() - 0.08).abs() < 1e-12);
}

/// On a ramp that moves the stage by many LSBs per period, each reading matches the
/// displacement one period before it, not the present one.
#[test]
fn sensor_readings_lag_the_stage_by_one_period_on_both_variants() {
    let config = quiet_linear();
    let mut internal = InternalBoard::internal(&config).unwrap();
    let mut external = ExternalBoard::external(&config).unwrap();
    check_latency(&mut internal, (0.0, 3.3), 0.03);
    check_latency(&mut external, (-10.24, 10.24), 0.003);
}

fn check_latency<D, A>(board: &mut SimBoard<D, A>, adc_volts: (f64, f64), tolerance_um: f64)
where
    D: AnalogDualDac<Error: Debug>,
    A: AnalogSensorAdc<Error: Debug>,
{
    settle(board, 70.0, 70.0);
    let mut history = vec![board.plant().stage_um()];
    for k in 0..60 {
        let reading = board.read().unwrap().0;
        let seen = um(board, reading, adc_volts);
        if k >= 10 {
            let previous = history[history.len() - 2];
            let present = history[history.len() - 1];
            assert!(
                (seen - previous).abs() < tolerance_um,
                "{k}: {seen} vs {previous}"
            );
            assert!(
                (present - previous).abs() > 5.0 * tolerance_um,
                "the ramp is too slow"
            );
        }
        let v = 1.0 * k as f64; // 1 V per period: ≈ 0.5 µm per period once moving
        let (l, r) = (code(board, 70.0 + v), code(board, 70.0 - v));
        board.write_both(l, r).unwrap();
        history.push(board.plant().stage_um());
    }
}

#[test]
fn external_board_exchanges_two_dac_frames_and_one_adc_frame_per_period() {
    let config = BoardConfig::paper(Configuration::Differential);
    let mut board = ExternalBoard::external(&config).unwrap();
    let (dac0, adc0) = (board.dac().device().frames(), board.adc().device().frames());
    for k in 0..100u16 {
        board.read().unwrap();
        board
            .write_both(DacCode(20_000 + k), DacCode(20_000 - k))
            .unwrap();
    }
    assert_eq!(board.dac().device().frames() - dac0, 200);
    assert_eq!(board.adc().device().frames() - adc0, 100);
    assert!(board.dac().device().errors().is_empty());
    assert!(board.adc().device().errors().is_empty());
    assert_eq!(board.dac().device().dac_codes(), [20_099, 19_901]);
}

#[test]
fn a_refused_dac_write_does_not_advance_the_board() {
    let mut board = InternalBoard::internal(&quiet_linear()).unwrap();
    board.write_both(DacCode(100), DacCode(100)).unwrap();
    assert_eq!(
        board.write_both(DacCode(5000), DacCode(0)),
        Err(InternalDacError::LeftOutOfRange(5000))
    );
    assert_eq!(board.periods(), 1);
}

#[test]
fn invalid_board_settings_are_refused_with_their_reason() {
    let mut c = BoardConfig::paper(Configuration::Unidirectional);
    c.sensor_range_um = (10.0, 10.0);
    assert_eq!(
        InternalBoard::internal(&c).err(),
        Some(BoardError::SensorRange((10.0, 10.0)))
    );
    let mut c = BoardConfig::paper(Configuration::Unidirectional);
    c.plant.dt = -1.0;
    assert_eq!(
        ExternalBoard::external(&c).err(),
        Some(BoardError::Plant(PlantError::InvalidTimeStep(-1.0)))
    );
}

/// The two handles of `split` (what the control tick takes) drive the board exactly as the
/// board's own trait methods do: same readings, same displacement, same noise.
#[test]
fn split_handles_drive_the_board_like_the_board_itself() {
    let config = BoardConfig::paper(Configuration::Differential);
    let mut whole = ExternalBoard::external(&config).unwrap();
    let mut parts = ExternalBoard::external(&config).unwrap();
    for k in 0..300u16 {
        let (l, r) = (DacCode(18_000 + 20 * k), DacCode(30_000 - 20 * k));
        let a = whole.read().unwrap();
        whole.write_both(l, r).unwrap();
        let (mut dac, mut adc) = parts.split();
        let b = adc.read().unwrap();
        dac.write_both(l, r).unwrap();
        assert_eq!(a, b, "period {k}");
    }
    assert_eq!(whole.plant().stage_um(), parts.plant().stage_um());
    assert_eq!(parts.periods(), 300);
}
