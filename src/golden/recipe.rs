//! A vector set's configuration in physical units, and its build into the tick's
//! [`ControlConfig`] — the same library calls on the host and on the board (the firmware builds
//! its configuration from physical settings the same way).
//!
//! Encoding (little-endian; `f64` as IEEE-754 bits, so the board decodes exactly what the
//! host wrote): compensator `u8` (0 none, 1 inverse P–I, 2 inverse Duhem); observer `u8`
//! (0 none, 1 P–I, 2 Duhem); P–I present `u8`, then `a0, offset` `f64`, count `u8`,
//! thresholds and weights `f64` each; Duhem present `u8`, then `α, β, γ, offset` `f64`;
//! scaling `input_min, input_max, output_min, output_max` `f64`; drive: configuration `u8`
//! (0 differential, 1 unidirectional), `amplifier_full_scale, bias, right_idle, min_voltage,
//! max_voltage, slew_rate, control_rate` `f64`, DAC full scale `u16`, safe state `u8` (0 bias,
//! 1 zero); feedback present `u8`, then ADC bits `u8`, `displacement_at_zero,
//! displacement_at_full_scale, kp, ki, limit` `f64`.

use crate::control::{Compensator, ControlConfig, Observer};
use crate::drive::{Configuration, DifferentialDrive, DriveError, DriveSettings, SafeState};
use crate::duhem::{Duhem, InverseDuhem};
use crate::params::{DuhemParams, ParamError, PiParams, MAX_OPERATORS};
use crate::prandtl_ishlinskii::{InversePrandtlIshlinskii, PrandtlIshlinskii};
use crate::scaling::Scaling;
use crate::settings::{FeedbackSettings, Mode, Model, SensorSettings, Settings, SettingsError};

/// Longest encoded recipe, bytes (a 32-operator P–I, Duhem and feedback fit easily).
pub const MAX_RECIPE: usize = 1024;

/// Which compensator the tick runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CompensatorChoice {
    /// None (the drive follows the setpoint).
    None,
    /// Inverse P–I of the recipe's P–I model.
    InversePi,
    /// Inverse Duhem of the recipe's Duhem model.
    InverseDuhem,
}

/// Which observer the tick runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ObserverChoice {
    /// None (estimate 0).
    None,
    /// Forward P–I of the recipe's P–I model.
    Pi,
    /// Forward Duhem of the recipe's Duhem model.
    Duhem,
}

/// A vector set's configuration, in physical units.
#[derive(Clone, Debug, PartialEq)]
pub struct Recipe {
    /// Compensator.
    pub compensator: CompensatorChoice,
    /// Observer.
    pub observer: ObserverChoice,
    /// P–I model (for a P–I compensator or observer).
    pub pi: Option<PiParams>,
    /// Duhem model (for a Duhem compensator or observer).
    pub duhem: Option<DuhemParams>,
    /// Model ranges.
    pub scaling: Scaling,
    /// The drive and its limits.
    pub drive: DriveSettings,
    /// Sensor feedback (PI on the sensor), if closed loop.
    pub feedback: Option<FeedbackSettings>,
}

/// Why a recipe could not be decoded or built.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RecipeError {
    /// The encoding ends early.
    Truncated,
    /// An enum tag or count is out of range (byte offset in the recipe).
    BadField {
        /// Offset of the field.
        at: usize,
    },
    /// Bytes left after the last field.
    TrailingBytes,
    /// The encoding would exceed [`MAX_RECIPE`].
    TooLong,
    /// A compensator, observer or feedback needs a model the recipe does not have.
    MissingModel,
    /// A model was refused.
    Params(ParamError),
    /// The drive was refused.
    Drive(DriveError),
    /// The feedback settings were refused.
    Settings(SettingsError),
}

impl From<ParamError> for RecipeError {
    fn from(e: ParamError) -> Self {
        RecipeError::Params(e)
    }
}

impl From<DriveError> for RecipeError {
    fn from(e: DriveError) -> Self {
        RecipeError::Drive(e)
    }
}

impl Recipe {
    /// Validates everything and builds the tick's configuration with the library's
    /// constructors (feedback through [`Settings::build`], as a parameter load does).
    pub fn build(&self) -> Result<ControlConfig, RecipeError> {
        let s = &self.scaling;
        let pi = || self.pi.as_ref().ok_or(RecipeError::MissingModel);
        let duhem = || self.duhem.as_ref().ok_or(RecipeError::MissingModel);
        let compensator = match self.compensator {
            CompensatorChoice::None => Compensator::None,
            CompensatorChoice::InversePi => {
                Compensator::InversePi(InversePrandtlIshlinskii::new(pi()?, s)?)
            }
            CompensatorChoice::InverseDuhem => {
                Compensator::InverseDuhem(InverseDuhem::new(duhem()?, s)?)
            }
        };
        let observer = match self.observer {
            ObserverChoice::None => Observer::None,
            ObserverChoice::Pi => Observer::Pi(PrandtlIshlinskii::new(pi()?, s)?),
            ObserverChoice::Duhem => Observer::Duhem(Duhem::new(duhem()?, s)?),
        };
        let feedback = match &self.feedback {
            None => None,
            Some(fb) => {
                let model = match (&self.pi, &self.duhem) {
                    (Some(p), _) => Model::PrandtlIshlinskii(p.clone()),
                    (None, Some(d)) => Model::Duhem(*d),
                    (None, None) => return Err(RecipeError::MissingModel),
                };
                let settings = Settings {
                    model: Some(model),
                    scaling: *s,
                    drive: self.drive,
                    feedback: Some(*fb),
                    mode: Mode::ClosedLoop,
                };
                settings.build().map_err(RecipeError::Settings)?.feedback
            }
        };
        // Closed loop with a sensor, else compensated open loop, else bypass.
        let mode = match (&feedback, &compensator) {
            (Some(_), _) => Mode::ClosedLoop,
            (None, Compensator::None) => Mode::Bypass,
            (None, _) => Mode::OpenLoop,
        };
        Ok(ControlConfig {
            compensator,
            observer,
            feedback,
            drive: DifferentialDrive::new(&self.drive, s)?,
            mode,
        })
    }

