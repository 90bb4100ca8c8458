//! The compensator and the observer a configuration picks, and what the tick runs of them:
//! one enum over the models each, static dispatch (a `match`, no `dyn`: the interrupt
//! branches through no register, and the whole-interrupt bench's walk of its call graph
//! checks it).
//!
//! The configuration's enums ([`Compensator`], [`Observer`]) hold the models; the tick's
//! ([`CompensatorRun`], [`ObserverRun`]) hold each model in series with the stage's creep and
//! its state ([`Running`]), one tag per tick. Creep is not a variant of its own: it is the
//! [`Series`] every model runs in, `None` where the stage has none.

use crate::models::bouc_wen::{BoucWen, InverseBoucWen};
use crate::models::creep::{Creep, InverseCreep};
use crate::models::duhem::{Duhem, InverseDuhem};
use crate::models::generalised_pi::{GeneralisedPi, InverseGeneralisedPi};
use crate::models::prandtl_ishlinskii::{InversePrandtlIshlinskii, PrandtlIshlinskii};
use crate::models::{Forward, Hysteresis, Inverse, Running, Series};

/// An inverse model after the inverse creep (setpoint → C⁻¹ → H⁻¹ → drive).
pub type Compensating<M> = Series<Option<InverseCreep>, M>;
/// A forward model followed by the creep (drive → H → C → displacement).
pub type Observing<M> = Series<M, Option<Creep>>;

/// The feedforward compensator: desired displacement → drive.
// The variants differ in size by design: there is no heap on the board, and the configuration
// lives in a static, so boxing the large variant is neither possible nor wanted.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Compensator {
    /// No compensation: the drive is the setpoint, range onto range (bypass).
    None,
    /// Analytic inverse Prandtl–Ishlinskii.
    InversePi(InversePrandtlIshlinskii),
    /// Inverse Duhem.
    InverseDuhem(InverseDuhem),
    /// Analytic inverse of the generalised (asymmetric) P–I.
    InverseGeneralisedPi(InverseGeneralisedPi),
    /// Inverse-multiplicative Bouc–Wen.
    InverseBoucWen(InverseBoucWen),
}

/// The forward observer: applied drive → estimated displacement.
#[allow(clippy::large_enum_variant)] // as for `Compensator`
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Observer {
    /// No observer (estimate reads 0).
    None,
    /// Forward Prandtl–Ishlinskii.
    Pi(PrandtlIshlinskii),
    /// Forward Duhem.
    Duhem(Duhem),
    /// Forward generalised (asymmetric) P–I.
    GeneralisedPi(GeneralisedPi),
    /// Forward Bouc–Wen.
    BoucWen(BoucWen),
}

/// The compensator as the tick runs it: the inverse creep and the model in series, and their
/// state, in one enum (one tag per tick).
// The order of the variants is the tag the tick's dispatch compares: the reference model first.
#[allow(clippy::large_enum_variant)] // no heap: the controllers live in statics
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CompensatorRun {
    /// Inverse P–I.
    InversePi(Running<Compensating<InversePrandtlIshlinskii>>),
    /// Inverse Duhem.
    InverseDuhem(Running<Compensating<InverseDuhem>>),
    /// No compensation: the drive is the setpoint.
    None,
    /// Inverse generalised P–I.
    InverseGeneralisedPi(Running<Compensating<InverseGeneralisedPi>>),
    /// Inverse Bouc–Wen.
    InverseBoucWen(Running<Compensating<InverseBoucWen>>),
}

/// The observer as the tick runs it (see [`CompensatorRun`]): the model and the creep in series.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ObserverRun {
    /// Forward Duhem.
    Duhem(Running<Observing<Duhem>>),
    /// Forward P–I.
    Pi(Running<Observing<PrandtlIshlinskii>>),
    /// No observer: the estimate reads 0.
    None,
    /// Forward generalised P–I.
    GeneralisedPi(Running<Observing<GeneralisedPi>>),
    /// Forward Bouc–Wen.
    BoucWen(Running<Observing<BoucWen>>),
}

/// `m` after the inverse creep, with its state: matched to the observer's where that runs the
/// model `m` inverts, else relaxed at drive `u` with the stage at `y`; the creep's modes
/// settled at `y` (where the models are relaxed, so it passes `y` through).
fn compensating<M: Inverse>(
    m: &M,
    observer: &ObserverRun,
    creep: Option<Creep>,
    u: i32,
    y: i32,
) -> Running<Compensating<M>>
where
    M: Copy,
{
    let state = m
        .matching(observer)
        .unwrap_or_else(|| Inverse::relaxed(m, u, y));
    let creep_state = creep.map(|c| c.state_at_rest(y)).unwrap_or_default();
    Running {
        model: Series(creep.map(InverseCreep), *m),
        state: (creep_state, state),
    }
}

