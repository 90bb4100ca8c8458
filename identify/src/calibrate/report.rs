//! What a calibration found ([`CalibrationReport`]: the model picked and the candidates, the
//! tracking before and after) and why one failed ([`CalibrateError`]).

use super::*;

/// A verification run's figures: the sensor against the setpoint over the trajectory.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Tracking {
    /// Largest |sensor − setpoint|, % of the trajectory's span.
    pub max_pct: f64,
    /// RMS of sensor − setpoint, % of the trajectory's span.
    pub rms_pct: f64,
    /// Frames scored.
    pub samples: usize,
    /// The board's queue ran dry during the stream (the setpoint then held: the figures
    /// include it).
    pub underran: bool,
}

/// A candidate of the ranking, for the report.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Candidate {
    /// The model, in words.
    pub label: String,
    /// Where it stands after the validation part (its forward figures).
    pub validation: Validation,
    /// Its inverse on the validation part (`None` if it was not fitted).
    pub inverse: Option<ErrorFigures>,
    /// Its compensated tracking on the validation part (`None` if it was not fitted).
    pub tracking: Option<ErrorFigures>,
    /// The larger of its inverse and tracking max errors, % (what it was ranked by).
    pub compensated_max_pct: Option<f64>,
    /// Why it was ranked after the candidates whose inverse holds, if it was.
    pub set_aside: Option<String>,
    /// Its figures and standing in one line, as `identify` prints them.
    pub summary: String,
}

/// What [`calibrate`] did and measured.
#[derive(Clone, Debug)]
pub struct CalibrationReport {
    /// The model identified, in words.
    pub model: String,
    /// Why it was picked (auto), or the one asked for.
    pub reason: String,
    /// Every candidate, best first (empty for one model).
    pub ranking: Vec<Candidate>,
    /// The parameter file (the settings the board was loaded with, open loop).
    pub file: ParamFile,
    /// The excitation as recorded, in physical units (`u` left stack V, `x` sensor).
    pub excitation: MeasuredData,
    /// The model's fixed-point prediction of the excitation.
    pub predicted: Vec<f64>,
    /// First held-out sample of the excitation.
    pub held_out_from: usize,
    /// First fitted sample of the excitation.
    pub fit_from: usize,
    /// The held-out figures of the model (the last cycle).
    pub held_out: ErrorFigures,
    /// Ticks per recorded frame of the excitation.
    pub decimation: u16,
    /// The board's control rate, Hz.
    pub tick_rate_hz: u32,
    /// The trajectory's range, output unit.
    pub trajectory_range: (f64, f64),
    /// Tracking in bypass with the new ranges (no compensation).
    pub before: Tracking,
    /// Tracking in open loop with the identified compensator.
    pub after: Tracking,
    /// The verification runs as recorded (setpoint and sensor): before, after.
    pub runs: [Recording; 2],
    /// The mode the stored settings boot in, if stored.
    pub stored: Option<Mode>,
    /// The model's input range reaches beyond the drive and was loaded with `clamp`.
    pub clamped: bool,
    /// The excitation's stream found the board's queue empty at least once (a link slower
    /// than the stream): the record holds the drive as the board applied it, held where the
    /// queue ran dry, so the identification stands, on a record other than the one planned.
    pub excitation_underran: bool,
    /// The stage's resonance, measured after the excitation where
    /// [`CalibrateOptions::resonance`] asks (and then in [`CalibrationReport::file`]).
    pub resonance: ResonanceOutcome,
}

/// What became of the resonance's measurement ([`CalibrateOptions::resonance`]).
#[derive(Clone, Debug, PartialEq)]
pub enum ResonanceOutcome {
    /// Not asked for.
    NotAsked,
    /// Measured and fitted as `tune` fits it; the parameter file holds it.
    Measured(Fit),
    /// Swept, but not fitted (why): the parameter file holds none, so a preview needs it
    /// given (`--resonance-hz`, `--resonance-damping`). The calibration stands.
    NotFitted(String),
}

