//! The compensator and the observer a configuration picks, and what the tick runs of them:
//! one enum over the models each, static dispatch (a `match`, no `dyn`: the interrupt
//! branches through no register, and the whole-interrupt bench's walk of its call graph
//! checks it).
//!
//! The configuration's enums ([`Compensator`], [`Observer`]) hold the models; the tick's
//! ([`CompensatorRun`], [`ObserverRun`]) hold each model, alone or in [`Series`] with the
//! stage's creep, and its state ([`Running`]), one tag per tick. Whether the creep runs is
//! part of that tag (`InversePi` / `InversePiCreep`), not a check of its own: a tick without
//! creep dispatches on the model alone, as cheap as a model run by hand (an `Option` of the
//! creep inside each variant cost the P–I 16 tick 15–20 instructions in the whole-interrupt
//! bench).

use crate::models::bouc_wen::{BoucWen, InverseBoucWen};
use crate::models::creep::{Creep, InverseCreep};
use crate::models::duhem::{Duhem, InverseDuhem};
use crate::models::generalised_pi::{GeneralisedPi, InverseGeneralisedPi};
use crate::models::prandtl_ishlinskii::{InversePrandtlIshlinskii, PrandtlIshlinskii};
use crate::models::{Forward, Hysteresis, Inverse, Running, Series};

/// An inverse model after the inverse creep (setpoint → C⁻¹ → H⁻¹ → drive).
pub type Compensating<M> = Series<InverseCreep, M>;
/// A forward model followed by the creep (drive → H → C → displacement).
pub type Observing<M> = Series<M, Creep>;

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
    /// Inverse Bouc–Wen.
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

/// The compensator as the tick runs it: the model, alone or after the inverse creep, and its
/// state, in one enum (one tag per tick).
// The order of the variants is the tag the tick's dispatch compares: the reference model first.
#[allow(clippy::large_enum_variant)] // no heap: the controllers live in statics
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CompensatorRun {
    /// Inverse P–I.
    InversePi(Running<InversePrandtlIshlinskii>),
    /// Inverse Duhem.
    InverseDuhem(Running<InverseDuhem>),
    /// No compensation: the drive is the setpoint.
    None,
    /// Inverse generalised P–I.
    InverseGeneralisedPi(Running<InverseGeneralisedPi>),
    /// Inverse Bouc–Wen.
    InverseBoucWen(Running<InverseBoucWen>),
    /// Inverse creep, then the inverse P–I.
    InversePiCreep(Running<Compensating<InversePrandtlIshlinskii>>),
    /// Inverse creep, then the inverse Duhem.
    InverseDuhemCreep(Running<Compensating<InverseDuhem>>),
    /// Inverse creep, then the inverse generalised P–I.
    InverseGeneralisedPiCreep(Running<Compensating<InverseGeneralisedPi>>),
    /// Inverse creep, then the inverse Bouc–Wen.
    InverseBoucWenCreep(Running<Compensating<InverseBoucWen>>),
}

/// The observer as the tick runs it (see [`CompensatorRun`]): the model, alone or followed by
/// the creep.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ObserverRun {
    /// Forward Duhem.
    Duhem(Running<Duhem>),
    /// Forward P–I.
    Pi(Running<PrandtlIshlinskii>),
    /// No observer: the estimate reads 0.
    None,
    /// Forward generalised P–I.
    GeneralisedPi(Running<GeneralisedPi>),
    /// Forward Bouc–Wen.
    BoucWen(Running<BoucWen>),
    /// Forward Duhem, then the creep.
    DuhemCreep(Running<Observing<Duhem>>),
    /// Forward P–I, then the creep.
    PiCreep(Running<Observing<PrandtlIshlinskii>>),
    /// Forward generalised P–I, then the creep.
    GeneralisedPiCreep(Running<Observing<GeneralisedPi>>),
    /// Forward Bouc–Wen, then the creep.
    BoucWenCreep(Running<Observing<BoucWen>>),
}

