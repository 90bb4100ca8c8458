//! Exponential relaxation in the input: the exact step of the Duhem and Bouc–Wen models, and the
//! one Newton step their compensators take on it.
//!
//! Both models relax a state toward a target at a rate `c` per unit of input travelled: on a
//! monotone stretch of input (direction `s`), `dh/du = s·(A/c·s − h)·c`, i.e. `h` moves toward
//! `h* = s·A/c` by the fraction
//!
//! `q = 1 − e^{−c·m}` of the way, `m = |Δu|`,
//!
//! and the input-proportional part moves by `φ = q/c` times the drive of the target. Taken
//! this way — integrated in the input, not stepped per sample — a model's output depends only
//! on the path of the input, not on how finely it is sampled: two samples of `m/2` give
//! `(1 − q(m/2))² = 1 − q(m)`, exactly one sample of `m`. This is what makes the models
//! rate-independent, as the physics they stand for is; an explicit step `f = c·|Δu|`
//! (Euler's) differs by `O(c·m)` per sample, and so by the sample rate.
//!
//! **Arithmetic.** `q` and `φ` are computed in `f32` from the step `m` (Q2.30) and the rate `c`
//! (the model's Q8.24 constant, converted once): for `x = c·m ≤ 1` by a polynomial of
//! `ψ(x) = (1 − e^{−x})/x` of degree 6 (`1 + x·R(x)`, `R` interpolating `(ψ − 1)/x` at the
//! Chebyshev nodes of `[0, 1]`: within 1.3·10⁻⁸ of `ψ`, below `2^-24`), `q = x·ψ`,
//! `φ = m·ψ` — no cancellation, so both keep `f32`'s relative precision however small the
//! step, which is what a sum over 10⁵ samples a second needs; for `x > 1`,
//! `e^{−x} = 2^{−n}·e^{−r}` (`r < ln 2` from the polynomial; `x ≥ 24`: `q = 1`). Each is
//! then rounded to nearest into a fixed-point fraction (`q` Q0.32, `φ` Q1.31) and the models
//! update their Q2.30 state with integer products, rounding once. Every `f32` operation is an
//! IEEE single-precision one (no fused multiply-add; a quotient is one `VDIV.F32` on the M4,
//! where an `i64` division would be a library call of a few hundred instructions), so the
//! host and the Cortex-M4's FPU compute the same bits (the golden vectors replay them).
//!
//! **Inverse.** A compensator wants the step `m ≥ 0` that moves its model's output by `R` in
//! direction `s`: with slope `k` of the output in the input and `D = s·(h* − h)` the state's
//! distance to its target that way, the output moves by `F(m) = k·m + D·q(c·m)`. `F` is
//! monotone where the model is invertible; its slope at `m = 0` is `g = k + c·D`. The linear
//! guess `m₀ = R/g` and one Newton step from it, `m₁ = m₀ − (F(m₀) − R)/F′(m₀)`, land within
//! `O((c·m₀)²)` of the exact step relative to `m₀` — far below a DAC code at any control rate —
//! and from the side `F`'s curvature sets (a concave `F` undershoots, a convex one
//! overshoots less than `m₀`), so the step never oscillates ([`RelaxationRate::solve`]).

use crate::fixed_point::GAIN_FRAC_BITS;

/// `2^-30`: a Q2.30 value times this is its real value (exact in `f32`).
pub const SIGNAL_TO_F32: f32 = 1.0 / (1u32 << 30) as f32;

/// `2^30`: a real value times this is its Q2.30 value.
const F32_TO_SIGNAL: f32 = (1u32 << 30) as f32;

/// `c·m` at and below which the polynomial gives `q` and `φ` directly.
pub const POLYNOMIAL_LIMIT: f32 = 1.0;

/// The largest step a compensator takes in one sample, in units of `1/c`: within the
/// polynomial's range ([`POLYNOMIAL_LIMIT`]) with room for the rounding, so that the
/// compensator's own model never takes the longer path of a large step on the tick.
pub const STEP_CAP: f32 = 0.99;

