//! Closed loop on the simulated stage: sensor feedback around the feedforward compensator.
//!
//! For each control rate (50 kHz and 100 kHz), on the paper's differential stage with the
//! external converters (16-bit DAC8562, 16-bit ADS8689 with its one sample of latency), the
//! position sensor's noise and the amplifiers' noise and slew limit:
//!
//! 1. **Identify** the feedforward model as a user would: the bypassed tick plays a 70 ± 70 V
//!    750 Hz sine, and a P–I model (16 operators, fewer where the rate's tick budget needs it:
//!    [`operators_at`]) is fitted to the first half of the record, each drive sample paired
//!    with the stage at the middle of its hold (half a sample's lag: see `identify`).
//! 2. **Track** a 100 Hz triangle and a 750 Hz sine over 10–90 % of the stroke with four
//!    configurations of the very same tick — no compensation (bypass), feedforward only (open
//!    loop), feedback only (closed loop without the inverse model), feedforward + feedback —
//!    and score the tracking error (max and RMS, % of the commanded stroke): the stage at
//!    each hold's end, where the sensor reads it, against the target of that instant, between
//!    the setpoints of the holds' middles around it (the rule the tick's feedback takes it
//!    by, `twinstack::control::instant`).
//! 3. **Step** the setpoint (30 % → 70 % of the stroke) in closed loop with and without the
//!    resonance notch, and measure the ringing.
//!
//! The feedback's gains are the same in every run at a rate: by default ([`Gains::Tuned`])
//! those `twinstack tune` picks at that rate on the simulated board (its sweep measured through
//! the protocol, fitted and designed: [`tuned_feedback`]); with [`Gains::Fixed`], a fixed PI
//! with the notch at the stage's resonance ([`feedback_settings`]). The steps run the same
//! gains with and without their notch.

use crate::plot::{draw_panels, Panel, Series};
use anyhow::{anyhow, Context, Result};
use hal_sim::plant::Configuration as StageConfiguration;
use hal_sim::sim_board::{BoardConfig, ExternalBoard, SimBoard};
use plotters::style::{BLUE, RED};
use std::path::PathBuf;
use twinstack::board::Hardware;
use twinstack::config::settings::{FeedbackSettings, Mode, Model, SensorSettings, Settings};
use twinstack::control::drive::{Configuration, DriveSettings, SafeState};
use twinstack::control::notch::NotchDesign;
use twinstack::control::preview::{PreviewDesign, PREVIEW_DELAY_TICKS};
use twinstack::control::{ControlConfig, Controller, TickFlags};
use twinstack::fixed_point::{signal_from_f64, signal_to_f64};
use twinstack::services::observer::Observed;
use twinstack::sources::waveform::{Shape, WaveformGenerator};
use twinstack::Scaling;
use twinstack_identify::identification::{
    identify, score::score, IdentifyOptions, ModelKind, ThresholdSpread,
};
use twinstack_identify::stage_model::{between_samples, Hysteresis, StageModel};
use twinstack_identify::tune::TuneReport;
use twinstack_link::measured_data::MeasuredData;

/// The differential stage's first resonance (see the book, docs/src/reference/physics.md), Hz: where the notch sits.
pub const RESONANCE_HZ: f64 = 21_800.0;

/// What the closed-loop study runs.
#[derive(Clone, Debug)]
pub struct ClosedLoopOptions {
    /// Control rates, Hz.
    pub rates: Vec<f64>,
    /// Cycles of the 750 Hz sine per run (the first two are not scored).
    pub sine_cycles: usize,
    /// Cycles of the 100 Hz triangle per run (the first is not scored).
    pub triangle_cycles: usize,
    /// Position sensor noise, µm rms.
    pub sensor_noise_um: f64,
    /// Where the PNG figure goes (`None`: no figure).
    pub out_dir: Option<PathBuf>,
    /// Which feedback gains run.
    pub gains: Gains,
    /// Also track with the board's preview: the feedforward's rows again with the settings'
    /// preview for the resonance `twinstack tune` measures at each rate
    /// ([`twinstack::config::settings::Settings::preview`]: every setpoint shaped before the
    /// compensator, the feedback aiming at the setpoint itself).
    pub preview: bool,
}

