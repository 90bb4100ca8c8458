//! Settings: everything the controller is configured with, in physical units, validated and
//! turned into the fixed-point [`ControlConfig`] in one place, off the tick path.
//!
//! The firmware builds one from a parameter-load message or the flash record, `hal-sim` from a
//! parameter file; both then swap the result in whole between two ticks.

use crate::control::{Compensator, ControlConfig, Feedback, Observer};
use crate::drive::{DifferentialDrive, DriveError, DriveSettings};
use crate::duhem::{Duhem, InverseDuhem};
use crate::fixed_point::{gain_from_f64, signal_from_f64, MAX_GAIN_SUM};
use crate::params::{DuhemParams, ParamError, PiParams};
use crate::prandtl_ishlinskii::{InversePrandtlIshlinskii, PrandtlIshlinskii};
use crate::scaling::Scaling;

/// The hysteresis model (the compensator inverts it; the observer runs it forward).
#[allow(clippy::large_enum_variant)] // no heap on the board; settings live in one static
#[derive(Clone, Debug, PartialEq)]
pub enum Model {
    /// Prandtl–Ishlinskii.
    PrandtlIshlinskii(PiParams),
    /// Duhem.
    Duhem(DuhemParams),
}

/// Control mode.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Mode {
    /// No compensation: the drive follows the setpoint linearly (observer still runs).
    Bypass,
    /// Inverse-model feedforward.
    OpenLoop,
    /// Feedforward plus PI feedback on the sensor.
    ClosedLoop,
}

/// The position sensor: ADC code → displacement.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SensorSettings {
    /// ADC resolution, bits (1…30).
    pub adc_bits: u32,
    /// Displacement at code 0, output units.
    pub displacement_at_zero: f64,
    /// Displacement at full-scale code, output units (below `displacement_at_zero` for an
    /// inverted sensor).
    pub displacement_at_full_scale: f64,
}

/// PI feedback on the sensor error.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FeedbackSettings {
    /// The sensor.
    pub sensor: SensorSettings,
    /// Proportional gain: normalised drive per normalised displacement error.
    pub kp: f64,
    /// Integral gain, per second (normalised drive per normalised error per second).
    pub ki: f64,
    /// Largest correction, as a fraction of the normalised drive range (0…1].
    pub limit: f64,
}

/// Everything the controller is configured with.
#[derive(Clone, Debug, PartialEq)]
pub struct Settings {
    /// The model, if any (bypass needs none).
    pub model: Option<Model>,
    /// Model input (left-stack volts) and output (displacement) ranges.
    pub scaling: Scaling,
    /// The drive and its limits.
    pub drive: DriveSettings,
    /// Sensor feedback, where the stage has a sensor.
    pub feedback: Option<FeedbackSettings>,
    /// Mode.
    pub mode: Mode,
}

/// Why settings were refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SettingsError {
    /// The model's parameters were refused.
    Params(ParamError),
    /// The drive settings were refused.
    Drive(DriveError),
    /// Open or closed loop asked for without a model.
    ModeNeedsModel,
    /// Closed loop asked for without feedback settings.
    ClosedLoopNeedsSensor,
    /// Feedback gains, limit or sensor calibration out of range.
    BadFeedback,
}

impl From<ParamError> for SettingsError {
    fn from(e: ParamError) -> Self {
        SettingsError::Params(e)
    }
}

impl From<DriveError> for SettingsError {
    fn from(e: DriveError) -> Self {
        SettingsError::Drive(e)
    }
}

impl Settings {
    /// Validates everything and builds the fixed-point configuration.
    pub fn build(&self) -> Result<ControlConfig, SettingsError> {
        let drive = DifferentialDrive::new(&self.drive, &self.scaling)?;
        let (compensator, observer) = match (&self.model, self.mode) {
            (None, Mode::Bypass) => (Compensator::None, Observer::None),
            (None, _) => return Err(SettingsError::ModeNeedsModel),
            // The compensator first: "not invertible" says more than a range error would.
            (Some(Model::PrandtlIshlinskii(p)), mode) => {
                let compensator = match mode {
                    Mode::Bypass => Compensator::None,
                    _ => Compensator::InversePi(InversePrandtlIshlinskii::new(p, &self.scaling)?),
                };
                let observer = Observer::Pi(PrandtlIshlinskii::new(p, &self.scaling)?);
                (compensator, observer)
            }
            (Some(Model::Duhem(p)), mode) => {
                let compensator = match mode {
                    Mode::Bypass => Compensator::None,
                    _ => Compensator::InverseDuhem(InverseDuhem::new(p, &self.scaling)?),
                };
                let observer = Observer::Duhem(Duhem::new(p, &self.scaling)?);
                (compensator, observer)
            }
        };
        let feedback = match (self.mode, &self.feedback) {
            (Mode::ClosedLoop, None) => return Err(SettingsError::ClosedLoopNeedsSensor),
            (Mode::ClosedLoop, Some(fb)) => Some(self.feedback_config(fb)?),
            _ => None,
        };
        Ok(ControlConfig {
            compensator,
            observer,
            feedback,
            drive,
        })
    }

