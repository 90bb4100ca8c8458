//! How far the fixed-point models are from their `f64` reference, measured over a fixed,
//! seeded set of random models and inputs (the figures the README quotes).
//!
//! Errors are reported in LSB of a 16-bit output over the configured output range (forward
//! models) or input range (inverse models): `LSB16 = span / 65536`.
//!
//! Each row also carries the bound its arithmetic guarantees ([`AccuracyRow::bound_lsb16`]).
//! For the models built on a play-operator bank (P–I, generalised P–I), whose operators run on
//! a Q1.15 grid (one grid step is 1 LSB16): each operator's output is within 1.5 LSB16 of the
//! `f64` operator's — half a step for the rounded input (and the rounded initial state; a
//! whole step at +1, which the lane's top `1 − 2^-15` misses), half a step for the rounded
//! threshold; the play operator is 1-Lipschitz in both — so the sum is within `1.5·Σ|w_i|`
//! LSB16 (`Σ|w_i|` the bank's gain, from its Q8.24 weights), times the forward map's
//! largest slope for the generalised P–I observer, plus 0.05 LSB16 for the weights' and the
//! map's rounding. For the other models the fixed bounds of their scalar arithmetic: 0.1
//! LSB16 forward, 0.5 inverse.

use crate::reference;
use twinstack::fixed_point::{signal_from_f64 as q, signal_to_f64 as f};
use twinstack::models::bouc_wen::{BoucWen, InverseBoucWen};
use twinstack::models::creep::{Creep, CreepParams};
use twinstack::models::duhem::{Duhem, InverseDuhem};
use twinstack::models::generalised_pi::{
    DeadZoneParams, GeneralisedPi, GpiParams, InverseGeneralisedPi,
};
use twinstack::models::prandtl_ishlinskii::{InversePrandtlIshlinskii, PrandtlIshlinskii};
use twinstack::{BoucWenParams, DuhemParams, PiParams, Scaling, Thresholds};

/// One LSB of a 16-bit converter over the normalised range [-1, 1].
pub const LSB16: f64 = 2.0 / 65536.0;

/// One row of the accuracy table.
#[derive(Clone, Debug, PartialEq)]
pub struct AccuracyRow {
    /// Model and size, e.g. `inverse P–I, N = 16`.
    pub model: String,
    /// Largest |fixed − f64| seen, in LSB16.
    pub max_lsb16: f64,
    /// RMS |fixed − f64|, in LSB16.
    pub rms_lsb16: f64,
    /// Samples compared.
    pub samples: usize,
    /// The largest error the arithmetic allows for the models measured, in LSB16 (see the
    /// module doc).
    pub bound_lsb16: f64,
}

/// A small deterministic generator (xorshift64*), so the figures are reproducible.
struct Rng(u64);
impl Rng {
    fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    }
    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }
}

/// A random invertible P–I model over 0…150 V with `n` operators.
fn random_pi(rng: &mut Rng, n: usize) -> (PiParams, Scaling) {
    let r = Thresholds::Uniform.generate(n, 150.0).expect("n ≤ 32");
    let mut w = Vec::with_capacity(n);
    let mut sum = 0.0;
    for i in 0..n {
        let mut x = if i == 0 {
            rng.range(0.05, 0.2)
        } else {
            rng.range(-0.03, 0.1)
        };
        if sum + x < 0.3 * sum {
            x = x.abs();
        }
        sum += x;
        w.push(x);
    }
    let reach = w.iter().map(|x: &f64| x.abs()).sum::<f64>() * 150.0;
    (
        PiParams::new(0.0, 0.0, &r, &w).expect("lengths match"),
        Scaling::new(0.0, 150.0, -reach, reach).expect("non-empty"),
    )
}

