//! The figures of a scan the board ran ([`twinstack::sources::scan`]): its pattern and trigger outputs
//! as the board captured them (the `setpoint` and `triggers` capture signals), against the
//! library's own generator replayed on the host (bit for bit the board's arithmetic).
//!
//! [`analyse`] aligns the replay on the first frame clock the board captured, then reports
//! for the line and frame clocks each pulse's measured tick against the replay's (and the
//! spread: the jitter), the measured line period against the pattern's (a non-integer period
//! puts each pulse on the first tick at or after its ideal time: up to one tick late), the
//! pulse widths, the time from each x turnaround (the apex of x, found in the captured
//! setpoint) to the line pulse after it, and how many captured setpoints and trigger levels
//! differ from the replay's.

use serde::Serialize;
use twinstack::fixed_point::SIGNAL_ONE;
use twinstack::services::recorder::q1_15;
use twinstack::sources::scan::{
    LissajousScan, RasterScan, ScanGenerator, ScanPattern, ScanRequest, SpiralScan, TriggerOutputs,
    FRAME, LINE, PIXEL,
};

/// A `--pattern` that does not parse.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PatternError {
    /// Not `raster:…`, `lissajous:…` or `spiral:…`.
    #[error("unknown pattern {0:?} (raster:…, lissajous:… or spiral:…)")]
    Kind(String),
    /// A `key=value` whose key the pattern does not have.
    #[error("{pattern} has no parameter {key:?} (it has: {known})")]
    Key {
        /// The pattern.
        pattern: &'static str,
        /// The key given.
        key: String,
        /// The keys it has.
        known: &'static str,
    },
    /// A value that is not a number.
    #[error("{key}={value:?} is not a number")]
    Value {
        /// The key.
        key: String,
        /// The value given.
        value: String,
    },
    /// A count (lines, pixels, turn ticks, cycles, turns) that is not a whole number the
    /// pattern holds.
    #[error("{key}={value}: must be a whole number from 0 to 65535")]
    Count {
        /// The key.
        key: String,
        /// The value given.
        value: f64,
    },
    /// A key given twice.
    #[error("{key} is given twice")]
    Repeated {
        /// The key.
        key: String,
    },
}

