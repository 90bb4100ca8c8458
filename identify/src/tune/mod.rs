//! Measured frequency response and automatic tuning (`twinstack tune`), over any
//! [`Transport`]: the simulated board, the virtual board, the emulator or a real board.
//!
//! 1. **Measure** ([`measure`]): stepped sines from the board's waveform generator in bypass,
//!    drive and sensor captured by its recorder, a lock-in per frequency on the host.
//! 2. **Fit** ([`fit`]): gain, resonance (frequency, damping) and the delay in ticks, as the
//!    tick sees the stage.
//! 3. **Design** ([`design`]): the notch on (or just above) the fitted resonance and the PI
//!    gains, judged on the discrete-time loop ([`loop_model`]) with the tick's delay and the
//!    notch: at least the asked phase and gain margins, at most 0.5 % ringing of a setpoint
//!    step on the model, the widest bandwidth. Or **check** a given gain set: refused when
//!    the fitted model says it is unstable or short of the margins.
//! 4. **Load** (optional): the board's settings with the feedback replaced, through the
//!    normal `LoadParams` path (the board validates them as any load).
//!
//! The caller's `progress` hears of each point measured and of each wait on the board
//! ([`SweepEvent`]) and can stop the sweep ([`ControlFlow::Break`]): the generator is left
//! stopped, the mode restored, nothing loaded ([`TuneError::Stopped`]).

pub mod design;
pub mod fit;
pub mod loop_model;
pub mod measure;

use design::{Design, Goals, Refused};
use fit::Fit;
use loop_model::LoopFigures;
pub use measure::SweepEvent;
use measure::{FrequencyPoint, MeasureError, SweepOptions};
use std::ops::ControlFlow;
use twinstack::control::feedback::FeedbackSettings;
use twinstack::control::notch::NotchDesign;
use twinstack::protocol::messages::{Mode, StatusReport, StreamControl};
use twinstack_link::client::{Client, LinkError};
use twinstack_link::Transport;

/// What [`tune`] does.
#[derive(Clone, Debug, PartialEq)]
pub struct TuneOptions {
    /// The sweep.
    pub sweep: SweepOptions,
    /// Least phase margin, degrees.
    pub phase_margin_deg: f64,
    /// Least gain margin, dB.
    pub gain_margin_db: f64,
    /// Check these settings instead of designing.
    pub check: Option<FeedbackSettings>,
    /// Load the result (the design, or the checked settings if they pass).
    pub load: bool,
}

impl Default for TuneOptions {
    /// The default sweep, 45°, 6 dB, design, no load.
    fn default() -> Self {
        Self {
            sweep: SweepOptions::default(),
            phase_margin_deg: 45.0,
            gain_margin_db: 6.0,
            check: None,
            load: false,
        }
    }
}

/// What [`tune`] measured, fitted and chose.
#[derive(Clone, Debug)]
pub struct TuneReport {
    /// The board's control rate, Hz.
    pub rate: f64,
    /// The measured response.
    pub points: Vec<FrequencyPoint>,
    /// The fitted model.
    pub fit: Fit,
    /// The goals the design or the check was held to.
    pub goals: Goals,
    /// The feedback chosen (or checked) and its figures on the fitted model.
    pub design: Design,
    /// The board's feedback before, and its figures on the fitted model (`Err`: why it is
    /// refused), if it had one.
    pub before: Option<(FeedbackSettings, Result<LoopFigures, Refused>)>,
    /// The result was loaded onto the board.
    pub loaded: bool,
}

impl TuneReport {
    /// The board's timing beside the tuned loop: sample to output, s
    /// ([`twinstack::board::sample_to_output_s`]), and the phase the sample's lead
    /// ([`twinstack::board::SAMPLE_LEAD_NS`]) costs at the loop's crossover, degrees — a delay
    /// the whole-tick loop model rounds away and the simulated board does not have.
    pub fn board_timing(&self) -> (f64, f64) {
        let lead_s = twinstack::board::SAMPLE_LEAD_NS as f64 * 1e-9;
        (
            twinstack::board::sample_to_output_s(self.rate),
            360.0 * self.design.figures.crossover_hz * lead_s,
        )
    }

