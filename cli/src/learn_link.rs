//! `twinstack learn --port P`: learning feedforward on a board (the simulated one, a virtual
//! board, the emulator or a real one) over the protocol (`Request::Learn`, v6). The board
//! learns from its own sensor; the host only configures, switches and reads.
//!
//! 1. Configure the learning (period from the waveform's frequency and the board's rate),
//!    empty the table, open loop, start the waveform (about the middle of the model's output
//!    range, `--amplitude`, 0.5 by default).
//! 2. **Feedforward alone**: the empty table frozen (plays nothing; the board still reports
//!    each period's error as its sensor sees it).
//! 3. **Learning** for `periods` periods: each period's error as the board's task saw it.
//! 4. **Frozen replay**: the table plays without updating; the sensor is read only for the
//!    report. (The in-process study, `twinstack learn` without a port, replays with the sensor
//!    removed from the settings.)
//! 5. The table is read back and written to `learn-table-<waveform>.json` beside the figure.
//!
//! Errors are in % of the commanded stroke as the **sensor** sees them (its noise included).

use crate::board_link::{connect, BoardClient, PortArgs};
use crate::learn::{period_ticks, LearnOptions};
use crate::plot::{draw_panels, Panel, Series};
use anyhow::{anyhow, bail, Context, Result};
use plotters::style::{BLACK, BLUE, RED};
use std::path::PathBuf;
use std::time::{Duration, Instant};
use twinstack::fixed_point::signal_to_f64;
use twinstack::protocol::messages::{
    LearnRequest, LearnState, LearnStatus, Mode, Request, Response, StreamControl, WaveShape,
    Waveform,
};
use twinstack::services::learning::PeriodError;

/// One period as the board's sensor saw it, % of the commanded stroke.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct SensedPeriod {
    /// The board's period count.
    pub period: u32,
    /// Largest |error|.
    pub max_pct: f64,
    /// RMS error.
    pub rms_pct: f64,
}

/// What `learn --port` found.
#[derive(Clone, Debug, serde::Serialize)]
pub struct LinkReport {
    /// `sine:750`, `triangle:200`.
    pub waveform: String,
    /// Which image answered (`board`, `emulator`, `simulator`).
    pub image: String,
    /// The board's control rate, Hz.
    pub rate_hz: u32,
    /// The learning period, ticks.
    pub period_ticks: u16,
    /// The feedforward alone (the empty table), its last periods.
    pub feedforward: Vec<SensedPeriod>,
    /// The learning curve.
    pub curve: Vec<SensedPeriod>,
    /// The frozen table replayed, its last periods.
    pub replay: Vec<SensedPeriod>,
    /// Tables the board's task posted.
    pub updates: u32,
    /// Periods its task missed.
    pub missed: u32,
    /// Files written (figure, table).
    pub files: Vec<PathBuf>,
}

/// `e` (Q2.30 normalised displacement) in % of a commanded stroke of `2 · amplitude`.
fn pct(e: i32, amplitude: f64) -> f64 {
    100.0 * signal_to_f64(e) / (2.0 * amplitude)
}

fn learn(client: &mut BoardClient, r: LearnRequest) -> Result<Response> {
    let response = client.request(&Request::Learn(r.clone()))?;
    match response {
        Response::Nack { reason } => Err(anyhow!(
            "the board refused Learn({r:?}): {}",
            twinstack_link::client::nack_text(&reason)
        )),
        other => Ok(other),
    }
}

fn learn_status(client: &mut BoardClient) -> Result<LearnStatus> {
    match learn(client, LearnRequest::Status)? {
        Response::Learn(s) => Ok(s),
        other => {
            bail!("unexpected answer to Learn(Status): {other:?} (a board older than protocol v6?)")
        }
    }
}

/// Collects `count` periods' errors as the board's task reports them (polling its status;
/// a period completed between two polls is missed from the curve, not from the learning).
fn collect(
    client: &mut BoardClient,
    count: usize,
    period_s: f64,
    amplitude: f64,
) -> Result<Vec<SensedPeriod>> {
    let mut seen = learn_status(client)?.periods;
    let mut out = Vec::new();
    // Generous: a real board takes real time, the simulated ones simulated time.
    let deadline = Instant::now() + Duration::from_secs_f64(10.0 + 20.0 * period_s * count as f64);
    while out.len() < count {
        if Instant::now() > deadline {
            bail!(
                "the board completed {} of {count} periods in time: is the waveform running?",
                out.len()
            );
        }
        client.wait(Duration::from_secs_f64((period_s / 4.0).max(1e-4)))?;
        let s = learn_status(client)?;
        if s.periods != seen {
            seen = s.periods;
            let PeriodError { max, rms } = s.last;
            out.push(SensedPeriod {
                period: s.periods,
                max_pct: pct(max, amplitude),
                rms_pct: pct(rms, amplitude),
            });
        }
    }
    Ok(out)
}

