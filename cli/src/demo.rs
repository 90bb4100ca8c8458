//! The main job: the first paper's study, on the simulated board and stage.
//!
//! For each configuration (unidirectional, differential):
//!
//! 1. **Excite.** The board's own control tick, in bypass, plays the built-in waveform
//!    generator's 750 Hz sine through the emulated 16-bit DACs and 150 V amplifiers:
//!    `u_l = 70 + 70 sin(2π·750 t)` V (and `u_r = 70 − 70 sin` in the differential
//!    configuration), as in the paper. The stage's displacement is recorded.
//! 2. **Identify** Duhem and P–I (N = 9, uniform thresholds) on the first half of the record and
//!    score them on the second: the rows of the paper's Tables 1 and 2 (modelling error, % of
//!    the output range).
//! 3. **Track** a 750 Hz sine over 10–90 % of the stroke with each compensator — none (bypass),
//!    inverse P–I, inverse Duhem — running in the same tick, and report the tracking error.
//! 4. **Plot** the hysteresis loops of both configurations and the tracking error over one
//!    cycle (PNG).

use crate::plot::{draw_panels, Panel, Series};
use anyhow::{anyhow, Context, Result};
use hal_sim::plant::Configuration as StageConfiguration;
use hal_sim::sim_board::{BoardConfig, ExternalBoard, SimBoard};
use indicatif::{ProgressBar, ProgressStyle};
use plotters::style::{RGBColor, BLACK, BLUE, RED};
use std::path::PathBuf;
use twinstack::board::Hardware;
use twinstack::config::settings::{Mode, Model, Settings};
use twinstack::control::drive::{Configuration, DriveSettings, SafeState};
use twinstack::control::{ControlConfig, Controller};
use twinstack::fixed_point::{signal_from_f64, signal_to_f64};
use twinstack::sources::waveform::{Shape, WaveformGenerator};
use twinstack::Scaling;
use twinstack_identify::identification::{
    identify, score::score, IdentifyOptions, ModelKind, ThresholdSpread,
};
use twinstack_identify::stage_model::{between_samples, Hysteresis, StageModel};
use twinstack_link::measured_data::MeasuredData;

/// What the demo runs.
#[derive(Clone, Debug)]
pub struct DemoOptions {
    /// Control rate, Hz.
    pub control_rate: f64,
    /// Excitation and tracking frequency, Hz.
    pub frequency: f64,
    /// Cycles per run (identification uses the first half, scores the second).
    pub cycles: usize,
    /// Where the PNG figures go.
    pub out_dir: PathBuf,
    /// Show progress bars.
    pub progress: bool,
}

impl Default for DemoOptions {
    fn default() -> Self {
        Self {
            control_rate: 50_000.0,
            frequency: 750.0,
            cycles: 40,
            out_dir: PathBuf::from("out"),
            progress: true,
        }
    }
}

/// One row of the modelling tables (the paper's Tables 1 and 2).
#[derive(Clone, Debug)]
pub struct ModellingRow {
    /// `differential` or `unidirectional`.
    pub configuration: &'static str,
    /// `Duhem` or `P–I, N = 9`.
    pub model: &'static str,
    /// Largest error on the held-out half, % of the output range.
    pub max_pct: f64,
    /// RMS error on the held-out half, % of the output range.
    pub rms_pct: f64,
}

/// One row of the tracking table.
#[derive(Clone, Debug)]
pub struct TrackingRow {
    /// `differential` or `unidirectional`.
    pub configuration: &'static str,
    /// `none`, `inverse P–I` or `inverse Duhem`.
    pub compensator: &'static str,
    /// Largest tracking error after the first cycles, % of the commanded stroke.
    pub max_pct: f64,
    /// RMS tracking error, % of the commanded stroke.
    pub rms_pct: f64,
}

/// Everything the demo found.
#[derive(Clone, Debug, Default)]
pub struct DemoReport {
    /// Modelling-error rows.
    pub modelling: Vec<ModellingRow>,
    /// Tracking-error rows.
    pub tracking: Vec<TrackingRow>,
    /// Figures written.
    pub figures: Vec<PathBuf>,
    /// The excitation's and the tracked sine's frequency, Hz.
    pub frequency_hz: f64,
}

impl DemoReport {
    /// The tracking row of `configuration` and `compensator`.
    pub fn tracking(&self, configuration: &str, compensator: &str) -> Option<&TrackingRow> {
        self.tracking
            .iter()
            .find(|r| r.configuration == configuration && r.compensator == compensator)
    }
}

/// A record of one simulated run: time, left-stack drive (V), stage displacement (µm), setpoint.
struct Record {
    t: Vec<f64>,
    u: Vec<f64>,
    x: Vec<f64>,
    desired: Vec<f64>,
}

