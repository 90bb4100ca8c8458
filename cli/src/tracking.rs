//! Open-loop tracking on the laboratory stage ([`hal_sim::plant::lab_stage`]), evaluated the way a
//! user evaluates a model on their own stage:
//!
//! 1. **Excite** ([`excite`]): from rest at 0 V, drive the stage over its whole drive range
//!    with the excitation `twinstack calibrate` streams to a board by default
//!    ([`twinstack_identify::excitation::Excitation::DEFAULT`], [`EXCITATION_S`] at
//!    [`EXCITATION_HZ`]: full-range cycles, cycles decaying about mid-range, nested
//!    off-centre loops and a multisine, so the record holds minor loops of every kind) and record `t, u, x` as a [`MeasuredData`].
//! 2. **Identify** ([`twinstack_identify::identification::identify`]) with the caller's
//!    [`IdentifyOptions`] (fitted on `t < fit_until_s`, by default [`FIT_UNTIL_S`]: the last
//!    cycle is held out and scored); with a board's control rate, only what the board runs at
//!    it ([`evaluate_methods_with_triangles`]).
//! 3. **Track** three desired trajectories ([`trajectories`]), placed inside the measured output
//!    range with a [`TRAJECTORY_MARGIN`] each side: a triangle, nested minor loops and a
//!    three-frequency multisine. The drive is the model's inverse ([`StageModel::compensate`],
//!    the library's fixed point), or for the *no compensation* row the least-squares line
//!    `u = a x + b` fitted to the excitation ([`LinearMap`]). The stage runs open loop from rest
//!    at 0 V, as for the excitation, through an unscored [`LEAD_IN_S`](twinstack_identify::trajectory::LEAD_IN_S) ramp to the
//!    trajectory's start ([`Trajectory::with_lead_in`]); the error is the reading minus the
//!    desired displacement, in % of the trajectory's span ([`TrackingScore`]).
//!
//! [`evaluate`] runs all of it and returns the table (`twinstack lab-stage`).
//!
//! **Sample rate.** [`SAMPLE_RATE_HZ`] = 10 kHz: 1 000 samples per 10 Hz cycle (the drive
//! moves at most 0.5 V between samples, far finer than the P–I thresholds), above twice the
//! stage's 3.5 kHz resonance so the record does not alias it, and 20 000 rows keep the
//! least-squares fits to seconds. The hysteresis models are rate-independent, so the
//! compensator run at 10 kHz gives the drive the board's 50–100 kHz tick would, sampled.

use hal_sim::plant::{LabStage, LabStageConfig, LabStageError, SetFieldError};
use std::path::PathBuf;
use twinstack::ParamError;
use twinstack_identify::excitation::Excitation;
use twinstack_identify::identification::auto::{identify_admitted, identify_auto_admitting};
use twinstack_identify::identification::run::{board_admission, BoardRate};
use twinstack_identify::identification::score::{score, ErrorFigures};
use twinstack_identify::identification::{creep, Identification, IdentifyOptions, ModelKind};
use twinstack_identify::preview::ResonancePreview;
use twinstack_identify::stage_model::StageModel;
use twinstack_identify::trajectory::{
    trajectories, triangle, triangle_fits, Trajectory, MIN_SAMPLES_PER_CYCLE, MIN_TRIANGLE_HZ,
    TRAJECTORY_MARGIN,
};
use twinstack_identify::tune::fit::fit as fit_resonance;
use twinstack_identify::tune::loop_model::C64;
use twinstack_identify::tune::measure::{
    coarse_frequencies, phasor, refined_frequencies, FrequencyPoint, SweepOptions,
};
use twinstack_link::measured_data::MeasuredData;

/// The default sample rate of the excitation and of tracking, Hz (see the module docs).
pub const SAMPLE_RATE_HZ: f64 = 10_000.0;

/// The unit of the stage's displacement, for the parameter file a board's admission is judged
/// on ([`board_admission`]).
const OUTPUT_UNIT: &str = "um";
/// The excitation: `calibrate`'s ([`Excitation::DEFAULT`]).
pub const EXCITATION: Excitation = Excitation::DEFAULT;
/// Length of the identification record, seconds.
pub const EXCITATION_S: f64 = EXCITATION.duration_s();
/// Base frequency of the excitation, Hz.
pub const EXCITATION_HZ: f64 = EXCITATION.hz;
/// The default `fit_until_s`: everything but the last excitation cycle is fitted.
pub const FIT_UNTIL_S: f64 = EXCITATION.held_out_from_s();

/// The excitation drive at `sample_rate_hz` for a stage whose drive range is `0 … drive_max`
/// volts: `excitation` ([`EXCITATION`] unless the user names the fastest motion) over the
/// whole range, from 0 V. Returns `(t, u)`.
pub fn excitation_drive(
    excitation: &Excitation,
    sample_rate_hz: f64,
    drive_max: f64,
) -> (Vec<f64>, Vec<f64>) {
    let x = excitation.sampled(sample_rate_hz);
    let t = (0..x.len()).map(|k| k as f64 / sample_rate_hz).collect();
    let u = x.iter().map(|v| 0.5 * drive_max * (1.0 + v)).collect();
    (t, u)
}