/// Why a calibration stopped. Nothing here panics; each says what to check.
#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
    /// An option is out of its range.
    #[error("calibrate option {field} = {value}: must be {rule}")]
    Option {
        /// The option.
        field: &'static str,
        /// What it must be.
        rule: &'static str,
        /// What it was.
        value: f64,
    },
    /// The fastest motion named is not above the excitation's frequency, or more than
    /// [`crate::excitation::MAX_SWEEP_RATIO`] times it (or not a number).
    #[error("calibrate option fastest_hz = {fastest_hz}: must be above the excitation's frequency, {excitation_hz} Hz (excitation_hz), and at most {} times it, {} Hz", crate::excitation::MAX_SWEEP_RATIO, crate::excitation::MAX_SWEEP_RATIO * excitation_hz)]
    FastestOutOfRange {
        /// The fastest motion named, Hz.
        fastest_hz: f64,
        /// The excitation's frequency, Hz.
        excitation_hz: f64,
    },
    /// The board would stream or record the excitation too coarsely for its fastest motion
    /// ([`CalibrateOptions::check_resolved`]).
    #[error("calibrate option fastest_hz = {fastest_hz}: the board streams the excitation at {stream_hz:.0} setpoints/s and records it at {recorded_hz:.0} frames/s, fewer than 20 a cycle of {fastest_hz} Hz; {remedy}")]
    FastestUnresolved {
        /// The excitation's fastest motion, Hz.
        fastest_hz: f64,
        /// Setpoints streamed a second.
        stream_hz: f64,
        /// Frames recorded a second.
        recorded_hz: f64,
        /// What would resolve it: a slower motion, or where the recorder is the limit, a
        /// shorter excitation too.
        remedy: &'static str,
    },
    /// The link failed, or the board refused a request (the message names the field and its
    /// limit).
    #[error("{step}: {source}")]
    Link {
        /// What calibrate was doing.
        step: &'static str,
        /// The cause.
        source: LinkError,
    },
    /// A capture did not complete or could not be read.
    #[error("{step}: {source}")]
    Capture {
        /// What calibrate was doing.
        step: &'static str,
        /// The cause.
        source: CaptureError,
    },
    /// A capture's window could not be put in physical units.
    #[error("{step}: {source}")]
    Convert {
        /// What calibrate was doing.
        step: &'static str,
        /// The cause.
        source: ConvertError,
    },
    /// A verification stream failed.
    #[error("{step}: {source}")]
    Stream {
        /// What calibrate was doing.
        step: &'static str,
        /// The cause.
        source: StreamError,
    },
    /// The capture read back lacks the left stack or the sensor (the board answered another
    /// capture: another client re-armed the recorder?).
    #[error("the excitation's capture holds no left-stack or sensor values (another client re-armed the recorder?)")]
    MissingSignals,
    /// The board's settings have no sensor calibration.
    #[error("the board has no sensor (its settings carry no sensor calibration): calibrate measures the stage through its sensor; load settings with a `sensor` section first")]
    NoSensor,
    /// The sensor did not move while the drive swept its range.
    #[error("the sensor did not follow the drive: it moved {span:.4} {unit} ({lsb} steps of its reading) while the left stack swept {drive_lo:.1}…{drive_hi:.1} V; is the sensor connected and the stage powered? Nothing was loaded")]
    SensorFlat {
        /// The sensor's span over the excitation.
        span: f64,
        /// Its unit.
        unit: String,
        /// Its span in recorder steps (Q1.15).
        lsb: i32,
        /// The drive's range, V.
        drive_lo: f64,
        /// The drive's range, V.
        drive_hi: f64,
    },
    /// The sensor's reading sat at the end of the output range.
    #[error("the sensor reading saturates at the end of the board's output range ({lo}…{hi} {unit}) in {count} of {total} samples: widen settings.ranges.output to the stage's stroke, then calibrate again; nothing was loaded")]
    SensorSaturated {
        /// The output range.
        lo: f64,
        /// The output range.
        hi: f64,
        /// Its unit.
        unit: String,
        /// Samples at an end.
        count: usize,
        /// Samples recorded.
        total: usize,
    },
    /// The resonance's sweep could not be run (the link, a capture or its conversion).
    #[error("measuring the resonance: {0}; nothing was loaded (calibrate without measuring it: --no-resonance)")]
    Resonance(MeasureError),
    /// Identification failed.
    #[error("identification: {0}; nothing was loaded")]
    Identify(#[from] IdentifyError),
    /// The best model does not predict the held-out cycle well enough.
    #[error("{model} does not fit the stage: it predicts the held-out last cycle within {max_pct:.2} % (max) of its span, more than the {limit} % allowed; nothing was loaded (is the sensor measuring this stage's displacement?)")]
    DoesNotFit {
        /// The model.
        model: String,
        /// Its held-out max error, %.
        max_pct: f64,
        /// The limit, %.
        limit: f64,
    },
    /// The library refused the identified model (its fixed-point form).
    #[error("the identified model: {0}; nothing was loaded")]
    Model(String),
    /// The model's input range is beyond the drive's reach.
    #[error("the model's input range {model_lo:.1}…{model_hi:.1} V reaches beyond what the drive can apply ({drive_lo:.1}…{drive_hi:.1} V on the left stack), so the drive limit would clip it; pass clamp (--clamp) to load it anyway; nothing was loaded")]
    Unreachable {
        /// The model's input range.
        model_lo: f64,
        /// The model's input range.
        model_hi: f64,
        /// The drive's window.
        drive_lo: f64,
        /// The drive's window.
        drive_hi: f64,
    },
}
