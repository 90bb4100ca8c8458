//! The compensator and the observer a configuration picks, and what the tick runs of them:
//! one enum over the models each, static dispatch (a `match`, no `dyn`: the interrupt
//! branches through no register, and the whole-interrupt bench's walk of its call graph
//! checks it).
//!
//! The configuration's enums ([`Compensator`], [`Observer`]) hold the models; the tick's
//! ([`InverseRun`], [`ForwardRun`]) hold each model with its state ([`Running`]), one tag per
//! tick. The stage's creep is composed in series by a wrapper, once for every model: the
//! compensator ([`CompensatorRun`]) runs the inverse creep, where the configuration has one,
//! then the inverse model; the observer ([`ObserverRun`]) the forward model, then the creep.
//! A model is written once, and the creep's step once in the tick (written out into each
//! model's variant, it cost the board image about 1 KiB of flash).

use crate::models::bouc_wen::{BoucWen, InverseBoucWen};
use crate::models::creep::{Creep, InverseCreep};
use crate::models::duhem::{Duhem, InverseDuhem};
use crate::models::generalised_pi::{GeneralisedPi, InverseGeneralisedPi};
use crate::models::prandtl_ishlinskii::{InversePrandtlIshlinskii, PrandtlIshlinskii};
use crate::models::{Forward, Hysteresis, Inverse, Rest, Running};

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

/// The inverse model as the tick runs it, with its state (one tag per tick).
// The order of the variants is the tag the tick's dispatch compares: the reference model first.
#[allow(clippy::large_enum_variant)] // no heap: the controllers live in statics
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InverseRun {
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
}

/// The forward model as the tick runs it, with its state (see [`InverseRun`]).
#[allow(clippy::large_enum_variant)] // as for `InverseRun`
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ForwardRun {
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
}

/// The compensator as the tick runs it: the inverse creep (where the stage has creep and the
/// configuration a model), then the inverse model — setpoint → C⁻¹ → H⁻¹ → drive.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CompensatorRun {
    /// The inverse creep and its state; `None` without creep or without a model.
    pub creep: Option<Running<InverseCreep>>,
    /// The inverse model and its state.
    pub model: InverseRun,
}

/// The observer as it runs (see [`CompensatorRun`]): the forward model, then the creep
/// (where the stage has creep and the configuration a model) — drive → H → C → displacement.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ObserverRun {
    /// The forward model and its state.
    pub model: ForwardRun,
    /// The creep and its state; `None` without creep or without a model.
    pub creep: Option<Running<Creep>>,
}

impl CompensatorRun {
    /// No compensation (bypass): the drive is the setpoint.
    pub const NONE: Self = Self {
        creep: None,
        model: InverseRun::None,
    };

    /// Whether there is no model: the drive is the setpoint.
    pub fn is_bypass(&self) -> bool {
        matches!(self.model, InverseRun::None)
    }

    /// One tick: desired displacement `y` (Q2.30) → drive (Q2.30); without a model, `y`.
    #[inline(always)]
    pub fn step(&mut self, y: i32) -> i32 {
        let x = match &mut self.creep {
            Some(c) => c.step(y),
            None => y,
        };
        self.model.step(x)
    }
}

impl ObserverRun {
    /// No observer: the estimate reads 0.
    pub const NONE: Self = Self {
        model: ForwardRun::None,
        creep: None,
    };

    /// One tick: applied drive `u` (Q2.30) → estimated displacement (Q2.30); without a
    /// model, 0.
    #[inline(always)]
    pub fn step(&mut self, u: i32) -> i32 {
        let y = self.model.step(u);
        match &mut self.creep {
            Some(c) => c.step(y),
            None => y,
        }
    }
}

