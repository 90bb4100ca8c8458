//! `twinstack tune --port P [--rate 50k|100k] [--phase-margin 45] [--gain-margin 6] [--load]
//! [--json] [--png F] [--kp K --ki I [--notch-hz F --notch-q Q --notch-depth D]]`: measures
//! the stage's frequency response with the board's generator and recorder, fits a resonance
//! and the loop's delay, places the notch and chooses the PI gains for the margins
//! ([`twinstack_identify::tune`]), prints the margins and the bandwidth, and with `--load` loads them.
//! With `--kp`/`--ki` it checks that gain set instead (exit 1 if the fitted model says it is
//! unstable or short of the margins). With `--params PARAMS.json` it writes the fitted
//! resonance into that parameter file (as `calibrate` does), for `compensate --preview`. The
//! `--json` object is the library's ([`TuneReport::to_json`]), what Python's `Board.tune` returns.

use super::board_link::{connect, PortArgs, UsageError};
use crate::plot::{draw_panels, Panel, Series};
use hal_sim::sim_device::{LinkDelay, SimDevice, SimDeviceConfig};
use plotters::style::RGBColor;
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::time::Duration;
use twinstack::control::feedback::FeedbackSettings;
use twinstack::control::notch::NotchDesign;
use twinstack_identify::param_file::ParamFile;
use twinstack_identify::preview::Resonance;
use twinstack_identify::tune::loop_model::{loop_response, LoopController};
use twinstack_identify::tune::{shaping_for, tune, SweepEvent, TuneOptions, TuneReport};
use twinstack_link::output_file::Staged;
use twinstack_link::{Client, Transport};

/// Arguments of `tune`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// Control rate of the simulated board (`--port sim` only): 50k or 100k (any rate in Hz
    /// from 10k to 100k); another board runs at its own rate.
    #[arg(long, value_parser = parse_rate)]
    pub rate: Option<f64>,
    /// Least phase margin, degrees.
    #[arg(long, default_value_t = 45.0)]
    pub phase_margin: f64,
    /// Least gain margin, dB.
    #[arg(long, default_value_t = 6.0)]
    pub gain_margin: f64,
    /// Load the tuned feedback onto the board (its other settings kept).
    #[arg(long)]
    pub load: bool,
    /// Print the figures as one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
    /// Write the fitted resonance into this parameter file (its `resonance`, what `calibrate`
    /// measures), for `load --preview` (the board's preview), `compensate --preview` and
    /// `stream --preview`; the rest of the file is kept. The file is checked before the sweep starts.
    #[arg(long, value_name = "PARAMS.json")]
    pub params: Option<PathBuf>,
    /// Write the Bode diagram (measured and fitted, and the loop) to this PNG.
    #[arg(long)]
    pub png: Option<PathBuf>,
    /// Check this proportional gain instead of designing (with --ki).
    #[arg(long, requires = "ki")]
    pub kp: Option<f64>,
    /// Check this integral gain, 1/s (with --kp).
    #[arg(long, requires = "kp")]
    pub ki: Option<f64>,
    /// The checked set's notch centre, Hz.
    #[arg(long, requires = "kp")]
    pub notch_hz: Option<f64>,
    /// The checked set's notch quality factor.
    #[arg(long, default_value_t = 2.0)]
    pub notch_q: f64,
    /// The checked set's notch depth (0: full).
    #[arg(long, default_value_t = 0.0)]
    pub notch_depth: f64,
    /// The checked set's correction limit, fraction of the drive range.
    #[arg(long, default_value_t = 0.25)]
    pub limit: f64,
}

/// `50k`, `100k`, or a number of Hz.
pub fn parse_rate(s: &str) -> Result<f64, String> {
    let t = s.trim().to_ascii_lowercase();
    let v = match t.strip_suffix('k') {
        Some(n) => n.parse::<f64>().map(|v| v * 1000.0),
        None => t.parse::<f64>(),
    }
    .map_err(|_| format!("--rate {s}: 50k, 100k or a number of Hz"))?;
    if !(10_000.0..=100_000.0).contains(&v) {
        return Err(format!("--rate {s}: the board runs from 10k to 100k"));
    }
    Ok(v)
}

impl Args {
    /// The library's options.
    pub fn options(&self) -> TuneOptions {
        TuneOptions {
            phase_margin_deg: self.phase_margin,
            gain_margin_db: self.gain_margin,
            check: match (self.kp, self.ki) {
                (Some(kp), Some(ki)) => Some(FeedbackSettings {
                    notch: self.notch_hz.map(|f| NotchDesign {
                        frequency_hz: f,
                        q: self.notch_q,
                        depth: self.notch_depth,
                    }),
                    ..FeedbackSettings::pi(kp, ki, self.limit)
                }),
                _ => None,
            },
            load: self.load,
            ..TuneOptions::default()
        }
    }
}