/// Which feedback gains the study runs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Gains {
    /// What `twinstack tune` picks at each rate on the simulated board ([`tuned_feedback`]).
    #[default]
    Tuned,
    /// The fixed PI with the notch of [`feedback_settings`].
    Fixed,
}

impl Default for ClosedLoopOptions {
    fn default() -> Self {
        Self {
            rates: vec![50_000.0, 100_000.0],
            sine_cycles: 30,
            triangle_cycles: 4,
            gains: Gains::Tuned,
            sensor_noise_um: 0.002,
            out_dir: Some(PathBuf::from("out")),
            preview: false,
        }
    }
}

/// One of the four configurations of the table.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Configuration4 {
    /// Bypass: the drive is the setpoint, range onto range.
    None,
    /// The inverse model alone (open loop).
    Feedforward,
    /// The feedback alone, on the linear range-onto-range drive.
    Feedback,
    /// The inverse model plus the feedback.
    Both,
}

impl Configuration4 {
    /// All four, in the table's order.
    pub const ALL: [Self; 4] = [Self::None, Self::Feedforward, Self::Feedback, Self::Both];

    /// The table's label.
    pub fn label(self) -> &'static str {
        match self {
            Self::None => "no compensation",
            Self::Feedforward => "feedforward only",
            Self::Feedback => "feedback only",
            Self::Both => "feedforward + feedback",
        }
    }
}

/// The board's mode for `c`.
fn mode_of(c: Configuration4) -> Mode {
    match c {
        Configuration4::None => Mode::Bypass,
        Configuration4::Feedforward => Mode::OpenLoop,
        Configuration4::Feedback | Configuration4::Both => Mode::ClosedLoop,
    }
}

/// One cell group of the table: a rate, a waveform, a configuration.
#[derive(Clone, Debug)]
pub struct TrackingRow {
    /// Control rate, Hz.
    pub rate: f64,
    /// `100 Hz triangle` or `750 Hz sine`.
    pub waveform: &'static str,
    /// The configuration.
    pub configuration: Configuration4,
    /// The board ran the preview ([`ClosedLoopOptions::preview`]).
    pub preview: bool,
    /// Largest tracking error, % of the commanded stroke.
    pub max_pct: f64,
    /// RMS tracking error, % of the commanded stroke.
    pub rms_pct: f64,
    /// Ticks the drift check flagged (`None`: no observer at this rate, so no check; see
    /// [`settings`]).
    pub drift_ticks: Option<u64>,
    /// Of those, the ticks in the scored cycles (the first cycles, which the tracking error
    /// leaves out, left out here too): the observer starts at rest on its ascending branch in
    /// the differential drive `v`, while both stacks rose together from 0 V to the bias, so the
    /// first move after boot can disagree until the drive has swept its range (see the book,
    /// reference/models.md, "At rest").
    pub drift_ticks_after_start: Option<u64>,
}

/// The step with or without the notch.
#[derive(Clone, Debug)]
pub struct StepRow {
    /// Control rate, Hz.
    pub rate: f64,
    /// Notch on.
    pub notch: bool,
    /// Overshoot beyond the final value, % of the step.
    pub overshoot_pct: f64,
    /// Largest |x − final| from 1 ms to 3 ms after the step, % of the step: the ringing that
    /// is left once the step itself is over.
    pub ringing_pct: f64,
    /// Time series for the figure: time after the step (ms), stage (µm).
    pub trace: Vec<(f64, f64)>,
}

/// Everything the study found.
#[derive(Clone, Debug, Default)]
pub struct ClosedLoopReport {
    /// The feedback each rate ran (in the study model's normalised units).
    pub feedback: Vec<(f64, FeedbackSettings)>,
    /// With [`ClosedLoopOptions::preview`], the resonance measured at each rate (rate, Hz,
    /// damping ratio), which the preview's rows shape the setpoints for.
    pub resonance: Vec<(f64, f64, f64)>,
    /// The table.
    pub tracking: Vec<TrackingRow>,
    /// The steps.
    pub steps: Vec<StepRow>,
    /// Figures written.
    pub figures: Vec<PathBuf>,
}

