//! The desired displacement records a tracking test plays: a triangle, nested minor loops and
//! a three-frequency multisine over a span ([`trajectories`]), each played after an unscored
//! lead-in from rest ([`Trajectory::with_lead_in`]). The laboratory stage's tracking study
//! and one-command calibration's before/after check both score a model on them.

use std::f64::consts::TAU;

/// Trajectories stay this fraction of the measured output span inside it, each side.
pub const TRAJECTORY_MARGIN: f64 = 0.1;

/// A desired displacement record.
#[derive(Clone, Debug, PartialEq)]
pub struct Trajectory {
    /// Its name in the table.
    pub name: String,
    /// Time, seconds.
    pub t: Vec<f64>,
    /// Desired reading, µm.
    pub x: Vec<f64>,
}

/// Length of the unscored lead-in before each trajectory, seconds.
pub const LEAD_IN_S: f64 = 0.1;

impl Trajectory {
    /// The record actually played: a [`LEAD_IN_S`] ramp from `x_rest` (the reading at rest at
    /// 0 V, where the stage starts) to the trajectory's first value, then the trajectory.
    /// Returns `(t, x, first)`, `first` being the index of the trajectory's first sample.
    ///
    /// The lead-in is what a user does (move to the start, then run), and it starts the
    /// stage and the compensator in the states the model was identified in: the excitation
    /// also started from rest at 0 V, and the model is run from rest at its first value.
    pub fn with_lead_in(&self, x_rest: f64, sample_rate_hz: f64) -> (Vec<f64>, Vec<f64>, usize) {
        let first = (LEAD_IN_S * sample_rate_hz).round() as usize;
        let x0 = self.x.first().copied().unwrap_or(x_rest);
        let mut x: Vec<f64> = (0..first)
            .map(|k| x_rest + (x0 - x_rest) * k as f64 / first as f64)
            .collect();
        x.extend_from_slice(&self.x);
        let t = (0..x.len()).map(|k| k as f64 / sample_rate_hz).collect();
        (t, x, first)
    }
}

/// Piecewise-linear through `points` (fractions) at `speed` fractions per second.
fn piecewise(points: &[f64], speed: f64, rate: f64) -> Vec<f64> {
    let mut out = Vec::new();
    for w in points.windows(2) {
        let steps = ((w[1] - w[0]).abs() / speed * rate).round().max(1.0) as usize;
        out.extend((0..steps).map(|k| w[0] + (w[1] - w[0]) * k as f64 / steps as f64));
    }
    out.push(points.last().copied().unwrap_or(0.0));
    out
}

/// Sweep speed of the triangle and the minor loops, fractions of the span per second.
pub const SWEEP_SPEED: f64 = 4.0;

/// The three trajectories over `lo … hi` µm (their full span) at `sample_rate_hz`, each
/// starting at `lo`:
/// * `triangle`: 2 Hz, 4 cycles (2 s);
/// * `minor loops`: reversals at 1, 0.2, 0.8, 0.35, 0.65, 0.45, 0.55, then out to 0.3, 0.9
///   and back to 0, at [`SWEEP_SPEED`] (≈ 1.4 s);
/// * `multisine`: `lo + span (0.5 − 0.25 cos 2π·1t − 0.15 cos 2π·3t − 0.1 cos 2π·7t)`, 2 s.
pub fn trajectories(lo: f64, hi: f64, sample_rate_hz: f64) -> [Trajectory; 3] {
    let span = hi - lo;
    let make = |name: &str, frac: Vec<f64>| Trajectory {
        name: name.to_string(),
        t: (0..frac.len()).map(|k| k as f64 / sample_rate_hz).collect(),
        x: frac.iter().map(|f| lo + span * f).collect(),
    };
    let triangle = piecewise(
        &[0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0],
        SWEEP_SPEED,
        sample_rate_hz,
    );
    let loops = piecewise(
        &[0.0, 1.0, 0.2, 0.8, 0.35, 0.65, 0.45, 0.55, 0.3, 0.9, 0.0],
        SWEEP_SPEED,
        sample_rate_hz,
    );
    let n = (2.0 * sample_rate_hz).round() as usize;
    let multisine = (0..n)
        .map(|k| {
            let t = k as f64 / sample_rate_hz;
            0.5 - 0.25 * (TAU * t).cos()
                - 0.15 * (TAU * 3.0 * t).cos()
                - 0.1 * (TAU * 7.0 * t).cos()
        })
        .collect();
    [
        make("triangle", triangle),
        make("minor loops", loops),
        make("multisine", multisine),
    ]
}

