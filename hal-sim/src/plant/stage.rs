//! Stage and stack parameters: the paper's identified figures, and the physical constants of
//! the electromechanical model (see the book, docs/src/reference/physics.md) derived from them.
//!
//! ## What the paper gives
//! Small-signal fits `G(s) = a0 / (1 + 2ζ s/ωn + (s/ωn)²)`, drive volts → stage µm:
//!
//! | configuration | `a0` (µm/V) | `ζ` | `ωn` (rad/s) |
//! |---|---|---|---|
//! | unidirectional (input `u_l`) | 0.43 | 0.022 | 1.08e5 |
//! | differential (input `v`, `u_l,r = ū ± v`) | 0.534 | 0.017 | 1.37e5 |
//!
//! and `K_I + Ks = 31.17 N/µm`, `Mp + Ms = 2.68 g`, `b = 12.72 N·s/m`.
//!
//! ## Derivation (`K_0 → ∞` models of the book's docs/src/reference/physics.md)
//! *Unidirectional*: `(Ms + Mp) ẍ + b ẋ + (K_I + Ks) x = T u_l`, so
//! `ωn = √(31.17e6 / 2.68e-3) = 1.0785e5` rad/s and `ζ = b / (2√(K M)) = 0.0220`: both agree with
//! the fit, and `T = a0 (K_I + Ks) = 0.43e-6 · 31.17e6 = 13.40 N/V`.
//!
//! *Differential*: `(Ms + 2Mp) ẍ + b ẋ + (2K_I + Ks) x = T (u_l − u_r) = 2T v`, so with
//! `M₂ = Ms + 2Mp`, `K₂ = 2K_I + Ks`: `ωn² = K₂/M₂`, `ζ = b/(2 ωn M₂)`, `a0 = 2T/K₂ = 2T/(ωn² M₂)`.
//! Two unknowns (`K_I`, `Mp`) face three figures, and the figures disagree: at a given `ωn`
//! both `ζ` and `a0` scale as `1/M₂`, so their ratio `a0/ζ = 4T/(ωn b)` is fixed by the other
//! data; the paper's ratio is 2.1 % higher. We keep `ωn` exact (the resonance the control rate
//! must resolve) and split the 2.1 % evenly in the log between `a0` and `ζ`:
//! `M₂ = √(A·Z / (a0·ζ))` with `A = 2T/ωn²`, `Z = b/(2ωn)`, which gives `Mp = 0.0225 g`,
//! `K_I = 19.55 N/µm`, hence `Ms = 2.6575 g`, `Ks = 11.62 N/µm`, and the model's differential
//! `a0 = 0.5285 µm/V` (−1.0 %) and `ζ = 0.01718` (+1.0 %). (The small `Mp` says the stacks add
//! about 1 % to the moving mass in the paper's set-up.)
//!
//! *Capacitance*: the figures say nothing about `C`; we take the clamped capacitance for a stack
//! coupling factor `k² = T²/(K_I C_free) = 1/2` (typical of PZT stacks), i.e. `C = T²/K_I`
//! ≈ 9.2 µF (free capacitance 18.4 µF, that of a ~100 µm commercial stack).
//!
//! *Contact `K_0`* and the coupled model's own `K_I`, `T`: see [`super::coupled`].

/// Which stacks drive the stage.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Configuration {
    /// Only the left stack drives the stage (there is no right stack).
    Unidirectional,
    /// The left stack pushes, the right stack pulls: `u_l = ū + v`, `u_r = ū − v`.
    Differential,
}

/// A second-order small-signal model `a0 / (1 + 2ζ s/ωn + (s/ωn)²)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SecondOrder {
    /// DC gain, µm per volt of drive (`u_l` unidirectional, `v` differential).
    pub a0_um_per_volt: f64,
    /// Damping ratio.
    pub zeta: f64,
    /// Natural frequency, rad/s.
    pub omega_n: f64,
}

impl SecondOrder {
    /// The paper's identified fit for `configuration`.
    pub fn paper(configuration: Configuration) -> Self {
        match configuration {
            Configuration::Unidirectional => Self {
                a0_um_per_volt: 0.43,
                zeta: 0.022,
                omega_n: 1.08e5,
            },
            Configuration::Differential => Self {
                a0_um_per_volt: 0.534,
                zeta: 0.017,
                omega_n: 1.37e5,
            },
        }
    }
}

/// The paper's `K_I + Ks`, N/m (31.17 N/µm).
pub const PAPER_TOTAL_STIFFNESS: f64 = 31.17e6;
/// The paper's `Mp + Ms`, kg (2.68 g).
pub const PAPER_TOTAL_MASS: f64 = 2.68e-3;
/// The paper's stage damping `b`, N·s/m.
pub const PAPER_DAMPING: f64 = 12.72;

/// Physical constants of one stage with its (identical) stacks, SI units, for the `K_0 → ∞`
/// model; the coupled model derives its own stack constants from these and `K_0`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StageParams {
    /// `Mp`, effective moving mass of one stack, kg.
    pub stack_mass: f64,
    /// `Ms`, stage mass, kg.
    pub stage_mass: f64,
    /// `K_I`, stiffness of one stack, N/m.
    pub stack_stiffness: f64,
    /// `Ks`, stage (flexure) stiffness, N/m.
    pub stage_stiffness: f64,
    /// `b`, stage damping, N·s/m.
    pub damping: f64,
    /// `T`, the stack's force factor, N/V (also C/m in the charge equation).
    pub force_factor: f64,
    /// `C`, the stack's clamped capacitance, F.
    pub capacitance: f64,
}

