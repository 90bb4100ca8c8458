//! `f64` reference implementations of every model, in physical units (volts in, output units
//! out). They are the specification the fixed-point code is checked against: same equations,
//! same clamps, no quantisation. They allocate nothing, but are not meant for the tick: they
//! live here, on the host, and not in the firmware's library.

use twinstack::models::creep::CreepParams;
use twinstack::models::generalised_pi::{DeadZoneParams, GpiParams};
use twinstack::models::params::{
    BoucWenParams, CanonicalPi, DuhemParams, ParamError, PiParams, MAX_CANONICAL_OPERATORS,
};
use twinstack::models::Rest;
use twinstack::scaling::Scaling;

/// Play operator: `max(u − r, min(u + r, p))`.
pub fn play(u: f64, r: f64, p: f64) -> f64 {
    (u - r).max((u + r).min(p))
}

fn clamp(x: f64, lo: f64, hi: f64) -> f64 {
    x.max(lo).min(hi)
}

/// Weighted sum of play operators with its states, in `f64`.
#[derive(Clone, Debug, PartialEq)]
pub struct PlaySum {
    model: CanonicalPi,
    states: heapless::Vec<f64, { MAX_CANONICAL_OPERATORS }>,
}

impl PlaySum {
    fn with_states(
        model: CanonicalPi,
        states: heapless::Vec<f64, { MAX_CANONICAL_OPERATORS }>,
    ) -> Self {
        Self { model, states }
    }

    /// At rest at `u0` on the ascending branch of the input range `lo … hi` (the library's
    /// `state_at_rest`): the input went to `hi`, down to `lo`, then up to `u0`.
    fn at_rest(model: CanonicalPi, lo: f64, hi: f64, u0: f64) -> Self {
        let states = model
            .thresholds
            .iter()
            .map(|&r| play(u0, r, (lo + r).min((hi - r).max(lo))))
            .collect();
        Self::with_states(model, states)
    }

    /// At rest at `u0` with the history `rest`: [`PlaySum::at_rest`], or every operator at
    /// `u0` ([`Rest::Relaxed`], the library's `state_at`).
    fn resting(model: CanonicalPi, lo: f64, hi: f64, u0: f64, rest: Rest) -> Self {
        match rest {
            Rest::Ascending => Self::at_rest(model, lo, hi, u0),
            Rest::Relaxed => {
                let states = model.thresholds.iter().map(|_| u0).collect();
                Self::with_states(model, states)
            }
        }
    }

    fn step(&mut self, x: f64) -> f64 {
        let mut sum = 0.0;
        for ((&r, &w), p) in self
            .model
            .thresholds
            .iter()
            .zip(self.model.weights.iter())
            .zip(self.states.iter_mut())
        {
            *p = play(x, r, *p);
            sum += w * *p;
        }
        sum
    }

    /// Operator states `p_i`.
    pub fn states(&self) -> &[f64] {
        &self.states
    }

    /// The model (thresholds, weights, offset).
    pub fn model(&self) -> &CanonicalPi {
        &self.model
    }
}

/// Forward P–I, `f64`: `y = c + Σ w_i P_{r_i}[u]`, input clamped to the input range.
#[derive(Clone, Debug, PartialEq)]
pub struct PrandtlIshlinskii {
    sum: PlaySum,
    scaling: Scaling,
}

impl PrandtlIshlinskii {
    /// The model `params`, at rest at input `u0` (volts) on the ascending branch: the drive
    /// went to the top of the input range, down to its bottom, then up to `u0`.
    pub fn new(params: &PiParams, scaling: &Scaling, u0: f64) -> Result<Self, ParamError> {
        Self::with_rest(params, scaling, u0, Rest::Ascending)
    }

    /// The model `params` at rest at input `u0` (volts) with the history `rest`.
    pub fn with_rest(
        params: &PiParams,
        scaling: &Scaling,
        u0: f64,
        rest: Rest,
    ) -> Result<Self, ParamError> {
        let u0 = clamp(u0, scaling.input_min, scaling.input_max);
        Ok(Self {
            sum: PlaySum::resting(
                params.canonical()?,
                scaling.input_min,
                scaling.input_max,
                u0,
                rest,
            ),
            scaling: *scaling,
        })
    }