fn name(c: StageConfiguration) -> &'static str {
    match c {
        StageConfiguration::Differential => "differential",
        StageConfiguration::Unidirectional => "unidirectional",
    }
}

/// The paper's board at `control_rate`: 150 V amplifiers on the 16-bit DACs, the sensor on
/// the 16-bit ADC.
fn hardware(control_rate: f64) -> Hardware {
    Hardware {
        amplifier_full_scale: 150.0,
        dac_full_scale: 65535,
        sensor_adc_bits: Some(16),
        control_rate_hz: control_rate,
    }
}

fn drive_settings(c: StageConfiguration) -> DriveSettings {
    DriveSettings {
        configuration: match c {
            StageConfiguration::Differential => Configuration::Differential,
            StageConfiguration::Unidirectional => Configuration::Unidirectional,
        },
        bias: 70.0,
        // The right stack idles here in the unidirectional configuration.
        min_voltage: 0.0,
        max_voltage: 140.0,
        // The amplifier's own limit is 1 V/µs; the controller's sits just below it.
        slew_rate: 0.9e6,
        safe_state: SafeState::Bias,
    }
}

fn progress(options: &DemoOptions, len: u64, message: String) -> ProgressBar {
    if !options.progress {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(len);
    bar.set_style(
        ProgressStyle::with_template("{msg:<44} [{bar:30}] {pos}/{len} ticks")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    bar.set_message(message);
    bar
}

/// Runs `config` on a fresh board for `ticks`, the setpoints coming from `setpoint(k)`.
fn simulate(
    options: &DemoOptions,
    stage: StageConfiguration,
    config: ControlConfig,
    ticks: usize,
    label: String,
    mut setpoint: impl FnMut(usize) -> i32,
    output_of: impl Fn(i32) -> f64,
) -> Result<Record> {
    let mut board: ExternalBoard = SimBoard::external(&BoardConfig::paper(stage))
        .map_err(|e| anyhow!("simulated board: {e}"))?;
    let mut controller = Controller::new(config);
    let bar = progress(options, ticks as u64, label);
    let dt = 1.0 / options.control_rate;
    let mut rec = Record {
        t: Vec::with_capacity(ticks),
        u: Vec::with_capacity(ticks),
        x: Vec::with_capacity(ticks),
        desired: Vec::with_capacity(ticks),
    };
    for k in 0..ticks {
        let sp = setpoint(k);
        // Sample k: the stage as the tick starts (the end of the hold before, where a sensor
        // reads it), then the drive the tick gives it to hold.
        rec.x.push(board.plant().stage_um());
        controller.tick_board(Some(sp), &mut board);
        rec.t.push(k as f64 * dt);
        rec.u.push(board.amplifier_volts()[0]);
        rec.desired.push(output_of(sp));
        if k % 1024 == 0 {
            bar.set_position(k as u64);
        }
    }
    bar.finish_and_clear();
    // Each setpoint is for the middle of its drive's hold, so the target of the stage's
    // sample k, the end of hold k − 1, lies between setpoints k − 1 and k
    // (`twinstack::control::instant`).
    let between = between_samples(&rec.desired);
    rec.desired = (0..between.len())
        .map(|k| between[k.saturating_sub(1)])
        .collect();
    Ok(rec)
}

/// Step 1: the paper's excitation through the bypassed tick.
fn excite(options: &DemoOptions, stage: StageConfiguration, ticks: usize) -> Result<Record> {
    // Bypass over the input range 0…140 V: setpoint ±1 is u_l = 70 ± 70 V.
    let scaling = Scaling::new(0.0, 140.0, -1.0, 1.0)?;
    let settings = Settings {
        ranges: scaling,
        compensator: None,
        observer: None,
        drive: drive_settings(stage),
        sensor: None,
        feedback: None,
        mode: Mode::Bypass,
        creep: None,
        shaping: None,
        preview: None,
        output_map: None,
    };
    let config = settings
        .build(&hardware(options.control_rate))
        .map_err(|e| anyhow!("{e}"))?;
    let mut wave = WaveformGenerator::new(
        Shape::Sine,
        0,
        signal_from_f64(1.0),
        options.frequency,
        options.control_rate,
    )
    .map_err(|e| anyhow!("{e:?}"))?;
    simulate(
        options,
        stage,
        config,
        ticks,
        format!("{}: {} Hz excitation", name(stage), options.frequency),
        |_| wave.next_sample(),
        signal_to_f64,
    )
}

/// Step 2: identify `kind` on the first half, score on the second.
fn identify_on(rec: &Record, kind: ModelKind, stage: StageConfiguration) -> Result<StageModel> {
    let data = MeasuredData {
        path: PathBuf::from(format!("simulated {} stage", name(stage))),
        t: rec.t.clone(),
        u: Some(rec.u.clone()),
        x: Some(rec.x.clone()),
    };
    let mut opts = IdentifyOptions::new(kind, rec.t[rec.t.len() / 2]);
    opts.operators = 9;
    opts.thresholds = ThresholdSpread::Uniform;
    // The drive of sample k is held from the stage's sample k to its sample k + 1: the model
    // maps it to the middle of that hold, half a sample on (see `identify`'s half lag).
    opts.lag = Some(0);
    opts.half_lag = true;
    Ok(identify(&data, &opts)
        .with_context(|| format!("identifying {kind:?} on the {} stage", name(stage)))?
        .model)
}

/// Step 3: track a sine over 10–90 % of the stroke with `model` as the compensator (or none).
fn track(
    options: &DemoOptions,
    stage: StageConfiguration,
    model: &StageModel,
    compensate: bool,
    ticks: usize,
    stroke: (f64, f64),
) -> Result<Record> {
    let hysteresis = match &model.hysteresis {
        Hysteresis::Pi(p) => Model::PrandtlIshlinskii(p.clone()),
        Hysteresis::Duhem(p) => Model::Duhem(*p),
        Hysteresis::GeneralisedPi(p) => Model::GeneralisedPi(p.clone()),
        Hysteresis::BoucWen(p) => Model::BoucWen(*p),
    };
    // Open loop runs the inverse of the model, the observer the model itself (so the
    // compensator starts consistent with where the observer puts the stage); the bypassed run
    // carries the same models (the compensator steps in every mode, its output unused).
    let settings = Settings {
        ranges: model.scaling,
        compensator: Some(hysteresis.clone()),
        observer: Some(hysteresis),
        drive: drive_settings(stage),
        sensor: None,
        feedback: None,
        mode: if compensate {
            Mode::OpenLoop
        } else {
            Mode::Bypass
        },
        creep: model.creep.clone(),
        shaping: None,
        preview: None,
        output_map: model.output_map.clone(),
    };
    let config = settings
        .build(&hardware(options.control_rate))
        .map_err(|e| anyhow!("{e}"))?;
    let s = model.scaling;
    let (lo, hi) = stroke;
    let centre = s.output_to_norm(0.5 * (lo + hi));
    let amplitude = 0.4 * (hi - lo) / s.output_half_span();
    let mut wave = WaveformGenerator::new(
        Shape::Sine,
        signal_from_f64(centre),
        signal_from_f64(amplitude),
        options.frequency,
        options.control_rate,
    )
    .map_err(|e| anyhow!("tracking waveform: {e:?}"))?;
    let label = format!(
        "{}: tracking, {}",
        name(stage),
        if compensate {
            "compensated"
        } else {
            "no compensation"
        }
    );
    simulate(
        options,
        stage,
        config,
        ticks,
        label,
        |_| wave.next_sample(),
        |q| s.norm_to_output(signal_to_f64(q)),
    )
}

/// Tracking error of `rec` over its last `cycles − 2` cycles, % of the commanded stroke.
fn tracking_error(rec: &Record, ticks_per_cycle: usize) -> (f64, f64) {
    let from = (2 * ticks_per_cycle).min(rec.x.len());
    // The stage follows with the plant's small phase lag; compare like with like.
    let fig = score(&rec.desired, &rec.x, from..rec.x.len());
    fig.map_or((f64::NAN, f64::NAN), |f| (f.max_pct, f.rms_pct))
}

/// Runs the whole study.
pub fn run(options: &DemoOptions) -> Result<DemoReport> {
    if !(options.control_rate > 0.0 && options.frequency > 0.0) || options.cycles < 4 {
        return Err(anyhow!(
            "control rate and frequency must be positive and cycles at least 4"
        ));
    }
    let ticks_per_cycle = (options.control_rate / options.frequency).round() as usize;
    let ticks = ticks_per_cycle * options.cycles;
    let mut report = DemoReport {
        frequency_hz: options.frequency,
        ..DemoReport::default()
    };
    let mut loops = Vec::new();
    let mut error_panels = Vec::new();
    for stage in [
        StageConfiguration::Unidirectional,
        StageConfiguration::Differential,
    ] {
        let excitation = excite(options, stage, ticks)?;
        let held = excitation.t.len() / 2;
        let mut models = Vec::new();
        for (kind, label) in [(ModelKind::Duhem, "Duhem"), (ModelKind::Pi, "P–I, N = 9")] {
            let model = identify_on(&excitation, kind, stage)?;
            let predicted = model.predict(&excitation.t, &excitation.u)?;
            let fig = score(&excitation.x, &predicted, held..excitation.x.len())
                .ok_or_else(|| anyhow!("no output range to score against"))?;
            report.modelling.push(ModellingRow {
                configuration: name(stage),
                model: label,
                max_pct: fig.max_pct,
                rms_pct: fig.rms_pct,
            });
            models.push((label, model, predicted));
        }
        let (lo, hi) = excitation.x[held..]
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
                (l.min(v), h.max(v))
            });
        let last_cycle = excitation.x.len() - ticks_per_cycle..excitation.x.len();
        let mut loop_series = vec![Series {
            label: "simulated stage".into(),
            points: last_cycle
                .clone()
                .map(|k| (excitation.u[k], excitation.x[k]))
                .collect(),
            color: BLUE,
        }];
        for ((label, _, predicted), color) in models.iter().zip([RED, RGBColor(0, 150, 0)]) {
            loop_series.push(Series {
                label: format!("{label} model"),
                points: last_cycle
                    .clone()
                    .map(|k| (excitation.u[k], predicted[k]))
                    .collect(),
                color,
            });
        }
        loops.push(Panel {
            caption: format!("{} stage, {} Hz, 70 ± 70 V", name(stage), options.frequency),
            x_label: "left-stack drive u_l [V]".into(),
            y_label: "stage displacement [µm]".into(),
            series: loop_series,
        });

        // Tracking: the P–I model's scaling is the reference for the stroke of both.
        let (_, pi_model, _) = &models[1];
        let (_, duhem_model, _) = &models[0];
        let runs = [
            ("none", pi_model, false, BLACK),
            ("inverse P–I", pi_model, true, RED),
            ("inverse Duhem", duhem_model, true, RGBColor(0, 150, 0)),
        ];
        let mut series = Vec::new();
        for (label, model, compensate, color) in runs {
            let rec = track(options, stage, model, compensate, ticks, (lo, hi))?;
            let (max_pct, rms_pct) = tracking_error(&rec, ticks_per_cycle);
            report.tracking.push(TrackingRow {
                configuration: name(stage),
                compensator: label,
                max_pct,
                rms_pct,
            });
            let n = rec.x.len();
            series.push(Series {
                label: label.into(),
                points: (n - ticks_per_cycle..n)
                    .map(|k| (rec.t[k] * 1e3, rec.x[k] - rec.desired[k]))
                    .collect(),
                color,
            });
        }
        error_panels.push(Panel {
            caption: format!("{} stage: tracking error over one cycle", name(stage)),
            x_label: "time [ms]".into(),
            y_label: "displacement − setpoint [µm]".into(),
            series,
        });
    }
    std::fs::create_dir_all(&options.out_dir)
        .with_context(|| format!("creating {}", options.out_dir.display()))?;
    let loops_png = options.out_dir.join("demo-loops.png");
    draw_panels(
        &loops_png,
        "Hysteresis loops: simulated stage and identified models",
        &loops,
        2,
    )?;
    let errors_png = options.out_dir.join("demo-tracking-error.png");
    draw_panels(
        &errors_png,
        &format!(
            "Tracking a {} Hz sine over 10–90 % of the stroke",
            options.frequency
        ),
        &error_panels,
        2,
    )?;
    report.figures = vec![loops_png, errors_png];
    Ok(report)
}

