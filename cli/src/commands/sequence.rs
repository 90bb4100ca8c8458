//! `twinstack sequence --port PORT --data POSITIONS.csv [--params PARAMS.json] [--edge rising]
//! [--window 0.005] [--settle-ticks 25]`: a TTL-stepped sequence ([`twinstack::sources::sequence`]).
//! Checks the whole positions file (the stream's format, [`twinstack_link::setpoint_file`]; every bad
//! row named with its line), fills the board's queue, arms the sequence, keeps the queue
//! topped up while the camera's edges step through it, and reports the steps, the early edges
//! (before the stage had settled) and the missed ones (no position left), and the first
//! edge's trigger-to-motion latency from a capture ([`twinstack_link::sequence_run`]).
//!
//! On `--port sim`, `--sim-camera-hz HZ` puts a simulated camera on the trigger input
//! ([`hal_sim::sim_camera`]; `--sim-camera-on-settled`: its exposures start on the settled
//! output). `twinstack virtual-board --camera-hz` does the same for a served board.
//!
//! Exit 0 when every position was reached without a missed edge; 1 otherwise (the message
//! gives the counts).

use std::path::PathBuf;
use std::time::Duration;

use super::board_link::{connect, port_spec, BoardClient, PortArgs};
use hal_sim::port::PortSpec;
use hal_sim::sim_camera::CameraConfig;
use hal_sim::sim_device::{SimDevice, SimDeviceConfig};
use twinstack::protocol::messages::{SequenceConfig, TriggerEdge};
use twinstack_identify::param_file::ParamFile;
use twinstack_link::client::Client;
use twinstack_link::sequence_run::{run_sequence, SequenceOptions, SequenceReport};
use twinstack_link::setpoint_file::{self, SetpointUnits};

/// Arguments of `sequence`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// Positions CSV: a `setpoint` column (normalised, −1…1), or an `x` column in the model's
    /// output units with --params; one position per edge, in order.
    #[arg(long)]
    pub data: PathBuf,
    /// Parameter file whose output range maps an `x` column onto −1…1.
    #[arg(long)]
    pub params: Option<PathBuf>,
    /// The trigger input's edge that advances the sequence.
    #[arg(long, value_enum, default_value_t = EdgeArg::Rising)]
    pub edge: EdgeArg,
    /// Settle window, ± normalised displacement around each position (0.005 of the half
    /// stroke: 0.225 µm on a 90 µm stage).
    #[arg(long, default_value_t = 0.005)]
    pub window: f32,
    /// Ticks in a row within the window before the settled output goes high.
    #[arg(long, default_value_t = 25)]
    pub settle_ticks: u16,
    /// Switch the board to this mode first (bypass, open-loop, closed-loop; bumpless) [default:
    /// leave it].
    #[arg(long)]
    pub mode: Option<String>,
    /// Stop waiting when no edge has advanced the sequence for this long, seconds.
    #[arg(long, default_value_t = 5.0, value_parser = super::parse_positive_seconds)]
    pub idle_s: f64,
    /// `--port sim` only: a simulated camera on the trigger input at this frame rate, one
    /// frame per position.
    #[arg(long, value_name = "HZ")]
    pub sim_camera_hz: Option<f64>,
    /// With --sim-camera-hz: each exposure starts on the settled output (settled → camera
    /// trigger-in) instead of free-running.
    #[arg(long, requires = "sim_camera_hz")]
    pub sim_camera_on_settled: bool,
    /// Print the result as one JSON object.
    #[arg(long)]
    pub json: bool,
}

/// `--edge` values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum EdgeArg {
    /// Low to high.
    Rising,
    /// High to low.
    Falling,
}

