//! Where the carriage is and how fast it goes, from the noisy, once-per-coarse-tick estimate
//! `ĉ = linear encoder − piezo sensor`: an α–β tracker, with the coarse command's change of
//! velocity fed forward (the stepper follows its steps, so that change is known a tick early).
//!
//! ```text
//! predicted = c + v;   e = ĉ − predicted;   c = predicted + α·e;   v += β·e + Δv_command
//! ```
//!
//! `β = α² / (2 − α)` (the critically damped choice). One `α` while the coarse stage moves
//! (fast: it follows the stepper's uneven motion), a smaller one while it rests, with the
//! velocity held at zero (the sensors' noise is then all there is to filter). Units: `c` pm, `v` pm per coarse tick
//! (`i64`); `α`, `β` Q8.24 (`i64`, in (0, 1]). The error is saturated to ±2^38 pm before the
//! products, which then fit `i64`.
//!
//! The fine setpoint for the end of the coming period is the residual against `c + v`: a
//! carriage moving at constant speed is met where it will be, not where it was, and the sensor
//! noise in `ĉ` reaches the piezo reduced by the filter.

/// Fractional bits of `α`, `β`.
const FRAC_BITS: u32 = 24;
const ERROR_LIMIT_PM: i64 = 1 << 38;

/// The α–β tracker's gains and state.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CarriageTracker {
    /// Gains while the coarse stage moves, Q8.24.
    moving: (i64, i64),
    /// Gains while it rests, Q8.24.
    resting: (i64, i64),
    /// Carriage position, pm.
    position: i64,
    /// Carriage velocity, pm per coarse tick.
    velocity: i64,
}

fn times_q24(x: i64, q: i64) -> i64 {
    (x * q + (1 << (FRAC_BITS - 1))) >> FRAC_BITS
}

impl CarriageTracker {
    /// A tracker with gain `moving` while the coarse stage moves and `resting` while it rests
    /// (Q8.24, each clamped to (0, 1]), at rest at `position` (pm).
    pub fn new(moving: i64, resting: i64, position: i64) -> Self {
        let gains = |alpha: i64| {
            let one = 1i64 << FRAC_BITS;
            let alpha = alpha.clamp(1, one);
            (alpha, alpha * alpha / (2 * one - alpha))
        };
        Self {
            moving: gains(moving),
            resting: gains(resting),
            position,
            velocity: 0,
        }
    }

    /// At rest at `position` (pm), with the same gains (no division: the coarse task's
    /// restart calls it).
    pub fn reset(&mut self, position: i64) {
        self.position = position;
        self.velocity = 0;
    }

    /// Gain `α` (Q8.24) from a value in (0, 1], or `None`.
    pub fn alpha_from_f64(alpha: f64) -> Option<i64> {
        (alpha > 0.0 && alpha <= 1.0)
            .then(|| libm::round(alpha * (1i64 << FRAC_BITS) as f64) as i64)
    }

    /// One coarse tick: the measured carriage `measured` (pm), the change of the coarse
    /// command's velocity this tick (pm per tick), and whether the coarse stage rests (the
    /// slower gain then filters the noise of a carriage that stands still). Returns the
    /// carriage predicted for the end of the coming period, pm.
    pub fn update(&mut self, measured: i64, command_velocity_change: i64, resting: bool) -> i64 {
        let (alpha, beta) = if resting {
            // A carriage whose command stands still stands still: no velocity to extrapolate
            // (what the moving gains left in it is noise), only a position to smooth.
            self.velocity = 0;
            (self.resting.0, 0)
        } else {
            self.moving
        };
        let predicted = self.position.saturating_add(self.velocity);
        let e = measured
            .saturating_sub(predicted)
            .clamp(-ERROR_LIMIT_PM, ERROR_LIMIT_PM); // constant bounds: no panic path
        self.position = predicted.saturating_add(times_q24(e, alpha));
        self.velocity = self
            .velocity
            .saturating_add(times_q24(e, beta))
            .saturating_add(command_velocity_change);
        self.position.saturating_add(self.velocity)
    }

    /// Filtered carriage position, pm.
    pub fn position(&self) -> i64 {
        self.position
    }

    /// Filtered carriage velocity, pm per coarse tick.
    pub fn velocity(&self) -> i64 {
        self.velocity
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_constant_speed_is_tracked_without_lag_and_noise_is_reduced() {
        let alpha = CarriageTracker::alpha_from_f64(0.3).unwrap();
        let mut t = CarriageTracker::new(alpha, alpha, 0);
        let mut seed = 7u32;
        let mut sum_sq_in = 0f64;
        let mut sum_sq_out = 0f64;
        for k in 1..=5000i64 {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let noise = (seed >> 20) as i64 - 2048; // ±2048 pm, uniform
            let truth = 10_000 * k;
            let predicted = t.update(truth + noise, 0, false);
            if k > 500 {
                sum_sq_in += (noise * noise) as f64;
                let e = (predicted - (truth + 10_000)) as f64;
                sum_sq_out += e * e;
            }
        }
        assert!(sum_sq_out < 0.6 * sum_sq_in, "{sum_sq_out} vs {sum_sq_in}");
        assert!((t.velocity() - 10_000).abs() < 200);
        assert!(CarriageTracker::alpha_from_f64(0.0).is_none());
        // At rest the velocity is dropped: a constant reading is met without drift.
        for _ in 0..200 {
            t.update(1_000, 0, true);
        }
        assert_eq!((t.velocity(), (t.position() - 1_000).abs() < 10), (0, true));
        assert!(CarriageTracker::alpha_from_f64(f64::NAN).is_none());
    }
}