/// `m` followed by the creep, relaxed at drive `u`, and its output there; the creep's modes
/// settled at the model's output (so it passes it through).
fn observing<M: Forward + Copy>(
    m: &M,
    creep: Option<Creep>,
    u: i32,
) -> (Running<Observing<M>>, i32) {
    let (state, y) = Forward::relaxed(m, u);
    let creep_state = creep.map(|c| c.state_at_rest(y)).unwrap_or_default();
    let run = Running {
        model: Series(*m, creep),
        state: (state, creep_state),
    };
    (run, y)
}

impl Compensator {
    /// What the tick runs of it, in series with `creep` (not applied without a model), its
    /// state from `observer`'s (prepared first) or relaxed at drive `u` with the stage at `y`.
    /// Off the tick.
    pub fn prepare(
        &self,
        observer: &ObserverRun,
        creep: Option<Creep>,
        u: i32,
        y: i32,
    ) -> CompensatorRun {
        match self {
            Self::None => CompensatorRun::None,
            Self::InversePi(m) => CompensatorRun::InversePi(compensating(m, observer, creep, u, y)),
            Self::InverseDuhem(m) => {
                CompensatorRun::InverseDuhem(compensating(m, observer, creep, u, y))
            }
            Self::InverseGeneralisedPi(m) => {
                CompensatorRun::InverseGeneralisedPi(compensating(m, observer, creep, u, y))
            }
            Self::InverseBoucWen(m) => {
                CompensatorRun::InverseBoucWen(compensating(m, observer, creep, u, y))
            }
        }
    }

    /// The model's own cost in the tick (its creep apart), cycles at 5 wait states; 0 without
    /// a model.
    pub fn cycles(&self) -> u32 {
        match self {
            Self::None => 0,
            Self::InversePi(m) => m.cycles(),
            Self::InverseDuhem(m) => m.cycles(),
            Self::InverseGeneralisedPi(m) => m.cycles(),
            Self::InverseBoucWen(m) => m.cycles(),
        }
    }
}

impl Observer {
    /// What the tick runs of it, followed by `creep` (not applied without a model), relaxed at
    /// drive `u`; and its estimate there (`u` without a model). Off the tick.
    pub fn prepare(&self, creep: Option<Creep>, u: i32) -> (ObserverRun, i32) {
        match self {
            Self::None => (ObserverRun::None, u),
            Self::Pi(m) => {
                let (run, y) = observing(m, creep, u);
                (ObserverRun::Pi(run), y)
            }
            Self::Duhem(m) => {
                let (run, y) = observing(m, creep, u);
                (ObserverRun::Duhem(run), y)
            }
            Self::GeneralisedPi(m) => {
                let (run, y) = observing(m, creep, u);
                (ObserverRun::GeneralisedPi(run), y)
            }
            Self::BoucWen(m) => {
                let (run, y) = observing(m, creep, u);
                (ObserverRun::BoucWen(run), y)
            }
        }
    }

    /// The estimate after the drive has rested at `u` (`u` without a model). Off the tick.
    pub fn relaxed_output(&self, u: i32) -> i32 {
        match self {
            Self::None => u,
            Self::Pi(m) => Forward::relaxed(m, u).1,
            Self::Duhem(m) => Forward::relaxed(m, u).1,
            Self::GeneralisedPi(m) => Forward::relaxed(m, u).1,
            Self::BoucWen(m) => Forward::relaxed(m, u).1,
        }
    }

    /// The model's own cost in the tick (its creep apart), cycles at 5 wait states; 0 without
    /// a model.
    pub fn cycles(&self) -> u32 {
        match self {
            Self::None => 0,
            Self::Pi(m) => m.cycles(),
            Self::Duhem(m) => m.cycles(),
            Self::GeneralisedPi(m) => m.cycles(),
            Self::BoucWen(m) => m.cycles(),
        }
    }
}

impl CompensatorRun {
    /// One tick: desired displacement `y` (Q2.30) → drive (Q2.30); without a model, `y`.
    #[inline(always)]
    pub fn step(&mut self, y: i32) -> i32 {
        match self {
            Self::InversePi(r) => r.step(y),
            Self::InverseDuhem(r) => r.step(y),
            Self::None => y,
            Self::InverseGeneralisedPi(r) => r.step(y),
            Self::InverseBoucWen(r) => r.step(y),
        }
    }
}

impl ObserverRun {
    /// One tick: applied drive `u` (Q2.30) → estimated displacement (Q2.30); without a
    /// model, 0.
    #[inline(always)]
    pub fn step(&mut self, u: i32) -> i32 {
        match self {
            Self::Duhem(r) => r.step(u),
            Self::Pi(r) => r.step(u),
            Self::None => 0,
            Self::GeneralisedPi(r) => r.step(u),
            Self::BoucWen(r) => r.step(u),
        }
    }
}
