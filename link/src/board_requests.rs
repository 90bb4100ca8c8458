//! What the host does with a board beyond single requests, shared by the `twinstack` board
//! commands and the Python package (`python/`), so that both send the same thing and refuse the
//! same thing:
//!
//! * the settings a parameter load sends ([`keep_from_board`]: the file's, with the sensor
//!   calibration, feedback gains, input shaping and preview it leaves out kept from the board) and the checks before
//!   sending them ([`check_load`]: closed loop on an inverted sensor, a model whose input range
//!   the drive cannot reach);
//! * a waveform request from physical numbers ([`waveform`]);
//! * a multi-signal capture request, checked before it is sent ([`capture_request`]);
//! * the status report as one JSON object ([`status_json`]).

use crate::capture::signal_mask;
use twinstack::config::settings::{Mode, Settings};
use twinstack::control::drive::Configuration;
use twinstack::protocol::messages::{CaptureRequest, StatusReport, Trigger, WaveShape, Waveform};

/// The settings a parameter load sends for a file's `file` settings: the file's, with the
/// sensor calibration, the feedback gains, the input shaping and the preview it leaves out (a file from
/// `identify` has none of them: they are the stage's, not the model's) taken from `board`,
/// the settings in force on the board.
pub fn keep_from_board(file: &Settings, board: Option<&Settings>) -> Settings {
    let mut s = file.clone();
    if s.sensor.is_none() {
        s.sensor = board.and_then(|b| b.sensor);
    }
    if s.feedback.is_none() {
        s.feedback = board.and_then(|b| b.feedback);
    }
    if s.shaping.is_none() {
        s.shaping = board.and_then(|b| b.shaping);
    }
    if s.preview.is_none() {
        s.preview = board.and_then(|b| b.preview);
    }
    s
}

/// Part of a model's input range the drive cannot reach, if any beyond a tolerance of 1 % of
/// the drive's window: `(model range, drive window)`, volts on the left stack.
pub fn unreachable_input(settings: &Settings) -> Option<((f64, f64), (f64, f64))> {
    let (lo, hi) = settings.drive.left_window();
    let r = &settings.ranges;
    let tolerance = 0.01 * (hi - lo).abs();
    (r.input_min < lo - tolerance || r.input_max > hi + tolerance)
        .then_some(((r.input_min, r.input_max), (lo, hi)))
}

/// Why a parameter load is not sent (or, with `clamp`, sent with a warning).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum LoadRefused {
    /// The drive's own settings are wrong (an empty voltage window, a bias outside it):
    /// said first, before what they would do to the model.
    #[error("drive: {0}")]
    Drive(twinstack::refusal::Refusal),
    /// Closed loop with a sensor that reads the model's output negated.
    #[error("the file's sensor is inverted (output_sign = -1): closed loop would feed back with the wrong sign; use open loop, or give the board a sensor calibration that reads the model's output")]
    InvertedSensor,
    /// The model's input range reaches beyond the drive's window.
    #[error("the model's input range {}…{} V reaches beyond what the drive can apply ({}…{} V on the left stack: {configuration:?}, {min_voltage}…{max_voltage} V, bias {bias} V), so the drive limit would clip it", model.0, model.1, drive.0, drive.1)]
    Unreachable {
        /// The model's input range, volts.
        model: (f64, f64),
        /// The left stack's window, volts.
        drive: (f64, f64),
        /// The drive's configuration.
        configuration: Configuration,
        /// Lowest stack voltage.
        min_voltage: f64,
        /// Highest stack voltage.
        max_voltage: f64,
        /// Bias.
        bias: f64,
    },
}

/// The checks before `settings` (of a model whose sensor reads `output_sign` × its output)
/// are sent: `Err` refuses the load; `Ok(Some(warning))` is a model the drive cannot reach in
/// full, accepted because of `clamp`.
///
/// ```
/// use twinstack_link::board_requests::{check_load, LoadRefused};
/// use twinstack::config::settings::{Mode, Settings};
/// // 0…140 V of model input on the default drive's 0…140 V.
/// let mut s = Settings { mode: Mode::OpenLoop, ..Settings::default() };
/// assert_eq!(check_load(&s, 1.0, false), Ok(None));
/// s.ranges.input_min = -150.0;
/// assert!(matches!(check_load(&s, 1.0, false), Err(LoadRefused::Unreachable { .. })));
/// assert!(matches!(check_load(&s, 1.0, true), Ok(Some(LoadRefused::Unreachable { .. }))));
/// ```
pub fn check_load(
    settings: &Settings,
    output_sign: f64,
    clamp: bool,
) -> Result<Option<LoadRefused>, LoadRefused> {
    if settings.mode == Mode::ClosedLoop && output_sign < 0.0 {
        return Err(LoadRefused::InvertedSensor);
    }
    let d = &settings.drive;
    if d.max_voltage.is_nan() || d.min_voltage.is_nan() || d.max_voltage <= d.min_voltage {
        return Err(LoadRefused::Drive(twinstack::refusal::Refusal::new(
            twinstack::refusal::Field::VoltageLimits,
            twinstack::refusal::Rule::Empty,
        )));
    }
    twinstack::refusal::within(
        twinstack::refusal::Field::Bias,
        d.bias,
        d.min_voltage,
        d.max_voltage,
    )
    .map_err(LoadRefused::Drive)?;
    let Some((model, drive)) = unreachable_input(settings) else {
        return Ok(None);
    };
    let d = &settings.drive;
    let e = LoadRefused::Unreachable {
        model,
        drive,
        configuration: d.configuration,
        min_voltage: d.min_voltage,
        max_voltage: d.max_voltage,
        bias: d.bias,
    };
    if clamp {
        Ok(Some(e))
    } else {
        Err(e)
    }
}