impl ClosedLoopReport {
    /// The row for `rate`, `waveform`, `configuration`, the setpoints as they come.
    pub fn row(&self, rate: f64, waveform: &str, c: Configuration4) -> Option<&TrackingRow> {
        self.row_shaped(rate, waveform, c, false)
    }

    /// The row for `rate`, `waveform`, `configuration`, with the setpoints shaped for the
    /// resonance (`preview`) or not.
    pub fn row_shaped(
        &self,
        rate: f64,
        waveform: &str,
        c: Configuration4,
        preview: bool,
    ) -> Option<&TrackingRow> {
        self.tracking.iter().find(|r| {
            r.rate == rate && r.waveform == waveform && r.configuration == c && r.preview == preview
        })
    }

    /// Whether feedforward + feedback beats feedforward only and feedback only, on max and on
    /// RMS, for every rate and waveform.
    pub fn both_beats_the_others_everywhere(&self) -> bool {
        self.tracking
            .iter()
            .filter(|r| r.configuration == Configuration4::Both && !r.preview)
            .all(|b| {
                [Configuration4::Feedforward, Configuration4::Feedback]
                    .iter()
                    .all(|&c| match self.row(b.rate, b.waveform, c) {
                        Some(o) => b.max_pct < o.max_pct && b.rms_pct < o.rms_pct,
                        None => false,
                    })
            })
    }
}

/// The board at `rate`: the paper's differential stage, external converters.
pub fn board(rate: f64, sensor_noise_um: f64) -> Result<ExternalBoard> {
    let mut config = BoardConfig::paper(StageConfiguration::Differential);
    config.plant.dt = 1.0 / rate;
    config.sensor_noise_um = sensor_noise_um;
    SimBoard::external(&config).map_err(|e| anyhow!("simulated board: {e}"))
}

/// The board the study runs on at `rate`: the 150 V amplifiers on the 16-bit DAC8562, the
/// sensor on the 16-bit ADS8689.
pub fn hardware(rate: f64) -> Hardware {
    Hardware {
        amplifier_full_scale: 150.0,
        dac_full_scale: 65535,
        sensor_adc_bits: Some(16),
        control_rate_hz: rate,
    }
}

/// The drive settings of the study.
pub fn drive_settings() -> DriveSettings {
    DriveSettings {
        configuration: Configuration::Differential,
        bias: 70.0,
        min_voltage: 0.0,
        max_voltage: 140.0,
        // The amplifier's own limit is 1 V/µs; the controller's sits just below it.
        slew_rate: 0.9e6,
        safe_state: SafeState::Bias,
    }
}

/// The sensor as the board reads it: the ADS8689's ±10.24 V over 16 bits, in µm; drift
/// flagged beyond 3 % of the output range.
pub fn sensor_settings(board: &ExternalBoard) -> SensorSettings {
    let s = board.sensor();
    let um_at = |volts: f64| (volts - s.offset_volts()) / s.volts_per_um();
    SensorSettings {
        displacement_at_zero: um_at(-10.24),
        displacement_at_full_scale: um_at(10.24),
        drift_limit: Some(0.03),
    }
}

/// The feedback of the study: PI on the notched error, `kp = 0.1` and `ki` = 10 000 /s at
/// 50 kHz (20 000 /s at 100 kHz: the same integral step at both rates), correction within
/// ±25 % of the drive range.
pub fn feedback_settings(rate: f64, notch: bool) -> FeedbackSettings {
    FeedbackSettings {
        notch: notch.then_some(NotchDesign {
            frequency_hz: RESONANCE_HZ,
            q: 2.0,
            depth: 0.0,
        }),
        ..FeedbackSettings::pi(0.1, 0.2 * rate, 0.25)
    }
}

/// The feedback `twinstack tune` picks at `rate` on the simulated board (the paper's stage:
/// sweep measured through the protocol, resonance and delay fitted, PI and notch designed to
/// its default margins), its gains carried from the board's normalised units (its 70 V input
/// half span onto ±45 µm) to those of `model`'s scaling.
pub fn tuned_feedback(rate: f64, model: &StageModel) -> Result<FeedbackSettings> {
    Ok(feedback_from(&tune_at(rate)?, model))
}

