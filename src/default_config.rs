//! The compiled-in default configuration the firmware boots with (and the tick-cost bench
//! measures), until identified parameters are stored on the board.
//!
//! The stage is the first paper's differential one: both stacks on a 150 V amplifier, bias
//! `ū = 70 V`, each stack within 0…140 V, so the left stack's voltage (the models' input)
//! spans 0…140 V and the stage about 0…70 µm. The hysteresis parameters below are
//! representative, not identified: a rising, concave P–I loading curve (`w_1` largest, the rest
//! decaying geometrically, every partial sum positive, so the analytic inverse exists) and a
//! Duhem model of similar slope. Replace them with the identification tool's output.

use crate::control::{Compensator, ControlConfig, Observer};
use crate::drive::{Configuration, DifferentialDrive, DriveError, DriveSettings, SafeState};
use crate::duhem::{Duhem, InverseDuhem};
use crate::feedback::{Derivative, Feedback};
use crate::fixed_point::{q0_32_from_f64, q1_31_from_f64, q4_28_from_f64, signal_from_f64};
use crate::notch::{Notch, NotchDesign, NotchError};
use crate::params::{DuhemParams, ParamError, PiParams, Thresholds, MAX_OPERATORS};
use crate::prandtl_ishlinskii::InversePrandtlIshlinskii;
use crate::protocol::messages::{FeedbackParams, ModelParams, ParamSet, MAX_PARAM_OPERATORS};
use crate::protocol::param_load::BoardProfile;
use crate::scaling::Scaling;
use crate::settings::{Mode, SensorSettings};

/// Left-stack voltage range, volts (model input).
pub const DRIVE_VOLTS: (f64, f64) = (0.0, 140.0);
/// Stage displacement range, µm (model output).
pub const STROKE_UM: (f64, f64) = (0.0, 70.0);
/// Play operators of the default inverse P–I.
pub const DEFAULT_OPERATORS: usize = 16;

/// Which feedforward compensator to build.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CompensatorKind {
    /// Bypass.
    None,
    /// Inverse P–I with this many play operators (1..=[`MAX_OPERATORS`]).
    InversePi(usize),
    /// Inverse Duhem.
    InverseDuhem,
}

/// Why the default configuration could not be built (only for an out-of-range operator
/// count or rate: the compiled-in parameters themselves are valid).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ConfigError {
    /// A model parameter was refused.
    Model(ParamError),
    /// The drive settings were refused.
    Drive(DriveError),
    /// The notch cannot be designed at this control rate.
    Notch(NotchError),
}

impl From<NotchError> for ConfigError {
    fn from(e: NotchError) -> Self {
        ConfigError::Notch(e)
    }
}

impl From<ParamError> for ConfigError {
    fn from(e: ParamError) -> Self {
        ConfigError::Model(e)
    }
}

impl From<DriveError> for ConfigError {
    fn from(e: DriveError) -> Self {
        ConfigError::Drive(e)
    }
}

/// The model scaling: 0…140 V onto 0…70 µm.
pub fn scaling() -> Scaling {
    // Constant, non-empty ranges: `Scaling::new` cannot refuse them.
    Scaling {
        input_min: DRIVE_VOLTS.0,
        input_max: DRIVE_VOLTS.1,
        output_min: STROKE_UM.0,
        output_max: STROKE_UM.1,
    }
}

/// Differential drive on a 150 V amplifier and the 12-bit DAC, 0…140 V per stack, bias 70 V,
/// slew limit 2 V/µs, at `control_rate_hz`.
pub fn drive_settings(control_rate_hz: f64, safe_state: SafeState) -> DriveSettings {
    DriveSettings {
        configuration: Configuration::Differential,
        amplifier_full_scale: 150.0,
        bias: 70.0,
        right_idle: 70.0,
        min_voltage: 0.0,
        max_voltage: 140.0,
        slew_rate: 2.0e6,
        control_rate: control_rate_hz,
        dac_full_scale: 4095,
        safe_state,
    }
}

