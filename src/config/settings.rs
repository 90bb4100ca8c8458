//! The one settings type: everything a user configures, in physical units.
//!
//! [`Settings`] is at once what a `LoadParams` request carries on the wire, what the flash
//! record holds, what a parameter file (`PARAMS.json`) carries and what a golden vector set
//! is built from: one serde type, encoded with `postcard` on the board and JSON on the host.
//! What the hardware fixes (amplifier, DAC, sensor ADC, control rate) is not a setting but a
//! [`Hardware`] fact that settings are validated against.
//!
//! [`Settings::build`] validates everything and turns it into the tick's fixed-point
//! [`ControlConfig`] with each part's own builder, next to its type:
//! [`DriveSettings::build`], [`SensorSettings::build`], [`FeedbackSettings::build`], and the
//! models' constructors. Every refusal names the field and the rule it broke ([`Refusal`]);
//! every float is checked for NaN and infinity before anything else.

use heapless::Vec;
use serde::{Deserialize, Serialize};

pub use crate::board::Hardware;
pub use crate::control::drive::{Configuration, DriveSettings, SafeState};
pub use crate::control::feedback::FeedbackSettings;
pub use crate::control::mode_switch::Mode;
use crate::control::notch::Notch;
pub use crate::control::notch::NotchDesign;
pub use crate::control::preview::PreviewDesign;
pub use crate::control::sensor::SensorSettings;
use crate::control::{Compensator, ControlConfig, Observer};
use crate::models::bouc_wen::{BoucWen, InverseBoucWen};
pub use crate::models::creep::CreepParams;
use crate::models::creep::{
    Creep, CreepError, MAX_CREEP_MODES, MAX_TIME_CONSTANT_TICKS, MAX_WEIGHT_SUM,
    MIN_TIME_CONSTANT_TICKS,
};
use crate::models::duhem::{Duhem, InverseDuhem};
use crate::models::generalised_pi::{
    GeneralisedPi, GpiParams, InverseGeneralisedPi, MAX_DEAD_ZONES,
};
pub use crate::models::output_map::DeadZoneParams;
use crate::models::output_map::OutputMap;
use crate::models::params::{
    BoucWenCoefficient, BoucWenParams, DuhemParams, ParamError, PiParams, MAX_OPERATORS,
};
use crate::models::prandtl_ishlinskii::{InversePrandtlIshlinskii, PrandtlIshlinskii};
use crate::refusal::{finite, CreepField, Field, ModelField, Refusal, Rule};
use crate::scaling::Scaling;

/// A hysteresis model in physical units (volts in, output units out).
#[allow(clippy::large_enum_variant)] // no heap on the board; settings live in one place
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Model {
    /// Prandtl–Ishlinskii.
    PrandtlIshlinskii(PiParams),
    /// Duhem.
    Duhem(DuhemParams),
    /// Generalised (asymmetric) Prandtl–Ishlinskii: a P–I followed by a dead-zone map
    /// ([`crate::models::generalised_pi`]).
    GeneralisedPi(GpiParams),
    /// Generalised (asymmetric) Bouc–Wen; compensated by its exact per-sample inverse.
    BoucWen(BoucWenParams),
}

/// Everything a user configures, in physical units (see the module doc).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Settings {
    /// The models' input range (left-stack volts) and output range (displacement): both map
    /// onto the normalised ±1 of the tick's signals; setpoints are fractions of the output
    /// range.
    pub ranges: Scaling,
    /// The feedforward compensator: the analytic inverse of this model. `None`: the drive
    /// follows the setpoint (only bypass and closed loop).
    pub compensator: Option<Model>,
    /// The forward observer: this model, fed the applied drive, estimates the displacement.
    /// `None`: no estimate and no drift check. Any model may pair with any compensator.
    pub observer: Option<Model>,
    /// The drive and its limits.
    pub drive: DriveSettings,
    /// The position sensor's calibration, if the stage has a sensor.
    pub sensor: Option<SensorSettings>,
    /// PI(D) feedback on the sensor, used in closed loop.
    pub feedback: Option<FeedbackSettings>,
    /// The mode to run in: entered once loaded, and at boot for a stored record.
    pub mode: Mode,
    /// The stage's creep, in series after the hysteresis model ([`crate::models::creep`]): the
    /// compensator runs its inverse before the inverse model (`setpoint → C⁻¹ → H⁻¹ →
    /// drive`), the observer runs it after the model (`drive → H → C → estimate`). `None`
    /// (and absent from older parameter files): no creep.
    #[serde(default)]
    pub creep: Option<CreepParams>,
    /// Input shaping: a notch on the feedforward (the compensator's output plus the learned
    /// correction), at the stage's resonance, so that the drive does not excite it: the
    /// tick runs it before the range and slew limits in every mode but bypass. Designed at the
    /// control rate ([`NotchDesign::coefficients`]); `twinstack tune` measures the resonance.
    /// `None` (and absent from older parameter files): no shaping.
    #[serde(default)]
    pub shaping: Option<NotchDesign>,
    /// The preview: every setpoint, whatever its source, shaped for the stage's resonance
    /// before the compensator, the feedback aiming at the setpoint itself, both
    /// [`PREVIEW_DELAY_TICKS`](crate::control::preview::PREVIEW_DELAY_TICKS) ticks after it
    /// is given ([`crate::control::preview`]): a corner without ringing, in open and closed
    /// loop. Designed at the control rate ([`PreviewDesign::preview`]); `twinstack tune`
    /// measures the resonance. `None` (and absent from older parameter files): no preview.
    #[serde(default)]
    pub preview: Option<PreviewDesign>,
    /// A static output map after the hysteresis model, before the creep
    /// ([`crate::models::output_map`]): a monotone dead-zone map in output units, for what
    /// bends every branch alike (a flexure's stiffening, a lever, a sensor's curve). The
    /// compensator runs its inverse before the inverse model (`setpoint → C⁻¹ → S⁻¹ → H⁻¹`),
    /// the observer runs it after the model (`drive → H → S → C`). Taken by the Bouc–Wen
    /// model (compensator and observer); refused with another model ([`Rule::NoOutputMap`]:
    /// the generalised P–I has its own, and is the P–I with one). `None` (and absent from
    /// older parameter files): no map.
    #[serde(default)]
    pub output_map: Option<DeadZoneParams>,
}

