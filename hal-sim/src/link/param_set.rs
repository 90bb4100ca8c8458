//! From the parameter file `identify` writes to the [`ParamSet`] a `LoadParams` request
//! carries: the model and ranges come from the file, the drive (configuration, bias, voltage
//! limits, slew rate, safe state), the feedback gains and the mode from [`DriveOptions`]
//! (defaults: the firmware's compiled-in drive, `twinstack::default_config`).
//!
//! The wire carries `f32`; the conversion refuses, before anything is sent, what the board
//! could not run: more operators than a message holds, a value `f32` cannot hold, a model
//! that the `f32` rounding makes non-invertible (the library's own checks are run on the
//! rounded values), drive settings the library refuses, feedback gains out of range, and
//! closed loop with an inverted sensor (`output_sign = −1`: the board's sensor calibration
//! is not part of a parameter load).

#[cfg(doc)]
use crate::param_file::ParamFile;
use crate::stage_model::{Hysteresis, StageModel};
use twinstack::default_config;
use twinstack::drive::{Configuration, DifferentialDrive, DriveError, SafeState};
use twinstack::duhem::{Duhem, InverseDuhem};
use twinstack::prandtl_ishlinskii::{InversePrandtlIshlinskii, PrandtlIshlinskii};
use twinstack::protocol::messages::{
    FeedbackParams, Mode, ModelParams, ParamSet, MAX_PARAM_OPERATORS,
};
use twinstack::{DuhemParams, ParamError, PiParams, Scaling};

/// What a parameter load sets besides the model: the drive, the feedback and the mode.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DriveOptions {
    /// Differential or unidirectional.
    pub configuration: Configuration,
    /// Bias ū, volts.
    pub bias: f64,
    /// Lowest and highest stack voltage, volts.
    pub voltage_limits: [f64; 2],
    /// Slew limit, volts per second.
    pub slew_rate: f64,
    /// Where the outputs go on a fault.
    pub safe_state: SafeState,
    /// PI feedback `[kp, ki per second, correction limit (fraction of the drive range)]`, or
    /// none.
    pub feedback: Option<[f64; 3]>,
    /// Mode to enter once loaded.
    pub mode: Mode,
}

impl Default for DriveOptions {
    /// The firmware's compiled-in drive (differential, bias 70 V, 0…140 V, 2 V/µs, safe state
    /// bias), its feedback gains (kp 0.2, ki 500 per second — 0.01 per tick at 50 kHz —,
    /// limit 0.2) and open loop.
    fn default() -> Self {
        let d = default_config::drive_settings(50_000.0, SafeState::Bias);
        Self {
            configuration: d.configuration,
            bias: d.bias,
            voltage_limits: [d.min_voltage, d.max_voltage],
            slew_rate: d.slew_rate,
            safe_state: d.safe_state,
            feedback: Some([0.2, 500.0, 0.2]),
            mode: Mode::OpenLoop,
        }
    }
}

/// Why a parameter file cannot be sent as a parameter load.
#[derive(Debug, thiserror::Error)]
pub enum ParamSetError {
    /// More play operators than a `LoadParams` message carries.
    #[error("{count} play operators, a parameter load carries at most {MAX_PARAM_OPERATORS}")]
    TooManyOperators {
        /// Operators in the file.
        count: usize,
    },
    /// A value does not fit an `f32`.
    #[error("`{field}` = {value} does not fit the wire's f32")]
    NotRepresentable {
        /// The field.
        field: &'static str,
        /// Its value.
        value: f64,
    },
    /// The model, rounded to `f32`, is refused by the library (e.g. no longer invertible).
    #[error("the model as sent (rounded to f32) is refused: {0}")]
    Model(ParamError),
    /// The drive settings are refused by the library.
    #[error("drive settings refused: {0:?}")]
    Drive(DriveError),
    /// Feedback gains out of range.
    #[error("feedback gains [kp, ki, limit] = {0:?}: kp and ki must be finite and ≥ 0, the limit in (0, 1]")]
    Feedback([f64; 3]),
    /// Closed loop with feedback off.
    #[error("closed loop needs feedback gains")]
    ClosedLoopWithoutFeedback,
    /// Closed loop with an inverted sensor.
    #[error("the file's sensor is inverted (output_sign = -1): closed loop would feed back with the wrong sign; use open loop, or recalibrate the board's sensor")]
    InvertedSensor,
}

fn f32_of(field: &'static str, value: f64) -> Result<f32, ParamSetError> {
    let v = value as f32;
    if v.is_finite() {
        Ok(v)
    } else {
        Err(ParamSetError::NotRepresentable { field, value })
    }
}

fn f32_pair(field: &'static str, a: f64, b: f64) -> Result<[f32; 2], ParamSetError> {
    Ok([f32_of(field, a)?, f32_of(field, b)?])
}

