//! Learning feedforward (iterative learning control) on the simulated differential stage, in
//! process: the library's [`ControlLoop`] with its learning ([`twinstack::services::learning`]) on the
//! closed-loop study's board (16-bit DAC8562 and ADS8689, 2 nm rms sensor noise, 1 mV
//! amplifier noise, 0.9 V/µs slew) and its identified P–I model (N = 16).
//!
//! 1. **Feedforward alone**: the inverse P–I in open loop plays the waveform (10–90 % of the
//!    stroke) for a few periods; the last are scored (stage against setpoint, % of the
//!    commanded stroke).
//! 2. **Learning**: the same tick with the learning on; after every period the low-priority
//!    task ([`twinstack::services::learning::service`]) takes the sensor's errors and posts the next
//!    table. Each period is scored from the stage itself: the learning curve.
//! 3. **Replay, sensor off**: the table is frozen and stored; a fresh board and controller
//!    whose settings have **no sensor** recall it and play it open loop.
//!
//! Deterministic (seeded noise, simulated time): the same options give the same figures.

use crate::closed_loop::{
    board, hardware, identify_model, sensor_settings, settings, ClosedLoopOptions, Configuration4,
};
use crate::plot::{draw_panels, Panel, Series};
use anyhow::{anyhow, bail, Context, Result};
use hal_sim::sim_board::ExternalBoard;
use plotters::style::{BLACK, BLUE, RED};
use rtic_core::Exclusive;
use std::path::PathBuf;
use twinstack::config::settings::{NotchDesign, Settings};
use twinstack::control::Controller;
use twinstack::control_loop::{ControlLoop, SetpointQueue};
use twinstack::fixed_point::{signal_from_f64, signal_to_f64};
use twinstack::services::learning::{
    configure, post_table, service, LearnSettings, LearnState, LearnTask, MAX_BINS,
};
use twinstack::services::snapshot::SnapshotRing;
use twinstack::sources::waveform::{Shape, WaveformGenerator};
use twinstack_identify::identification::score::score;
use twinstack_identify::stage_model::{between_periodic, StageModel};

/// The waveform to learn: a shape and a frequency.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Motion {
    /// Sine or triangle.
    pub shape: Shape,
    /// Frequency, Hz.
    pub frequency_hz: f64,
}

impl Motion {
    /// `sine:750` or `triangle:200`.
    pub fn label(&self) -> String {
        let shape = match self.shape {
            Shape::Sine => "sine",
            Shape::Triangle => "triangle",
        };
        format!("{shape}:{}", self.frequency_hz)
    }
}

impl std::str::FromStr for Motion {
    type Err = anyhow::Error;

    /// `sine:HZ` or `triangle:HZ`.
    fn from_str(s: &str) -> Result<Self> {
        let (shape, f) = s
            .split_once(':')
            .ok_or_else(|| anyhow!("waveform `{s}`: expected sine:HZ or triangle:HZ"))?;
        let shape = match shape {
            "sine" => Shape::Sine,
            "triangle" => Shape::Triangle,
            other => bail!("waveform shape `{other}`: expected sine or triangle"),
        };
        let frequency_hz: f64 = f
            .parse()
            .map_err(|_| anyhow!("waveform frequency `{f}`: not a number"))?;
        if !(frequency_hz.is_finite() && frequency_hz > 0.0) {
            bail!("waveform frequency {frequency_hz} Hz: must be a positive number");
        }
        Ok(Self {
            shape,
            frequency_hz,
        })
    }
}

/// The learning period of `frequency_hz` at `rate_hz`: the fewest ticks that hold a whole
/// number of cycles (3 cycles = 200 ticks for 750 Hz at 50 kHz), or why there is none within
/// [`MAX_BINS`] ticks.
pub fn period_ticks(frequency_hz: f64, rate_hz: f64) -> Result<u16> {
    let per_cycle = rate_hz / frequency_hz;
    for cycles in 1..=MAX_BINS {
        let ticks = per_cycle * cycles as f64;
        if ticks > MAX_BINS as f64 + 0.5 {
            break;
        }
        if (ticks - ticks.round()).abs() < 1e-6 * ticks && ticks.round() >= 2.0 {
            return Ok(ticks.round() as u16);
        }
    }
    bail!(
        "{frequency_hz} Hz at {rate_hz} Hz: no whole number of cycles fits {MAX_BINS} ticks \
         (the learning table's bins); choose a frequency that divides the control rate more evenly"
    )
}