    /// The report as one JSON object: the measured points (magnitude in dB, phase in
    /// degrees), the fit, the goals, the feedback and its figures, the input shaping for the
    /// fitted resonance ([`shaping_for`]), the board's feedback before and its verdict, whether
    /// it was loaded, and the board's timing ([`Self::board_timing`]). What `twinstack tune
    /// --json` prints and Python's `Board.tune` returns.
    pub fn to_json(&self) -> serde_json::Value {
        let p = &self.fit.plant;
        let (latency_s, lead_deg) = self.board_timing();
        serde_json::json!({
            "rate_hz": self.rate,
            "points": self.points.iter().map(|q| serde_json::json!({
                "frequency_hz": q.frequency_hz,
                "magnitude_db": q.magnitude_db(),
                "phase_deg": q.phase_deg(),
            })).collect::<Vec<_>>(),
            "fit": {
                "gain": p.gain, "resonance_hz": p.resonance_hz, "zeta": p.zeta,
                "delay_ticks": p.delay, "rms_db": self.fit.rms_db, "rms_deg": self.fit.rms_deg,
            },
            "goals": self.goals,
            "feedback": self.design.settings,
            "shaping": shaping_for(p.resonance_hz, p.zeta),
            "figures": self.design.figures,
            "before": self.before.as_ref().map(|(s, f)| serde_json::json!({
                "feedback": s,
                "figures": f.as_ref().ok(),
                "refused": f.as_ref().err().map(|e| e.to_string()),
            })),
            "loaded": self.loaded,
            "board_timing": {
                "sample_to_output_s": latency_s,
                "lead_phase_deg": lead_deg,
            },
        })
    }
}

/// The input shaping for a resonance at `resonance_hz` with damping `zeta` (what [`tune`]
/// fits): a notch whose zeros are the resonance's poles (`depth = 2·Q·ζ`) and whose poles are
/// critically damped (`Q = ½`). The shaped stage's response has the notch's poles where the
/// resonance was.
///
/// ```
/// let n = twinstack_identify::tune::shaping_for(21_807.0, 0.01729);
/// assert_eq!((n.frequency_hz, n.q, n.depth), (21_807.0, 0.5, 0.01729));
/// ```
pub fn shaping_for(resonance_hz: f64, zeta: f64) -> NotchDesign {
    let q = 0.5;
    NotchDesign {
        frequency_hz: resonance_hz,
        q,
        depth: (2.0 * q * zeta).clamp(0.0, 1.0),
    }
}

/// Why tuning stopped.
#[derive(Debug, thiserror::Error)]
pub enum TuneError {
    /// Measuring failed.
    #[error(transparent)]
    Measure(#[from] MeasureError),
    /// The link failed or the board refused.
    #[error("{step}: {source}")]
    Link {
        /// What was being done.
        step: &'static str,
        /// The cause.
        source: LinkError,
    },
    /// The response could not be fitted.
    #[error(
        "the measured response could not be fitted with a resonance and a delay ({points} points)"
    )]
    Fit {
        /// Points measured.
        points: usize,
    },
    /// No gain set on the search grid meets the goals.
    #[error("no PI gains and notch meet {pm}° phase margin, {gm} dB gain margin and 0.5 % ringing on the fitted model (resonance {resonance_hz:.0} Hz, ζ = {zeta:.4}); nothing was loaded")]
    NoDesign {
        /// Asked.
        pm: f64,
        /// Asked.
        gm: f64,
        /// Fitted.
        resonance_hz: f64,
        /// Fitted.
        zeta: f64,
    },
    /// The gain set checked is refused.
    #[error("refused: {0}; nothing was loaded")]
    Refused(Refused),
    /// The caller's `progress` stopped the sweep.
    #[error("the tuning sweep was stopped at {frequency_hz:.0} Hz with {measured} frequencies measured: the generator is stopped, the board's mode restored and nothing was loaded")]
    Stopped {
        /// The frequency being measured (or last measured), Hz.
        frequency_hz: f64,
        /// Frequencies measured before the stop.
        measured: usize,
    },
}

fn link(step: &'static str) -> impl Fn(LinkError) -> TuneError {
    move |source| TuneError::Link { step, source }
}