    /// One sample: drive `u` (volts) → displacement (output units).
    pub fn step(&mut self, u: f64) -> f64 {
        let u = clamp(u, self.scaling.input_min, self.scaling.input_max);
        self.sum.model.offset + self.sum.step(u)
    }

    /// Operators and their states.
    pub fn operators(&self) -> &PlaySum {
        &self.sum
    }
}

/// Inverse P–I, `f64`: `u = Σ w'_i P_{r'_i}[y_d − c]`, desired output clamped to the output range.
#[derive(Clone, Debug, PartialEq)]
pub struct InversePrandtlIshlinskii {
    sum: PlaySum,
    scaling: Scaling,
}

impl InversePrandtlIshlinskii {
    /// The inverse of `params`, at rest at drive `u0` (volts): the state matching the forward
    /// model at rest at `u0` ([`PrandtlIshlinskii::new`]), `p'_i = S_i p_i + Σ_{j>i} w_j p_j`
    /// with `S_i = Σ_{j≤i} w_j` (the library reaches the same state another way: the
    /// forward's major-loop bottom mapped, then raised to the desired output).
    pub fn new(params: &PiParams, scaling: &Scaling, u0: f64) -> Result<Self, ParamError> {
        Self::with_rest(params, scaling, u0, Rest::Ascending)
    }

    /// The inverse of `params`, matching the forward model at rest at drive `u0` (volts) with
    /// the history `rest` ([`PrandtlIshlinskii::with_rest`]).
    pub fn with_rest(
        params: &PiParams,
        scaling: &Scaling,
        u0: f64,
        rest: Rest,
    ) -> Result<Self, ParamError> {
        let forward = params.canonical()?;
        let inverse = forward.inverse()?;
        let u0 = clamp(u0, scaling.input_min, scaling.input_max);
        let p = PlaySum::resting(
            forward.clone(),
            scaling.input_min,
            scaling.input_max,
            u0,
            rest,
        );
        let (w, p) = (&forward.weights, p.states());
        let states = (0..w.len())
            .map(|i| {
                let s_i: f64 = w[..=i].iter().sum();
                s_i * p[i]
                    + w[i + 1..]
                        .iter()
                        .zip(&p[i + 1..])
                        .map(|(a, b)| a * b)
                        .sum::<f64>()
            })
            .collect();
        Ok(Self {
            sum: PlaySum::with_states(inverse, states),
            scaling: *scaling,
        })
    }

    /// One sample: desired displacement (output units) → drive (volts, not clamped).
    pub fn step(&mut self, y: f64) -> f64 {
        let y = clamp(y, self.scaling.output_min, self.scaling.output_max);
        self.sum.step(y - self.sum.model.offset)
    }

    /// Operators and their states.
    pub fn operators(&self) -> &PlaySum {
        &self.sum
    }
}

/// The one-sided dead-zone map, `f64`, written out from its definition:
/// `c + g_0 (z − c) + Σ g_j S_{d_j}(z − c)`, `S_d(x) = max(x − d, 0)` (`d > 0`), `min(x − d, 0)`
/// (`d < 0`).
pub fn dead_zone_map(m: &DeadZoneParams, z: f64) -> f64 {
    let x = z - m.centre;
    let mut y = m.centre + m.linear * x;
    for (&d, &g) in m.thresholds.iter().zip(m.weights.iter()) {
        y += g * if d > 0.0 {
            (x - d).max(0.0)
        } else {
            (x - d).min(0.0)
        };
    }
    y
}

