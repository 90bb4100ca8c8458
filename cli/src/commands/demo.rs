//! `twinstack demo`: the first paper's study on the simulated board and stage.

use crate::demo::{print, run as run_demo, DemoOptions};
use std::path::PathBuf;

/// Arguments of `twinstack demo`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Directory for the PNG figures.
    #[arg(long, default_value = "out")]
    pub out: PathBuf,
    /// Cycles per simulated run (at least 4; identification fits the first half).
    #[arg(long, default_value_t = 40)]
    pub cycles: usize,
    /// Control rate, Hz (10 000 … 100 000).
    #[arg(long, default_value_t = 50_000.0)]
    pub rate: f64,
    /// Excitation and tracking frequency, Hz.
    #[arg(long, default_value_t = 750.0)]
    pub frequency: f64,
    /// Hide the progress bars.
    #[arg(long)]
    pub quiet: bool,
}

/// Runs the demo and prints its tables.
pub fn run(args: &Args) -> anyhow::Result<()> {
    if !(10_000.0..=100_000.0).contains(&args.rate) {
        anyhow::bail!("--rate {} is outside 10 000 … 100 000 Hz", args.rate);
    }
    if !(args.frequency > 0.0 && args.frequency < args.rate / 8.0) {
        anyhow::bail!(
            "--frequency {} must be positive and below an eighth of the control rate",
            args.frequency
        );
    }
    if args.cycles < 4 || args.cycles > 100_000 {
        anyhow::bail!("--cycles {} is outside 4 … 100 000", args.cycles);
    }
    let report = run_demo(&DemoOptions {
        control_rate: args.rate,
        frequency: args.frequency,
        cycles: args.cycles,
        out_dir: args.out.clone(),
        progress: !args.quiet,
    })?;
    print(&report, &mut std::io::stdout().lock())?;
    Ok(())
}
