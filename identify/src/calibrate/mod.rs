//! One-command calibration (`twinstack calibrate`): excite the stage with the
//! [`crate::excitation`] streamed to the board, record drive and sensor with the board's
//! recorder, identify the best model, load it (and store it), then verify it by tracking a test trajectory before and
//! after compensation — over any [`Transport`], so the same function serves the command line,
//! a real board, the emulator and the virtual board (and a Python binding later).
//!
//! The steps of [`calibrate`]:
//!
//! 1. **Check** the board: it has a sensor calibration ([`CalibrateError::NoSensor`]); a
//!    running stream or waveform is stopped; the mode is set to bypass (the drive then follows
//!    the setpoint linearly, so the excitation *is* the drive).
//! 2. **Excite**: a multi-signal capture of the left stack and the sensor is armed on the
//!    stream's start, decimated so the run fits the board's capture slots (at most
//!    [`CalibrateOptions::sample_rate_hz`]), then the excitation is streamed in bypass
//!    ([`CalibrateOptions::excitation_setpoints`], at [`CalibrateOptions::stream_divider`]
//!    ticks a setpoint): a quarter cycle from the middle of the range down to the bottom of the
//!    swept range, then [`crate::excitation::Excitation`] over the middle ±
//!    [`CalibrateOptions::amplitude`] — full cycles, cycles decaying to
//!    [`CalibrateOptions::final_amplitude`], and where asked nested off-centre minor loops
//!    ([`CalibrateOptions::loop_cycles`]) and a multisine
//!    ([`CalibrateOptions::multisine_cycles`]). The
//!    record is the drive the board applied, so a stream that found the queue empty on a
//!    slow link still records what the stage did ([`CalibrationReport::excitation_underran`]
//!    says so).
//! 3. **Identify**: the window in physical units (left stack V, sensor in the output unit) is a
//!    `t,u,x` record; the last cycle is held out; [`identify_auto_admitting`] ranks every model
//!    of the family (or one model, [`CalibrateOptions::model`]) and keeps the best among those
//!    the board's tick budget runs at its control rate. A sensor that
//!    does not move ([`CalibrateError::SensorFlat`]), that saturates
//!    ([`CalibrateError::SensorSaturated`]), or a model that does not predict the held-out cycle
//!    within [`CalibrateOptions::max_held_out_pct`] ([`CalibrateError::DoesNotFit`]) stops here,
//!    before anything is loaded.
//!    Then, unless [`CalibrateOptions::resonance`] is off, **the resonance**: the sweep and
//!    fit `twinstack tune` runs ([`crate::tune::measure::sweep`], [`crate::tune::fit::fit`]),
//!    written into the parameter file ([`ParamFile::resonance`]) for a planned trajectory's
//!    preview; a response no resonance fits is left out and said
//!    ([`ResonanceOutcome::NotFitted`]).
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
use crate::preview::Resonance;
use crate::trajectory;
use crate::tune::fit::{fit, Fit};
use crate::tune::measure::{sweep, MeasureError, SweepOptions};
use std::time::Duration;
use twinstack::config::settings::Settings;
use twinstack::protocol::messages::{
    CaptureRequest, CaptureStatus, Mode, StatusReport, StreamControl, Trigger, UnderrunPolicy,
};
use twinstack::services::recorder::Channel;
use twinstack_link::capture::{self, CaptureError, ConvertError, Recording};
use twinstack_link::client::{Client, LinkError};
use twinstack_link::measured_data::MeasuredData;
use twinstack_link::setpoint_file::q1_15;
use twinstack_link::streamer::{stream_setpoints, StreamError, StreamOptions};
use twinstack_link::Transport;

mod measure;
mod options;
mod report;
mod track;

use measure::{decimation_for, identify_excited, measure, Excited, Measured};
pub use options::CalibrateOptions;
pub use report::{CalibrateError, CalibrationReport, Candidate, ResonanceOutcome, Tracking};
use track::track;

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

/// Why the board refused the identified settings.
enum LoadRefusal {
    /// Its tick budget: `needs` cycles a tick with what it runs beside them.
    Budget { needs: u32 },
    /// Anything else.
    Other(LinkError),
}