/// The inverse of [`dead_zone_map`] found numerically (bisection to the last bit of an `f64`),
/// independent of the library's closed form. The map must be increasing (validated).
pub fn dead_zone_map_inverse(m: &DeadZoneParams, y: f64) -> f64 {
    // The map's slopes are positive, so it leaves every bracket; widen until y is inside.
    let (mut lo, mut hi) = (m.centre - 1.0, m.centre + 1.0);
    let mut width = 1.0;
    while dead_zone_map(m, lo) > y && width < 1e300 {
        width *= 2.0;
        lo = m.centre - width;
    }
    width = 1.0;
    while dead_zone_map(m, hi) < y && width < 1e300 {
        width *= 2.0;
        hi = m.centre + width;
    }
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if mid == lo || mid == hi {
            break;
        }
        if dead_zone_map(m, mid) < y {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// Forward generalised P–I, `f64`: `y = S[PI[u]]` (the P–I reference, then [`dead_zone_map`]).
#[derive(Clone, Debug, PartialEq)]
pub struct GeneralisedPi {
    pi: PrandtlIshlinskii,
    map: DeadZoneParams,
}

impl GeneralisedPi {
    /// The model `params`, at rest at input `u0` (volts).
    pub fn new(params: &GpiParams, scaling: &Scaling, u0: f64) -> Result<Self, ParamError> {
        Self::with_rest(params, scaling, u0, Rest::Ascending)
    }

    /// The model `params`, at rest at input `u0` (volts) with the history `rest`.
    pub fn with_rest(
        params: &GpiParams,
        scaling: &Scaling,
        u0: f64,
        rest: Rest,
    ) -> Result<Self, ParamError> {
        params.validate()?;
        Ok(Self {
            pi: PrandtlIshlinskii::with_rest(&params.pi, scaling, u0, rest)?,
            map: params.dead_zones.clone(),
        })
    }

    /// One sample: drive `u` (volts) → displacement (output units).
    pub fn step(&mut self, u: f64) -> f64 {
        dead_zone_map(&self.map, self.pi.step(u))
    }
}

/// Inverse generalised P–I, `f64`: `u = PI⁻¹[S⁻¹[y_d]]`, the map inverted numerically
/// ([`dead_zone_map_inverse`]), the desired output clamped to the output range (as the
/// fixed-point compensator clamps it to ±1), and so is the P–I's desired output.
#[derive(Clone, Debug, PartialEq)]
pub struct InverseGeneralisedPi {
    pi: InversePrandtlIshlinskii,
    map: DeadZoneParams,
    scaling: Scaling,
}

impl InverseGeneralisedPi {
    /// The inverse of `params`, its P–I part at rest as [`InversePrandtlIshlinskii::new`] puts it.
    pub fn new(params: &GpiParams, scaling: &Scaling, u0: f64) -> Result<Self, ParamError> {
        Self::with_rest(params, scaling, u0, Rest::Ascending)
    }

    /// The inverse of `params`, its P–I part as [`InversePrandtlIshlinskii::with_rest`] puts it.
    pub fn with_rest(
        params: &GpiParams,
        scaling: &Scaling,
        u0: f64,
        rest: Rest,
    ) -> Result<Self, ParamError> {
        params.validate()?;
        Ok(Self {
            pi: InversePrandtlIshlinskii::with_rest(&params.pi, scaling, u0, rest)?,
            map: params.dead_zones.clone(),
            scaling: *scaling,
        })
    }

    /// The P–I part's input `z = S⁻¹[y]` for a desired output `y` (output units, clamped).
    pub fn map_inverse(&self, y: f64) -> f64 {
        let y = clamp(y, self.scaling.output_min, self.scaling.output_max);
        dead_zone_map_inverse(&self.map, y)
    }

    /// One sample: desired displacement (output units) → drive (volts, not clamped).
    pub fn step(&mut self, y: f64) -> f64 {
        let z = self.map_inverse(y);
        self.pi.step(z)
    }
}

/// The exact relaxation over an input step `m ≥ 0` at rate `c`: `q = 1 − e^{−c·m}` and
/// `φ = q/c` (`c > 0`), as `twinstack::models::relaxation` computes them.
pub fn relax(c: f64, m: f64) -> (f64, f64) {
    let q = -libm::expm1(-c * m);
    (q, q / c)
}

/// The step `m ≥ 0` (at most `cap`) with `k·m + d·q(c·m) = target`: the linear guess and one
/// Halley step, slopes floored at `floor`, as `RelaxationRate::solve` in the library.
pub fn solve(c: f64, k: f64, d: f64, floor: f64, target: f64, cap: f64) -> f64 {
    let m0 = (target / (k + c * d).max(floor)).min(cap);
    let q0 = relax(c, m0).0;
    let miss = k * m0 + d * q0 - target;
    let slope = (k + c * d * (1.0 - q0)).max(floor);
    let bend = -c * c * d * (1.0 - q0);
    let square = slope * slope;
    let denominator = (square - 0.5 * miss * bend).max(0.5 * square);
    (m0 - miss * slope / denominator).clamp(0.0, cap)
}

/// Forward Duhem, `f64`: `ẏ = α|u̇|(βu + δ − y) + γu̇` integrated exactly over each sample's
/// (monotone) step of the input ([`Duhem::step`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Duhem {
    params: DuhemParams,
    scaling: Scaling,
    /// Previous input, volts.
    pub u: f64,
    /// Previous output, output units.
    pub y: f64,
}

impl Duhem {
    /// The model `params` starting at input `u0` (volts) and output `y0`.
    pub fn new(
        params: &DuhemParams,
        scaling: &Scaling,
        u0: f64,
        y0: f64,
    ) -> Result<Self, ParamError> {
        params.validate()?;
        Ok(Self {
            params: *params,
            scaling: *scaling,
            u: clamp(u0, scaling.input_min, scaling.input_max),
            y: y0,
        })
    }

    /// The model `params` at rest at input `u0` (volts): on the anhysteretic curve at the
    /// range's top, then the drive history of [`rest_history`], as the library's
    /// `Duhem::state_at_rest`.
    pub fn at_rest(params: &DuhemParams, scaling: &Scaling, u0: f64) -> Result<Self, ParamError> {
        Self::with_rest(params, scaling, u0, Rest::Ascending)
    }

    /// The model `params` at rest at input `u0` (volts) with the history `rest`:
    /// [`Duhem::at_rest`], or on the anhysteretic curve ([`Rest::Relaxed`]).
    pub fn with_rest(
        params: &DuhemParams,
        scaling: &Scaling,
        u0: f64,
        rest: Rest,
    ) -> Result<Self, ParamError> {
        if rest == Rest::Relaxed {
            let u0 = clamp(u0, scaling.input_min, scaling.input_max);
            return Self::new(params, scaling, u0, params.beta * u0 + params.offset);
        }
        let top = scaling.input_max;
        let mut m = Self::new(params, scaling, top, params.beta * top + params.offset)?;
        rest_history(scaling, u0, |v| {
            m.step(v);
        });
        Ok(m)
    }

    /// One sample: drive (volts) → displacement (output units): the exact relaxation over
    /// the step, `y += β·Δu + q·e − s·(β − γ)·q/α`, `q = 1 − e^{−α|Δu|}`, `e = βu + δ − y`.
    pub fn step(&mut self, u: f64) -> f64 {
        let u = clamp(u, self.scaling.input_min, self.scaling.input_max);
        let du = u - self.u;
        let p = &self.params;
        let (q, phi) = relax(p.alpha, du.abs());
        let e = p.beta * self.u + p.offset - self.y;
        self.y += p.beta * du + q * e - du.signum() * (p.beta - p.gamma) * phi;
        self.u = u;
        self.y
    }

    /// Exact solution of the continuous Duhem model for a monotone input from `(u0, y0)` to
    /// `u` (output units): `y = βu + δ + s(γ−β)/α + (y0 − βu0 − δ − s(γ−β)/α)·e^{−α|u−u0|}`.
    pub fn closed_form_monotone(p: &DuhemParams, u0: f64, y0: f64, u: f64) -> f64 {
        let s = if u >= u0 { 1.0 } else { -1.0 };
        let shift = s * (p.gamma - p.beta) / p.alpha;
        p.beta * u
            + p.offset
            + shift
            + (y0 - p.beta * u0 - p.offset - shift) * libm::exp(-p.alpha * (u - u0).abs())
    }
}

/// Inverse Duhem, `f64`: the same construction as the fixed-point compensator (the linear
/// guess over the slope floored at `min(β, γ)/16`, one Halley step on the exact relaxation,
/// the step capped at `0.99/α`, the drive clamped to the input range).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InverseDuhem {
    model: Duhem,
}