/// `twinstack tune` at `rate` on the simulated board (the study's stage), default options.
pub fn tune_at(rate: f64) -> Result<TuneReport> {
    use hal_sim::sim_device::{SimDevice, SimDeviceConfig};
    use twinstack_identify::tune::{tune, TuneOptions};
    use twinstack_link::Client;
    let mut config = SimDeviceConfig::paper();
    config.board.plant.dt = 1.0 / rate;
    let device = SimDevice::new(config).map_err(|e| anyhow!("simulated board: {e}"))?;
    let mut client = Client::new(device);
    tune(&mut client, &TuneOptions::default(), |_| {
        std::ops::ControlFlow::Continue(())
    })
    .map_err(|e| anyhow!("tuning at {rate} Hz: {e}"))
}

/// The gains `report` picked, rescaled to `model` (see [`tuned_feedback`]).
fn feedback_from(report: &TuneReport, model: &StageModel) -> FeedbackSettings {
    use hal_sim::sim_device::SimDeviceConfig;
    let board_ranges =
        SimDeviceConfig::paper_settings(twinstack::protocol::messages::Mode::Bypass).ranges;
    let s = model.scaling;
    // Loop gain per normalised error is the same on both scalings when kp scales by
    // (board's volts per µm) / (model's volts per µm), normalised.
    let k = (s.input_half_span() / s.output_half_span())
        / (board_ranges.input_half_span() / board_ranges.output_half_span());
    let d = report.design.settings;
    FeedbackSettings {
        kp: d.kp / k,
        ki: d.ki / k,
        ..d
    }
}

/// The model as the settings carry it.
pub fn model_of(model: &StageModel) -> Model {
    match &model.hysteresis {
        Hysteresis::Pi(p) => Model::PrandtlIshlinskii(p.clone()),
        Hysteresis::Duhem(p) => Model::Duhem(*p),
        Hysteresis::GeneralisedPi(p) => Model::GeneralisedPi(p.clone()),
        Hysteresis::BoucWen(p) => Model::BoucWen(*p),
    }
}

/// The settings for `c` with `model` as the compensator (except feedback only) and as the
/// observer where the rate leaves the pipeline time for it (the observer runs below the tick;
/// where it does not fit, the model runs as the compensator only and there is no drift
/// check, as `calibrate` loads it: the compensator's size comes first).
pub fn settings(
    rate: f64,
    model: &StageModel,
    sensor: SensorSettings,
    c: Configuration4,
    notch: bool,
) -> Settings {
    observer_if_it_fits(settings_observed(rate, model, sensor, c, notch), rate).0
}

/// `with` (its observer set) where the rate leaves the pipeline time for the observer, else
/// `with` without it; and the configuration the settings kept build on [`hardware`].
fn observer_if_it_fits(with: Settings, rate: f64) -> (Settings, Result<ControlConfig>) {
    let hw = hardware(rate);
    if let Ok(config) = with.build(&hw) {
        return (with, Ok(config));
    }
    let without = Settings {
        observer: None,
        ..with
    };
    let config = without
        .build(&hw)
        .map_err(|e| anyhow!("settings refused: {e}"));
    (without, config)
}

fn settings_observed(
    rate: f64,
    model: &StageModel,
    sensor: SensorSettings,
    c: Configuration4,
    notch: bool,
) -> Settings {
    let m = model_of(model);
    Settings {
        ranges: model.scaling,
        compensator: (c != Configuration4::Feedback).then(|| m.clone()),
        observer: Some(m),
        drive: drive_settings(),
        sensor: Some(sensor),
        feedback: Some(feedback_settings(rate, notch)),
        mode: mode_of(c),
        creep: model.creep.clone(),
        shaping: None,
        preview: None,
        output_map: model.output_map.clone(),
    }
}

/// The controller configuration for `c` ([`settings`], built on [`hardware`]).
pub fn configuration(
    rate: f64,
    model: &StageModel,
    sensor: SensorSettings,
    c: Configuration4,
    notch: bool,
) -> Result<ControlConfig> {
    settings(rate, model, sensor, c, notch)
        .build(&hardware(rate))
        .map_err(|e| anyhow!("settings refused: {e}"))
}

/// A run: setpoint (µm), stage (µm), drift ticks.
struct Run {
    desired: Vec<f64>,
    x: Vec<f64>,
    drift_ticks: u64,
    drift_ticks_after_start: u64,
}

