//! `twinstack stream --port PORT --data SETPOINTS.csv [--params PARAMS.json] [--divider D]`:
//! streams a setpoint record to the board (format: [`twinstack_link::setpoint_file`]), within the
//! credits it grants, starts it once the queue is primed, waits until it has played and stops
//! (the output holds the last setpoint). The whole file is checked before anything is sent.
//!
//! `--record setpoint,left,sensor,estimate --record-out run.csv` records the streamed run over
//! the same connection (the port is exclusive): before anything is streamed it arms a
//! multi-signal capture triggered by the stream's start, and once the stream has played it
//! reads the capture back and writes it in physical units, as `twinstack record --signals`
//! does (CSV and PNG). By default the capture spans the whole run (setpoints × divider
//! ticks, less if the board's buffer holds fewer).
//!
//! `--telemetry sensor,setpoint:10000 --telemetry-out t.csv` watches the streamed run live over
//! the same connection: telemetry of the listed signals at that rate (samples per second,
//! default 10 000) starts before the first setpoint is sent and stops once the stream has
//! played; its samples are written as `twinstack telemetry` writes them (CSV and PNG, physical
//! units), and a sample that did not arrive is an error ([`super::telemetry::finish`]).
//!
//! `--preview` (the resonance `twinstack calibrate` measured into the `--params` file) or
//! `--resonance-hz F --resonance-damping Z` (what `twinstack tune` fits and prints) shapes the
//! setpoints ahead of time so that the stage's resonance does not ring at their corners
//! ([`twinstack_identify::preview`]): for a board in open or closed loop (its compensator
//! inverts the shaped positions, and closed loop its feedback follows them, which stand off the
//! trajectory by the resonance's share: briefly at a corner, all along on fast smooth motion;
//! in bypass they would be the drive), one
//! setpoint a tick (the board holds each one over its tick; interpolated between
//! setpoints further apart, shaped ones would not be what the preview assumes)
//! ([`twinstack_identify::preview::ResonancePreview::shape_stream`]). Shaped setpoints outside −1…1 (a turn too near the
//! range's end) are refused, naming the first; nothing is sent.
//!
//! Exit codes: [`EXIT_CODES`] (0 played without underrun, 1 error, 2 usage, 3 completed with
//! underruns: [`Underran`]).

use super::board_link::{connect, PortArgs};
use super::compensate::Preview;
use std::path::PathBuf;
use std::time::Duration;
use twinstack::protocol::messages::{Trigger, TriggerEdge, UnderrunPolicy};
use twinstack_identify::param_file::ParamFile;
use twinstack_identify::preview::PreviewError;
use twinstack_link::capture::signal_mask;
use twinstack_link::setpoint_file::{self, SetpointUnits};
use twinstack_link::streamer::{stream_setpoints, StartOn, StreamOptions};

/// The exit codes of `twinstack stream`, as `twinstack stream --help` lists them.
pub const EXIT_CODES: &str = "\
Exit codes:
  0  every setpoint was accepted and played without an underrun
  1  error (bad file, link failure, refusal, the stream did not play); the message says which
  2  usage (a bad or missing argument)
  3  completed with underruns: every setpoint was accepted, but the board's queue ran dry
     while setpoints were still to come (or that could not be ruled out), so the output held
     or ramped in between: raise --divider or the baud rate, or shorten the link";

/// Exit code of a stream that completed with underruns (see [`EXIT_CODES`]).
pub const EXIT_UNDERRUN: u8 = 3;

/// A stream that completed, but ran dry on the way: `main` reports it and exits with
/// [`EXIT_UNDERRUN`] rather than 0.
#[derive(Debug, thiserror::Error)]
#[error("the stream completed with {underruns} underruns (the board's queue ran dry while setpoints were still to come)")]
pub struct Underran {
    /// Underruns the board counted during the stream.
    pub underruns: u32,
}