/// `c·m` at and above which `e^{−c·m}` (< 4·10⁻¹¹) is taken as 0.
const DECAYED: f32 = 24.0;

/// A relaxation rate `c` (per unit of normalised input) and its reciprocal, as `f32` bits (so
/// that a model holding one still compares with `Eq`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RelaxationRate {
    rate: u32,
    reciprocal: u32,
}

/// One step's relaxation: the fraction `q = 1 − e^{−c·m}` of the way to the target and
/// `φ = q/c`, in `f32`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Relaxed {
    /// `q ∈ [0, 1]`.
    pub q: f32,
    /// `φ = q/c ∈ [0, m]`, normalised input.
    pub phi: f32,
}

impl Relaxed {
    /// `q` as a Q0.32 fraction, rounded to nearest (`q = 1` saturates one LSB short).
    #[inline(always)]
    pub fn q_q32(&self) -> u32 {
        (self.q * 4_294_967_296.0 + 0.5) as u32
    }

    /// `φ` (< 2) as a Q1.31 value, rounded to nearest.
    #[inline(always)]
    pub fn phi_q31(&self) -> u32 {
        (self.phi * 2_147_483_648.0 + 0.5) as u32
    }
}

impl RelaxationRate {
    /// The rate `c` of a model's Q8.24 constant (at least one LSB: the callers floor it).
    ///
    /// ```
    /// use twinstack::models::relaxation::RelaxationRate;
    /// use twinstack::fixed_point::{gain_from_f64, signal_from_f64};
    /// let rate = RelaxationRate::from_gain(gain_from_f64(2.0));
    /// // Half the input span at c = 2: q = 1 − e^{−1}.
    /// let r = rate.relax(signal_from_f64(0.5) as u32);
    /// assert!((r.q - (1.0 - (-1.0f32).exp())).abs() < 1e-6);
    /// ```
    #[inline(never)] // configuration, off the tick path
    pub fn from_gain(c: i32) -> Self {
        let rate = c.max(1) as f32 / (1u32 << GAIN_FRAC_BITS) as f32;
        Self {
            rate: rate.to_bits(),
            reciprocal: (1.0 / rate).to_bits(),
        }
    }

    /// `c`.
    #[inline(always)]
    pub fn rate(&self) -> f32 {
        f32::from_bits(self.rate)
    }

    /// `1/c`.
    #[inline(always)]
    pub fn reciprocal(&self) -> f32 {
        f32::from_bits(self.reciprocal)
    }

    /// The relaxation over an input step of magnitude `m` (Q2.30, as the `u32` of
    /// `|Δu|`).
    #[inline(always)]
    pub fn relax(&self, m: u32) -> Relaxed {
        self.relax_normalised(m as f32 * SIGNAL_TO_F32)
    }

    /// The relaxation over an input step `m ≥ 0` (normalised, `f32`). One copy in flash
    /// (each model's step calls it, in every configuration that holds the model).
    #[inline(never)]
    pub fn relax_normalised(&self, m: f32) -> Relaxed {
        let x = self.rate() * m;
        if x <= POLYNOMIAL_LIMIT {
            let psi = psi(x);
            Relaxed {
                q: x * psi,
                phi: m * psi,
            }
        } else {
            let q = 1.0 - decay(x);
            Relaxed {
                q,
                phi: q * self.reciprocal(),
            }
        }
    }

    /// The input step (normalised) over which the state covers the fraction `w/(1 + w)` of
    /// its way to the target, `ln(1 + w)/c` (`w ≥ 0`): where a state `h` heading for a
    /// target `h*` of the other sign crosses zero, `w = −h/h*`.
    #[inline(always)]
    pub fn step_to_cover(&self, w: f32) -> f32 {
        ln_1p(w) * self.reciprocal()
    }

