//! `twinstack calibrate --port PORT --out PARAMS.json [--model auto|…] [--no-store] [--json]`:
//! the whole calibration in one command ([`twinstack_identify::calibrate`]): excites the stage with
//! the identification excitation streamed in bypass ([`twinstack_identify::excitation`]: the
//! major loop and concentric minor loops, nested loops and a multisine where asked), records
//! drive and sensor, identifies the best model, writes the
//! parameter file (the format `identify` writes) and a PNG beside it (the fit, the ranking, the
//! tracking before and after), loads the settings (open loop), verifies them on a test
//! trajectory and stores them to flash (to boot in bypass unless `--store MODE`). After the
//! excitation it measures the stage's resonance as `tune` does (unless `--no-resonance`) and
//! writes it into the parameter file, for `load --preview` (the board's preview, every
//! setpoint shaped on the board), `compensate --preview` and `stream --preview`.
//!
//! The files are written only once the calibration has succeeded; a failure changes nothing on
//! disk and loads nothing on a board it stopped before (see [`twinstack_identify::calibrate`] for which
//! step does what).

use super::board_link::{connect, PortArgs};
use super::params::ModeArg;
use crate::plot::{draw_charts, Bar, BarPanel, Chart, Panel, Series};
use anyhow::bail;
use plotters::style::RGBColor;
use std::path::{Path, PathBuf};
use twinstack::services::recorder::Channel;
use twinstack_identify::calibrate::{
    calibrate, CalibrateOptions, CalibrationReport, Progress, ResonanceOutcome,
};
use twinstack_identify::excitation::Excitation;
use twinstack_identify::identification::auto::{Validation, INVERSE_TO_FORWARD_LIMIT};
use twinstack_identify::identification::score::ErrorFigures;
use twinstack_link::output_file::Staged;

/// Arguments of `calibrate`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// Parameter file to write (the figure goes beside it, extension .png).
    #[arg(long)]
    pub out: PathBuf,
    /// Model to fit: `auto` (the default) ranks every model of the family and keeps the best;
    /// or one model by name.
    #[arg(long, default_value = "auto", value_parser = super::identify::parse_model,
          value_name = "auto|pi|gpi|bouc-wen|duhem")]
    pub model: super::identify::ModelChoice,
    /// Play operators of a P–I model (1 to 32) [default: 17, or as many as the board runs at
    /// its rate where 17 are too many].
    #[arg(long)]
    pub operators: Option<usize>,
    /// Sensor lag in samples of the recorded excitation [default: 0]; `--lag auto` estimates
    /// it as `identify` does.
    #[arg(long, default_value = "0", value_parser = parse_lag, value_name = "N|auto")]
    pub lag: LagArg,
    /// Base frequency of the excitation, Hz (its parts last whole cycles of it).
    #[arg(long, default_value_t = Excitation::DEFAULT.hz)]
    pub frequency: f64,
    /// Cycles of the excitation over the whole swept range.
    #[arg(long, default_value_t = Excitation::DEFAULT.full_cycles)]
    pub full_cycles: u16,
    /// Cycles decaying about the middle after them.
    #[arg(long, default_value_t = Excitation::DEFAULT.decay_cycles)]
    pub decay_cycles: u16,
    /// The decaying cycles' last amplitude, fraction of the full cycles'.
    #[arg(long, default_value_t = Excitation::DEFAULT.final_amplitude)]
    pub final_amplitude: f64,
    /// Cycles' time of nested, off-centre minor loops after them.
    #[arg(long, default_value_t = Excitation::DEFAULT.loop_cycles)]
    pub loop_cycles: u16,
    /// Cycles' time of a three-tone multisine last. The excitation's last cycle, whichever
    /// part it is of, is held out to score the model.
    #[arg(long, default_value_t = Excitation::DEFAULT.multisine_cycles)]
    pub multisine_cycles: u16,
    /// The fastest motion you will run, Hz (e.g. a 200 Hz scan line): the excitation gains a
    /// sweep from its frequency up to this one before the multisine (0.4 s more at 10 Hz), so
    /// that the model and its creep are fitted on the rates the compensator will be asked
    /// for. Without it, the fastest motion is the multisine's 13 Hz tone
    #[arg(long, value_name = "HZ")]
    pub fastest_hz: Option<f64>,
    /// Refuse the model if it predicts the held-out cycle worse than this, % of span (max).
    #[arg(long, default_value_t = 5.0, value_name = "PERCENT")]
    pub max_held_out: f64,
    /// Store to flash to boot in this mode.
    #[arg(long, value_enum, default_value_t = ModeArg::Bypass)]
    pub store: ModeArg,
    /// Do not store the settings to flash (they stay loaded until the board restarts).
    #[arg(long)]
    pub no_store: bool,
    /// Load a model whose input range the drive cannot reach in full, with a warning.
    #[arg(long)]
    pub clamp: bool,
    /// Load the model as the compensator only, not as the observer too: the board then has no
    /// estimate of the displacement and no drift check of its sensor, and the tick saves the
    /// observer's cost (the feedback runs on the sensor either way). A faster board admits
    /// larger models this way (`twinstack budget` shows by how much).
    #[arg(long)]
    pub no_observer: bool,
    /// Do not measure the stage's resonance after the excitation (the sweep `twinstack tune`
    /// runs: 36 frequencies, each a sine burst captured and read back over the link).
    /// Measured, it goes into the parameter file, where
    /// `load --preview` runs the board's preview for it, and `compensate --preview` and
    /// `stream --preview` shape a planned trajectory for it.
    #[arg(long)]
    pub no_resonance: bool,
    /// Print the figures as one JSON object on stdout instead of text.
    #[arg(long)]
    pub json: bool,
}