/// Arguments of `stream`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// Setpoint CSV: a `setpoint` column (normalised, −1…1), or an `x` column in the model's
    /// output units with --params.
    #[arg(long)]
    pub data: PathBuf,
    /// Parameter file whose output range maps an `x` column onto −1…1.
    #[arg(long)]
    pub params: Option<PathBuf>,
    /// Ticks per setpoint (the board interpolates linearly in between) [default: from the t
    /// column, else 1].
    #[arg(long)]
    pub divider: Option<u16>,
    /// The board's control rate, Hz, that the t column is checked against (the board's
    /// status must agree).
    #[arg(long, default_value_t = 50_000.0)]
    pub tick_rate: f64,
    /// What the board does if the queue runs dry.
    #[arg(long, value_enum)]
    pub underrun: Option<UnderrunArg>,
    /// Return once everything is queued, without waiting for it to play (the stream keeps
    /// running).
    #[arg(long)]
    pub no_wait: bool,
    /// Record the streamed run over this connection: signals, comma-separated (setpoint,
    /// left, right, sensor, estimate, error), captured from the stream's start.
    #[arg(long, requires = "record_out")]
    pub record: Option<String>,
    /// CSV of the recorded run (physical units); a PNG is written next to it.
    #[arg(long, requires = "record")]
    pub record_out: Option<PathBuf>,
    /// Frames of the recorded run [default: setpoints × divider / decimation, at most what
    /// the board's buffer holds].
    #[arg(long, requires = "record")]
    pub record_samples: Option<u32>,
    /// Frames recorded from before the stream's start.
    #[arg(long, default_value_t = 0, requires = "record")]
    pub record_pre: u32,
    /// Ticks per recorded frame.
    #[arg(long, default_value_t = 1, requires = "record")]
    pub record_decimation: u16,
    /// Watch the streamed run with continuous telemetry: `SIGNALS[:RATE]`, the signals
    /// comma-separated (setpoint, left, right, sensor, estimate, error), RATE samples per
    /// second of each (default 10000).
    #[arg(long, requires = "telemetry_out", value_name = "SIGNALS[:RATE]")]
    pub telemetry: Option<String>,
    /// CSV of the telemetry (physical units); a PNG is written next to it.
    #[arg(long, requires = "telemetry")]
    pub telemetry_out: Option<PathBuf>,
    /// Shape the setpoints ahead of time so that the stage's resonance does not ring at their
    /// corners: the resonance's frequency, Hz, as `twinstack tune` fits it (with
    /// --resonance-damping). For a board in open or closed loop, one setpoint a tick.
    #[arg(long, requires = "resonance_damping", conflicts_with = "preview")]
    pub resonance_hz: Option<f64>,
    /// The resonance's damping ratio, in (0, 1), as `twinstack tune` fits it (with
    /// --resonance-hz).
    #[arg(long, requires = "resonance_hz")]
    pub resonance_damping: Option<f64>,
    /// Shape the setpoints for the resonance the --params file holds (what `twinstack
    /// calibrate` measured), as --resonance-hz/--resonance-damping would.
    #[arg(long, requires = "params")]
    pub preview: bool,
    /// Wait for this edge of the trigger input to start the stream (`rising` or `falling`: a
    /// camera's frame starts it): the queue is primed, the input armed, and the stream (and
    /// its --record) starts on the edge's tick; `off` (the default) starts it at once.
    #[arg(long, default_value = "off", value_parser = super::scan::parse_edge)]
    pub start_on: TriggerEdge,
    /// Longest wait for the --start-on edge, seconds (then the input is disarmed and the
    /// setpoints accepted stay queued).
    #[arg(long, default_value_t = 60.0, value_parser = super::parse_seconds)]
    pub edge_wait_s: f64,
}

/// `--underrun` values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum UnderrunArg {
    /// Hold the last setpoint.
    Hold,
    /// Ramp to the rest position within the slew limit.
    RampToBias,
}