/// What the study runs.
#[derive(Clone, Debug)]
pub struct LearnOptions {
    /// Control rate, Hz.
    pub rate: f64,
    /// The motion.
    pub motion: Motion,
    /// Learning periods (the learning curve's length).
    pub periods: usize,
    /// Position sensor noise, µm rms.
    pub sensor_noise_um: f64,
    /// Learning gain.
    pub gain: f64,
    /// Robustness filter corner, Hz.
    pub cutoff_hz: f64,
    /// Phase lead, ticks.
    pub lead_ticks: u16,
    /// Input shaping: the notch on the feedforward ([`Settings::shaping`]); `None`: none.
    /// With it, the inverse P–I feedforward alone is also run without it: the baseline.
    pub shaping: Option<NotchDesign>,
    /// Where the PNG goes (`None`: no figure).
    pub out_dir: Option<PathBuf>,
}

impl LearnOptions {
    /// The defaults for `motion` at 50 kHz: 50 periods, 2 nm sensor noise, gain 0.3, no
    /// lead (the error is already aligned with the sensor's two ticks of delay, and the stage
    /// answers within the tick it is driven), the robustness filter's corner at 18 kHz: the
    /// highest that stays stable below the 21.8 kHz resonance (chosen on this stage by a
    /// sweep of gain 0.25–0.6, corner 8–20 kHz, lead 0–4: higher gains or corners, or any
    /// lead, diverge or ring).
    pub fn new(motion: Motion) -> Self {
        Self {
            rate: 50_000.0,
            motion,
            periods: 50,
            sensor_noise_um: 0.002,
            gain: 0.3,
            cutoff_hz: 18_000.0,
            lead_ticks: 0,
            shaping: None,
            out_dir: Some(PathBuf::from("out")),
        }
    }

    /// The defaults for `motion` with input shaping ([`shaped`]: the notch
    /// [`shaping_for`] places on the resonance `twinstack tune` fits on this stage, 21 807 Hz,
    /// ζ = 0.01729) and the learning's corner raised to 23 kHz, above the resonance: the shaped
    /// stage no longer rings there, and the learning then removes what is left in that band
    /// too (chosen by a sweep of Q 0.3–0.7 × corner 20–24.5 kHz × gain 0.3, 0.5: gain 0.5
    /// diverges, Q 0.7 is worse; 24 kHz does a little better with the notch exactly on the
    /// resonance but diverges with it 0.5 % off, 23 kHz stands ±0.5 %, 22 kHz ±2 % but leaves
    /// the 750 Hz sine at 19.5×).
    ///
    /// ```
    /// use twinstack_cli::learn::LearnOptions;
    /// let o = LearnOptions::shaped("sine:750".parse().unwrap());
    /// assert_eq!(o.cutoff_hz, 23_000.0);
    /// assert_eq!(o.shaping.unwrap().frequency_hz, 21_807.0);
    /// ```
    pub fn shaped(motion: Motion) -> Self {
        Self {
            cutoff_hz: SHAPED_CUTOFF_HZ,
            shaping: Some(shaped()),
            ..Self::new(motion)
        }
    }

    /// The learning settings these options give for `period_ticks`.
    pub fn learn_settings(&self, period_ticks: u16) -> LearnSettings {
        LearnSettings {
            period_ticks,
            gain: self.gain,
            cutoff_hz: self.cutoff_hz,
            lead_ticks: self.lead_ticks,
            limit: 0.25,
        }
    }
}

/// The learning's robustness corner with input shaping, Hz.
pub const SHAPED_CUTOFF_HZ: f64 = 23_000.0;

// The input shaping for a resonance (what `twinstack tune` fits, and reports in its JSON):
// the tuning library's.
pub use twinstack_identify::tune::shaping_for;

/// The simulated differential stage's shaping, from its tuned fit at 50 kHz (21 807 Hz,
/// ζ = 0.01729; docs/src/results/tuning.md).
pub fn shaped() -> NotchDesign {
    shaping_for(21_807.0, 0.01729)
}

