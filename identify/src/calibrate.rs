//! One-command calibration (`twinstack calibrate`): excite the stage with the board's own
//! waveform generator, record drive and sensor with the board's recorder, identify the best
//! model, load it (and store it), then verify it by tracking a test trajectory before and
//! after compensation — over any [`Transport`], so the same function serves the command line,
//! a real board, the emulator and the virtual board (and a Python binding later).
//!
//! The steps of [`calibrate`]:
//!
//! 1. **Check** the board: it has a sensor calibration ([`CalibrateError::NoSensor`]); a
//!    running stream or waveform is stopped; the mode is set to bypass (the drive then follows
//!    the setpoint linearly, so the excitation *is* the drive).
//! 2. **Excite**: a multi-signal capture of the left stack and the sensor is armed on the
//!    waveform's start, decimated so the run fits the board's capture slots (at most
//!    [`CalibrateOptions::sample_rate_hz`]), then the generator plays a sine about the middle of
//!    the range: [`CalibrateOptions::full_cycles`] cycles of amplitude
//!    [`CalibrateOptions::amplitude`], then [`CalibrateOptions::decay_cycles`] cycles decaying
//!    geometrically (the generator's per-cycle decay, protocol v5) to
//!    [`CalibrateOptions::final_amplitude`] of it: nested minor loops.
//! 3. **Identify**: the window in physical units (left stack V, sensor in the output unit) is a
//!    `t,u,x` record; the last cycle is held out; [`identify_auto_admitting`] ranks every model
//!    of the family (or one model, [`CalibrateOptions::model`]) and keeps the best among those
//!    the board's tick budget runs at its control rate. A sensor that
//!    does not move ([`CalibrateError::SensorFlat`]), that saturates
//!    ([`CalibrateError::SensorSaturated`]), or a model that does not predict the held-out cycle
//!    within [`CalibrateOptions::max_held_out_pct`] ([`CalibrateError::DoesNotFit`]) stops here,
//!    before anything is loaded.
//! 4. **Load**: the parameter file `identify` would write ([`ParamFile::from_model`]), with the
//!    board's own drive, sensor calibration and feedback gains kept; a model whose input range
//!    the drive cannot reach is refused as `load` refuses it
//!    ([`twinstack_link::board_requests::unreachable_input`]) unless [`CalibrateOptions::clamp`].
//! 5. **Verify**: a test trajectory — two triangle cycles, then nested minor loops
//!    ([`crate::trajectory::trajectories`]), not the excitation — over the measured output range
//!    less [`crate::trajectory::TRAJECTORY_MARGIN`] each side, streamed in bypass (the new
//!    ranges' linear map: what a user gets without compensation) and then in open loop
//!    (the inverse model), each recorded (setpoint and sensor) and scored: the sensor against
//!    the setpoint, max and RMS in % of the trajectory's span ([`Tracking`]).
//! 6. **Store** (unless [`CalibrateOptions::store`] is `None`): the settings in force (open
//!    loop) to flash, to boot in the mode asked for.

use crate::identification::auto::{
    identify_admitted, identify_auto_admitting, Ranked, Size, Validation,
};
use crate::identification::run::{admission_at, BoardRate};
use crate::identification::score::{score, ErrorFigures};
use crate::identification::{
    Identification, IdentifyError, IdentifyOptions, ModelKind, DEFAULT_OPERATORS,
};
use crate::param_file::{IdentificationRecord, ParamFile};
use crate::trajectory;
use std::time::Duration;
use twinstack::config::settings::Settings;
use twinstack::protocol::messages::{
    CaptureRequest, CaptureStatus, Mode, StatusReport, StreamControl, Trigger, UnderrunPolicy,
    WaveDecay, WaveShape, Waveform,
};
use twinstack::services::recorder::Channel;
use twinstack_link::capture::{self, CaptureError, ConvertError, Recording};
use twinstack_link::client::{Client, LinkError};
use twinstack_link::measured_data::MeasuredData;
use twinstack_link::setpoint_file::q1_15;
use twinstack_link::streamer::{stream_setpoints, StreamError, StreamOptions};
use twinstack_link::Transport;