/// [`Settings`] as it was laid out before the output map (every field but the last,
/// `output_map`): what flash records of version 8 and golden vector sets of format 6 hold.
/// Read only, into [`Settings`] without an output map.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SettingsWithoutOutputMap {
    before_preview: SettingsWithoutPreview,
    preview: Option<PreviewDesign>,
}

impl From<SettingsWithoutOutputMap> for Settings {
    fn from(s: SettingsWithoutOutputMap) -> Self {
        Self {
            preview: s.preview,
            ..Settings::from(s.before_preview)
        }
    }
}

/// [`Settings`] as it was laid out before the preview (every field but the last,
/// `preview`): what flash records of versions 5 to 7 and golden vector sets of formats 4
/// and 5 hold. Read only, into [`Settings`] without a preview.
///
/// Each layout is the one before it and the field it added: `postcard` writes a struct as
/// its fields one after another, so a layout nested in the next reads the same bytes.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SettingsWithoutPreview {
    before_shaping: SettingsWithoutShaping,
    shaping: Option<NotchDesign>,
}

impl From<SettingsWithoutPreview> for Settings {
    fn from(s: SettingsWithoutPreview) -> Self {
        let b = s.before_shaping;
        Self {
            ranges: b.ranges,
            compensator: b.compensator,
            observer: b.observer,
            drive: b.drive,
            sensor: b.sensor,
            feedback: b.feedback,
            mode: b.mode,
            creep: b.creep,
            shaping: s.shaping,
            preview: None,
            output_map: None,
        }
    }
}

/// [`Settings`] as it was laid out before input shaping (every field but the last two,
/// `shaping` and `preview`): what flash records of version 4 and golden vector sets of
/// format 3 hold. Read only, into [`Settings`] without shaping or a preview.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SettingsWithoutShaping {
    ranges: Scaling,
    compensator: Option<Model>,
    observer: Option<Model>,
    drive: DriveSettings,
    sensor: Option<SensorSettings>,
    feedback: Option<FeedbackSettings>,
    mode: Mode,
    creep: Option<CreepParams>,
}

impl From<SettingsWithoutShaping> for Settings {
    fn from(s: SettingsWithoutShaping) -> Self {
        SettingsWithoutPreview {
            before_shaping: s,
            shaping: None,
        }
        .into()
    }
}

impl Default for Settings {
    /// The board's compiled-in settings: bypass (no model, no loop closed), the default drive
    /// (differential, bias 70 V, 0…140 V), 0…140 V onto 0…70 µm, the sensor spanning the
    /// stroke without a drift check.
    fn default() -> Self {
        Self {
            ranges: Scaling {
                input_min: 0.0,
                input_max: 140.0,
                output_min: 0.0,
                output_max: 70.0,
            },
            compensator: None,
            observer: None,
            drive: DriveSettings::DEFAULT,
            sensor: Some(SensorSettings {
                displacement_at_zero: 0.0,
                displacement_at_full_scale: 70.0,
                drift_limit: None,
            }),
            feedback: None,
            mode: Mode::Bypass,
            creep: None,
            shaping: None,
            preview: None,
            output_map: None,
        }
    }
}

impl Settings {
    /// Whether the compensator or the observer is a Bouc–Wen model (whose coefficients a
    /// stored layout before `χ` laid out without it).
    pub fn has_bouc_wen(&self) -> bool {
        let bouc_wen = |m: &Option<Model>| matches!(m, Some(Model::BoucWen(_)));
        bouc_wen(&self.compensator) || bouc_wen(&self.observer)
    }

    /// The ranges' scaling (input and output units ↔ normalised), as [`Settings::build`]
    /// takes it.
    fn scaling(&self) -> Result<Scaling, Refusal> {
        Scaling::new(
            self.ranges.input_min,
            self.ranges.input_max,
            self.ranges.output_min,
            self.ranges.output_max,
        )
        .map_err(|e| model_refusal(Field::Compensator, e.into()))
    }

    /// The position sensor's resolution on `hw`: one ADC code, Q2.30 normalised displacement
    /// ([`crate::control::sensor::Sensor::quantum`]); `None` without a sensor (or with
    /// settings [`Settings::build`] refuses). Builds the sensor alone, not the models.
    pub fn sensor_quantum(&self, hw: &Hardware) -> Option<i32> {
        let sensor = self.sensor.as_ref()?;
        let ranges = self.scaling().ok()?;
        let built = sensor.build(hw.sensor_adc_bits, &ranges, self.observer.is_some());
        built.ok().map(|s| s.quantum())
    }