/// One period's tracking error, % of the commanded stroke.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct PeriodFigures {
    /// Largest |error|.
    pub max_pct: f64,
    /// RMS error.
    pub rms_pct: f64,
    /// RMS of the error's content below [`RESONANCE_BAND_HZ`] (what the learning acts on).
    pub below_band_rms_pct: f64,
    /// RMS of the error's content from [`RESONANCE_BAND_HZ`] to Nyquist: the ringing of the
    /// stage's 21.8 kHz resonance (ζ ≈ 0.017).
    pub band_rms_pct: f64,
}

/// Where the resonance band starts, Hz: the error above it is the 21.8 kHz resonance's
/// ringing, which the learning (its filter's corner below the resonance) does not act on.
pub const RESONANCE_BAND_HZ: f64 = 15_000.0;

/// The RMS of `e`'s content below and above `split_hz` (one period of `e` at `rate_hz`, by
/// its discrete Fourier transform; Parseval: the two add up to the RMS in quadrature).
pub fn band_rms(e: &[f64], rate_hz: f64, split_hz: f64) -> (f64, f64) {
    let n = e.len();
    if n == 0 {
        return (0.0, 0.0);
    }
    let (mut low, mut high) = (0.0, 0.0);
    for k in 0..n {
        let (mut re, mut im) = (0.0, 0.0);
        for (i, &x) in e.iter().enumerate() {
            let phase = -2.0 * std::f64::consts::PI * (k * i % n) as f64 / n as f64;
            re += x * phase.cos();
            im += x * phase.sin();
        }
        let power = (re * re + im * im) / (n * n) as f64;
        // Bin k and its mirror n − k are the same frequency.
        let f = k.min(n - k) as f64 * rate_hz / n as f64;
        if f < split_hz {
            low += power;
        } else {
            high += power;
        }
    }
    (low.sqrt(), high.sqrt())
}

/// Everything the study found.
#[derive(Clone, Debug, serde::Serialize)]
pub struct LearnReport {
    /// `sine:750`, `triangle:200`.
    pub waveform: String,
    /// Control rate, Hz.
    pub rate_hz: f64,
    /// The learning period, ticks.
    pub period_ticks: u16,
    /// The inverse-P–I feedforward alone (open loop, without shaping: the goal's baseline),
    /// over its last periods.
    pub feedforward: PeriodFigures,
    /// The input shaping, if any.
    pub shaping: Option<NotchDesign>,
    /// The learning's gain and robustness corner (Hz).
    pub gain: f64,
    /// The robustness filter's corner, Hz.
    pub cutoff_hz: f64,
    /// With shaping: the shaped feedforward alone (before learning), over its last periods.
    pub shaped_feedforward: Option<PeriodFigures>,
    /// Each learning period, scored from the stage (the learning curve).
    pub curve: Vec<PeriodFigures>,
    /// The last learning period.
    pub learned: PeriodFigures,
    /// The frozen table replayed open loop with the sensor off (a fresh board), over its last
    /// periods.
    pub replay: PeriodFigures,
    /// `feedforward.rms / learned.rms` (against the unshaped feedforward alone).
    pub rms_reduction: f64,
    /// Tables posted by the task.
    pub updates: u32,
    /// Periods the task missed.
    pub missed: u32,
    /// Times the divergence guard stopped the learning
    /// (`twinstack::services::learning::DIVERGENCE_FACTOR`: switched off, the feedforward alone
    /// plays).
    pub guard_stops: u32,
    /// Figures written.
    pub figures: Vec<PathBuf>,
}