impl Args {
    /// The library's options for these arguments.
    pub fn options(&self) -> CalibrateOptions {
        CalibrateOptions {
            excitation_hz: self.frequency,
            full_cycles: self.full_cycles,
            decay_cycles: self.decay_cycles,
            final_amplitude: self.final_amplitude,
            loop_cycles: self.loop_cycles,
            multisine_cycles: self.multisine_cycles,
            fastest_hz: self.fastest_hz,
            model: match self.model {
                super::identify::ModelChoice::Auto => None,
                super::identify::ModelChoice::Only(kind) => Some(kind),
            },
            operators: self.operators,
            lag: self.lag.0,
            max_held_out_pct: self.max_held_out,
            clamp: self.clamp,
            store: (!self.no_store).then(|| self.store.into()),
            observer: !self.no_observer,
            resonance: !self.no_resonance,
            ..CalibrateOptions::default()
        }
    }
}

/// `--lag`: a number of samples, or `None` for `auto` (estimated).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LagArg(pub Option<usize>);

/// Parses `--lag`: a number of samples, or `auto`.
pub fn parse_lag(s: &str) -> Result<LagArg, String> {
    if s.eq_ignore_ascii_case("auto") {
        return Ok(LagArg(None));
    }
    s.parse()
        .map(|n| LagArg(Some(n)))
        .map_err(|_| format!("--lag {s}: a number of samples, or auto"))
}

/// The figures as one JSON object (what `--json` prints).
pub fn report_json(r: &CalibrationReport, out: &Path, png: &Path) -> serde_json::Value {
    serde_json::json!({
        "model": r.model,
        "reason": r.reason,
        "ranking": r.ranking.iter().map(|c| {
            let mut v = match &c.validation {
                Validation::Scored(f) => serde_json::json!({"model": c.label, "max_pct": f.max_pct, "rms_pct": f.rms_pct}),
                Validation::NotAdmitted { figures: f, why } => serde_json::json!({"model": c.label, "max_pct": f.max_pct, "rms_pct": f.rms_pct, "not_admitted": why}),
                Validation::NotFitted(e) => serde_json::json!({"model": c.label, "error": e}),
            };
            // The compensator's figures beside the forward ones: what it was ranked by.
            if let (Some(i), Some(t), Some(c_max)) = (c.inverse, c.tracking, c.compensated_max_pct) {
                v["inverse_max_pct"] = i.max_pct.into();
                v["tracking_max_pct"] = t.max_pct.into();
                v["compensated_max_pct"] = c_max.into();
            }
            if let Some(why) = &c.set_aside {
                v["set_aside"] = why.as_str().into();
            }
            v
        }).collect::<Vec<_>>(),
        "held_out": r.held_out,
        // The excitation's fastest motion as the model was fitted on it (`identify`'s).
        "fastest_motion_hz": r.file.identification.as_ref().and_then(|i| i.fastest_motion_hz),
        "tracking_before": r.before,
        "tracking_after": r.after,
        "trajectory_range": [r.trajectory_range.0, r.trajectory_range.1],
        "output_unit": r.file.units.output,
        "samples": r.excitation.t.len(),
        "decimation": r.decimation,
        "tick_rate_hz": r.tick_rate_hz,
        "stored": r.stored.map(|m| format!("{m:?}")),
        "clamped": r.clamped,
        "excitation_underran": r.excitation_underran,
        "resonance": match &r.resonance {
            ResonanceOutcome::NotAsked => serde_json::Value::Null,
            ResonanceOutcome::Measured(f) => serde_json::json!({
                "frequency_hz": f.plant.resonance_hz,
                "damping": f.plant.zeta,
                "fit_rms_db": f.rms_db,
                "fit_rms_deg": f.rms_deg,
            }),
            ResonanceOutcome::NotFitted(why) => serde_json::json!({ "not_fitted": why }),
        },
        "params": out.display().to_string(),
        "png": png.display().to_string(),
    })
}