impl InverseDuhem {
    /// The compensator for `params`, its model starting at `(u0, y0)`.
    pub fn new(
        params: &DuhemParams,
        scaling: &Scaling,
        u0: f64,
        y0: f64,
    ) -> Result<Self, ParamError> {
        Ok(Self {
            model: Duhem::new(params, scaling, u0, y0)?,
        })
    }

    /// The compensator for `params`, its model as [`Duhem::with_rest`] puts it.
    pub fn with_rest(
        params: &DuhemParams,
        scaling: &Scaling,
        u0: f64,
        rest: Rest,
    ) -> Result<Self, ParamError> {
        Ok(Self {
            model: Duhem::with_rest(params, scaling, u0, rest)?,
        })
    }

    /// One sample: desired displacement (output units) → drive (volts).
    pub fn step(&mut self, y_desired: f64) -> f64 {
        let s = &self.model.scaling;
        let dy = clamp(y_desired, s.output_min, s.output_max) - self.model.y;
        if dy == 0.0 {
            return self.model.u;
        }
        let p = &self.model.params;
        let e = p.beta * self.model.u + p.offset - self.model.y;
        let sign = dy.signum();
        let m = solve(
            p.alpha,
            p.beta,
            (p.gamma - p.beta) / p.alpha + sign * e,
            p.beta.min(p.gamma) / 16.0,
            dy.abs(),
            (0.99 / p.alpha).min(2.0 * s.input_half_span()),
        );
        let u = clamp(self.model.u + sign * m, s.input_min, s.input_max);
        self.model.step(u);
        u
    }