impl LearnReport {
    /// The learning's goals: RMS ≥ 20× lower than feedforward alone, max ≤ 0.1 %, replay
    /// max ≤ 0.2 %.
    pub fn goals(&self) -> [(&'static str, bool); 3] {
        [
            (
                "RMS ≥ 20× lower than feedforward alone",
                self.rms_reduction >= 20.0,
            ),
            ("max ≤ 0.1 % of the stroke", self.learned.max_pct <= 0.1),
            (
                "replay (sensor off) max ≤ 0.2 %",
                self.replay.max_pct <= 0.2,
            ),
        ]
    }
}

/// The loop the study runs: the library's, with the simulator's buffers.
type SimLoop = ControlLoop<Box<Controller>>;

/// A run of the waveform on one board: the loop, the task, the setpoint and the stage.
struct Rig {
    board: ExternalBoard,
    control: SimLoop,
    task: LearnTask,
    queue: Box<SetpointQueue>,
    /// The tick's snapshots (the study records from the stage, not the board's recorder:
    /// they are dropped after each tick).
    snapshots: Box<SnapshotRing>,
    scaling: twinstack::Scaling,
    period: usize,
    rate: f64,
}

impl Rig {
    fn new(options: &LearnOptions, settings: &Settings, period: u16) -> Result<Self> {
        let config = settings
            .build(&hardware(options.rate))
            .map_err(|e| anyhow!("settings refused: {e}"))?;
        let mut control = ControlLoop::new(
            Box::new(Controller::new(config)),
            Box::new(Controller::new(config)),
            options.rate.round() as u32,
        );
        let learn = options
            .learn_settings(period)
            .build(options.rate)
            .map_err(|e| anyhow!("learning settings refused: {e}"))?;
        let mut task = LearnTask::new();
        // The guard's allowance at the sensor's resolution, as the board's command handler
        // sets it.
        task.set_resolution(config.sensor.as_ref().map(|s| s.quantum()));
        configure(&mut task, learn, &mut Exclusive(&mut control));
        Ok(Self {
            board: board(options.rate, options.sensor_noise_um)?,
            control,
            task,
            queue: Box::new(SetpointQueue::new()),
            snapshots: Box::new(SnapshotRing::new()),
            scaling: settings.ranges,
            period: period as usize,
            rate: options.rate,
        })
    }

    /// Starts the waveform over 10–90 % of the stroke.
    fn play(&mut self, options: &LearnOptions) -> Result<()> {
        let s = self.scaling;
        let (lo, hi) = (s.output_min, s.output_max);
        let centre = s.output_to_norm(0.5 * (lo + hi));
        let amplitude = 0.4 * (hi - lo) / s.output_half_span();
        let wave = WaveformGenerator::new(
            options.motion.shape,
            signal_from_f64(centre),
            signal_from_f64(amplitude),
            options.motion.frequency_hz,
            options.rate,
        )
        .map_err(|e| anyhow!("waveform: {e:?}"))?;
        self.control.play(wave);
        Ok(())
    }

    /// [`SETTLE`] periods run, then [`SCORED`] periods scored and pooled.
    fn scored(&mut self) -> Result<PeriodFigures> {
        let mut scored = Vec::new();
        for k in 0..SETTLE + SCORED {
            let f = self.period()?;
            if k >= SETTLE {
                scored.push(f);
            }
        }
        Ok(pooled(&scored))
    }

    /// Runs one period (the task serving the learning after each tick, as the board's
    /// low-priority task would between ticks) and scores it against the stage.
    fn period(&mut self) -> Result<PeriodFigures> {
        let (mut desired, mut x) = (Vec::new(), Vec::new());
        for _ in 0..self.period {
            let (_, mut consumer) = self.queue.split();
            let (mut dac, mut adc) = self.board.split();
            let (mut snapshots, mut dropped) = self.snapshots.split();
            self.control
                .tick(&mut consumer, &mut snapshots, &mut adc, &mut dac);
            while dropped.dequeue().is_some() {}
            service(&mut self.task, &mut Exclusive(&mut self.control));
            desired.push(
                self.scaling
                    .norm_to_output(signal_to_f64(self.control.controller().setpoint())),
            );
            // The stage at the hold's end, where the sensor reads it.
            x.push(self.board.plant().stage_um());
        }
        // Each setpoint is for the middle of its drive's hold: the target at a hold's end lies
        // between two (the rule the tick's learning and feedback take it by,
        // `twinstack::control::instant`), the waveform periodic over the period.
        let desired = between_periodic(&desired);
        let c = self.control.counters();
        if c.adc_errors + c.dac_errors > 0 {
            bail!("converter errors in the simulated run: {c:?}");
        }
        let f = score(&desired, &x, 0..desired.len())
            .ok_or_else(|| anyhow!("nothing to score in a period"))?;
        let (lo, hi) = desired
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
                (l.min(v), h.max(v))
            });
        let span = hi - lo;
        let e: Vec<f64> = x.iter().zip(&desired).map(|(x, d)| x - d).collect();
        let (below, band) = band_rms(&e, self.rate, RESONANCE_BAND_HZ);
        Ok(PeriodFigures {
            max_pct: f.max_pct,
            rms_pct: f.rms_pct,
            below_band_rms_pct: 100.0 * below / span,
            band_rms_pct: 100.0 * band / span,
        })
    }
}