/// A random generalised P–I over 0…150 V: [`random_pi`] with `n` operators, then a map
/// centred on the P–I's output range with three dead zones each side, at ±0.2, 0.4, 0.6 of
/// its reach, every slope between 0.3 and 1.8 (so the output stays within twice the reach,
/// the output range).
fn random_gpi(rng: &mut Rng, n: usize) -> (GpiParams, Scaling) {
    let (pi, s) = random_pi(rng, n);
    let reach = s.output_max;
    let thresholds = [-0.6, -0.4, -0.2, 0.2, 0.4, 0.6].map(|f| f * reach);
    let linear = rng.range(0.6, 1.2);
    let mut weights = [0.0; 6];
    // Outward from the centre on each side, each slope kept within [0.3, 1.8].
    for side in [[2usize, 1, 0], [3, 4, 5]] {
        let mut slope = linear;
        for j in side {
            let target = rng.range(0.3, 1.8);
            weights[j] = target - slope;
            slope = target;
        }
    }
    let map = DeadZoneParams::new(0.0, linear, &thresholds, &weights).expect("six dead zones");
    (
        GpiParams {
            pi,
            dead_zones: map,
        },
        Scaling::new(0.0, 150.0, -2.0 * reach, 2.0 * reach).expect("non-empty"),
    )
}

/// A bank's bound in LSB16: its gain `Σ|w_i|` (its Q8.24 weights) times 1.5 LSB16, how far
/// each operator may be from the `f64` one (see the module doc).
fn gain(bank: &twinstack::models::prandtl_ishlinskii::PlayOperatorBank) -> f64 {
    1.5 * (0..bank.operators())
        .map(|i| (bank.weight(i) as f64).abs() / (1u64 << 24) as f64)
        .sum::<f64>()
}

/// Slack for the weights' (Q8.24) and the dead-zone maps' rounding, LSB16.
const ROUNDING_SLACK: f64 = 0.05;

/// A random piecewise-linear drive (normalised) with full-range steps mixed in.
fn random_drive(rng: &mut Rng, samples: usize) -> Vec<f64> {
    let mut out = Vec::with_capacity(samples);
    let mut from = 0.0;
    while out.len() < samples {
        let to = if rng.uniform() < 0.1 {
            if rng.uniform() < 0.5 {
                -1.0
            } else {
                1.0
            }
        } else {
            rng.range(-1.0, 1.0)
        };
        let steps = 1 + (rng.uniform() * 200.0) as usize;
        for k in 1..=steps {
            out.push(from + (to - from) * k as f64 / steps as f64);
        }
        from = to;
    }
    out.truncate(samples);
    out
}

struct Stats {
    max: f64,
    sum_sq: f64,
    n: usize,
    bound: f64,
}
impl Stats {
    fn new() -> Self {
        Self {
            max: 0.0,
            sum_sq: 0.0,
            n: 0,
            bound: 0.0,
        }
    }
    /// A model measured into this row allows `bound` LSB16.
    fn allow(&mut self, bound: f64) {
        self.bound = self.bound.max(bound);
    }
    /// The fixed bound of a row of scalar arithmetic.
    fn fixed(mut self, bound: f64) -> Self {
        self.bound = bound;
        self
    }
    fn add(&mut self, err_norm: f64) {
        let e = err_norm.abs() / LSB16;
        self.max = self.max.max(e);
        self.sum_sq += e * e;
        self.n += 1;
    }
    fn row(self, model: String) -> AccuracyRow {
        AccuracyRow {
            model,
            max_lsb16: self.max,
            rms_lsb16: (self.sum_sq / self.n.max(1) as f64).sqrt(),
            samples: self.n,
            bound_lsb16: self.bound,
        }
    }
}

