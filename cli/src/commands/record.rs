//! `twinstack record`, two forms:
//!
//! * `--signals setpoint,left,right,sensor,estimate,error --samples N [--pre P]
//!   [--trigger now|stream|waveform] [--decimation D] --out run.csv [--png run.png]`: arms a
//!   multi-signal capture (protocol v4: `N` frames of the listed signals, `P` of them from
//!   before the trigger), waits until it is done, reads the window back and writes it in
//!   physical units (header `t [s],setpoint [um],left [V],…`: `t` from the trigger frame, the
//!   stacks in volts, displacements in the output unit of the settings read back from the
//!   board), plus a PNG. With `--trigger stream` or `waveform` start the stream or the
//!   waveform from another command while it waits (or record a streamed run over one
//!   connection: `twinstack stream --record`).
//! * `--signal S --count N [--decimation D] --out FILE.csv` (protocol v3's `Record`): `N`
//!   values of one signal, full Q2.30; writes `t,<signal>,<signal>_q2_30` — `t` in seconds
//!   from the arming, the value normalised (−1…1 of the model's range) and as the raw Q2.30
//!   integer.
//!
//! Files are written only if the whole capture arrived.

use super::board_link::{connect, BoardClient, PortArgs};
use anyhow::bail;
use std::path::{Path, PathBuf};
use std::time::Duration;
use twinstack::protocol::messages::{CaptureRequest, RecordRequest, Signal, Trigger};
use twinstack_link::capture;
use twinstack_link::output_file::Staged;

/// Arguments of `record`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// Signals of a multi-signal capture, comma-separated: setpoint, left, right, sensor,
    /// estimate, error.
    #[arg(long, conflicts_with_all = ["signal", "count"], requires = "samples")]
    pub signals: Option<String>,
    /// Frames (values per signal) of a multi-signal capture, pre-trigger included.
    #[arg(long, requires = "signals")]
    pub samples: Option<u32>,
    /// Frames of a multi-signal capture from before the trigger.
    #[arg(long, default_value_t = 0, requires = "signals")]
    pub pre: u32,
    /// What triggers a multi-signal capture.
    #[arg(long, value_enum, default_value_t = TriggerArg::Now, requires = "signals")]
    pub trigger: TriggerArg,
    /// Seconds to wait for a multi-signal capture to complete (the trigger included).
    #[arg(long, default_value_t = 30.0, requires = "signals", value_parser = super::parse_positive_seconds)]
    pub wait_s: f64,
    /// PNG of a multi-signal capture [default: the CSV's name with .png].
    #[arg(long, requires = "signals")]
    pub png: Option<PathBuf>,
    /// One signal to record at full Q2.30 (protocol v3's record).
    #[arg(long, value_enum, requires = "count")]
    pub signal: Option<SignalArg>,
    /// Values of the one signal.
    #[arg(long, requires = "signal")]
    pub count: Option<u32>,
    /// Ticks per captured value.
    #[arg(long, default_value_t = 1)]
    pub decimation: u16,
    /// Arm the multi-signal capture and return (the port is then free for the command that
    /// triggers it: `twinstack stream`, `twinstack waveform`); read it later with --fetch.
    #[arg(long, requires = "signals")]
    pub arm_only: bool,
    /// Arm nothing: wait for the capture armed before (--arm-only) and read it back.
    #[arg(long, conflicts_with_all = ["signals", "signal"])]
    pub fetch: bool,
    /// CSV to write.
    #[arg(long, required_unless_present = "arm_only")]
    pub out: Option<PathBuf>,
}

/// `--trigger` values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum TriggerArg {
    /// At once.
    Now,
    /// When the setpoint stream starts.
    Stream,
    /// When the waveform generator starts.
    Waveform,
    /// When a scan starts (`twinstack scan`).
    Scan,
    /// On the external trigger input's armed edge.
    External,
}