    /// The compensator's internal forward model.
    pub fn model(&self) -> &Duhem {
        &self.model
    }
}

/// Creep operator, `f64`: `z_k ← a_k z_k + b_k y`, `x = c0·y + Σ c_k z_k` (see
/// `twinstack::models::creep`), in any units (the static gain is 1, so an affine change of units
/// commutes with it). Where the modes take turns at the rate
/// (`twinstack::models::creep::takes_turns`), one mode updates a sample, with the coefficients
/// of its update period.
#[derive(Clone, Debug, PartialEq)]
pub struct Creep {
    /// `(a_k, b_k, c_k)` per mode, per update.
    modes: Vec<(f64, f64, f64)>,
    /// The modes' states `z_k`.
    z: Vec<f64>,
    /// Taking turns: the mode the next sample updates.
    turn: Option<usize>,
}

impl Creep {
    /// The operator `params` at `rate_hz` (ticks or samples per second), at rest at `y0`.
    pub fn new(params: &CreepParams, rate_hz: f64, y0: f64) -> Result<Self, ParamError> {
        params.check(rate_hz)?;
        let modes: Vec<(f64, f64, f64)> = params
            .update_poles(rate_hz)
            .zip(&params.weights)
            .map(|((a, b), &c)| (a, b, c))
            .collect();
        let z = vec![y0; modes.len()];
        let turn = params.takes_turns(rate_hz).then_some(0);
        Ok(Self { modes, z, turn })
    }

    /// The modes that update this sample: all, or the one whose turn it is.
    fn moving(&self) -> std::ops::Range<usize> {
        match self.turn {
            Some(j) => j..j + 1,
            None => 0..self.modes.len(),
        }
    }

    /// The next turn comes (taking turns).
    fn advance(&mut self) {
        if let Some(j) = self.turn.as_mut() {
            *j = (*j + 1) % self.modes.len().max(1);
        }
    }

    /// One sample forward: `y` → `x` (modes updated first).
    pub fn step(&mut self, y: f64) -> f64 {
        for k in self.moving() {
            let (a, b, _) = self.modes[k];
            self.z[k] = a * self.z[k] + b * y;
        }
        self.advance();
        let mut x = y;
        for (&(_, _, c), &z) in self.modes.iter().zip(&self.z) {
            x += c * (z - y);
        }
        x
    }

    /// One sample of the exact inverse: `x` → the `y` that [`Creep::step`] turns into `x`,
    /// `y = (x − Σ_moving c_k a_k z_k − Σ_held c_k z_k) / (1 − Σ_moving c_k a_k − Σ_held c_k)`;
    /// the moving modes are then updated with it.
    pub fn inverse_step(&mut self, x: f64) -> f64 {
        let (mut rest, mut d) = (x, 1.0);
        let moving = self.moving();
        for (k, (&(a, _, c), &z)) in self.modes.iter().zip(&self.z).enumerate() {
            let kept = if moving.contains(&k) { a } else { 1.0 };
            rest -= c * kept * z;
            d -= c * kept;
        }
        let y = rest / d;
        for k in moving {
            let (a, b, _) = self.modes[k];
            self.z[k] = a * self.z[k] + b * y;
        }
        self.advance();
        y
    }
}