/// Runs `learn --port` with the waveform's amplitude `amplitude` (normalised, about 0).
pub fn run(port: &PortArgs, options: &LearnOptions, amplitude: f64) -> Result<LinkReport> {
    if !(amplitude > 0.0 && amplitude <= 1.0) {
        bail!("amplitude {amplitude}: must lie in (0, 1] (normalised)");
    }
    let mut client = connect(port)?;
    let status = client.status()?;
    let rate = status.tick_rate_hz;
    let period = period_ticks(options.motion.frequency_hz, rate as f64)?;
    let period_s = period as f64 / rate as f64;
    let settings = options.learn_settings(period);
    learn(&mut client, LearnRequest::Configure(settings))?;
    learn(&mut client, LearnRequest::Reset)?;
    learn(&mut client, LearnRequest::State(LearnState::Frozen))?;
    client
        .set_mode(Mode::OpenLoop)
        .context("open loop (the learning plays on the inverse-model feedforward)")?;
    client.waveform(Waveform {
        shape: match options.motion.shape {
            twinstack::sources::waveform::Shape::Sine => WaveShape::Sine,
            twinstack::sources::waveform::Shape::Triangle => WaveShape::Triangle,
        },
        offset: 0,
        amplitude: twinstack_link::setpoint_file::q1_15(amplitude),
        frequency_mhz: (options.motion.frequency_hz * 1000.0).round() as u32,
        decay: None,
    })?;
    let feedforward = collect(&mut client, 8, period_s, amplitude)?.split_off(3);
    learn(&mut client, LearnRequest::State(LearnState::Learning))?;
    let curve = collect(&mut client, options.periods, period_s, amplitude)?;
    learn(&mut client, LearnRequest::State(LearnState::Frozen))?;
    let replay = collect(&mut client, 8, period_s, amplitude)?.split_off(3);
    let s = learn_status(&mut client)?;
    // Read the table back (the host's copy: played again by `learning::write_table`).
    let table = twinstack_link::learning::read_table(&mut client)?;
    client.stream(StreamControl::Stop)?;
    let mut report = LinkReport {
        waveform: options.motion.label(),
        image: status.image().name().to_string(),
        rate_hz: rate,
        period_ticks: period,
        feedforward,
        curve,
        replay,
        updates: s.updates,
        missed: s.missed,
        files: Vec::new(),
    };
    if let Some(dir) = &options.out_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let name = options.motion.label().replace(':', "-");
        let json = dir.join(format!("learn-table-{name}.json"));
        let text = serde_json::json!({
            "waveform": report.waveform,
            "rate_hz": rate,
            "period_ticks": period,
            "format": "Q2.30 normalised drive per tick of the period",
            "table": table,
        });
        std::fs::write(&json, serde_json::to_string_pretty(&text)?)
            .with_context(|| format!("writing {}", json.display()))?;
        let png = dir.join(format!("learn-board-{name}.png"));
        draw(&png, &report)?;
        report.files.extend([png, json]);
    }
    Ok(report)
}

fn draw(path: &std::path::Path, r: &LinkReport) -> Result<()> {
    let log = |v: f64| v.max(1e-6).log10();
    let pts = |f: fn(&SensedPeriod) -> f64| -> Vec<(f64, f64)> {
        r.curve
            .iter()
            .enumerate()
            .map(|(k, p)| ((k + 1) as f64, log(f(p))))
            .collect()
    };
    let ff_rms = r.feedforward.iter().map(|p| p.rms_pct).fold(0.0, f64::max);
    let n = r.curve.len().max(1) as f64;
    draw_panels(
        path,
        &format!(
            "Learning on the {} ({} at {} Hz)",
            r.image, r.waveform, r.rate_hz
        ),
        &[Panel {
            caption: "error per period as the board's sensor sees it".into(),
            x_label: "period".into(),
            y_label: "log10 error [% of the stroke]".into(),
            series: vec![
                Series {
                    label: "max".into(),
                    points: pts(|p| p.max_pct),
                    color: RED,
                },
                Series {
                    label: "RMS".into(),
                    points: pts(|p| p.rms_pct),
                    color: BLUE,
                },
                Series {
                    label: "feedforward alone, RMS".into(),
                    points: vec![(1.0, log(ff_rms)), (n, log(ff_rms))],
                    color: BLACK,
                },
            ],
        }],
        1,
    )?;
    Ok(())
}

/// Prints the curve and the table.
pub fn print(r: &LinkReport, out: &mut impl std::io::Write) -> std::io::Result<()> {
    writeln!(
        out,
        "Learning on the {} at {} Hz, {} (period {} ticks); error as the sensor sees it, % of the commanded stroke",
        r.image, r.rate_hz, r.waveform, r.period_ticks
    )?;
    writeln!(out, "| period | max % | RMS % |")?;
    writeln!(out, "|---:|---:|---:|")?;
    for (k, p) in r.curve.iter().enumerate() {
        writeln!(out, "| {} | {:.4} | {:.4} |", k + 1, p.max_pct, p.rms_pct)?;
    }
    let last = |v: &[SensedPeriod]| {
        let n = v.len().max(1) as f64;
        (
            v.iter().map(|p| p.max_pct).fold(0.0, f64::max),
            (v.iter().map(|p| p.rms_pct * p.rms_pct).sum::<f64>() / n).sqrt(),
        )
    };
    writeln!(out, "\n| run | max % | RMS % |\n|---|---:|---:|")?;
    for (label, v) in [
        ("feedforward alone", &r.feedforward[..]),
        (
            "learned (last 5 periods)",
            &r.curve[r.curve.len().saturating_sub(5)..],
        ),
        ("frozen replay", &r.replay[..]),
    ] {
        let (m, s) = last(v);
        writeln!(out, "| {label} | {m:.4} | {s:.4} |")?;
    }
    writeln!(
        out,
        "\n{} tables posted, {} periods missed",
        r.updates, r.missed
    )?;
    for f in &r.files {
        writeln!(out, "wrote {}", f.display())?;
    }
    Ok(())
}