/// How a calibration runs. [`CalibrateOptions::default`] is what `twinstack calibrate` runs.
#[derive(Clone, Debug, PartialEq)]
pub struct CalibrateOptions {
    /// Frequency of the excitation, Hz.
    pub excitation_hz: f64,
    /// Amplitude of the full cycles, normalised (fraction of the half range about its middle);
    /// the identified input range is the range swept (see
    /// [`crate::identification::INPUT_MARGIN`]).
    pub amplitude: f64,
    /// Cycles at full amplitude.
    pub full_cycles: u16,
    /// Cycles decaying after them (the last one is held out of the fit and scores it).
    pub decay_cycles: u16,
    /// Amplitude of the last cycle, fraction of [`CalibrateOptions::amplitude`].
    pub final_amplitude: f64,
    /// Highest rate the excitation and the verification runs are recorded at, Hz (lower if
    /// the board's capture slots do not hold the run at this rate).
    pub sample_rate_hz: f64,
    /// The model to fit; `None`: every model of the family, the best kept (`--model auto`).
    pub model: Option<ModelKind>,
    /// Play operators of a P–I model; `None`: 17, or as many as the board runs at its rate
    /// where 17 are too many.
    pub operators: Option<usize>,
    /// Sensor lag, samples of the recorded excitation; `None`: estimated as `identify` does.
    pub lag: Option<usize>,
    /// Largest held-out max error of the identified model, % of span, before the calibration
    /// is refused as a fit that does not fit.
    pub max_held_out_pct: f64,
    /// Load a model whose input range the drive cannot reach in full (as `load --clamp`).
    pub clamp: bool,
    /// Store the settings to flash once verified, to boot in this mode; `None`: do not store.
    pub store: Option<Mode>,
    /// Ticks per streamed setpoint of the verification runs.
    pub stream_divider: u16,
    /// Unit of the sensor's displacement, written into the parameter file.
    pub output_unit: String,
}

impl Default for CalibrateOptions {
    /// 10 Hz, 6 full cycles at 0.97 then 14 decaying to 15 %, recorded at up to 10 kHz, the
    /// model picked by `auto`, refused above 5 % held-out max error, stored to boot in
    /// bypass, verification streamed at 10 000 setpoints/s on a 50 kHz board.
    fn default() -> Self {
        Self {
            excitation_hz: 10.0,
            amplitude: 0.97,
            full_cycles: 6,
            decay_cycles: 14,
            final_amplitude: 0.15,
            sample_rate_hz: 10_000.0,
            model: None,
            operators: None,
            lag: Some(0),
            max_held_out_pct: 5.0,
            clamp: false,
            store: Some(Mode::Bypass),
            stream_divider: 5,
            output_unit: "um".into(),
        }
    }
}

impl CalibrateOptions {
    /// Checks the options (every number finite and in its range), naming the first bad one.
    pub fn check(&self) -> Result<(), CalibrateError> {
        let bad = |field: &'static str, rule: &'static str, value: f64| {
            Err(CalibrateError::Option { field, rule, value })
        };
        if !(self.excitation_hz.is_finite() && self.excitation_hz > 0.0) {
            return bad(
                "excitation_hz",
                "a positive number of Hz",
                self.excitation_hz,
            );
        }
        if !(self.amplitude > 0.0 && self.amplitude <= 1.0) {
            return bad("amplitude", "in (0, 1]", self.amplitude);
        }
        if self.full_cycles == 0 {
            return bad("full_cycles", "at least 1", 0.0);
        }
        if self.decay_cycles < 2 {
            return bad("decay_cycles", "at least 2", self.decay_cycles as f64);
        }
        if !(self.final_amplitude > 0.0 && self.final_amplitude < 1.0) {
            return bad("final_amplitude", "in (0, 1)", self.final_amplitude);
        }
        if !(self.sample_rate_hz.is_finite() && self.sample_rate_hz > 0.0) {
            return bad(
                "sample_rate_hz",
                "a positive number of Hz",
                self.sample_rate_hz,
            );
        }
        if !(self.max_held_out_pct.is_finite() && self.max_held_out_pct > 0.0) {
            return bad("max_held_out_pct", "a positive %", self.max_held_out_pct);
        }
        if self.stream_divider == 0 {
            return bad("stream_divider", "at least 1", 0.0);
        }
        Ok(())
    }