/// Measures fixed point against `f64` for forward and inverse P–I at N = 8, 16, 32, for
/// the Duhem and Bouc–Wen observers and compensators, for the forward and inverse
/// generalised P–I (N = 16, 6 dead zones) and for the creep operator and its inverse:
/// `models` random models × `samples` samples each.
pub fn measure(seed: u64, models: usize, samples: usize) -> Vec<AccuracyRow> {
    let mut rng = Rng(seed.max(1));
    let mut rows = Vec::new();
    for n in [8, 16, 32] {
        let mut fwd_stats = Stats::new();
        let mut inv_stats = Stats::new();
        for _ in 0..models {
            let (p, s) = random_pi(&mut rng, n);
            let drive = random_drive(&mut rng, samples);
            let fwd = PrandtlIshlinskii::new(&p, &s).expect("valid");
            fwd_stats.allow(gain(fwd.bank()) + ROUNDING_SLACK);
            let mut fs = fwd.state_at_rest(q(-1.0));
            let mut fr = reference::PrandtlIshlinskii::new(&p, &s, 0.0).expect("valid");
            // A random model whose inverse needs gains beyond Q8.24 is refused: skip it.
            let inv = InversePrandtlIshlinskii::new(&p, &s).ok();
            if let Some(i) = &inv {
                inv_stats.allow(gain(i.bank()) + ROUNDING_SLACK);
            }
            let y0 = fr.clone().step(0.0);
            let mut ir = reference::InversePrandtlIshlinskii::new(&p, &s, 0.0).expect("valid");
            let mut is = inv.map(|i| i.state_at_rest(q(s.output_to_norm(y0))));
            for &u in &drive {
                let y_ref = fr.step(s.norm_to_input(u));
                let y_fix = f(fwd.step(&mut fs, q(u)));
                fwd_stats.add(y_fix - s.output_to_norm(y_ref));
                if let (Some(inv), Some(st)) = (inv.as_ref(), is.as_mut()) {
                    let u_ref = s.input_to_norm(ir.step(y_ref));
                    let u_fix = f(inv.step(st, q(s.output_to_norm(y_ref))));
                    inv_stats.add(u_fix - u_ref);
                }
            }
        }
        rows.push(fwd_stats.row(format!("forward P–I, N = {n}")));
        rows.push(inv_stats.row(format!("inverse P–I, N = {n}")));
    }
    let mut obs = Stats::new();
    let mut comp = Stats::new();
    for _ in 0..models {
        let p = DuhemParams {
            alpha: rng.range(0.005, 0.05),
            beta: rng.range(0.05, 0.15),
            gamma: rng.range(0.04, 0.15),
            offset: 0.0,
        };
        let reach = p.beta * 150.0 + (p.gamma - p.beta).abs() / p.alpha + 1.0;
        let s = Scaling::new(0.0, 150.0, -reach, reach).expect("non-empty");
        let fwd = Duhem::new(&p, &s).expect("valid");
        let inv = InverseDuhem::new(&p, &s).expect("valid");
        let mut fs = fwd.state_at(q(-1.0), q(s.output_to_norm(0.0)));
        let mut fr = reference::Duhem::new(&p, &s, 0.0, 0.0).expect("valid");
        let mut is = fwd.state_at(q(-1.0), q(s.output_to_norm(0.0)));
        let mut ir = reference::InverseDuhem::new(&p, &s, 0.0, 0.0).expect("valid");
        let mut truth = reference::Duhem::new(&p, &s, 0.0, 0.0).expect("valid");
        for &u in &random_drive(&mut rng, samples) {
            let y_ref = fr.step(s.norm_to_input(u));
            obs.add(f(fwd.step(&mut fs, q(u))) - s.output_to_norm(y_ref));
            // Compensator: reachable setpoints from a smooth-enough truth response.
            let y_d = truth.step(s.norm_to_input(u));
            let u_ref = s.input_to_norm(ir.step(y_d));
            let u_fix = f(inv.step(&mut is, q(s.output_to_norm(y_d))));
            comp.add(u_fix - u_ref);
        }
    }
    rows.push(obs.fixed(0.1).row("Duhem observer".into()));
    rows.push(comp.fixed(0.5).row("inverse Duhem".into()));
    let mut fwd_stats = Stats::new();
    let mut inv_stats = Stats::new();
    for _ in 0..models {
        let (p, s) = random_gpi(&mut rng, 16);
        let drive = random_drive(&mut rng, samples);
        let fwd = GeneralisedPi::new(&p, &s).expect("valid");
        let steepest =
            p.dead_zones.linear + p.dead_zones.weights.iter().map(|g| g.abs()).sum::<f64>();
        fwd_stats.allow(gain(fwd.pi().bank()) * steepest + ROUNDING_SLACK);
        let mut fs = fwd.state_at_rest(q(-1.0));
        let mut fr = reference::GeneralisedPi::new(&p, &s, 0.0).expect("valid");
        // A random model whose inverse needs gains beyond Q8.24 is refused: skip it.
        let inv = InverseGeneralisedPi::new(&p, &s).ok();
        if let Some(i) = &inv {
            inv_stats.allow(gain(i.pi().bank()) + ROUNDING_SLACK);
        }
        let y0 = fr.clone().step(0.0);
        let mut ir = reference::InverseGeneralisedPi::new(&p, &s, 0.0).expect("valid");
        let mut is = inv.map(|i| i.state_at_rest(q(s.output_to_norm(y0))));
        for &u in &drive {
            let y_ref = fr.step(s.norm_to_input(u));
            fwd_stats.add(f(fwd.step(&mut fs, q(u))) - s.output_to_norm(y_ref));
            if let (Some(inv), Some(st)) = (inv.as_ref(), is.as_mut()) {
                let u_ref = s.input_to_norm(ir.step(y_ref));
                let u_fix = f(inv.step(st, q(s.output_to_norm(y_ref))));
                inv_stats.add(u_fix - u_ref);
            }
        }
    }
    rows.push(fwd_stats.row("forward generalised P–I, N = 16, 6 dead zones".into()));
    rows.push(inv_stats.row("inverse generalised P–I, N = 16, 6 dead zones".into()));
    let (fwd, inv) = measure_creep(&mut rng, models, samples, Schedule::EveryTick);
    rows.push(fwd);
    rows.push(inv);
    let (obs, comp) = bouc_wen(&mut rng, models, samples);
    let (fwd, inv) = measure_creep(&mut rng, models, samples, Schedule::TakingTurns);
    rows.push(fwd);
    rows.push(inv);
    rows.push(obs.fixed(0.1).row("Bouc-Wen observer".into()));
    rows.push(comp.fixed(0.5).row("inverse Bouc-Wen".into()));
    rows
}