/// A representative P–I model with `n` operators, uniform thresholds over the 140 V span:
/// total slope 0.5 µm/V, `w_1 = 0.3 µm/V`, the other 0.2 µm/V decaying by 0.8 per operator.
pub fn pi_params(n: usize) -> Result<PiParams, ParamError> {
    let thresholds = Thresholds::Uniform.generate(n, DRIVE_VOLTS.1 - DRIVE_VOLTS.0)?;
    // 0.8^i by repeated multiplication (no `libm::pow` in the firmware image).
    let mut decay = [0.0; MAX_OPERATORS];
    let mut p = 1.0;
    for d in decay.iter_mut().take(n).skip(1) {
        p *= 0.8;
        *d = p;
    }
    let tail: f64 = decay.iter().sum();
    let mut weights = [0.0; MAX_OPERATORS];
    for (i, w) in weights.iter_mut().enumerate().take(n) {
        *w = if i == 0 {
            0.3
        } else if tail > 0.0 {
            0.2 * decay[i] / tail
        } else {
            0.0
        };
    }
    let a0 = if n == 1 { 0.2 } else { 0.0 };
    PiParams::new(a0, 0.0, &thresholds, &weights[..n])
}

/// A representative Duhem model: anhysteretic slope 0.5 µm/V through the origin, slope after
/// a reversal 0.35 µm/V, `α = 0.02 /V`.
pub fn duhem_params() -> DuhemParams {
    DuhemParams {
        alpha: 0.02,
        beta: 0.5,
        gamma: 0.35,
        offset: 0.0,
    }
}

/// Sensor feedback: a 12-bit ADC spanning the stroke, `kp = 0.2`, `ki = 0.01` per tick,
/// correction limited to ±0.2 (normalised drive), drift flagged beyond 2 % of the stroke; no
/// notch, no derivative.
pub fn feedback() -> Feedback {
    let limit = signal_from_f64(0.2);
    let kp = q4_28_from_f64(0.2);
    Feedback {
        adc_bits: 12,
        sensor_offset: q4_28_from_f64(-1.0),
        sensor_gain: q4_28_from_f64(2.0),
        kp,
        error_bound: Feedback::error_bound(limit, kp),
        ki: q0_32_from_f64(0.01),
        derivative: None,
        limit,
        notch: None,
        drift_limit: signal_from_f64(0.04) as u32,
    }
}

/// The differential stage's first resonance as a notch: 21.8 kHz, Q = 2, full depth.
pub fn stage_notch() -> NotchDesign {
    NotchDesign {
        frequency_hz: 21_800.0,
        q: 2.0,
        depth: 0.0,
    }
}

/// [`feedback`] plus the [`stage_notch`] designed for `control_rate_hz` and a derivative term
/// (`kd = 0.05` per tick, low pass at a tenth of the rate).
pub fn feedback_with_notch(control_rate_hz: f64) -> Result<Feedback, ConfigError> {
    Ok(Feedback {
        notch: Some(Notch::new(&stage_notch(), control_rate_hz)?),
        derivative: Some(Derivative {
            kd: q4_28_from_f64(0.05),
            smoothing: q1_31_from_f64(1.0 - libm::exp(-2.0 * core::f64::consts::PI / 10.0)),
        }),
        ..feedback()
    })
}

/// A complete configuration: `compensator`, the Duhem observer, feedback on, the default drive.
pub fn control_config(
    compensator: CompensatorKind,
    control_rate_hz: f64,
    safe_state: SafeState,
) -> Result<ControlConfig, ConfigError> {
    let s = scaling();
    let compensator = match compensator {
        CompensatorKind::None => Compensator::None,
        CompensatorKind::InversePi(n) => {
            Compensator::InversePi(InversePrandtlIshlinskii::new(&pi_params(n)?, &s)?)
        }
        CompensatorKind::InverseDuhem => {
            Compensator::InverseDuhem(InverseDuhem::new(&duhem_params(), &s)?)
        }
    };
    Ok(ControlConfig {
        compensator,
        observer: Observer::Duhem(Duhem::new(&duhem_params(), &s)?),
        feedback: Some(feedback()),
        drive: DifferentialDrive::new(&drive_settings(control_rate_hz, safe_state), &s)?,
        mode: Mode::ClosedLoop,
    })
}

