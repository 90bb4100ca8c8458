//! `twinstack telemetry --port P --signals sensor,setpoint --rate 10000 --duration 2 --out t.csv`:
//! continuous telemetry (protocol v5). Starts the board's telemetry of the listed signals
//! (setpoint, left, right, sensor, estimate, error) at `--rate` samples per second (the
//! board's tick rate divided by a whole number: the nearest is taken and said), receives its
//! frames for `--duration` seconds of samples, stops it, waits for its end frame and writes the
//! samples in physical units (`t [s]` from the first sample, the stacks in volts,
//! displacements in the output unit of the settings read back from the board) as CSV, plus a
//! PNG. The board keeps running whatever it runs (a stream, the waveform): telemetry only
//! watches.
//!
//! Nothing missing goes unsaid: samples the board dropped (its queue full) and frames damaged
//! on the line are counted from the frames' sample indices and sequence numbers, and the end
//! frame counts the tail; if any sample did not arrive, the files are still written (the
//! gaps show in `t`) and the command exits 1 saying how many and why.
//!
//! `twinstack stream --telemetry sensor,setpoint:10000 --telemetry-out t.csv` does the same
//! around a streamed run, over its one connection ([`start`], [`finish`]).

use super::board_link::{connect, BoardClient, PortArgs};
use anyhow::bail;
use std::path::{Path, PathBuf};
use twinstack::services::recorder::Channel;
use twinstack_link::capture::{self, signal_mask};
use twinstack_link::output_file::Staged;
use twinstack_link::telemetry::RunError;

/// Arguments of `telemetry`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// Signals, comma-separated: setpoint, left, right, sensor, estimate, error.
    #[arg(long)]
    pub signals: String,
    /// Samples per second of each signal (the board's tick rate / a whole number; the nearest
    /// is taken).
    #[arg(long, default_value_t = 10_000.0)]
    pub rate: f64,
    /// Seconds of samples to receive.
    #[arg(long, default_value_t = 1.0, value_parser = super::parse_positive_seconds)]
    pub duration: f64,
    /// CSV to write (physical units).
    #[arg(long)]
    pub out: PathBuf,
    /// PNG [default: the CSV's name with .png].
    #[arg(long)]
    pub png: Option<PathBuf>,
}

/// A telemetry run started on a board.
/// A run under way: [`twinstack_link::telemetry::TelemetryRun`].
pub use twinstack_link::telemetry::TelemetryRun;

/// Parses `SIGNALS[:RATE]` (`stream --telemetry`): the signal list and the rate (default
/// 10 000 samples per second).
pub fn parse_spec(spec: &str) -> anyhow::Result<(String, f64)> {
    match spec.rsplit_once(':') {
        Some((signals, rate)) => {
            let rate: f64 = rate.trim().parse().map_err(|_| {
                anyhow::anyhow!("--telemetry {spec:?}: the rate after ':' is not a number")
            })?;
            Ok((signals.to_string(), rate))
        }
        None => Ok((spec.to_string(), 10_000.0)),
    }
}

/// Starts the board's telemetry of `signals` (a comma-separated list) at the rate nearest
/// `rate` samples per second ([`TelemetryRun::start`]), saying so where it is not the rate
/// asked for. Errors name the flag (`--signals`, `--rate`).
pub fn start(client: &mut BoardClient, signals: &str, rate: f64) -> anyhow::Result<TelemetryRun> {
    let mask = signal_mask(signals).map_err(|e| anyhow::anyhow!("--signals {signals:?}: {e}"))?;
    let run = TelemetryRun::start(client, mask, rate).map_err(|e| match e {
        e @ (RunError::Rate(_) | RunError::TooFast { .. }) => anyhow::anyhow!("--{e}"),
        e => e.into(),
    })?;
    if run.rate.differs_from(rate) {
        eprintln!(
            "note: {rate} samples/s is not {} Hz / a whole number: {} samples/s (one every {} ticks)",
            run.rate.tick_rate_hz, run.rate.rate_hz, run.rate.decimation
        );
    }
    Ok(run)
}

/// Stops the run, waits for its end frame, writes the CSV `out` and the PNG `png` in
/// physical units and returns a one-line summary; an error (after the files are written) if
/// any sample did not arrive.
pub fn finish(
    client: &mut BoardClient,
    mut telemetry: TelemetryRun,
    out: &Path,
    png: &Path,
) -> anyhow::Result<String> {
    let (recording, ended) = telemetry.finish(client)?;
    let record = &telemetry.record;
    let mut files = Staged::new();
    files.write(out, &capture::csv(&recording)?)?;
    let temp_png = files.temporary_for(png);
    crate::plot::capture(
        &recording,
        &temp_png,
        &format!(
            "telemetry, {} samples at {} Hz",
            record.samples(),
            telemetry.rate.rate_hz
        ),
    )?;
    files.commit()?;
    let names: Vec<&str> = Channel::of_mask(record.signals())
        .map(|c| c.name())
        .collect();
    let summary = format!(
        "wrote {} and {} ({} samples of {} at {} Hz in {} frames)",
        out.display(),
        png.display(),
        record.samples(),
        names.join(", "),
        telemetry.rate.rate_hz,
        record.frames()
    );
    if let Some(shortfall) = telemetry.shortfall(ended) {
        bail!("{summary}; but {shortfall}");
    }
    Ok(summary)
}

/// Runs `telemetry`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    super::check_positive_seconds("--duration", args.duration)?;
    let mut client = connect(&args.port)?;
    let mut telemetry = start(&mut client, &args.signals, args.rate)?;
    let wanted = (args.duration * telemetry.rate.rate_hz).ceil() as u64;
    let bar = super::progress::bar(wanted, "telemetry", "samples");
    telemetry.collect(&mut client, wanted, |n| {
        bar.set_position(n);
        std::ops::ControlFlow::Continue(())
    })?;
    bar.finish_and_clear();
    let png = args
        .png
        .clone()
        .unwrap_or_else(|| args.out.with_extension("png"));
    println!("{}", finish(&mut client, telemetry, &args.out, &png)?);
    Ok(())
}