/// Why a waveform cannot be sent.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum WaveformError {
    /// NaN or infinite.
    #[error("offset, amplitude and frequency must be finite numbers")]
    NotFinite,
    /// Amplitude outside 0…1.
    #[error("amplitude {0}: must lie in 0…1 (normalised)")]
    Amplitude(f64),
    /// Offset ± amplitude beyond −1…1.
    #[error("offset {offset} ± amplitude {amplitude} leaves the normalised range -1…1")]
    Range {
        /// Offset.
        offset: f64,
        /// Amplitude.
        amplitude: f64,
    },
    /// Below 1 mHz or beyond the wire's range (its mHz in 32 bits): the board's own limit,
    /// half its tick rate and below, is the board's to say.
    #[error("frequency {0} Hz: must be from 0.001 Hz to 4294967.295 Hz (the request's range)")]
    Frequency(f64),
    /// A decay (amplitude kept per cycle) outside 0…1 (below 1).
    #[error("decay {0}: the amplitude kept per cycle must lie in 0…1 (below 1)")]
    Decay(f64),
}

/// The waveform request for `shape` around `offset` with `amplitude` (normalised, −1…1 over
/// the model's output range) at `frequency_hz` (resolution 1 mHz).
///
/// ```
/// use twinstack_link::board_requests::waveform;
/// use twinstack::protocol::messages::WaveShape;
/// let w = waveform(WaveShape::Sine, 0.0, 0.5, 2.5, None).unwrap();
/// assert_eq!((w.amplitude, w.frequency_mhz), (16384, 2500));
/// assert!(waveform(WaveShape::Sine, 0.6, 0.5, 1.0, None).is_err());
/// // Beyond the request's range either way, named with both ends.
/// let e = waveform(WaveShape::Sine, 0.0, 0.5, 1e7, None).unwrap_err().to_string();
/// assert!(e.contains("from 0.001 Hz to 4294967.295 Hz"), "{e}");
/// ```
pub fn waveform(
    shape: WaveShape,
    offset: f64,
    amplitude: f64,
    frequency_hz: f64,
    decay: Option<(f64, u16)>,
) -> Result<Waveform, WaveformError> {
    let (o, a, f) = (offset, amplitude, frequency_hz);
    if !(o.is_finite() && a.is_finite() && f.is_finite()) {
        return Err(WaveformError::NotFinite);
    }
    if !(0.0..=1.0).contains(&a) {
        return Err(WaveformError::Amplitude(a));
    }
    if o - a < -1.0 || o + a > 1.0 {
        return Err(WaveformError::Range {
            offset: o,
            amplitude: a,
        });
    }
    let decay = match decay {
        None => None,
        Some((d, hold_cycles)) if d.is_finite() && (0.0..1.0).contains(&d) => {
            Some(twinstack::protocol::messages::WaveDecay {
                hold_cycles,
                keep: (d * 65536.0).round().min(65535.0) as u16,
            })
        }
        Some((d, _)) => return Err(WaveformError::Decay(d)),
    };
    let mhz = (f * 1000.0).round();
    if !(1.0..=u32::MAX as f64).contains(&mhz) {
        return Err(WaveformError::Frequency(f));
    }
    Ok(Waveform {
        shape,
        offset: crate::setpoint_file::q1_15(o),
        amplitude: crate::setpoint_file::q1_15(a),
        frequency_mhz: mhz as u32,
        decay,
    })
}

