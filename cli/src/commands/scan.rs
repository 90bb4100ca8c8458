//! `twinstack scan --port PORT --pattern raster:lines=64,… | lissajous:… | spiral:…`: runs a
//! scan pattern generated on the board with its pixel, line and frame trigger outputs,
//! captures the setpoint and the trigger levels from the scan's start, and prints the timing
//! table ([`twinstack_link::scan_timing`]: each line and frame pulse against the library's replay of
//! the pattern, the jitter, the turnaround-to-pulse time); writes a PNG (x–y of the pattern,
//! and x(t) with the clocks); `--json` prints the figures as one JSON object instead.
//! Works against the simulated board (`--port sim`), the virtual board and the emulator.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Context};
use plotters::style::{RGBColor, BLACK, BLUE, RED};

use super::board_link::{connect, PortArgs};
use crate::plot::{draw_panels, Panel, Series};
use twinstack::protocol::messages::ScanRequest;
use twinstack::sources::scan::{TriggerEdge, LINE, PIXEL};
use twinstack_link::scan_timing::{parse_pattern, run_scan, table, ScanFigures};

/// Arguments of `scan`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// The pattern: `raster:lines=64,pixels=100,turn=40,amplitude=0.5,offset=0,y-amplitude=0.5,y-offset=0`,
    /// `lissajous:hz=20,x=3,y=2,phase=90,amplitude=0.5,…` or `spiral:hz=200,turns=10,amplitude=0.5,…`
    /// (normalised units, −1…1 over the output range).
    #[arg(long)]
    pub pattern: String,
    /// Ticks per pixel (the pixel clock's period; more than `--pulse`).
    #[arg(long, default_value_t = 4)]
    pub ticks_per_pixel: u16,
    /// Frames to scan (then the board holds the end point); 0 scans until `twinstack stop`
    /// (the capture then takes what fits).
    #[arg(long, default_value_t = 1)]
    pub frames: u16,
    /// Width of the trigger pulses, ticks.
    #[arg(long, default_value_t = 2)]
    pub pulse: u16,
    /// The figure.
    #[arg(long, default_value = "scan.png")]
    pub out: PathBuf,
    /// Print the figures as one JSON object on stdout (no table).
    #[arg(long)]
    pub json: bool,
    /// Longest wait for the capture, seconds.
    #[arg(long, default_value_t = 60.0, value_parser = super::parse_positive_seconds)]
    pub wait_s: f64,
    /// Wait for this edge of the trigger input to start the scan (`rising` or `falling`: a
    /// camera's frame starts it); `off` (the default) starts it at once.
    #[arg(long, default_value = "off", value_parser = parse_edge)]
    pub start_on: TriggerEdge,
}

/// `--start-on`'s value (here and in `twinstack stream`).
pub fn parse_edge(s: &str) -> Result<TriggerEdge, String> {
    match s {
        "off" => Ok(TriggerEdge::Off),
        "rising" => Ok(TriggerEdge::Rising),
        "falling" => Ok(TriggerEdge::Falling),
        other => Err(format!("{other:?}: expected off, rising or falling")),
    }
}

/// Runs `scan`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    super::check_positive_seconds("--wait-s", args.wait_s)?;
    let pattern = parse_pattern(&args.pattern)?;
    let request = ScanRequest {
        pattern,
        ticks_per_pixel: args.ticks_per_pixel,
        frames: args.frames,
        on_trigger: false,
    };
    let mut client = connect(&args.port)?;
    let run = run_scan(
        &mut client,
        request,
        args.pulse,
        args.start_on,
        Duration::from_secs_f64(args.wait_s.max(0.1)),
    )?;
    let (figures, x, trig, replay) = (&run.figures, &run.x, &run.triggers, &run.replay);
    draw(&args.out, figures, x, trig, replay)
        .with_context(|| format!("writing {}", args.out.display()))?;
    if args.json {
        let mut v = serde_json::to_value(figures)?;
        v["figure"] = serde_json::Value::String(args.out.display().to_string());
        v["truncated"] = serde_json::Value::Bool(run.truncated());
        println!("{}", serde_json::to_string(&v)?);
    } else {
        print!("{}", table(figures));
        if run.truncated() {
            println!(
                "(the capture holds {} of the {:.0} ticks the scan takes: the rest is not analysed)",
                x.len(),
                run.wanted_ticks
            );
        }
        println!("wrote {}", args.out.display());
    }
    if figures.x_mismatches > 0 || figures.trigger_mismatches > 0 {
        bail!(
            "the board's scan differs from the library's replay: {} setpoints, {} trigger ticks",
            figures.x_mismatches,
            figures.trigger_mismatches
        );
    }
    Ok(())
}

/// Two panels: x–y (captured x, replayed y) and x(t) with the line and pixel clocks over the
/// first lines.
fn draw(
    path: &std::path::Path,
    f: &ScanFigures,
    x: &[i16],
    trig: &[i16],
    replay: &twinstack_link::scan_timing::Replay,
) -> anyhow::Result<()> {
    let xy: Vec<(f64, f64)> = x
        .iter()
        .zip(replay)
        .filter_map(|(&xv, r)| r.map(|(_, y)| (xv as f64 / 32768.0, y)))
        .collect();
    let from = f.first_frame_tick.saturating_sub(10);
    let span = ((3.0 * f.line_ticks) as usize).max(50);
    let to = (from + span).min(x.len());
    let ms = |k: usize| k as f64 / f.rate_hz * 1e3;
    let level = |bit: i16, lo: f64, hi: f64| -> Vec<(f64, f64)> {
        (from..to)
            .map(|k| (ms(k), if trig[k] & bit != 0 { hi } else { lo }))
            .collect()
    };
    let panels = [
        Panel {
            caption: "pattern: x (captured setpoint) vs y (reported)".into(),
            x_label: "x (normalised)".into(),
            y_label: "y (normalised)".into(),
            series: vec![Series {
                label: "x–y".into(),
                points: xy,
                color: BLUE,
            }],
        },
        Panel {
            caption: format!(
                "x(t) and the clocks, first lines (line every {:.1} ticks)",
                f.line_ticks
            ),
            x_label: "t (ms)".into(),
            y_label: "x (normalised); clocks".into(),
            series: vec![
                Series {
                    label: "x".into(),
                    points: (from..to).map(|k| (ms(k), x[k] as f64 / 32768.0)).collect(),
                    color: BLUE,
                },
                Series {
                    label: "line clock".into(),
                    points: level(LINE as i16, -1.2, -1.0),
                    color: RED,
                },
                Series {
                    label: "pixel clock".into(),
                    points: level(PIXEL as i16, -1.45, -1.3),
                    color: RGBColor(0, 140, 0),
                },
            ],
        },
    ];
    let _ = BLACK;
    draw_panels(path, &format!("twinstack scan: {}", f.pattern), &panels, 2)?;
    Ok(())
}