    /// Validates everything on `hw` and builds the tick's fixed-point configuration. Nothing
    /// is partly accepted: the first refusal is returned, naming its field.
    ///
    /// ```
    /// use twinstack::config::settings::{Hardware, Mode, Settings};
    /// let config = Settings::default().build(&Hardware::driver_board(50_000.0)).unwrap();
    /// assert_eq!(config.mode, Mode::Bypass);
    /// let mut s = Settings::default();
    /// s.drive.bias = f64::NAN;
    /// assert_eq!(s.build(&Hardware::driver_board(50_000.0)).unwrap_err().to_string(),
    ///            "drive.bias is NaN or infinite");
    /// ```
    pub fn build(&self, hw: &Hardware) -> Result<ControlConfig, Refusal> {
        self.check_finite()?;
        let ranges = self.scaling()?;
        // The output map, for the models that take one (Bouc–Wen's), before either is built.
        let output_map = match &self.output_map {
            Some(m) => {
                Some(OutputMap::new(m, &ranges).map_err(|e| model_refusal(Field::OutputMap, e))?)
            }
            None => None,
        };
        for (model, field) in [
            (&self.compensator, Field::Compensator(ModelField::Model)),
            (&self.observer, Field::Observer(ModelField::Model)),
        ] {
            if output_map.is_some() && matches!(model, Some(m) if !matches!(m, Model::BoucWen(_))) {
                return Err(Refusal::new(field, Rule::NoOutputMap));
            }
        }
        // The compensator first: "not invertible" says more than a range error would.
        let compensator = match &self.compensator {
            None => Compensator::None,
            Some(Model::PrandtlIshlinskii(p)) => Compensator::InversePi(
                InversePrandtlIshlinskii::new(p, &ranges)
                    .map_err(|e| model_refusal(Field::Compensator, e))?,
            ),
            Some(Model::Duhem(p)) => Compensator::InverseDuhem(
                InverseDuhem::new(p, &ranges).map_err(|e| model_refusal(Field::Compensator, e))?,
            ),
            Some(Model::GeneralisedPi(p)) => Compensator::InverseGeneralisedPi(
                InverseGeneralisedPi::new(p, &ranges)
                    .map_err(|e| model_refusal(Field::Compensator, e))?,
            ),
            Some(Model::BoucWen(p)) => Compensator::InverseBoucWen(
                InverseBoucWen::new(p, &ranges)
                    .map_err(|e| model_refusal(Field::Compensator, e))?
                    .with_output_map(output_map.as_ref()),
            ),
        };
        let observer = match &self.observer {
            None => Observer::None,
            Some(Model::PrandtlIshlinskii(p)) => Observer::Pi(
                PrandtlIshlinskii::new(p, &ranges)
                    .map_err(|e| model_refusal(Field::Observer, e))?,
            ),
            Some(Model::Duhem(p)) => Observer::Duhem(
                Duhem::new(p, &ranges).map_err(|e| model_refusal(Field::Observer, e))?,
            ),
            Some(Model::GeneralisedPi(p)) => Observer::GeneralisedPi(
                GeneralisedPi::new(p, &ranges).map_err(|e| model_refusal(Field::Observer, e))?,
            ),
            Some(Model::BoucWen(p)) => Observer::BoucWen(
                BoucWen::new(p, &ranges)
                    .map_err(|e| model_refusal(Field::Observer, e))?
                    .with_output_map(output_map.as_ref()),
            ),
        };
        let drive = self.drive.build(hw, &ranges)?;
        let sensor = match &self.sensor {
            Some(s) => Some(s.build(hw.sensor_adc_bits, &ranges, self.observer.is_some())?),
            None => None,
        };
        let feedback = match &self.feedback {
            Some(f) => Some(f.build(hw.control_rate_hz)?),
            None => None,
        };
        let creep = match &self.creep {
            Some(c) => Some(
                Creep::new(c, hw.control_rate_hz)
                    .map_err(|e| creep_refusal(e, Some(hw.control_rate_hz)))?,
            ),
            None => None,
        };
        let shaping = match &self.shaping {
            Some(d) => Some(Notch::new(d, hw.control_rate_hz).map_err(|e| {
                crate::control::notch::refusal(
                    d,
                    e,
                    [
                        Field::ShapingFrequency,
                        Field::ShapingQ,
                        Field::ShapingDepth,
                    ],
                )
            })?),
            None => None,
        };
        let preview = match &self.preview {
            Some(d) => Some(
                d.preview(hw.control_rate_hz)
                    .map_err(|e| crate::control::preview::refusal(d, e, hw.control_rate_hz))?,
            ),
            None => None,
        };
        self.check_mode(self.mode)?;
        let config = ControlConfig {
            compensator,
            observer,
            sensor,
            feedback,
            drive,
            mode: self.mode,
            creep,
            shaping,
            preview,
        };
        // Last: what the tick runs must fit its period at this rate.
        crate::config::tick_budget::check(&config, hw.control_rate_hz)?;
        Ok(config)
    }

    /// Whether `mode` can run on these settings: open loop needs a compensator, closed loop a
    /// sensor and feedback gains ([`Settings::build`] checks its own mode so).
    pub fn check_mode(&self, mode: Mode) -> Result<(), Refusal> {
        match mode {
            Mode::OpenLoop if self.compensator.is_none() => Err(Refusal::new(
                Field::Compensator(ModelField::Model),
                Rule::Required,
            )),
            Mode::ClosedLoop if self.sensor.is_none() => {
                Err(Refusal::new(Field::Sensor, Rule::Required))
            }
            Mode::ClosedLoop if self.feedback.is_none() => {
                Err(Refusal::new(Field::Feedback, Rule::Required))
            }
            _ => Ok(()),
        }
    }

    /// Every float of the settings is finite, or the first that is not is named.
    fn check_finite(&self) -> Result<(), Refusal> {
        let r = &self.ranges;
        for x in [r.input_min, r.input_max] {
            finite(Field::InputRange, x)?;
        }
        for x in [r.output_min, r.output_max] {
            finite(Field::OutputRange, x)?;
        }
        for (model, field) in [
            (
                &self.compensator,
                Field::Compensator as fn(ModelField) -> Field,
            ),
            (&self.observer, Field::Observer),
        ] {
            match model {
                Some(Model::PrandtlIshlinskii(p)) => check_pi_finite(field, p)?,
                Some(Model::Duhem(p)) => {
                    finite(field(ModelField::Alpha), p.alpha)?;
                    finite(field(ModelField::Beta), p.beta)?;
                    finite(field(ModelField::Gamma), p.gamma)?;
                    finite(field(ModelField::Offset), p.offset)?;
                }
                Some(Model::GeneralisedPi(p)) => {
                    check_pi_finite(field, &p.pi)?;
                    check_map_finite(field, &p.dead_zones)?;
                }
                Some(Model::BoucWen(p)) => {
                    finite(field(ModelField::K), p.k)?;
                    finite(field(ModelField::Offset), p.offset)?;
                    finite(field(ModelField::A), p.a)?;
                    finite(field(ModelField::Beta), p.beta)?;
                    finite(field(ModelField::Gamma), p.gamma)?;
                    finite(field(ModelField::Psi), p.psi)?;
                    finite(field(ModelField::Chi), p.chi)?;
                }
                None => {}
            }
        }
        let d = &self.drive;
        finite(Field::Bias, d.bias)?;
        finite(Field::VoltageLimits, d.min_voltage)?;
        finite(Field::VoltageLimits, d.max_voltage)?;
        finite(Field::SlewRate, d.slew_rate)?;
        if let Some(s) = &self.sensor {
            finite(Field::SensorCalibration, s.displacement_at_zero)?;
            finite(Field::SensorCalibration, s.displacement_at_full_scale)?;
            if let Some(x) = s.drift_limit {
                finite(Field::DriftLimit, x)?;
            }
        }
        if let Some(f) = &self.feedback {
            finite(Field::Kp, f.kp)?;
            finite(Field::Ki, f.ki)?;
            finite(Field::Kd, f.kd)?;
            finite(Field::DerivativeCutoff, f.derivative_cutoff_hz)?;
            finite(Field::FeedbackLimit, f.limit)?;
            if let Some(n) = &f.notch {
                finite(Field::NotchFrequency, n.frequency_hz)?;
                finite(Field::NotchQ, n.q)?;
                finite(Field::NotchDepth, n.depth)?;
            }
        }
        if let Some(n) = &self.shaping {
            finite(Field::ShapingFrequency, n.frequency_hz)?;
            finite(Field::ShapingQ, n.q)?;
            finite(Field::ShapingDepth, n.depth)?;
        }
        if let Some(p) = &self.preview {
            finite(Field::PreviewFrequency, p.frequency_hz)?;
            finite(Field::PreviewDamping, p.damping)?;
        }
        if let Some(m) = &self.output_map {
            check_map_finite(Field::OutputMap, m)?;
        }
        if let Some(c) = &self.creep {
            for (i, &x) in c.time_constants_s.iter().enumerate() {
                finite(Field::Creep(CreepField::TimeConstant(i as u8 + 1)), x)?;
            }
            for (i, &x) in c.weights.iter().enumerate() {
                finite(Field::Creep(CreepField::Weight(i as u8 + 1)), x)?;
            }
        }
        Ok(())
    }
}