/// The worst max and the RMS of RMS over `periods`.
fn pooled(periods: &[PeriodFigures]) -> PeriodFigures {
    let n = periods.len().max(1) as f64;
    let rms = |f: fn(&PeriodFigures) -> f64| {
        (periods.iter().map(|p| f(p) * f(p)).sum::<f64>() / n).sqrt()
    };
    PeriodFigures {
        max_pct: periods.iter().map(|p| p.max_pct).fold(0.0, f64::max),
        rms_pct: rms(|p| p.rms_pct),
        below_band_rms_pct: rms(|p| p.below_band_rms_pct),
        band_rms_pct: rms(|p| p.band_rms_pct),
    }
}

/// Periods the feedforward alone and the replay run before they are scored (the stage's
/// hysteresis settles onto its loop), and periods scored.
const SETTLE: usize = 3;
const SCORED: usize = 5;

/// Runs the study with `model` (identified on the same board, [`identify_model`]).
pub fn run_with(options: &LearnOptions, model: &StageModel) -> Result<LearnReport> {
    if options.periods == 0 {
        bail!("at least one learning period is needed");
    }
    let period = period_ticks(options.motion.frequency_hz, options.rate)?;
    let board0 = board(options.rate, options.sensor_noise_um)?;
    let sensor = sensor_settings(&board0);
    let open = Settings {
        shaping: options.shaping,
        ..settings(
            options.rate,
            model,
            sensor,
            Configuration4::Feedforward,
            false,
        )
    };

    // 1 and 2: feedforward alone, then learning, on one board.
    let mut rig = Rig::new(options, &open, period)?;
    rig.play(options)?;
    let ff = rig.scored()?;
    // With shaping, the baseline is the feedforward without it, on a board of its own.
    let (ff, shaped_ff) = if options.shaping.is_some() {
        let plain = Settings {
            shaping: None,
            ..open.clone()
        };
        let mut base = Rig::new(options, &plain, period)?;
        base.play(options)?;
        (base.scored()?, Some(ff))
    } else {
        (ff, None)
    };
    rig.control.set_learning(LearnState::Learning);
    let mut curve = Vec::new();
    for _ in 0..options.periods {
        curve.push(rig.period()?);
    }
    let learned = *curve.last().ok_or_else(|| anyhow!("no learning period"))?;
    // Freeze and store the table.
    rig.control.set_learning(LearnState::Frozen);
    let stored: Vec<i32> = rig.task.table()[..period as usize].to_vec();

    // 3: replay on a fresh board, with the sensor off (no sensor in the settings).
    let blind = Settings {
        sensor: None,
        ..open.clone()
    };
    let mut replay_rig = Rig::new(options, &blind, period)?;
    replay_rig.task.set_table(&stored);
    post_table(&replay_rig.task, &mut Exclusive(&mut replay_rig.control));
    replay_rig.control.set_learning(LearnState::Frozen);
    replay_rig.play(options)?;
    let replay = replay_rig.scored()?;
    let mut report = LearnReport {
        waveform: options.motion.label(),
        rate_hz: options.rate,
        period_ticks: period,
        feedforward: ff,
        shaping: options.shaping,
        gain: options.gain,
        cutoff_hz: options.cutoff_hz,
        shaped_feedforward: shaped_ff,
        curve,
        learned,
        replay,
        rms_reduction: ff.rms_pct / learned.rms_pct.max(1e-12),
        updates: rig.task.updates(),
        missed: rig.task.missed(),
        guard_stops: rig.task.guard_stops(),
        figures: Vec::new(),
    };
    if let Some(dir) = &options.out_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let mut name = options.motion.label().replace(':', "-");
        if options.shaping.is_some() {
            name.push_str("-shaped");
        }
        let png = dir.join(format!("learn-{name}.png"));
        draw_curve(&png, &report)?;
        report.figures.push(png);
    }
    Ok(report)
}

/// Identifies the model on the study's board, then runs the study.
pub fn run(options: &LearnOptions) -> Result<LearnReport> {
    let model = identify_model(
        options.rate,
        &ClosedLoopOptions {
            sensor_noise_um: options.sensor_noise_um,
            ..ClosedLoopOptions::default()
        },
    )?;
    run_with(options, &model)
}