/// The board as a parameter load cannot change it: 150 V amplifier on the 12-bit DAC at
/// `control_rate_hz`, and the 12-bit sensor ADC spanning the stroke (code 0 at 0 µm, full
/// scale at 70 µm — the calibration [`feedback`] uses).
pub fn board_profile(control_rate_hz: f64) -> BoardProfile {
    BoardProfile {
        amplifier_full_scale: 150.0,
        dac_full_scale: 4095,
        control_rate_hz,
        sensor: Some(SensorSettings {
            adc_bits: 12,
            displacement_at_zero: STROKE_UM.0,
            displacement_at_full_scale: STROKE_UM.1,
        }),
    }
}

/// The parameter set the firmware boots on when flash holds none: the representative P–I
/// model of [`pi_params`] with [`DEFAULT_OPERATORS`] operators (compensator and observer),
/// the drive of [`drive_settings`], the gains of [`feedback`], closed loop.
pub fn boot_param_set(safe_state: SafeState) -> Result<ParamSet, ParamError> {
    let pi = pi_params(DEFAULT_OPERATORS)?;
    let f32s = |v: &[f64]| -> heapless::Vec<f32, MAX_PARAM_OPERATORS> {
        v.iter().map(|&x| x as f32).collect()
    };
    let d = drive_settings(1.0, safe_state);
    Ok(ParamSet {
        model: ModelParams::PrandtlIshlinskii {
            a0: pi.a0 as f32,
            offset: pi.offset as f32,
            thresholds: f32s(&pi.thresholds),
            weights: f32s(&pi.weights),
        },
        input_range: [DRIVE_VOLTS.0 as f32, DRIVE_VOLTS.1 as f32],
        output_range: [STROKE_UM.0 as f32, STROKE_UM.1 as f32],
        configuration: d.configuration,
        bias: d.bias as f32,
        voltage_limits: [d.min_voltage as f32, d.max_voltage as f32],
        slew_rate: d.slew_rate as f32,
        safe_state,
        // kp 0.2, ki 0.01 per tick at the default 50 kHz (500 per second), correction within
        // ±0.2 of the normalised drive (a tenth of its range): as `feedback()`.
        feedback: Some(FeedbackParams {
            kp: 0.2,
            ki: 500.0,
            kd: 0.0,
            derivative_cutoff_hz: 1.0,
            limit: 0.1,
            notch: None,
            drift_limit: Some(0.02),
        }),
        mode: Mode::ClosedLoop,
    })
}

