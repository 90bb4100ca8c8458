//! The coupled electromechanical model of the book's docs/src/reference/physics.md: left stack tip, stage, right stack tip,
//! joined by contacts of stiffness `K_0`.
//!
//! ```text
//! Mp ẍ_l + (K_I + K_0) x_l − K_0 x_s                    =  T e_l
//! Ms ẍ_s + b ẋ_s − K_0 x_l + (Ks + 2K_0) x_s − K_0 x_r  =  0
//! Mp ẍ_r + (K_I + K_0) x_r − K_0 x_s                    = −T e_r
//! ```
//!
//! with `e = u − v^h` each stack's effective voltage. In the unidirectional configuration there
//! is no right stack: its contact is absent (`Ks + K_0` on the stage) and its tip stays at rest.
//!
//! **Constants.** The paper's `K_I`, `T` ([`StageParams`]) are those of the `K_0 → ∞` model, in
//! which the stack and its contact act as one spring. With a finite contact the stack's own
//! constants must be such that stack-plus-contact is that spring, with that blocked force:
//! `K_I,c K_0 / (K_I,c + K_0) = K_I` and `T_c K_0 / (K_I,c + K_0) = T`, i.e.
//! `K_I,c = K_I K_0 / (K_0 − K_I)`, `T_c = T (K_I,c + K_0) / K_0`. Then the coupled model has
//! exactly the reduced model's DC gain for any `K_0 > K_I`, and its first resonance tends to the
//! reduced one as `K_0` grows (the contact only adds the tip modes, near
//! `√((K_I,c + K_0)/Mp)`).
//!
//! Default `K_0` = [`DEFAULT_CONTACT_STIFFNESS`]: a stiff, preloaded ceramic–steel contact,
//! about 100 `K_I`, which keeps the first resonance within 0.1 % of the `K_0 → ∞` value.
//!
//! **Contact damping (an addition to the book's docs/src/reference/physics.md).** Each contact also has a dashpot `b_0` in
//! parallel with `K_0`, acting on the relative velocity `ẋ_l − ẋ_s` (resp. `ẋ_s − ẋ_r`).
//! The book's equations are the case `b_0 = 0`; there the MHz tip modes have almost no damping
//! (only through the stage's `b`) and ring for seconds after every step, which shows up in the
//! stack charges. The default [`DEFAULT_CONTACT_DAMPING_RATIO`] damps them at 5 % of critical;
//! in the first mode tips and stage move together, so `b_0` leaves it untouched.
//!
//! State (SI): `[x_l, x_s, x_r, ẋ_l, ẋ_s, ẋ_r]`, metres and m/s; advanced by the exact
//! zero-order hold of [`ZeroOrderHold`].

use super::stage::{Configuration, StageParams};
use twinstack_identify::zero_order_hold::ZeroOrderHold;

/// Default stack–stage contact stiffness `K_0`, N/m (2000 N/µm).
pub const DEFAULT_CONTACT_STIFFNESS: f64 = 2.0e9;

/// Damping ratio given to the tip modes by the contact dashpot `b_0`:
/// `b_0 = 2 ζ_0 √((K_I,c + K_0) Mp)`.
pub const DEFAULT_CONTACT_DAMPING_RATIO: f64 = 0.05;

/// The 3-DOF coupled model, advanced one control period at a time.
#[derive(Clone, Debug, PartialEq)]
pub struct CoupledModel {
    zoh: ZeroOrderHold<6, 2>,
    /// `[x_l, x_s, x_r, ẋ_l, ẋ_s, ẋ_r]`, m and m/s.
    state: [f64; 6],
    stack_stiffness: f64,
    force_factor: f64,
    contact_stiffness: f64,
}

impl CoupledModel {
    /// The model of `stage` with contacts of stiffness `contact_stiffness` (N/m, must exceed
    /// `K_I`), at rest, advanced in periods of `dt` seconds.
    pub fn new(
        stage: &StageParams,
        contact_stiffness: f64,
        configuration: Configuration,
        dt: f64,
    ) -> Self {
        let k0 = contact_stiffness;
        let ki = stage.stack_stiffness * k0 / (k0 - stage.stack_stiffness);
        let t = stage.force_factor * (ki + k0) / k0;
        let (mp, ms, ks, b) = (
            stage.stack_mass,
            stage.stage_mass,
            stage.stage_stiffness,
            stage.damping,
        );
        let b0 = 2.0 * DEFAULT_CONTACT_DAMPING_RATIO * ((ki + k0) * mp).sqrt();
        let (k0r, b0r) = match configuration {
            Configuration::Unidirectional => (0.0, 0.0),
            Configuration::Differential => (k0, b0),
        };
        let mut a = [[0.0; 6]; 6];
        for i in 0..3 {
            a[i][i + 3] = 1.0;
        }
        a[3][0] = -(ki + k0) / mp;
        a[3][1] = k0 / mp;
        a[3][3] = -b0 / mp;
        a[3][4] = b0 / mp;
        a[4][0] = k0 / ms;
        a[4][1] = -(ks + k0 + k0r) / ms;
        a[4][2] = k0r / ms;
        a[4][3] = b0 / ms;
        a[4][4] = -(b + b0 + b0r) / ms;
        a[4][5] = b0r / ms;
        a[5][1] = k0r / mp;
        a[5][2] = -(ki + k0r) / mp;
        a[5][4] = b0r / mp;
        a[5][5] = -b0r / mp;
        let mut bm = [[0.0; 2]; 6];
        bm[3][0] = t / mp;
        if configuration == Configuration::Differential {
            bm[5][1] = -t / mp;
        }
        Self {
            zoh: ZeroOrderHold::new(&a, &bm, dt),
            state: [0.0; 6],
            stack_stiffness: ki,
            force_factor: t,
            contact_stiffness: k0,
        }
    }

    /// One control period with the effective voltages `[e_l, e_r]` (volts) held.
    #[inline]
    pub fn step(&mut self, effective_volts: [f64; 2]) {
        self.zoh.step(&mut self.state, &effective_volts);
    }

    /// Stage displacement `x_s`, m.
    pub fn stage_m(&self) -> f64 {
        self.state[1]
    }

    /// Stack tips `[x_l, x_r]`, m.
    pub fn tips_m(&self) -> [f64; 2] {
        [self.state[0], self.state[2]]
    }

    /// The full state `[x_l, x_s, x_r, ẋ_l, ẋ_s, ẋ_r]`, m and m/s.
    pub fn state(&self) -> &[f64; 6] {
        &self.state
    }

    /// The stack's own stiffness in this model, `K_I,c`, N/m.
    pub fn stack_stiffness(&self) -> f64 {
        self.stack_stiffness
    }

    /// The stack's force factor in this model, `T_c`, N/V.
    pub fn force_factor(&self) -> f64 {
        self.force_factor
    }

    /// The contact stiffness `K_0`, N/m.
    pub fn contact_stiffness(&self) -> f64 {
        self.contact_stiffness
    }
}
