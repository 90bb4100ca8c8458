//! `twinstack lab-stage [--model pi,duhem] [--creep] [--output-map] [--seed N] [--json]
//! [--without creep,…] [--set field=value,…] [--variants] [--tick-rate HZ] [--fastest-hz HZ]
//! [--triangles 1,5,…] [--preview]`: the tracking table on the simulated laboratory stage
//! ([`hal_sim::plant::lab_stage`], outside the model family) — identified from 2 s of 10 Hz
//! excitation (with `--fastest-hz`, a sweep up to it too), then a triangle, nested minor loops
//! and a multisine tracked open loop with each model's compensator and with none
//! ([`crate::tracking`]); with `--variants`, the worst error on each of
//! [`crate::tracking::STAGE_VARIANTS`] (stages the family was not tuned on); with
//! `--preview`, each model again with every trajectory shaped for the stage's resonance,
//! measured as `tune` measures a board's ([`crate::tracking::measure_resonance`]).

use crate::commands::identify::{parse_model, ModelChoice};
use crate::tracking::{
    evaluate_methods_with_triangles, evaluate_variants, excite_with, print_variants, Method,
    BOUC_WEN_VARIANTS, EXCITATION, SAMPLE_RATE_HZ, STAGE_VARIANTS,
};
use hal_sim::plant::{LabStage, LabStageConfig, StageHysteresis};
use std::path::PathBuf;
use twinstack_identify::identification::run::{check_tick_rate, BoardRate};
use twinstack_identify::identification::{IdentifyOptions, ModelKind};
use twinstack_link::output_file::{csv_t_u_x, Staged};

/// Arguments of `twinstack lab-stage`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Models to identify and compensate with, comma-separated (one row each); `auto` ranks
    /// them all as `identify` does and keeps the best.
    #[arg(long, value_delimiter = ',', default_value = "auto,pi,gpi", value_parser = parse_model)]
    pub model: Vec<ModelChoice>,
    /// Fit each model with a creep operator in series (for `auto`: only candidates with creep).
    #[arg(long)]
    pub creep: bool,
    /// Fit a static output map after each Bouc–Wen model, the model refined with it (rows
    /// `bouc-wen+map`, `bouc-wen+map+creep`; the other models as they are, the board takes a
    /// map after a Bouc–Wen only); for `auto`: only the Bouc–Wen candidates with a map.
    /// Without it, auto ranks Bouc–Wen with and without one.
    #[arg(long)]
    pub output_map: bool,
    /// Seed of the stage's sensor noise.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Sample rate of the excitation and of tracking, Hz (2 000 … 100 000).
    #[arg(long, default_value_t = SAMPLE_RATE_HZ)]
    pub rate: f64,
    /// Play operators of a P–I model (1 … the library's maximum).
    #[arg(long, default_value_t = 17)]
    pub operators: usize,
    /// Samples before this time (s) are fitted, the rest of the excitation held out
    /// (default: all but its last cycle, 1.9 s of the 2 s; with `--fastest-hz`, 2.3 of 2.4).
    #[arg(long)]
    pub fit_until: Option<f64>,
    /// The fastest motion to be run, Hz: the excitation gains a sweep up to it before its
    /// multisine, as `calibrate --fastest-hz` streams it (at least 20 samples a cycle at
    /// `--rate`); with `--variants`, every variant is identified from it.
    #[arg(long, value_name = "HZ")]
    pub fastest_hz: Option<f64>,
    /// Print the table as JSON.
    #[arg(long)]
    pub json: bool,
    /// Also write the excitation record (t,u,x) to this CSV, for `twinstack identify`.
    #[arg(long)]
    pub write_excitation: Option<PathBuf>,
    /// The stage's hysteresis: `preisach` (an asymmetric Preisach operator) or `bouc-wen` (a
    /// Bouc–Wen-class operator with `n = 1.5` and a rising branch that saturates first), both
    /// outside the model family; `--set` takes the fields of the one chosen (`preisach.…` or
    /// `bouc_wen.…`), `--variants` its list of variants.
    #[arg(long, value_enum, default_value_t = Hysteresis::Preisach)]
    pub hysteresis: Hysteresis,
    /// Take non-idealities out of the stage, comma-separated, to see what each costs.
    #[arg(long, value_enum, value_delimiter = ',')]
    pub without: Vec<NonIdeality>,
    /// Change the stage's physics, comma-separated `field=value` (the fields: see
    /// `hal_sim::plant::SETTABLE_FIELDS`, e.g. `preisach.bottom_saturation=0.6`,
    /// `flexure_saturation_um=100`, `resonance_hz=1200`).
    #[arg(long, value_delimiter = ',', value_parser = parse_setting)]
    pub set: Vec<(String, f64)>,
    /// Track on every stage of the built-in list of variants (the default stage made
    /// otherwise, one non-ideality at a time and combined) and print each one's worst error.
    #[arg(long, conflicts_with_all = ["set", "without", "write_excitation", "triangles"])]
    pub variants: bool,
    /// Also track a triangle at each of these frequencies, Hz, comma-separated (e.g.
    /// `1,5,20,50,100,200`), over the same span with the same calibration: how one model holds
    /// from slow motion (creep) to fast (the stage's dynamics). At least 20 samples a cycle at
    /// `--rate`; whole cycles for at least a second and at least four.
    #[arg(long, value_delimiter = ',')]
    pub triangles: Vec<f64>,
    /// Also track with a preview: the stage's resonance measured as `twinstack tune` measures
    /// a board's, and each model's row followed by `… + preview`, every trajectory shaped
    /// first so that the resonance does not ring at its corners (`compensate
    /// --resonance-hz`).
    #[arg(long, conflicts_with = "variants")]
    pub preview: bool,
    /// Fit only what the board runs at this control rate, Hz (10 000 … 100 000), as
    /// `calibrate` does: `auto` picks among the models the board's tick budget admits, sized
    /// down where that lets one in (fewer creep modes or play operators, no observer); a
    /// model named with `--model` that does not fit is refused on its row. Without it, every
    /// model is fitted as asked.
    #[arg(long)]
    pub tick_rate: Option<f64>,
}