/// The fewest samples a cycle of [`triangle`] may have.
pub const MIN_SAMPLES_PER_CYCLE: f64 = 20.0;

/// The slowest triangle [`triangle`] makes, Hz: its four cycles last 40 s.
pub const MIN_TRIANGLE_HZ: f64 = 0.1;

/// Whether [`triangle`] makes a triangle of `hz` at `sample_rate_hz`: a frequency of at
/// least [`MIN_TRIANGLE_HZ`] with at least [`MIN_SAMPLES_PER_CYCLE`] samples a cycle.
pub fn triangle_fits(hz: f64, sample_rate_hz: f64) -> bool {
    hz.is_finite() && hz >= MIN_TRIANGLE_HZ && sample_rate_hz / hz >= MIN_SAMPLES_PER_CYCLE
}

/// A triangle over `lo … hi` µm (its full span) at `hz` cycles per second, sampled at
/// `sample_rate_hz`, starting at `lo`: whole cycles for at least a second and at least
/// four (so a 1 Hz triangle lasts 4 s, a 200 Hz one 1 s). Named `triangle HZ Hz`. `None` for
/// a frequency below [`MIN_TRIANGLE_HZ`] or not finite, or one that leaves a cycle fewer than
/// [`MIN_SAMPLES_PER_CYCLE`] samples.
///
/// ```
/// use twinstack_identify::trajectory::triangle;
/// let t = triangle(10.0, 70.0, 200.0, 10_000.0).unwrap();
/// assert_eq!(t.name, "triangle 200 Hz");
/// assert_eq!(t.x.len(), 10_001);
/// assert!(triangle(10.0, 70.0, 600.0, 10_000.0).is_none());
/// assert!(triangle(10.0, 70.0, 1e-300, 10_000.0).is_none());
/// ```
pub fn triangle(lo: f64, hi: f64, hz: f64, sample_rate_hz: f64) -> Option<Trajectory> {
    if !triangle_fits(hz, sample_rate_hz) {
        return None;
    }
    let cycles = (hz.ceil() as usize).max(4);
    let per_cycle = sample_rate_hz / hz;
    let n = (cycles as f64 * per_cycle).round() as usize;
    let span = hi - lo;
    let x = (0..=n)
        .map(|k| {
            // The phase within the cycle, 0 … 1: up over the first half, down over the second.
            let phase = (k as f64 / per_cycle).fract();
            lo + span * (1.0 - (2.0 * phase - 1.0).abs())
        })
        .collect();
    Some(Trajectory {
        name: format!("triangle {hz} Hz"),
        t: (0..=n).map(|k| k as f64 / sample_rate_hz).collect(),
        x,
    })
}

/// Calibration's test record: two triangle cycles then the nested minor loops of [`trajectories`] over
/// `lo … hi`, at `rate` setpoints per second.
pub fn test_trajectory((lo, hi): (f64, f64), rate: f64) -> Trajectory {
    let [triangle, loops, _] = trajectories(lo, hi, rate);
    // The triangle's first two of four cycles end at `lo`, where the loops start.
    let mut x: Vec<f64> = triangle.x[..triangle.x.len() / 2].to_vec();
    x.extend_from_slice(&loops.x);
    Trajectory {
        name: "triangle + minor loops".into(),
        t: (0..x.len()).map(|k| k as f64 / rate).collect(),
        x,
    }
}

/// The record streamed for `trajectory`: from `x_rest` (where the output holds) up to the
/// trajectory's top, down to its bottom (its start), then the trajectory, at
/// [`SWEEP_SPEED`]; returns it and the index of the trajectory's first setpoint.
///
/// The sweep over the whole range before the scored part wipes the hysteresis memory of the
/// stage and of the model alike (both end on the same descending branch), so the scored part
/// starts with the compensator's state matching the stage's: a mode switch prepares the
/// compensator relaxed at the present drive, which the stage's branch need not be.
pub fn with_conditioning(trajectory: &Trajectory, x_rest: f64, rate: f64) -> (Vec<f64>, usize) {
    let (lo, hi) = trajectory
        .x
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    let start = trajectory.x.first().copied().unwrap_or(lo);
    let speed = SWEEP_SPEED * (hi - lo).max(f64::MIN_POSITIVE);
    let mut x = Vec::new();
    for (a, b) in [(x_rest, hi), (hi, start)] {
        let steps = ((b - a).abs() / speed * rate).round().max(1.0) as usize;
        x.extend((0..steps).map(|k| a + (b - a) * k as f64 / steps as f64));
    }
    let first = x.len();
    x.extend_from_slice(&trajectory.x);
    (x, first)
}