/// Parses `raster:lines=64,pixels=100,turn=40,amplitude=0.5,offset=0,y-amplitude=0.5,y-offset=0`,
/// `lissajous:hz=20,x=3,y=2,phase=90,amplitude=0.5,offset=0,y-amplitude=0.5,y-offset=0` or
/// `spiral:hz=200,turns=10,amplitude=0.5,offset=0,y-offset=0` (normalised units; what is not
/// given keeps its default, shown here).
///
/// ```
/// use twinstack_link::scan_timing::parse_pattern;
/// use twinstack::sources::scan::ScanPattern;
/// let p = parse_pattern("raster:lines=8,turn=20").unwrap();
/// assert!(matches!(p, ScanPattern::Raster(r) if r.lines == 8 && r.turn_ticks == 20 && r.pixels == 100));
/// assert!(parse_pattern("raster:lines=x").is_err());
/// // A count is taken as given or refused: never rounded, clamped, or given twice.
/// assert!(parse_pattern("raster:lines=4.5").is_err());
/// assert!(parse_pattern("raster:lines=99999999").is_err());
/// assert!(parse_pattern("raster:lines=4,lines=5").is_err());
/// ```
pub fn parse_pattern(spec: &str) -> Result<ScanPattern, PatternError> {
    let (kind, rest) = spec.split_once(':').unwrap_or((spec, ""));
    let pairs = rest
        .split(',')
        .map(str::trim)
        .filter(|p| !p.is_empty())
        .map(|p| {
            let (k, v) = p.split_once('=').unwrap_or((p, ""));
            let value = v.trim().parse::<f64>().map_err(|_| PatternError::Value {
                key: k.trim().to_string(),
                value: v.to_string(),
            })?;
            Ok((k.trim().to_ascii_lowercase(), value))
        })
        .collect::<Result<Vec<_>, _>>()?;
    if let Some((_, (key, _))) = pairs
        .iter()
        .enumerate()
        .find(|(i, (k, _))| pairs[..*i].iter().any(|(seen, _)| seen == k))
    {
        return Err(PatternError::Repeated { key: key.clone() });
    }
    // A count as given: a whole number in range, never rounded or clamped into one.
    let count = |key: &str, v: f64| {
        if v.fract() == 0.0 && (0.0..=u16::MAX as f64).contains(&v) {
            Ok(v as u16)
        } else {
            Err(PatternError::Count {
                key: key.to_string(),
                value: v,
            })
        }
    };
    match kind.trim().to_ascii_lowercase().as_str() {
        "raster" => {
            let mut r = RasterScan {
                lines: 64,
                pixels: 100,
                turn_ticks: 40,
                offset: 0.0,
                amplitude: 0.5,
                y_offset: 0.0,
                y_amplitude: 0.5,
            };
            for (k, v) in pairs {
                match k.as_str() {
                    "lines" => r.lines = count(&k, v)?,
                    "pixels" => r.pixels = count(&k, v)?,
                    "turn" => r.turn_ticks = count(&k, v)?,
                    "offset" => r.offset = v,
                    "amplitude" => r.amplitude = v,
                    "y-offset" => r.y_offset = v,
                    "y-amplitude" => r.y_amplitude = v,
                    _ => {
                        return Err(PatternError::Key {
                            pattern: "raster",
                            key: k,
                            known: "lines, pixels, turn, offset, amplitude, y-offset, y-amplitude",
                        })
                    }
                }
            }
            Ok(ScanPattern::Raster(r))
        }
        "lissajous" => {
            let mut l = LissajousScan {
                frame_hz: 20.0,
                x_cycles: 3,
                y_cycles: 2,
                y_phase_deg: 90.0,
                offset: 0.0,
                amplitude: 0.5,
                y_offset: 0.0,
                y_amplitude: 0.5,
            };
            for (k, v) in pairs {
                match k.as_str() {
                    "hz" => l.frame_hz = v,
                    "x" => l.x_cycles = count(&k, v)?,
                    "y" => l.y_cycles = count(&k, v)?,
                    "phase" => l.y_phase_deg = v,
                    "offset" => l.offset = v,
                    "amplitude" => l.amplitude = v,
                    "y-offset" => l.y_offset = v,
                    "y-amplitude" => l.y_amplitude = v,
                    _ => {
                        return Err(PatternError::Key {
                            pattern: "lissajous",
                            key: k,
                            known: "hz, x, y, phase, offset, amplitude, y-offset, y-amplitude",
                        })
                    }
                }
            }
            Ok(ScanPattern::Lissajous(l))
        }
        "spiral" => {
            let mut s = SpiralScan {
                turn_hz: 200.0,
                turns: 10,
                offset: 0.0,
                amplitude: 0.5,
                y_offset: 0.0,
            };
            for (k, v) in pairs {
                match k.as_str() {
                    "hz" => s.turn_hz = v,
                    "turns" => s.turns = count(&k, v)?,
                    "offset" => s.offset = v,
                    "amplitude" => s.amplitude = v,
                    "y-offset" => s.y_offset = v,
                    _ => {
                        return Err(PatternError::Key {
                            pattern: "spiral",
                            key: k,
                            known: "hz, turns, offset, amplitude, y-offset",
                        })
                    }
                }
            }
            Ok(ScanPattern::Spiral(s))
        }
        _ => Err(PatternError::Kind(kind.to_string())),
    }
}

/// One clock's measured pulses against the replay.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct ClockFigures {
    /// Rising edges captured.
    pub pulses: usize,
    /// Largest |measured − replayed| edge time, ticks.
    pub error_max_ticks: i64,
    /// Spread of (measured − replayed), ticks: the jitter against the replay.
    pub jitter_ticks: i64,
    /// Shortest and longest time the output stayed high, ticks.
    pub width_ticks: (u32, u32),
    /// Shortest and longest interval between consecutive edges, ticks.
    pub period_ticks: (i64, i64),
    /// Largest |edge − (first edge + i × the pattern's ideal period)|, ticks (below one for a
    /// period that is not a whole number of ticks; 0 for the raster's).
    pub ideal_error_max_ticks: f64,
}