/// The sign of a Bouc–Wen state `h` for its rate: at `h = 0`, the sign it takes on the step,
/// that of `s·A` (`pull`).
fn heading_sign(h: f64, pull: f64) -> f64 {
    if h < 0.0 || (h == 0.0 && pull < 0.0) {
        -1.0
    } else {
        1.0
    }
}

/// The drive history of a stage at rest at `u0` (volts), in `scaling`'s input range: the
/// library's [`twinstack::models::rest_history`] in volts (its turning points the range's
/// ends; `step` called with each, then with `u0`).
pub fn rest_history(scaling: &Scaling, u0: f64, mut step: impl FnMut(f64)) {
    for _ in 0..twinstack::models::REST_CYCLES {
        step(scaling.input_min);
        step(scaling.input_max);
    }
    step(scaling.input_min);
    step(u0);
}

/// The drive at which a model at rest gives `y0`: `output_at_rest(u)` (rising in `u`, the
/// model monotone) solved by bisection over `scaling`'s input range (60 halvings, to the
/// `f64`'s resolution), or the range's end nearer where `y0` lies outside what it gives.
pub fn drive_at_rest(scaling: &Scaling, y0: f64, output_at_rest: impl Fn(f64) -> f64) -> f64 {
    let (mut lo, mut hi) = (scaling.input_min, scaling.input_max);
    if output_at_rest(lo) >= y0 {
        return lo;
    }
    if output_at_rest(hi) <= y0 {
        return hi;
    }
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if output_at_rest(mid) < y0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// Forward generalised Bouc–Wen, `f64`: `y = k·u + δ + h`, `h` relaxed exactly over each
/// step toward `s·A/c`: `h ← h − q·h + s·A·q/c`, `q = 1 − e^{−c|Δu|}`,
/// `c = β + s·sgn(h)·γ + s·ψ` (`s` the sign of `Δu`, `sgn(h)` at the step's start; at
/// `h = 0` the sign of `s·A`, the sign `h` takes).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BoucWen {
    params: BoucWenParams,
    scaling: Scaling,
    /// Previous input, volts.
    pub u: f64,
    /// Hysteretic state, output units.
    pub h: f64,
}

impl BoucWen {
    /// The model `params` relaxed (`h = 0`) at input `u0` (volts, clamped to the range).
    pub fn new(params: &BoucWenParams, scaling: &Scaling, u0: f64) -> Result<Self, ParamError> {
        params.validate()?;
        Ok(Self {
            params: *params,
            scaling: *scaling,
            u: clamp(u0, scaling.input_min, scaling.input_max),
            h: 0.0,
        })
    }

    /// The model `params` at rest at input `u0` (volts): relaxed at the range's top, then the
    /// drive history of [`rest_history`], as the library's `BoucWen::state_at_rest`.
    pub fn at_rest(params: &BoucWenParams, scaling: &Scaling, u0: f64) -> Result<Self, ParamError> {
        Self::with_rest(params, scaling, u0, Rest::Ascending)
    }

    /// The model `params` at rest at input `u0` (volts) with the history `rest`:
    /// [`BoucWen::at_rest`], or relaxed ([`Rest::Relaxed`], [`BoucWen::new`]).
    pub fn with_rest(
        params: &BoucWenParams,
        scaling: &Scaling,
        u0: f64,
        rest: Rest,
    ) -> Result<Self, ParamError> {
        if rest == Rest::Relaxed {
            return Self::new(params, scaling, u0);
        }
        let mut m = Self::new(params, scaling, scaling.input_max)?;
        rest_history(scaling, u0, |v| {
            m.step(v);
        });
        Ok(m)
    }

    /// The output in the present state: `k·u + δ + h`.
    pub fn output(&self) -> f64 {
        self.params.k * self.u + self.params.offset + self.h
    }

    /// One sample: drive (volts) → displacement (output units).
    pub fn step(&mut self, u: f64) -> f64 {
        let u = clamp(u, self.scaling.input_min, self.scaling.input_max);
        let du = u - self.u;
        let p = &self.params;
        let s = if du < 0.0 { -1.0 } else { 1.0 };
        let sh = heading_sign(self.h, s * p.a);
        let c = p.factor(s, sh);
        let (q, phi) = relax(c, du.abs());
        let h = self.h + s * p.a * phi - q * self.h;
        self.h = if h * self.h < 0.0 {
            // Through zero: to zero at c, the rest from zero at the other sign's rate.
            let c_other = p.factor(s, -sh);
            let to_zero = libm::log1p(self.h.abs() * c / p.a.abs()) / c;
            s * p.a * relax(c_other, (du.abs() - to_zero).max(0.0)).1
        } else {
            h
        };
        self.u = u;
        self.output()
    }
}

