//! `twinstack coarse home|move|jog|stop|release|status --port PORT`: the dual-actuated stage's coarse
//! axis on a board with it (`cargo build-fw-dual`, the emulator image `cargo build-emu-dual`,
//! the virtual board `virtual-board --dual-stage`). With `--port sim` the in-process board is
//! the simulated dual-stage board ([`hal_sim::coarse_rig`]: the piezo stage on the ball screw),
//! booted afresh for the command, so it starts unhomed: `move --home --wait` homes it first
//! and waits for the move to end.
//!
//! Refusals (not homed, a target outside the travel, a speed or acceleration beyond the
//! stage's, a move into an active limit switch) come back from the board with the field and
//! the limit, and exit with 1.

use std::time::Duration;

use super::board_link::{connect, port_spec, BoardClient, PortArgs};
use hal_sim::coarse_rig::{DualStageDevice, DualStageDeviceConfig};
use hal_sim::port::PortSpec;
use twinstack::dual_stage::CoarseStatus;
use twinstack::protocol::messages::{CoarseMove, Request, StatusReport};
use twinstack_link::Client;

/// Arguments of `coarse`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// What to do.
    #[command(subcommand)]
    pub action: Action,
}

/// The coarse axis's commands.
#[derive(Debug, clap::Subcommand)]
pub enum Action {
    /// Home the axis (to its home switch; clears a latched fault).
    Home(WaitArgs),
    /// Move to a position (a homed axis; the target within the travel).
    Move(MoveArgs),
    /// Jog toward a travel limit until `stop`.
    Jog(JogArgs),
    /// Controlled stop (brakes at the move's acceleration).
    Stop(PortOnly),
    /// Hand the piezo back to its own sources (stream, waveform, scans, sequences, the
    /// analog input), the axis at rest holding where it is; the next move, jog or homing
    /// takes it again (refused while one of those sources runs).
    Release(PortOnly),
    /// Position, state, faults and switches, and whether the piezo follows the axis.
    Status(PortOnly),
}

/// Only the port.
#[derive(Debug, clap::Args)]
pub struct PortOnly {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
}

/// `home`'s arguments.
#[derive(Debug, clap::Args)]
pub struct WaitArgs {
    /// Wait until the homing ends, then print the status.
    #[arg(long)]
    pub wait: bool,
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
}

/// `move`'s arguments.
#[derive(Debug, clap::Args)]
pub struct MoveArgs {
    /// Target position, mm (relative to the home reference).
    #[arg(long, allow_negative_numbers = true)]
    pub to_mm: f64,
    /// Cruise speed, mm/s.
    #[arg(long, default_value_t = 10.0)]
    pub speed: f64,
    /// Acceleration, mm/s².
    #[arg(long, default_value_t = 200.0)]
    pub accel: f64,
    /// Home first (and wait for it).
    #[arg(long)]
    pub home: bool,
    /// Wait until the move ends, then print the status.
    #[arg(long)]
    pub wait: bool,
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
}

/// `jog`'s arguments.
#[derive(Debug, clap::Args)]
pub struct JogArgs {
    /// Speed, mm/s; positive toward the upper limit.
    #[arg(long, allow_negative_numbers = true)]
    pub speed: f64,
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
}

/// Opens the board behind `port`; `sim` is the simulated dual-stage board.
pub fn connect_coarse(port: &PortArgs) -> anyhow::Result<BoardClient> {
    if port.port.is_some() && port_spec(port)? == PortSpec::Sim {
        let config = DualStageDeviceConfig {
            baud: port.baud,
            ..DualStageDeviceConfig::paper()
        };
        let device = DualStageDevice::dual_stage(&config)?;
        let mut client = Client::new(Box::new(device) as Box<dyn twinstack_link::Transport>);
        client.set_timeout(Duration::from_millis(port.timeout_ms.max(1)));
        client.resync(Duration::from_millis(20))?;
        return Ok(client);
    }
    connect(port)
}

/// The status as `name value` lines.
pub fn format_coarse_status(s: &CoarseStatus) -> String {
    let names = |v: Vec<&str>| {
        if v.is_empty() {
            "-".to_string()
        } else {
            v.join(",")
        }
    };
    format!(
        "state {}\nhomed {}\nposition_mm {:.6}\nsetpoint_mm {:.6}\nfollowing_error_um {:.3}\nfaults {}\nswitches {}\nfine_setpoint {:.6}\nticks {}\n",
        s.state.name(),
        if s.homed { "yes" } else { "no" },
        s.position_pm as f64 / 1e9,
        s.setpoint_pm as f64 / 1e9,
        s.following_error_pm as f64 / 1e6,
        names(CoarseStatus::fault_names(s.faults).collect()),
        names(CoarseStatus::switch_names(s.switches).collect()),
        s.fine_setpoint as f64 / (1u64 << 30) as f64,
        s.ticks,
    )
}

/// Polls the status until the axis is no longer homing, moving, jogging or stopping (at most
/// `limit`, in the link's time: simulated on `sim`):
/// [`twinstack_link::board_requests::wait_until_coarse_settled`].
pub fn wait_until_settled(
    client: &mut BoardClient,
    limit: Duration,
) -> anyhow::Result<CoarseStatus> {
    Ok(twinstack_link::board_requests::wait_until_coarse_settled(
        client, limit,
    )?)
}

/// Runs `coarse`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let limit = Duration::from_secs(120);
    match &args.action {
        Action::Home(a) => {
            let mut client = connect_coarse(&a.port)?;
            client.coarse(&Request::CoarseHome)?;
            if a.wait {
                print!(
                    "{}",
                    format_coarse_status(&wait_until_settled(&mut client, limit)?)
                );
            } else {
                println!("homing");
            }
        }
        Action::Move(a) => {
            let mut client = connect_coarse(&a.port)?;
            if a.home {
                client.coarse(&Request::CoarseHome)?;
                let s = wait_until_settled(&mut client, limit)?;
                if !s.homed {
                    anyhow::bail!(
                        "homing failed: {}\n{}",
                        CoarseStatus::fault_names(s.faults)
                            .collect::<Vec<_>>()
                            .join(","),
                        format_coarse_status(&s)
                    );
                }
            }
            client.coarse(&Request::CoarseMove(CoarseMove {
                target_mm: a.to_mm,
                velocity_mm_s: a.speed,
                acceleration_mm_s2: a.accel,
            }))?;
            if a.wait {
                print!(
                    "{}",
                    format_coarse_status(&wait_until_settled(&mut client, limit)?)
                );
            } else {
                println!("moving");
            }
        }
        Action::Jog(a) => {
            let mut client = connect_coarse(&a.port)?;
            client.coarse(&Request::CoarseJog {
                velocity_mm_s: a.speed,
            })?;
            println!("jogging");
        }
        Action::Stop(a) => {
            let mut client = connect_coarse(&a.port)?;
            client.coarse(&Request::CoarseStop)?;
            println!("stopping");
        }
        Action::Release(a) => {
            let mut client = connect_coarse(&a.port)?;
            client.coarse(&Request::CoarseRelease)?;
            println!("released: the piezo plays its own sources until the next coarse motion");
        }
        Action::Status(a) => {
            let mut client = connect_coarse(&a.port)?;
            print!("{}", format_coarse_status(&client.coarse_status()?));
            let follows = client.status()?.has(StatusReport::COARSE);
            println!("piezo {}", if follows { "coarse" } else { "own" });
        }
    }
    Ok(())
}