/// Why a capture request cannot be armed.
#[derive(Debug, PartialEq, Eq, thiserror::Error)]
pub enum CaptureRequestError {
    /// The signal list.
    #[error("signals {list:?}: {error}")]
    Signals {
        /// The list as given.
        list: String,
        /// What is wrong with it.
        error: crate::capture::SignalListError,
    },
    /// No frames.
    #[error("samples must be at least 1")]
    NoSamples,
    /// Decimation 0.
    #[error("decimation must be at least 1")]
    NoDecimation,
    /// Pre-trigger frames not below the frames.
    #[error("pre-trigger {pre}: must be below the samples ({samples})")]
    PreNotBelowSamples {
        /// Pre-trigger frames.
        pre: u32,
        /// Frames.
        samples: u32,
    },
    /// Pre-trigger frames with an immediate trigger.
    #[error(
        "pre-trigger {0} with the trigger `now`: nothing comes before an immediate trigger; use 0"
    )]
    PreWithNow(u32),
}

/// The capture request for `signals` (comma-separated names: setpoint, left, right, sensor,
/// estimate, error), `samples` frames of which `pre` from before the `trigger`, one every
/// `decimation` ticks, or why it cannot be armed.
///
/// ```
/// use twinstack_link::board_requests::capture_request;
/// use twinstack::protocol::messages::Trigger;
/// let r = capture_request("setpoint,sensor", 1000, 0, Trigger::Now, 1).unwrap();
/// assert_eq!((r.signals.count_ones(), r.samples), (2, 1000));
/// assert!(capture_request("setpoint", 1000, 10, Trigger::Now, 1).is_err());
/// ```
pub fn capture_request(
    signals: &str,
    samples: u32,
    pre: u32,
    trigger: Trigger,
    decimation: u16,
) -> Result<CaptureRequest, CaptureRequestError> {
    let mask = signal_mask(signals).map_err(|error| CaptureRequestError::Signals {
        list: signals.to_string(),
        error,
    })?;
    if samples == 0 {
        return Err(CaptureRequestError::NoSamples);
    }
    if decimation == 0 {
        return Err(CaptureRequestError::NoDecimation);
    }
    if pre >= samples {
        return Err(CaptureRequestError::PreNotBelowSamples { pre, samples });
    }
    if trigger == Trigger::Now && pre != 0 {
        return Err(CaptureRequestError::PreWithNow(pre));
    }
    Ok(CaptureRequest {
        signals: mask,
        samples,
        pre_trigger: pre,
        trigger,
        decimation,
    })
}

/// The names of the flags set in `s`.
pub fn flag_names(s: &StatusReport) -> Vec<&'static str> {
    [
        (StatusReport::DEFAULTS, "defaults"),
        (StatusReport::STREAMING, "streaming"),
        (StatusReport::WAVEFORM, "waveform"),
        (StatusReport::RECORDING, "recording"),
        (StatusReport::TELEMETRY, "telemetry"),
        (StatusReport::SEQUENCE, "sequence"),
        (StatusReport::SCANNING, "scanning"),
        (StatusReport::TRIGGER_ARMED, "trigger-armed"),
        (StatusReport::ANALOG, "analog"),
        (StatusReport::ANALOG_FAULT, "analog-fault"),
        (StatusReport::WATCHDOG_RESET, "watchdog-reset"),
        (StatusReport::COARSE, "coarse"),
    ]
    .into_iter()
    .filter(|&(bit, _)| s.has(bit))
    .map(|(_, name)| name)
    .collect()
}

/// The report as one JSON object: every field under its own name, `image` as `board`,
/// `emulator` or `simulator`, `mode` as `bypass`/`open-loop`/`closed-loop`, `flags` a list,
/// `estimate` normalised (±1 of the output range) and `estimate_q2_30` raw.
pub fn status_json(s: &StatusReport) -> serde_json::Value {
    serde_json::json!({
        "image": s.image().name(),
        "ticks": s.ticks,
        "tick_rate_hz": s.tick_rate_hz,
        "mode": mode_name(s.mode()),
        "flags": flag_names(s),
        "queue_fill": s.queue_fill,
        "credits": s.credits,
        "next_seq": s.next_seq,
        "underruns": s.underruns,
        "overruns": s.overruns,
        "crc_errors": s.crc_errors,
        "frame_errors": s.frame_errors,
        "limit_hits": s.limit_hits,
        "drifts": s.drifts,
        "estimate": s.estimate as f64 / (1u64 << 30) as f64,
        "estimate_q2_30": s.estimate,
        "recorded": s.recorded,
    })
}

/// The analog input's state as one JSON object: `running`, `lost`, `over_range`, `faults`,
/// `reading` (fraction of the input's span, 0–1) and `setpoint` (normalised, ±1 of the
/// output range).
pub fn analog_status_json(s: &twinstack::sources::analog_input::AnalogStatus) -> serde_json::Value {
    serde_json::json!({
        "running": s.running,
        "lost": s.lost,
        "over_range": s.over_range,
        "faults": s.faults,
        "reading": s.reading as f64 / 65536.0,
        "setpoint": s.setpoint as f64 / twinstack::fixed_point::SIGNAL_ONE as f64,
    })
}