    /// Encodes the recipe (see the module doc) into `out`.
    pub fn encode(&self, out: &mut heapless::Vec<u8, MAX_RECIPE>) -> Result<(), RecipeError> {
        let mut w = Writer(out);
        w.u8(match self.compensator {
            CompensatorChoice::None => 0,
            CompensatorChoice::InversePi => 1,
            CompensatorChoice::InverseDuhem => 2,
        })?;
        w.u8(match self.observer {
            ObserverChoice::None => 0,
            ObserverChoice::Pi => 1,
            ObserverChoice::Duhem => 2,
        })?;
        match &self.pi {
            None => w.u8(0)?,
            Some(p) => {
                w.u8(1)?;
                w.f64s(&[p.a0, p.offset])?;
                let n = p.thresholds.len().min(p.weights.len());
                w.u8(n as u8)?;
                w.f64s(&p.thresholds[..n])?;
                w.f64s(&p.weights[..n])?;
            }
        }
        match &self.duhem {
            None => w.u8(0)?,
            Some(d) => {
                w.u8(1)?;
                w.f64s(&[d.alpha, d.beta, d.gamma, d.offset])?;
            }
        }
        let s = &self.scaling;
        w.f64s(&[s.input_min, s.input_max, s.output_min, s.output_max])?;
        let d = &self.drive;
        w.u8(match d.configuration {
            Configuration::Differential => 0,
            Configuration::Unidirectional => 1,
        })?;
        w.f64s(&[
            d.amplifier_full_scale,
            d.bias,
            d.right_idle,
            d.min_voltage,
            d.max_voltage,
            d.slew_rate,
            d.control_rate,
        ])?;
        w.bytes(&d.dac_full_scale.to_le_bytes())?;
        w.u8(match d.safe_state {
            SafeState::Bias => 0,
            SafeState::Zero => 1,
        })?;
        match &self.feedback {
            None => w.u8(0)?,
            Some(fb) => {
                w.u8(1)?;
                w.u8(fb.sensor.adc_bits.min(255) as u8)?;
                w.f64s(&[
                    fb.sensor.displacement_at_zero,
                    fb.sensor.displacement_at_full_scale,
                    fb.kp,
                    fb.ki,
                    fb.limit,
                ])?;
            }
        }
        Ok(())
    }

    /// Decodes a recipe; every tag, count and length is checked.
    pub fn decode(bytes: &[u8]) -> Result<Self, RecipeError> {
        let mut r = Reader { b: bytes, pos: 0 };
        let compensator = match r.tag(3)? {
            0 => CompensatorChoice::None,
            1 => CompensatorChoice::InversePi,
            _ => CompensatorChoice::InverseDuhem,
        };
        let observer = match r.tag(3)? {
            0 => ObserverChoice::None,
            1 => ObserverChoice::Pi,
            _ => ObserverChoice::Duhem,
        };
        let pi = if r.tag(2)? == 1 {
            let a0 = r.f64()?;
            let offset = r.f64()?;
            let at = r.pos;
            let n = r.u8()? as usize;
            if n > MAX_OPERATORS {
                return Err(RecipeError::BadField { at });
            }
            let mut t = [0.0; MAX_OPERATORS];
            let mut w = [0.0; MAX_OPERATORS];
            for x in t.iter_mut().take(n) {
                *x = r.f64()?;
            }
            for x in w.iter_mut().take(n) {
                *x = r.f64()?;
            }
            Some(PiParams::new(a0, offset, &t[..n], &w[..n])?)
        } else {
            None
        };
        let duhem = if r.tag(2)? == 1 {
            Some(DuhemParams {
                alpha: r.f64()?,
                beta: r.f64()?,
                gamma: r.f64()?,
                offset: r.f64()?,
            })
        } else {
            None
        };
        let scaling = Scaling {
            input_min: r.f64()?,
            input_max: r.f64()?,
            output_min: r.f64()?,
            output_max: r.f64()?,
        };
        let configuration = match r.tag(2)? {
            0 => Configuration::Differential,
            _ => Configuration::Unidirectional,
        };
        let mut v = [0.0; 7];
        for x in v.iter_mut() {
            *x = r.f64()?;
        }
        let dac_full_scale = r.u16()?;
        let safe_state = match r.tag(2)? {
            0 => SafeState::Bias,
            _ => SafeState::Zero,
        };
        let drive = DriveSettings {
            configuration,
            amplifier_full_scale: v[0],
            bias: v[1],
            right_idle: v[2],
            min_voltage: v[3],
            max_voltage: v[4],
            slew_rate: v[5],
            control_rate: v[6],
            dac_full_scale,
            safe_state,
        };
        let feedback = if r.tag(2)? == 1 {
            let adc_bits = r.u8()? as u32;
            let sensor = SensorSettings {
                adc_bits,
                displacement_at_zero: r.f64()?,
                displacement_at_full_scale: r.f64()?,
            };
            let (kp, ki, limit) = (r.f64()?, r.f64()?, r.f64()?);
            // PI feedback only: the golden sets carry no derivative, notch or drift limit.
            Some(FeedbackSettings::pi(sensor, kp, ki, limit))
        } else {
            None
        };
        if r.pos != bytes.len() {
            return Err(RecipeError::TrailingBytes);
        }
        // Ranges are validated like any other input (the struct literal above skips `new`).
        Scaling::new(
            scaling.input_min,
            scaling.input_max,
            scaling.output_min,
            scaling.output_max,
        )?;
        Ok(Self {
            compensator,
            observer,
            pi,
            duhem,
            scaling,
            drive,
            feedback,
        })
    }
}

