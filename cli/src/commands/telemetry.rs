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
use std::time::Duration;
use twinstack::protocol::messages::NackReason;
use twinstack::refusal::{Field, Rule};
use twinstack::services::recorder::Channel;
use twinstack_link::capture::{self, signal_mask};
use twinstack_link::output_file::Staged;
use twinstack_link::telemetry::{wait_for_end, TelemetryRecord};
use twinstack_link::LinkError;

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
    #[arg(long, default_value_t = 1.0)]
    pub duration: f64,
    /// CSV to write (physical units).
    #[arg(long)]
    pub out: PathBuf,
    /// PNG [default: the CSV's name with .png].
    #[arg(long)]
    pub png: Option<PathBuf>,
}

/// A telemetry run started on a board.
#[derive(Debug)]
pub struct TelemetryRun {
    /// The frames received so far.
    pub record: TelemetryRecord,
    /// Samples per second (the board's tick rate / the decimation).
    pub rate_hz: f64,
    /// The board's tick rate, Hz.
    pub tick_rate_hz: u32,
}

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

/// Starts telemetry of `signals` (names) at about `rate` samples per second on `client`.
pub fn start(client: &mut BoardClient, signals: &str, rate: f64) -> anyhow::Result<TelemetryRun> {
    let mask = signal_mask(signals).map_err(|e| anyhow::anyhow!("--signals {signals:?}: {e}"))?;
    if !(rate.is_finite() && rate > 0.0) {
        bail!("--rate {rate}: must be a positive number of samples per second");
    }
    let tick_rate_hz = client.status()?.tick_rate_hz.max(1);
    let tick = tick_rate_hz as f64;
    if rate > tick {
        bail!("--rate {rate}: the board ticks at {tick_rate_hz} Hz, the most a signal can have");
    }
    let decimation = (tick / rate).round().max(1.0);
    if decimation > u16::MAX as f64 {
        bail!(
            "--rate {rate}: at least {:.3} samples per second at {tick_rate_hz} Hz",
            tick / u16::MAX as f64
        );
    }
    let decimation = decimation as u16;
    let rate_hz = tick / decimation as f64;
    if (rate_hz - rate).abs() > 1e-9 * rate {
        eprintln!(
            "note: {rate} samples/s is not {tick_rate_hz} Hz / a whole number: {rate_hz} samples/s (one every {decimation} ticks)"
        );
    }
    match client.start_telemetry(mask, decimation) {
        Err(LinkError::Nack {
            reason: NackReason::Refused(r),
            ..
        }) if r.field == Field::TelemetryDecimation => {
            let Rule::AtLeast(least) = r.rule else {
                return Err(LinkError::Nack {
                    request: "Telemetry",
                    reason: NackReason::Refused(r),
                }
                .into());
            };
            bail!(
                "--rate {rate}: the board refused it ({r}): {} signals at most {} samples/s each at {tick_rate_hz} Hz ({} values/s in all, what its link carries)",
                mask.count_ones(),
                tick / least.max(1.0),
                twinstack::services::telemetry::MAX_VALUES_PER_SECOND
            )
        }
        other => other?,
    }
    Ok(TelemetryRun {
        record: TelemetryRecord::new(mask, decimation),
        rate_hz,
        tick_rate_hz,
    })
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
    client.stop_telemetry()?;
    let ended = wait_for_end(client, &mut telemetry.record, Duration::from_secs(2))?;
    let record = &telemetry.record;
    let settings = client.read_params()?;
    let facts = client.capture_status()?;
    let recording = record.recording(&facts, &settings)?;
    let mut files = Staged::new();
    files.write(out, &capture::csv(&recording)?)?;
    let temp_png = files.temporary_for(png);
    crate::plot::capture(
        &recording,
        &temp_png,
        &format!(
            "telemetry, {} samples at {} Hz",
            record.samples(),
            telemetry.rate_hz
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
        telemetry.rate_hz,
        record.frames()
    );
    if !ended {
        bail!("{summary}; but the board's end frame never came, so samples lost at the end cannot be ruled out");
    }
    if record.missing() > 0 {
        bail!(
            "{summary}; but {} of the {} samples the board took did not arrive ({} dropped on the board, its queue full: lower --rate or the signals; the rest in {} frames damaged on the line): the gaps show in t",
            record.missing(),
            record.produced().unwrap_or(0),
            record.lost_on_board(),
            record.frames_missing()
        );
    }
    Ok(summary)
}

/// Runs `telemetry`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    if !(args.duration.is_finite() && args.duration > 0.0) {
        bail!(
            "--duration {}: must be a positive number of seconds",
            args.duration
        );
    }
    let mut client = connect(&args.port)?;
    let mut telemetry = start(&mut client, &args.signals, args.rate)?;
    let wanted = (args.duration * telemetry.rate_hz).ceil() as u64;
    let bar = super::progress::bar(wanted, "telemetry", "samples");
    // The samples come at their rate: allow their duration twice over, plus the link's
    // timeout, before deciding the board is not sending them.
    let budget = Duration::from_secs_f64(2.0 * args.duration) + client.timeout();
    let mut waited = Duration::ZERO;
    let step = Duration::from_millis(20);
    let reached = |r: &TelemetryRecord| r.samples() as u64 + r.missing();
    while reached(&telemetry.record) < wanted {
        if waited > budget {
            let got = reached(&telemetry.record);
            let _ = client.stop_telemetry();
            bail!(
                "{got} of {wanted} samples after {:.1} s: is the board ticking?",
                waited.as_secs_f64()
            );
        }
        let frames = client.collect_telemetry(step)?;
        telemetry.record.add_all(&frames)?;
        waited += step;
        bar.set_position(reached(&telemetry.record).min(wanted));
    }
    bar.finish_and_clear();
    let png = args
        .png
        .clone()
        .unwrap_or_else(|| args.out.with_extension("png"));
    println!("{}", finish(&mut client, telemetry, &args.out, &png)?);
    Ok(())
}