/// The parameter load for `model` (as [`ParamFile::load`] returns it) with `drive`.
pub fn param_set(model: &StageModel, drive: &DriveOptions) -> Result<ParamSet, ParamSetError> {
    let s = &model.scaling;
    let input_range = f32_pair("input_range", s.input_min, s.input_max)?;
    let output_range = f32_pair("output_range", s.output_min, s.output_max)?;
    let scaling = Scaling::new(
        input_range[0] as f64,
        input_range[1] as f64,
        output_range[0] as f64,
        output_range[1] as f64,
    )
    .map_err(ParamSetError::Model)?;
    let wire_model = match &model.hysteresis {
        Hysteresis::Pi(p) => {
            if p.thresholds.len() > MAX_PARAM_OPERATORS {
                return Err(ParamSetError::TooManyOperators {
                    count: p.thresholds.len(),
                });
            }
            let mut thresholds = heapless::Vec::new();
            let mut weights = heapless::Vec::new();
            for (&r, &w) in p.thresholds.iter().zip(p.weights.iter()) {
                // Capacity checked above.
                let _ = thresholds.push(f32_of("pi.thresholds", r)?);
                let _ = weights.push(f32_of("pi.weights", w)?);
            }
            let a0 = f32_of("pi.a0", p.a0)?;
            let offset = f32_of("pi.offset", p.offset)?;
            // The board's checks, on the values it will receive.
            let t64: Vec<f64> = thresholds.iter().map(|&v| v as f64).collect();
            let w64: Vec<f64> = weights.iter().map(|&v| v as f64).collect();
            let sent = PiParams::new(a0 as f64, offset as f64, &t64, &w64)
                .map_err(ParamSetError::Model)?;
            PrandtlIshlinskii::new(&sent, &scaling).map_err(ParamSetError::Model)?;
            InversePrandtlIshlinskii::new(&sent, &scaling).map_err(ParamSetError::Model)?;
            ModelParams::PrandtlIshlinskii {
                a0,
                offset,
                thresholds,
                weights,
            }
        }
        Hysteresis::Duhem(d) => {
            let alpha = f32_of("duhem.alpha", d.alpha)?;
            let beta = f32_of("duhem.beta", d.beta)?;
            let gamma = f32_of("duhem.gamma", d.gamma)?;
            let offset = f32_of("duhem.offset", d.offset)?;
            let sent = DuhemParams {
                alpha: alpha as f64,
                beta: beta as f64,
                gamma: gamma as f64,
                offset: offset as f64,
            };
            Duhem::new(&sent, &scaling).map_err(ParamSetError::Model)?;
            InverseDuhem::new(&sent, &scaling).map_err(ParamSetError::Model)?;
            ModelParams::Duhem {
                alpha,
                beta,
                gamma,
                offset,
            }
        }
    };
    let bias = f32_of("bias", drive.bias)?;
    let voltage_limits = f32_pair(
        "voltage_limits",
        drive.voltage_limits[0],
        drive.voltage_limits[1],
    )?;
    let slew_rate = f32_of("slew_rate", drive.slew_rate)?;
    let mut settings = default_config::drive_settings(50_000.0, drive.safe_state);
    settings.configuration = drive.configuration;
    settings.bias = bias as f64;
    settings.right_idle = bias as f64;
    settings.min_voltage = voltage_limits[0] as f64;
    settings.max_voltage = voltage_limits[1] as f64;
    settings.slew_rate = slew_rate as f64;
    DifferentialDrive::new(&settings, &scaling).map_err(ParamSetError::Drive)?;
    let feedback = match drive.feedback {
        None => None,
        Some(g) => {
            let ok = g.iter().all(|v| v.is_finite())
                && g[0] >= 0.0
                && g[1] >= 0.0
                && g[2] > 0.0
                && g[2] <= 1.0;
            if !ok {
                return Err(ParamSetError::Feedback(g));
            }
            Some(FeedbackParams {
                kp: f32_of("kp", g[0])?,
                ki: f32_of("ki", g[1])?,
                kd: 0.0,
                derivative_cutoff_hz: 1.0,
                limit: f32_of("limit", g[2])?,
                notch: None,
                drift_limit: None,
            })
        }
    };
    if drive.mode == Mode::ClosedLoop {
        if feedback.is_none() {
            return Err(ParamSetError::ClosedLoopWithoutFeedback);
        }
        if model.output_sign < 0.0 {
            return Err(ParamSetError::InvertedSensor);
        }
    }
    Ok(ParamSet {
        model: wire_model,
        input_range,
        output_range,
        configuration: drive.configuration,
        bias,
        voltage_limits,
        slew_rate,
        safe_state: drive.safe_state,
        feedback,
        mode: drive.mode,
    })
}
