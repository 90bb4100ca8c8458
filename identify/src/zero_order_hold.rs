//! Exact zero-order-hold discretisation of a linear time-invariant system.
//!
//! For `ẋ = A x + B u` with `u` held constant over a period `dt` (what a DAC does), the state
//! after one period is exactly
//!
//! `x_{k+1} = Φ x_k + Γ u_k`,  `Φ = e^{A dt}`,  `Γ = Ψ B`,  `Ψ = ∫_0^dt e^{A τ} dτ`.
//!
//! No integration error, whatever the ratio of `dt` to the plant's time constants: the 21.8 kHz
//! stage resonance comes out right at a 50 kHz control rate, and the stiff stack–stage
//! contact modes (MHz) cost nothing per step.
//!
//! `Φ` and `Ψ` are computed once, off the hot path, by scaling and squaring: a Taylor series
//! over a sub-step `h = dt / 2^s` short enough that `‖A h‖ ≤ 1/2`, then `s` doublings
//! `Ψ_{2h} = Ψ_h + Φ_h Ψ_h`, `Φ_{2h} = Φ_h²` (the sub-steps are exact compositions, not an
//! approximation). Before that, `A` is balanced by a diagonal similarity with power-of-two
//! factors: the mechanical models mix positions (µm) and velocities (m/s) whose blocks differ by
//! ten orders of magnitude, and balancing keeps the number of doublings (and their rounding)
//! small.

/// `x_{k+1} = Φ x_k + Γ u_k` for `N` states and `M` held inputs.
#[derive(Clone, Debug, PartialEq)]
pub struct ZeroOrderHold<const N: usize, const M: usize> {
    phi: [[f64; N]; N],
    gamma: [[f64; M]; N],
}

/// Terms of the Taylor series over one sub-step (`‖A h‖ ≤ 1/2`: the remainder is below
/// `0.5^19 / 19!`, far under `f64` rounding).
const TAYLOR_TERMS: usize = 18;
/// Balancing sweeps (each rescales every state once; a handful suffices for these sizes).
const BALANCING_SWEEPS: usize = 8;

impl<const N: usize, const M: usize> ZeroOrderHold<N, M> {
    /// The exact discretisation of `ẋ = A x + B u` over `dt` seconds (`dt > 0`, finite `A`, `B`).
    pub fn new(a: &[[f64; N]; N], b: &[[f64; M]; N], dt: f64) -> Self {
        let (ab, scale) = balance(a);
        let norm = ab
            .iter()
            .map(|row| row.iter().map(|v| v.abs()).sum::<f64>())
            .fold(0.0, f64::max)
            * dt;
        let mut doublings = 0u32;
        while norm / f64::powi(2.0, doublings as i32) > 0.5 && doublings < 200 {
            doublings += 1;
        }
        let h = dt / f64::powi(2.0, doublings as i32);

        // Taylor series of Φ_h = Σ (A h)^k / k! and Ψ_h = h Σ (A h)^k / (k+1)!.
        let ah = scaled(&ab, h);
        let mut term = identity::<N>();
        let mut phi = identity::<N>();
        let mut psi = scaled(&identity::<N>(), h);
        for k in 1..=TAYLOR_TERMS {
            term = scaled(&mul(&term, &ah), 1.0 / k as f64);
            add_assign(&mut phi, &term, 1.0);
            add_assign(&mut psi, &term, h / (k + 1) as f64);
        }
        for _ in 0..doublings {
            let phi_psi = mul(&phi, &psi);
            add_assign(&mut psi, &phi_psi, 1.0);
            phi = mul(&phi, &phi);
        }

        // Undo the balancing: e^{A t} = S⁻¹ e^{Ab t} S, with Ab = S A S⁻¹.
        for i in 0..N {
            for j in 0..N {
                phi[i][j] *= scale[j] / scale[i];
                psi[i][j] *= scale[j] / scale[i];
            }
        }
        let mut gamma = [[0.0; M]; N];
        for i in 0..N {
            for k in 0..M {
                gamma[i][k] = (0..N).map(|j| psi[i][j] * b[j][k]).sum();
            }
        }
        Self { phi, gamma }
    }

    /// Advances `x` by one period with the inputs `u` held.
    #[inline]
    pub fn step(&self, x: &mut [f64; N], u: &[f64; M]) {
        let mut next = [0.0; N];
        for (i, out) in next.iter_mut().enumerate() {
            let mut acc = 0.0;
            for (p, xj) in self.phi[i].iter().zip(x.iter()) {
                acc += p * xj;
            }
            for (g, uk) in self.gamma[i].iter().zip(u.iter()) {
                acc += g * uk;
            }
            *out = acc;
        }
        *x = next;
    }

    /// The state transition matrix `Φ = e^{A dt}`.
    pub fn phi(&self) -> &[[f64; N]; N] {
        &self.phi
    }

