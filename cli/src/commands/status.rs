//! `twinstack status --port PORT [--json]`: the board's status and telemetry, one `name value`
//! per line, or one JSON object ([`status_json`]).

use super::board_link::{connect, PortArgs};
use twinstack::protocol::messages::StatusReport;

/// Arguments of `status`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// One JSON object on stdout (the same fields, flags as a list, the estimate both
    /// normalised and raw) instead of `name value` lines.
    #[arg(long)]
    pub json: bool,
}

pub use twinstack_link::board_requests::{flag_names, status_json};

/// The report as `name value` lines.
pub fn format_status(s: &StatusReport) -> String {
    let flags = flag_names(s);
    format!(
        "image {}\nticks {}\ntick_rate_hz {}\nmode {:?}\nflags {}\nqueue_fill {}\ncredits {}\nnext_seq {}\nunderruns {}\noverruns {}\ncrc_errors {}\nframe_errors {}\nlimit_hits {}\ndrifts {}\nestimate {:.6} (Q2.30 {})\nrecorded {}\n",
        s.image().name(),
        s.ticks,
        s.tick_rate_hz,
        s.mode(),
        if flags.is_empty() { "-".to_string() } else { flags.join(",") },
        s.queue_fill,
        s.credits,
        s.next_seq,
        s.underruns,
        s.overruns,
        s.crc_errors,
        s.frame_errors,
        s.limit_hits,
        s.drifts,
        s.estimate as f64 / (1u64 << 30) as f64,
        s.estimate,
        s.recorded,
    )
}

/// Runs `status`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let mut client = connect(&args.port)?;
    let s = client.status()?;
    if args.json {
        println!("{}", status_json(&s));
    } else {
        print!("{}", format_status(&s));
    }
    Ok(())
}