    /// Cycles of the excitation in all.
    pub fn cycles(&self) -> u32 {
        self.full_cycles as u32 + self.decay_cycles as u32
    }

    /// Length of the excitation, seconds.
    pub fn excitation_s(&self) -> f64 {
        self.cycles() as f64 / self.excitation_hz
    }

    /// The waveform request: a sine about the middle, decaying per cycle after the full ones
    /// so that the last cycle's amplitude is [`CalibrateOptions::final_amplitude`] of the first.
    pub fn waveform(&self) -> Waveform {
        // Cycle `full_cycles + k` (k = 0 …) has `keep^(k + 1)`: the last, `keep^decay_cycles`.
        let keep = self.final_amplitude.powf(1.0 / self.decay_cycles as f64);
        Waveform {
            shape: WaveShape::Sine,
            offset: 0,
            amplitude: q1_15(self.amplitude),
            frequency_mhz: (self.excitation_hz * 1000.0).round().max(1.0) as u32,
            decay: Some(WaveDecay {
                hold_cycles: self.full_cycles,
                keep: (keep * 65536.0).round().min(65535.0) as u16,
            }),
        }
    }
}

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
    /// Where it stands after the validation part.
    pub validation: Validation,
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

/// What [`calibrate`] tells its caller as it goes (for a progress display).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Progress<'a> {
    /// A step starts (its name).
    Step(&'a str),
    /// Within a step: `done` of `total` (frames captured, values read, setpoints sent).
    Count {
        /// What is counted.
        what: &'a str,
        /// How many so far.
        done: u64,
    },
}

fn link(step: &'static str) -> impl Fn(LinkError) -> CalibrateError {
    move |source| CalibrateError::Link { step, source }
}