fn simulate(
    rate: f64,
    options: &ClosedLoopOptions,
    config: ControlConfig,
    scaling: &Scaling,
    setpoints: impl Iterator<Item = i32>,
    start_up: usize,
) -> Result<Run> {
    let mut board = board(rate, options.sensor_noise_um)?;
    // The tick and, with the sensor, the observer and its drift check below it.
    let mut controller = Observed::new(config);
    let mut run = Run {
        desired: Vec::new(),
        x: Vec::new(),
        drift_ticks: 0,
        drift_ticks_after_start: 0,
    };
    for sp in setpoints {
        let r = controller.tick_board(Some(sp), &mut board);
        if r.flags.contains(TickFlags::DRIFT) {
            run.drift_ticks += 1;
            if run.x.len() >= start_up {
                run.drift_ticks_after_start += 1;
            }
        }
        run.desired.push(scaling.norm_to_output(signal_to_f64(sp)));
        // The stage at the hold's end, where the sensor reads it.
        run.x.push(board.plant().stage_um());
    }
    // Each setpoint is for the middle of its drive's hold: the target at a hold's end lies
    // between two, by the rule the tick's feedback takes it (`twinstack::control::instant`).
    // The last is the last setpoint (no setpoint after it): a run's last two samples are
    // not scored.
    run.desired = between_samples(&run.desired);
    let c = controller.controller.counters();
    if c.adc_errors + c.dac_errors > 0 {
        return Err(anyhow!("converter errors in the simulated run: {c:?}"));
    }
    Ok(run)
}

/// The P–I size the study fits at `rate`: 16 operators, or the most (in pairs) the tick budget
/// admits at that rate as the study loads them — the compensator, the sensor, PI with the
/// notch ([`twinstack::config::tick_budget`]; the observer only where it fits beside them,
/// [`settings`]).
pub fn operators_at(rate: f64) -> usize {
    let admitted = |n: usize| {
        let Ok(pi) = twinstack::config::settings::representative_pi(n) else {
            return false;
        };
        let settings = Settings {
            compensator: Some(pi),
            observer: None,
            sensor: Some(SensorSettings {
                displacement_at_zero: 0.0,
                displacement_at_full_scale: 70.0,
                drift_limit: Some(0.03),
            }),
            feedback: Some(feedback_settings(rate, true)),
            mode: Mode::ClosedLoop,
            ..Settings::default()
        };
        settings.build(&hardware(rate)).is_ok()
    };
    (1..=8)
        .rev()
        .map(|pairs| 2 * pairs)
        .find(|&n| admitted(n))
        .unwrap_or(2)
}

/// Step 1: excite with the bypassed tick, identify P–I N = [`operators_at`] the rate.
pub fn identify_model(rate: f64, options: &ClosedLoopOptions) -> Result<StageModel> {
    let cycles = 20;
    let ticks = (rate / 750.0).round() as usize * cycles;
    // Bypass over 0…140 V, no model and no sensor: setpoint ±1 is u_l = 70 ± 70 V.
    let settings = Settings {
        ranges: Scaling::new(0.0, 140.0, -1.0, 1.0)?,
        compensator: None,
        observer: None,
        drive: drive_settings(),
        sensor: None,
        feedback: None,
        mode: Mode::Bypass,
        creep: None,
        shaping: None,
        preview: None,
        output_map: None,
    };
    let config = settings
        .build(&hardware(rate))
        .map_err(|e| anyhow!("{e}"))?;
    let mut wave = WaveformGenerator::new(Shape::Sine, 0, signal_from_f64(1.0), 750.0, rate)
        .map_err(|e| anyhow!("{e:?}"))?;
    let mut board = board(rate, options.sensor_noise_um)?;
    let mut controller = Controller::new(config);
    let (mut t, mut u, mut x) = (Vec::new(), Vec::new(), Vec::new());
    // Sample k: the stage at the tick's instant (the end of the hold before), then the drive
    // the tick gives it to hold.
    for k in 0..ticks {
        x.push(board.plant().stage_um());
        controller.tick_board(Some(wave.next_sample()), &mut board);
        t.push(k as f64 / rate);
        u.push(board.amplifier_volts()[0]);
    }
    let data = MeasuredData {
        path: PathBuf::from("simulated differential stage"),
        t: t.clone(),
        u: Some(u),
        x: Some(x),
    };
    let mut opts = IdentifyOptions::new(ModelKind::Pi, t[t.len() / 2]);
    opts.operators = operators_at(rate);
    opts.thresholds = ThresholdSpread::Uniform;
    // The drive of sample k is held from the stage's sample k to its sample k + 1: the model
    // maps it to the middle of that hold, half a sample on (see `identify`'s half lag).
    opts.lag = Some(0);
    opts.half_lag = true;
    Ok(identify(&data, &opts)
        .context("identifying P–I on the simulated stage")?
        .model)
}