/// Runs `stage` open loop from rest at 0 V on the drive `u`; returns the readings.
pub fn run_open_loop(stage: &mut LabStage, u: &[f64]) -> Vec<f64> {
    stage.reset();
    u.iter().map(|&v| stage.step(v)).collect()
}

/// The identification record: the [`excitation_drive`] of [`EXCITATION`] played on `stage`
/// from rest, at the stage's sample rate.
pub fn excite(stage: &mut LabStage) -> MeasuredData {
    excite_with(stage, &EXCITATION)
}

/// [`excite`] with `excitation`.
pub fn excite_with(stage: &mut LabStage, excitation: &Excitation) -> MeasuredData {
    let rate = 1.0 / stage.sample_period_s();
    let (t, u) = excitation_drive(excitation, rate, stage.config().drive_max_volts);
    let x = run_open_loop(stage, &u);
    MeasuredData {
        path: PathBuf::from("lab-stage-excitation"),
        t,
        u: Some(u),
        x: Some(x),
    }
}

/// The user's linear calibration `u = a x + b`, least squares over the fitted part of the
/// excitation: the "no compensation" drive.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct LinearMap {
    /// `a`, volts per µm.
    pub volts_per_um: f64,
    /// `b`, volts.
    pub offset_volts: f64,
}

impl LinearMap {
    /// Fits `u = a x + b` on the samples of `data` with `t < fit_until_s`; `None` without
    /// `u`/`x` columns or when `x` does not vary there.
    pub fn fit(data: &MeasuredData, fit_until_s: f64) -> Option<Self> {
        let (u, x) = (data.u.as_ref()?, data.x.as_ref()?);
        let n = data.t.iter().take_while(|&&t| t < fit_until_s).count();
        if n < 2 {
            return None;
        }
        let nf = n as f64;
        let (mx, mu) = (
            x[..n].iter().sum::<f64>() / nf,
            u[..n].iter().sum::<f64>() / nf,
        );
        let sxx: f64 = x[..n].iter().map(|v| (v - mx) * (v - mx)).sum();
        let sxu: f64 = x[..n]
            .iter()
            .zip(&u[..n])
            .map(|(a, b)| (a - mx) * (b - mu))
            .sum();
        if sxx.is_nan() || sxx <= 0.0 {
            return None;
        }
        let a = sxu / sxx;
        Some(Self {
            volts_per_um: a,
            offset_volts: mu - a * mx,
        })
    }

    /// The drive for the desired readings `x`.
    pub fn drive(&self, x: &[f64]) -> Vec<f64> {
        x.iter()
            .map(|v| self.volts_per_um * v + self.offset_volts)
            .collect()
    }
}

/// How well a run tracked its trajectory.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct TrackingScore {
    /// Largest `|reading − desired|`, % of the trajectory's span.
    pub max_pct: f64,
    /// RMS of `reading − desired`, % of the trajectory's span.
    pub rms_pct: f64,
    /// Scored drive samples outside the stage's `0 … drive_max` (clamped by the amplifier).
    pub clipped: usize,
}

/// Plays `drive` (lead-in and trajectory, see [`Trajectory::with_lead_in`]) on `stage` from
/// rest at 0 V and scores the readings from sample `first` on against `trajectory`.
pub fn track_drive(
    stage: &mut LabStage,
    trajectory: &Trajectory,
    drive: &[f64],
    first: usize,
) -> TrackingScore {
    let max = stage.config().drive_max_volts;
    let clipped = drive
        .get(first..)
        .unwrap_or_default()
        .iter()
        .filter(|&&u| !(0.0..=max).contains(&u))
        .count();
    let x = run_open_loop(stage, drive);
    let x = x.get(first..).unwrap_or_default();
    let n = trajectory.x.len().min(x.len());
    let figures = score(&trajectory.x[..n], &x[..n], 0..n).unwrap_or(ErrorFigures {
        max_pct: f64::NAN,
        rms_pct: f64::NAN,
        samples: 0,
    });
    TrackingScore {
        max_pct: figures.max_pct,
        rms_pct: figures.rms_pct,
        clipped,
    }
}

/// Compensated open-loop tracking: `model`'s fixed-point inverse turns the trajectory, after
/// its lead-in from `x_rest` (the reading at rest at 0 V), into a drive, played on `stage`
/// from rest at 0 V. Fails only if the library refuses the model.
pub fn track(
    stage: &mut LabStage,
    model: &StageModel,
    trajectory: &Trajectory,
    x_rest: f64,
) -> Result<TrackingScore, ParamError> {
    let (t, x, first) = trajectory.with_lead_in(x_rest, 1.0 / stage.sample_period_s());
    let drive = model.compensate(&t, &x)?;
    Ok(track_drive(stage, trajectory, &drive, first))
}

