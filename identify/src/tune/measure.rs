//! Measuring the frequency response over the board link: stepped sines from the board's own
//! waveform generator in bypass (the drive is the setpoint, range onto range), each captured
//! by the board's recorder (left stack and sensor, from the waveform's start), and a
//! per-frequency lock-in on the host.
//!
//! **Lock-in.** After the settling time, drive and sensor are each fitted by least squares
//! with `a + b cos ωt + c sin ωt` at the frequency the generator realises (its phase step is
//! `round(f / f_s · 2³²)`), so the window need not hold whole cycles and the offset and slow
//! drift do not leak in. The response is the ratio of the two phasors, in normalised units
//! (sensor over its output half span, per left-stack volts over the input half span: what the
//! feedback's gains multiply). Both come from the same ticks, so the ratio holds every delay
//! between the DAC write and the sensor reading the tick sees.
//!
//! **Sweep.** A coarse logarithmic sweep from [`SweepOptions::lowest_hz`] to 0.47 f_s, then
//! [`SweepOptions::refine_points`] more, evenly spaced within ±25 % of the largest response
//! found (the resonance). Near the resonance the amplitude is lowered so the sensor stays
//! within a third of its range: a point whose sensor swing is larger is measured again at an
//! amplitude scaled down to a sixth of the range.
//!
//! **Stopping.** The caller's `progress` hears of each point measured and, while the sweep
//! waits on the board for a capture, of each wait (every [`POLL`]); answering
//! [`ControlFlow::Break`] stops the sweep there, the generator stopped, with
//! [`MeasureError::Stopped`].

use super::loop_model::C64;
use std::f64::consts::PI;
use std::ops::ControlFlow;
use std::time::Duration;
use twinstack::config::settings::Settings;
use twinstack::protocol::messages::{
    CaptureRequest, CaptureStatus, StreamControl, Trigger, WaveShape, Waveform,
};
use twinstack::services::recorder::Channel;
use twinstack_link::capture::{self, CaptureError, ConvertError};
use twinstack_link::client::{Client, LinkError};
use twinstack_link::setpoint_file::q1_15;
use twinstack_link::Transport;

/// How the sweep runs.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct SweepOptions {
    /// Lowest frequency, Hz.
    pub lowest_hz: f64,
    /// Frequencies of the coarse sweep.
    pub points: usize,
    /// Frequencies added about the resonance.
    pub refine_points: usize,
    /// Amplitude of the setpoint sine, normalised (fraction of the half range).
    pub amplitude: f64,
    /// Time left out after each start (the transient), s.
    pub settle_s: f64,
    /// Least measured time per frequency, s.
    pub window_s: f64,
    /// Least whole cycles measured per frequency.
    pub cycles: f64,
}

impl Default for SweepOptions {
    /// 200 Hz up, 24 + 12 frequencies, 3 % of the half range, 3 ms settling, at least 4 ms
    /// or 10 cycles measured.
    fn default() -> Self {
        Self {
            lowest_hz: 200.0,
            points: 24,
            refine_points: 12,
            amplitude: 0.03,
            settle_s: 0.003,
            window_s: 0.004,
            cycles: 10.0,
        }
    }
}

impl SweepOptions {
    /// Checks the options, naming the first bad one.
    pub fn check(&self) -> Result<(), MeasureError> {
        let bad = |field: &'static str, rule: &'static str, value: f64| {
            Err(MeasureError::Option { field, rule, value })
        };
        if !(self.lowest_hz.is_finite() && self.lowest_hz > 0.0) {
            return bad("lowest_hz", "a positive number of Hz", self.lowest_hz);
        }
        if self.points < 4 {
            return bad("points", "at least 4", self.points as f64);
        }
        if !(self.amplitude > 0.0 && self.amplitude <= 0.5) {
            return bad("amplitude", "in (0, 0.5]", self.amplitude);
        }
        for (field, v) in [
            ("settle_s", self.settle_s),
            ("window_s", self.window_s),
            ("cycles", self.cycles),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return bad(field, "positive", v);
            }
        }
        Ok(())
    }
}

/// The response at one frequency.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrequencyPoint {
    /// The frequency the generator realised, Hz.
    pub frequency_hz: f64,
    /// Sensor over drive, normalised.
    pub response: C64,
    /// The drive's amplitude, left-stack volts.
    pub drive_volts: f64,
    /// The sensor's amplitude, output unit.
    pub sensor_amplitude: f64,
}

impl FrequencyPoint {
    /// The response's magnitude, dB.
    pub fn magnitude_db(&self) -> f64 {
        20.0 * self.response.abs().log10()
    }