/// Prints the report as the paper's tables (Markdown tables: the book's results page is this
/// output, written by `cargo xtask figures`).
pub fn print(report: &DemoReport, out: &mut impl std::io::Write) -> std::io::Result<()> {
    writeln!(
        out,
        "Modelling error on the held-out half (% of the output range)"
    )?;
    writeln!(out, "| configuration | model | max % | RMS % |")?;
    writeln!(out, "|---|---|---:|---:|")?;
    for r in &report.modelling {
        writeln!(
            out,
            "| {} | {} | {:.2} | {:.2} |",
            r.configuration, r.model, r.max_pct, r.rms_pct
        )?;
    }
    writeln!(out)?;
    writeln!(
        out,
        "Tracking a {} Hz sine over 10–90 % of the stroke (% of the commanded stroke)",
        report.frequency_hz
    )?;
    writeln!(
        out,
        "| configuration | compensator | max % | RMS % | RMS vs none |"
    )?;
    writeln!(out, "|---|---|---:|---:|---:|")?;
    for r in &report.tracking {
        let none = report
            .tracking(r.configuration, "none")
            .map_or(f64::NAN, |n| n.rms_pct);
        writeln!(
            out,
            "| {} | {} | {:.2} | {:.2} | {:.1}× |",
            r.configuration,
            r.compensator,
            r.max_pct,
            r.rms_pct,
            none / r.rms_pct
        )?;
    }
    writeln!(out)?;
    for f in &report.figures {
        writeln!(out, "wrote {}", f.display())?;
    }
    Ok(())
}