/// [`track`] with the trajectory (after its lead-in) shaped by `preview` first, so that the
/// stage's resonance does not ring at its corners ([`twinstack_identify::preview`]): the
/// model's inverse is given the shaped positions.
pub fn track_previewed(
    stage: &mut LabStage,
    model: &StageModel,
    trajectory: &Trajectory,
    x_rest: f64,
    preview: &ResonancePreview,
) -> Result<TrackingScore, ParamError> {
    let (t, x, first) = trajectory.with_lead_in(x_rest, 1.0 / stage.sample_period_s());
    let drive = model.compensate(&t, &preview.shape(&x))?;
    Ok(track_drive(stage, trajectory, &drive, first))
}

/// The stage's resonance, measured as `twinstack tune` measures a board's
/// ([`twinstack_identify::tune::measure::sweep`], its default options): from rest at mid-drive,
/// a sine of 3 % of the drive's half range at each frequency of the coarse sweep, then about
/// the largest response, each measured by its phasors after the settling time; fitted by
/// [`twinstack_identify::tune::fit::fit`]. A reading is the position at the end of its
/// drive's hold, one sample earlier than the tick's model reads it: the response is taken
/// that sample later.
pub fn measure_resonance(
    config: &LabStageConfig,
) -> anyhow::Result<twinstack_identify::tune::fit::Fit> {
    let mut stage = LabStage::new(config)?;
    let rate = 1.0 / stage.sample_period_s();
    let half = 0.5 * config.drive_max_volts;
    let options = SweepOptions::default();
    let mut measure = |f: f64| -> FrequencyPoint {
        stage.rest(half);
        let w = std::f64::consts::TAU * f;
        let window = options.window_s.max(options.cycles / f);
        let settle = (options.settle_s * rate).ceil() as usize;
        let n = settle + (window * rate).ceil() as usize;
        let amplitude = options.amplitude * half;
        let (mut t, mut u, mut x) = (Vec::new(), Vec::new(), Vec::new());
        for k in 0..n {
            let tk = k as f64 / rate;
            let uk = half + amplitude * (w * tk).sin();
            let xk = stage.step(uk);
            if k >= settle {
                t.push(tk);
                u.push(uk);
                x.push(xk);
            }
        }
        let (pu, px) = (phasor(&t, &u, w), phasor(&t, &x, w));
        FrequencyPoint {
            frequency_hz: f,
            response: px.over(pu).times(C64::cis(-w / rate)),
            drive_volts: pu.abs(),
            sensor_amplitude: px.abs(),
        }
    };
    let mut points: Vec<FrequencyPoint> = coarse_frequencies(&options, rate)
        .into_iter()
        .map(&mut measure)
        .collect();
    for f in refined_frequencies(&options, &points, rate) {
        points.push(measure(f));
    }
    points.sort_by(|a, b| a.frequency_hz.total_cmp(&b.frequency_hz));
    fit_resonance(&points, rate)
        .ok_or_else(|| anyhow::anyhow!("the stage's measured response has no finite fit"))
}

/// Uncompensated tracking: the linear map turns the trajectory (after its lead-in) into a
/// drive.
pub fn track_linear(
    stage: &mut LabStage,
    map: &LinearMap,
    trajectory: &Trajectory,
    x_rest: f64,
) -> TrackingScore {
    let (_, x, first) = trajectory.with_lead_in(x_rest, 1.0 / stage.sample_period_s());
    track_drive(stage, trajectory, &map.drive(&x), first)
}

/// One row of the table: a way of computing the drive and its score on each trajectory.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct TrackingRow {
    /// `none` (the linear map) or the model's name as `--model` spells it.
    pub method: String,
    /// The identified model's held-out error on the excitation's last cycle (`None` for
    /// `none`, or when identification failed).
    pub held_out: Option<ErrorFigures>,
    /// One score per trajectory, in the table's order (empty when `error` is set).
    pub scores: Vec<TrackingScore>,
    /// Why this row has no scores (identification or the library refused the model).
    pub error: Option<String>,
}

impl TrackingRow {
    /// The worst max error over the trajectories, % (`None` without scores).
    pub fn worst_max_pct(&self) -> Option<f64> {
        self.scores.iter().map(|s| s.max_pct).reduce(f64::max)
    }
}

/// The whole evaluation.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct TrackingTable {
    /// The noise seed of the stage.
    pub seed: u64,
    /// Sample rate, Hz.
    pub sample_rate_hz: f64,
    /// The trajectories' names, the columns' order.
    pub trajectories: Vec<String>,
    /// The measured output range of the excitation, µm.
    pub excitation_range_um: (f64, f64),
    /// The range the trajectories span, µm.
    pub trajectory_range_um: (f64, f64),
    /// The linear map behind the `none` row.
    pub linear_map: Option<LinearMap>,
    /// `none` first, then one row per model (with a preview, each model's row followed by
    /// its row with the preview).
    pub rows: Vec<TrackingRow>,
    /// The resonance the preview inverts, as measured on the stage (`None`: no preview).
    pub resonance: Option<MeasuredResonance>,
    /// The excitation's sweep top, Hz, where the user named the fastest motion (`None`: the
    /// default excitation).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fastest_hz: Option<f64>,
    /// The excitation's length, seconds.
    #[serde(skip)]
    pub excitation_s: f64,
}