/// Runs `calibrate`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    if args
        .out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("png"))
    {
        bail!(
            "--out {}: the parameter file must not end in .png (the figure goes there)",
            args.out.display()
        );
    }
    let options = args.options();
    options.check()?;
    let mut client = connect(&args.port)?;
    let bar = super::progress::bar(0, "calibrating", "");
    let quiet = args.json || !super::progress::enabled();
    let report = calibrate(&mut client, &options, |p| match p {
        Progress::Step(step) => {
            bar.set_message(step.to_string());
            if !quiet {
                bar.println(step);
            }
        }
        Progress::Count { done, .. } => bar.set_position(done),
    });
    bar.finish_and_clear();
    let report = report?;
    let png = args.out.with_extension("png");
    let mut files = Staged::new();
    let temp_png = files.temporary_for(&png);
    plot(&report, &temp_png)?;
    files.write(&args.out, report.file.to_json().as_bytes())?;
    files.commit()?;
    if report.excitation_underran {
        eprintln!(
            "warning: the excitation's stream found the board's queue empty (a slow link): the model was identified on the drive as applied, held where the queue ran dry"
        );
    }
    if report.clamped {
        eprintln!(
            "warning: the model's input range reaches beyond the drive's (--clamp: loaded anyway)"
        );
    }
    if let ResonanceOutcome::NotFitted(why) = &report.resonance {
        eprintln!(
            "warning: the resonance was not measured: {why}; the parameter file holds none (a preview then needs --resonance-hz and --resonance-damping)"
        );
    }
    if args.json {
        println!("{}", report_json(&report, &args.out, &png));
        return Ok(());
    }
    let unit = &report.file.units.output;
    println!(
        "excited {} s at {} Hz ({} samples, every {} ticks at {} Hz)",
        options.excitation_s(),
        options.excitation_hz,
        report.excitation.t.len(),
        report.decimation,
        report.tick_rate_hz
    );
    if !report.ranking.is_empty() {
        println!("ranking (validation part of the excitation, max error % of span):");
        println!(
            "  (ranked by the larger of inverse and tracking; set aside after the others, with why: a candidate whose inverse is beyond {INVERSE_TO_FORWARD_LIMIT} × its forward max and {INVERSE_TO_FORWARD_LIMIT} × the best inverse)"
        );
        for (i, c) in report.ranking.iter().enumerate() {
            let place = match (c.validation.admitted(), &c.set_aside) {
                (Some(_), None) => format!("{}.", i + 1),
                _ => "-.".into(),
            };
            println!("  {place:<3} {:<40} {}", c.label, c.summary);
        }
    }
    println!("picked: {}", report.reason);
    println!(
        "held-out last cycle: max {:.2} %  RMS {:.2} % of span",
        report.held_out.max_pct, report.held_out.rms_pct
    );
    // What the model has seen of fast motion: the excitation's, the sweep's with
    // `--fastest-hz` (never an octave short of it, so no advice is due).
    let seen = report
        .file
        .identification
        .as_ref()
        .and_then(|r| r.fastest_motion_hz);
    println!(
        "motion: {}",
        twinstack_identify::identification::coverage::seen(seen)
    );
    println!(
        "tracking over {:.2} … {:.2} {unit} (triangle + nested minor loops), % of span:",
        report.trajectory_range.0, report.trajectory_range.1
    );
    for (name, t) in [
        ("before (bypass)", report.before),
        ("after (open loop)", report.after),
    ] {
        println!(
            "  {name:<18} max {:.2} %  RMS {:.2} %{}",
            t.max_pct,
            t.rms_pct,
            if t.underran {
                "  (the stream underran)"
            } else {
                ""
            }
        );
    }
    if let ResonanceOutcome::Measured(f) = &report.resonance {
        println!(
            "resonance: {:.0} Hz, damping {:.4} (fit {:.2} dB, {:.1}° RMS), in the parameter file for `load --preview`, `compensate --preview` and `stream --preview`",
            f.plant.resonance_hz, f.plant.zeta, f.rms_db, f.rms_deg
        );
    }
    match report.stored {
        Some(m) => println!("loaded (open loop) and stored to flash (boots in {m:?})"),
        None => println!("loaded (open loop), not stored (--no-store)"),
    }
    println!("wrote {} and {}", args.out.display(), png.display());
    Ok(())
}

