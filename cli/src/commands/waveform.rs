//! `twinstack waveform --port PORT --shape sine|triangle --offset O --amplitude A --frequency HZ`:
//! starts the board's waveform generator (normalised units, −1…1 over the model's output
//! range; `offset ± amplitude` must stay inside it). `twinstack stop` stops it. `--decay F
//! [--hold-cycles N]` shrinks the amplitude by the factor `F` per cycle after `N` full ones
//! (nested minor loops about the offset).

use super::board_link::{connect, PortArgs};
use twinstack::protocol::messages::{WaveShape, Waveform};

/// Arguments of `waveform`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// Shape.
    #[arg(long, value_enum)]
    pub shape: Shape,
    /// Centre, normalised (−1…1).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub offset: f64,
    /// Amplitude, normalised (0…1; offset ± amplitude within −1…1).
    #[arg(long)]
    pub amplitude: f64,
    /// Frequency, Hz (resolution 1 mHz).
    #[arg(long)]
    pub frequency: f64,
    /// Amplitude kept per cycle once decaying (0…1, resolution 1/65536) [default: no decay].
    #[arg(long)]
    pub decay: Option<f64>,
    /// Cycles at full amplitude before the decay starts.
    #[arg(long, default_value_t = 1, requires = "decay")]
    pub hold_cycles: u16,
}

/// `--shape` values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Shape {
    /// Sine.
    Sine,
    /// Symmetric triangle.
    Triangle,
}

/// The request for `args`, or why the values cannot be sent.
pub fn waveform_of(args: &Args) -> anyhow::Result<Waveform> {
    let shape = match args.shape {
        Shape::Sine => WaveShape::Sine,
        Shape::Triangle => WaveShape::Triangle,
    };
    Ok(twinstack_link::board_requests::waveform(
        shape,
        args.offset,
        args.amplitude,
        args.frequency,
        args.decay.map(|d| (d, args.hold_cycles)),
    )?)
}

/// Runs `waveform`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let w = waveform_of(args)?;
    let mut client = connect(&args.port)?;
    client.waveform(w)?;
    println!(
        "waveform running: {:?}, offset {}, amplitude {}, {} Hz (stop with twinstack stop)",
        w.shape,
        args.offset,
        args.amplitude,
        w.frequency_mhz as f64 / 1000.0
    );
    Ok(())
}