fn run_on<T: Transport>(args: &Args, client: &mut Client<T>) -> anyhow::Result<()> {
    let options = args.options();
    // A parameter file to take the resonance: refused before anything moves.
    let file = match &args.params {
        Some(path) => Some((path, ParamFile::load(path)?.0)),
        None => None,
    };
    let report = tune(client, &options, |event| {
        if let SweepEvent::Point(p) = event {
            if !args.json {
                eprintln!(
                    "  {:>8.0} Hz  {:>7.2} dB  {:>8.1}°",
                    p.frequency_hz,
                    p.magnitude_db(),
                    p.phase_deg()
                );
            }
        }
        ControlFlow::Continue(())
    })?;
    if let Some(png) = &args.png {
        plot(&report, png)?;
    }
    if let Some((path, mut file)) = file {
        let p = &report.fit.plant;
        let resonance = Resonance::new(p.resonance_hz, p.zeta).map_err(|e| {
            anyhow::anyhow!(
                "--params {}: the fitted resonance: {e}; the file is unchanged",
                path.display()
            )
        })?;
        file.resonance = Some(resonance);
        let mut out = Staged::new();
        out.write(path, file.to_json().as_bytes())?;
        out.commit()?;
        if !args.json {
            println!(
                "wrote the resonance ({:.0} Hz, damping {:.4}) into {}: `compensate --preview` and `stream --preview` shape for it",
                resonance.frequency_hz,
                resonance.damping,
                path.display()
            );
        }
    }
    if args.json {
        let mut v = report.to_json();
        if let Some(path) = &args.params {
            v["params"] = path.display().to_string().into();
        }
        println!("{v}");
        return Ok(());
    }
    let p = &report.fit.plant;
    let f = &report.design.figures;
    let s = &report.design.settings;
    println!(
        "fit: gain {:.3}, resonance {:.0} Hz, ζ = {:.4}, delay {} tick(s) (RMS error {:.2} dB, {:.1}°)",
        p.gain, p.resonance_hz, p.zeta, p.delay, report.fit.rms_db, report.fit.rms_deg
    );
    let shape = shaping_for(p.resonance_hz, p.zeta);
    println!(
        "input shaping (the feedforward's notch, for open loop and `learn`): --shape-hz {:.0} \
         --shape-q {} --shape-depth {:.4}",
        shape.frequency_hz, shape.q, shape.depth
    );
    println!(
        "preview (a planned trajectory shaped ahead of time, open loop): `compensate \
         --resonance-hz {:.0} --resonance-damping {:.4}`",
        p.resonance_hz, p.zeta
    );
    let notch = s.notch.map_or("none".to_string(), |n| {
        format!("{:.0} Hz, Q {}, depth {}", n.frequency_hz, n.q, n.depth)
    });
    println!(
        "{}: kp {:.4}, ki {:.0} /s, notch {notch}",
        if options.check.is_some() {
            "checked"
        } else {
            "tuned"
        },
        s.kp,
        s.ki
    );
    println!(
        "| phase margin | gain margin | closed-loop bandwidth | rejection bandwidth | sensitivity peak | step ringing 1–3 ms (model) |"
    );
    println!("|---:|---:|---:|---:|---:|---:|");
    println!(
        "| {:.1}° | {:.1} dB | {:.0} Hz | {:.0} Hz | {:.1} dB | {:.3} % |",
        f.phase_margin_deg,
        f.gain_margin_db,
        f.closed_loop_bandwidth_hz,
        f.bandwidth_hz,
        f.sensitivity_peak_db,
        f.ringing_pct
    );
    // The board's own timing, beside the loop the fit found: the sample's lead is a delay the
    // whole-tick model rounds (and the simulated board does not have).
    let (latency_s, lead_deg) = report.board_timing();
    println!(
        "board timing: sample to output {:.0} µs (one period, the DAC latched by the timer, plus \
         the sample's {:.0} µs lead); the lead costs {lead_deg:.1}° of phase at the {:.0} Hz \
         crossover",
        latency_s * 1e6,
        twinstack::board::SAMPLE_LEAD_NS as f64 * 1e-3,
        f.crossover_hz
    );
    if let Some((b, verdict)) = &report.before {
        match verdict {
            Ok(g) => println!(
                "the board's gains before (kp {}, ki {}): phase margin {:.1}°, gain margin {:.1} dB, closed-loop bandwidth {:.0} Hz",
                b.kp, b.ki, g.phase_margin_deg, g.gain_margin_db, g.closed_loop_bandwidth_hz
            ),
            Err(e) => println!("the board's gains before (kp {}, ki {}): {e}", b.kp, b.ki),
        }
    }
    if report.loaded {
        println!("loaded");
    }
    if let Some(png) = &args.png {
        println!("wrote {}", png.display());
    }
    Ok(())
}

