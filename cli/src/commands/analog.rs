//! `twinstack analog start|stop|status --port PORT`: the analog setpoint input
//! ([`twinstack::sources::analog_input`]) — the board as a linearising front-end between a lab's
//! controller (an analog voltage on the input pin) and the piezo stacks.
//!
//! `start` checks the settings here first (a refusal names the field, and nothing is sent),
//! then makes the input the setpoint source; `--store` then stores it with the settings in
//! the board's flash (with `--start-at-boot` the board starts it at power-up, with no host
//! connected: the input stops for the store, which stalls the tick, and starts again).
//! `status` prints the input's state (`--json`: one object); exit 1 while it is lost or
//! over-range.

use super::board_link::{connect, PortArgs};
use twinstack::fixed_point::SIGNAL_ONE;
use twinstack::protocol::messages::Request;
use twinstack::sources::analog_input::{AnalogInputConfig, AnalogRequest, AnalogStatus, OnFault};

/// Arguments of `analog`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// What to do.
    #[command(subcommand)]
    pub action: Action,
}

/// `analog` actions.
#[derive(Debug, clap::Subcommand)]
pub enum Action {
    /// Make the analog input the setpoint source (refused while a stream, waveform, scan or
    /// sequence runs).
    Start(StartArgs),
    /// Stop it: the output holds where it is.
    Stop(BoardArgs),
    /// Print its state: running, lost, over-range, faults, the reading and the setpoint.
    Status(StatusArgs),
}

/// The board alone.
#[derive(Debug, clap::Args)]
pub struct BoardArgs {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
}

/// Arguments of `analog status`.
#[derive(Debug, clap::Args)]
pub struct StatusArgs {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `analog start`.
#[derive(Debug, clap::Args)]
pub struct StartArgs {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// Normalised displacement per input span (0 V to 3.3 V at the pin); 2.0 with offset
    /// −1.0 maps the span onto the whole stroke.
    #[arg(long, default_value_t = 2.0, allow_hyphen_values = true)]
    pub gain: f32,
    /// Normalised displacement at 0 V on the pin.
    #[arg(long, default_value_t = -1.0, allow_hyphen_values = true)]
    pub offset: f32,
    /// One-pole low-pass corner, Hz [default: no filter].
    #[arg(long)]
    pub corner_hz: Option<f32>,
    /// Readings below this fraction of the span are a lost input (0: never).
    #[arg(long, default_value_t = 0.0)]
    pub lost_below: f32,
    /// Readings above this fraction of the span are over-range (1: never).
    #[arg(long, default_value_t = 1.0)]
    pub over_above: f32,
    /// What the output does on a lost or over-range input.
    #[arg(long, value_enum, default_value_t = FaultArg::Hold)]
    pub on_fault: FaultArg,
    /// Ramp rate on a fault (ramp-to-rest) and on recovery, normalised displacement per
    /// second (10: the whole stroke in 0.2 s).
    #[arg(long, default_value_t = 10.0)]
    pub rate: f32,
    /// With --store: the board starts the input at power-up from the stored settings.
    #[arg(long)]
    pub start_at_boot: bool,
    /// Store the settings (and this input's) in the board's flash, to boot in the mode in
    /// force (`bypass`, `open-loop` or `closed-loop`; the input stops for the store and
    /// starts again).
    #[arg(long, value_name = "BOOT_MODE")]
    pub store: Option<String>,
}

/// `--on-fault` values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum FaultArg {
    /// Hold where the last valid reading left the output.
    Hold,
    /// Ramp to the rest position (the drive at rest) at --rate.
    RampToRest,
}

/// Runs `analog`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    match &args.action {
        Action::Start(a) => start(a),
        Action::Stop(a) => {
            let mut client = connect(&a.port)?;
            client.expect_ack(&Request::Analog(AnalogRequest::Stop))?;
            println!("analog input stopped");
            Ok(())
        }
        Action::Status(a) => {
            let mut client = connect(&a.port)?;
            let s = client.analog_status()?;
            print_status(&s, a.json)?;
            if s.running && (s.lost || s.over_range) {
                anyhow::bail!(
                    "the analog input is {}",
                    if s.lost { "lost" } else { "over-range" }
                );
            }
            Ok(())
        }
    }
}

fn start(a: &StartArgs) -> anyhow::Result<()> {
    let config = AnalogInputConfig {
        gain: a.gain,
        offset: a.offset,
        corner_hz: a.corner_hz,
        lost_below: a.lost_below,
        over_above: a.over_above,
        on_fault: match a.on_fault {
            FaultArg::Hold => OnFault::Hold,
            FaultArg::RampToRest => OnFault::RampToRest,
        },
        rate: a.rate,
        start_at_boot: a.start_at_boot,
    };
    let boot_mode = match &a.store {
        Some(m) => Some(
            twinstack_link::board_requests::parse_mode(m).ok_or_else(|| {
                anyhow::anyhow!("--store {m:?}: give bypass, open-loop or closed-loop")
            })?,
        ),
        None => None,
    };
    if a.start_at_boot && boot_mode.is_none() {
        anyhow::bail!("--start-at-boot: only with --store (it is a stored setting)");
    }
    let mut client = connect(&a.port)?;
    // Checked here at the board's rate: a refusal names the field before anything is sent.
    let rate = client.status()?.tick_rate_hz as f64;
    config
        .check(rate)
        .map_err(|r| anyhow::anyhow!("refused: {r}; nothing was sent"))?;
    let start = Request::Analog(AnalogRequest::Start(config));
    client.expect_ack(&start)?;
    if let Some(boot_mode) = boot_mode {
        client.expect_ack(&Request::Analog(AnalogRequest::Stop))?;
        client.expect_ack(&Request::StoreParams { boot_mode })?;
        client.expect_ack(&start)?;
        println!("analog input started and stored (boot mode {boot_mode:?})");
    } else {
        println!("analog input started");
    }
    Ok(())
}

fn print_status(s: &AnalogStatus, json: bool) -> anyhow::Result<()> {
    let setpoint = s.setpoint as f64 / SIGNAL_ONE as f64;
    let reading = s.reading as f64 / 65536.0;
    if json {
        let v = twinstack_link::board_requests::analog_status_json(s);
        println!("{}", serde_json::to_string(&v)?);
    } else {
        println!(
            "analog input: {}{}{}, faults {}, reading {:.4} of the span ({:.3} V at the pin), setpoint {:+.6}",
            if s.running { "running" } else { "stopped" },
            if s.lost { ", lost" } else { "" },
            if s.over_range { ", over-range" } else { "" },
            s.faults,
            reading,
            reading * 3.3,
            setpoint
        );
    }
    Ok(())
}
