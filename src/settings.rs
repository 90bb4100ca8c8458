//! Settings: everything the controller is configured with, in physical units, validated and
//! turned into the fixed-point [`ControlConfig`] in one place, off the tick path.
//!
//! The firmware builds one from a parameter-load message or the flash record, `hal-sim` from a
//! parameter file; both then swap the result in whole between two ticks.

use crate::control::{Compensator, ControlConfig, Observer};
use crate::drive::{DifferentialDrive, DriveError, DriveSettings};
use crate::duhem::{Duhem, InverseDuhem};
use crate::feedback::{Derivative, Feedback};
use crate::fixed_point::{q0_32_from_f64, q1_31_from_f64, q4_28_from_f64, signal_from_f64};
use crate::notch::{Notch, NotchDesign, NotchError};
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

/// Control mode. Settings name the mode to start in; [`crate::control::Controller::set_mode`]
/// switches between them later, between two ticks and without a bump.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Mode {
    /// No compensation: the drive follows the setpoint linearly (observer still runs).
    Bypass,
    /// Inverse-model feedforward.
    OpenLoop,
    /// Feedforward plus PI(D) feedback on the sensor.
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

/// PI(D) feedback on the sensor error, the resonance notch and the drift check
/// (see [`crate::feedback`]). Gains are in normalised units: drive as a fraction of the model's
/// input half-range per displacement error as a fraction of its output half-range.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FeedbackSettings {
    /// The sensor.
    pub sensor: SensorSettings,
    /// Proportional gain, 0 ≤ kp < 8.
    pub kp: f64,
    /// Integral gain, per second; per tick (`ki / control rate`) it must be below 1/2.
    pub ki: f64,
    /// Derivative gain, seconds (0: no derivative term); per tick (`kd · control rate`) below 8.
    pub kd: f64,
    /// Corner of the derivative's low pass, Hz (0 < f < control rate / 2; unused when kd = 0).
    pub derivative_cutoff_hz: f64,
    /// Largest correction, as a fraction of the normalised drive range (0…1].
    pub limit: f64,
    /// Notch on the error at the stage's resonance, if any.
    pub notch: Option<NotchDesign>,
    /// Drift limit: largest low-passed |measured − observer estimate| as a fraction of the
    /// output range (0…1], or `None` for no drift check.
    pub drift_limit: Option<f64>,
}

impl FeedbackSettings {
    /// PI feedback with the given gains and limit; no derivative, notch or drift check.
    pub fn pi(sensor: SensorSettings, kp: f64, ki: f64, limit: f64) -> Self {
        Self {
            sensor,
            kp,
            ki,
            kd: 0.0,
            derivative_cutoff_hz: 1.0,
            limit,
            notch: None,
            drift_limit: None,
        }
    }
}