/// The coarse axis's status as one JSON object: `state` (`unhomed`, `homing`, `idle`,
/// `moving`, `jogging`, `stopping`, `fault`), `homed`, `position_mm`, `setpoint_mm`,
/// `following_error_um`, `faults` and `switches` (lists of names), `fine_setpoint` (the
/// piezo's, normalised) and `ticks` (coarse periods run).
pub fn coarse_status_json(s: &twinstack::dual_stage::CoarseStatus) -> serde_json::Value {
    use twinstack::dual_stage::CoarseStatus;
    serde_json::json!({
        "state": s.state.name(),
        "homed": s.homed,
        "position_mm": s.position_pm as f64 / 1e9,
        "setpoint_mm": s.setpoint_pm as f64 / 1e9,
        "following_error_um": s.following_error_pm as f64 / 1e6,
        "faults": CoarseStatus::fault_names(s.faults).collect::<Vec<_>>(),
        "switches": CoarseStatus::switch_names(s.switches).collect::<Vec<_>>(),
        "fine_setpoint": s.fine_setpoint as f64 / twinstack::fixed_point::SIGNAL_ONE as f64,
        "ticks": s.ticks,
    })
}

/// Why the coarse axis did not come to rest.
#[derive(Debug, thiserror::Error)]
pub enum CoarseWaitError {
    /// The link.
    #[error(transparent)]
    Link(#[from] crate::client::LinkError),
    /// Still homing, moving, jogging or stopping when the time allowed ran out.
    #[error("the coarse axis is still {state} after {limit:?}")]
    Busy {
        /// Its state's name.
        state: &'static str,
        /// The time allowed.
        limit: std::time::Duration,
    },
}

/// Polls the coarse axis's status until it is no longer homing, moving, jogging or stopping
/// (at most `limit`, in the link's time: simulated on the in-process board), and returns it.
pub fn wait_until_coarse_settled<T: crate::Transport>(
    client: &mut crate::client::Client<T>,
    limit: std::time::Duration,
) -> Result<twinstack::dual_stage::CoarseStatus, CoarseWaitError> {
    use std::time::{Duration, Instant};
    use twinstack::dual_stage::CoarseState;
    let start = Instant::now();
    // The coarse task takes an acknowledged command at its next period (200 µs): the status
    // shows it from then on.
    client.wait(Duration::from_millis(2))?;
    let mut waited = Duration::ZERO;
    loop {
        let s = client.coarse_status()?;
        if !matches!(
            s.state,
            CoarseState::Homing
                | CoarseState::Moving
                | CoarseState::Jogging
                | CoarseState::Stopping
        ) {
            return Ok(s);
        }
        if waited > limit || start.elapsed() > limit {
            return Err(CoarseWaitError::Busy {
                state: s.state.name(),
                limit,
            });
        }
        let step = Duration::from_millis(20);
        client.wait(step)?;
        waited += step;
    }
}

/// A mode's name on the command line and in JSON: `bypass`, `open-loop`, `closed-loop`.
pub fn mode_name(mode: Mode) -> &'static str {
    match mode {
        Mode::Bypass => "bypass",
        Mode::OpenLoop => "open-loop",
        Mode::ClosedLoop => "closed-loop",
    }
}

/// The mode named `name` ([`mode_name`]'s names; `_` for `-` and any case accepted).
pub fn parse_mode(name: &str) -> Option<Mode> {
    match name.to_ascii_lowercase().replace('_', "-").as_str() {
        "bypass" => Some(Mode::Bypass),
        "open-loop" => Some(Mode::OpenLoop),
        "closed-loop" => Some(Mode::ClosedLoop),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use twinstack::config::settings::NotchDesign;

    /// A file without shaping (as `identify` writes) keeps the board's; a file with its own
    /// replaces it.
    #[test]
    fn the_board_s_shaping_is_kept_unless_the_file_has_its_own() {
        let shaping = |f| {
            Some(NotchDesign {
                frequency_hz: f,
                q: 0.5,
                depth: 0.0173,
            })
        };
        let board = Settings {
            shaping: shaping(21_807.0),
            ..Settings::default()
        };
        let file = Settings::default();
        assert_eq!(keep_from_board(&file, Some(&board)).shaping, board.shaping);
        assert_eq!(keep_from_board(&file, None).shaping, None);
        let own = Settings {
            shaping: shaping(16_312.0),
            ..Settings::default()
        };
        assert_eq!(keep_from_board(&own, Some(&board)).shaping, own.shaping);
    }
}