impl Compensator {
    /// What the tick runs of it, after `creep` (not applied without a model), its state from
    /// `observer`'s (prepared first) where that runs the model this inverts, else at rest
    /// (`rest`) at drive `u` with the stage at `y`; the creep's modes settled at `y` (where
    /// the models rest, so it passes `y` through). Off the tick.
    pub fn prepare(
        &self,
        observer: &ObserverRun,
        creep: Option<Creep>,
        u: i32,
        y: i32,
        rest: Rest,
    ) -> CompensatorRun {
        use ForwardRun as F;
        use InverseRun as I;
        let model = match (self, &observer.model) {
            (Self::None, _) => return CompensatorRun::NONE,
            (Self::InversePi(m), F::Pi(o)) => I::InversePi(inverse(m, Some(o), u, y, rest)),
            (Self::InversePi(m), _) => I::InversePi(inverse(m, None, u, y, rest)),
            (Self::InverseDuhem(m), F::Duhem(o)) => {
                I::InverseDuhem(inverse(m, Some(o), u, y, rest))
            }
            (Self::InverseDuhem(m), _) => I::InverseDuhem(inverse(m, None, u, y, rest)),
            (Self::InverseGeneralisedPi(m), F::GeneralisedPi(o)) => {
                I::InverseGeneralisedPi(inverse(m, Some(o), u, y, rest))
            }
            (Self::InverseGeneralisedPi(m), _) => {
                I::InverseGeneralisedPi(inverse(m, None, u, y, rest))
            }
            (Self::InverseBoucWen(m), F::BoucWen(o)) => {
                I::InverseBoucWen(inverse(m, Some(o), u, y, rest))
            }
            (Self::InverseBoucWen(m), _) => I::InverseBoucWen(inverse(m, None, u, y, rest)),
        };
        CompensatorRun {
            creep: creep.map(|c| Running {
                model: InverseCreep(c),
                state: c.state_at_rest(y),
            }),
            model,
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

    /// Whether the model computes in floating point ([`Hysteresis::uses_fpu`]); `false`
    /// without a model.
    pub fn uses_fpu(&self) -> bool {
        match self {
            Self::None => false,
            Self::InversePi(m) => m.uses_fpu(),
            Self::InverseDuhem(m) => m.uses_fpu(),
            Self::InverseGeneralisedPi(m) => m.uses_fpu(),
            Self::InverseBoucWen(m) => m.uses_fpu(),
        }
    }
}

/// `m` with its state: matched to the observer's where that runs the model `m` inverts,
/// else at rest (`rest`) at drive `u` with the stage at `y`.
fn inverse<M: Inverse + Copy>(
    m: &M,
    observer: Option<&Running<M::Forward>>,
    u: i32,
    y: i32,
    rest: Rest,
) -> Running<M> {
    let state = observer
        .and_then(|o| m.matching(&o.model, &o.state))
        .unwrap_or_else(|| Inverse::at_rest(m, u, y, rest));
    Running { model: *m, state }
}

/// `m` at rest (`rest`) at drive `u`, and its output there.
fn forward<M: Forward + Copy>(m: &M, u: i32, rest: Rest) -> (Running<M>, i32) {
    let (state, y) = Forward::at_rest(m, u, rest);
    (Running { model: *m, state }, y)
}

impl Observer {
    /// What the tick runs of it, followed by `creep` (not applied without a model), at rest
    /// (`rest`) at drive `u`, the creep's modes settled at the model's output (so it passes
    /// it through); and its estimate there (`u` without a model). Off the tick.
    pub fn prepare(&self, creep: Option<Creep>, u: i32, rest: Rest) -> (ObserverRun, i32) {
        use ForwardRun as F;
        let (model, y) = match self {
            Self::None => return (ObserverRun::NONE, u),
            Self::Pi(m) => {
                let (r, y) = forward(m, u, rest);
                (F::Pi(r), y)
            }
            Self::Duhem(m) => {
                let (r, y) = forward(m, u, rest);
                (F::Duhem(r), y)
            }
            Self::GeneralisedPi(m) => {
                let (r, y) = forward(m, u, rest);
                (F::GeneralisedPi(r), y)
            }
            Self::BoucWen(m) => {
                let (r, y) = forward(m, u, rest);
                (F::BoucWen(r), y)
            }
        };
        let creep = creep.map(|c| Running {
            model: c,
            state: c.state_at_rest(y),
        });
        (ObserverRun { model, creep }, y)
    }

    /// The estimate after the drive has rested at `u` with the history `rest` (`u` without a
    /// model). Off the tick.
    pub fn output_at_rest(&self, u: i32, rest: Rest) -> i32 {
        match self {
            Self::None => u,
            Self::Pi(m) => Forward::at_rest(m, u, rest).1,
            Self::Duhem(m) => Forward::at_rest(m, u, rest).1,
            Self::GeneralisedPi(m) => Forward::at_rest(m, u, rest).1,
            Self::BoucWen(m) => Forward::at_rest(m, u, rest).1,
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

impl InverseRun {
    /// One tick of the model: `x` (Q2.30) → drive (Q2.30); without a model, `x`. The
    /// integer models inline into the tick; the floating-point ones (Duhem, Bouc–Wen) are
    /// called ([`Running::step_out_of_line`]), so that the tick of any other configuration
    /// never touches the FPU.
    #[inline(always)]
    pub fn step(&mut self, x: i32) -> i32 {
        match self {
            Self::InversePi(r) => r.step(x),
            Self::InverseDuhem(r) => r.step_out_of_line(x),
            Self::None => x,
            Self::InverseGeneralisedPi(r) => r.step(x),
            Self::InverseBoucWen(r) => r.step_out_of_line(x),
        }
    }
}

impl ForwardRun {
    /// One tick of the model: drive `u` (Q2.30) → its output (Q2.30); without a model, 0.
    /// Every model inline: the services run it on a batch of snapshots at once, below the
    /// tick, where a call per snapshot would cost more than the floating-point context their
    /// task saves once a batch.
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
        let (mut observer, y0) = config.observer.prepare(config.creep, u0, Rest::Ascending);
        let mut compensator =
            config
                .compensator
                .prepare(&observer, config.creep, u0, y0, Rest::Ascending);
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
        let (mut run, _) = config.observer.prepare(None, u0, Rest::Ascending);
        assert!(
            matches!(run.model, ForwardRun::Pi(_)) && run.creep.is_none(),
            "a P–I observer, alone: {run:?}"
        );
        let y = run.step(u0);
        let alone = config
            .compensator
            .prepare(&run, None, u0, y, Rest::Ascending);
        assert!(
            matches!(alone.model, InverseRun::InversePi(_)) && alone.creep.is_none(),
            "without creep the inverse runs alone: {alone:?}"
        );
        assert!(!alone.is_bypass());
        let (run, y) = Observer::None.prepare(config.creep, u0, Rest::Ascending);
        assert_eq!((run, y), (ObserverRun::NONE, u0));
        assert_eq!(Observer::None.cycles(), 0);
        let mut none = Compensator::None.prepare(&run, config.creep, u0, y, Rest::Ascending);
        assert_eq!(none, CompensatorRun::NONE, "no creep without a model");
        assert!(none.is_bypass());
        assert_eq!(none.step(12_345), 12_345);
        // With creep, both wrap it.
        let (run, y) = config.observer.prepare(config.creep, u0, Rest::Ascending);
        assert!(matches!(run.model, ForwardRun::Pi(_)) && run.creep.is_some());
        let c = config
            .compensator
            .prepare(&run, config.creep, u0, y, Rest::Ascending);
        assert!(matches!(c.model, InverseRun::InversePi(_)) && c.creep.is_some());
    }
}