    /// The step `m ≥ 0` (Q2.30, at most `cap`) that moves a relaxing model's output by
    /// `target` (normalised, `≥ 0`) in its direction: `k` the output's slope in the input,
    /// `d` the state's distance to its target that way (`D` in the module doc), `floor` the
    /// least slope taken (the model may not be monotone far outside its range), `cap` the
    /// largest step (normalised). The linear guess and one Halley step (module doc).
    #[inline(always)]
    pub fn solve(&self, k: f32, d: f32, floor: f32, target: f32, cap: f32) -> i32 {
        to_signal(self.solve_normalised(k, d, floor, target, cap))
    }

    /// [`RelaxationRate::solve`], the step normalised in `f32`. One copy in flash (called
    /// by each compensator's step).
    ///
    /// `cap` is at most [`STEP_CAP`]`/c` (the compensators' caps are), so that `c·m₀` is
    /// within the polynomial's range: `q(m₀)` is the polynomial alone, with no call to the
    /// large steps' path (whose call would make this function save and restore eight FPU
    /// registers on every step). A larger `cap` still gives a step in `[0, cap]`, not an exact
    /// one.
    #[inline(never)]
    pub fn solve_normalised(&self, k: f32, d: f32, floor: f32, target: f32, cap: f32) -> f32 {
        let c = self.rate();
        let cd = c * d;
        let m0 = smaller(target / larger(k + cd, floor), cap);
        let x0 = c * m0;
        let q0 = x0 * psi(x0);
        // F(m₀) − R, F′(m₀) (floored) and F″(m₀) = −c²·D·e^{−c·m₀}.
        let miss = k * m0 + d * q0 - target;
        let decay = 1.0 - q0;
        let slope = larger(k + cd * decay, floor);
        let bend = -c * cd * decay;
        // Halley's step, m₀ − F·F′/(F′² − F·F″/2) (one quotient): Newton's with the
        // curvature's correction, kept from more than doubling it.
        let square = slope * slope;
        let denominator = larger(square - 0.5 * miss * bend, 0.5 * square);
        smaller(larger(m0 - miss * slope / denominator, 0.0), cap)
    }
}