    /// The response's phase, degrees.
    pub fn phase_deg(&self) -> f64 {
        self.response.arg().to_degrees()
    }
}

/// What [`sweep`] tells its caller's `progress` as it goes; the caller answers
/// [`ControlFlow::Break`] to stop the sweep.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SweepEvent<'a> {
    /// A frequency was measured (in the order measured: the coarse sweep, then the points
    /// about the resonance).
    Point(&'a FrequencyPoint),
    /// The sweep is waiting on the board for the capture at `frequency_hz` (every [`POLL`]).
    Waiting {
        /// The frequency being measured, Hz.
        frequency_hz: f64,
    },
}

/// How often the sweep asks the board whether a capture is done, and so how often `progress`
/// hears [`SweepEvent::Waiting`].
pub const POLL: Duration = capture::POLL;

/// Why a measurement stopped.
#[derive(Debug, thiserror::Error)]
pub enum MeasureError {
    /// An option is out of range.
    #[error("tune option {field} = {value}: must be {rule}")]
    Option {
        /// The option.
        field: &'static str,
        /// What it must be.
        rule: &'static str,
        /// What it was.
        value: f64,
    },
    /// The link failed or the board refused a request.
    #[error("{step}: {source}")]
    Link {
        /// What was being done.
        step: &'static str,
        /// The cause.
        source: LinkError,
    },
    /// A capture failed.
    #[error("capture at {frequency_hz:.0} Hz: {source}")]
    Capture {
        /// Where.
        frequency_hz: f64,
        /// The cause.
        source: CaptureError,
    },
    /// A capture could not be converted.
    #[error("capture at {frequency_hz:.0} Hz: {source}")]
    Convert {
        /// Where.
        frequency_hz: f64,
        /// The cause.
        source: ConvertError,
    },
    /// The board has no sensor calibration.
    #[error("the board has no sensor (its settings carry no sensor calibration): tune measures the stage through its sensor")]
    NoSensor,
    /// The drive or the sensor did not move at a frequency.
    #[error("at {frequency_hz:.0} Hz the {what} did not move (amplitude {amplitude:.3e}): is the stage powered and the sensor connected?")]
    Flat {
        /// Where.
        frequency_hz: f64,
        /// `drive` or `sensor`.
        what: &'static str,
        /// What was measured.
        amplitude: f64,
    },
    /// The caller's `progress` stopped the sweep.
    #[error("the sweep was stopped at {frequency_hz:.0} Hz with {measured} frequencies measured; the generator is stopped")]
    Stopped {
        /// The frequency being measured (or last measured), Hz.
        frequency_hz: f64,
        /// Frequencies measured before the stop.
        measured: usize,
    },
}

fn link(step: &'static str) -> impl Fn(LinkError) -> MeasureError {
    move |source| MeasureError::Link { step, source }
}

/// The least-squares phasor of `x` at `w` rad/s over times `t`: `x ≈ a + Re(P e^{jwt})`.
pub fn phasor(t: &[f64], x: &[f64], w: f64) -> C64 {
    // Normal equations of [1, cos, sin].
    let mut m = [[0.0f64; 3]; 3];
    let mut r = [0.0f64; 3];
    for (&ti, &xi) in t.iter().zip(x) {
        let v = [1.0, (w * ti).cos(), (w * ti).sin()];
        for i in 0..3 {
            r[i] += v[i] * xi;
            for j in 0..3 {
                m[i][j] += v[i] * v[j];
            }
        }
    }
    let [_, b, c] = solve3(m, r);
    C64::new(b, -c)
}

#[allow(clippy::needless_range_loop)] // Gauss–Jordan on a 3×3, indexed
fn solve3(mut m: [[f64; 3]; 3], mut r: [f64; 3]) -> [f64; 3] {
    for col in 0..3 {
        let pivot = (col..3)
            .max_by(|&a, &b| m[a][col].abs().total_cmp(&m[b][col].abs()))
            .unwrap_or(col);
        m.swap(col, pivot);
        r.swap(col, pivot);
        let p = m[col][col];
        if p.abs() < 1e-300 {
            return [0.0; 3];
        }
        for row in 0..3 {
            if row != col {
                let k = m[row][col] / p;
                for j in 0..3 {
                    m[row][j] -= k * m[col][j];
                }
                r[row] -= k * r[col];
            }
        }
    }
    [r[0] / m[0][0], r[1] / m[1][1], r[2] / m[2][2]]
}