/// Runs `sequence`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let config = SequenceConfig {
        edge: match args.edge {
            EdgeArg::Rising => TriggerEdge::Rising,
            EdgeArg::Falling => TriggerEdge::Falling,
        },
        window: args.window,
        settle_ticks: args.settle_ticks,
    };
    config
        .check()
        .map_err(|r| anyhow::anyhow!("refused: {r}; nothing was sent"))?;
    super::check_positive_seconds("--idle-s", args.idle_s)?;
    let model = match &args.params {
        Some(p) => Some(ParamFile::load(p)?.1),
        None => None,
    };
    let units = match &model {
        Some(m) => SetpointUnits::Output(&m.scaling),
        None => SetpointUnits::Normalised,
    };
    // A `t` column, if any, is checked as a stream's (uniform steps); the sequence itself
    // takes its time from the edges.
    let positions = setpoint_file::read(&args.data, units, 50_000.0, None)?.samples;
    let mode = match &args.mode {
        Some(m) => Some(
            twinstack_link::board_requests::parse_mode(m).ok_or_else(|| {
                anyhow::anyhow!("--mode {m:?}: give bypass, open-loop or closed-loop")
            })?,
        ),
        None => None,
    };
    let mut client = match args.sim_camera_hz {
        Some(hz) => sim_with_camera(args, hz, positions.len() as u32)?,
        None => connect(&args.port)?,
    };
    if let Some(mode) = mode {
        client.set_mode(mode)?;
    }
    let options = SequenceOptions {
        config,
        idle: Duration::from_secs_f64(args.idle_s),
        poll: Duration::from_millis(20),
        timing: true,
    };
    let report = run_sequence(&mut client, &positions, &options, |_| {
        std::ops::ControlFlow::Continue(())
    })?;
    print_report(&report, positions.len(), args.json)?;
    let s = report.status;
    if s.steps == 0 && s.missed == 0 {
        anyhow::bail!(
            "no edge came in {} s: check the camera's TTL output on the trigger input (PA6) and --edge; a camera triggered by the settled output (PA7) waits for the stage to settle within --window {}",
            args.idle_s,
            args.window
        );
    }
    if !report.complete || s.missed > 0 {
        anyhow::bail!(
            "the sequence reached {} of {} positions ({} edges missed, {} early): no edge for {} s",
            s.steps,
            positions.len(),
            s.missed,
            s.early,
            args.idle_s
        );
    }
    Ok(())
}

/// The simulated board with a camera (`--port sim` only).
fn sim_with_camera(args: &Args, hz: f64, frames: u32) -> anyhow::Result<BoardClient> {
    if port_spec(&args.port)? != PortSpec::Sim {
        anyhow::bail!(
            "--sim-camera-hz: only with --port sim (a served virtual board takes `twinstack virtual-board --camera-hz`; a real board, a real camera)"
        );
    }
    let mut config = SimDeviceConfig {
        baud: args.port.baud,
        link: args.port.link.delay()?,
        ..SimDeviceConfig::paper()
    };
    let rate = 1.0 / config.board.plant.dt;
    config.camera = Some(
        CameraConfig::at_rate(hz, rate, frames, args.sim_camera_on_settled)
            .map_err(|e| anyhow::anyhow!("--sim-camera-hz: {e}"))?,
    );
    let device = SimDevice::new(config)?;
    let mut client: BoardClient = Client::new(Box::new(device));
    client.set_timeout(Duration::from_millis(args.port.timeout_ms.max(1)));
    client.resync(Duration::from_millis(20))?;
    Ok(client)
}

fn print_report(r: &SequenceReport, total: usize, json: bool) -> anyhow::Result<()> {
    let s = r.status;
    if json {
        let v = serde_json::json!({
            "positions": total,
            "sent": r.sent,
            "steps": s.steps,
            "early": s.early,
            "missed": s.missed,
            "complete": r.complete,
            "ticks_to_motion": r.timing.map(|t| t.ticks_to_motion),
        });
        println!("{}", serde_json::to_string(&v)?);
        return Ok(());
    }
    println!("positions  {total} (sent {})", r.sent);
    println!("steps      {}", s.steps);
    println!(
        "early      {} (edges before the stage had settled)",
        s.early
    );
    println!("missed     {} (edges with no position left)", s.missed);
    match r.timing {
        Some(t) => println!(
            "first edge to the first moved DAC sample: {} ticks after the tick that sampled it (DAC code {} -> {})",
            t.ticks_to_motion, t.codes.0, t.codes.1
        ),
        None => println!(
            "first edge to motion: not measured (no edge in the capture, or its position is where the stage already was)"
        ),
    }
    Ok(())
}