/// Runs the whole calibration on the board behind `client` (see the module doc).
///
/// ```no_run
/// use twinstack_identify::calibrate::{calibrate, CalibrateOptions};
/// use twinstack_link::{socket::SocketTransport, Client};
/// let transport = SocketTransport::tcp("127.0.0.1:4000").unwrap();
/// let mut client = Client::new(transport);
/// let report = calibrate(&mut client, &CalibrateOptions::default(), |_| {}).unwrap();
/// println!("{}: {:.2} % -> {:.2} %", report.model, report.before.max_pct, report.after.max_pct);
/// ```
pub fn calibrate<T: Transport>(
    client: &mut Client<T>,
    options: &CalibrateOptions,
    mut progress: impl FnMut(Progress),
) -> Result<CalibrationReport, CalibrateError> {
    options.check()?;
    progress(Progress::Step("checking the board"));
    let status = client.status().map_err(link("status"))?;
    let board = client.read_params().map_err(link("reading the settings"))?;
    if board.sensor.is_none() {
        return Err(CalibrateError::NoSensor);
    }
    if status.has(StatusReport::STREAMING) || status.has(StatusReport::WAVEFORM) {
        client
            .stream(StreamControl::Stop)
            .map_err(link("stopping the stream"))?;
    }
    client
        .set_mode(Mode::Bypass)
        .map_err(link("switching to bypass"))?;

    // Steps 2 and 3, and the checks before a load: a failure there leaves the board's settings
    // as they were, and its mode is restored.
    let previous = status.mode();
    let Measured {
        excitation,
        predicted,
        id,
        label,
        reason,
        ranking,
        file,
        held_out,
        decimation,
        tick_rate_hz,
        clamped,
    } = match measure(client, options, &board, &mut progress) {
        Ok(m) => m,
        Err(e) => {
            // Best effort: the error at hand says more than a failure to restore the mode.
            let _ = client.set_mode(previous);
            return Err(e);
        }
    };
    let rate = tick_rate_hz.max(1) as f64;
    // 4. Load, first in bypass for the "before".
    progress(Progress::Step("loading"));
    let settings = Settings {
        mode: Mode::Bypass,
        ..file.settings.clone()
    };
    client
        .load_params(&settings)
        .map_err(link("loading the identified settings"))?;

    // 5. Verify: the same trajectory before (bypass) and after (open loop).
    let (lo, hi) = excitation
        .x
        .as_deref()
        .unwrap_or_default()
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    let margin = trajectory::TRAJECTORY_MARGIN * (hi - lo);
    let trajectory_range = (lo + margin, hi - margin);
    let setpoint_rate = rate / options.stream_divider as f64;
    let trajectory = trajectory::test_trajectory(trajectory_range, setpoint_rate);
    let mut x_rest = settings.ranges.norm_to_output(0.0);
    let mut run = |client: &mut Client<T>, mode: Mode, step: &'static str| {
        progress(Progress::Step(step));
        client.set_mode(mode).map_err(link(step))?;
        let r = track(client, &trajectory, x_rest, options, &settings, step);
        x_rest = trajectory.x.last().copied().unwrap_or(x_rest);
        r
    };
    let (before, run_before) = run(client, Mode::Bypass, "tracking in bypass (before)")?;
    let (after, run_after) = run(client, Mode::OpenLoop, "tracking compensated (after)")?;

    // 6. Store.
    if let Some(boot) = options.store {
        progress(Progress::Step("storing to flash"));
        client
            .store_params(boot)
            .map_err(link("storing the settings"))?;
    }
    Ok(CalibrationReport {
        model: label,
        reason,
        ranking,
        file,
        excitation,
        predicted,
        held_out_from: id.held_out_from,
        fit_from: id.motion.first_fitted,
        held_out,
        decimation,
        tick_rate_hz,
        trajectory_range,
        before,
        after,
        runs: [run_before, run_after],
        stored: options.store,
        clamped,
    })
}

/// What steps 2 and 3 measured and identified, checked for loading.
struct Measured {
    excitation: MeasuredData,
    predicted: Vec<f64>,
    id: Identification,
    label: String,
    reason: String,
    ranking: Vec<Candidate>,
    file: ParamFile,
    held_out: ErrorFigures,
    decimation: u16,
    tick_rate_hz: u32,
    clamped: bool,
}