/// What [`analyse`] finds.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ScanFigures {
    /// The pattern, in words.
    pub pattern: String,
    /// Control rate, Hz.
    pub rate_hz: f64,
    /// Ticks per line the pattern defines.
    pub line_ticks: f64,
    /// Line rate, Hz.
    pub line_hz: f64,
    /// Ticks per pixel.
    pub pixel_ticks: u16,
    /// Pixel clock, Hz.
    pub pixel_hz: f64,
    /// Trigger pulse width asked, ticks.
    pub pulse_ticks: u16,
    /// Ticks captured.
    pub captured_ticks: usize,
    /// Tick (from the scan's start) of the first frame clock: the approach's length.
    pub first_frame_tick: usize,
    /// Pixel clock.
    pub pixel: ClockFigures,
    /// Line clock.
    pub line: ClockFigures,
    /// Frame clock.
    pub frame: ClockFigures,
    /// From each x turnaround (the apex, found in the captured setpoint) to the line pulse
    /// after it, ticks: (min, max, expected); `None` for the spiral (no turnaround).
    pub turnaround_to_line: Option<(f64, f64, f64)>,
    /// Captured setpoints compared with the replay's, and how many differ.
    pub x_compared: usize,
    /// Captured setpoints that differ from the replay's (Q1.15).
    pub x_mismatches: usize,
    /// Ticks whose trigger levels differ from the replay's.
    pub trigger_mismatches: usize,
}

/// The replayed pattern aligned on the capture, for the figure: (x, y) normalised per tick of
/// the capture (`None` before the replay's start).
pub type Replay = Vec<Option<(f64, f64)>>;

/// Why a capture cannot be analysed.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum AnalyseError {
    /// The scan itself (the board would have refused it too).
    #[error("the scan is refused: {0}")]
    Refused(twinstack::refusal::Refusal),
    /// No frame clock in the capture.
    #[error("no frame clock in the {0} ticks captured (pulse width 0, or the capture ended in the approach)")]
    NoFrame(usize),
    /// The two columns differ in length.
    #[error("the setpoint and trigger columns differ in length")]
    Length,
}

/// Rising edges of `bit` in `levels` (a high first tick counts as one).
fn rising(levels: &[u8], bit: u8) -> Vec<usize> {
    (0..levels.len())
        .filter(|&k| levels[k] & bit != 0 && (k == 0 || levels[k - 1] & bit == 0))
        .collect()
}

/// Runs of `bit` high, as (start, length); a run cut by the end of the capture is left out.
fn widths(levels: &[u8], bit: u8) -> Vec<u32> {
    let mut out = Vec::new();
    let mut run = 0u32;
    for &l in levels {
        if l & bit != 0 {
            run += 1;
        } else if run > 0 {
            out.push(run);
            run = 0;
        }
    }
    out
}

fn clock(measured: &[u8], replayed: &[u8], bit: u8, ideal: f64) -> ClockFigures {
    let m = rising(measured, bit);
    let r = rising(replayed, bit);
    let errors: Vec<i64> = m
        .iter()
        .zip(&r)
        .map(|(&a, &b)| a as i64 - b as i64)
        .collect();
    let w = widths(measured, bit);
    let periods: Vec<i64> = m.windows(2).map(|p| p[1] as i64 - p[0] as i64).collect();
    let ideal_error = m
        .iter()
        .enumerate()
        .map(|(i, &k)| (k as f64 - (m[0] as f64 + i as f64 * ideal)).abs())
        .fold(0.0, f64::max);
    ClockFigures {
        pulses: m.len(),
        error_max_ticks: errors.iter().map(|e| e.abs()).max().unwrap_or(0),
        jitter_ticks: errors.iter().max().unwrap_or(&0) - errors.iter().min().unwrap_or(&0),
        width_ticks: (
            w.iter().copied().min().unwrap_or(0),
            w.iter().copied().max().unwrap_or(0),
        ),
        period_ticks: (
            periods.iter().copied().min().unwrap_or(0),
            periods.iter().copied().max().unwrap_or(0),
        ),
        ideal_error_max_ticks: if m.is_empty() { 0.0 } else { ideal_error },
    }
}

/// The pattern's kind, as [`parse_pattern`] takes it: `"raster"`, `"lissajous"` or
/// `"spiral"`. A raster's lines run back and forth (serpentine): its odd lines' pixels are
/// numbered back along the line.
///
/// ```
/// use twinstack_link::scan_timing::{parse_pattern, pattern_kind};
/// assert_eq!(pattern_kind(&parse_pattern(" Raster:lines=8").unwrap()), "raster");
/// assert_eq!(pattern_kind(&parse_pattern("spiral:hz=200").unwrap()), "spiral");
/// ```
pub fn pattern_kind(pattern: &ScanPattern) -> &'static str {
    match pattern {
        ScanPattern::Raster(_) => "raster",
        ScanPattern::Lissajous(_) => "lissajous",
        ScanPattern::Spiral(_) => "spiral",
    }
}