impl LoadRefusal {
    fn into_error(self) -> CalibrateError {
        let source = match self {
            LoadRefusal::Other(e) => e,
            LoadRefusal::Budget { needs } => LinkError::Unexpected {
                request: "LoadParams",
                got: format!(
                    "refused for the tick budget: the identified settings need {needs} cycles a tick with what the board runs beside them"
                ),
            },
        };
        CalibrateError::Link {
            step: "loading the identified settings",
            source,
        }
    }
}

/// Loads `measured`'s settings in bypass (the "before"): the settings loaded, or why not.
fn load_bypassed<T: Transport>(
    client: &mut Client<T>,
    measured: &Measured,
) -> Result<Settings, LoadRefusal> {
    let settings = Settings {
        mode: Mode::Bypass,
        ..measured.file.settings.clone()
    };
    match client.load_params(&settings) {
        Ok(()) => Ok(settings),
        Err(e) => Err(match budget_needs(&e) {
            Some(needs) => LoadRefusal::Budget { needs },
            None => LoadRefusal::Other(e),
        }),
    }
}

/// The cycles a tick the board named when it refused a request for its tick budget.
fn budget_needs(e: &LinkError) -> Option<u32> {
    match e {
        LinkError::Nack {
            reason:
                twinstack::protocol::messages::NackReason::Refused(twinstack::refusal::Refusal {
                    field: twinstack::refusal::Field::Workload,
                    rule: twinstack::refusal::Rule::TickOverrun { needs, .. },
                }),
            ..
        } => Some(*needs),
        _ => None,
    }
}

/// What `settings` cost a tick at `rate` by the library's tick budget with the services'
/// `load` beside them: none, as the board charges a load; a capture's, as it charges the
/// capture's arming (`None`: they do not build for the driver board at that rate).
fn cycles_beside(
    settings: &Settings,
    rate: f64,
    load: twinstack::config::tick_budget::ServicesLoad,
) -> Option<u32> {
    let config = settings
        .build(&twinstack::board::Hardware::driver_board(rate))
        .ok()?;
    Some(twinstack::config::tick_budget::pipeline_cycles(
        &config,
        twinstack::config::tick_budget::Beside {
            services: load,
            ..Default::default()
        },
    ))
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

    // Steps 2 and 3, the checks before a load and the resonance: a failure there leaves the
    // board's settings as they were, and its mode is restored (best effort: the error at hand
    // says more than a failure to restore the mode).
    let previous = status.mode();
    let restoring = |client: &mut Client<T>, e: CalibrateError| {
        let _ = client.set_mode(previous);
        e
    };
    let (excited, measured) =
        measure(client, options, &board, &mut progress).map_err(|e| restoring(client, e))?;
    let resonance = if options.resonance {
        progress(Progress::Step("measuring the resonance"));
        measure_resonance(client, &board).map_err(|e| restoring(client, e))?
    } else {
        ResonanceOutcome::NotAsked
    };
    let with_resonance = |mut m: Measured| {
        if let ResonanceOutcome::Measured(f) = &resonance {
            m.file.resonance = Some(Resonance {
                frequency_hz: f.plant.resonance_hz,
                damping: f.plant.zeta,
            });
        }
        m
    };
    let rate = excited.tick_rate_hz.max(1) as f64;
    // 4. Load, first in bypass for the "before".
    progress(Progress::Step("loading"));
    let measured = with_resonance(measured);
    // Whether the model was identified again beside the board's own load.
    let mut resized = true;
    let (mut measured, mut settings) = match load_bypassed(client, &measured) {
        Ok(settings) => {
            resized = false;
            (measured, settings)
        }
        Err(refusal) => {
            // Refused for the tick budget with more cycles than the model costs alone: the
            // board runs something of its own beside every model (a dual-stage image's coarse
            // task). Identified again from the same excitation with that charged, and loaded.
            let beside = match refusal {
                LoadRefusal::Budget { needs } => {
                    cycles_beside(&measured.file.settings, rate, Default::default())
                        .and_then(|alone| needs.checked_sub(alone))
                        .filter(|&beside| beside > 0)
                }
                _ => None,
            };
            let Some(beside) = beside else {
                return Err(restoring(client, refusal.into_error()));
            };
            progress(Progress::Step(
                "identifying again, beside the board's own load",
            ));
            let again = identify_excited(&excited, options, &board, beside, &mut progress)
                .map(with_resonance)
                .map_err(|e| restoring(client, e))?;
            let settings = load_bypassed(client, &again)
                .map_err(|refusal| restoring(client, refusal.into_error()))?;
            (again, settings)
        }
    };

    // 5. Verify: the same trajectory before (bypass) and after (open loop).
    let (lo, hi) = excited
        .excitation
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
    let x_rest = settings.ranges.norm_to_output(0.0);
    let before_step = "tracking in bypass (before)";
    let before = loop {
        progress(Progress::Step(before_step));
        client.set_mode(Mode::Bypass).map_err(link(before_step))?;
        match track(client, &trajectory, x_rest, options, &settings, before_step) {
            // The capture the tracking takes, refused for the tick budget: a model that fits
            // the board alone and beside its own load (a dual-stage image's coarse task) may
            // not fit beside both. The board's load is what it needs beyond the library's
            // prediction of the model with that capture: identified again with it charged
            // (once), and loaded.
            Err(CalibrateError::Link { source, .. })
                if !resized && budget_needs(&source).is_some() =>
            {
                let needs = budget_needs(&source).unwrap_or(0);
                let facts = client.capture_status().map_err(link(before_step))?;
                let (x, _) = trajectory::with_conditioning(&trajectory, x_rest, setpoint_rate);
                let (_, decimation, _) = track::tracking_capture(&facts, x.len(), options);
                let capture = twinstack::config::tick_budget::ServicesLoad {
                    capture_decimation: Some(decimation),
                    ..Default::default()
                };
                let Some(beside) = cycles_beside(&measured.file.settings, rate, capture)
                    .and_then(|predicted| needs.checked_sub(predicted))
                    .filter(|&beside| beside > 0)
                else {
                    return Err(restoring(
                        client,
                        LoadRefusal::Budget { needs }.into_error(),
                    ));
                };
                progress(Progress::Step(
                    "identifying again, beside the board's own load",
                ));
                measured = identify_excited(&excited, options, &board, beside, &mut progress)
                    .map(with_resonance)
                    .map_err(|e| restoring(client, e))?;
                settings = load_bypassed(client, &measured)
                    .map_err(|refusal| restoring(client, refusal.into_error()))?;
                resized = true;
            }
            other => break other?,
        }
    };
    let Measured {
        predicted,
        id,
        label,
        reason,
        ranking,
        file,
        held_out,
        clamped,
    } = measured;
    let Excited {
        excitation,
        decimation,
        tick_rate_hz,
        underran,
    } = excited;

    let (before, run_before) = before;
    let after_step = "tracking compensated (after)";
    progress(Progress::Step(after_step));
    client.set_mode(Mode::OpenLoop).map_err(link(after_step))?;
    let x_rest = trajectory.x.last().copied().unwrap_or(x_rest);
    let (after, run_after) = track(client, &trajectory, x_rest, options, &settings, after_step)?;

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
        excitation_underran: underran,
        resonance,
    })
}