/// Runs `tune`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let is_sim = args.port.port.as_deref().map(str::trim) == Some("sim");
    if let (Some(rate), true) = (args.rate, is_sim) {
        let config = SimDeviceConfig::paper_at(rate, args.port.baud, LinkDelay::IDEAL);
        let device = SimDevice::new(config).map_err(|e| anyhow::anyhow!("{e}"))?;
        let mut client = Client::new(device);
        client.set_timeout(Duration::from_millis(args.port.timeout_ms.max(1)));
        return run_on(args, &mut client);
    }
    if args.rate.is_some() && !is_sim {
        return Err(UsageError(
            "--rate applies to --port sim only: a board runs at its own rate".into(),
        )
        .into());
    }
    let mut client = connect(&args.port)?;
    run_on(args, &mut client)
}

/// The Bode diagram: measured and fitted response, and the loop with the chosen feedback.
fn plot(r: &TuneReport, path: &Path) -> anyhow::Result<()> {
    let black = RGBColor(0, 0, 0);
    let blue = RGBColor(31, 119, 180);
    let red = RGBColor(214, 39, 40);
    let lg = |f: f64| f.log10();
    let measured_mag: Vec<(f64, f64)> = r
        .points
        .iter()
        .map(|p| (lg(p.frequency_hz), 20.0 * p.response.abs().log10()))
        .collect();
    let measured_phase: Vec<(f64, f64)> = r
        .points
        .iter()
        .map(|p| (lg(p.frequency_hz), p.response.arg().to_degrees()))
        .collect();
    let lo = r.points.first().map_or(100.0, |p| p.frequency_hz);
    let grid: Vec<f64> = (0..400)
        .map(|i| lo * (0.4999 * r.rate / lo).powf(i as f64 / 399.0))
        .collect();
    let plant = &r.fit.plant;
    let fit_mag = grid
        .iter()
        .map(|&f| (lg(f), 20.0 * plant.response(f).abs().log10()))
        .collect();
    let fit_phase = grid
        .iter()
        .map(|&f| (lg(f), plant.response(f).arg().to_degrees()))
        .collect();
    let mut panels = vec![
        Panel {
            caption: format!(
                "magnitude: fit {:.0} Hz, ζ = {:.4}, delay {} tick(s)",
                plant.resonance_hz, plant.zeta, plant.delay
            ),
            x_label: "log10 frequency [Hz]".into(),
            y_label: "sensor / drive [dB]".into(),
            series: vec![
                Series {
                    label: "measured".into(),
                    points: measured_mag,
                    color: black,
                },
                Series {
                    label: "fitted".into(),
                    points: fit_mag,
                    color: blue,
                },
            ],
        },
        Panel {
            caption: "phase".into(),
            x_label: "log10 frequency [Hz]".into(),
            y_label: "[deg]".into(),
            series: vec![
                Series {
                    label: "measured".into(),
                    points: measured_phase,
                    color: black,
                },
                Series {
                    label: "fitted".into(),
                    points: fit_phase,
                    color: blue,
                },
            ],
        },
    ];
    if let Some(c) = LoopController::new(&r.design.settings, r.rate) {
        let l = loop_response(plant, &c, lo, 400);
        let f = &r.design.figures;
        panels.push(Panel {
            caption: format!(
                "loop gain |L|: PM {:.1}°, GM {:.1} dB, closed-loop bandwidth {:.0} Hz",
                f.phase_margin_deg, f.gain_margin_db, f.closed_loop_bandwidth_hz
            ),
            x_label: "log10 frequency [Hz]".into(),
            y_label: "[dB]".into(),
            series: vec![
                Series {
                    label: "|L| (fitted plant, chosen feedback)".into(),
                    points: l
                        .iter()
                        .map(|(f, v)| (lg(*f), 20.0 * v.abs().log10()))
                        .collect(),
                    color: red,
                },
                Series {
                    label: "0 dB".into(),
                    points: vec![(lg(lo), 0.0), (lg(0.4999 * r.rate), 0.0)],
                    color: black,
                },
            ],
        });
    }
    draw_panels(
        path,
        &format!(
            "tune at {:.0} kHz: measured and fitted response",
            r.rate / 1e3
        ),
        &panels,
        2,
    )?;
    Ok(())
}
