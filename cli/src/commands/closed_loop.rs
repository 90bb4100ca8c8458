//! `twinstack closed-loop`: sensor feedback around the feedforward compensator on the simulated
//! stage — the tracking table (4 configurations × 2 waveforms × each rate) and the step with and
//! without the resonance notch.

use crate::closed_loop::{print, run as run_study, ClosedLoopOptions, Gains};
use std::path::PathBuf;

/// Arguments of `twinstack closed-loop`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Control rates, Hz, comma-separated (each 44 500 … 200 000, so the notch at the
    /// 21.8 kHz resonance lies below Nyquist).
    #[arg(long, value_delimiter = ',', default_values_t = [50_000.0, 100_000.0])]
    pub rates: Vec<f64>,
    /// Cycles of the 750 Hz sine per run (4 … 10 000; the first two are not scored).
    #[arg(long, default_value_t = 30)]
    pub sine_cycles: usize,
    /// Cycles of the 100 Hz triangle per run (2 … 1000; the first is not scored).
    #[arg(long, default_value_t = 4)]
    pub triangle_cycles: usize,
    /// Position sensor noise, µm rms (0 … 1).
    #[arg(long, default_value_t = 0.002)]
    pub sensor_noise_um: f64,
    /// Directory for the step figure (PNG).
    #[arg(long, default_value = "out")]
    pub out: PathBuf,
    /// Write no figure.
    #[arg(long)]
    pub no_plot: bool,
    /// The feedback gains: `tuned` (what `twinstack tune` picks at each rate on the simulated
    /// board) or `fixed` (kp 0.1, ki 0.2 × rate /s, notch at 21.8 kHz, Q 2).
    #[arg(long, value_enum, default_value_t = GainsArg::Tuned)]
    pub gains: GainsArg,
    /// Also track with the setpoints shaped for the stage's resonance, as `twinstack stream
    /// --preview` shapes a stream: the resonance `twinstack tune` measures at each rate, and
    /// the feedforward's rows again (open and closed loop), scored against the waveform.
    #[arg(long)]
    pub preview: bool,
}

/// `--gains` values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum GainsArg {
    /// What `twinstack tune` picks at each rate.
    Tuned,
    /// The fixed PI with the notch.
    Fixed,
}

/// Runs the study and prints its tables.
pub fn run(args: &Args) -> anyhow::Result<()> {
    if !(0.0..=1.0).contains(&args.sensor_noise_um) {
        anyhow::bail!(
            "--sensor-noise-um {} is outside 0 … 1",
            args.sensor_noise_um
        );
    }
    if !(4..=10_000).contains(&args.sine_cycles) {
        anyhow::bail!("--sine-cycles {} is outside 4 … 10 000", args.sine_cycles);
    }
    if !(2..=1000).contains(&args.triangle_cycles) {
        anyhow::bail!(
            "--triangle-cycles {} is outside 2 … 1000",
            args.triangle_cycles
        );
    }
    let report = run_study(&ClosedLoopOptions {
        rates: args.rates.clone(),
        sine_cycles: args.sine_cycles,
        triangle_cycles: args.triangle_cycles,
        sensor_noise_um: args.sensor_noise_um,
        out_dir: (!args.no_plot).then(|| args.out.clone()),
        gains: match args.gains {
            GainsArg::Tuned => Gains::Tuned,
            GainsArg::Fixed => Gains::Fixed,
        },
        preview: args.preview,
    })?;
    print(&report, &mut std::io::stdout().lock())?;
    Ok(())
}