/// The pattern in words.
pub fn describe(pattern: &ScanPattern) -> String {
    match pattern {
        ScanPattern::Raster(r) => format!(
            "raster {} lines × {} pixels, turnaround {} ticks, x {} ± {}, y {} ± {}",
            r.lines, r.pixels, r.turn_ticks, r.offset, r.amplitude, r.y_offset, r.y_amplitude
        ),
        ScanPattern::Lissajous(l) => format!(
            "Lissajous {}:{} at {} Hz, y phase {}°, x {} ± {}, y {} ± {}",
            l.x_cycles,
            l.y_cycles,
            l.frame_hz,
            l.y_phase_deg,
            l.offset,
            l.amplitude,
            l.y_offset,
            l.y_amplitude
        ),
        ScanPattern::Spiral(s) => format!(
            "spiral {} turns out and in at {} Hz, radius {}, centre ({}, {})",
            s.turns, s.turn_hz, s.amplitude, s.offset, s.y_offset
        ),
    }
}

/// Analyses a capture of `request` run at `rate_hz` with slew step `max_step` (Q2.30 per tick,
/// [`twinstack::sources::scan::slew_step`]) and pulses of `pulse_ticks`: `x` the captured setpoint
/// (Q1.15) and `triggers` the captured trigger levels, both from the scan's first tick.
pub fn analyse(
    request: &ScanRequest,
    rate_hz: f64,
    max_step: i32,
    pulse_ticks: u16,
    x: &[i16],
    triggers: &[i16],
) -> Result<(ScanFigures, Replay), AnalyseError> {
    if x.len() != triggers.len() {
        return Err(AnalyseError::Length);
    }
    let levels: Vec<u8> = triggers.iter().map(|&t| (t & 0b111) as u8).collect();
    let mut g = ScanGenerator::new(request, rate_hz, max_step, pulse_ticks)
        .map_err(AnalyseError::Refused)?;
    let Some(&c0) = rising(&levels, FRAME).first() else {
        return Err(AnalyseError::NoFrame(x.len()));
    };
    // The replay starts at the pattern's first point (no approach): its first sample is the
    // approach's one tick there.
    g.start(g.start_point().0);
    let mut outputs = TriggerOutputs::new(pulse_ticks);
    let mut host = Vec::new();
    let mut found: Option<usize> = None;
    for j in 0.. {
        let s = g.next_sample();
        let level = outputs.tick(s.events);
        host.push((s.x, g.y(), level));
        if found.is_none() && s.events & FRAME != 0 {
            found = Some(j);
        }
        if let Some(h0) = found {
            if j >= h0 + x.len() {
                break;
            }
        }
        if j > 4 * x.len() + 1_000_000 {
            break;
        }
    }
    let h0 = found.unwrap_or(0);
    // Capture tick k ↔ replay sample k − c0 + h0.
    let at = |k: usize| -> Option<&(i32, i32, u8)> {
        (k + h0).checked_sub(c0).and_then(|j| host.get(j))
    };
    let mut replay_levels = vec![0u8; x.len()];
    let mut replay: Replay = vec![None; x.len()];
    let (mut compared, mut mismatches, mut trig_mismatch) = (0, 0, 0);
    let one = SIGNAL_ONE as f64;
    for k in 0..x.len() {
        if let Some(&(hx, hy, hl)) = at(k) {
            if k + h0 < c0 {
                continue;
            }
            replay_levels[k] = hl;
            replay[k] = Some((hx as f64 / one, hy as f64 / one));
            compared += 1;
            if q1_15(hx) != x[k] {
                mismatches += 1;
            }
            if hl != levels[k] {
                trig_mismatch += 1;
            }
        }
    }
    // Before the alignment point the replay has no levels: take the capture's so that those
    // ticks do not count as errors (they are the approach: no pulses).
    let before = c0.saturating_sub(h0);
    replay_levels[..before].copy_from_slice(&levels[..before]);
    let line_ticks = g.line_ticks();
    let tpp = request.ticks_per_pixel;
    let (frame_ideal, centre) = match request.pattern {
        ScanPattern::Raster(r) => (line_ticks * r.lines as f64, r.offset),
        ScanPattern::Lissajous(l) => (rate_hz / l.frame_hz, l.offset),
        ScanPattern::Spiral(s) => (rate_hz / s.turn_hz * 2.0 * s.turns as f64, s.offset),
    };
    let pixel_ideal = match request.pattern {
        // Pixels restart at each trace: the ideal spacing holds within a line only.
        ScanPattern::Raster(_) => f64::NAN,
        _ => tpp as f64,
    };
    let mut pixel = clock(&levels, &replay_levels, PIXEL, pixel_ideal);
    if pixel_ideal.is_nan() {
        pixel.ideal_error_max_ticks = 0.0;
    }
    let line = clock(&levels, &replay_levels, LINE, line_ticks);
    let frame = clock(&levels, &replay_levels, FRAME, frame_ideal);
    // Turnaround → line pulse: the apex is the middle of the plateau of the largest |x − c|
    // within a quarter line of the pulse.
    let turnaround_to_line = match request.pattern {
        ScanPattern::Spiral(_) => None,
        _ => {
            let c = centre * 32768.0;
            let q = (line_ticks / 4.0).floor() as usize;
            let offsets: Vec<f64> = rising(&levels, LINE)
                .into_iter()
                .filter(|&p| p >= q && p + q < x.len())
                .map(|p| {
                    let window = p - q..=p + q;
                    let dev = |k: usize| (x[k] as f64 - c).abs();
                    let top = window.clone().map(dev).fold(0.0, f64::max);
                    let first = window.clone().find(|&k| dev(k) == top).unwrap_or(p);
                    let last = window.rev().find(|&k| dev(k) == top).unwrap_or(p);
                    p as f64 - (first + last) as f64 / 2.0
                })
                .collect();
            let expected = match request.pattern {
                ScanPattern::Raster(r) => (r.turn_ticks - r.turn_ticks / 2) as f64,
                _ => 0.0,
            };
            if offsets.is_empty() {
                None
            } else {
                Some((
                    offsets.iter().copied().fold(f64::MAX, f64::min),
                    offsets.iter().copied().fold(f64::MIN, f64::max),
                    expected,
                ))
            }
        }
    };
    Ok((
        ScanFigures {
            pattern: describe(&request.pattern),
            rate_hz,
            line_ticks,
            line_hz: rate_hz / line_ticks,
            pixel_ticks: tpp,
            pixel_hz: rate_hz / tpp as f64,
            pulse_ticks,
            captured_ticks: x.len(),
            first_frame_tick: c0,
            pixel,
            line,
            frame,
            turnaround_to_line,
            x_compared: compared,
            x_mismatches: mismatches,
            trigger_mismatches: trig_mismatch,
        },
        replay,
    ))
}