impl StageParams {
    /// The stage of the paper, derived as documented at the top of this module.
    pub fn paper() -> Self {
        let uni = SecondOrder::paper(Configuration::Unidirectional);
        let diff = SecondOrder::paper(Configuration::Differential);
        let t = uni.a0_um_per_volt * 1e-6 * PAPER_TOTAL_STIFFNESS;
        let w2 = diff.omega_n * diff.omega_n;
        let a = 2.0 * t / w2;
        let z = PAPER_DAMPING / (2.0 * diff.omega_n);
        let m2 = (a * z / (diff.a0_um_per_volt * 1e-6 * diff.zeta)).sqrt();
        let k2 = w2 * m2;
        let stack_mass = m2 - PAPER_TOTAL_MASS;
        let stack_stiffness = k2 - PAPER_TOTAL_STIFFNESS;
        Self {
            stack_mass,
            stage_mass: PAPER_TOTAL_MASS - stack_mass,
            stack_stiffness,
            stage_stiffness: PAPER_TOTAL_STIFFNESS - stack_stiffness,
            damping: PAPER_DAMPING,
            force_factor: t,
            capacitance: t * t / stack_stiffness,
        }
    }

    /// Moving mass, stiffness and force per volt of the `K_0 → ∞` model:
    /// `(Ms + Mp, K_I + Ks)` unidirectional, `(Ms + 2Mp, 2K_I + Ks)` differential.
    pub fn reduced_mass_stiffness(&self, configuration: Configuration) -> (f64, f64) {
        match configuration {
            Configuration::Unidirectional => (
                self.stage_mass + self.stack_mass,
                self.stage_stiffness + self.stack_stiffness,
            ),
            Configuration::Differential => (
                self.stage_mass + 2.0 * self.stack_mass,
                self.stage_stiffness + 2.0 * self.stack_stiffness,
            ),
        }
    }

    /// The small-signal model these constants predict (`K_0 → ∞`), in the paper's inputs
    /// (`u_l` unidirectional, `v` differential: `T(u_l − u_r) = 2T v`).
    pub fn second_order(&self, configuration: Configuration) -> SecondOrder {
        let (m, k) = self.reduced_mass_stiffness(configuration);
        let drive = match configuration {
            Configuration::Unidirectional => 1.0,
            Configuration::Differential => 2.0,
        };
        let omega_n = (k / m).sqrt();
        SecondOrder {
            a0_um_per_volt: drive * self.force_factor / k * 1e6,
            zeta: self.damping / (2.0 * omega_n * m),
            omega_n,
        }
    }

    /// Checks every constant is finite and positive; names the first one that is not.
    pub fn validate(&self) -> Result<(), &'static str> {
        let fields = [
            ("stack_mass", self.stack_mass),
            ("stage_mass", self.stage_mass),
            ("stack_stiffness", self.stack_stiffness),
            ("stage_stiffness", self.stage_stiffness),
            ("damping", self.damping),
            ("force_factor", self.force_factor),
            ("capacitance", self.capacitance),
        ];
        match fields.iter().find(|(_, v)| !(v.is_finite() && *v > 0.0)) {
            Some((name, _)) => Err(name),
            None => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn derived_constants_reproduce_the_papers_totals_and_unidirectional_fit() {
        let p = StageParams::paper();
        assert!(p.validate().is_ok());
        assert!((p.stack_mass + p.stage_mass - PAPER_TOTAL_MASS).abs() < 1e-12);
        assert!((p.stack_stiffness + p.stage_stiffness - PAPER_TOTAL_STIFFNESS).abs() < 1e-3);
        let uni = p.second_order(Configuration::Unidirectional);
        let fit = SecondOrder::paper(Configuration::Unidirectional);
        assert!((uni.a0_um_per_volt / fit.a0_um_per_volt - 1.0).abs() < 1e-12);
        assert!((uni.omega_n / fit.omega_n - 1.0).abs() < 0.002);
        assert!((uni.zeta / fit.zeta - 1.0).abs() < 0.002);
    }

    #[test]
    fn differential_fit_keeps_omega_exact_and_splits_the_papers_inconsistency() {
        let p = StageParams::paper();
        let d = p.second_order(Configuration::Differential);
        let fit = SecondOrder::paper(Configuration::Differential);
        assert!((d.omega_n / fit.omega_n - 1.0).abs() < 1e-12);
        let ea = d.a0_um_per_volt / fit.a0_um_per_volt - 1.0;
        let ez = d.zeta / fit.zeta - 1.0;
        // Equal and opposite (in the log), each about 1 %.
        assert!(((1.0 + ea) * (1.0 + ez) - 1.0).abs() < 1e-12);
        assert!(ea < -0.009 && ea > -0.012, "{ea}");
        assert!(p.stack_mass > 0.0 && p.stack_mass < 0.1e-3);
    }
}
