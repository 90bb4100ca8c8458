//! `twinstack identify [--model auto|pi|duhem|gpi|…] [--creep] [--output-map] --data FILE.csv --fit-until SECONDS
//! --out PARAMS.json [--operators N] [--thresholds uniform|geometric] [--lag N]`: fits on
//! `t < SECONDS`, scores
//! on the rest, writes the parameter file and a PNG beside it (`PARAMS.png`).

use crate::plot::{draw, IdentificationFigure};
use anyhow::{anyhow, bail};
use std::path::PathBuf;
use twinstack_identify::identification::auto::{Size, INVERSE_TO_FORWARD_LIMIT};
use twinstack_identify::identification::coverage;
use twinstack_identify::identification::run::{
    check_tick_rate, identify_and_score, BoardRate, RunError,
};
use twinstack_identify::identification::score::ErrorFigures;
use twinstack_identify::identification::{
    half_samples, IdentifyError, IdentifyOptions, ModelKind, ThresholdSpread, DEFAULT_OPERATORS,
};
use twinstack_link::measured_data::{ColumnNames, Columns, MeasuredData};
use twinstack_link::output_file::Staged;

/// Arguments of `identify`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Model to fit: `auto` (the default) fits every model on the first part of the fit
    /// window, ranks them on its last part and keeps the best; or one model by name.
    #[arg(long, default_value = "auto", value_parser = parse_model,
          value_name = "auto|pi|gpi|bouc-wen|duhem")]
    pub model: ModelChoice,
    /// Measured CSV (t,u,x).
    #[arg(long)]
    pub data: PathBuf,
    /// Names of the t, u, x columns in the CSV when it calls them something else (matched
    /// without unit suffix and case, like the header): `--columns t=time,u=drive,x=sensor`.
    #[arg(long, value_name = "t=NAME,u=NAME,x=NAME")]
    pub columns: Option<ColumnNames>,
    /// Fit on samples with t < SECONDS, score on the rest.
    #[arg(long, value_name = "SECONDS")]
    pub fit_until: f64,
    /// Parameter file to write (the figure goes beside it, extension .png).
    #[arg(long)]
    pub out: PathBuf,
    /// Play operators of a P–I model (1 to 32) [default: 17, or with `--tick-rate` as many as
    /// the board runs at that rate where 17 are too many].
    #[arg(long)]
    pub operators: Option<usize>,
    /// Spread of the P–I thresholds.
    #[arg(long, value_enum, default_value_t = Spread::Uniform)]
    pub thresholds: Spread,
    /// Sensor lag in samples, a whole or a half number (1.5: a reading of a held drive's end,
    /// one and a half samples after the middle of its hold); estimated in half samples over 0
    /// to 10 when not given.
    #[arg(long, allow_negative_numbers = true, value_parser = parse_lag)]
    pub lag: Option<f64>,
    /// Fit a creep operator (4 log-spaced first-order modes, 10 samples to the fit window,
    /// at most 100 s) in series with the model. It is kept only where it lowers the fit
    /// error (modes fitted with no weight are dropped), and the run says what was kept
    /// ("creep asked for, none kept" when nothing was). With `--model auto`, only the
    /// candidates with creep are ranked (the ranking says so); without `--creep`, auto ranks
    /// every model with and without creep.
    #[arg(long)]
    pub creep: bool,
    /// Fit a static output map after a Bouc–Wen model (the board runs it between the model
    /// and the creep), the model refined with it: a monotone dead-zone curve, four dead zones
    /// a side, for what bends every branch alike (a flexure's stiffening, a lever, a sensor's
    /// curve), which a Bouc–Wen output, linear in its state, cannot follow. It is kept only
    /// where it lowers the fit error, and the run says so. Bouc–Wen only, as the board takes
    /// it (the generalised P–I has its own map). With `--model auto`, only the Bouc–Wen
    /// candidates with a map are ranked; without it, auto ranks Bouc–Wen with and without
    /// one.
    #[arg(long)]
    pub output_map: bool,
    /// Keep only a model the board runs at this control rate, Hz (its tick budget, as the
    /// board applies it at load, with the file's settings): `auto` picks among those, a P–I
    /// gets fewer operators where that makes it fit (unless `--operators` is given), a model
    /// asked for by name that does not fit is an error. Without it any model is kept, and a
    /// fast board may refuse the file.
    #[arg(long, value_name = "HZ")]
    pub tick_rate: Option<f64>,
    /// With `--tick-rate`: the board is a dual-stage image whose coarse task runs at this
    /// rate, Hz (5000 on the shipped images), and its share of each tick is charged beside
    /// every model, as the board charges it (`twinstack budget --coarse-rate` prints the
    /// rates). Without it the file is sized for a piezo-only image, which a dual-stage board
    /// at the same rate may refuse.
    #[arg(
        long,
        value_name = "HZ",
        requires = "tick_rate",
        allow_negative_numbers = true
    )]
    pub coarse_rate: Option<f64>,
    /// Write the model as the compensator only, not as the observer too: the board then has
    /// no estimate of the displacement and no drift check of its sensor, and its tick saves
    /// the observer's cost, so that with `--tick-rate` larger models are admitted (a
    /// generalised P–I at 100 kHz; `twinstack budget` shows each model's figures).
    #[arg(long)]
    pub no_observer: bool,
    /// Unit of the x column, recorded in the parameter file.
    #[arg(long, default_value = "units of the x column")]
    pub output_unit: String,
    /// The fastest motion you will run with the model, Hz. The run prints the fitted part's
    /// own fastest motion either way (the highest rate at which its drive swings by a fifth
    /// of its span or more); where that is more than an octave slower than this, it says so
    /// and how to record an excitation that reaches it (`twinstack calibrate --fastest-hz`).
    #[arg(long, value_name = "HZ", allow_negative_numbers = true)]
    pub fastest_hz: Option<f64>,
}