/// One `--set` entry: `field=value`, the value a number (`inf` for an unbounded field).
fn parse_setting(s: &str) -> Result<(String, f64), String> {
    let (field, value) = s
        .split_once('=')
        .ok_or_else(|| format!("`{s}`: expected field=value"))?;
    let field = field.trim();
    if !hal_sim::plant::SETTABLE_FIELDS.contains(&field) {
        return Err(format!(
            "`{field}`: no such field (the fields: {})",
            hal_sim::plant::SETTABLE_FIELDS.join(", ")
        ));
    }
    let v: f64 = value
        .trim()
        .parse()
        .map_err(|_| format!("`{s}`: `{}` is not a number", value.trim()))?;
    if v.is_nan() {
        return Err(format!("`{s}`: not a number"));
    }
    Ok((field.to_string(), v))
}

/// The stage's hysteresis, as `--hysteresis` names it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Hysteresis {
    /// The asymmetric Preisach operator.
    Preisach,
    /// The Bouc–Wen-class operator.
    BoucWen,
}

impl From<Hysteresis> for StageHysteresis {
    fn from(h: Hysteresis) -> Self {
        match h {
            Hysteresis::Preisach => Self::Preisach,
            Hysteresis::BoucWen => Self::BoucWen,
        }
    }
}

/// The `--set` field that belongs to the hysteresis not chosen, if any, as an error.
fn check_fields_of(chosen: Hysteresis, set: &[(String, f64)]) -> anyhow::Result<()> {
    let prefix = StageHysteresis::from(chosen).prefix();
    let of_a_hysteresis = |f: &str| {
        [StageHysteresis::Preisach, StageHysteresis::BoucWen]
            .iter()
            .any(|h| f.starts_with(h.prefix()))
    };
    if let Some((field, _)) = set
        .iter()
        .find(|(f, _)| of_a_hysteresis(f) && !f.starts_with(prefix))
    {
        anyhow::bail!(
            "--set {field}: the stage's hysteresis is {} (--hysteresis), whose fields are {prefix}…",
            clap::ValueEnum::to_possible_value(&chosen)
                .map_or_else(String::new, |v| v.get_name().to_string()),
        );
    }
    Ok(())
}

/// A non-ideality of the lab stage that `--without` removes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum NonIdeality {
    /// The creep (`creep_per_decade = 0`).
    Creep,
    /// The flexure's nonlinearity (a linear flexure).
    Flexure,
    /// The hysteresis's asymmetry: the Preisach density's bottom saturation made equal to
    /// the top's; the Bouc–Wen-class rising branch's extra saturation (`bouc_wen.rising`) 0.
    Asymmetry,
    /// The sensor noise and rounding.
    Noise,
}

impl NonIdeality {
    /// Removes it from `config`.
    pub fn remove(self, config: &mut LabStageConfig) {
        match self {
            Self::Creep => config.creep_per_decade = 0.0,
            Self::Flexure => config.flexure_saturation_um = f64::INFINITY,
            Self::Asymmetry => match config.hysteresis {
                StageHysteresis::Preisach => {
                    config.preisach.bottom_saturation = config.preisach.top_saturation;
                }
                StageHysteresis::BoucWen => config.bouc_wen.rising = 0.0,
            },
            Self::Noise => {
                config.noise_rms_nm = 0.0;
                config.sensor_lsb_nm = 0.0;
            }
        }
    }
}

