//! Underruns by link latency and rate: streams a full-range triangle of `--seconds` (default
//! 10) at 50 kHz and 100 kHz (divider 1) to the simulated board behind a USB–serial adapter
//! whose latency is 0, 2, 8, 16 and 32 ms each way (jitter a quarter of it), twice:
//!
//! * **after**: as the host streams now (packed two-byte setpoints, the board's whole queue,
//!   3 Mbaud);
//! * **before**: as it streamed before (varint setpoints, at most 511 queued — the board's old
//!   queue —, 2 Mbaud).
//!
//! Every count is the board's own underrun counter (the stream ends with `Finish`, so the
//! ticks after its end are not counted). Then the link's share at 100 kHz, each way.
//!
//! ```text
//! cargo run --release -p twinstack-cli --example link_latency -- --seconds 10
//! ```

use std::time::Duration;

use hal_sim::sim_device::{full_range_triangle, LinkDelay, SimDevice, SimDeviceConfig};
use twinstack::protocol::messages::UnderrunPolicy;
use twinstack_link::client::Client;
use twinstack_link::streamer::{stream_setpoints, StreamOptions, StreamReport};

struct Setup {
    baud: u32,
    queue_limit: Option<usize>,
    varint: bool,
}

fn run(setup: &Setup, rate: f64, latency_ms: f64, seconds: f64) -> Result<StreamReport, String> {
    let latency = Duration::from_secs_f64(latency_ms / 1e3);
    let link = LinkDelay::new(latency, latency / 4).map_err(|e| e.to_string())?;
    let config = SimDeviceConfig::paper_at(rate, setup.baud, link);
    let mut client = Client::new(SimDevice::new(config).map_err(|e| e.to_string())?);
    let samples = full_range_triangle((seconds * rate) as usize, (rate / 10.0) as usize);
    let options = StreamOptions {
        underrun: Some(UnderrunPolicy::Hold),
        queue_limit: setup.queue_limit,
        varint: setup.varint,
        ..StreamOptions::default()
    };
    let before = client.transport().control().telemetry().underruns;
    let r = stream_setpoints(&mut client, &samples, &options, |_| {}).map_err(|e| e.to_string())?;
    let counted = client
        .transport()
        .control()
        .telemetry()
        .underruns
        .wrapping_sub(before);
    if counted != r.underruns_during_stream() {
        return Err(format!(
            "the streamer counted {} underruns, the board {counted}",
            r.underruns_during_stream()
        ));
    }
    Ok(r)
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let seconds = args
        .iter()
        .position(|a| a == "--seconds")
        .and_then(|i| args.get(i + 1))
        .map_or(Ok(10.0), |s| s.parse::<f64>())
        .ok()
        .filter(|s| s.is_finite() && *s > 0.0)
        .unwrap_or_else(|| {
            eprintln!("--seconds needs a positive number");
            std::process::exit(2);
        });
    let setups = [
        (
            "before",
            Setup {
                baud: 2_000_000,
                queue_limit: Some(511),
                varint: true,
            },
        ),
        (
            "after",
            Setup {
                baud: 3_000_000,
                queue_limit: None,
                varint: false,
            },
        ),
    ];
    let latencies = [0.0, 2.0, 8.0, 16.0, 32.0];
    println!(
        "underruns streaming {seconds} s of a full-range triangle, divider 1 (jitter ± a quarter of the latency)"
    );
    println!("| setup | rate | 0 ms | 2 ms | 8 ms | 16 ms | 32 ms |");
    println!("|---|---|---|---|---|---|---|");
    let mut share = None;
    for (name, setup) in &setups {
        for rate in [50_000.0, 100_000.0] {
            let mut row = format!("| {name} | {} kHz |", rate / 1e3);
            for &latency in &latencies {
                match run(setup, rate, latency, seconds) {
                    Ok(r) => {
                        row += &format!(" {} |", r.underruns_during_stream());
                        if *name == "after" && rate == 100_000.0 && latency == 16.0 {
                            share = Some(r);
                        }
                    }
                    Err(e) => row += &format!(" error: {e} |"),
                }
            }
            println!("{row}");
        }
    }
    if let Some(r) = share {
        let end = r.drained.unwrap_or(r.after_last_batch);
        let board_s = end.ticks.wrapping_sub(r.before.ticks) as f64 / 100_000.0;
        println!(
            "link share at 100 kHz, 16 ms ± 4 ms, 3 Mbaud (300 000 bytes/s each way), over the board's {board_s:.3} s: host → board {:.0} bytes/s ({:.1} %, {:.3} bytes a setpoint), board → host {:.0} bytes/s ({:.2} %)",
            r.link.bytes_sent as f64 / board_s,
            r.link.bytes_sent as f64 / board_s / 3000.0,
            r.link.bytes_sent as f64 / r.accepted as f64,
            r.link.bytes_received as f64 / board_s,
            r.link.bytes_received as f64 / board_s / 3000.0,
        );
    }
}