/// The stage's resonance as [`measure_resonance`] fitted it.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct MeasuredResonance {
    /// Hz.
    pub frequency_hz: f64,
    /// Damping ratio.
    pub zeta: f64,
    /// The fit's RMS magnitude error, dB.
    pub rms_db: f64,
    /// The fit's RMS phase error, degrees.
    pub rms_deg: f64,
}

impl TrackingTable {
    /// The row of `method`.
    pub fn row(&self, method: &str) -> Option<&TrackingRow> {
        self.rows.iter().find(|r| r.method == method)
    }

    /// Prints the table as text.
    pub fn print(&self, out: &mut impl std::io::Write) -> std::io::Result<()> {
        writeln!(
            out,
            "Lab stage (seed {}, {} Hz): identified from {} s of {} Hz{}, tracked open loop over {:.2} … {:.2} µm",
            self.seed,
            self.sample_rate_hz,
            self.excitation_s,
            EXCITATION_HZ,
            match self.fastest_hz {
                Some(hz) => format!(" with a sweep up to {hz} Hz"),
                None => String::new(),
            },
            self.trajectory_range_um.0,
            self.trajectory_range_um.1
        )?;
        if let Some(r) = &self.resonance {
            writeln!(
                out,
                "preview: the resonance measured on the stage, {:.0} Hz, damping {:.4} (fit {:.2} dB, {:.1}° RMS)",
                r.frequency_hz, r.zeta, r.rms_db, r.rms_deg
            )?;
        }
        write!(out, "{:<10} {:>16}", "method", "held-out max/rms")?;
        for name in &self.trajectories {
            write!(out, " {:>16}", name)?;
        }
        writeln!(out, " {:>10}", "worst max")?;
        for row in &self.rows {
            let held = row
                .held_out
                .map(|h| format!("{:.2}/{:.2}", h.max_pct, h.rms_pct))
                .unwrap_or_else(|| "-".into());
            write!(out, "{:<10} {:>16}", row.method, held)?;
            if let Some(e) = &row.error {
                writeln!(out, " failed: {e}")?;
                continue;
            }
            for s in &row.scores {
                let clip = if s.clipped > 0 { "*" } else { " " };
                write!(
                    out,
                    " {:>15}{clip}",
                    format!("{:.2}/{:.2}", s.max_pct, s.rms_pct)
                )?;
            }
            writeln!(
                out,
                " {:>10}",
                row.worst_max_pct()
                    .map(|w| format!("{w:.2}"))
                    .unwrap_or_default()
            )?;
        }
        writeln!(
            out,
            "(max/rms error in % of each trajectory's span; * = drive clipped at the rails)"
        )
    }
}