/// How the creep's modes update in [`measure_creep`]: the first mode's time constant decides.
#[derive(Clone, Copy, PartialEq)]
enum Schedule {
    /// From 2 to 20 ticks: every mode every tick.
    EveryTick,
    /// From 80 to 2 000 ticks: the modes take turns.
    TakingTurns,
}

/// The creep operator (4 random modes, from 2 ticks (every tick) or 80 ticks (taking turns)
/// up to 2^26 ticks, weights summing to up to 0.9) forward, and its inverse fed the `f64`
/// forward output, against the `f64` reference.
fn measure_creep(
    rng: &mut Rng,
    models: usize,
    samples: usize,
    schedule: Schedule,
) -> (AccuracyRow, AccuracyRow) {
    let rate = 50_000.0;
    let mut fwd_stats = Stats::new();
    let mut inv_stats = Stats::new();
    // The first mode's time constant and the spacing, in ticks (the slowest stays within
    // 2^26 ticks).
    let (first, spacing, name) = match schedule {
        Schedule::EveryTick => ((2.0, 20.0), 60.0, "4 modes"),
        Schedule::TakingTurns => ((80.0, 2000.0), 30.0, "4 modes taking turns"),
    };
    for _ in 0..models {
        let mut taus = Vec::new();
        let mut ticks = rng.range(first.0, first.1);
        for _ in 0..4 {
            taus.push(ticks / rate);
            ticks *= rng.range(4.0, spacing);
        }
        let raw: Vec<f64> = (0..4).map(|_| rng.uniform()).collect();
        let total = rng.range(0.05, 0.9) / raw.iter().sum::<f64>();
        let weights: Vec<f64> = raw.iter().map(|w| w * total * 0.999).collect();
        let p = CreepParams::new(&taus, &weights).expect("4 modes");
        let fixed = Creep::new(&p, rate).expect("valid");
        assert_eq!(fixed.takes_turns(), schedule == Schedule::TakingTurns);
        let drive = random_drive(rng, samples);
        let y0 = drive.first().copied().unwrap_or(0.0);
        let (mut fs, mut is) = (fixed.state_at_rest(q(y0)), fixed.state_at_rest(q(y0)));
        let mut fr = reference::Creep::new(&p, rate, y0).expect("valid");
        let mut ir = reference::Creep::new(&p, rate, y0).expect("valid");
        for &y in &drive {
            let x_ref = fr.step(y);
            fwd_stats.add(f(fixed.forward_step(&mut fs, q(y))) - x_ref);
            let y_ref = ir.inverse_step(x_ref);
            inv_stats.add(f(fixed.inverse_step(&mut is, q(x_ref))) - y_ref);
        }
    }
    (
        fwd_stats.fixed(0.1).row(format!("creep, {name}")),
        inv_stats.fixed(0.5).row(format!("inverse creep, {name}")),
    )
}