/// The stage's resonance as `tune` measures and fits it ([`sweep`] with its default options
/// on the board in bypass, then [`fit`]). A sweep the link or a capture failed stops the
/// calibration; one that found the stage flat at a frequency, or a response no resonance
/// fits, leaves the resonance out and says why.
fn measure_resonance<T: Transport>(
    client: &mut Client<T>,
    board: &Settings,
) -> Result<ResonanceOutcome, CalibrateError> {
    let (points, rate) = match sweep(client, board, &SweepOptions::default(), |_| {
        std::ops::ControlFlow::Continue(())
    }) {
        Ok(r) => r,
        Err(
            e @ (MeasureError::Link { .. }
            | MeasureError::Capture { .. }
            | MeasureError::Convert { .. }),
        ) => return Err(CalibrateError::Resonance(e)),
        Err(e) => return Ok(ResonanceOutcome::NotFitted(e.to_string())),
    };
    Ok(match fit(&points, rate as f64) {
        Some(f) if Resonance::new(f.plant.resonance_hz, f.plant.zeta).is_ok() => {
            ResonanceOutcome::Measured(f)
        }
        Some(f) => ResonanceOutcome::NotFitted(format!(
            "the fit's resonance ({:.0} Hz, damping {:.4}) is not a lightly damped one",
            f.plant.resonance_hz, f.plant.zeta
        )),
        None => ResonanceOutcome::NotFitted(format!(
            "the response measured at {} frequencies could not be fitted with a resonance and a delay",
            points.len()
        )),
    })
}

#[cfg(test)]
mod tests;