/// A stage other than the default: a name and the fields ([`LabStageConfig::set`]) it changes.
pub type StageVariant = (&'static str, &'static [(&'static str, f64)]);

/// The stages `twinstack lab-stage --variants` tracks on besides the default: each
/// non-ideality of the default stage made stronger, weaker or turned around, and two
/// combinations. The default stage is what the family was tuned on; these say how far that
/// carries to a stage it was not (see the book, results/lab-stage.md, "Other stages").
pub const STAGE_VARIANTS: [StageVariant; 21] = [
    ("default", &[]),
    (
        "mirrored asymmetry",
        &[
            ("preisach.top_saturation", 0.2),
            ("preisach.bottom_saturation", 0.6),
        ],
    ),
    (
        "strong top saturation",
        &[
            ("preisach.top_saturation", 0.9),
            ("preisach.bottom_saturation", 0.0),
        ],
    ),
    (
        "symmetric density",
        &[
            ("preisach.top_saturation", 0.0),
            ("preisach.bottom_saturation", 0.0),
        ],
    ),
    ("wide loops", &[("preisach.width", 0.3)]),
    ("narrow loops", &[("preisach.width", 0.06)]),
    ("less reversible", &[("preisach.reversible", 0.2)]),
    ("more reversible", &[("preisach.reversible", 0.7)]),
    ("strong creep", &[("creep_per_decade", 0.04)]),
    ("weak creep", &[("creep_per_decade", 0.005)]),
    ("no creep", &[("creep_per_decade", 0.0)]),
    (
        "slower creep",
        &[("creep_fastest_s", 1e-3), ("creep_slowest_s", 1e5)],
    ),
    ("stiff flexure", &[("flexure_saturation_um", 100.0)]),
    (
        "linear flexure",
        &[("flexure_saturation_um", f64::INFINITY)],
    ),
    (
        "low resonance",
        &[("resonance_hz", 1200.0), ("damping_ratio", 0.01)],
    ),
    (
        "high resonance",
        &[("resonance_hz", 8000.0), ("damping_ratio", 0.1)],
    ),
    ("noisy sensor", &[("noise_rms_nm", 10.0)]),
    (
        "fine sensor",
        &[("noise_rms_nm", 0.5), ("sensor_lsb_nm", 0.5)],
    ),
    ("short stroke", &[("stroke_um", 20.0)]),
    (
        "combined A",
        &[
            ("preisach.top_saturation", 0.3),
            ("preisach.bottom_saturation", 0.7),
            ("creep_per_decade", 0.03),
            ("flexure_saturation_um", 120.0),
            ("resonance_hz", 2000.0),
            ("damping_ratio", 0.02),
            ("noise_rms_nm", 5.0),
        ],
    ),
    (
        "combined B",
        &[
            ("preisach.width", 0.25),
            ("preisach.reversible", 0.25),
            ("creep_per_decade", 0.025),
            ("flexure_saturation_um", 300.0),
            ("noise_rms_nm", 3.0),
        ],
    ),
];

/// The Bouc–Wen-class stage's variants (`twinstack lab-stage --hysteresis bouc-wen
/// --variants`): its default, its exponent and asymmetry made otherwise, its loops wider and
/// narrower, and one with every non-ideality stronger.
pub const BOUC_WEN_VARIANTS: [StageVariant; 8] = [
    ("default", &[]),
    ("exponent 1", &[("bouc_wen.exponent", 1.0)]),
    ("exponent 2.5", &[("bouc_wen.exponent", 2.5)]),
    ("symmetric branches", &[("bouc_wen.rising", 0.0)]),
    ("rising saturates more", &[("bouc_wen.rising", 30.0)]),
    ("wide loops", &[("bouc_wen.alpha", 0.45)]),
    ("narrow loops", &[("bouc_wen.alpha", 0.15)]),
    (
        "combined",
        &[
            ("bouc_wen.rising", 20.0),
            ("creep_per_decade", 0.03),
            ("flexure_saturation_um", 120.0),
            ("resonance_hz", 2000.0),
            ("damping_ratio", 0.02),
            ("noise_rms_nm", 5.0),
        ],
    ),
];

/// A variant's changes as `--set` spells them: `field=value,…` (`-` for none).
pub fn variant_settings(changes: &[(&str, f64)]) -> String {
    if changes.is_empty() {
        return "-".into();
    }
    changes
        .iter()
        .map(|(f, v)| format!("{f}={v}"))
        .collect::<Vec<_>>()
        .join(",")
}

/// `base` with a variant's changes applied.
pub fn variant_config(
    base: &LabStageConfig,
    changes: &[(&str, f64)],
) -> Result<LabStageConfig, SetFieldError> {
    let mut c = base.clone();
    for &(field, value) in changes {
        c.set(field, value)?;
    }
    Ok(c)
}

/// One stage's tracking table, for [`evaluate_variants`].
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct VariantTable {
    /// The variant's name.
    pub variant: &'static str,
    /// Its changes, as `--set` spells them.
    pub settings: String,
    /// The tracking table on it.
    pub table: TrackingTable,
}

/// [`evaluate_methods`] on each of `variants` applied to `base`, each stage excited with
/// `excitation`, the stages evaluated two at a time (each is independent and deterministic
/// for its seed); with `board`, as [`evaluate_methods_with_triangles`] fits them. An
/// excitation the stage's rate does not resolve is refused as there
/// ([`check_excitation`]).
pub fn evaluate_variants(
    base: &LabStageConfig,
    variants: &[StageVariant],
    methods: &[Method],
    board: Option<&BoardRate>,
    excitation: &Excitation,
) -> Result<Vec<VariantTable>, VariantError> {
    check_excitation(excitation, 1.0 / base.sample_period_s).map_err(VariantError::Excitation)?;
    let configs = variants
        .iter()
        .map(|(_, changes)| variant_config(base, changes))
        .collect::<Result<Vec<_>, _>>()?;
    let mut out = Vec::with_capacity(variants.len());
    for (pair, configs) in variants.chunks(2).zip(configs.chunks(2)) {
        let tables: Vec<Result<TrackingTable, LabStageError>> = std::thread::scope(|s| {
            let running: Vec<_> = configs
                .iter()
                .map(|c| s.spawn(move || evaluate_all(c, methods, &[], board, None, excitation)))
                .collect();
            running
                .into_iter()
                .map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e)))
                .collect()
        });
        for ((variant, changes), table) in pair.iter().zip(tables) {
            out.push(VariantTable {
                variant,
                settings: variant_settings(changes),
                table: table?,
            });
        }
    }
    Ok(out)
}

