//! `twinstack learn --waveform sine:750|triangle:200 --periods 50`: learning feedforward
//! (iterative learning control) for periodic motion.
//!
//! Without `--port` (and without `TWINSTACK_PORT`) it runs the study in process on the
//! simulated differential stage ([`crate::learn`]): the P–I model identified there, the
//! feedforward alone, the learning curve scored from the stage itself, and the frozen table
//! replayed on a fresh board with the sensor off. With `--port` it drives a board (`sim`, a
//! virtual board, the emulator, a real one) over the protocol ([`crate::learn_link`]): the
//! board learns from its own sensor and reports each period's error.
//!
//! Prints the learning curve and a table (max and RMS in % of the stroke), writes a PNG of
//! the curve, and with `--json` prints the figures as one JSON object on stdout instead.

use super::board_link::PortArgs;
use crate::learn::{LearnOptions, Motion};
use std::path::PathBuf;

/// Arguments of `twinstack learn`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// The board; without it (and without TWINSTACK_PORT) the study runs in process on the
    /// simulated stage.
    #[command(flatten)]
    pub port: PortArgs,
    /// The motion: sine:HZ or triangle:HZ (a whole number of cycles must fit 512 ticks).
    #[arg(long, default_value = "sine:750")]
    pub waveform: Motion,
    /// Learning periods (1 … 10 000).
    #[arg(long, default_value_t = 50)]
    pub periods: usize,
    /// Control rate of the in-process study, Hz (20 000 … 200 000; a board uses its own).
    #[arg(long, default_value_t = 50_000.0)]
    pub rate: f64,
    /// Learning gain (0 < L ≤ 1.5).
    #[arg(long, default_value_t = 0.3)]
    pub gain: f64,
    /// Corner of the robustness filter, Hz (below half the control rate); default 18 000,
    /// or 23 000 with input shaping (--shape-hz).
    #[arg(long)]
    pub cutoff_hz: Option<f64>,
    /// Phase lead, ticks (0 … 64).
    #[arg(long, default_value_t = 0)]
    pub lead: u16,
    /// Input shaping: centre of a notch on the feedforward, Hz (the stage's resonance, as
    /// `twinstack tune` fits it and prints the shaping for; 21 807 on the simulated stage);
    /// without it, no shaping.
    #[arg(long)]
    pub shape_hz: Option<f64>,
    /// Quality factor of the shaping notch (0.1 … 50); ½ puts its poles at critical damping.
    #[arg(long, default_value_t = 0.5, requires = "shape_hz")]
    pub shape_q: f64,
    /// Gain of the shaping notch at its centre (0 … 1): 2·Q·ζ of the resonance cancels its
    /// poles with the notch's zeros (0.0173 on the simulated stage, ζ = 0.01729, Q = ½).
    #[arg(long, default_value_t = 0.0173, requires = "shape_hz")]
    pub shape_depth: f64,
    /// Amplitude of the waveform on a board (--port), normalised about the middle of the
    /// model's output range (0 < A ≤ 1; 0.8 is 10–90 % of it, more than the simulated
    /// board's stage reaches with its representative model). The in-process study always
    /// plays 10–90 % of its identified model's range.
    #[arg(long, default_value_t = 0.5)]
    pub amplitude: f64,
    /// Position sensor noise of the in-process study, µm rms (0 … 1).
    #[arg(long, default_value_t = 0.002)]
    pub sensor_noise_um: f64,
    /// Directory for the learning-curve figure (PNG).
    #[arg(long, default_value = "out")]
    pub out: PathBuf,
    /// Write no figure.
    #[arg(long)]
    pub no_plot: bool,
    /// Print the figures as one JSON object on stdout (instead of the tables).
    #[arg(long)]
    pub json: bool,
}

/// Runs `learn`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    if !(1..=10_000).contains(&args.periods) {
        anyhow::bail!("--periods {} is outside 1 … 10 000", args.periods);
    }
    if !(0.0..=1.0).contains(&args.sensor_noise_um) {
        anyhow::bail!(
            "--sensor-noise-um {} is outside 0 … 1",
            args.sensor_noise_um
        );
    }
    if !(20_000.0..=200_000.0).contains(&args.rate) {
        anyhow::bail!("--rate {} is outside 20 000 … 200 000 Hz", args.rate);
    }
    let options = LearnOptions {
        rate: args.rate,
        periods: args.periods,
        sensor_noise_um: args.sensor_noise_um,
        gain: args.gain,
        cutoff_hz: args.cutoff_hz.unwrap_or(if args.shape_hz.is_some() {
            crate::learn::SHAPED_CUTOFF_HZ
        } else {
            18_000.0
        }),
        lead_ticks: args.lead,
        shaping: args
            .shape_hz
            .map(|frequency_hz| twinstack::control::notch::NotchDesign {
                frequency_hz,
                q: args.shape_q,
                depth: args.shape_depth,
            }),
        out_dir: (!args.no_plot).then(|| args.out.clone()),
        ..LearnOptions::new(args.waveform)
    };
    let stdout = &mut std::io::stdout().lock();
    if args.port.port.is_some() {
        if args.shape_hz.is_some() {
            anyhow::bail!(
                "--shape-hz is for the in-process study; on a board the shaping is a setting: \
                 load it with the parameters (`shaping` in the parameter file, `twinstack load`)"
            );
        }
        let report = crate::learn_link::run(&args.port, &options, args.amplitude)?;
        if args.json {
            serde_json::to_writer_pretty(&mut *stdout, &report)?;
            println!();
        } else {
            crate::learn_link::print(&report, stdout)?;
        }
        return Ok(());
    }
    let report = crate::learn::run(&options)?;
    if args.json {
        serde_json::to_writer_pretty(&mut *stdout, &report)?;
        println!();
    } else {
        crate::learn::print(&report, stdout)?;
    }
    Ok(())
}