/// The learning curve: log10 of max and RMS per period, the feedforward alone as lines.
pub fn draw_curve(path: &std::path::Path, report: &LearnReport) -> Result<()> {
    let n = report.curve.len();
    let log = |v: f64| v.max(1e-6).log10();
    let line = |v: f64| vec![(1.0, log(v)), (n as f64, log(v))];
    let series = vec![
        Series {
            label: "max, learning".into(),
            points: (0..n)
                .map(|k| ((k + 1) as f64, log(report.curve[k].max_pct)))
                .collect(),
            color: RED,
        },
        Series {
            label: "RMS, learning".into(),
            points: (0..n)
                .map(|k| ((k + 1) as f64, log(report.curve[k].rms_pct)))
                .collect(),
            color: BLUE,
        },
        Series {
            label: "feedforward alone, max".into(),
            points: line(report.feedforward.max_pct),
            color: BLACK,
        },
        Series {
            label: "feedforward alone, RMS".into(),
            points: line(report.feedforward.rms_pct),
            color: BLACK,
        },
    ];
    draw_panels(
        path,
        &format!(
            "Learning {}, {} at {:.0} kHz",
            if report.shaping.is_some() {
                "+ shaping"
            } else {
                "feedforward"
            },
            report.waveform,
            report.rate_hz / 1e3,
        ),
        &[Panel {
            caption: "tracking error per period".into(),
            x_label: "period".into(),
            y_label: "log10 error [% of the stroke]".into(),
            series,
        }],
        1,
    )?;
    Ok(())
}

/// Prints the learning curve and the table.
pub fn print(report: &LearnReport, out: &mut impl std::io::Write) -> std::io::Result<()> {
    writeln!(
        out,
        "Learning feedforward, {} at {:.0} kHz (period {} ticks); error in % of the commanded stroke",
        report.waveform,
        report.rate_hz / 1e3,
        report.period_ticks
    )?;
    let shaping = report.shaping.map_or("none".to_string(), |n| {
        format!(
            "notch {:.0} Hz, Q {}, depth {:.4}",
            n.frequency_hz, n.q, n.depth
        )
    });
    writeln!(
        out,
        "learning gain {}, corner {:.0} Hz; input shaping: {shaping}",
        report.gain, report.cutoff_hz
    )?;
    writeln!(out, "| period | max % | RMS % |")?;
    writeln!(out, "|---:|---:|---:|")?;
    for (k, p) in report.curve.iter().enumerate() {
        writeln!(out, "| {} | {:.4} | {:.4} |", k + 1, p.max_pct, p.rms_pct)?;
    }
    writeln!(out)?;
    writeln!(
        out,
        "| run | max % | RMS % | RMS below {:.0} kHz % | RMS {:.0} kHz–Nyquist % |",
        RESONANCE_BAND_HZ / 1e3,
        RESONANCE_BAND_HZ / 1e3
    )?;
    writeln!(out, "|---|---:|---:|---:|---:|")?;
    let mut rows = vec![("inverse P–I feedforward alone", report.feedforward)];
    if let Some(f) = report.shaped_feedforward {
        rows.push(("shaped feedforward alone", f));
    }
    rows.push(("learned (last period)", report.learned));
    rows.push(("replayed, sensor off", report.replay));
    for (label, f) in rows {
        writeln!(
            out,
            "| {label} | {:.4} | {:.4} | {:.4} | {:.4} |",
            f.max_pct, f.rms_pct, f.below_band_rms_pct, f.band_rms_pct
        )?;
    }
    writeln!(
        out,
        "\nRMS reduction {:.1}×; {} tables posted, {} periods missed{}",
        report.rms_reduction,
        report.updates,
        report.missed,
        if report.guard_stops > 0 {
            "; the learning diverged (its error grew past twice its best and past where it started) and its guard switched it off: the feedforward alone plays"
        } else {
            ""
        }
    )?;
    for (goal, met) in report.goals() {
        writeln!(out, "goal: {goal}: {}", if met { "met" } else { "NOT met" })?;
    }
    for f in &report.figures {
        writeln!(out, "wrote {}", f.display())?;
    }
    Ok(())
}