/// Why [`evaluate_variants`] could not run.
#[derive(Debug, thiserror::Error)]
pub enum VariantError {
    /// A variant names a field the stage does not have.
    #[error(transparent)]
    Field(#[from] SetFieldError),
    /// A variant's stage is out of range.
    #[error(transparent)]
    Stage(#[from] LabStageError),
    /// The excitation is not one the stage's rate resolves ([`check_excitation`]).
    #[error("{0}")]
    Excitation(String),
}

/// Prints one line per variant: its name, the uncompensated worst max and each method's
/// (`auto` with what it picked), % of span.
pub fn print_variants(
    tables: &[VariantTable],
    out: &mut impl std::io::Write,
) -> std::io::Result<()> {
    let Some(first) = tables.first() else {
        return Ok(());
    };
    writeln!(
        out,
        "Worst max tracking error (% of span) over the triangle, minor loops and multisine, per stage{}",
        match first.table.fastest_hz {
            Some(hz) => format!(" (identified with a sweep up to {hz} Hz)"),
            None => String::new(),
        }
    )?;
    write!(out, "{:<22}", "stage")?;
    for row in &first.table.rows {
        let head = row.method.split(':').next().unwrap_or(&row.method);
        write!(out, " {head:>8}")?;
    }
    writeln!(out, "  auto picked / settings")?;
    for v in tables {
        write!(out, "{:<22}", v.variant)?;
        let mut picked = "";
        for row in &v.table.rows {
            if let Some(p) = row.method.strip_prefix("auto: ") {
                picked = p;
            }
            match row.worst_max_pct() {
                Some(w) => write!(out, " {w:>8.2}")?,
                None => write!(out, " {:>8}", "failed")?,
            }
        }
        writeln!(out, "  {picked} / {}", v.settings)?;
    }
    Ok(())
}

/// The name `--model` gives `kind`.
pub fn model_name(kind: ModelKind) -> String {
    kind.name().to_string()
}

/// How a row's model is identified.
#[derive(Clone, Debug)]
pub enum Method {
    /// One model, these options.
    One(IdentifyOptions),
    /// `--model auto`: every candidate ranked on the last part of the fit window, the best kept.
    Auto(Vec<IdentifyOptions>),
}

impl Method {
    /// The row's name: the model (`+map` with an output map, then `+creep` with creep, in
    /// the order the board runs them: `bouc-wen+map+creep`), or `auto: ` and what auto
    /// picked.
    fn name(o: &IdentifyOptions) -> String {
        let mut name = model_name(o.model);
        if o.output_map {
            name.push_str("+map");
        }
        if o.creep {
            name.push_str("+creep");
        }
        name
    }

    /// The options asked for (`auto`: its first candidate's).
    fn asked(&self) -> Option<&IdentifyOptions> {
        match self {
            Method::One(o) => Some(o),
            Method::Auto(c) => c.first(),
        }
    }
}

/// A fitted row's name ([`Method::name`]) with what a board's rate made smaller than `asked`:
/// `gpi+creep (12 operators, 1 creep mode, no observer)`; the creep's modes are those the fit
/// kept. Nothing is added where nothing was made smaller.
fn fitted_name(fitted: &IdentifyOptions, model: &StageModel, asked: &IdentifyOptions) -> String {
    let mut parts = Vec::new();
    let sized = matches!(fitted.model, ModelKind::Pi | ModelKind::Gpi);
    if sized && fitted.operators != asked.operators {
        parts.push(format!("{} operators", fitted.operators));
    }
    if let Some(c) = &model.creep {
        let modes = c.weights.len();
        if modes != creep::MODES {
            parts.push(format!(
                "{modes} creep mode{}",
                if modes == 1 { "" } else { "s" }
            ));
        }
    }
    if asked.observer && !fitted.observer {
        parts.push("no observer".to_string());
    }
    let name = Method::name(fitted);
    if parts.is_empty() {
        name
    } else {
        format!("{name} ({})", parts.join(", "))
    }
}

/// [`evaluate_methods`] with one model per row.
pub fn evaluate(
    config: &LabStageConfig,
    options: &[IdentifyOptions],
) -> Result<TrackingTable, LabStageError> {
    let methods: Vec<Method> = options.iter().cloned().map(Method::One).collect();
    evaluate_methods(config, &methods)
}

/// Excites the stage built from `config`, identifies a model with each of `methods`, and
/// tracks the three trajectories with each model and without compensation.
///
/// ```no_run
/// use twinstack_identify::identification::{IdentifyOptions, ModelKind};
/// use hal_sim::plant::LabStageConfig;
/// use twinstack_cli::tracking::{evaluate, FIT_UNTIL_S, SAMPLE_RATE_HZ};
/// let table = evaluate(
///     &LabStageConfig::new(SAMPLE_RATE_HZ, 1),
///     &[IdentifyOptions::new(ModelKind::Pi, FIT_UNTIL_S)],
/// )
/// .unwrap();
/// table.print(&mut std::io::stdout()).unwrap();
/// ```
pub fn evaluate_methods(
    config: &LabStageConfig,
    methods: &[Method],
) -> Result<TrackingTable, LabStageError> {
    evaluate_all(config, methods, &[], None, None, &EXCITATION)
}

/// Whether a stage sampled at `rate` Hz can be excited with `excitation`: the excitation is
/// well formed ([`Excitation::check`]) and its fastest motion has at least
/// [`MIN_SAMPLES_PER_CYCLE`] samples a cycle. The error names what is wrong and the limit.
pub fn check_excitation(excitation: &Excitation, rate: f64) -> Result<(), String> {
    if let Err((field, rule, value)) = excitation.check() {
        return Err(format!(
            "the excitation's {field} = {value}: must be {rule}"
        ));
    }
    if excitation.fastest_hz() * MIN_SAMPLES_PER_CYCLE > rate {
        return Err(format!(
            "the excitation's fastest motion, {} Hz, is sampled with fewer than {MIN_SAMPLES_PER_CYCLE} samples a cycle at {rate} Hz: at most {} Hz",
            excitation.fastest_hz(),
            rate / MIN_SAMPLES_PER_CYCLE
        ));
    }
    Ok(())
}

/// [`evaluate_methods`] with, after the three trajectories, a triangle at each of
/// `triangles_hz` over the same span ([`triangle`]): one calibration, tracked from slow
/// motion (creep) to fast (the stage's dynamics). A frequency [`triangle`] cannot sample at the
/// stage's rate is refused, naming it. The stage is excited with `excitation` (a
/// frequency in it the stage's rate samples with fewer than [`MIN_SAMPLES_PER_CYCLE`] a
/// cycle is refused too).
///
/// With `board`, each model is fitted only as the board runs it at that control rate: `auto`
/// picks among what the board's tick budget admits (sizing a model down where it allows, as
/// `identify --tick-rate` and `calibrate` do), and a row names what was made smaller.
///
/// With `preview`, the stage's resonance is measured as `twinstack tune` measures a board's
/// ([`measure_resonance`]) and each model's row is followed by `… + preview`: the same model,
/// each trajectory shaped first so that the resonance does not ring at its corners
/// ([`track_previewed`]).
pub fn evaluate_methods_with_triangles(
    config: &LabStageConfig,
    methods: &[Method],
    triangles_hz: &[f64],
    board: Option<&BoardRate>,
    preview: bool,
    excitation: &Excitation,
) -> anyhow::Result<TrackingTable> {
    let rate = 1.0 / config.sample_period_s;
    check_excitation(excitation, rate).map_err(anyhow::Error::msg)?;
    for &hz in triangles_hz {
        if !triangle_fits(hz, rate) {
            anyhow::bail!(
                "triangle {hz} Hz: a triangle's frequency must be from {MIN_TRIANGLE_HZ} Hz (four cycles in 40 s) to {} Hz at {rate} Hz (at least {MIN_SAMPLES_PER_CYCLE} samples a cycle)",
                rate / MIN_SAMPLES_PER_CYCLE
            );
        }
    }
    let preview = if preview {
        let fit = measure_resonance(config)?;
        let p = &fit.plant;
        let shaping = ResonancePreview::new(p.resonance_hz, p.zeta, rate)
            .map_err(|e| anyhow::anyhow!("the stage's measured resonance: {e}"))?;
        let measured = MeasuredResonance {
            frequency_hz: p.resonance_hz,
            zeta: p.zeta,
            rms_db: fit.rms_db,
            rms_deg: fit.rms_deg,
        };
        Some((shaping, measured))
    } else {
        None
    };
    Ok(evaluate_all(
        config,
        methods,
        triangles_hz,
        board,
        preview.as_ref(),
        excitation,
    )?)
}

/// [`evaluate_methods_with_triangles`] on frequencies it has checked; with `board`, each model
/// fitted only as the board runs it at that control rate ([`board_admission`]: `auto` picks
/// among those, a model asked for by name is sized down or refused).
fn evaluate_all(
    config: &LabStageConfig,
    methods: &[Method],
    triangles_hz: &[f64],
    board: Option<&BoardRate>,
    preview: Option<&(ResonancePreview, MeasuredResonance)>,
    excitation: &Excitation,
) -> Result<TrackingTable, LabStageError> {
    let mut stage = LabStage::new(config)?;
    let data = excite_with(&mut stage, excitation);
    let x = data.x.as_deref().unwrap_or_default();
    let (lo, hi) = x
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    let margin = TRAJECTORY_MARGIN * (hi - lo);
    let rate = 1.0 / config.sample_period_s;
    let mut trajectories = trajectories(lo + margin, hi - margin, rate).to_vec();
    // Checked by the caller: `triangle` refuses a frequency whatever the span.
    trajectories.extend(
        triangles_hz
            .iter()
            .filter_map(|&hz| triangle(lo + margin, hi - margin, hz, rate)),
    );
    let x_rest = x.first().copied().unwrap_or(0.0);

    let fit_until = methods
        .iter()
        .find_map(|m| match m {
            Method::One(o) => Some(o.fit_until_s),
            Method::Auto(c) => c.first().map(|o| o.fit_until_s),
        })
        .unwrap_or(excitation.held_out_from_s());
    let linear_map = LinearMap::fit(&data, fit_until);
    let mut rows = vec![match linear_map {
        Some(map) => TrackingRow {
            method: "none".into(),
            held_out: None,
            scores: trajectories
                .iter()
                .map(|tr| track_linear(&mut stage, &map, tr, x_rest))
                .collect(),
            error: None,
        },
        None => TrackingRow {
            method: "none".into(),
            held_out: None,
            scores: Vec::new(),
            error: Some("the excitation's reading does not vary".into()),
        },
    }];
    // With a board's rate, only what the board runs at it (sized down where it allows).
    let admit = board_admission(board, OUTPUT_UNIT);
    for m in methods {
        // With a board's rate, the row says what the rate took away.
        let named = |fitted: &IdentifyOptions, id: &Identification| match (board, m.asked()) {
            (Some(_), Some(asked)) => fitted_name(fitted, &id.model, asked),
            _ => Method::name(fitted),
        };
        let (method, identified) = match m {
            Method::One(o) => match identify_admitted(&data, o.clone(), &admit) {
                Ok((fitted, id)) => (named(&fitted, &id), Ok(id)),
                Err(e) => (Method::name(o), Err(e)),
            },
            Method::Auto(candidates) => match identify_auto_admitting(&data, candidates, &admit) {
                Ok(a) => {
                    let picked = named(&a.options, &a.identification);
                    (format!("auto: {picked}"), Ok(a.identification))
                }
                Err(e) => ("auto".into(), Err(e)),
            },
        };
        let outcome = identified.map_err(|e| e.to_string()).and_then(|id| {
            let u = data.u.as_deref().unwrap_or_default();
            let predicted = id.model.predict(&data.t, u).map_err(|e| e.to_string())?;
            let held_out = score(x, &predicted, id.held_out_from..x.len());
            let scores = trajectories
                .iter()
                .map(|tr| track(&mut stage, &id.model, tr, x_rest))
                .collect::<Result<Vec<_>, _>>()
                .map_err(|e| e.to_string())?;
            let previewed = match preview {
                Some((shaping, _)) => Some(
                    trajectories
                        .iter()
                        .map(|tr| track_previewed(&mut stage, &id.model, tr, x_rest, shaping))
                        .collect::<Result<Vec<_>, _>>()
                        .map_err(|e| e.to_string())?,
                ),
                None => None,
            };
            Ok((held_out, scores, previewed))
        });
        match outcome {
            Ok((held_out, scores, previewed)) => {
                let previewed = previewed.map(|scores| TrackingRow {
                    method: format!("{method} + preview"),
                    held_out,
                    scores,
                    error: None,
                });
                rows.push(TrackingRow {
                    method,
                    held_out,
                    scores,
                    error: None,
                });
                rows.extend(previewed);
            }
            Err(e) => rows.push(TrackingRow {
                method,
                held_out: None,
                scores: Vec::new(),
                error: Some(e),
            }),
        }
    }
    Ok(TrackingTable {
        seed: config.seed,
        // The configuration holds the period: 50 kHz comes back as 49 999.999 999 999 99.
        sample_rate_hz: (rate * 1e6).round() / 1e6,
        trajectories: trajectories.iter().map(|t| t.name.clone()).collect(),
        excitation_range_um: (lo, hi),
        trajectory_range_um: (lo + margin, hi - margin),
        linear_map,
        rows,
        resonance: preview.map(|p| p.1),
        fastest_hz: excitation.sweep_top_hz(),
        excitation_s: excitation.duration_s(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_excitation_starts_at_rest_covers_the_range_and_ends_inside_it() {
        let (t, u) = excitation_drive(&EXCITATION, SAMPLE_RATE_HZ, 150.0);
        assert_eq!(t.len(), 20_000);
        assert_eq!(t.len() as f64, EXCITATION_S * SAMPLE_RATE_HZ);
        assert!(u[0].abs() < 1e-12);
        let top = u[..6000].iter().copied().fold(0.0, f64::max);
        assert!((top - 150.0).abs() < 1e-6);
        assert!(u.iter().all(|&v| (0.0..=150.0).contains(&v)));
        let last_cycle = &u[19_000..];
        let (lo, hi) = last_cycle
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
                (l.min(v), h.max(v))
            });
        // The last cycle, held out, is the multisine's: inside the range, still moving.
        assert!(
            lo > 0.05 * 150.0 && hi < 0.95 * 150.0 && hi - lo > 0.1 * 150.0,
            "{lo} … {hi}"
        );
    }

    #[test]
    fn trajectories_start_low_and_stay_within_their_range() {
        for tr in trajectories(10.0, 70.0, 1000.0) {
            assert!((tr.x[0] - 10.0).abs() < 1e-9, "{}", tr.name);
            let (lo, hi) =
                tr.x.iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
                        (l.min(v), h.max(v))
                    });
            assert!(lo >= 10.0 - 1e-9 && hi <= 70.0 + 1e-9, "{}", tr.name);
            assert!(hi - lo > 59.0, "{} spans the range", tr.name);
            assert_eq!(tr.t.len(), tr.x.len());
        }
    }

    #[test]
    fn the_linear_map_recovers_a_line() {
        let t: Vec<f64> = (0..100).map(|k| k as f64 * 0.01).collect();
        let x: Vec<f64> = t.iter().map(|t| 5.0 * (7.0 * t).sin()).collect();
        let u: Vec<f64> = x.iter().map(|x| 2.0 * x + 3.0).collect();
        let data = MeasuredData {
            path: "line".into(),
            t,
            u: Some(u),
            x: Some(x),
        };
        let m = LinearMap::fit(&data, 0.5).unwrap();
        assert!((m.volts_per_um - 2.0).abs() < 1e-12 && (m.offset_volts - 3.0).abs() < 1e-12);
        let flat = MeasuredData {
            x: Some(vec![1.0; 100]),
            ..data
        };
        assert!(LinearMap::fit(&flat, 0.5).is_none());
    }
}
