//! `hal-sim lab-stage [--model pi,duhem] [--seed N] [--json]`: the tracking table on the
//! simulated laboratory stage ([`crate::plant::lab_stage`], outside the model family) —
//! identified from 2 s of 10 Hz excitation, then a triangle, nested minor loops and a
//! multisine tracked open loop with each model's compensator and with none
//! ([`crate::tracking`]).

use crate::identification::{IdentifyOptions, ModelKind};
use crate::output_file::{csv_t_u_x, Staged};
use crate::plant::{LabStage, LabStageConfig};
use crate::tracking::{evaluate, excite, EXCITATION_S, FIT_UNTIL_S, SAMPLE_RATE_HZ};
use std::path::PathBuf;

/// Arguments of `hal-sim lab-stage`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Models to identify and compensate with, comma-separated (one row each).
    #[arg(long, value_enum, value_delimiter = ',', default_values_t = [ModelKind::Pi, ModelKind::Duhem])]
    pub model: Vec<ModelKind>,
    /// Seed of the stage's sensor noise.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Sample rate of the excitation and of tracking, Hz (2 000 … 100 000).
    #[arg(long, default_value_t = SAMPLE_RATE_HZ)]
    pub rate: f64,
    /// Play operators of a P–I model (1 … the library's maximum).
    #[arg(long, default_value_t = 17)]
    pub operators: usize,
    /// Samples before this time (s) are fitted, the rest of the 2 s excitation held out.
    #[arg(long, default_value_t = FIT_UNTIL_S)]
    pub fit_until: f64,
    /// Print the table as JSON.
    #[arg(long)]
    pub json: bool,
    /// Also write the excitation record (t,u,x) to this CSV, for `hal-sim identify`.
    #[arg(long)]
    pub write_excitation: Option<PathBuf>,
}

/// Runs the evaluation and prints the table.
pub fn run(args: &Args) -> anyhow::Result<()> {
    if !(args.rate.is_finite() && (2_000.0..=100_000.0).contains(&args.rate)) {
        anyhow::bail!("--rate {} is outside 2 000 … 100 000 Hz", args.rate);
    }
    if !(args.fit_until.is_finite() && args.fit_until > 0.1 && args.fit_until < EXCITATION_S) {
        anyhow::bail!(
            "--fit-until {} must lie within 0.1 … {EXCITATION_S} s (the excitation's length), leaving a part to hold out",
            args.fit_until
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
    let config = LabStageConfig::new(args.rate, args.seed);
    let options: Vec<IdentifyOptions> = args
        .model
        .iter()
        .map(|&m| IdentifyOptions {
            operators: args.operators,
            ..IdentifyOptions::new(m, args.fit_until)
        })
        .collect();
    if let Some(path) = &args.write_excitation {
        let data = excite(&mut LabStage::new(&config)?);
        let (u, x) = (data.u.unwrap_or_default(), data.x.unwrap_or_default());
        let mut out = Staged::new();
        out.write(path, csv_t_u_x(&data.t, &u, &x).as_bytes())?;
        out.commit()?;
    }
    let table = evaluate(&config, &options)?;
    let mut stdout = std::io::stdout().lock();
    if args.json {
        use std::io::Write;
        serde_json::to_writer_pretty(&mut stdout, &table)?;
        writeln!(stdout)?;
    } else {
        table.print(&mut stdout)?;
    }
    Ok(())
}