struct Writer<'a>(&'a mut heapless::Vec<u8, MAX_RECIPE>);

impl Writer<'_> {
    fn bytes(&mut self, b: &[u8]) -> Result<(), RecipeError> {
        self.0
            .extend_from_slice(b)
            .map_err(|_| RecipeError::TooLong)
    }
    fn u8(&mut self, x: u8) -> Result<(), RecipeError> {
        self.bytes(&[x])
    }
    fn f64s(&mut self, xs: &[f64]) -> Result<(), RecipeError> {
        xs.iter().try_for_each(|x| self.bytes(&x.to_le_bytes()))
    }
}

struct Reader<'a> {
    b: &'a [u8],
    pos: usize,
}

impl Reader<'_> {
    fn take<const N: usize>(&mut self) -> Result<[u8; N], RecipeError> {
        let s = self
            .b
            .get(self.pos..self.pos + N)
            .ok_or(RecipeError::Truncated)?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        self.pos += N;
        Ok(a)
    }
    fn u8(&mut self) -> Result<u8, RecipeError> {
        Ok(self.take::<1>()?[0])
    }
    /// A `u8` that must be below `count`.
    fn tag(&mut self, count: u8) -> Result<u8, RecipeError> {
        let at = self.pos;
        let t = self.u8()?;
        if t < count {
            Ok(t)
        } else {
            Err(RecipeError::BadField { at })
        }
    }
    fn u16(&mut self) -> Result<u16, RecipeError> {
        Ok(u16::from_le_bytes(self.take()?))
    }
    fn f64(&mut self) -> Result<f64, RecipeError> {
        Ok(f64::from_le_bytes(self.take()?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::default_config;

    fn recipe() -> Recipe {
        Recipe {
            compensator: CompensatorChoice::InversePi,
            observer: ObserverChoice::Duhem,
            pi: Some(default_config::pi_params(16).unwrap()),
            duhem: Some(default_config::duhem_params()),
            scaling: default_config::scaling(),
            drive: default_config::drive_settings(50_000.0, SafeState::Bias),
            feedback: Some(FeedbackSettings::pi(
                SensorSettings {
                    adc_bits: 12,
                    displacement_at_zero: -1.0,
                    displacement_at_full_scale: 71.0,
                },
                0.2,
                500.0,
                0.1,
            )),
        }
    }

    #[test]
    fn a_recipe_round_trips_bit_for_bit_and_builds() {
        let r = recipe();
        let mut b = heapless::Vec::new();
        r.encode(&mut b).unwrap();
        let back = Recipe::decode(&b).unwrap();
        assert_eq!(back, r);
        assert_eq!(back.build().unwrap(), r.build().unwrap());
        assert!(back.build().unwrap().feedback.is_some());
    }

    #[test]
    fn malformed_recipes_are_refused_not_panicked_on() {
        let r = recipe();
        let mut b = heapless::Vec::new();
        r.encode(&mut b).unwrap();
        for cut in 0..b.len() {
            assert!(Recipe::decode(&b[..cut]).is_err(), "cut at {cut}");
        }
        let mut bad = b.clone();
        bad[0] = 7;
        assert_eq!(Recipe::decode(&bad), Err(RecipeError::BadField { at: 0 }));
        let mut long = b.clone();
        long.push(0).unwrap();
        assert_eq!(Recipe::decode(&long), Err(RecipeError::TrailingBytes));
        let mut missing = recipe();
        missing.duhem = None;
        assert_eq!(missing.build(), Err(RecipeError::MissingModel));
    }
}