/// The stroke the model covers, µm: its output range.
fn stroke(model: &StageModel) -> (f64, f64) {
    let s = model.scaling;
    (s.output_min, s.output_max)
}

/// Step 2: one tracking run, scored.
pub fn track(
    rate: f64,
    options: &ClosedLoopOptions,
    model: &StageModel,
    shape: Shape,
    c: Configuration4,
) -> Result<TrackingRow> {
    track_with(
        rate,
        options,
        model,
        shape,
        c,
        &feedback_settings(rate, true),
        None,
    )
}

/// [`track`] with the feedback `feedback` and the board's preview for the resonance `preview`
/// where there is one ([`Settings::preview`]): scored against the waveform, which the stage
/// then follows [`PREVIEW_DELAY_TICKS`] ticks late.
pub fn track_with(
    rate: f64,
    options: &ClosedLoopOptions,
    model: &StageModel,
    shape: Shape,
    c: Configuration4,
    feedback: &FeedbackSettings,
    preview: Option<PreviewDesign>,
) -> Result<TrackingRow> {
    let board0 = board(rate, options.sensor_noise_um)?;
    let sensor = sensor_settings(&board0);
    // The observer where the tuned feedback leaves it time ([`settings`]).
    let with = Settings {
        feedback: Some(*feedback),
        preview,
        ..settings_observed(rate, model, sensor, c, feedback.notch.is_some())
    };
    let config = observer_if_it_fits(with, rate).1?;
    let observed = !matches!(config.observer, twinstack::control::Observer::None);
    let (frequency, cycles, skip, label) = match shape {
        Shape::Triangle => (100.0, options.triangle_cycles, 1, "100 Hz triangle"),
        Shape::Sine => (750.0, options.sine_cycles, 2, "750 Hz sine"),
    };
    let s = model.scaling;
    let (lo, hi) = stroke(model);
    let centre = s.output_to_norm(0.5 * (lo + hi));
    let amplitude = 0.4 * (hi - lo) / s.output_half_span();
    let mut wave = WaveformGenerator::new(
        shape,
        signal_from_f64(centre),
        signal_from_f64(amplitude),
        frequency,
        rate,
    )
    .map_err(|e| anyhow!("tracking waveform: {e:?}"))?;
    let per_cycle = (rate / frequency).round() as usize;
    let ticks = per_cycle * cycles;
    let from = (skip * per_cycle).min(ticks);
    let wanted: Vec<i32> = (0..ticks).map(|_| wave.next_sample()).collect();
    let mut run = simulate(rate, options, config, &s, wanted.into_iter(), from)?;
    if preview.is_some() {
        // The preview aims the stage at each setpoint PREVIEW_DELAY_TICKS ticks after it is
        // given: scored against the waveform that late.
        run.desired = (0..run.desired.len())
            .map(|k| run.desired[k.saturating_sub(PREVIEW_DELAY_TICKS)])
            .collect();
    }
    let fig = score(&run.desired, &run.x, from..ticks.saturating_sub(2))
        .ok_or_else(|| anyhow!("nothing to score ({cycles} cycles)"))?;
    Ok(TrackingRow {
        rate,
        waveform: label,
        configuration: c,
        preview: preview.is_some(),
        max_pct: fig.max_pct,
        rms_pct: fig.rms_pct,
        drift_ticks: observed.then_some(run.drift_ticks),
        drift_ticks_after_start: observed.then_some(run.drift_ticks_after_start),
    })
}