impl TriggerArg {
    /// The wire trigger.
    pub fn trigger(self) -> Trigger {
        match self {
            TriggerArg::Now => Trigger::Now,
            TriggerArg::Stream => Trigger::StreamStart,
            TriggerArg::Waveform => Trigger::WaveformStart,
            TriggerArg::Scan => Trigger::ScanStart,
            TriggerArg::External => Trigger::External,
        }
    }
}

/// `--signal` values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum SignalArg {
    /// The setpoint.
    Setpoint,
    /// The applied drive.
    Drive,
    /// The sensor reading.
    Sensor,
    /// The observer's estimate.
    Estimate,
}

impl SignalArg {
    fn signal(self) -> Signal {
        match self {
            SignalArg::Setpoint => Signal::Setpoint,
            SignalArg::Drive => Signal::Drive,
            SignalArg::Sensor => Signal::Sensor,
            SignalArg::Estimate => Signal::Estimate,
        }
    }

    fn name(self) -> &'static str {
        match self {
            SignalArg::Setpoint => "setpoint",
            SignalArg::Drive => "drive",
            SignalArg::Sensor => "sensor",
            SignalArg::Estimate => "estimate",
        }
    }
}

/// The CSV of a single-signal record: `t,<name>,<name>_q2_30`, one row per value.
pub fn recording_csv(
    name: &str,
    values: &[i32],
    seconds_per_value: f64,
) -> Result<Vec<u8>, csv::Error> {
    twinstack_link::output_file::csv_bytes(|w| {
        w.write_record(["t".to_string(), name.to_string(), format!("{name}_q2_30")])?;
        for (i, &v) in values.iter().enumerate() {
            w.write_record([
                (i as f64 * seconds_per_value).to_string(),
                (v as f64 / (1u64 << 30) as f64).to_string(),
                v.to_string(),
            ])?;
        }
        Ok(())
    })
}

/// Arms a multi-signal capture of `signals` (a list of names) on `client`, checking the
/// request against the board's capacity first; returns the request armed.
pub fn arm_capture(
    client: &mut BoardClient,
    signals: &str,
    samples: u32,
    pre: u32,
    trigger: Trigger,
    decimation: u16,
) -> anyhow::Result<CaptureRequest> {
    use twinstack_link::board_requests::CaptureRequestError as E;
    let request = twinstack_link::board_requests::capture_request(signals, samples, pre, trigger, decimation)
        .map_err(|e| match e {
            E::Signals { list, error } => anyhow::anyhow!("--signals {list:?}: {error}"),
            E::NoSamples => anyhow::anyhow!("--samples must be at least 1"),
            E::NoDecimation => anyhow::anyhow!("--decimation must be at least 1"),
            E::PreNotBelowSamples { pre, samples } => {
                anyhow::anyhow!("--pre {pre}: must be below --samples {samples}")
            }
            E::PreWithNow(pre) => anyhow::anyhow!(
                "--pre {pre} with --trigger now: nothing comes before an immediate trigger; use --pre 0"
            ),
        })?;
    client.arm_capture(request)?;
    Ok(request)
}

/// Waits for the capture armed on `client`, reads it back, converts it with the settings in
/// force and writes the CSV `out` and the PNG `png`; returns a one-line summary.
pub fn finish_capture(
    client: &mut BoardClient,
    wait: Duration,
    out: &Path,
    png: &Path,
) -> anyhow::Result<String> {
    let settings = client.read_params()?;
    let bar = super::progress::bar(0, "capturing", "values");
    let r = capture::wait_and_read(client, wait, |what, n| {
        bar.set_message(what.to_string());
        bar.set_position(n as u64)
    });
    bar.finish_and_clear();
    let (status, window) = r?;
    let recording = capture::convert(&status, &settings, &window)?;
    let mut files = Staged::new();
    files.write(out, &capture::csv(&recording)?)?;
    let temp_png = files.temporary_for(png);
    let names: Vec<&str> = recording.columns.iter().map(|c| c.channel.name()).collect();
    crate::plot::capture(
        &recording,
        &temp_png,
        &format!(
            "{} frames, {} Hz / {}",
            recording.t.len(),
            status.tick_rate_hz,
            status.decimation
        ),
    )?;
    files.commit()?;
    Ok(format!(
        "wrote {} and {} ({} frames of {}, {} before the trigger, one every {} ticks at {} Hz)",
        out.display(),
        png.display(),
        recording.t.len(),
        names.join(", "),
        status.pre_available,
        status.decimation,
        status.tick_rate_hz
    ))
}