/// Fits `points` and designs (or checks `options.check`) at `rate`: everything after the
/// measurement, without a board.
pub fn analyse(
    points: &[FrequencyPoint],
    rate: f64,
    options: &TuneOptions,
) -> Result<(Fit, Goals, Design), TuneError> {
    let fit = fit::fit(points, rate).ok_or(TuneError::Fit {
        points: points.len(),
    })?;
    let goals = Goals {
        phase_margin_deg: options.phase_margin_deg,
        gain_margin_db: options.gain_margin_db,
        ..Goals::at(rate)
    };
    let design = match &options.check {
        Some(s) => Design {
            settings: *s,
            figures: design::check(&fit.plant, s, &goals).map_err(TuneError::Refused)?,
        },
        None => design::design(&fit.plant, &goals).ok_or(TuneError::NoDesign {
            pm: goals.phase_margin_deg,
            gm: goals.gain_margin_db,
            resonance_hz: fit.plant.resonance_hz,
            zeta: fit.plant.zeta,
        })?,
    };
    Ok((fit, goals, design))
}

/// Measures, fits, designs (or checks) and optionally loads, on the board behind `client`
/// (see the module doc). The board's mode is restored afterwards; its settings change only
/// with [`TuneOptions::load`].
///
/// `progress` hears of each point measured and of each wait on the board
/// ([`measure::sweep`]); answering [`ControlFlow::Break`] stops the sweep within one
/// [`measure::POLL`]: [`TuneError::Stopped`], the generator stopped, the mode restored,
/// nothing loaded.
///
/// ```no_run
/// use std::ops::ControlFlow;
/// use twinstack_identify::tune::{tune, SweepEvent, TuneOptions};
/// use twinstack_link::{socket::SocketTransport, Client};
/// // A board behind TCP: a virtual board (`twinstack virtual-board`) or QEMU's UART.
/// let transport = SocketTransport::tcp("127.0.0.1:4000").unwrap();
/// let mut client = Client::new(transport);
/// let r = tune(&mut client, &TuneOptions::default(), |event| {
///     if let SweepEvent::Point(p) = event {
///         println!("{:.0} Hz: {:.1} dB", p.frequency_hz, p.magnitude_db());
///     }
///     ControlFlow::Continue(())
/// })
/// .unwrap();
/// println!("bandwidth {:.0} Hz", r.design.figures.bandwidth_hz);
/// ```
pub fn tune<T: Transport>(
    client: &mut Client<T>,
    options: &TuneOptions,
    progress: impl FnMut(SweepEvent<'_>) -> ControlFlow<()>,
) -> Result<TuneReport, TuneError> {
    options.sweep.check()?;
    let status = client.status().map_err(link("status"))?;
    let board = client.read_params().map_err(link("reading the settings"))?;
    if status.has(StatusReport::STREAMING) || status.has(StatusReport::WAVEFORM) {
        client
            .stream(StreamControl::Stop)
            .map_err(link("stopping the stream"))?;
    }
    let previous = status.mode();
    client
        .set_mode(Mode::Bypass)
        .map_err(link("switching to bypass"))?;
    let measured = measure::sweep(client, &board, &options.sweep, progress);
    let restored = client.set_mode(previous);
    let (points, rate) = match measured {
        Ok(m) => m,
        // A stop is no fault of the board's: a failure to restore the mode says more.
        Err(MeasureError::Stopped {
            frequency_hz,
            measured,
        }) => {
            restored.map_err(link("restoring the mode after the stop"))?;
            return Err(TuneError::Stopped {
                frequency_hz,
                measured,
            });
        }
        // Best effort: the error at hand says more than a failure to restore the mode.
        Err(e) => return Err(e.into()),
    };
    restored.map_err(link("restoring the mode"))?;
    let rate = rate as f64;
    let (fit, goals, design) = analyse(&points, rate, options)?;
    let before = board
        .feedback
        .map(|f| (f, design::check(&fit.plant, &f, &goals)));
    let mut loaded = false;
    if options.load {
        let settings = twinstack::config::settings::Settings {
            feedback: Some(design.settings),
            ..board
        };
        client
            .load_params(&settings)
            .map_err(link("loading the tuned feedback"))?;
        loaded = true;
    }
    Ok(TuneReport {
        rate,
        points,
        fit,
        goals,
        design,
        before,
        loaded,
    })
}