/// Every float of a dead-zone map is finite, or the first that is not is named.
fn check_map_finite(field: fn(ModelField) -> Field, d: &DeadZoneParams) -> Result<(), Refusal> {
    finite(field(ModelField::DeadZoneCentre), d.centre)?;
    finite(field(ModelField::DeadZoneLinear), d.linear)?;
    for (i, &x) in d.thresholds.iter().enumerate() {
        finite(field(ModelField::DeadZoneThreshold(i as u8 + 1)), x)?;
    }
    for (i, &x) in d.weights.iter().enumerate() {
        finite(field(ModelField::DeadZoneWeight(i as u8 + 1)), x)?;
    }
    Ok(())
}

/// Every float of a P–I model is finite, or the first that is not is named.
fn check_pi_finite(field: fn(ModelField) -> Field, p: &PiParams) -> Result<(), Refusal> {
    finite(field(ModelField::A0), p.a0)?;
    finite(field(ModelField::Offset), p.offset)?;
    for (i, &x) in p.thresholds.iter().enumerate() {
        finite(field(ModelField::Threshold(i as u8 + 1)), x)?;
    }
    for (i, &x) in p.weights.iter().enumerate() {
        finite(field(ModelField::Weight(i as u8 + 1)), x)?;
    }
    Ok(())
}

/// A P–I model from thresholds and weights (volts, output units per volt), as a [`Model`].
pub fn pi_model(
    a0: f64,
    offset: f64,
    thresholds: &[f64],
    weights: &[f64],
) -> Result<Model, ParamError> {
    PiParams::new(a0, offset, thresholds, weights).map(Model::PrandtlIshlinskii)
}

/// The refusal a model's own error amounts to, on the compensator's or the observer's fields.
fn model_refusal(model: fn(ModelField) -> Field, e: ParamError) -> Refusal {
    use ParamError as E;
    let op = |i: usize| i.min(u8::MAX as usize) as u8;
    let (field, rule) = match e {
        E::EmptyInputRange => return Refusal::new(Field::InputRange, Rule::Empty),
        E::EmptyOutputRange => return Refusal::new(Field::OutputRange, Rule::Empty),
        E::NoOperators => (ModelField::Operators, Rule::Required),
        E::TooManyOperators { .. } => (ModelField::Operators, Rule::TooMany(MAX_OPERATORS as u32)),
        E::LengthMismatch { .. } => (ModelField::Operators, Rule::LengthMismatch),
        E::NotFinite => (ModelField::Model, Rule::NotFinite),
        E::NegativeThreshold { operator } => {
            (ModelField::Threshold(op(operator)), Rule::AtLeast(0.0))
        }
        E::ThresholdsNotIncreasing { operator } => {
            (ModelField::Threshold(op(operator)), Rule::NotIncreasing)
        }
        E::ThresholdOutOfRange { operator } => {
            (ModelField::Threshold(op(operator)), Rule::BeyondFixedPoint)
        }
        E::FirstThresholdNotZero => (ModelField::Threshold(1), Rule::NotInvertible),
        E::FirstWeightNotPositive => (ModelField::Weight(1), Rule::NotInvertible),
        E::PartialSumNotPositive { operator } => {
            (ModelField::Weight(op(operator)), Rule::NotInvertible)
        }
        E::WeightOutOfRange { operator } => {
            (ModelField::Weight(op(operator)), Rule::BeyondFixedPoint)
        }
        E::GainSumTooLarge => (ModelField::Operators, Rule::BeyondFixedPoint),
        E::OffsetOutOfRange => (ModelField::Offset, Rule::BeyondFixedPoint),
        E::DuhemAlphaNotPositive => (ModelField::Alpha, Rule::Above(0.0)),
        E::DuhemBetaNotPositive => (ModelField::Beta, Rule::Above(0.0)),
        E::DuhemGammaNotPositive => (ModelField::Gamma, Rule::Above(0.0)),
        E::DuhemCoefficientOutOfRange => (ModelField::Model, Rule::BeyondFixedPoint),
        E::TooManyDeadZones { .. } => (ModelField::DeadZones, Rule::TooMany(MAX_DEAD_ZONES as u32)),
        E::DeadZoneLengthMismatch { .. } => (ModelField::DeadZones, Rule::LengthMismatch),
        E::DeadZoneThresholdsNotIncreasing { dead_zone } => (
            ModelField::DeadZoneThreshold(op(dead_zone)),
            Rule::NotIncreasing,
        ),
        E::DeadZoneThresholdOutOfRange { dead_zone } => (
            ModelField::DeadZoneThreshold(op(dead_zone)),
            Rule::BeyondFixedPoint,
        ),
        E::DeadZoneLinearNotPositive => (ModelField::DeadZoneLinear, Rule::NotInvertible),
        E::DeadZoneSlopeNotPositive { dead_zone } => (
            ModelField::DeadZoneWeight(op(dead_zone)),
            Rule::NotInvertible,
        ),
        E::DeadZoneWeightOutOfRange { dead_zone: 0 } => {
            (ModelField::DeadZoneLinear, Rule::BeyondFixedPoint)
        }
        E::DeadZoneWeightOutOfRange { dead_zone } => (
            ModelField::DeadZoneWeight(op(dead_zone)),
            Rule::BeyondFixedPoint,
        ),
        E::DeadZoneGainSumTooLarge => (ModelField::DeadZones, Rule::BeyondFixedPoint),
        E::DeadZoneCentreOutOfRange => (ModelField::DeadZoneCentre, Rule::BeyondFixedPoint),
        // The models' constructors do not return it; should one, its limits in seconds
        // cannot be given without the rate.
        E::Creep(e) => return creep_refusal(e, None),
        E::BoucWenNotPositive(c) => (bouc_wen_field(c), Rule::Above(0.0)),
        E::BoucWenUnbounded(c) => (bouc_wen_field(c), Rule::Unbounded),
        E::BoucWenOutOfRange(c) => (bouc_wen_field(c), Rule::BeyondFixedPoint),
        E::BoucWenNotInvertible(c) => (bouc_wen_field(c), Rule::NotInvertible),
    };
    Refusal::new(model(field), rule)
}