/// The frequency the board's generator realises for `frequency_hz` at `rate`: the request in
/// whole millihertz, the phase step rounded to 2⁻³² of a cycle.
pub fn realised(frequency_hz: f64, rate: f64) -> (u32, f64) {
    let mhz = (frequency_hz * 1000.0).round().max(1.0) as u32;
    let step = (mhz as f64 / 1000.0 / rate * 4_294_967_296.0).round();
    (mhz, step / 4_294_967_296.0 * rate)
}

/// The frequencies of the coarse sweep at `rate`.
pub fn coarse_frequencies(options: &SweepOptions, rate: f64) -> Vec<f64> {
    let top = 0.47 * rate;
    let n = options.points;
    (0..n)
        .map(|i| options.lowest_hz * (top / options.lowest_hz).powf(i as f64 / (n - 1) as f64))
        .collect()
}

/// Waits for the recorder's capture (for at most `budget`) and reads its window
/// ([`capture::wait_and_read_or_stop`]), asking `progress` at each poll
/// ([`MeasureError::Stopped`] on a stop, `measured` frequencies before it). Capture errors
/// are at `frequency_hz`.
fn wait_and_read<T: Transport>(
    client: &mut Client<T>,
    budget: Duration,
    frequency_hz: f64,
    measured: usize,
    progress: &mut impl FnMut(SweepEvent<'_>) -> ControlFlow<()>,
) -> Result<(CaptureStatus, Vec<i16>), MeasureError> {
    capture::wait_and_read_or_stop(client, budget, |what, _| match what {
        "captured" => progress(SweepEvent::Waiting { frequency_hz }),
        _ => ControlFlow::Continue(()),
    })
    .map_err(|source| match source {
        CaptureError::Stopped { .. } => MeasureError::Stopped {
            frequency_hz,
            measured,
        },
        source => MeasureError::Capture {
            frequency_hz,
            source,
        },
    })
}

/// Measures the response at one frequency (see the module doc), `measured` frequencies
/// before it; `progress` can stop it while it waits for the capture. Leaves the generator
/// stopped.
#[allow(clippy::too_many_arguments)] // the sweep's state, passed down
fn one<T: Transport>(
    client: &mut Client<T>,
    board: &Settings,
    options: &SweepOptions,
    rate: f64,
    capacity: u32,
    frequency_hz: f64,
    amplitude: f64,
    measured: usize,
    progress: &mut impl FnMut(SweepEvent<'_>) -> ControlFlow<()>,
) -> Result<FrequencyPoint, MeasureError> {
    let (mhz, f) = realised(frequency_hz, rate);
    let w = 2.0 * PI * f;
    let window = options.window_s.max(options.cycles / f);
    let ticks = ((options.settle_s + window) * rate).ceil() as u64;
    let max_frames = (capacity / 2).max(16) as u64;
    // At least 16 samples a cycle; few enough frames for the recorder.
    let by_rate = (rate / (16.0 * f)).floor().max(1.0) as u64;
    let decimation = by_rate
        .max(ticks.div_ceil(max_frames))
        .clamp(1, u16::MAX as u64);
    let frames = ticks.div_ceil(decimation).clamp(1, max_frames);
    client
        .arm_capture(CaptureRequest {
            signals: Channel::Left.bit() | Channel::Sensor.bit(),
            samples: frames as u32,
            pre_trigger: 0,
            trigger: Trigger::WaveformStart,
            decimation: decimation as u16,
        })
        .map_err(link("arming the recorder"))?;
    client
        .waveform(Waveform {
            shape: WaveShape::Sine,
            offset: 0,
            amplitude: q1_15(amplitude),
            frequency_mhz: mhz,
            decay: None,
        })
        .map_err(link("starting the sine"))?;
    let budget = Duration::from_secs_f64(2.0 * ticks as f64 / rate + 5.0);
    let read = wait_and_read(client, budget, f, measured, progress);
    // The sine is stopped whatever became of the capture (a stop included).
    let stopped = client.stream(StreamControl::Stop);
    let (cap, window_values) = read?;
    stopped.map_err(link("stopping the sine"))?;
    let rec =
        capture::convert(&cap, board, &window_values).map_err(|source| MeasureError::Convert {
            frequency_hz: f,
            source,
        })?;
    let (Some(left), Some(sensor)) = (rec.column(Channel::Left), rec.column(Channel::Sensor))
    else {
        return Err(MeasureError::Flat {
            frequency_hz: f,
            what: "recorder (no left stack or sensor column)",
            amplitude: 0.0,
        });
    };
    let t0 = rec.t.first().copied().unwrap_or(0.0);
    let from = rec
        .t
        .iter()
        .position(|&t| t - t0 >= options.settle_s)
        .unwrap_or(rec.t.len());
    let t: Vec<f64> = rec.t[from..].iter().map(|t| t - t0).collect();
    let u = phasor(&t, &left.values[from..], w);
    let x = phasor(&t, &sensor.values[from..], w);
    let r = &board.ranges;
    let (u_amp, x_amp) = (u.abs(), x.abs());
    if u_amp.is_nan() || u_amp <= 1e-6 * r.input_half_span() {
        return Err(MeasureError::Flat {
            frequency_hz: f,
            what: "drive",
            amplitude: u_amp,
        });
    }
    let response = x
        .scale(1.0 / r.output_half_span())
        .over(u.scale(1.0 / r.input_half_span()));
    Ok(FrequencyPoint {
        frequency_hz: f,
        response,
        drive_volts: u_amp,
        sensor_amplitude: x_amp,
    })
}

/// Runs the sweep on the board behind `client` (its settings `board`, in bypass), telling
/// `progress` of each point measured and of each wait on the board ([`SweepEvent`]). Leaves
/// the generator stopped, also when `progress` answers [`ControlFlow::Break`]: then
/// [`MeasureError::Stopped`], within one [`POLL`] of the answer.
///
/// Returns the points in order of frequency and the board's tick rate, Hz.
pub fn sweep<T: Transport>(
    client: &mut Client<T>,
    board: &Settings,
    options: &SweepOptions,
    mut progress: impl FnMut(SweepEvent<'_>) -> ControlFlow<()>,
) -> Result<(Vec<FrequencyPoint>, u32), MeasureError> {
    options.check()?;
    if board.sensor.is_none() {
        return Err(MeasureError::NoSensor);
    }
    let facts = client
        .capture_status()
        .map_err(link("the recorder's capacity"))?;
    let rate = facts.tick_rate_hz.max(1) as f64;
    let half = board.ranges.output_half_span();
    let mut measure = |f: f64, measured: usize| -> Result<FrequencyPoint, MeasureError> {
        let mut a = options.amplitude;
        let mut at = |a: f64| {
            one(
                client,
                board,
                options,
                rate,
                facts.capacity,
                f,
                a,
                measured,
                &mut progress,
            )
        };
        let mut p = at(a)?;
        for _ in 0..3 {
            if p.sensor_amplitude <= half / 3.0 {
                break;
            }
            a *= (half / 6.0) / p.sensor_amplitude;
            p = at(a.max(1e-4))?;
        }
        if p.sensor_amplitude < 1e-7 * half {
            return Err(MeasureError::Flat {
                frequency_hz: f,
                what: "sensor",
                amplitude: p.sensor_amplitude,
            });
        }
        if progress(SweepEvent::Point(&p)).is_break() {
            return Err(MeasureError::Stopped {
                frequency_hz: p.frequency_hz,
                measured: measured + 1,
            });
        }
        Ok(p)
    };
    let mut points = Vec::new();
    for f in coarse_frequencies(options, rate) {
        points.push(measure(f, points.len())?);
    }
    for f in refined_frequencies(options, &points, rate) {
        points.push(measure(f, points.len())?);
    }
    points.sort_by(|a, b| a.frequency_hz.total_cmp(&b.frequency_hz));
    Ok((points, facts.tick_rate_hz))
}

/// The frequencies the sweep adds after the coarse `points` at `rate`:
/// [`SweepOptions::refine_points`] evenly spaced within ±25 % of the largest response (at
/// most `0.47 · rate`).
pub fn refined_frequencies(
    options: &SweepOptions,
    points: &[FrequencyPoint],
    rate: f64,
) -> Vec<f64> {
    let peak = points
        .iter()
        .max_by(|a, b| a.response.abs().total_cmp(&b.response.abs()))
        .map_or(options.lowest_hz, |p| p.frequency_hz);
    let (lo, hi) = (peak / 1.25, (peak * 1.25).min(0.47 * rate));
    let n = options.refine_points;
    (0..n)
        .map(|i| lo + (hi - lo) * (i as f64 + 0.5) / n as f64)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_lock_in_recovers_amplitude_and_phase_over_a_partial_cycle() {
        let w = 2.0 * PI * 1234.5;
        let t: Vec<f64> = (0..300).map(|k| k as f64 * 1e-5).collect();
        let x: Vec<f64> = t.iter().map(|&t| 0.7 + 2.0 * (w * t + 0.6).cos()).collect();
        let p = phasor(&t, &x, w);
        assert!(
            (p.abs() - 2.0).abs() < 1e-9 && (p.arg() - 0.6).abs() < 1e-9,
            "{p:?}"
        );
    }
}
