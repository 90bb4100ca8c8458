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
pub mod output_map;
pub mod params;
pub mod play_operator;
pub mod prandtl_ishlinskii;
pub mod relaxation;

pub use dispatch::{Compensator, CompensatorRun, ForwardRun, InverseRun, Observer, ObserverRun};

/// Full strokes down and up over the input range by which a Duhem-class model (Duhem,
/// Bouc–Wen) is brought to rest on its major loop ([`rest_history`]).
pub const REST_CYCLES: usize = 256;

/// The drive history of a stage at rest at `u` (Q2.30 normalised), for the models whose memory
/// fades rather than wipes (Duhem, Bouc–Wen): `step` is called with each turning point of
/// [`REST_CYCLES`] full cycles over the input range, from its top (where the caller starts
/// the model relaxed), then the range's bottom and `u`. A stage in use has been cycled over
/// its range and last left at 0 V at its bottom (the P–I models' start,
/// [`prandtl_ishlinskii`]'s `state_at_rest`, "top of the range → bottom → u"); a model whose
/// state relaxes toward its loop by a factor `e^{−c·|Δu|}` reaches the loop only after
/// several strokes, so it is cycled until the start is forgotten: at the slowest relaxation
/// identification fits (a Duhem's `α` of 0.01 per normalised unit, strokes of 2) 256 cycles
/// leave `e^{−10}` of it. Off the tick (a reload's preparation, about 500 model steps): every
/// step is one model step of a whole stroke, exact in the input, the same in the `f64`
/// references.
pub fn rest_history(u: i32, mut step: impl FnMut(i32)) {
    let (bottom, top) = (
        -crate::fixed_point::SIGNAL_ONE,
        crate::fixed_point::FULL_SCALE_MAX,
    );
    for _ in 0..REST_CYCLES {
        step(bottom);
        step(top);
    }
    step(bottom);
    step(u);
}

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

    /// Whether the model's step computes in floating point (single precision, on the
    /// Cortex-M4's FPU): the first floating-point instruction of an interrupt that runs it
    /// saves the interrupted code's floating-point registers, and its return restores them
    /// ([`crate::config::tick_budget::FP_CONTEXT_CYCLES`], which the tick budget charges such
    /// a model beside its [`Hysteresis::cycles`]). The integer models keep the interrupt
    /// clear of the FPU.
    fn uses_fpu(&self) -> bool {
        false
    }
}

/// Where a model's memory stands when the drive rests: what the stage has behind it, which
/// the drive's configuration decides (`control::drive::Configuration::rest`). Every model
/// starts by it, on the board
/// ([`crate::control::Controller::prepare`]) and in the references that replay the board.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rest {
    /// On the major loop's ascending branch: the stack was cycled over its range and last
    /// raised from its bottom to the drive ([`rest_history`]; the P–I's "top → bottom → u").
    /// A single-ended stack, raised from its lowest voltage to where it rests.
    Ascending,
    /// Relaxed, no hysteresis stored (Duhem and Bouc–Wen: `h = 0`, on the anhysteretic
    /// curve; the P–I: every operator at the input, the virgin state). A push-pull pair
    /// brought to its bias: both stacks rose together, and in the model's coordinate (the
    /// left stack's voltage, `u_r = 2ū − u_l`) the right stack's rise is a fall, so the two
    /// halves of the pair's hysteresis cancel.
    Relaxed,
}

/// A forward model (the observer: drive in, displacement out).
pub trait Forward: Hysteresis {
    /// The state after the drive has rested at `u` (Q2.30) with the history `rest`, and the
    /// output there.
    fn at_rest(&self, u: i32, rest: Rest) -> (Self::State, i32);
}

/// An inverse model (the compensator: desired displacement in, drive out).
pub trait Inverse: Hysteresis {
    /// The state after the drive has rested at `u` with the history `rest`, the stage at `y`
    /// (both Q2.30; `y` is where the observer puts the stage, or `u` without one).
    fn at_rest(&self, u: i32, y: i32, rest: Rest) -> Self::State;

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

    /// One tick of a floating-point model ([`Hysteresis::uses_fpu`]) on its state, in a
    /// function of its own: the floating-point registers it uses are saved and restored in
    /// this call, on the ticks that run it, not in the prologue of the interrupt that calls
    /// it — where every configuration's tick would pay for them, and touch the FPU (whose
    /// context the hardware then saves) even with an integer model or none. A direct call:
    /// the tick branches through no register.
    #[inline(never)]
    pub fn step_out_of_line(&mut self, x: i32) -> i32 {
        self.model.step(&mut self.state, x)
    }
}
