//! `twinstack params --port PORT [--out FILE]`: reads back the settings in force on the board
//! (physical units, the same JSON a parameter file's `settings` holds); `twinstack mode` and
//! `twinstack recall` switch the mode and reload the stored settings.

use super::board_link::{connect, PortArgs};
use std::path::PathBuf;
use twinstack::config::settings::Mode;

/// `--mode` values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum ModeArg {
    /// No compensation: the drive follows the setpoint.
    Bypass,
    /// Inverse-model feedforward.
    OpenLoop,
    /// Feedforward plus sensor feedback.
    ClosedLoop,
}

impl From<ModeArg> for Mode {
    fn from(m: ModeArg) -> Self {
        match m {
            ModeArg::Bypass => Mode::Bypass,
            ModeArg::OpenLoop => Mode::OpenLoop,
            ModeArg::ClosedLoop => Mode::ClosedLoop,
        }
    }
}

/// Arguments of `params`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// Write the settings to this file (JSON) instead of printing them.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// Runs `params`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let mut client = connect(&args.port)?;
    let settings = client.read_params()?;
    let text = serde_json::to_string_pretty(&settings)? + "\n";
    match &args.out {
        Some(path) => {
            std::fs::write(path, text)?;
            println!("wrote {}", path.display());
        }
        None => print!("{text}"),
    }
    Ok(())
}

/// Arguments of `mode`.
#[derive(Debug, clap::Args)]
pub struct ModeArgs {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// The mode to switch to (bumpless, between two ticks).
    #[arg(value_enum)]
    pub mode: ModeArg,
}

/// Runs `mode`.
pub fn run_mode(args: &ModeArgs) -> anyhow::Result<()> {
    let mut client = connect(&args.port)?;
    client.set_mode(args.mode.into())?;
    println!("mode {:?}", Mode::from(args.mode));
    Ok(())
}

/// Arguments of `recall`.
#[derive(Debug, clap::Args)]
pub struct RecallArgs {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
}

/// Runs `recall`.
pub fn run_recall(args: &RecallArgs) -> anyhow::Result<()> {
    let mut client = connect(&args.port)?;
    client.recall_params()?;
    println!("recalled the stored settings");
    Ok(())
}
