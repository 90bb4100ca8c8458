//! The setpoint split: the low-frequency, large part of the setpoint, which the coarse stage
//! follows. The piezo takes the rest.
//!
//! A critically damped second-order low-pass *with* a zero, `Y/R = (2ωs + ω²)/(s + ω)²`:
//! it follows a ramp with no steady-state lag (a constant-velocity move stays inside the
//! piezo's stroke however fast it is), passes what is slower than `ω` and leaves what is faster
//! to the piezo. Per coarse tick `T` (forward Euler, `ωT ≤ 0.5`):
//!
//! ```text
//! ŷ = y + v;   e = r − ŷ;   v += (ωT)²·e;   y = ŷ + 2ωT·e
//! ```
//!
//! Units: `r`, `y` in picometres (`i64`), `v` in picometres per tick (`i64`); the coefficients
//! `(ωT)²` and `2ωT` in **Q8.24** (`i64`, ≤ 1.0 by validation). The error is saturated to
//! ±2^38 pm (0.27 m) before the products, so `e · coefficient < 2^62` never overflows.

/// Coefficients of the split filter for one bandwidth and coarse rate.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SplitCoefficients {
    /// `(ωT)²`, Q8.24; 0 with `gain = 0` means "no filter" (the coarse stage takes all of it).
    pub velocity_gain: i64,
    /// `2ωT`, Q8.24.
    pub position_gain: i64,
}

/// Fractional bits of the filter's coefficients.
pub const COEFFICIENT_FRAC_BITS: u32 = 24;
/// The filter's error is saturated to this magnitude, pm.
const ERROR_LIMIT_PM: i64 = 1 << 38;

impl SplitCoefficients {
    /// Coefficients for bandwidth `hz` at `coarse_rate_hz`, or `None` when `ωT` would exceed
    /// 0.5 (the discrete filter would no longer resemble the continuous one) or is not a finite
    /// positive number. `hz = 0` gives the pass-through.
    pub fn new(hz: f64, coarse_rate_hz: f64) -> Option<Self> {
        if hz == 0.0 {
            return Some(Self::pass_through());
        }
        let wt = 2.0 * core::f64::consts::PI * hz / coarse_rate_hz;
        if !(wt > 0.0 && wt <= 0.5 && coarse_rate_hz.is_finite()) {
            return None;
        }
        let one = (1i64 << COEFFICIENT_FRAC_BITS) as f64;
        Some(Self {
            velocity_gain: libm::round(wt * wt * one) as i64,
            position_gain: libm::round(2.0 * wt * one) as i64,
        })
    }

    /// No filter: the output is the input.
    pub fn pass_through() -> Self {
        Self {
            velocity_gain: 0,
            position_gain: 0,
        }
    }
}

/// The split filter's state.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SplitFilter {
    coefficients: SplitCoefficients,
    /// Output, pm.
    y: i64,
    /// Output velocity, pm per tick.
    v: i64,
}

fn times_q24(x: i64, q: i64) -> i64 {
    // Rounded to nearest; |x| < 2^38 and q ≤ 2^24, so the product fits.
    (x * q + (1 << (COEFFICIENT_FRAC_BITS - 1))) >> COEFFICIENT_FRAC_BITS
}

impl SplitFilter {
    /// At rest on `position` (pm).
    pub fn new(coefficients: SplitCoefficients, position: i64) -> Self {
        Self {
            coefficients,
            y: position,
            v: 0,
        }
    }

    /// One coarse tick with input `r` (pm); returns the low-frequency part, pm.
    pub fn step(&mut self, r: i64) -> i64 {
        let c = self.coefficients;
        if c.position_gain == 0 {
            self.y = r;
            self.v = 0;
            return r;
        }
        // Predict with the present velocity, then correct on the error of the prediction (so
        // a ramp is followed with neither lag nor lead).
        let predicted = self.y.saturating_add(self.v);
        let e = r
            .saturating_sub(predicted)
            .clamp(-ERROR_LIMIT_PM, ERROR_LIMIT_PM); // constant bounds: no panic path
        self.v = self.v.saturating_add(times_q24(e, c.velocity_gain));
        self.y = predicted.saturating_add(times_q24(e, c.position_gain));
        self.y
    }

    /// Passes `r` (pm) through unfiltered for this tick, keeping the filter's state consistent
    /// with it (velocity = this tick's change), so filtering can resume without a jump.
    pub fn track(&mut self, r: i64) -> i64 {
        self.v = r.saturating_sub(self.y);
        self.y = r;
        r
    }

    /// Output, pm.
    pub fn output(&self) -> i64 {
        self.y
    }

    /// Restarts at rest on `position`.
    pub fn reset_to(&mut self, position: i64) {
        self.y = position;
        self.v = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn follows_a_ramp_without_steady_state_lag() {
        let mut f = SplitFilter::new(SplitCoefficients::new(10.0, 1000.0).unwrap(), 0);
        let mut r = 0;
        for _ in 0..2000 {
            r += 10_000_000; // 10 mm/s
            f.step(r);
        }
        assert!((f.output() - r).abs() < 1000, "lag {} pm", r - f.output());
    }

    #[test]
    fn passes_slow_and_removes_fast_content() {
        // Gain at f against the continuous |(2jωf/ω... )|: check 1 Hz passes, 200 Hz is cut.
        let c = SplitCoefficients::new(10.0, 1000.0).unwrap();
        let amplitude = |hz: f64| {
            let mut f = SplitFilter::new(c, 0);
            let mut peak = 0f64;
            for k in 0..20_000 {
                let t = k as f64 / 1000.0;
                let r = (1e9 * libm::sin(2.0 * core::f64::consts::PI * hz * t)) as i64;
                let y = f.step(r);
                if k > 10_000 {
                    peak = peak.max((y as f64).abs());
                }
            }
            peak / 1e9
        };
        assert!((amplitude(1.0) - 1.0).abs() < 0.03);
        assert!(amplitude(200.0) < 0.15);
    }

    #[test]
    fn bandwidth_out_of_range_is_refused_and_zero_passes_through() {
        assert!(SplitCoefficients::new(100.0, 1000.0).is_none());
        assert!(SplitCoefficients::new(f64::NAN, 1000.0).is_none());
        assert!(SplitCoefficients::new(-1.0, 1000.0).is_none());
        let mut f = SplitFilter::new(SplitCoefficients::new(0.0, 1000.0).unwrap(), 5);
        assert_eq!(f.step(123_456), 123_456);
    }
}
