//! `hal-sim status --port PORT`: the board's status and telemetry, one `name value` per line.

use super::board_link::{connect, PortArgs};
use twinstack::protocol::messages::StatusReport;

/// Arguments of `status`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
}

/// The report as `name value` lines.
pub fn format_status(s: &StatusReport) -> String {
    format!(
        "ticks {}\nqueue_fill {}\ncredits {}\nunderruns {}\noverruns {}\ncrc_errors {}\nlimit_hits {}\nestimate {:.6} (Q2.30 {})\nflags {:#06x}{}\n",
        s.ticks,
        s.queue_fill,
        s.credits,
        s.underruns,
        s.overruns,
        s.crc_errors,
        s.limit_hits,
        s.estimate as f64 / (1u64 << 30) as f64,
        s.estimate,
        s.flags,
        if s.flags & 1 != 0 {
            " (parameters from defaults: no valid record in flash)"
        } else {
            ""
        }
    )
}

/// Runs `status`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let mut client = connect(&args.port)?;
    let s = client.status()?;
    print!("{}", format_status(&s));
    Ok(())
}