    /// The fixed-point feedback (sensor calibration and PI gains) for `fb` under these
    /// settings' scaling and control rate, validated.
    pub fn feedback_config(&self, fb: &FeedbackSettings) -> Result<Feedback, SettingsError> {
        let s = &fb.sensor;
        let at_zero = self.scaling.output_to_norm(s.displacement_at_zero);
        let at_full = self.scaling.output_to_norm(s.displacement_at_full_scale);
        let gain = at_full - at_zero;
        let ki_per_tick = fb.ki / self.drive.control_rate;
        let finite = [at_zero, gain, fb.kp, ki_per_tick, fb.limit]
            .iter()
            .all(|v| v.is_finite());
        let ok = finite
            && (1..=30).contains(&s.adc_bits)
            && gain != 0.0
            && gain.abs() < MAX_GAIN_SUM
            && at_zero.abs() < 1.9
            && (0.0..MAX_GAIN_SUM).contains(&fb.kp)
            && (0.0..1.0).contains(&ki_per_tick)
            && fb.limit > 0.0
            && fb.limit <= 1.0;
        if !ok {
            return Err(SettingsError::BadFeedback);
        }
        Ok(Feedback {
            adc_bits: s.adc_bits,
            sensor_offset: signal_from_f64(at_zero),
            sensor_gain: gain_from_f64(gain),
            kp: gain_from_f64(fb.kp),
            ki: gain_from_f64(ki_per_tick),
            limit: signal_from_f64(fb.limit * 2.0),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::{Configuration, SafeState};
    use crate::fixed_point::signal_from_f64;
    use crate::params::Thresholds;

    fn settings(mode: Mode) -> Settings {
        let r = Thresholds::Uniform.generate(9, 140.0).unwrap();
        let w = [0.06, 0.01, 0.008, 0.006, 0.004, 0.003, 0.002, 0.001, 0.001];
        Settings {
            model: Some(Model::PrandtlIshlinskii(
                PiParams::new(0.0, 0.0, &r, &w).unwrap(),
            )),
            scaling: Scaling::new(0.0, 140.0, 0.0, 13.0).unwrap(),
            drive: DriveSettings {
                configuration: Configuration::Differential,
                amplifier_full_scale: 150.0,
                bias: 70.0,
                right_idle: 0.0,
                min_voltage: 0.0,
                max_voltage: 140.0,
                slew_rate: 1.0e6,
                control_rate: 50_000.0,
                dac_full_scale: 4095,
                safe_state: SafeState::Bias,
            },
            feedback: Some(FeedbackSettings {
                sensor: SensorSettings {
                    adc_bits: 16,
                    displacement_at_zero: 0.0,
                    displacement_at_full_scale: 13.0,
                },
                kp: 0.2,
                ki: 2000.0,
                limit: 0.2,
            }),
            mode,
        }
    }

    #[test]
    fn each_mode_builds_the_matching_configuration() {
        let c = settings(Mode::Bypass).build().unwrap();
        assert!(matches!(c.compensator, Compensator::None) && c.feedback.is_none());
        assert!(matches!(c.observer, Observer::Pi(_)));
        let c = settings(Mode::OpenLoop).build().unwrap();
        assert!(matches!(c.compensator, Compensator::InversePi(_)) && c.feedback.is_none());
        let c = settings(Mode::ClosedLoop).build().unwrap();
        assert!(c.feedback.is_some());
    }

    /// Swapping configurations mid-run keeps the output where it is: the new models are
    /// relaxed at the present drive and the compensator starts out agreeing with them.
    #[test]
    fn reconfigure_mid_run_does_not_move_the_output() {
        use crate::board::fakes::{FixedAdc, RecordingDac};
        use crate::board::{AdcCode, DacCode};
        use crate::control::Controller;
        let mut adc = FixedAdc(Some(AdcCode(30000)));
        let mut c = Controller::new(settings(Mode::Bypass).build().unwrap());
        let mut dac = RecordingDac::default();
        for k in 0..500 {
            let sp = signal_from_f64(0.6 * libm::sin(k as f64 * 0.01));
            c.tick(Some(sp), &mut adc, &mut dac);
        }
        let before = (dac.left, dac.right);
        c.reconfigure(settings(Mode::OpenLoop).build().unwrap());
        c.tick(None, &mut adc, &mut dac);
        let moved = |a: DacCode, b: DacCode| (a.0 as i32 - b.0 as i32).abs();
        assert!(moved(dac.left, before.0) <= 1 && moved(dac.right, before.1) <= 1);
    }

    #[test]
    fn refusals_say_what_is_wrong() {
        let mut s = settings(Mode::ClosedLoop);
        s.feedback = None;
        assert_eq!(s.build(), Err(SettingsError::ClosedLoopNeedsSensor));
        let mut s = settings(Mode::OpenLoop);
        s.model = None;
        assert_eq!(s.build(), Err(SettingsError::ModeNeedsModel));
        let mut s = settings(Mode::ClosedLoop);
        s.feedback.as_mut().unwrap().kp = f64::NAN;
        assert_eq!(s.build(), Err(SettingsError::BadFeedback));
        let mut s = settings(Mode::OpenLoop);
        s.drive.bias = 145.0;
        assert_eq!(
            s.build(),
            Err(SettingsError::Drive(DriveError::BiasOutsideRange))
        );
        let mut s = settings(Mode::OpenLoop);
        if let Some(Model::PrandtlIshlinskii(p)) = s.model.as_mut() {
            p.weights[0] = -0.1;
        }
        assert_eq!(
            s.build(),
            Err(SettingsError::Params(ParamError::FirstWeightNotPositive))
        );
    }
}