/// The firmware's boot configuration: inverse P–I with [`DEFAULT_OPERATORS`] operators.
pub fn boot_config(
    control_rate_hz: f64,
    safe_state: SafeState,
) -> Result<ControlConfig, ConfigError> {
    control_config(
        CompensatorKind::InversePi(DEFAULT_OPERATORS),
        control_rate_hz,
        safe_state,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::board::{AdcCode, DacCode, DualDac, SensorAdc};
    use crate::control::Controller;
    use core::convert::Infallible;

    struct Dac(DacCode, DacCode);
    impl DualDac for Dac {
        type Error = Infallible;
        fn full_scale(&self) -> DacCode {
            DacCode(4095)
        }
        fn write_both(&mut self, l: DacCode, r: DacCode) -> Result<(), Infallible> {
            self.0 = l;
            self.1 = r;
            Ok(())
        }
    }
    struct Adc;
    impl SensorAdc for Adc {
        type Error = Infallible;
        fn full_scale(&self) -> AdcCode {
            AdcCode(4095)
        }
        fn read(&mut self) -> Result<AdcCode, Infallible> {
            Ok(AdcCode(2048))
        }
    }

    /// The boot parameter set, through the protocol's load path, runs the same compensator,
    /// feedback and drive as [`boot_config`] (observer aside: a load runs one model both ways).
    #[test]
    fn the_boot_parameter_set_loads_to_the_boot_configuration() {
        use crate::protocol::param_load::settings_from_params;
        let rate = 50_000.0;
        let p = boot_param_set(SafeState::Bias).unwrap();
        let s = settings_from_params(&p, &board_profile(rate)).unwrap();
        let c = s.build().unwrap();
        let want = boot_config(rate, SafeState::Bias).unwrap();
        let (fa, fb) = (c.feedback.unwrap(), want.feedback.unwrap());
        assert_eq!(
            (fa.sensor_offset, fa.sensor_gain),
            (fb.sensor_offset, fb.sensor_gain)
        );
        // kp crosses the wire as f32 (0.2 is not exact there): within an LSB of Q4.28.
        assert!((fa.kp - fb.kp).abs() <= 1, "{fa:?} vs {fb:?}");
        assert_eq!(fa.ki, fb.ki);
        assert!((fa.limit - fb.limit).abs() < 16, "{fa:?} vs {fb:?}"); // f32 on the wire
        assert_eq!(c.drive.safe_codes(), want.drive.safe_codes());
        assert_eq!(c.drive.drive_range(), want.drive.drive_range());
        assert!(matches!(c.compensator, Compensator::InversePi(_)));
        // Same drive from the same setpoints (f32 on the wire: within a DAC code).
        use crate::board::fakes::{FixedAdc, RecordingDac};
        let (mut ours, mut theirs) = (Controller::new(c), Controller::new(want));
        let (mut da, mut db) = (RecordingDac::default(), RecordingDac::default());
        let mut adc = FixedAdc(Some(AdcCode(2048)));
        for k in 0..2000 {
            let sp = crate::fixed_point::signal_from_f64(0.8 * libm::sin(k as f64 * 0.005));
            ours.tick(Some(sp), &mut adc, &mut da);
            theirs.tick(Some(sp), &mut adc, &mut db);
            assert!((da.left.0 as i32 - db.left.0 as i32).abs() <= 1, "tick {k}");
        }
    }

    #[test]
    fn every_compensator_the_bench_measures_builds() {
        for kind in [
            CompensatorKind::None,
            CompensatorKind::InversePi(8),
            CompensatorKind::InversePi(16),
            CompensatorKind::InversePi(32),
            CompensatorKind::InverseDuhem,
        ] {
            let c = control_config(kind, 50_000.0, SafeState::Bias);
            assert!(c.is_ok(), "{kind:?}: {c:?}");
        }
        assert_eq!(
            control_config(CompensatorKind::InversePi(33), 50_000.0, SafeState::Bias),
            Err(ConfigError::Model(ParamError::TooManyOperators {
                count: 33
            }))
        );
    }

    #[test]
    fn boot_config_rests_at_the_bias_and_safe_state_follows_the_setting() {
        let bias_code = (70.0f64 / 150.0 * 4095.0).round() as u16;
        let c = Controller::new(boot_config(50_000.0, SafeState::Bias).unwrap());
        assert_eq!(c.safe_codes(), (DacCode(bias_code), DacCode(bias_code)));
        let z = Controller::new(boot_config(50_000.0, SafeState::Zero).unwrap());
        assert_eq!(z.safe_codes(), (DacCode(0), DacCode(0)));
        // With the sensor reading mid-stroke and no setpoint, the outputs stay near the bias
        // and mirror about it.
        let mut c = c;
        let mut dac = Dac(DacCode(0), DacCode(0));
        for _ in 0..10 {
            c.tick(None, &mut Adc, &mut dac);
        }
        let sum = dac.0 .0 as i32 + dac.1 .0 as i32;
        assert!(
            (sum - 2 * bias_code as i32).abs() <= 1,
            "{:?}",
            (dac.0, dac.1)
        );
    }
}