/// The refusal a creep error amounts to, on the `creep` fields; the time constants' limits
/// in seconds at `control_rate_hz` (without a rate: [`Rule::BeyondFixedPoint`]).
fn creep_refusal(e: CreepError, control_rate_hz: Option<f64>) -> Refusal {
    use CreepError as E;
    let mode = |i: usize| i.clamp(1, u8::MAX as usize) as u8;
    let seconds = |ticks: f64, rule: fn(f64) -> Rule| match control_rate_hz {
        Some(rate) => rule(ticks / rate),
        None => Rule::BeyondFixedPoint,
    };
    let (field, rule) = match e {
        E::NoModes => (CreepField::Modes, Rule::Required),
        E::TooManyModes { .. } => (CreepField::Modes, Rule::TooMany(MAX_CREEP_MODES as u32)),
        E::LengthMismatch { .. } => (CreepField::Modes, Rule::LengthMismatch),
        E::NotFinite { mode: 0 } => (CreepField::Modes, Rule::NotFinite),
        E::NotFinite { mode: i } => (CreepField::TimeConstant(mode(i)), Rule::NotFinite),
        E::TimeConstantTooShort { mode: i } => (
            CreepField::TimeConstant(mode(i)),
            seconds(MIN_TIME_CONSTANT_TICKS, Rule::AtLeast),
        ),
        E::TimeConstantTooLong { mode: i } => (
            CreepField::TimeConstant(mode(i)),
            seconds(MAX_TIME_CONSTANT_TICKS, Rule::AtMost),
        ),
        E::TimeConstantsNotIncreasing { mode: i } => {
            (CreepField::TimeConstant(mode(i)), Rule::NotIncreasing)
        }
        E::NegativeWeight { mode: i } => (CreepField::Weight(mode(i)), Rule::AtLeast(0.0)),
        E::WeightSumTooLarge => (CreepField::Modes, Rule::AtMost(MAX_WEIGHT_SUM)),
    };
    Refusal::new(Field::Creep(field), rule)
}

/// The settings field a Bouc–Wen coefficient is.
fn bouc_wen_field(c: BoucWenCoefficient) -> ModelField {
    match c {
        BoucWenCoefficient::K => ModelField::K,
        BoucWenCoefficient::Offset => ModelField::Offset,
        BoucWenCoefficient::A => ModelField::A,
        BoucWenCoefficient::Beta => ModelField::Beta,
        BoucWenCoefficient::Gamma => ModelField::Gamma,
        BoucWenCoefficient::Psi => ModelField::Psi,
        BoucWenCoefficient::Chi => ModelField::Chi,
    }
}

/// The representative (not identified) P–I model the examples, benches and tests use: `n`
/// operators (1…32) with uniform thresholds over 0…140 V, total slope 0.5 µm/V, `w_1 =
/// 0.3 µm/V`, the other 0.2 µm/V decaying by 0.8 per operator. Replace it with the
/// identification tool's output for a real stage.
pub fn representative_pi(n: usize) -> Result<Model, ParamError> {
    let thresholds = crate::models::params::Thresholds::Uniform.generate(n, 140.0)?;
    let mut weights: Vec<f64, MAX_OPERATORS> = Vec::new();
    let mut decay = 1.0;
    let mut tail = 0.0;
    for _ in 1..n {
        decay *= 0.8;
        tail += decay;
    }
    let mut d = 1.0;
    for i in 0..n {
        let w = if i == 0 {
            0.3
        } else {
            d *= 0.8;
            0.2 * d / tail
        };
        let _ = weights.push(w);
    }
    let a0 = if n == 1 { 0.2 } else { 0.0 };
    pi_model(a0, 0.0, &thresholds, &weights)
}

/// The representative (not identified) generalised P–I: [`representative_pi`]`(n)` followed
/// by a map of six dead zones around 35 µm, flatter below the centre (slopes 0.95, 0.85, 0.75
/// beyond −8, −16, −24 µm) and steeper above it (1.05, 1.15, 1.3 beyond 8, 16, 24 µm): an
/// asymmetric loop over 0…140 V onto 0…70 µm.
pub fn representative_gpi(n: usize) -> Result<Model, ParamError> {
    let Model::PrandtlIshlinskii(pi) = representative_pi(n)? else {
        return Err(ParamError::NoOperators);
    };
    let dead_zones = crate::models::generalised_pi::DeadZoneParams::new(
        35.0,
        1.0,
        &[-24.0, -16.0, -8.0, 8.0, 16.0, 24.0],
        &[-0.1, -0.1, -0.05, 0.05, 0.1, 0.15],
    )?;
    Ok(Model::GeneralisedPi(GpiParams { pi, dead_zones }))
}

/// The representative Duhem model: anhysteretic slope 0.5 µm/V through the origin, slope after
/// a reversal 0.35 µm/V, `α = 0.02 /V`.
pub fn representative_duhem() -> Model {
    Model::Duhem(DuhemParams {
        alpha: 0.02,
        beta: 0.5,
        gamma: 0.35,
        offset: 0.0,
    })
}