/// Runs the evaluation and prints the table.
pub fn run(args: &Args) -> anyhow::Result<()> {
    if !(args.rate.is_finite() && (2_000.0..=100_000.0).contains(&args.rate)) {
        anyhow::bail!("--rate {} is outside 2 000 … 100 000 Hz", args.rate);
    }
    let excitation = match args.fastest_hz {
        Some(hz) => EXCITATION.reaching(hz),
        None => EXCITATION,
    };
    if let Err((_, rule, value)) = excitation.check() {
        anyhow::bail!(
            "--fastest-hz {value}: must be {rule} ({} Hz)",
            excitation.hz
        );
    }
    let length = excitation.duration_s();
    let fit_until = args.fit_until.unwrap_or(excitation.held_out_from_s());
    if !(fit_until.is_finite() && fit_until > 0.1 && fit_until < length) {
        anyhow::bail!(
            "--fit-until {fit_until} must lie within 0.1 … {length} s (the excitation's length), leaving a part to hold out",
        );
    }
    if !(1..=twinstack::MAX_OPERATORS).contains(&args.operators) {
        anyhow::bail!(
            "--operators {}: must be 1 to {}",
            args.operators,
            twinstack::MAX_OPERATORS
        );
    }
    if args.model.is_empty() {
        anyhow::bail!("--model: name at least one model");
    }
    let board = match args.tick_rate {
        Some(hz) => {
            check_tick_rate(hz).map_err(|e| anyhow::anyhow!("--tick-rate {e}"))?;
            Some(BoardRate::sizing(hz, false))
        }
        None => None,
    };
    let mut config = LabStageConfig::new(args.rate, args.seed);
    config.hysteresis = args.hysteresis.into();
    check_fields_of(args.hysteresis, &args.set)?;
    for n in &args.without {
        n.remove(&mut config);
    }
    for (field, value) in &args.set {
        config.set(field, *value)?;
    }
    config.validate()?;
    let options = |kind: ModelKind| IdentifyOptions {
        operators: args.operators,
        creep: args.creep,
        output_map: args.output_map && IdentifyOptions::takes_output_map(kind),
        ..IdentifyOptions::new(kind, fit_until)
    };
    let methods: Vec<Method> = args
        .model
        .iter()
        .map(|&m| match m {
            ModelChoice::Only(kind) => Method::One(options(kind)),
            ModelChoice::Auto => Method::Auto(
                IdentifyOptions {
                    output_map: args.output_map,
                    ..options(ModelKind::Pi)
                }
                .candidates(),
            ),
        })
        .collect();
    if let Some(path) = &args.write_excitation {
        let data = excite_with(&mut LabStage::new(&config)?, &excitation);
        let (u, x) = (data.u.unwrap_or_default(), data.x.unwrap_or_default());
        let mut out = Staged::new();
        out.write(path, &csv_t_u_x(&data.t, &u, &x)?)?;
        out.commit()?;
    }
    let mut stdout = std::io::stdout().lock();
    if args.variants {
        let variants: &[_] = match config.hysteresis {
            StageHysteresis::Preisach => &STAGE_VARIANTS,
            StageHysteresis::BoucWen => &BOUC_WEN_VARIANTS,
        };
        let tables = evaluate_variants(&config, variants, &methods, board.as_ref(), &excitation)?;
        if args.json {
            use std::io::Write;
            serde_json::to_writer_pretty(&mut stdout, &tables)?;
            writeln!(stdout)?;
        } else {
            print_variants(&tables, &mut stdout)?;
        }
        return Ok(());
    }
    let table = evaluate_methods_with_triangles(
        &config,
        &methods,
        &args.triangles,
        board.as_ref(),
        args.preview,
        &excitation,
    )?;
    if args.json {
        use std::io::Write;
        serde_json::to_writer_pretty(&mut stdout, &table)?;
        writeln!(stdout)?;
    } else {
        table.print(&mut stdout)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_non_ideality_is_removed_from_the_stage() {
        let base = LabStageConfig::new(SAMPLE_RATE_HZ, 1);
        let without = |n: NonIdeality| {
            let mut c = base.clone();
            n.remove(&mut c);
            c
        };
        assert_eq!(without(NonIdeality::Creep).creep_per_decade, 0.0);
        assert!(without(NonIdeality::Flexure)
            .flexure_saturation_um
            .is_infinite());
        let sym = without(NonIdeality::Asymmetry).preisach;
        assert_eq!(sym.bottom_saturation, sym.top_saturation);
        assert_ne!(
            base.preisach.bottom_saturation,
            base.preisach.top_saturation
        );
        let quiet = without(NonIdeality::Noise);
        assert_eq!((quiet.noise_rms_nm, quiet.sensor_lsb_nm), (0.0, 0.0));
        // Each leaves a stage that builds.
        for c in [quiet, without(NonIdeality::Flexure)] {
            LabStage::new(&c).unwrap();
        }
    }
}
