//! The `K_0 → ∞` reduction of the coupled model (see the book, docs/src/reference/physics.md): stack tips and stage move as one.
//!
//! ```text
//! unidirectional: (Ms + Mp)  ẍ_s + b ẋ_s + (K_I + Ks)  x_s = T e_l
//! differential:   (Ms + 2Mp) ẍ_s + b ẋ_s + (2K_I + Ks) x_s = T (e_l − e_r)
//! ```
//!
//! State (SI): `[x_s, ẋ_s]`; exact zero-order hold per control period.

use super::stage::{Configuration, StageParams};
use twinstack_identify::zero_order_hold::ZeroOrderHold;

/// The 1-DOF stage model, advanced one control period at a time.
#[derive(Clone, Debug, PartialEq)]
pub struct ReducedModel {
    zoh: ZeroOrderHold<2, 2>,
    /// `[x_s, ẋ_s]`, m and m/s.
    state: [f64; 2],
    force_factor: f64,
}

impl ReducedModel {
    /// The reduced model of `stage` in `configuration`, at rest, period `dt` seconds.
    pub fn new(stage: &StageParams, configuration: Configuration, dt: f64) -> Self {
        let (m, k) = stage.reduced_mass_stiffness(configuration);
        let t = stage.force_factor;
        let a = [[0.0, 1.0], [-k / m, -stage.damping / m]];
        let right = match configuration {
            Configuration::Unidirectional => 0.0,
            Configuration::Differential => -t / m,
        };
        let b = [[0.0, 0.0], [t / m, right]];
        Self {
            zoh: ZeroOrderHold::new(&a, &b, dt),
            state: [0.0; 2],
            force_factor: t,
        }
    }

    /// One control period with the effective voltages `[e_l, e_r]` (volts) held.
    #[inline]
    pub fn step(&mut self, effective_volts: [f64; 2]) {
        self.zoh.step(&mut self.state, &effective_volts);
    }

    /// Stage displacement `x_s`, m (the stack tips are at the stage).
    pub fn stage_m(&self) -> f64 {
        self.state[0]
    }

    /// The state `[x_s, ẋ_s]`, m and m/s.
    pub fn state(&self) -> &[f64; 2] {
        &self.state
    }

    /// The force factor `T`, N/V.
    pub fn force_factor(&self) -> f64 {
        self.force_factor
    }
}
