//! Where the useful part of a record starts: the first sample of motion, the start-up
//! glitch (a drive that steps at that sample and makes the stage ring) to skip, and — for a
//! record that does not start at rest — the warm-up before the model's state is known.
//!
//! A model run from rest on a record that starts in the middle of its motion starts in the
//! wrong state (a P–I operator's memory, a Duhem output). Once the drive has been to both
//! its extremes, every play operator up to the drive's amplitude has been wiped, so rows
//! from there on are fitted against the right state.

/// A drive change above this fraction of the record's drive span counts as motion.
pub const MOTION_FRACTION: f64 = 0.01;
/// A first move larger than this fraction of the drive span is a step (a start-up glitch).
pub const STEP_FRACTION: f64 = 0.05;
/// After a step, this fraction of the moving samples (at least [`MIN_SETTLE_SAMPLES`]) is
/// left out of the fit while the stage settles.
pub const SETTLE_FRACTION: f64 = 0.01;
/// Fewest samples skipped after a start-up step.
pub const MIN_SETTLE_SAMPLES: usize = 5;
/// A record whose drive holds still for at least this many samples before moving starts at
/// rest (its initial state is the relaxed one).
pub const REST_SAMPLES: usize = 10;

/// The start of motion in `u` and what to skip after it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MotionStart {
    /// First sample whose drive differs from the first one by more than
    /// [`MOTION_FRACTION`] of the span.
    pub first_moving: usize,
    /// Whether the drive stepped there (a start-up glitch).
    pub stepped: bool,
    /// Whether the record starts at rest ([`REST_SAMPLES`] still samples before motion).
    pub started_at_rest: bool,
    /// First sample to fit: `first_moving`; after the settling samples if it stepped; once
    /// the drive has reached both its extremes if the record did not start at rest.
    pub first_fitted: usize,
}

/// Finds where the drive `u` starts to move; `None` if it never does.
pub fn find(u: &[f64]) -> Option<MotionStart> {
    let (lo, hi) = u
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    let span = hi - lo;
    let u0 = *u.first()?;
    if span.is_nan() || span <= 0.0 {
        return None;
    }
    let first_moving = u
        .iter()
        .position(|&v| (v - u0).abs() > MOTION_FRACTION * span)?;
    let stepped =
        first_moving > 0 && (u[first_moving] - u[first_moving - 1]).abs() > STEP_FRACTION * span;
    let settle = if stepped {
        (((u.len() - first_moving) as f64 * SETTLE_FRACTION) as usize).max(MIN_SETTLE_SAMPLES)
    } else {
        0
    };
    let started_at_rest = first_moving >= REST_SAMPLES;
    let mut first_fitted = first_moving + settle;
    if !started_at_rest {
        first_fitted = first_fitted.max(both_extremes_reached(u));
    }
    Some(MotionStart {
        first_moving,
        stepped,
        started_at_rest,
        first_fitted: first_fitted.min(u.len() - 1),
    })
}

/// First sample by which the drive has come within [`MOTION_FRACTION`] of the span to both
/// its minimum and its maximum over `u`: from there on every play operator up to the drive's
/// amplitude has been wiped, whatever the initial state (0 if `u` is empty).
pub fn both_extremes_reached(u: &[f64]) -> usize {
    let (lo, hi) = u
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    let near = |v: f64, target: f64| (v - target).abs() <= MOTION_FRACTION * (hi - lo);
    let reached_lo = u.iter().position(|&v| near(v, lo)).unwrap_or(0);
    let reached_hi = u.iter().position(|&v| near(v, hi)).unwrap_or(0);
    reached_lo.max(reached_hi)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_record_at_rest_then_a_smooth_ramp_starts_where_the_ramp_leaves_the_rest_value() {
        let mut u = vec![0.0; 50];
        u.extend((0..100).map(|k| k as f64));
        let m = find(&u).unwrap();
        assert_eq!(m.first_moving, 50 + 1); // 1 % of the span 99 is 0.99: exceeded at 1
        assert!(!m.stepped);
        assert!(m.started_at_rest);
        assert_eq!(m.first_fitted, m.first_moving);
    }

    #[test]
    fn a_record_that_starts_moving_is_fitted_once_the_drive_has_seen_both_extremes() {
        // Starts mid-way up a sine: the maximum comes after ~¼ period, the minimum after ¾.
        let u: Vec<f64> = (0..400).map(|k| (k as f64 * 0.05).sin()).collect();
        let m = find(&u).unwrap();
        assert!(!m.started_at_rest);
        let lowest = (0..u.len()).find(|&k| u[k] < -0.99).unwrap();
        assert!(
            m.first_fitted >= lowest - 1 && m.first_fitted <= lowest,
            "{m:?}"
        );
    }

    #[test]
    fn a_drive_that_steps_at_the_start_is_a_glitch_and_the_settling_is_skipped() {
        let mut u = vec![0.0; 20];
        u.extend((0..1000).map(|k| -80.0 + 0.1 * k as f64));
        let m = find(&u).unwrap();
        assert_eq!(m.first_moving, 20);
        assert!(m.stepped);
        assert_eq!(m.first_fitted, 20 + 10);
    }

    #[test]
    fn both_extremes_are_reached_where_the_drive_first_comes_near_the_later_one() {
        let u = [0.0, 1.0, 2.0, 1.0, 0.0, -1.0, -2.0, -1.0, 0.0];
        assert_eq!(both_extremes_reached(&u), 6);
        assert_eq!(both_extremes_reached(&[]), 0);
    }

    #[test]
    fn a_constant_drive_has_no_motion() {
        assert_eq!(find(&[1.0; 30]), None);
    }
}