/// A random bounded Bouc–Wen over 0…150 V (`|γ| ≤ 0.4 β`, `|ψ| ≤ 0.7 (β − |γ|)`,
/// `|χ| ≤ 0.7 (β − |γ| − |ψ|)`, either sign of `A`, the compensator's loop gain below 0.85),
/// with an output range holding `k·u + δ` and the state bound.
fn random_bouc_wen(rng: &mut Rng) -> (BoucWenParams, Scaling) {
    let k = rng.range(0.05, 0.15);
    let beta = rng.range(0.005, 0.05);
    let gamma = rng.range(-0.4, 0.4) * beta;
    let mut p = BoucWenParams {
        k,
        offset: 0.0,
        a: 0.0,
        beta,
        gamma,
        psi: rng.range(-0.7, 0.7) * (beta - gamma.abs()),
        chi: 0.0,
    };
    p.chi = rng.range(-0.7, 0.7) * (beta - gamma.abs() - p.psi.abs());
    p.a = rng.range(-0.85, 0.85) * k / (1.0 + p.max_factor() / p.min_factor());
    // |h| ≤ |A|·max(1/c_min, 2U) in output units (U = 75 V).
    let h = p.a.abs() * (1.0 / p.min_factor()).max(150.0);
    let reach = k * 150.0 + h + 1.0;
    (
        p,
        Scaling::new(0.0, 150.0, -reach, reach).expect("non-empty"),
    )
}

/// The Bouc–Wen observer and compensator against their `f64`
/// reference, as for Duhem: the compensator is fed the reference model's output on a random
/// drive (reachable setpoints).
fn bouc_wen(rng: &mut Rng, models: usize, samples: usize) -> (Stats, Stats) {
    let mut obs = Stats::new();
    let mut comp = Stats::new();
    for _ in 0..models {
        let (p, s) = random_bouc_wen(rng);
        let fwd = BoucWen::new(&p, &s).expect("valid");
        let inv = InverseBoucWen::new(&p, &s).expect("valid");
        let mut fs = fwd.relaxed(q(-1.0));
        let mut fr = reference::BoucWen::new(&p, &s, 0.0).expect("valid");
        let mut is = fwd.relaxed(q(-1.0));
        let mut ir = reference::InverseBoucWen::new(&p, &s, 0.0).expect("valid");
        let mut truth = reference::BoucWen::new(&p, &s, 0.0).expect("valid");
        for &u in &random_drive(rng, samples) {
            let y_ref = fr.step(s.norm_to_input(u));
            obs.add(f(fwd.step(&mut fs, q(u))) - s.output_to_norm(y_ref));
            let y_d = truth.step(s.norm_to_input(u));
            let u_ref = s.input_to_norm(ir.step(y_d));
            let u_fix = f(inv.step(&mut is, q(s.output_to_norm(y_d))));
            comp.add(u_fix - u_ref);
        }
    }
    (obs, comp)
}
