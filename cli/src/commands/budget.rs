//! `twinstack budget [PARAMS.json …] [--rate HZ] [--coarse-rate HZ] [--json]`: what each configuration costs the
//! control tick (the whole interrupt's predicted worst case, cycles at 5 flash wait states) and
//! the highest control rate the board admits it at — as loaded, without its observer, and with
//! the learning, a scan, the trigger input, a capture and telemetry beside it. Without files, every model
//! `calibrate` can pick, loaded as it loads them ([`twinstack_identify::budget::family`]).

use anyhow::Context as _;
use std::path::PathBuf;
use twinstack::board::Hardware;
use twinstack::config::tick_budget::TICK_SHARE_PERCENT;
use twinstack_identify::budget::{family, BudgetRow, Prediction};
use twinstack_identify::param_file::ParamFile;

/// Arguments of `budget`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Parameter files (as `identify` and `calibrate` write them); none: the model family.
    pub params: Vec<PathBuf>,
    /// Also say whether each is admitted at this control rate, Hz.
    #[arg(long, allow_negative_numbers = true)]
    pub rate: Option<f64>,
    /// Print JSON (one object per configuration) instead of the table.
    #[arg(long)]
    pub json: bool,
    /// The board is a dual-stage image whose coarse task runs at this rate, Hz (5000 on the
    /// shipped images): its share of each tick (3 600 cycles a coarse period) is charged
    /// beside every configuration, as the board charges it, so the rates are lower.
    #[arg(long, value_name = "HZ", allow_negative_numbers = true)]
    pub coarse_rate: Option<f64>,
}

/// `--coarse-rate` as the board takes it: a positive number of hertz, rounded up to a whole
/// one (the dual-stage image's rounding, `PreparedCoarse::new`), at most the highest control
/// rate.
pub fn coarse_rate_hz(hz: Option<f64>) -> anyhow::Result<u32> {
    let Some(hz) = hz else {
        return Ok(0);
    };
    let max = f64::from(Hardware::MAX_CONTROL_RATE_HZ);
    if !(hz.is_finite() && hz > 0.0 && hz <= max) {
        anyhow::bail!("--coarse-rate {hz}: must be above 0 and at most {max} Hz");
    }
    Ok(hz.ceil() as u32)
}

/// Runs `budget`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    if let Some(rate) = args.rate {
        if !(rate.is_finite() && rate > 0.0) {
            anyhow::bail!("--rate {rate}: not a positive number of hertz");
        }
    }
    let coarse = coarse_rate_hz(args.coarse_rate)?;
    let mut rows = Vec::new();
    if args.params.is_empty() {
        for (name, settings) in family() {
            rows.push(
                BudgetRow::beside_coarse(&name, &settings, coarse)
                    .map_err(|e| anyhow::anyhow!("{name}: {e}"))?,
            );
        }
    } else {
        for path in &args.params {
            let (file, _) = ParamFile::load(path)?;
            let name = path.display().to_string();
            let row = BudgetRow::beside_coarse(&name, &file.settings, coarse)
                .map_err(|e| anyhow::anyhow!("{e}"))
                .with_context(|| format!("{name}: the board refuses these settings"))?;
            rows.push(row);
        }
    }
    if args.json {
        let out: Vec<_> = rows
            .iter()
            .map(|r| {
                let mut v = serde_json::to_value(r).unwrap_or_default();
                if let Some(rate) = args.rate {
                    v["admitted_at_rate"] = r.loaded.admitted_at(rate).into();
                }
                v
            })
            .collect();
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    if coarse > 0 {
        println!(
            "On a dual-stage image whose coarse task runs at {coarse} Hz: its share of each tick is charged beside every configuration.\n"
        );
    }
    print!("{}", table(&rows, args.rate));
    Ok(())
}

/// `12.3 kHz`, or the board's limit when the budget allows more.
fn rate(p: &Prediction) -> String {
    let max = f64::from(Hardware::MAX_CONTROL_RATE_HZ);
    if p.highest_rate_hz < f64::from(Hardware::MIN_CONTROL_RATE_HZ) {
        // Below the board's slowest rate (beside a coarse task that takes the period: none).
        if p.highest_rate_hz > 0.0 {
            format!("none ({})", kilo(p.highest_rate_hz))
        } else {
            "none".into()
        }
    } else if p.highest_rate_hz >= max {
        format!("{} ({:.1})", kilo(max), p.highest_rate_hz / 1e3)
    } else {
        kilo(p.highest_rate_hz)
    }
}

fn kilo(hz: f64) -> String {
    format!("{:.1} kHz", hz / 1e3)
}

fn table(rows: &[BudgetRow], at: Option<f64>) -> String {
    let mut out = format!(
        "Predicted worst tick (cycles at 5 wait states) and the highest rate admitted ({TICK_SHARE_PERCENT} % of the period; the board runs {}–{} kHz, the budget's own figure in brackets where it allows more):\n\n",
        Hardware::MIN_CONTROL_RATE_HZ / 1000,
        Hardware::MAX_CONTROL_RATE_HZ / 1000
    );
    out += "| configuration | as loaded | highest rate | without its observer | highest rate | + learning + scan + trigger + capture + telemetry | highest rate |";
    if let Some(r) = at {
        out += &format!(" admitted at {} |", kilo(r));
    }
    out += "\n|---|---:|---:|---:|---:|---:|---:|";
    if at.is_some() {
        out += "---|";
    }
    out += "\n";
    for r in rows {
        let (without, without_rate) = match &r.without_observer {
            Some(p) => (p.cycles.to_string(), rate(p)),
            None => ("–".into(), "–".into()),
        };
        out += &format!(
            "| {} | {} | {} | {} | {} | {} | {} |",
            r.name,
            r.loaded.cycles,
            rate(&r.loaded),
            without,
            without_rate,
            r.every_feature.cycles,
            rate(&r.every_feature)
        );
        if let Some(at) = at {
            let yes = |p: &Prediction| if p.admitted_at(at) { "yes" } else { "no" };
            let bare = r.without_observer.as_ref().map_or("–", yes);
            out += &format!(
                " {} (without its observer: {}; with every feature: {}) |",
                yes(&r.loaded),
                bare,
                yes(&r.every_feature)
            );
        }
        out += "\n";
    }
    out
}
