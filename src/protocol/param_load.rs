//! Parameter loads: a [`ParamSet`] from the wire (or the flash record) onto the board's
//! [`Settings`], and back into the record.
//!
//! A load sets what the host may change — model, ranges, bias, limits, slew, safe state, PI
//! gains, mode — while the [`BoardProfile`] keeps what the hardware fixes: amplifier and DAC
//! full scale, control rate, the sensor's ADC and calibration. Validation is whole
//! ([`Settings::build`]) and happens here, off the tick path; nothing is applied unless all of
//! it passes.

use crate::control::Feedback;
use crate::drive::{Configuration, DriveSettings};
use crate::param_store::{self, BoardSettings, MAX_RECORD, PARAMS_VERSION};
use crate::params::{DuhemParams, PiParams};
use crate::scaling::Scaling;
use crate::settings::{FeedbackSettings, Mode, Model, SensorSettings, Settings, SettingsError};

use super::messages::{ModelParams, NackReason, ParamSet};

/// What the board's hardware fixes, whatever a parameter load says.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BoardProfile {
    /// Amplifier output at DAC full scale, volts.
    pub amplifier_full_scale: f64,
    /// Full-scale DAC code (4095 for the STM32's DAC).
    pub dac_full_scale: u16,
    /// Control rate, Hz.
    pub control_rate_hz: f64,
    /// The position sensor and its ADC, if the board has one.
    pub sensor: Option<SensorSettings>,
}

/// Why a parameter set was refused, as the NACK reason the host gets.
pub fn nack_reason(e: SettingsError) -> NackReason {
    match e {
        SettingsError::Params(p) => NackReason::InvalidParams(p),
        SettingsError::Drive(d) => NackReason::InvalidDrive(d),
        SettingsError::ModeNeedsModel | SettingsError::ClosedLoopNeedsSensor => {
            NackReason::Unsupported
        }
        SettingsError::BadFeedback | SettingsError::Notch(_) => NackReason::OutOfRange,
    }
}

/// The settings a parameter set describes on `board` (not yet validated as a whole: call
/// [`Settings::build`]). Refuses closed loop on a board without a sensor or without gains.
pub fn settings_from_params(p: &ParamSet, board: &BoardProfile) -> Result<Settings, NackReason> {
    let f = |x: f32| x as f64;
    let model = match &p.model {
        ModelParams::PrandtlIshlinskii {
            a0,
            offset,
            thresholds,
            weights,
        } => {
            let mut r = [0.0f64; super::messages::MAX_PARAM_OPERATORS];
            let mut w = [0.0f64; super::messages::MAX_PARAM_OPERATORS];
            for (d, s) in r.iter_mut().zip(thresholds.iter()) {
                *d = f(*s);
            }
            for (d, s) in w.iter_mut().zip(weights.iter()) {
                *d = f(*s);
            }
            let params = PiParams::new(
                f(*a0),
                f(*offset),
                &r[..thresholds.len()],
                &w[..weights.len()],
            )
            .map_err(NackReason::InvalidParams)?;
            Model::PrandtlIshlinskii(params)
        }
        ModelParams::Duhem {
            alpha,
            beta,
            gamma,
            offset,
        } => Model::Duhem(DuhemParams {
            alpha: f(*alpha),
            beta: f(*beta),
            gamma: f(*gamma),
            offset: f(*offset),
        }),
    };
    let scaling = Scaling::new(
        f(p.input_range[0]),
        f(p.input_range[1]),
        f(p.output_range[0]),
        f(p.output_range[1]),
    )
    .map_err(NackReason::InvalidParams)?;
    let drive = DriveSettings {
        configuration: p.configuration,
        amplifier_full_scale: board.amplifier_full_scale,
        bias: f(p.bias),
        right_idle: match p.configuration {
            Configuration::Differential => f(p.bias),
            Configuration::Unidirectional => f(p.voltage_limits[0]),
        },
        min_voltage: f(p.voltage_limits[0]),
        max_voltage: f(p.voltage_limits[1]),
        slew_rate: f(p.slew_rate),
        control_rate: board.control_rate_hz,
        dac_full_scale: board.dac_full_scale,
        safe_state: p.safe_state,
    };
    if p.mode == Mode::ClosedLoop && (board.sensor.is_none() || p.feedback.is_none()) {
        return Err(NackReason::Unsupported);
    }
    // With a sensor on board the feedback settings are always present (the recorder uses
    // the calibration); the gains only act in closed loop.
    let feedback = board.sensor.map(|sensor| match &p.feedback {
        Some(params) => FeedbackSettings::from_wire(params, sensor),
        None => FeedbackSettings::pi(sensor, 0.0, 0.0, 1.0),
    });
    Ok(Settings {
        model: Some(model),
        scaling,
        drive,
        feedback,
        mode: p.mode,
    })
}

/// The sensor's calibration under `settings` (for recording the sensor when feedback is
/// off), if the board has a sensor and it maps into range.
pub fn sensor_calibration(settings: &Settings) -> Option<Feedback> {
    settings
        .feedback
        .as_ref()
        .and_then(|fb| settings.feedback_config(fb, false).ok())
}

/// Encodes the flash record holding `board` and `params` (layout [`PARAMS_VERSION`]) into
/// `out`; returns its length.
pub fn encode_record(
    board: &BoardSettings,
    params: &ParamSet,
    out: &mut [u8; MAX_RECORD],
) -> Result<usize, NackReason> {
    let mut payload = [0u8; param_store::MAX_PAYLOAD];
    payload[..BoardSettings::PAYLOAD_LEN].copy_from_slice(&board.to_payload());
    let used = postcard::to_slice(params, &mut payload[BoardSettings::PAYLOAD_LEN..])
        .map_err(|_| NackReason::StoreFailed)?
        .len();
    param_store::encode(
        PARAMS_VERSION,
        &payload[..BoardSettings::PAYLOAD_LEN + used],
        out,
    )
    .map_err(|_| NackReason::StoreFailed)
}

/// The parameter set a flash record holds, if it is sound and has one.
pub fn decode_record(record: &[u8]) -> Option<ParamSet> {
    let (_, params) = param_store::decode_payload(record).ok()?;
    match postcard::take_from_bytes::<ParamSet>(params) {
        Ok((p, [])) => Some(p),
        _ => None,
    }
}