/// The figures as the table `twinstack scan` prints.
pub fn table(f: &ScanFigures) -> String {
    let mut out = String::new();
    let row = |out: &mut String, k: &str, v: String| out.push_str(&format!("{k:<28} {v}\n"));
    row(&mut out, "pattern", f.pattern.clone());
    row(
        &mut out,
        "line period",
        format!(
            "{:.3} ticks ({:.2} Hz at {} Hz); measured {}–{} ticks",
            f.line_ticks, f.line_hz, f.rate_hz, f.line.period_ticks.0, f.line.period_ticks.1
        ),
    );
    row(
        &mut out,
        "pixel clock",
        format!("every {} ticks ({:.1} Hz)", f.pixel_ticks, f.pixel_hz),
    );
    row(
        &mut out,
        "captured",
        format!(
            "{} ticks; first frame clock at tick {} (the approach)",
            f.captured_ticks, f.first_frame_tick
        ),
    );
    out.push_str(&format!(
        "{:<8} {:>7} {:>18} {:>14} {:>12} {:>20}\n",
        "clock", "pulses", "max |err| (ticks)", "jitter (ticks)", "width", "vs ideal period"
    ));
    for (name, c) in [("pixel", &f.pixel), ("line", &f.line), ("frame", &f.frame)] {
        out.push_str(&format!(
            "{:<8} {:>7} {:>18} {:>14} {:>12} {:>20}\n",
            name,
            c.pulses,
            c.error_max_ticks,
            c.jitter_ticks,
            format!("{}–{}", c.width_ticks.0, c.width_ticks.1),
            format!("≤ {:.3} ticks", c.ideal_error_max_ticks)
        ));
    }
    if let Some((lo, hi, want)) = f.turnaround_to_line {
        row(
            &mut out,
            "turnaround apex → line pulse",
            format!("{lo:.1}–{hi:.1} ticks (pattern: {want:.1})"),
        );
    }
    row(
        &mut out,
        "setpoint vs replay",
        format!("{} of {} ticks differ", f.x_mismatches, f.x_compared),
    );
    row(
        &mut out,
        "trigger levels vs replay",
        format!("{} ticks differ", f.trigger_mismatches),
    );
    out
}