/// Steps 2 and 3: excite and record, identify, and the checks before a load (the fit, the
/// drive's reach). Loads nothing.
fn measure<T: Transport>(
    client: &mut Client<T>,
    options: &CalibrateOptions,
    board: &Settings,
    progress: &mut impl FnMut(Progress),
) -> Result<Measured, CalibrateError> {
    // 2. Excite and record.
    progress(Progress::Step("exciting the stage"));
    let facts = client
        .capture_status()
        .map_err(link("the recorder's capacity"))?;
    let rate = facts.tick_rate_hz.max(1) as f64;
    let mask = Channel::Left.bit() | Channel::Sensor.bit();
    let ticks = (options.excitation_s() * rate).ceil() as u64;
    let (decimation, frames) = decimation_for(ticks, rate, options.sample_rate_hz, &facts, 2);
    client
        .arm_capture(CaptureRequest {
            signals: mask,
            samples: frames,
            pre_trigger: 0,
            trigger: Trigger::WaveformStart,
            decimation,
        })
        .map_err(link("arming the recorder"))?;
    client
        .waveform(options.waveform())
        .map_err(link("starting the excitation"))?;
    let budget = Duration::from_secs_f64(2.0 * options.excitation_s() + 10.0);
    let read = capture::wait_and_read(client, budget, |what, n| {
        progress(Progress::Count {
            what,
            done: n as u64,
        })
    });
    // Stop the generator whatever happened (the output holds near the middle).
    let stopped = client.stream(StreamControl::Stop);
    let (cap, window) = read.map_err(|source| CalibrateError::Capture {
        step: "recording the excitation",
        source,
    })?;
    stopped.map_err(link("stopping the excitation"))?;
    let recording =
        capture::convert(&cap, board, &window).map_err(|source| CalibrateError::Convert {
            step: "the excitation",
            source,
        })?;
    let excitation = excitation_record(&recording, board, &options.output_unit)?;

    // 3. Identify.
    progress(Progress::Step("identifying"));
    let fit_until = options.excitation_s() - 1.0 / options.excitation_hz;
    let mut id_options = IdentifyOptions::new(options.model.unwrap_or(ModelKind::Pi), fit_until);
    id_options.operators = options.operators.unwrap_or(DEFAULT_OPERATORS);
    let rate_limit = BoardRate::sizing(rate, options.operators.is_some());
    id_options.lag = options.lag;
    // Only a model the board runs at its control rate with its drive, sensor and feedback:
    // the tick budget the board applies at load ([`twinstack::config::tick_budget`]), applied here
    // first, so that `auto` picks among what the board takes.
    let runs_on_board = |id: &Identification| {
        let mut settings = ParamFile::from_model(&id.model, &options.output_unit, None).settings;
        settings.drive = board.drive;
        settings.sensor = board.sensor;
        settings.feedback = board.feedback;
        admission_at(&settings, &rate_limit)
    };
    let (id, operators, label, reason, ranking) = match options.model {
        Some(_) => {
            let asked = Size::of(&id_options);
            let (fitted, id) = identify_admitted(&excitation, id_options.clone(), &runs_on_board)?;
            let label = fitted.model_label();
            let reason = match Size::of(&fitted).sized_down_note(&asked) {
                Some(note) => format!("{label} (asked for; {note})"),
                None => format!("{label} (asked for)"),
            };
            (id, fitted.operators, label, reason, Vec::new())
        }
        None => {
            let auto =
                identify_auto_admitting(&excitation, &id_options.candidates(), runs_on_board)?;
            let picked = auto.options.clone();
            let ranking = auto.ranking.iter().map(candidate).collect();
            (
                auto.identification,
                picked.operators,
                picked.model_label(),
                auto.reason,
                ranking,
            )
        }
    };
    let (record, predicted) = identification_record(&excitation, &id, fit_until, operators)?;
    if record.held_out.max_pct > options.max_held_out_pct {
        return Err(CalibrateError::DoesNotFit {
            model: label,
            max_pct: record.held_out.max_pct,
            limit: options.max_held_out_pct,
        });
    }
    let held_out = record.held_out;
    let mut file = ParamFile::from_model(&id.model, &options.output_unit, Some(record));

    // The settings to load: the board's drive, sensor and gains kept.
    file.settings.drive = board.drive;
    file.settings.sensor = board.sensor;
    file.settings.feedback = board.feedback;
    let clamped = match twinstack_link::board_requests::unreachable_input(&file.settings) {
        Some(((model_lo, model_hi), (drive_lo, drive_hi))) if !options.clamp => {
            return Err(CalibrateError::Unreachable {
                model_lo,
                model_hi,
                drive_lo,
                drive_hi,
            })
        }
        Some(_) => true,
        None => false,
    };
    Ok(Measured {
        excitation,
        predicted,
        id,
        label,
        reason,
        ranking,
        file,
        held_out,
        decimation: cap.decimation,
        tick_rate_hz: facts.tick_rate_hz,
        clamped,
    })
}

fn candidate(r: &Ranked) -> Candidate {
    Candidate {
        label: r.label.clone(),
        validation: r.validation.clone(),
    }
}

