//! `hal-sim status --port PORT [--json]`: the board's status and telemetry, one `name value`
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

/// The names of the flags set in `s`.
fn flag_names(s: &StatusReport) -> Vec<&'static str> {
    [
        (StatusReport::DEFAULTS, "defaults"),
        (StatusReport::STREAMING, "streaming"),
        (StatusReport::WAVEFORM, "waveform"),
        (StatusReport::RECORDING, "recording"),
        (StatusReport::TELEMETRY, "telemetry"),
    ]
    .into_iter()
    .filter(|&(bit, _)| s.has(bit))
    .map(|(_, name)| name)
    .collect()
}

/// The report as one JSON object: the fields of [`format_status`] under the same names, `mode`
/// as `bypass`/`open-loop`/`closed-loop`, `flags` a list, `estimate` normalised (±1 of the
/// output range) and `estimate_q2_30` raw.
pub fn status_json(s: &StatusReport) -> serde_json::Value {
    use twinstack::settings::Mode;
    serde_json::json!({
        "image": s.image().name(),
        "ticks": s.ticks,
        "tick_rate_hz": s.tick_rate_hz,
        "mode": match s.mode() {
            Mode::Bypass => "bypass",
            Mode::OpenLoop => "open-loop",
            Mode::ClosedLoop => "closed-loop",
        },
        "flags": flag_names(s),
        "queue_fill": s.queue_fill,
        "credits": s.credits,
        "next_seq": s.next_seq,
        "underruns": s.underruns,
        "overruns": s.overruns,
        "crc_errors": s.crc_errors,
        "frame_errors": s.frame_errors,
        "limit_hits": s.limit_hits,
        "estimate": s.estimate as f64 / (1u64 << 30) as f64,
        "estimate_q2_30": s.estimate,
        "recorded": s.recorded,
    })
}

/// The report as `name value` lines.
pub fn format_status(s: &StatusReport) -> String {
    let flags = flag_names(s);
    format!(
        "image {}\nticks {}\ntick_rate_hz {}\nmode {:?}\nflags {}\nqueue_fill {}\ncredits {}\nnext_seq {}\nunderruns {}\noverruns {}\ncrc_errors {}\nframe_errors {}\nlimit_hits {}\nestimate {:.6} (Q2.30 {})\nrecorded {}\n",
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