/// Step 3: a step from 30 % to 70 % of the stroke in closed loop (feedforward + feedback),
/// with or without the notch.
pub fn step(
    rate: f64,
    options: &ClosedLoopOptions,
    model: &StageModel,
    notch: bool,
) -> Result<StepRow> {
    let mut row = step_with(rate, options, model, &feedback_settings(rate, notch))?;
    row.notch = notch;
    Ok(row)
}

/// [`step`] with the feedback `feedback` (e.g. what `twinstack tune` chose); the row's `notch`
/// says whether it has one.
pub fn step_with(
    rate: f64,
    options: &ClosedLoopOptions,
    model: &StageModel,
    feedback: &FeedbackSettings,
) -> Result<StepRow> {
    let board0 = board(rate, options.sensor_noise_um)?;
    let sensor = sensor_settings(&board0);
    let notch = feedback.notch.is_some();
    let config = Settings {
        feedback: Some(*feedback),
        ..settings(rate, model, sensor, Configuration4::Both, notch)
    }
    .build(&hardware(rate))
    .map_err(|e| anyhow!("settings refused: {e}"))?;
    let s = model.scaling;
    let (lo, hi) = stroke(model);
    let (from_um, to_um) = (lo + 0.3 * (hi - lo), lo + 0.7 * (hi - lo));
    let before = (0.005 * rate) as usize; // 5 ms to settle at the start
    let after = (0.004 * rate) as usize;
    let sp = |um: f64| signal_from_f64(s.output_to_norm(um));
    let run = simulate(
        rate,
        options,
        config,
        &s,
        (0..before + after).map(|k| if k < before { sp(from_um) } else { sp(to_um) }),
        before,
    )?;
    let x = &run.x[before..];
    let last = (0.0035 * rate) as usize..after;
    let final_um = x[last.clone()].iter().sum::<f64>() / last.len() as f64;
    let size = to_um - from_um;
    let peak = x.iter().fold(f64::NEG_INFINITY, |m, &v| m.max(v));
    let window = (0.001 * rate) as usize..(0.003 * rate) as usize;
    let ringing = x[window]
        .iter()
        .fold(0.0f64, |m, &v| m.max((v - final_um).abs()));
    Ok(StepRow {
        rate,
        notch,
        overshoot_pct: 100.0 * (peak - final_um) / size,
        ringing_pct: 100.0 * ringing / size,
        trace: x
            .iter()
            .enumerate()
            .take((0.0015 * rate) as usize)
            .map(|(k, &v)| (k as f64 * 1e3 / rate, v))
            .collect(),
    })
}

/// Runs the whole study.
pub fn run(options: &ClosedLoopOptions) -> Result<ClosedLoopReport> {
    if options.rates.is_empty()
        || options
            .rates
            .iter()
            .any(|&r| !(RESONANCE_HZ / 0.49..=200_000.0).contains(&r))
    {
        return Err(anyhow!(
            "control rates must lie within {:.0} … 200 000 Hz (the notch at {RESONANCE_HZ} Hz \
             needs it below Nyquist)",
            RESONANCE_HZ / 0.49
        ));
    }
    if options.sine_cycles < 4 || options.triangle_cycles < 2 {
        return Err(anyhow!(
            "at least 4 sine cycles and 2 triangle cycles are needed"
        ));
    }
    let mut report = ClosedLoopReport::default();
    let mut panels = Vec::new();
    for &rate in &options.rates {
        let model = identify_model(rate, options)?;
        // `tune` on the stage: the gains it picks, the resonance it measures.
        let tuned = match (options.gains, options.preview) {
            (Gains::Fixed, false) => None,
            _ => Some(tune_at(rate)?),
        };
        let feedback = match (options.gains, &tuned) {
            (Gains::Tuned, Some(t)) => feedback_from(t, &model),
            _ => feedback_settings(rate, true),
        };
        report.feedback.push((rate, feedback));
        let preview = match tuned.as_ref().filter(|_| options.preview) {
            Some(t) => {
                let p = &t.fit.plant;
                report.resonance.push((rate, p.resonance_hz, p.zeta));
                Some(PreviewDesign {
                    frequency_hz: p.resonance_hz,
                    damping: p.zeta,
                })
            }
            None => None,
        };
        for shape in [Shape::Triangle, Shape::Sine] {
            for c in Configuration4::ALL {
                report.tracking.push(track_with(
                    rate, options, &model, shape, c, &feedback, None,
                )?);
            }
            // The feedforward's rows again, with the preview: feedback alone has no compensator
            // to give the shaped setpoints to.
            if let Some(p) = preview {
                for c in [Configuration4::Feedforward, Configuration4::Both] {
                    report.tracking.push(track_with(
                        rate,
                        options,
                        &model,
                        shape,
                        c,
                        &feedback,
                        Some(p),
                    )?);
                }
            }
        }
        let mut series = Vec::new();
        for (notch, color) in [(false, RED), (true, BLUE)] {
            let gains = FeedbackSettings {
                notch: if notch { feedback.notch } else { None },
                ..feedback
            };
            let mut row = step_with(rate, options, &model, &gains)?;
            row.notch = notch;
            series.push(Series {
                label: if notch { "with notch" } else { "without notch" }.into(),
                points: row.trace.clone(),
                color,
            });
            report.steps.push(row);
        }
        panels.push(Panel {
            caption: format!("step 30 → 70 % of the stroke, {:.0} kHz", rate / 1e3),
            x_label: "time after the step [ms]".into(),
            y_label: "stage displacement [µm]".into(),
            series,
        });
    }
    if let Some(dir) = &options.out_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let png = dir.join("closed-loop-step.png");
        draw_panels(
            &png,
            "Closed-loop step (feedforward + feedback), with and without the notch",
            &panels,
            panels.len().min(2),
        )?;
        report.figures.push(png);
    }
    Ok(report)
}