/// The representative Bouc–Wen model: slope 0.42 µm/V, `A = 0.1 µm/V`, `β = 0.04 /V`,
/// `γ = 0.008 /V` and an asymmetric `ψ = 0.006 /V`, no `χ` (with `A > 0` the output's slope
/// is never below `k`: compensator loop gain 0).
pub fn representative_bouc_wen() -> Model {
    Model::BoucWen(BoucWenParams {
        k: 0.42,
        offset: 0.0,
        a: 0.1,
        beta: 0.04,
        gamma: 0.008,
        psi: 0.006,
        chi: 0.0,
    })
}

/// The representative output map, over the default 0…70 µm: a flexure's stiffening, the
/// slope 1 about the middle (35 µm) and 6 % flatter toward either end, in three dead zones a
/// side (±10, ±20 and ±30 µm).
pub fn representative_output_map() -> DeadZoneParams {
    DeadZoneParams {
        centre: 35.0,
        linear: 1.0,
        thresholds: Vec::from_slice(&[-30.0, -20.0, -10.0, 10.0, 20.0, 30.0]).unwrap_or_default(),
        weights: Vec::from_slice(&[-0.03, -0.02, -0.01, -0.01, -0.02, -0.03]).unwrap_or_default(),
    }
}

/// An output map with every dead zone the settings hold (8), over the default 0…70 µm: what
/// the largest settings on the wire and in a golden vector recipe carry.
pub fn widest_output_map() -> DeadZoneParams {
    DeadZoneParams {
        centre: 35.0,
        linear: 1.0,
        thresholds: Vec::from_slice(&[-30.0, -20.0, -12.0, -4.0, 4.0, 12.0, 20.0, 30.0])
            .unwrap_or_default(),
        weights: Vec::from_slice(&[-0.01, -0.01, -0.01, -0.01, -0.01, -0.01, -0.02, -0.03])
            .unwrap_or_default(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hw() -> Hardware {
        Hardware::driver_board(50_000.0)
    }

    fn closed() -> Settings {
        Settings {
            compensator: Some(representative_pi(16).unwrap()),
            observer: Some(representative_duhem()),
            feedback: Some(FeedbackSettings::pi(0.2, 500.0, 0.1)),
            mode: Mode::ClosedLoop,
            ..Settings::default()
        }
    }

    #[test]
    fn the_default_is_bypass_without_a_model_and_builds() {
        let c = Settings::default().build(&hw()).unwrap();
        assert_eq!(c.mode, Mode::Bypass);
        assert!(matches!(c.compensator, Compensator::None));
        assert!(c.feedback.is_none() && c.sensor.is_some());
    }

    #[test]
    fn any_compensator_pairs_with_any_observer() {
        for comp in [
            None,
            Some(representative_pi(8).unwrap()),
            Some(representative_duhem()),
            Some(representative_gpi(8).unwrap()),
            Some(representative_bouc_wen()),
        ] {
            for obs in [
                None,
                Some(representative_pi(16).unwrap()),
                Some(representative_duhem()),
                Some(representative_gpi(16).unwrap()),
                Some(representative_bouc_wen()),
            ] {
                let s = Settings {
                    compensator: comp.clone(),
                    observer: obs.clone(),
                    ..closed()
                };
                assert!(s.build(&hw()).is_ok(), "{comp:?} / {obs:?}");
            }
        }
    }

    #[test]
    fn modes_need_what_they_run() {
        let mut s = closed();
        s.feedback = None;
        assert_eq!(
            s.build(&hw()).unwrap_err(),
            Refusal::new(Field::Feedback, Rule::Required)
        );
        let mut s = closed();
        s.sensor = None;
        assert_eq!(
            s.build(&hw()).unwrap_err(),
            Refusal::new(Field::Sensor, Rule::Required)
        );
        let mut s = closed();
        s.mode = Mode::OpenLoop;
        s.compensator = None;
        assert_eq!(
            s.build(&hw()).unwrap_err(),
            Refusal::new(Field::Compensator(ModelField::Model), Rule::Required)
        );
        let mut board = hw();
        board.sensor_adc_bits = None;
        assert_eq!(
            closed().build(&board).unwrap_err(),
            Refusal::new(Field::Sensor, Rule::NoHardware)
        );
    }

    #[test]
    fn model_refusals_name_the_operator() {
        let mut s = closed();
        if let Some(Model::PrandtlIshlinskii(p)) = s.compensator.as_mut() {
            p.weights[0] = -0.1;
        }
        assert_eq!(
            s.build(&hw()).unwrap_err(),
            Refusal::new(
                Field::Compensator(ModelField::Weight(1)),
                Rule::NotInvertible
            )
        );
        let mut s = closed();
        if let Some(Model::PrandtlIshlinskii(p)) = s.compensator.as_mut() {
            p.thresholds[3] = p.thresholds[2];
        }
        assert_eq!(
            s.build(&hw()).unwrap_err(),
            Refusal::new(
                Field::Compensator(ModelField::Threshold(4)),
                Rule::NotIncreasing
            )
        );
    }

    #[test]
    fn a_finite_weight_too_large_for_fixed_point_is_named_alike_whatever_its_size() {
        // 1e300 and f64::MIN are both finite: each is beyond fixed point for its own weight
        // (f64::MIN overflowed when scaled, and was "not finite" for the whole model).
        for (i, w) in [(1, 1e300), (1, f64::MIN), (2, f64::MAX), (0, f64::MIN)] {
            let mut s = closed();
            if let Some(Model::PrandtlIshlinskii(p)) = s.compensator.as_mut() {
                if i == 0 {
                    p.a0 = w;
                } else {
                    p.weights[i] = w;
                }
            }
            let operator = if i == 0 { 1 } else { i as u8 + 1 };
            assert_eq!(
                s.build(&hw()).unwrap_err(),
                Refusal::new(
                    Field::Compensator(ModelField::Weight(operator)),
                    Rule::BeyondFixedPoint
                ),
                "weight {i} = {w:e}"
            );
        }
    }

    fn gpi(s: &mut Settings) -> &mut GpiParams {
        match s.compensator.as_mut() {
            Some(Model::GeneralisedPi(p)) => p,
            _ => unreachable!("a generalised P–I compensator"),
        }
    }

    #[test]
    fn generalised_pi_refusals_name_the_dead_zone() {
        let base = || Settings {
            compensator: Some(representative_gpi(16).unwrap()),
            observer: Some(representative_gpi(16).unwrap()),
            ..closed()
        };
        let refused = |f: fn(&mut GpiParams)| {
            let mut s = base();
            f(gpi(&mut s));
            s.build(&hw()).unwrap_err()
        };
        let comp = |m| Field::Compensator(m);
        assert_eq!(
            refused(|p| p.dead_zones.weights[2] = f64::NAN),
            Refusal::new(comp(ModelField::DeadZoneWeight(3)), Rule::NotFinite)
        );
        assert_eq!(
            refused(|p| p.dead_zones.centre = f64::INFINITY),
            Refusal::new(comp(ModelField::DeadZoneCentre), Rule::NotFinite)
        );
        assert_eq!(
            refused(|p| p.dead_zones.thresholds[4] = p.dead_zones.thresholds[3]),
            Refusal::new(comp(ModelField::DeadZoneThreshold(5)), Rule::NotIncreasing)
        );
        assert_eq!(
            refused(|p| p.dead_zones.weights[4] = -1.2),
            Refusal::new(comp(ModelField::DeadZoneWeight(5)), Rule::NotInvertible)
        );
        assert_eq!(
            refused(|p| p.dead_zones.linear = 0.0),
            Refusal::new(comp(ModelField::DeadZoneLinear), Rule::NotInvertible)
        );
        assert_eq!(
            refused(|p| p.dead_zones.thresholds[5] = 100.0),
            Refusal::new(
                comp(ModelField::DeadZoneThreshold(6)),
                Rule::BeyondFixedPoint
            )
        );
        assert_eq!(
            refused(|p| p.dead_zones.centre = 80.0),
            Refusal::new(comp(ModelField::DeadZoneCentre), Rule::BeyondFixedPoint)
        );
        assert_eq!(
            refused(|p| p.dead_zones.weights.truncate(5)),
            Refusal::new(comp(ModelField::DeadZones), Rule::LengthMismatch)
        );
        // The P–I part keeps its own fields.
        assert_eq!(
            refused(|p| p.pi.weights[0] = -0.5),
            Refusal::new(comp(ModelField::Weight(1)), Rule::NotInvertible)
        );
        // The observer's are the observer's.
        let mut s = base();
        if let Some(Model::GeneralisedPi(p)) = s.observer.as_mut() {
            p.dead_zones.weights[0] = f64::NAN;
        }
        let r = s.build(&hw()).unwrap_err();
        assert_eq!(
            r,
            Refusal::new(
                Field::Observer(ModelField::DeadZoneWeight(1)),
                Rule::NotFinite
            )
        );
        let mut text = heapless::String::<64>::new();
        core::fmt::write(&mut text, format_args!("{r}")).unwrap();
        assert_eq!(text, "observer.dead_zones.weights[0] is NaN or infinite");
    }

    /// The largest settings a board accepts (two generalised P–I models of 32 operators and
    /// 8 dead zones, both notches, the preview) still fit one frame's body and the flash
    /// record; an output map is refused with them by name, and a Bouc–Wen pair with the widest
    /// map, six creep modes and the rest fits too.
    #[test]
    fn the_largest_generalised_pi_settings_fit_a_frame() {
        let Model::GeneralisedPi(mut g) = representative_gpi(32).unwrap() else {
            unreachable!()
        };
        g.dead_zones = crate::models::generalised_pi::DeadZoneParams::new(
            35.0,
            1.0,
            &[-32.0, -24.0, -16.0, -8.0, 8.0, 16.0, 24.0, 32.0],
            &[-0.1, -0.1, -0.1, -0.05, 0.05, 0.1, 0.15, 0.1],
        )
        .unwrap();
        let mut s = closed();
        s.compensator = Some(Model::GeneralisedPi(g.clone()));
        s.observer = Some(Model::GeneralisedPi(g));
        s.feedback.as_mut().unwrap().notch = Some(NotchDesign {
            frequency_hz: 1000.0,
            q: 2.0,
            depth: 0.1,
        });
        s.sensor.as_mut().unwrap().drift_limit = Some(0.1);
        s.shaping = Some(NotchDesign {
            frequency_hz: 21_807.0,
            q: 0.5,
            depth: 0.0173,
        });
        s.preview = Some(PreviewDesign {
            frequency_hz: 21_807.0,
            damping: 0.0173,
        });
        s.output_map = Some(widest_output_map());
        // A generalised P–I takes no output map (it has its own): refused by name.
        assert_eq!(
            s.build(&hw()).unwrap_err(),
            Refusal::new(Field::Compensator(ModelField::Model), Rule::NoOutputMap)
        );
        let mut bouc_wen = Settings {
            compensator: Some(representative_bouc_wen()),
            observer: Some(representative_bouc_wen()),
            ..s.clone()
        };
        bouc_wen.creep =
            Some(CreepParams::new(&[1e-3, 1e-2, 0.1, 1.0, 10.0, 100.0], &[0.01; 6]).unwrap());
        s.output_map = None;
        assert!(s.build(&hw()).is_ok());
        for s in [s, bouc_wen] {
            let mut buf = [0u8; 4096];
            let n = postcard::to_slice(&s, &mut buf).unwrap().len();
            // Version byte, message tag and CRC around it.
            assert!(
                n + 1 + 1 + 4 <= crate::protocol::frame::MAX_BODY,
                "{n} bytes of settings"
            );
            assert!(n + 5 <= crate::config::param_store::MAX_PAYLOAD);
        }
    }

    /// The feedforward's notch is designed at the board's rate; a design that cannot work
    /// there is refused on its own fields (`shaping.…`), not the feedback notch's.
    #[test]
    fn shaping_is_built_at_the_rate_and_refused_on_its_fields() {
        let design = NotchDesign {
            frequency_hz: 21_807.0,
            q: 0.5,
            depth: 0.0173,
        };
        let s = Settings {
            shaping: Some(design),
            ..closed()
        };
        let c = s.build(&hw()).unwrap();
        assert_eq!(
            c.shaping,
            Some(crate::control::notch::Notch::new(&design, 50_000.0).unwrap())
        );
        assert_eq!(closed().build(&hw()).unwrap().shaping, None);
        let refused = |f: fn(&mut NotchDesign)| {
            let mut d = design;
            f(&mut d);
            Settings {
                shaping: Some(d),
                ..closed()
            }
            .build(&hw())
            .unwrap_err()
        };
        // 21.8 kHz is beyond what a 40 kHz tick can place (0.49 of the rate).
        let slow = Settings {
            shaping: Some(design),
            ..closed()
        };
        assert_eq!(
            slow.build(&Hardware::driver_board(40_000.0)).unwrap_err(),
            Refusal::new(Field::ShapingFrequency, Rule::Unreachable)
        );
        assert_eq!(
            refused(|d| d.q = 60.0),
            Refusal::new(Field::ShapingQ, Rule::AtMost(50.0))
        );
        assert_eq!(
            refused(|d| d.depth = -0.1),
            Refusal::new(Field::ShapingDepth, Rule::AtMost(1.0))
        );
        let r = refused(|d| d.frequency_hz = f64::NAN);
        assert_eq!(r, Refusal::new(Field::ShapingFrequency, Rule::NotFinite));
        let mut text = heapless::String::<64>::new();
        core::fmt::write(&mut text, format_args!("{r}")).unwrap();
        assert_eq!(text, "shaping.frequency_hz is NaN or infinite");
    }

    #[test]
    fn creep_refusals_name_the_field_and_the_limit() {
        let with = |t: &[f64], w: &[f64]| {
            Settings {
                creep: Some(CreepParams {
                    time_constants_s: Vec::from_slice(t).unwrap(),
                    weights: Vec::from_slice(w).unwrap(),
                }),
                ..closed()
            }
            .build(&hw())
        };
        let refused = |field, rule| Err(Refusal::new(Field::Creep(field), rule));
        assert!(with(&[1e-3, 0.1], &[0.02, 0.03]).unwrap().creep.is_some());
        assert!(closed().build(&hw()).unwrap().creep.is_none());
        use CreepField::{Modes, TimeConstant, Weight};
        assert_eq!(
            with(&[1e-3, f64::NAN], &[0.1, 0.1]),
            refused(TimeConstant(2), Rule::NotFinite)
        );
        assert_eq!(
            with(&[1e-3], &[f64::INFINITY]),
            refused(Weight(1), Rule::NotFinite)
        );
        // 2 ticks at 50 kHz.
        let e = with(&[1e-5, 0.1], &[0.1, 0.1]).unwrap_err();
        assert_eq!(
            e,
            Refusal::new(Field::Creep(TimeConstant(1)), Rule::AtLeast(4e-5))
        );
        assert_eq!(
            with(&[1e-3, 2e3], &[0.1, 0.1]),
            refused(
                TimeConstant(2),
                Rule::AtMost((1u64 << 26) as f64 / 50_000.0)
            )
        );
        assert_eq!(
            with(&[0.1, 0.1], &[0.1, 0.1]),
            refused(TimeConstant(2), Rule::NotIncreasing)
        );
        assert_eq!(
            with(&[0.1, 1.0], &[0.1, -0.1]),
            refused(Weight(2), Rule::AtLeast(0.0))
        );
        assert_eq!(
            with(&[0.1, 1.0], &[0.5, 0.5]),
            refused(Modes, Rule::AtMost(0.9))
        );
        assert_eq!(
            with(&[0.1, 1.0], &[0.5]),
            refused(Modes, Rule::LengthMismatch)
        );
        assert_eq!(with(&[], &[]), refused(Modes, Rule::Required));
    }

    #[test]
    fn bouc_wen_refusals_name_the_coefficient() {
        let with = |f: fn(&mut BoucWenParams)| {
            let mut s = closed();
            let Model::BoucWen(mut p) = representative_bouc_wen() else {
                unreachable!()
            };
            f(&mut p);
            s.observer = Some(Model::BoucWen(p));
            s.compensator = Some(Model::BoucWen(p));
            s.build(&hw()).unwrap_err()
        };
        let c = |m| Field::Compensator(m);
        assert_eq!(
            with(|p| p.k = -0.1),
            Refusal::new(c(ModelField::K), Rule::Above(0.0))
        );
        assert_eq!(
            with(|p| p.beta = 0.0),
            Refusal::new(c(ModelField::Beta), Rule::Above(0.0))
        );
        assert_eq!(
            with(|p| p.gamma = -0.05),
            Refusal::new(c(ModelField::Gamma), Rule::Unbounded)
        );
        assert_eq!(
            with(|p| p.psi = 0.035),
            Refusal::new(c(ModelField::Psi), Rule::Unbounded)
        );
        assert_eq!(
            with(|p| p.a = 1.0),
            Refusal::new(c(ModelField::A), Rule::BeyondFixedPoint)
        );
        // Within range but, with A < 0, a compensator loop gain of 0.2·(1 + 0.056/0.028)/0.42
        // = 1.43 (rising just after the falling branch's saturation).
        assert_eq!(
            with(|p| p.a = -0.2),
            Refusal::new(c(ModelField::A), Rule::NotInvertible)
        );
        assert_eq!(
            with(|p| p.psi = f64::NAN),
            Refusal::new(c(ModelField::Psi), Rule::NotFinite)
        );
        assert_eq!(
            with(|p| p.chi = -0.03),
            Refusal::new(c(ModelField::Chi), Rule::Unbounded)
        );
        assert_eq!(
            with(|p| p.chi = f64::NAN),
            Refusal::new(c(ModelField::Chi), Rule::NotFinite)
        );
        // The observer's own refusal names the observer.
        let mut s = closed();
        s.observer = Some(Model::BoucWen(BoucWenParams {
            k: 0.0001,
            offset: 0.0,
            a: 0.1,
            beta: 0.04,
            gamma: 0.0,
            psi: 0.0,
            chi: 0.0,
        }));
        assert_eq!(
            s.build(&hw()).unwrap_err(),
            Refusal::new(Field::Observer(ModelField::K), Rule::BeyondFixedPoint)
        );
    }

    #[test]
    fn settings_round_trip_through_postcard() {
        let mut s = closed();
        s.observer = Some(representative_gpi(8).unwrap());
        s.creep = Some(CreepParams::new(&[1e-3, 0.1], &[0.02, 0.03]).unwrap());
        let mut buf = [0u8; 2048];
        let bytes = postcard::to_slice(&s, &mut buf).unwrap();
        let back: Settings = postcard::from_bytes(bytes).unwrap();
        assert_eq!(back, s);
    }
}