/// Runs `stream`. A stream that underran returns [`Underran`] after its report is printed.
pub fn run(args: &Args) -> anyhow::Result<()> {
    if !(args.tick_rate.is_finite() && args.tick_rate > 0.0) {
        anyhow::bail!(
            "--tick-rate {}: must be a positive number of Hz",
            args.tick_rate
        );
    }
    if args.divider == Some(0) {
        anyhow::bail!("--divider must be at least 1");
    }
    let (file, model) = match &args.params {
        Some(p) => {
            let (file, model) = ParamFile::load(p)?;
            (Some(file), Some(model))
        }
        None => (None, None),
    };
    // The resonance to shape for, and the flags that asked for it (for errors).
    let resonance =
        Preview::from_flags(args.resonance_hz.zip(args.resonance_damping), args.preview)
            .resonance(
                file.as_ref(),
                args.params.as_deref().unwrap_or(std::path::Path::new("")),
            )
            .map_err(|e| anyhow::anyhow!("{e}; nothing was sent"))?;
    let units = match &model {
        Some(m) => SetpointUnits::Output(&m.scaling),
        None => SetpointUnits::Normalised,
    };
    let sp = setpoint_file::read(&args.data, units, args.tick_rate, args.divider)?;
    let options = StreamOptions {
        divider: args.divider.or(sp.divider_from_t).unwrap_or(1),
        underrun: args.underrun.map(|u| match u {
            UnderrunArg::Hold => UnderrunPolicy::Hold,
            UnderrunArg::RampToBias => UnderrunPolicy::RampToBias,
        }),
        tick_rate_hz: args.tick_rate,
        drain: !args.no_wait,
        start_on: (args.start_on != TriggerEdge::Off).then(|| StartOn {
            edge: args.start_on,
            pulse_ticks: 2,
            wait: Duration::from_secs_f64(args.edge_wait_s),
        }),
        ..StreamOptions::default()
    };
    let mut client = connect(&args.port)?;
    let board_rate = client.status()?.tick_rate_hz;
    if sp.divider_from_t.is_some() && board_rate > 0 && board_rate as f64 != args.tick_rate {
        anyhow::bail!(
            "the board ticks at {board_rate} Hz but the t column of {} was checked against --tick-rate {}: pass --tick-rate {board_rate}; nothing was sent",
            args.data.display(),
            args.tick_rate
        );
    }
    let tick_rate = if board_rate > 0 {
        board_rate as f64
    } else {
        args.tick_rate
    };
    let samples = match resonance {
        Some((resonance, flags)) => {
            let refused = |e: PreviewError| {
                let fix = match e {
                    PreviewError::Mode(_) => {
                        " (`twinstack set /mode OpenLoop` or `ClosedLoop` first)"
                    }
                    PreviewError::Divider(_) => " (a t column at the board's rate, or --divider 1)",
                    _ => "",
                };
                anyhow::anyhow!("{flags}: {e}{fix}; nothing was sent")
            };
            let preview = resonance.preview(tick_rate).map_err(refused)?;
            let (hz, zeta) = (resonance.frequency_hz, resonance.damping);
            let board = client.read_params()?;
            let shaped = preview
                .shape_stream_for(&sp.samples, &board, options.divider)
                .map_err(refused)?;
            eprintln!(
                "note: setpoints shaped for a resonance at {hz} Hz, damping {zeta}, at the board's {tick_rate} Hz"
            );
            shaped
        }
        None => sp.samples.clone(),
    };
    // Arm the capture before the stream starts: its start is the trigger.
    let recording = match (&args.record, &args.record_out) {
        (Some(signals), Some(out)) => {
            let n = signal_mask(signals)
                .map_err(|e| anyhow::anyhow!("--record {signals:?}: {e}"))?
                .count_ones();
            let capacity = client.capture_status()?.capacity / n.max(1);
            let decimation = args.record_decimation.max(1) as u64;
            let samples = match args.record_samples {
                Some(s) => s,
                None => {
                    let ticks = sp.samples.len() as u64 * options.divider as u64;
                    (ticks.div_ceil(decimation) + args.record_pre as u64).min(capacity as u64)
                        as u32
                }
            };
            let request = super::record::arm_capture(
                &mut client,
                signals,
                samples,
                args.record_pre,
                Trigger::StreamStart,
                args.record_decimation,
            )?;
            Some((request, out.clone()))
        }
        _ => None,
    };
    // Telemetry watches the run from before its first setpoint.
    let telemetry = match (&args.telemetry, &args.telemetry_out) {
        (Some(spec), Some(out)) => {
            let (signals, rate) = super::telemetry::parse_spec(spec)?;
            Some((
                super::telemetry::start(&mut client, &signals, rate)?,
                out.clone(),
            ))
        }
        _ => None,
    };
    let bar = super::progress::bar(samples.len() as u64, "streaming", "setpoints");
    let r = stream_setpoints(&mut client, &samples, &options, |n| {
        bar.set_position(n as u64)
    });
    bar.finish_and_clear();
    let r = r?;
    if r.before.queue_fill > 0 {
        eprintln!(
            "note: the board's queue held {} setpoints from before; they played first",
            r.before.queue_fill
        );
    }
    let end = r.drained.unwrap_or(r.after_last_batch);
    let seconds = end.ticks.wrapping_sub(r.before.ticks) as f64 / tick_rate;
    println!(
        "streamed {} setpoints from {} at divider {} ({} batches, {} resent, {} refused and retried, {} credit probes)",
        r.accepted,
        args.data.display(),
        options.divider,
        r.batches,
        r.resent_batches,
        r.nacks.len(),
        r.credit_probes
    );
    println!(
        "underruns during the stream: {}",
        r.underruns_during_stream()
    );
    println!(
        "board: {:.3} s of ticks, {} setpoints/s; overruns {}, CRC errors {}, limit hits {}",
        seconds,
        if seconds > 0.0 {
            format!("{:.0}", r.accepted as f64 / seconds)
        } else {
            "-".into()
        },
        end.overruns.wrapping_sub(r.before.overruns),
        end.crc_errors.wrapping_sub(r.before.crc_errors),
        end.limit_hits.wrapping_sub(r.before.limit_hits)
    );
    println!(
        "link: {} bytes in {} frames sent ({:.2} bytes per setpoint), {} bytes received, {} corrupt frames",
        r.link.bytes_sent,
        r.link.frames_sent,
        r.link.bytes_sent as f64 / r.accepted.max(1) as f64,
        r.link.bytes_received,
        r.link.corrupt_frames
    );
    if seconds > 0.0 {
        println!(
            "link share: host → board {:.0} bytes/s, board → host {:.0} bytes/s over the board's {:.3} s",
            r.link.bytes_sent as f64 / seconds,
            r.link.bytes_received as f64 / seconds,
            seconds
        );
    }
    if r.drained.is_some() {
        println!("queue played out; stream stopped (output holds the last setpoint)");
    } else {
        println!("queued; the stream keeps playing");
    }
    if let Some((request, out)) = recording {
        // The capture ends by itself `samples − pre` frames after the stream's start: wait
        // that long twice over, plus a margin for the link.
        let seconds =
            (request.samples - request.pre_trigger) as f64 * request.decimation as f64 / tick_rate;
        let wait = std::time::Duration::from_secs_f64(2.0 * seconds + 5.0);
        let png = out.with_extension("png");
        println!(
            "{}",
            super::record::finish_capture(&mut client, wait, &out, &png)?
        );
    }
    if let Some((telemetry, out)) = telemetry {
        let png = out.with_extension("png");
        println!(
            "{}",
            super::telemetry::finish(&mut client, telemetry, &out, &png)?
        );
    }
    if r.underran() {
        return Err(Underran {
            underruns: r.underruns_during_stream(),
        }
        .into());
    }
    Ok(())
}