/// The larger of `a` and `b` (`b` if either is NaN): one compare. `f32::max` is a library
/// call on the M4 (`fmaxf`, for its NaN rules), a few tens of cycles.
#[inline(always)]
pub fn larger(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// The smaller of `a` and `b` (`b` if either is NaN): one compare (see [`larger`]).
#[inline(always)]
pub fn smaller(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

/// `|x|`: the sign bit cleared.
#[inline(always)]
pub fn magnitude(x: f32) -> f32 {
    f32::from_bits(x.to_bits() & 0x7fff_ffff)
}

/// A normalised step (`0 ≤ m < 2`) as Q2.30, rounded to nearest (the conversion saturates,
/// and takes NaN to 0).
#[inline(always)]
pub fn to_signal(m: f32) -> i32 {
    (m * F32_TO_SIGNAL + 0.5) as i32
}

/// `ln(1 + w)` for `w ≥ 0` (`f32`): the exponent of `1 + w` times `ln 2`, and the mantissa
/// `f ∈ [√½, √2)` by the series `2·atanh((f − 1)/(f + 1))` to the 9th power (truncation
/// below `2^-30`). One quotient; no loop.
#[inline(never)] // a crossing of zero only: kept out of the common path
pub fn ln_1p(w: f32) -> f32 {
    let y = 1.0 + larger(w, 0.0);
    let bits = y.to_bits();
    let mut exponent = ((bits >> 23) & 0xff) as i32 - 127;
    let mut f = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000);
    if f > core::f32::consts::SQRT_2 {
        f *= 0.5;
        exponent += 1;
    }
    let z = (f - 1.0) / (f + 1.0);
    let z2 = z * z;
    let series =
        z * (2.0 + z2 * (2.0 / 3.0 + z2 * (2.0 / 5.0 + z2 * (2.0 / 7.0 + z2 * (2.0 / 9.0)))));
    exponent as f32 * core::f32::consts::LN_2 + series
}

/// `ψ(x) = (1 − e^{−x})/x` for `0 ≤ x ≤ 1`: `1 + x·R(x)`, `R` the polynomial of degree 5
/// that interpolates `(ψ(x) − 1)/x` at the six Chebyshev nodes of `[0, 1]` (near the minimax
/// one: within 1.3·10⁻⁸ of `ψ` relative, below `f32`'s `2^-24`; `ψ(0) = 1` and
/// `ψ′(0) = −½` exactly, so that the smallest steps keep their precision), Horner's rule.
/// Seven coefficients where the Taylor series needs eleven for the same bound: four
/// multiply-adds and four constant loads fewer each time a relaxing model steps (twice in its
/// compensator's tick). `psi_is_within_f32_of_the_exact_function` holds it.
#[inline(always)]
fn psi(x: f32) -> f32 {
    // `1`, `−½` and the interpolant's four higher coefficients, rounded to `f32`.
    const C: [f32; 7] = [
        1.0,
        -0.5,
        0.166_666_03,
        -0.041_659_254,
        0.008_301_171,
        -0.001_324_818,
        0.000_137_424_18,
    ];
    let mut p = C[6];
    p = p * x + C[5];
    p = p * x + C[4];
    p = p * x + C[3];
    p = p * x + C[2];
    p = p * x + C[1];
    p * x + C[0]
}

/// `e^{−x}` for `x > 1`: `2^{−n}·e^{−r}` with `x = n·ln 2 + r`, `0 ≤ r < ln 2` (so
/// `e^{−r} = 1 − r·ψ(r)` from [`psi`]), `2^{−n}` put into the exponent's bits; 0 from
/// [`DECAYED`] on. No loop.
#[inline(never)] // the large steps only: kept out of the common path
fn decay(x: f32) -> f32 {
    if x >= DECAYED || x.is_nan() {
        return 0.0;
    }
    // x < 24: n ≤ 34, so the exponent stays normal (2^-34 ≫ f32's least normal).
    let n = (x * core::f32::consts::LOG2_E) as i32;
    let r = x - n as f32 * core::f32::consts::LN_2;
    let scale = f32::from_bits(((127 - n) as u32) << 23);
    (1.0 - r * psi(r)) * scale
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed_point::{gain_from_f64, signal_from_f64};

    fn exact(c: f64, m: f64) -> (f64, f64) {
        let q = -libm::expm1(-c * m);
        (q, q / c)
    }

    #[test]
    fn q_and_phi_keep_their_relative_precision_from_tiny_steps_to_full_relaxation() {
        for c in [0.01, 0.3, 2.0, 17.0, 120.0] {
            let rate = RelaxationRate::from_gain(gain_from_f64(c));
            let c = rate.rate() as f64;
            for m in [1e-9, 3e-7, 1e-5, 1e-3, 0.02, 0.3, 0.9, 1.5, 1.999] {
                let code = signal_from_f64(m) as u32;
                let m = code as f64 / (1u64 << 30) as f64;
                let r = rate.relax(code);
                let (q, phi) = exact(c, m);
                let tolerance = 4e-7 + if c * m >= 24.0 { 1e-10 / q } else { 0.0 };
                assert!(
                    ((r.q as f64 - q) / q).abs() < tolerance,
                    "q at c = {c}, m = {m}: {} vs {q}",
                    r.q
                );
                assert!(
                    ((r.phi as f64 - phi) / phi).abs() < tolerance,
                    "φ at c = {c}, m = {m}: {} vs {phi}",
                    r.phi
                );
            }
        }
    }

    /// `ψ` in `f32` is within a few `f32` roundings of the exact function over its whole
    /// range (the polynomial's own error is 1.3·10⁻⁸), and exact at 0.
    #[test]
    fn psi_is_within_f32_of_the_exact_function() {
        assert_eq!(psi(0.0), 1.0);
        let mut worst = 0.0f64;
        for i in 0..=100_000 {
            let x = i as f32 / 100_000.0;
            let xd = x as f64;
            let exact = if xd == 0.0 {
                1.0
            } else {
                -libm::expm1(-xd) / xd
            };
            worst = worst.max(((psi(x) as f64 - exact) / exact).abs());
        }
        assert!(worst < 2e-7, "ψ within {worst:e} of the exact function");
    }

    #[test]
    fn a_step_taken_in_two_halves_relaxes_as_far_as_the_whole() {
        // (1 − q(m/2))² = 1 − q(m): the property that makes the models rate-independent.
        let rate = RelaxationRate::from_gain(gain_from_f64(5.0));
        for m in [1e-5, 1e-3, 0.05, 0.4, 1.2] {
            let half_code = signal_from_f64(m / 2.0) as u32;
            let whole = rate.relax(2 * half_code).q as f64;
            let half = rate.relax(half_code).q as f64;
            let halves = 1.0 - (1.0 - half) * (1.0 - half);
            assert!(((halves - whole) / whole).abs() < 1e-6, "m = {m}");
        }
    }

    #[test]
    fn ln_1p_is_the_logarithm_over_every_scale() {
        for w in [0.0, 1e-7, 3e-4, 0.2, 0.41, 0.5, 1.0, 1.72, 7.0, 1e3, 2.6e10] {
            let exact = libm::log1p(w);
            let got = ln_1p(w as f32) as f64;
            assert!(
                (got - exact).abs() <= 2e-7 * exact.max(1.0),
                "w = {w}: {got} vs {exact}"
            );
        }
    }

    #[test]
    fn the_fixed_point_fractions_round_to_nearest() {
        let r = Relaxed { q: 0.25, phi: 1.5 };
        assert_eq!(r.q_q32(), 1 << 30);
        assert_eq!(r.phi_q31(), 3 << 30);
        let full = Relaxed { q: 1.0, phi: 0.0 };
        assert_eq!(full.q_q32(), u32::MAX);
        // 1.4 LSB of Q0.32 rounds to 1, 1.6 to 2.
        let lsb = 1.0 / 4_294_967_296.0f32;
        assert_eq!(
            Relaxed {
                q: 1.4 * lsb,
                phi: 0.0
            }
            .q_q32(),
            1
        );
        assert_eq!(
            Relaxed {
                q: 1.6 * lsb,
                phi: 0.0
            }
            .q_q32(),
            2
        );
    }

    #[test]
    fn the_halley_step_lands_on_the_target() {
        let rate = RelaxationRate::from_gain(gain_from_f64(4.0));
        let c = rate.rate() as f64;
        let k = 0.5;
        // The compensators' cap: the largest step within the polynomial's range.
        let cap = STEP_CAP * rate.reciprocal();
        // d > 0: F concave; d < 0: convex; 0: linear. The largest target needs c·m ≈ 0.9.
        for d in [0.08, -0.05, 0.0] {
            for target in [1e-6, 1e-4, 1e-3, 0.01, 0.08] {
                let m = rate.solve(k as f32, d as f32, 0.01, target as f32, cap) as f64
                    / (1u64 << 30) as f64;
                assert!(m < cap as f64, "d = {d}, target = {target}: within the cap");
                let reached = k * m + d * exact(c, m).0;
                let miss = (reached - target) / target;
                // The step's rounding to Q2.30 (half an LSB times the slope), f32's, and the
                // Halley step's own miss, of the order of (c·m)³.
                let rounding = (k + c * d.abs()) * 0.5 / (1u64 << 30) as f64 / target;
                let x = c * m;
                let tolerance = 2e-6 + rounding + 1e-3 * x * x * x;
                assert!(miss.abs() < tolerance, "d = {d}, target = {target}: {miss}");
            }
        }
    }

    /// A cap beyond the polynomial's range (no compensator passes one) still gives a step in
    /// `[0, cap]`, whatever the polynomial makes of `c·m₀` out there.
    #[test]
    fn a_cap_beyond_the_polynomial_range_gives_a_bounded_step() {
        let rate = RelaxationRate::from_gain(gain_from_f64(4.0));
        for target in [0.05, 0.5, 3.0, 1e6] {
            for d in [0.08, -0.05] {
                let m = rate.solve_normalised(0.5, d, 0.01, target, 1.9);
                assert!((0.0..=1.9).contains(&m), "d = {d}, target = {target}: {m}");
            }
        }
    }
}