impl FeedbackSettings {
    /// The feedback a parameter load carries, with the board's `sensor` calibration.
    pub fn from_wire(
        p: &crate::protocol::messages::FeedbackParams,
        sensor: SensorSettings,
    ) -> Self {
        Self {
            sensor,
            kp: p.kp as f64,
            ki: p.ki as f64,
            kd: p.kd as f64,
            derivative_cutoff_hz: p.derivative_cutoff_hz as f64,
            limit: p.limit as f64,
            notch: p.notch.map(|n| NotchDesign {
                frequency_hz: n.frequency_hz as f64,
                q: n.q as f64,
                depth: n.depth as f64,
            }),
            drift_limit: p.drift_limit.map(|d| d as f64),
        }
    }
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
    /// Feedback gains, limit, drift limit or sensor calibration out of range.
    BadFeedback,
    /// The notch design was refused.
    Notch(NotchError),
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
        // Every part the configuration has is built, whatever the mode, so that
        // `Controller::set_mode` can switch later; the mode says what the tick runs now.
        let (compensator, observer) = match &self.model {
            None if self.mode != Mode::Bypass => return Err(SettingsError::ModeNeedsModel),
            None => (Compensator::None, Observer::None),
            // The compensator first: "not invertible" says more than a range error would.
            Some(Model::PrandtlIshlinskii(p)) => (
                Compensator::InversePi(InversePrandtlIshlinskii::new(p, &self.scaling)?),
                Observer::Pi(PrandtlIshlinskii::new(p, &self.scaling)?),
            ),
            Some(Model::Duhem(p)) => (
                Compensator::InverseDuhem(InverseDuhem::new(p, &self.scaling)?),
                Observer::Duhem(Duhem::new(p, &self.scaling)?),
            ),
        };
        let feedback = match (self.mode, &self.feedback) {
            (Mode::ClosedLoop, None) => return Err(SettingsError::ClosedLoopNeedsSensor),
            (_, Some(fb)) => Some(self.feedback_config(fb, self.model.is_some())?),
            (_, None) => None,
        };
        Ok(ControlConfig {
            compensator,
            observer,
            feedback,
            drive,
            mode: self.mode,
        })
    }

    /// The fixed-point feedback; `observed` says whether an observer runs (the drift check
    /// needs one).
    pub fn feedback_config(
        &self,
        fb: &FeedbackSettings,
        observed: bool,
    ) -> Result<Feedback, SettingsError> {
        let s = &fb.sensor;
        let rate = self.drive.control_rate;
        let at_zero = self.scaling.output_to_norm(s.displacement_at_zero);
        let at_full = self.scaling.output_to_norm(s.displacement_at_full_scale);
        let gain = at_full - at_zero;
        let ki_per_tick = fb.ki / rate;
        let kd_per_tick = fb.kd * rate;
        let drift = fb.drift_limit.unwrap_or(0.5);
        let finite = [
            at_zero,
            at_full,
            fb.kp,
            ki_per_tick,
            kd_per_tick,
            fb.limit,
            drift,
        ]
        .iter()
        .all(|v| v.is_finite());
        // The sensor's reading is formed in Q4.28 (|x| < 8) before it saturates to Q2.30.
        let ok = finite
            && (1..=30).contains(&s.adc_bits)
            && gain != 0.0
            && at_zero.abs() < 7.5
            && at_full.abs() < 7.5
            && gain.abs() < 7.5
            && (0.0..7.5).contains(&fb.kp)
            && (0.0..0.5).contains(&ki_per_tick)
            && (0.0..7.5).contains(&kd_per_tick)
            && (fb.kd == 0.0
                || (fb.derivative_cutoff_hz > 0.0 && fb.derivative_cutoff_hz < rate / 2.0))
            && fb.limit > 0.0
            && fb.limit <= 1.0
            && drift > 0.0
            && drift <= 1.0;
        if !ok {
            return Err(SettingsError::BadFeedback);
        }
        let notch = match &fb.notch {
            Some(d) => Some(Notch::new(d, rate).map_err(SettingsError::Notch)?),
            None => None,
        };
        let derivative = (fb.kd > 0.0).then(|| Derivative {
            kd: q4_28_from_f64(kd_per_tick),
            smoothing: q1_31_from_f64(
                1.0 - libm::exp(-2.0 * core::f64::consts::PI * fb.derivative_cutoff_hz / rate),
            ),
        });
        // Q2.30; 1.0 of the drive range is 2 normalised units (saturates just below 2).
        let limit = signal_from_f64(fb.limit * 2.0);
        let kp = q4_28_from_f64(fb.kp);
        let error_bound = Feedback::error_bound(limit, kp);
        let drift_limit = match fb.drift_limit {
            Some(d) if observed => signal_from_f64(d * 2.0) as u32,
            _ => u32::MAX,
        };
        Ok(Feedback {
            adc_bits: s.adc_bits,
            sensor_offset: q4_28_from_f64(at_zero),
            sensor_gain: q4_28_from_f64(gain),
            kp,
            error_bound,
            ki: q0_32_from_f64(ki_per_tick),
            derivative,
            limit,
            notch,
            drift_limit,
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
            feedback: Some(FeedbackSettings::pi(
                SensorSettings {
                    adc_bits: 16,
                    displacement_at_zero: 0.0,
                    displacement_at_full_scale: 13.0,
                },
                0.2,
                2000.0,
                0.2,
            )),
            mode,
        }
    }

    #[test]
    fn every_mode_builds_every_part_and_starts_in_its_mode() {
        for mode in [Mode::Bypass, Mode::OpenLoop, Mode::ClosedLoop] {
            let c = settings(mode).build().unwrap();
            assert_eq!(c.mode, mode);
            assert!(matches!(c.compensator, Compensator::InversePi(_)));
            assert!(matches!(c.observer, Observer::Pi(_)));
            assert!(c.feedback.is_some());
        }
        let mut s = settings(Mode::Bypass);
        s.model = None;
        let c = s.build().unwrap();
        assert!(matches!(c.compensator, Compensator::None));
        assert_eq!(
            c.feedback.unwrap().drift_limit,
            u32::MAX,
            "no observer, no drift check"
        );
    }

    #[test]
    fn notch_derivative_and_drift_limit_are_built_for_the_control_rate() {
        let mut s = settings(Mode::ClosedLoop);
        let fb = s.feedback.as_mut().unwrap();
        fb.notch = Some(NotchDesign {
            frequency_hz: 21_800.0,
            q: 2.0,
            depth: 0.0,
        });
        fb.kd = 1e-6;
        fb.derivative_cutoff_hz = 5_000.0;
        fb.drift_limit = Some(0.02);
        let design = fb.notch.unwrap();
        let c = s.build().unwrap().feedback.unwrap();
        assert_eq!(c.notch, Some(Notch::new(&design, 50_000.0).unwrap()));
        assert_eq!(c.derivative.unwrap().kd, q4_28_from_f64(0.05));
        assert_eq!(c.drift_limit, signal_from_f64(0.04) as u32);
        // The same notch is refused at a rate whose Nyquist frequency is below it.
        s.drive.control_rate = 40_000.0;
        assert_eq!(
            s.build(),
            Err(SettingsError::Notch(NotchError::FrequencyOutOfRange))
        );
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
        for bad in [
            |f: &mut FeedbackSettings| f.ki = 30_000.0, // ≥ 1/2 per tick
            |f: &mut FeedbackSettings| f.kp = 9.0,
            |f: &mut FeedbackSettings| f.limit = 0.0,
            |f: &mut FeedbackSettings| f.drift_limit = Some(-0.1),
            |f: &mut FeedbackSettings| {
                f.kd = 1e-6;
                f.derivative_cutoff_hz = 30_000.0
            },
        ] {
            let mut s = settings(Mode::Bypass);
            bad(s.feedback.as_mut().unwrap());
            assert_eq!(s.build(), Err(SettingsError::BadFeedback));
        }
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