/// Ticks per frame and frames for a capture of `signals` signals over `ticks` ticks: at most
/// `sample_rate_hz`, and few enough frames for the board's slots.
fn decimation_for(
    ticks: u64,
    rate: f64,
    sample_rate_hz: f64,
    facts: &CaptureStatus,
    signals: u32,
) -> (u16, u32) {
    let max_frames = (facts.capacity / signals).max(1) as u64;
    let by_rate = (rate / sample_rate_hz).ceil().max(1.0) as u64;
    let by_slots = ticks.div_ceil(max_frames).max(1);
    let decimation = by_rate.max(by_slots).min(u16::MAX as u64);
    let frames = ticks.div_ceil(decimation).clamp(1, max_frames);
    (decimation as u16, frames as u32)
}

/// The excitation as a `t,u,x` record (left stack volts, sensor in the output unit), after
/// checking that the sensor moved and did not saturate.
fn excitation_record(
    recording: &Recording,
    board: &Settings,
    unit: &str,
) -> Result<MeasuredData, CalibrateError> {
    let column = |c: Channel| recording.column(c).cloned();
    let (Some(left), Some(sensor)) = (column(Channel::Left), column(Channel::Sensor)) else {
        return Err(CalibrateError::MissingSignals);
    };
    let range = |v: &[i16]| {
        v.iter().fold((i32::MAX, i32::MIN), |(l, h), &q| {
            (l.min(q as i32), h.max(q as i32))
        })
    };
    let (q_lo, q_hi) = range(&sensor.raw);
    // (Saturating: an empty capture reads as the widest negative span, i.e. flat.)
    let lsb = q_hi.saturating_sub(q_lo);
    // Fewer than 64 steps of the reading (0.2 % of the output range): no stage to identify.
    if lsb < 64 {
        let (d_lo, d_hi) = left
            .values
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
                (l.min(v), h.max(v))
            });
        let span = board.ranges.norm_to_output(q_hi as f64 / 32768.0)
            - board.ranges.norm_to_output(q_lo as f64 / 32768.0);
        return Err(CalibrateError::SensorFlat {
            span: span.abs(),
            unit: unit.into(),
            lsb,
            drive_lo: d_lo,
            drive_hi: d_hi,
        });
    }
    let at_ends = sensor
        .raw
        .iter()
        .filter(|&&q| q == i16::MAX || q == i16::MIN)
        .count();
    // A few samples at an end can be noise; one in a hundred is a clipped loop.
    if at_ends * 100 > sensor.raw.len() {
        return Err(CalibrateError::SensorSaturated {
            lo: board.ranges.output_min,
            hi: board.ranges.output_max,
            unit: unit.into(),
            count: at_ends,
            total: sensor.raw.len(),
        });
    }
    let t0 = recording.t.first().copied().unwrap_or(0.0);
    Ok(MeasuredData {
        path: "calibrate-excitation".into(),
        t: recording.t.iter().map(|t| t - t0).collect(),
        u: Some(left.values),
        x: Some(sensor.values),
    })
}

/// The figures `identify` writes into the parameter file, and the model's prediction.
fn identification_record(
    data: &MeasuredData,
    id: &Identification,
    fit_until: f64,
    operators: usize,
) -> Result<(IdentificationRecord, Vec<f64>), CalibrateError> {
    let (t, u, x) = (
        &data.t,
        data.u.as_deref().unwrap_or_default(),
        data.x.as_deref().unwrap_or_default(),
    );
    let n = t.len();
    let model = &id.model;
    let lib = |e: twinstack::ParamError| CalibrateError::Model(e.to_string());
    let predicted = model.predict(t, u).map_err(lib)?;
    let reference = model.predict_reference(t, u).map_err(lib)?;
    let drive = model.compensate(t, x).map_err(lib)?;
    let drive_reference = model.compensate_reference(t, x).map_err(lib)?;
    let (fit_from, held) = (id.motion.first_fitted, id.held_out_from);
    let flat = || CalibrateError::Model("the recorded output is flat: cannot score".into());
    let aimed = n - model.lag_samples(t).min(n.saturating_sub(held + 1));
    let record = IdentificationRecord {
        data: data.path.display().to_string(),
        fit_until_s: fit_until,
        fit_from_s: t.get(fit_from).copied().unwrap_or(0.0),
        operators,
        thresholds: "uniform".into(),
        lag_samples: id.lag_samples,
        lag_estimated: id.lag_estimated,
        outliers: id.outliers,
        fit: score(x, &predicted, fit_from..held).ok_or_else(flat)?,
        held_out: score(x, &predicted, held..n).ok_or_else(flat)?,
        inverse_held_out: score(u, &drive, held..aimed).ok_or_else(flat)?,
        fixed_vs_reference_max_pct: score(&reference, &predicted, fit_from..n)
            .ok_or_else(flat)?
            .max_pct,
        inverse_fixed_vs_reference_max_pct: score(&drive_reference, &drive, fit_from..n)
            .ok_or_else(flat)?
            .max_pct,
        notes: id.notes.clone(),
    };
    Ok((record, predicted))
}

