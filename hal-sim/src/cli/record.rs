//! `hal-sim record --port PORT --signal S --count N [--decimation D] --out FILE.csv`: arms the
//! board's data recorder (`N` values of one signal, one every `D` ticks), waits for the
//! capture, reads it back in chunks and writes `t,<signal>,<signal>_q2_30` — `t` in seconds
//! from the arming, the value normalised (−1…1 of the model's range) and as the raw Q2.30
//! integer. The file is written only if all `N` values arrived.

use super::board_link::{connect, PortArgs};
use crate::output_file::Staged;
use anyhow::bail;
use std::path::PathBuf;
use std::time::Duration;
use twinstack::protocol::messages::{RecordRequest, Signal};

/// Arguments of `record`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// Signal to capture.
    #[arg(long, value_enum)]
    pub signal: SignalArg,
    /// Values to capture.
    #[arg(long)]
    pub count: u32,
    /// Ticks per captured value.
    #[arg(long, default_value_t = 1)]
    pub decimation: u16,
    /// CSV to write.
    #[arg(long)]
    pub out: PathBuf,
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

/// The CSV text of a capture.
pub fn recording_csv(name: &str, values: &[i32], seconds_per_value: f64) -> String {
    let mut s = format!("t,{name},{name}_q2_30\n");
    for (i, &v) in values.iter().enumerate() {
        s.push_str(&format!(
            "{},{},{v}\n",
            i as f64 * seconds_per_value,
            v as f64 / (1u64 << 30) as f64
        ));
    }
    s
}

/// Runs `record`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    if args.count == 0 {
        bail!("--count must be at least 1");
    }
    if args.decimation == 0 {
        bail!("--decimation must be at least 1");
    }
    let mut client = connect(&args.port)?;
    let tick_rate = client.status()?.tick_rate_hz.max(1) as f64;
    client.arm_recorder(RecordRequest {
        signal: args.signal.signal(),
        count: args.count,
        decimation: args.decimation,
    })?;
    // Wait for the capture: poll the status's `recorded` until it reaches the count, for at
    // most twice the capture's duration plus the response timeout.
    let capture = args.count as f64 * args.decimation as f64 / tick_rate;
    let step = (capture / 20.0).clamp(0.001, 0.25);
    let budget = capture * 2.0 + client.timeout().as_secs_f64();
    let mut waited = 0.0;
    let bar = super::progress::bar(args.count as u64, "recording", "values");
    loop {
        let s = client.status()?;
        bar.set_position(s.recorded.min(args.count) as u64);
        if s.recorded >= args.count {
            break;
        }
        if waited > budget {
            bail!(
                "the recorder holds {} of {} values after {waited:.1} s (capture {capture:.3} s): is the board ticking?",
                s.recorded,
                args.count
            );
        }
        client.wait(Duration::from_secs_f64(step))?;
        waited += step;
    }
    bar.finish_and_clear();
    let bar = super::progress::bar(args.count as u64, "reading", "values");
    let values = client.read_recording(args.count, |n| bar.set_position(n as u64));
    bar.finish_and_clear();
    let values = values?;
    let mut out = Staged::new();
    out.write(
        &args.out,
        recording_csv(
            args.signal.name(),
            &values,
            args.decimation as f64 / tick_rate,
        )
        .as_bytes(),
    )?;
    out.commit()?;
    println!(
        "wrote {} ({} values of {}, one every {} ticks at {} Hz)",
        args.out.display(),
        values.len(),
        args.signal.name(),
        args.decimation,
        tick_rate
    );
    Ok(())
}
