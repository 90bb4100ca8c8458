//! `hal-sim load --port PORT --params PARAMS.json [--mode …] [--store] [drive options]`: sends
//! the parameter file `identify` writes as one parameter load (the board validates it whole
//! and swaps it in between two ticks), optionally storing it to flash.
//!
//! The drive settings, feedback gains and mode are not in the file; they default to the
//! firmware's compiled-in drive (see [`DriveOptions`]) and can be set here. Everything is
//! checked before anything is sent (see [`crate::link::param_set`]).

use super::board_link::{connect, PortArgs};
use crate::link::param_set::{param_set, DriveOptions};
use crate::param_file::ParamFile;
use std::path::PathBuf;
use twinstack::drive::{Configuration, SafeState};
use twinstack::protocol::messages::{Mode, ModelParams};

/// Arguments of `load`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// Parameter file written by `identify`.
    #[arg(long)]
    pub params: PathBuf,
    /// Mode to enter once loaded.
    #[arg(long, value_enum, default_value_t = ModeArg::OpenLoop)]
    pub mode: ModeArg,
    /// Also write the parameters to the board's flash.
    #[arg(long)]
    pub store: bool,
    /// Drive only the left stack (the right one idles at the bias).
    #[arg(long)]
    pub unidirectional: bool,
    /// Bias ū, volts [default: 70].
    #[arg(long)]
    pub bias: Option<f64>,
    /// Lowest stack voltage, volts [default: 0].
    #[arg(long, allow_negative_numbers = true)]
    pub min_voltage: Option<f64>,
    /// Highest stack voltage, volts [default: 140].
    #[arg(long)]
    pub max_voltage: Option<f64>,
    /// Slew limit, volts per second [default: 2e6].
    #[arg(long)]
    pub slew_rate: Option<f64>,
    /// Where the outputs go on a fault.
    #[arg(long, value_enum, default_value_t = SafeArg::Bias)]
    pub safe_state: SafeArg,
    /// PI feedback proportional gain [default: 0.2].
    #[arg(long)]
    pub kp: Option<f64>,
    /// PI feedback integral gain per second [default: 500, i.e. 0.01 per tick at 50 kHz].
    #[arg(long)]
    pub ki: Option<f64>,
    /// Largest feedback correction, fraction of the drive range [default: 0.2].
    #[arg(long)]
    pub correction_limit: Option<f64>,
    /// No sensor feedback (open loop and bypass only).
    #[arg(long, conflicts_with_all = ["kp", "ki", "correction_limit"])]
    pub no_feedback: bool,
}

/// `--mode` values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum ModeArg {
    /// No compensation.
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

/// `--safe-state` values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum SafeArg {
    /// Both stacks at the bias.
    Bias,
    /// Both stacks at 0 V.
    Zero,
}

/// The drive options `args` ask for.
pub fn drive_options(args: &Args) -> DriveOptions {
    let mut d = DriveOptions::default();
    if args.unidirectional {
        d.configuration = Configuration::Unidirectional;
    }
    d.bias = args.bias.unwrap_or(d.bias);
    d.voltage_limits = [
        args.min_voltage.unwrap_or(d.voltage_limits[0]),
        args.max_voltage.unwrap_or(d.voltage_limits[1]),
    ];
    d.slew_rate = args.slew_rate.unwrap_or(d.slew_rate);
    d.safe_state = match args.safe_state {
        SafeArg::Bias => SafeState::Bias,
        SafeArg::Zero => SafeState::Zero,
    };
    d.feedback = if args.no_feedback {
        None
    } else {
        d.feedback.map(|[kp, ki, limit]| {
            [
                args.kp.unwrap_or(kp),
                args.ki.unwrap_or(ki),
                args.correction_limit.unwrap_or(limit),
            ]
        })
    };
    d.mode = args.mode.into();
    d
}

/// Runs `load`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let (_, model) = ParamFile::load(&args.params)?;
    let set = param_set(&model, &drive_options(args))
        .map_err(|e| anyhow::anyhow!("{}: {e}; nothing was sent", args.params.display()))?;
    let mut client = connect(&args.port)?;
    client.load_params(&set)?;
    let what = match &set.model {
        ModelParams::PrandtlIshlinskii { thresholds, .. } => {
            format!("P–I, {} operators", thresholds.len())
        }
        ModelParams::Duhem { .. } => "Duhem".to_string(),
    };
    println!(
        "loaded {} ({what}), mode {:?}, drive {:?} {}…{} V bias {} V",
        args.params.display(),
        set.mode,
        set.configuration,
        set.voltage_limits[0],
        set.voltage_limits[1],
        set.bias
    );
    if args.store {
        client.store_params()?;
        println!("stored to flash");
    }
    Ok(())
}