/// Runs `record`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    super::check_positive_seconds("--wait-s", args.wait_s)?;
    let wait = Duration::from_secs_f64(args.wait_s);
    let png_for = |out: &Path| {
        args.png
            .clone()
            .unwrap_or_else(|| out.with_extension("png"))
    };
    if args.fetch {
        let Some(out) = &args.out else {
            bail!("--fetch needs --out FILE.csv");
        };
        let mut client = connect(&args.port)?;
        println!("{}", finish_capture(&mut client, wait, out, &png_for(out))?);
        return Ok(());
    }
    if let Some(signals) = &args.signals {
        let mut client = connect(&args.port)?;
        let request = arm_capture(
            &mut client,
            signals,
            args.samples.unwrap_or(0),
            args.pre,
            args.trigger.trigger(),
            args.decimation,
        )?;
        let Some(out) = args.out.as_deref().filter(|_| !args.arm_only) else {
            println!(
                "capture armed ({} frames, {} before the trigger, trigger {:?}): read it with `twinstack record --fetch --out FILE.csv` once triggered",
                request.samples, request.pre_trigger, request.trigger
            );
            return Ok(());
        };
        println!("{}", finish_capture(&mut client, wait, out, &png_for(out))?);
        return Ok(());
    }
    let Some(out) = &args.out else {
        bail!("--out FILE.csv is required");
    };
    let (Some(signal), Some(count)) = (args.signal, args.count) else {
        bail!("give --signals LIST --samples N (a multi-signal capture) or --signal S --count N (one signal, Q2.30)");
    };
    if count == 0 {
        bail!("--count must be at least 1");
    }
    if args.decimation == 0 {
        bail!("--decimation must be at least 1");
    }
    let mut client = connect(&args.port)?;
    let tick_rate = client.status()?.tick_rate_hz.max(1) as f64;
    client.arm_recorder(RecordRequest {
        signal: signal.signal(),
        count,
        decimation: args.decimation,
    })?;
    // Wait for the capture: poll the status's `recorded` until it reaches the count, for at
    // most twice the capture's duration plus the response timeout.
    let capture = count as f64 * args.decimation as f64 / tick_rate;
    let step = (capture / 20.0).clamp(0.001, 0.25);
    let budget = capture * 2.0 + client.timeout().as_secs_f64();
    let mut waited = 0.0;
    let bar = super::progress::bar(count as u64, "recording", "values");
    loop {
        let s = client.status()?;
        bar.set_position(s.recorded.min(count) as u64);
        if s.recorded >= count {
            break;
        }
        if waited > budget {
            bail!(
                "the recorder holds {} of {} values after {waited:.1} s (capture {capture:.3} s): is the board ticking?",
                s.recorded,
                count
            );
        }
        client.wait(Duration::from_secs_f64(step))?;
        waited += step;
    }
    bar.finish_and_clear();
    let bar = super::progress::bar(count as u64, "reading", "values");
    let values = client.read_recording(count, |n| bar.set_position(n as u64));
    bar.finish_and_clear();
    let values = values?;
    let mut files = Staged::new();
    files.write(
        out,
        &recording_csv(signal.name(), &values, args.decimation as f64 / tick_rate)?,
    )?;
    files.commit()?;
    println!(
        "wrote {} ({} values of {}, one every {} ticks at {} Hz)",
        out.display(),
        values.len(),
        signal.name(),
        args.decimation,
        tick_rate
    );
    Ok(())
}