/// `m` alone or after the inverse creep, with its state: matched to the observer's where that
/// runs the model `m` inverts, else relaxed at drive `u` with the stage at `y`; the creep's
/// modes settled at `y` (where the models are relaxed, so it passes `y` through).
fn compensating<M: Inverse + Copy>(
    m: &M,
    observer: Option<(&M::Forward, &<M::Forward as Hysteresis>::State)>,
    creep: Option<Creep>,
    u: i32,
    y: i32,
    alone: fn(Running<M>) -> CompensatorRun,
    with_creep: fn(Running<Compensating<M>>) -> CompensatorRun,
) -> CompensatorRun {
    let state = observer
        .and_then(|(model, state)| m.matching(model, state))
        .unwrap_or_else(|| Inverse::relaxed(m, u, y));
    match creep {
        None => alone(Running { model: *m, state }),
        Some(c) => with_creep(Running {
            model: Series(InverseCreep(c), *m),
            state: (c.state_at_rest(y), state),
        }),
    }
}

/// `m` alone or followed by the creep, relaxed at drive `u`, and its output there; the
/// creep's modes settled at the model's output (so it passes it through).
fn observing<M: Forward + Copy>(
    m: &M,
    creep: Option<Creep>,
    u: i32,
    alone: fn(Running<M>) -> ObserverRun,
    with_creep: fn(Running<Observing<M>>) -> ObserverRun,
) -> (ObserverRun, i32) {
    let (state, y) = Forward::relaxed(m, u);
    let run = match creep {
        None => alone(Running { model: *m, state }),
        Some(c) => with_creep(Running {
            model: Series(*m, c),
            state: (state, c.state_at_rest(y)),
        }),
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
        use CompensatorRun as C;
        use ObserverRun as O;
        match self {
            Self::None => C::None,
            Self::InversePi(m) => {
                let o = match observer {
                    O::Pi(o) => Some((&o.model, &o.state)),
                    O::PiCreep(o) => Some((&o.model.0, &o.state.0)),
                    _ => None,
                };
                compensating(m, o, creep, u, y, C::InversePi, C::InversePiCreep)
            }
            Self::InverseDuhem(m) => {
                let o = match observer {
                    O::Duhem(o) => Some((&o.model, &o.state)),
                    O::DuhemCreep(o) => Some((&o.model.0, &o.state.0)),
                    _ => None,
                };
                compensating(m, o, creep, u, y, C::InverseDuhem, C::InverseDuhemCreep)
            }
            Self::InverseGeneralisedPi(m) => {
                let o = match observer {
                    O::GeneralisedPi(o) => Some((&o.model, &o.state)),
                    O::GeneralisedPiCreep(o) => Some((&o.model.0, &o.state.0)),
                    _ => None,
                };
                let (alone, with_creep) = (C::InverseGeneralisedPi, C::InverseGeneralisedPiCreep);
                compensating(m, o, creep, u, y, alone, with_creep)
            }
            Self::InverseBoucWen(m) => {
                let o = match observer {
                    O::BoucWen(o) => Some((&o.model, &o.state)),
                    O::BoucWenCreep(o) => Some((&o.model.0, &o.state.0)),
                    _ => None,
                };
                compensating(m, o, creep, u, y, C::InverseBoucWen, C::InverseBoucWenCreep)
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
        use ObserverRun as O;
        match self {
            Self::None => (O::None, u),
            Self::Pi(m) => observing(m, creep, u, O::Pi, O::PiCreep),
            Self::Duhem(m) => observing(m, creep, u, O::Duhem, O::DuhemCreep),
            Self::GeneralisedPi(m) => {
                observing(m, creep, u, O::GeneralisedPi, O::GeneralisedPiCreep)
            }
            Self::BoucWen(m) => observing(m, creep, u, O::BoucWen, O::BoucWenCreep),
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
            Self::InversePiCreep(r) => r.step(y),
            Self::InverseDuhemCreep(r) => r.step(y),
            Self::InverseGeneralisedPiCreep(r) => r.step(y),
            Self::InverseBoucWenCreep(r) => r.step(y),
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
            Self::DuhemCreep(r) => r.step(u),
            Self::PiCreep(r) => r.step(u),
            Self::GeneralisedPiCreep(r) => r.step(u),
            Self::BoucWenCreep(r) => r.step(u),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::board::Hardware;
    use crate::config::settings::{representative_pi, Settings};
    use crate::models::creep::CreepParams;

    /// A P–I 8 compensator and observer with two creep modes, built as the board builds them.
    fn config() -> crate::control::ControlConfig {
        let pi = representative_pi(8).unwrap();
        Settings {
            compensator: Some(pi.clone()),
            observer: Some(pi),
            creep: Some(CreepParams::new(&[0.01, 0.1], &[0.02, 0.03]).unwrap()),
            ..Settings::default()
        }
        .build(&Hardware::driver_board(50_000.0))
        .unwrap()
    }

    #[test]
    fn creep_runs_in_series_before_the_inverse_and_after_the_forward_model() {
        let config = config();
        let (Compensator::InversePi(inverse), Observer::Pi(forward), Some(creep)) =
            (config.compensator, config.observer, config.creep)
        else {
            panic!("the settings build a P–I pair with creep");
        };
        let u0 = crate::fixed_point::signal_from_f64(0.25);
        let (mut observer, y0) = config.observer.prepare(config.creep, u0);
        let mut compensator = config.compensator.prepare(&observer, config.creep, u0, y0);
        // By hand: the observer relaxed at u0, the compensator's operators from the
        // observer's, both creeps settled at the observer's output.
        let mut fs = forward.state_at_rest(u0);
        assert_eq!(forward.step(&mut fs, u0), y0);
        let mut is = inverse.state_from_forward(&forward.bank().outputs(&fs));
        let (mut cf, mut ci) = (creep.state_at_rest(y0), creep.state_at_rest(y0));
        let mut moved = false;
        for k in 0..400 {
            let x = crate::fixed_point::signal_from_f64(0.8 * libm::sin(k as f64 * 0.05));
            let u = compensator.step(x);
            assert_eq!(
                u,
                inverse.step(&mut is, creep.inverse_step(&mut ci, x)),
                "tick {k}"
            );
            let y = observer.step(u);
            assert_eq!(
                y,
                creep.forward_step(&mut cf, forward.step(&mut fs, u)),
                "tick {k}"
            );
            moved |= u != x;
        }
        assert!(moved, "the compensator shapes the drive");
    }

    #[test]
    fn without_creep_a_model_runs_alone_and_without_a_model_creep_does_not_run() {
        let config = config();
        let u0 = 1 << 28;
        let (run, _) = config.observer.prepare(None, u0);
        let ObserverRun::Pi(mut r) = run else {
            panic!("a P–I observer, alone");
        };
        assert_eq!(r.model.cycles(), config.observer.cycles());
        let alone = config.compensator.prepare(&run, None, u0, r.step(u0));
        assert!(
            matches!(alone, CompensatorRun::InversePi(_)),
            "without creep the inverse runs alone: {alone:?}"
        );
        let (run, y) = Observer::None.prepare(config.creep, u0);
        assert_eq!((run, y), (ObserverRun::None, u0));
        assert_eq!(Observer::None.cycles(), 0);
        let mut none = Compensator::None.prepare(&run, config.creep, u0, y);
        assert_eq!(none.step(12_345), 12_345);
        // With creep, the series costs the model and the creep.
        let (run, y) = config.observer.prepare(config.creep, u0);
        let ObserverRun::PiCreep(r) = run else {
            panic!("a P–I observer and the creep");
        };
        let creep = config.creep.unwrap();
        assert_eq!(r.model.cycles(), config.observer.cycles() + creep.cycles());
        let CompensatorRun::InversePiCreep(c) =
            config.compensator.prepare(&run, config.creep, u0, y)
        else {
            panic!("the inverse creep and a P–I compensator");
        };
        assert_eq!(
            c.model.cycles(),
            config.compensator.cycles() + creep.cycles()
        );
    }
}