/// A scan the board ran ([`run_scan`]): what it captured from the scan's start, and the
/// figures against the replay.
#[derive(Clone, Debug)]
pub struct ScanRun {
    /// The figures ([`analyse`]).
    pub figures: ScanFigures,
    /// The replay aligned on the capture ([`Replay`]).
    pub replay: Replay,
    /// The captured setpoint, Q1.15, one a tick from the scan's start.
    pub x: Vec<i16>,
    /// The captured trigger levels ([`PIXEL`], [`LINE`], [`FRAME`] bits), one a tick.
    pub triggers: Vec<i16>,
    /// The capture in physical units (`t` from the scan's start; `setpoint` in the output
    /// unit of the settings in force; `triggers` as bits).
    pub recording: crate::capture::Recording,
    /// Ticks the approach and the frames take (an estimate from above: the approach taken at
    /// the full stroke).
    pub wanted_ticks: f64,
}

impl ScanRun {
    /// Whether the capture ended before the scan did (the board's buffer is shorter than the
    /// approach and the frames): the rest is not analysed.
    pub fn truncated(&self) -> bool {
        (self.x.len() as f64) < self.wanted_ticks
    }
}

/// Why a scan could not be run and analysed.
#[derive(Debug, thiserror::Error)]
pub enum ScanRunError {
    /// The scan is refused: the library's check, before anything was sent.
    #[error("refused: {0}; nothing was sent")]
    Refused(twinstack::refusal::Refusal),
    /// The link, or the board's refusal.
    #[error(transparent)]
    Link(#[from] crate::client::LinkError),
    /// The capture did not complete in time.
    #[error(transparent)]
    Capture(#[from] crate::capture::CaptureError),
    /// The capture could not be put in physical units.
    #[error(transparent)]
    Convert(#[from] crate::capture::ConvertError),
    /// The capture could not be analysed.
    #[error(transparent)]
    Analyse(#[from] AnalyseError),
}

/// Runs `request` on the board behind `client` with trigger pulses of `pulse_ticks` and reads
/// it back, as `twinstack scan` does: the request checked first by the library (a refusal names
/// the field, nothing sent), the trigger outputs set, the setpoint and the trigger levels
/// captured from the scan's start for the approach and the frames (as far as the board's
/// buffer goes), the scan started, the capture awaited for at most `budget` and analysed
/// against the library's replay. With `start_on` an edge (not [`twinstack::sources::scan::TriggerEdge::Off`]), the
/// trigger input is armed on it and the scan waits for it (a camera's frame starts the scan),
/// whatever `request.on_trigger` says; with `Off`, it starts at once. A scan of endless frames
/// (`frames` 0) is stopped once the capture is read.
pub fn run_scan<T: crate::Transport>(
    client: &mut crate::client::Client<T>,
    mut request: ScanRequest,
    pulse_ticks: u16,
    start_on: twinstack::sources::scan::TriggerEdge,
    budget: std::time::Duration,
) -> Result<ScanRun, ScanRunError> {
    use twinstack::protocol::messages::{
        CaptureRequest, Request, StreamControl, Trigger, TriggerConfig, TriggerEdge,
    };
    use twinstack::services::recorder::Channel;
    request.on_trigger = start_on != TriggerEdge::Off;
    let settings = client.read_params()?;
    let rate = client.status()?.tick_rate_hz as f64;
    let max_step = twinstack::sources::scan::slew_step(
        settings.drive.slew_rate,
        settings.drive.min_voltage,
        settings.drive.max_voltage,
        rate,
    );
    let generator =
        ScanGenerator::new(&request, rate, max_step, pulse_ticks).map_err(ScanRunError::Refused)?;
    client.expect_ack(&Request::Trigger(TriggerConfig {
        pulse_ticks,
        input: start_on,
        start_stream: false,
    }))?;
    // Enough frames for the approach (at most the full stroke at a quarter of the slew step)
    // and the scan, as far as the board's buffer goes.
    let approach = (2.0 * 4.0 * SIGNAL_ONE as f64 / max_step.max(1) as f64)
        .ceil()
        .min(1e7);
    let frame_ticks = match request.pattern {
        ScanPattern::Raster(r) => generator.line_ticks() * r.lines as f64,
        ScanPattern::Lissajous(l) => rate / l.frame_hz,
        ScanPattern::Spiral(s) => rate / s.turn_hz * 2.0 * s.turns as f64,
    };
    let wanted_ticks =
        approach + frame_ticks * request.frames.max(1) as f64 + 2.0 * generator.line_ticks();
    let capacity = client.capture_status()?.capacity;
    let samples = (wanted_ticks.ceil().min(u32::MAX as f64) as u32)
        .min(capacity / 2)
        .max(1);
    client.arm_capture(CaptureRequest {
        signals: Channel::Setpoint.bit() | Channel::Triggers.bit(),
        samples,
        pre_trigger: 0,
        trigger: Trigger::ScanStart,
        decimation: 1,
    })?;
    client.expect_ack(&Request::Scan(request))?;
    let (status, window) = crate::capture::wait_and_read(client, budget, |_, _| {})?;
    if request.frames == 0 {
        client.stream(StreamControl::Stop)?;
    }
    let recording = crate::capture::convert(&status, &settings, &window)?;
    let x: Vec<i16> = window.iter().step_by(2).copied().collect();
    let triggers: Vec<i16> = window.iter().skip(1).step_by(2).copied().collect();
    let (figures, replay) = analyse(&request, rate, max_step, pulse_ticks, &x, &triggers)?;
    Ok(ScanRun {
        figures,
        replay,
        x,
        triggers,
        recording,
        wanted_ticks,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_patterns_are_named() {
        assert!(matches!(
            parse_pattern("zigzag:lines=3"),
            Err(PatternError::Kind(_))
        ));
        assert!(matches!(
            parse_pattern("raster:rows=3"),
            Err(PatternError::Key { key, .. }) if key == "rows"
        ));
        assert!(matches!(
            parse_pattern("spiral:hz=fast"),
            Err(PatternError::Value { .. })
        ));
        assert!(matches!(
            parse_pattern("lissajous:x=5,y=4,hz=10"),
            Ok(ScanPattern::Lissajous(l)) if l.x_cycles == 5 && l.y_cycles == 4
        ));
    }

    #[test]
    fn a_capture_shifted_or_corrupted_shows_in_the_figures() {
        // The replay itself, as a board would capture it after a 7-tick approach: no error.
        let request = ScanRequest {
            pattern: parse_pattern("raster:lines=4,pixels=20,turn=10").unwrap(),
            ticks_per_pixel: 3,
            frames: 1,
            on_trigger: false,
        };
        let step = 1 << 26;
        let mut g = ScanGenerator::new(&request, 50_000.0, step, 1).unwrap();
        let mut out = TriggerOutputs::new(1);
        g.start(-(1 << 29));
        let (mut x, mut t) = (Vec::new(), Vec::new());
        for _ in 0..400 {
            let s = g.next_sample();
            x.push(q1_15(s.x));
            t.push(out.tick(s.events) as i16);
        }
        let (f, _) = analyse(&request, 50_000.0, step, 1, &x, &t).unwrap();
        assert_eq!((f.x_mismatches, f.trigger_mismatches), (0, 0));
        assert_eq!(f.line.pulses, 4);
        assert_eq!(f.line.period_ticks, (70, 70));
        assert_eq!((f.line.error_max_ticks, f.line.jitter_ticks), (0, 0));
        assert_eq!(f.pixel.pulses, 80);
        let (lo, hi, want) = f.turnaround_to_line.unwrap();
        assert_eq!((lo, hi, want), (5.0, 5.0, 5.0));
        // One line pulse a tick late: the error and the jitter say so.
        let late = t.iter().rposition(|&v| v & LINE as i16 != 0).unwrap();
        t[late] &= !(LINE as i16);
        t[late + 1] |= LINE as i16;
        let (f, _) = analyse(&request, 50_000.0, step, 1, &x, &t).unwrap();
        assert_eq!((f.line.error_max_ticks, f.line.jitter_ticks), (1, 1));
        assert!(f.trigger_mismatches >= 2);
    }
}
