//! `hal-sim`: the PC-side tools of the twinstack board (see `hal-sim --help`).

use clap::{Parser, Subcommand};
use hal_sim::cli;

/// Host tools for the twinstack piezo front-end.
#[derive(Debug, Parser)]
#[command(name = "hal-sim", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// One variant per subcommand, each delegating to `hal_sim::cli::<name>::run`.
#[derive(Debug, Subcommand)]
enum Command {
    /// Fit a P–I or Duhem model to a measured CSV and write a parameter file and a figure.
    Identify(cli::identify::Args),
    /// Run the fixed-point forward model on a drive record.
    Predict(cli::predict::Args),
    /// Run the fixed-point inverse model on a desired-output record.
    Compensate(cli::compensate::Args),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let result = match &cli.command {
        Command::Identify(a) => cli::identify::run(a),
        Command::Predict(a) => cli::predict::run(a),
        Command::Compensate(a) => cli::compensate::run(a),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