/// Bouc–Wen compensator, `f64`, as the fixed-point one: per sample the drive step `m` in
/// the direction `s` of the desired change with `k·m + D·q(c·m) = |y_d − y|`,
/// `D = A/c − s·h` — the linear guess over the slope `g_s = k + A − c·s·h` (floored at `k/16`)
/// and one Halley step, solved past zero at the other sign's rate where `h` crosses it —
/// capped at `0.99/c` and at the input span, the drive clamped to the input
/// range; then the internal model advanced on it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InverseBoucWen {
    model: BoucWen,
}

impl InverseBoucWen {
    /// The compensator for `params`, its model relaxed at drive `u0` (volts).
    pub fn new(params: &BoucWenParams, scaling: &Scaling, u0: f64) -> Result<Self, ParamError> {
        Ok(Self {
            model: BoucWen::new(params, scaling, u0)?,
        })
    }

    /// The compensator for `params`, its model as [`BoucWen::with_rest`] puts it.
    pub fn with_rest(
        params: &BoucWenParams,
        scaling: &Scaling,
        u0: f64,
        rest: Rest,
    ) -> Result<Self, ParamError> {
        Ok(Self {
            model: BoucWen::with_rest(params, scaling, u0, rest)?,
        })
    }

    /// One sample: desired displacement (output units, clamped to the output range) → drive
    /// (volts).
    pub fn step(&mut self, y_desired: f64) -> f64 {
        let s = self.model.scaling;
        let p = self.model.params;
        let r = clamp(y_desired, s.output_min, s.output_max) - self.model.output();
        if r == 0.0 {
            return self.model.u;
        }
        let sign = if r > 0.0 { 1.0 } else { -1.0 };
        let h = self.model.h;
        let sh = heading_sign(h, sign * p.a);
        let c = p.factor(sign, sh);
        // As the library's `STEP_CAP`: 0.99/c.
        let cap = |c: f64| (0.99 / c).min(2.0 * s.input_half_span());
        let toward = -sign * h;
        let at_zero = if toward * p.a > 0.0 {
            // h heads across zero: the step to it, and the output change there.
            let to_zero = libm::log1p(h.abs() * c / p.a.abs()) / c;
            Some((to_zero, p.k * to_zero + toward))
        } else {
            None
        };
        let m = match at_zero {
            Some((to_zero, change)) if r.abs() > change => {
                let c_other = p.factor(sign, -sh);
                to_zero
                    + solve(
                        c_other,
                        p.k,
                        p.a / c_other,
                        p.k / 16.0,
                        r.abs() - change,
                        cap(c_other).min(cap(c) - to_zero),
                    )
            }
            _ => solve(c, p.k, p.a / c - sign * h, p.k / 16.0, r.abs(), cap(c)),
        };
        let u = clamp(self.model.u + sign * m, s.input_min, s.input_max);
        self.model.step(u);
        u
    }

    /// The compensator's internal forward model.
    pub fn model(&self) -> &BoucWen {
        &self.model
    }
}

/// A biquad in `f64`, direct form I (`a₀ = 1`): the reference the fixed-point
/// [`twinstack::control::notch::Notch`] is checked against.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Biquad {
    b: [f64; 3],
    a: [f64; 2],
    x: [f64; 2],
    y: [f64; 2],
}

impl Biquad {
    /// A biquad at rest with feedforward `b` and feedback `a` (`a₁, a₂`) coefficients.
    pub fn new(b: [f64; 3], a: [f64; 2]) -> Self {
        Self {
            b,
            a,
            x: [0.0; 2],
            y: [0.0; 2],
        }
    }

    /// One sample.
    pub fn step(&mut self, x: f64) -> f64 {
        let y = self.b[0] * x + self.b[1] * self.x[0] + self.b[2] * self.x[1]
            - self.a[0] * self.y[0]
            - self.a[1] * self.y[1];
        self.x = [x, self.x[0]];
        self.y = [y, self.y[0]];
        y
    }
}
