//! The hysteresis and creep models, in fixed point: each one's forward form (the observer,
//! drive in, displacement out) and its inverse (the compensator, setpoint in, drive out),
//! with their physical (`f64`) parameters. These run in the interrupt, inside the control law.
//!
//! Every model has the same shape: its configuration (the immutable, validated model, built
//! off the tick) apart from its state (what one step changes), one [`Hysteresis::step`] and a
//! declared cost ([`Hysteresis::cycles`], the cycles it adds to the tick's worst case, which
//! the [tick budget](crate::config::tick_budget) adds up). Creep is composed in series with
//! whichever model runs, by a wrapper ([`CompensatorRun`]: the inverse creep before the
//! inverse model; [`ObserverRun`]: the creep after the forward one), not written into each
//! model. The tick runs the models by static dispatch ([`dispatch`]: one enum over the
//! models, no `dyn`: the interrupt branches through no register).
//!
//! * [`play_operator`] — the play (backlash) operator, the building block of P–I.
//! * [`prandtl_ishlinskii`] — forward and analytic-inverse Prandtl–Ishlinskii models.
//! * [`generalised_pi`] — the generalised (asymmetric) P–I: a P–I followed by a monotone
//!   dead-zone map, and its analytic inverse.
//! * [`duhem`] — Duhem forward observer and inverse Duhem compensator.
//! * [`bouc_wen`] — generalised (asymmetric) Bouc–Wen observer and its compensator.
//! * [`relaxation`] — the exponential relaxation in the input that Duhem and Bouc–Wen take
//!   exactly over each sample (what makes them rate-independent), and the step their
//!   compensators solve for.
//! * [`creep`] — the creep operator (log-spaced first-order modes) in series with a
//!   hysteresis model, and its exact inverse.
//! * [`params`] — the models' physical (`f64`) parameters and their own checks.
//! * [`dispatch`] — the compensator and the observer a configuration picks, and what the tick
//!   runs of them: each model with its state, after (or before) the creep.
//!
//! Adding a model: its module here (the forward and inverse types, [`Hysteresis`],
//! [`Forward`] and [`Inverse`] implemented on them, their cost beside them), its variants in
//! [`dispatch`]'s enums (the configuration's and the tick's), its parameters in
//! [`params`] and a [`Model`](crate::config::settings::Model) variant, with the lines in
//! [`crate::config::settings::Settings::build`] that build it.

pub mod bouc_wen;
pub mod creep;
pub mod dispatch;
pub mod duhem;
pub mod generalised_pi;
pub mod params;
pub mod play_operator;
pub mod prandtl_ishlinskii;
pub mod relaxation;

pub use dispatch::{Compensator, CompensatorRun, ForwardRun, InverseRun, Observer, ObserverRun};

/// A model in fixed point, in idsp's shape: the configuration is `self` (immutable on the
/// tick), the state apart, one step per tick.
pub trait Hysteresis {
    /// What one step changes.
    type State: Copy + core::fmt::Debug + PartialEq + Eq;

    /// One tick: input `x` (Q2.30 normalised) → output (Q2.30 normalised, saturated).
    fn step(&self, state: &mut Self::State, x: i32) -> i32;

    /// The cycles this model adds to the tick's worst case (5 flash wait states, cache cold;
    /// measured by the whole-interrupt bench, `tests/irq_bench.rs`, which holds every
    /// configuration's worst tick under the sum the [tick budget](crate::config::tick_budget)
    /// makes of these).
    fn cycles(&self) -> u32;
}

/// A forward model (the observer: drive in, displacement out).
pub trait Forward: Hysteresis {
    /// The state after the drive has rested at `u` (Q2.30), and the output there.
    fn relaxed(&self, u: i32) -> (Self::State, i32);
}

/// An inverse model (the compensator: desired displacement in, drive out).
pub trait Inverse: Hysteresis {
    /// The state after the drive has rested at `u` with the stage at `y` (both Q2.30; `y` is
    /// where the observer puts the stage, or `u` without one).
    fn relaxed(&self, u: i32, y: i32) -> Self::State;

    /// The forward model this inverts (the observer that can hand it its history).
    type Forward: Hysteresis;

    /// The state matching an observer's (`forward` in state `state`), where `forward` is the
    /// very model this inverts (then the compensator continues from the observer's
    /// history); `None` otherwise.
    fn matching(
        &self,
        forward: &Self::Forward,
        state: &<Self::Forward as Hysteresis>::State,
    ) -> Option<Self::State>;
}

/// A model and its state, as the tick runs it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Running<M: Hysteresis> {
    /// The configuration.
    pub model: M,
    /// Its state.
    pub state: M::State,
}

impl<M: Hysteresis> Running<M> {
    /// One tick of the model on its state.
    #[inline(always)]
    pub fn step(&mut self, x: i32) -> i32 {
        self.model.step(&mut self.state, x)
    }
}