/// Prints the table and the step figures.
pub fn print(report: &ClosedLoopReport, out: &mut impl std::io::Write) -> std::io::Result<()> {
    for (rate, f) in &report.feedback {
        writeln!(
            out,
            "feedback at {:.0} kHz: kp {:.4}, ki {:.0} /s, notch {}",
            rate / 1e3,
            f.kp,
            f.ki,
            match &f.notch {
                Some(n) => format!(
                    "{:.0} Hz, Q {:.2}, depth {:.2}",
                    n.frequency_hz, n.q, n.depth
                ),
                None => "none".into(),
            }
        )?;
    }
    for (rate, hz, zeta) in &report.resonance {
        writeln!(
            out,
            "resonance at {:.0} kHz, as `tune` measures it (the preview's): {hz:.0} Hz, damping ratio {zeta:.4}",
            rate / 1e3
        )?;
    }
    writeln!(
        out,
        "Tracking error over 10–90 % of the stroke (% of the commanded stroke)"
    )?;
    writeln!(
        out,
        "| rate | waveform | configuration | max % | RMS % | drift ticks |"
    )?;
    writeln!(out, "|---|---|---|---:|---:|---:|")?;
    for r in &report.tracking {
        writeln!(
            out,
            "| {:.0} kHz | {} | {} | {:.2} | {:.2} | {} |",
            r.rate / 1e3,
            r.waveform,
            format_args!(
                "{}{}",
                r.configuration.label(),
                if r.preview { " + preview" } else { "" }
            ),
            r.max_pct,
            r.rms_pct,
            r.drift_ticks_after_start
                .map_or("–".to_string(), |n| n.to_string())
        )?;
    }
    writeln!(
        out,
        "\nfeedforward + feedback beats both others on every row (max and RMS): {}",
        if report.both_beats_the_others_everywhere() {
            "yes"
        } else {
            "NO"
        }
    )?;
    writeln!(
        out,
        "\nStep 30 → 70 % of the stroke, feedforward + feedback (% of the step)"
    )?;
    writeln!(
        out,
        "| rate | notch | overshoot % | ringing 1–3 ms after % |"
    )?;
    writeln!(out, "|---|---|---:|---:|")?;
    for s in &report.steps {
        writeln!(
            out,
            "| {:.0} kHz | {} | {:.2} | {:.3} |",
            s.rate / 1e3,
            if s.notch { "on" } else { "off" },
            s.overshoot_pct,
            s.ringing_pct
        )?;
    }
    for f in &report.figures {
        writeln!(out, "\nwrote {}", f.display())?;
    }
    Ok(())
}