    /// The input matrix `Γ = ∫_0^dt e^{A τ} dτ · B`.
    pub fn gamma(&self) -> &[[f64; M]; N] {
        &self.gamma
    }
}

/// Diagonal balancing `Ab = S A S⁻¹` (power-of-two `S`, so exact): returns `Ab` and `S`.
fn balance<const N: usize>(a: &[[f64; N]; N]) -> ([[f64; N]; N], [f64; N]) {
    let mut ab = *a;
    let mut scale = [1.0; N];
    for _ in 0..BALANCING_SWEEPS {
        for i in 0..N {
            let row: f64 = (0..N).filter(|&j| j != i).map(|j| ab[i][j].abs()).sum();
            let col: f64 = (0..N).filter(|&j| j != i).map(|j| ab[j][i].abs()).sum();
            if row == 0.0 || col == 0.0 {
                continue;
            }
            // s_i = sqrt(col/row), rounded to a power of two: row·s_i = col/s_i.
            let s = f64::powi(2.0, (0.5 * (col / row).log2()).round() as i32);
            if s == 1.0 {
                continue;
            }
            ab[i].iter_mut().for_each(|v| *v *= s);
            ab.iter_mut().for_each(|row| row[i] /= s);
            scale[i] *= s;
        }
    }
    (ab, scale)
}

fn identity<const N: usize>() -> [[f64; N]; N] {
    let mut m = [[0.0; N]; N];
    for (i, row) in m.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    m
}

fn scaled<const N: usize>(m: &[[f64; N]; N], k: f64) -> [[f64; N]; N] {
    let mut out = *m;
    out.iter_mut().flatten().for_each(|v| *v *= k);
    out
}

fn add_assign<const N: usize>(m: &mut [[f64; N]; N], other: &[[f64; N]; N], k: f64) {
    for (row, other_row) in m.iter_mut().zip(other.iter()) {
        for (v, o) in row.iter_mut().zip(other_row.iter()) {
            *v += k * o;
        }
    }
}

fn mul<const N: usize>(a: &[[f64; N]; N], b: &[[f64; N]; N]) -> [[f64; N]; N] {
    let mut out = [[0.0; N]; N];
    for i in 0..N {
        for k in 0..N {
            let aik = a[i][k];
            for j in 0..N {
                out[i][j] += aik * b[k][j];
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_order_lag_matches_its_closed_form() {
        let (lambda, b, dt) = (3.0e4, 2.0, 2.0e-5);
        let zoh = ZeroOrderHold::<1, 1>::new(&[[-lambda]], &[[b]], dt);
        let e = (-lambda * dt).exp();
        assert!((zoh.phi()[0][0] - e).abs() < 1e-14);
        assert!((zoh.gamma()[0][0] - b * (1.0 - e) / lambda).abs() < 1e-18);
    }

    /// An undamped oscillator far above the sample rate (≈ 190 rad per period, as the stiff
    /// stack–stage contact modes are) is still a pure rotation: `Φ = [[cos, sin/ω], [−ω sin, cos]]`.
    #[test]
    fn stiff_oscillator_is_exact_far_above_the_sample_rate() {
        let (omega, dt): (f64, f64) = (9.5e6, 2.0e-5);
        let zoh =
            ZeroOrderHold::<2, 1>::new(&[[0.0, 1.0], [-omega * omega, 0.0]], &[[0.0], [1.0]], dt);
        let (s, c) = (omega * dt).sin_cos();
        let phi = zoh.phi();
        assert!((phi[0][0] - c).abs() < 1e-9, "{} vs {c}", phi[0][0]);
        assert!((phi[0][1] * omega - s).abs() < 1e-9);
        assert!((phi[1][0] / omega + s).abs() < 1e-9);
        assert!((phi[1][1] - c).abs() < 1e-9);
        // Γ for a unit force: position gain (1 − cos)/ω², velocity gain sin/ω.
        let g = zoh.gamma();
        assert!((g[0][0] * omega * omega - (1.0 - c)).abs() < 1e-9);
        assert!((g[1][0] * omega - s).abs() < 1e-9);
    }

    #[test]
    fn composing_two_half_periods_equals_one_period() {
        let a = [[0.0, 1.0], [-1.2e10, -4.7e3]];
        let b = [[0.0], [5.0e3]];
        let full = ZeroOrderHold::<2, 1>::new(&a, &b, 2.0e-5);
        let half = ZeroOrderHold::<2, 1>::new(&a, &b, 1.0e-5);
        let (mut x1, mut x2) = ([1.0e-6, 0.3], [1.0e-6, 0.3]);
        full.step(&mut x1, &[2.0]);
        half.step(&mut x2, &[2.0]);
        half.step(&mut x2, &[2.0]);
        assert!((x1[0] - x2[0]).abs() < 1e-12 * x1[0].abs().max(1e-9));
        assert!((x1[1] - x2[1]).abs() < 1e-9 * x1[1].abs().max(1e-3));
    }
}