use twinstack::config::tick_budget::coarse_task_share;
pub use twinstack_identify::identification::run::{parse_model, ModelChoice};

/// `--lag`: a whole or a half number of samples ([`half_samples`]).
fn parse_lag(s: &str) -> Result<f64, String> {
    let v: f64 = s
        .parse()
        .map_err(|_| format!("lag {s}: not a number of samples"))?;
    half_samples(v).map(|_| v)
}

/// `--thresholds` values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Spread {
    /// r_i = (i - 1)/N · A.
    Uniform,
    /// Geometric progression, denser near zero.
    Geometric,
}

fn show(f: &ErrorFigures) -> String {
    format!(
        "max {:.2} %  RMS {:.2} %  ({} samples)",
        f.max_pct, f.rms_pct, f.samples
    )
}

/// Runs `identify`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    if !args.fit_until.is_finite() {
        bail!(
            "--fit-until {}: not a finite number of seconds",
            args.fit_until
        );
    }
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
    if let Some(rate) = args.tick_rate {
        check_tick_rate(rate).map_err(|e| anyhow!("--tick-rate {e}"))?;
    }
    if let Some(hz) = args.fastest_hz {
        coverage::check_named(hz).map_err(|e| anyhow!("--fastest-hz {e}"))?;
    }
    let coarse = super::budget::coarse_rate_hz(args.coarse_rate)?;
    let data = MeasuredData::read_with(
        &args.data,
        Columns::TimeDriveOutput,
        &args.columns.clone().unwrap_or_default(),
    )?;
    let mut options = IdentifyOptions::new(ModelKind::Pi, args.fit_until);
    options.operators = args.operators.unwrap_or(DEFAULT_OPERATORS);
    options.thresholds = match args.thresholds {
        Spread::Uniform => ThresholdSpread::Uniform,
        Spread::Geometric => ThresholdSpread::Geometric,
    };
    if let Some(lag) = args.lag {
        options.given_lag(lag).map_err(|e| anyhow!("--lag: {e}"))?;
    }
    options.observer = !args.no_observer;
    options.output_map = args.output_map;
    let in_file = |e: RunError| match e {
        RunError::Params(e) => anyhow!("{e}"),
        // The rate or an option refused the models, not the file.
        // What identify can change to make a model fit the rate: its own options only.
        RunError::Identify(e @ IdentifyError::NoneAdmitted(_)) => anyhow!(
            "{e} (a smaller model runs faster: fewer --operators, no --creep, another --model, \
             {}or a lower --tick-rate)",
            if args.no_observer {
                ""
            } else {
                "the compensator alone (--no-observer: no estimate, no drift check), "
            }
        ),
        RunError::Identify(
            e @ (IdentifyError::BadOperatorCount(_) | IdentifyError::BadCreepModes(_)),
        ) => anyhow!("{e}"),
        RunError::Identify(e @ IdentifyError::NoOutputMapFor(_)) => anyhow!("--output-map: {e}"),
        e => anyhow!("{}: {e}", args.data.display()),
    };
    let run = identify_and_score(
        &data,
        args.model,
        &options,
        args.creep.then_some(true),
        &args.output_unit,
        args.tick_rate.map(|hz| {
            // The board's rate is a whole number of hertz, as the share is computed there.
            BoardRate::sizing(hz, args.operators.is_some())
                .beside(coarse_task_share(coarse, hz as u32))
        }),
    )
    .map_err(in_file)?;
    if let Some(auto) = &run.auto {
        println!(
            "ranking (fitted on t < {:.4} s, scored on {:.4} <= t < {} s):",
            auto.validation_from_s, auto.validation_from_s, args.fit_until
        );
        println!(
            "  (compensated max = the larger of inverse and tracking; inverse: compensate on the measured x against the measured u; tracking: that drive through the best forward model)"
        );
        println!(
            "  (ranked by compensated max; set aside after the others, with why: a candidate whose inverse is beyond {INVERSE_TO_FORWARD_LIMIT} × its forward max and {INVERSE_TO_FORWARD_LIMIT} × the best inverse)"
        );
        if args.creep {
            println!("  (--creep: only the candidates with creep are ranked)");
        }
        if args.output_map {
            println!("  (--output-map: only the candidates with an output map are ranked)");
        }
        for (i, r) in auto.ranking.iter().enumerate() {
            let place = match (r.validation.admitted(), &r.set_aside) {
                (Some(_), None) => format!("{}.", i + 1),
                _ => "-.".into(),
            };
            println!("  {place:<3} {:<40} {}", r.label, r.summary());
        }
        println!("picked: {}", auto.reason);
    }
    // A model asked for by name, made smaller to run at the board's rate, says so.
    let sized = run
        .auto
        .is_none()
        .then(|| Size::of(&run.options).sized_down_note(&Size::of(&options)))
        .flatten();
    let (options, id, record) = (&run.options, &run.identification, &run.record);
    let t = &data.t;
    let u = data.u.as_deref().unwrap_or_default();
    let x = data.x.as_deref().unwrap_or_default();
    let model = &id.model;
    let (fit, held_out, inverse) = (record.fit, record.held_out, record.inverse_held_out);
    let fit_from = id.motion.first_fitted;
    let held = id.held_out_from;
    let model_name = options.label_of_fit(model);
    println!("identified {model_name} from {}", args.data.display());
    if let Some(note) = sized {
        println!("  note: sized to the board's rate: {note}");
    }
    println!(
        "  fitted t = {:.4} .. {} s ({} rows, {} outliers dropped), scored t >= {} s",
        t[fit_from], args.fit_until, id.fitted_rows, id.outliers, args.fit_until
    );
    println!(
        "  sensor lag {} samples ({}), output sign {:+}",
        id.lag_samples,
        if id.lag_estimated {
            "estimated"
        } else {
            "given"
        },
        model.output_sign
    );
    for note in &id.notes {
        println!("  note: {note}");
    }
    println!("  motion: {}", coverage::seen(record.fastest_motion_hz));
    if let Some(advice) = args
        .fastest_hz
        .and_then(|n| coverage::advice(record.fastest_motion_hz, n))
    {
        println!("  note: {advice}");
    }
    println!("  fit      (predict vs measured x): {}", show(&fit));
    println!("  held-out (predict vs measured x): {}", show(&held_out));
    println!(
        "  inverse held-out (compensate u vs measured u): {}",
        show(&inverse)
    );
    println!(
        "  inverse held-out, f64 reference: {}",
        show(&run.inverse_reference)
    );
    println!(
        "  fixed point vs f64 reference: predict max {:.2e} %, compensate max {:.2e} % of span",
        record.fixed_vs_reference_max_pct, record.inverse_fixed_vs_reference_max_pct
    );

    let file = &run.file;

    let figure_path = args.out.with_extension("png");
    let mut out = Staged::new();
    let temp_png = out.temporary_for(&figure_path);
    let title = format!(
        "{model_name}: held-out max {:.2} % RMS {:.2} % of span ({})",
        held_out.max_pct,
        held_out.rms_pct,
        args.data
            .file_name()
            .map(|f| f.to_string_lossy().into_owned())
            .unwrap_or_default()
    );
    draw(
        &temp_png,
        &IdentificationFigure {
            title: &title,
            t,
            u,
            measured: x,
            model: &run.predicted,
            held_out_from: held,
            fit_from,
            output_unit: &args.output_unit,
        },
    )?;
    out.write(&args.out, file.to_json().as_bytes())?;
    out.commit()?;
    println!("wrote {} and {}", args.out.display(), figure_path.display());
    Ok(())
}