/// The calibration figure: the excitation's fit, the held-out loops, the ranking, and the
/// tracking error before and after.
fn plot(r: &CalibrationReport, path: &Path) -> anyhow::Result<()> {
    let black = RGBColor(0, 0, 0);
    let blue = RGBColor(31, 119, 180);
    let red = RGBColor(214, 39, 40);
    let unit = r.file.units.output.clone();
    let t = &r.excitation.t;
    let u = r.excitation.u.as_deref().unwrap_or_default();
    let x = r.excitation.x.as_deref().unwrap_or_default();
    let line = |label: &str, xs: &[f64], ys: &[f64], color| Series {
        label: label.to_string(),
        points: xs.iter().copied().zip(ys.iter().copied()).collect(),
        color,
    };
    let held = r.held_out_from.min(x.len());
    let mut panels = vec![
        Panel {
            caption: "excitation: measured and model".into(),
            x_label: "t [s]".into(),
            y_label: format!("[{unit}]"),
            series: vec![
                line("measured", t, x, black),
                line(&r.model, t, &r.predicted, blue),
            ],
        },
        Panel {
            caption: "held-out last cycle".into(),
            x_label: "left stack [V]".into(),
            y_label: format!("[{unit}]"),
            series: vec![
                line("measured", &u[held..], &x[held..], black),
                line(
                    "model",
                    &u[held..],
                    &r.predicted[held.min(r.predicted.len())..],
                    blue,
                ),
            ],
        },
    ];
    // The ranking: one bar per candidate at its compensated max error on the validation part
    // (what it was ranked by; its forward max where it has none), best first; the model kept
    // in blue, the others light, one set aside or the board would not run grey.
    let ranking = BarPanel {
        caption: "ranking: validation compensated max error".into(),
        x_label: "[% of span]".into(),
        bars: r
            .ranking
            .iter()
            .enumerate()
            .map(|(i, c)| {
                // The pick heads the ranking.
                let kept = i == 0;
                let value = |f: &ErrorFigures| c.compensated_max_pct.unwrap_or(f.max_pct);
                let (value, note, color) = match &c.validation {
                    Validation::Scored(f) if c.set_aside.is_some() && !kept => {
                        (value(f), "set aside", RGBColor(190, 190, 190))
                    }
                    Validation::Scored(f) => (
                        value(f),
                        if kept { "kept" } else { "" },
                        if kept { blue } else { RGBColor(158, 202, 225) },
                    ),
                    Validation::NotAdmitted { figures, .. } => {
                        (value(figures), "not admitted", RGBColor(190, 190, 190))
                    }
                    Validation::NotFitted(_) => (f64::NAN, "not fitted", RGBColor(190, 190, 190)),
                };
                Bar {
                    label: format!("{}. {}", i + 1, c.label),
                    value,
                    note: note.to_string(),
                    color,
                }
            })
            .collect(),
    };
    let error = |rec: &twinstack_link::capture::Recording, label: String, color| {
        let sp = rec.column(Channel::Setpoint).map(|c| &c.values[..]);
        let se = rec.column(Channel::Sensor).map(|c| &c.values[..]);
        let points = match (sp, se) {
            (Some(sp), Some(se)) => rec
                .t
                .iter()
                .zip(sp.iter().zip(se))
                .map(|(&t, (a, b))| (t, b - a))
                .collect(),
            _ => Vec::new(),
        };
        Series {
            label,
            points,
            color,
        }
    };
    panels.push(Panel {
        caption: "tracking error (sensor - setpoint)".into(),
        x_label: "t from the stream's start [s]".into(),
        y_label: format!("[{unit}]"),
        series: vec![
            error(
                &r.runs[0],
                format!("bypass: max {:.2} %", r.before.max_pct),
                red,
            ),
            error(
                &r.runs[1],
                format!("compensated: max {:.2} %", r.after.max_pct),
                blue,
            ),
        ],
    });
    let mut charts: Vec<Chart> = panels[..2].iter().map(Chart::Lines).collect();
    if !ranking.bars.is_empty() {
        charts.push(Chart::Bars(&ranking));
    }
    charts.extend(panels[2..].iter().map(Chart::Lines));
    draw_charts(
        path,
        &format!(
            "calibrate: {} (held-out max {:.2} %), tracking max {:.2} % -> {:.2} %",
            r.model, r.held_out.max_pct, r.before.max_pct, r.after.max_pct
        ),
        &charts,
        2,
    )?;
    Ok(())
}