/// Streams `trajectory` (after [`trajectory::with_conditioning`] from `x_rest`) in the mode in
/// force, records the setpoint and the sensor from the stream's start and scores the sensor
/// against the setpoint over the trajectory.
fn track<T: Transport>(
    client: &mut Client<T>,
    trajectory: &trajectory::Trajectory,
    x_rest: f64,
    options: &CalibrateOptions,
    settings: &Settings,
    step: &'static str,
) -> Result<(Tracking, Recording), CalibrateError> {
    let facts = client.capture_status().map_err(link(step))?;
    let rate = facts.tick_rate_hz.max(1) as f64;
    let divider = options.stream_divider;
    let setpoint_rate = rate / divider as f64;
    let (x, first) = trajectory::with_conditioning(trajectory, x_rest, setpoint_rate);
    let samples: Vec<i16> = x
        .iter()
        .map(|&v| q1_15(settings.ranges.output_to_norm(v)))
        .collect();
    let ticks = samples.len() as u64 * divider as u64;
    let (decimation, frames) = decimation_for(ticks, rate, options.sample_rate_hz, &facts, 2);
    client
        .arm_capture(CaptureRequest {
            signals: Channel::Setpoint.bit() | Channel::Sensor.bit(),
            samples: frames,
            pre_trigger: 0,
            trigger: Trigger::StreamStart,
            decimation,
        })
        .map_err(link(step))?;
    let stream = StreamOptions {
        divider,
        underrun: Some(UnderrunPolicy::Hold),
        tick_rate_hz: rate,
        drain: true,
        ..StreamOptions::default()
    };
    let r = stream_setpoints(client, &samples, &stream, |_| {})
        .map_err(|source| CalibrateError::Stream { step, source })?;
    let seconds = ticks as f64 / rate;
    let budget = Duration::from_secs_f64(2.0 * seconds + 10.0);
    let (cap, window) = capture::wait_and_read(client, budget, |_, _| {})
        .map_err(|source| CalibrateError::Capture { step, source })?;
    let recording = capture::convert(&cap, settings, &window)
        .map_err(|source| CalibrateError::Convert { step, source })?;
    let empty = Vec::new();
    let column = |c: Channel| recording.column(c).map_or(&empty, |c| &c.values);
    let (setpoint, sensor) = (column(Channel::Setpoint), column(Channel::Sensor));
    // Scored from the trajectory's first setpoint to its last (the lead-in is not).
    let dt = cap.decimation.max(1) as f64 / rate;
    let start = ((first as f64 / setpoint_rate) / dt).ceil() as usize;
    let end = ((x.len() as f64 / setpoint_rate) / dt).floor() as usize;
    let end = end.min(setpoint.len()).min(sensor.len());
    let figures = score(setpoint, sensor, start.min(end)..end).unwrap_or(ErrorFigures {
        max_pct: f64::NAN,
        rms_pct: f64::NAN,
        samples: 0,
    });
    Ok((
        Tracking {
            max_pct: figures.max_pct,
            rms_pct: figures.rms_pct,
            samples: figures.samples,
            underran: r.underran(),
        },
        recording,
    ))
}

#[cfg(test)]
mod tests;
