//! `f64` reference implementations of every model, in physical units (volts in, output units
//! out). They are the specification the fixed-point code is checked against: same equations,
//! same clamps, no quantisation. They allocate nothing, but are not meant for the tick: they
//! live here, on the host, and not in the firmware's library.

use twinstack::params::{BoucWenParams, CanonicalPi, DuhemParams, ParamError, PiParams};
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
    states: heapless::Vec<f64, { twinstack::params::MAX_CANONICAL_OPERATORS }>,
}

impl PlaySum {
    fn new(model: CanonicalPi, at: f64) -> Self {
        let states = model.thresholds.iter().map(|_| at).collect();
        Self { model, states }
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
    /// The model `params`, at rest at input `u0` (volts).
    pub fn new(params: &PiParams, scaling: &Scaling, u0: f64) -> Result<Self, ParamError> {
        let u0 = clamp(u0, scaling.input_min, scaling.input_max);
        Ok(Self {
            sum: PlaySum::new(params.canonical()?, u0),
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
    /// The inverse of `params`, at rest at drive `u0` (volts): states `p'_i = y(u0) − c`.
    pub fn new(params: &PiParams, scaling: &Scaling, u0: f64) -> Result<Self, ParamError> {
        let forward = params.canonical()?;
        let inverse = forward.inverse()?;
        let u0 = clamp(u0, scaling.input_min, scaling.input_max);
        let y0_minus_c: f64 = forward.weights.iter().sum::<f64>() * u0;
        Ok(Self {
            sum: PlaySum::new(inverse, y0_minus_c),
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

/// Forward Duhem, `f64`: `y_k = y_{k−1} + min(α|Δu|, 1)(β u_{k−1} + δ − y_{k−1}) + γ Δu`.
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

    /// One sample: drive (volts) → displacement (output units).
    pub fn step(&mut self, u: f64) -> f64 {
        let u = clamp(u, self.scaling.input_min, self.scaling.input_max);
        let du = u - self.u;
        let p = &self.params;
        let a = (p.alpha * du.abs()).min(1.0);
        self.y += a * (p.beta * self.u + p.offset - self.y) + p.gamma * du;
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

/// Inverse Duhem, `f64`: the same construction as the fixed-point compensator
/// (slope floored at `min(β, γ)/16`, step capped at `1/α`, drive clamped to the input range).
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

    /// One sample: desired displacement (output units) → drive (volts).
    pub fn step(&mut self, y_desired: f64) -> f64 {
        let s = &self.model.scaling;
        let dy = clamp(y_desired, s.output_min, s.output_max) - self.model.y;
        if dy == 0.0 {
            return self.model.u;
        }
        let p = &self.model.params;
        let e = p.beta * self.model.u + p.offset - self.model.y;
        let sign = if dy > 0.0 { 1.0 } else { -1.0 };
        let slope = (p.gamma + sign * p.alpha * e).max(p.beta.min(p.gamma) / 16.0);
        // Steps capped at 1/α, where the discrete model stops being linear in Δu.
        let m = (dy.abs() / slope)
            .min(2.0 * s.input_half_span())
            .min(1.0 / p.alpha);
        let u = clamp(self.model.u + sign * m, s.input_min, s.input_max);
        self.model.step(u);
        u
    }

    /// The compensator's internal forward model.
    pub fn model(&self) -> &Duhem {
        &self.model
    }
}

/// Forward generalised Bouc–Wen, `f64`: `y = k·u + δ + h`,
/// `h_k = (1 − f)·h_{k−1} + A·Δu` with `f = clamp((β + s·sgn(h)·γ + s·ψ)·|Δu|, 0, 1)` (`s` the
/// sign of `Δu`), i.e. `Δh = A·Δu − β|Δu|h − γΔu|h| − ψΔu·h` with the factor on `h` clamped.
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
        let sh = if self.h < 0.0 { -1.0 } else { 1.0 };
        let c = p.beta + s * sh * p.gamma + s * p.psi;
        let f = clamp(c * du.abs(), 0.0, 1.0);
        self.h = (1.0 - f) * self.h + p.a * du;
        self.u = u;
        self.output()
    }
}

/// Inverse-multiplicative Bouc–Wen, `f64`: `u = (y_d − δ − h)/k` clamped to the input range,
/// then the internal model advanced on that `u` (as the fixed-point compensator).
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

    /// One sample: desired displacement (output units, clamped to the output range) → drive
    /// (volts).
    pub fn step(&mut self, y_desired: f64) -> f64 {
        let s = self.model.scaling;
        let p = self.model.params;
        let y = clamp(y_desired, s.output_min, s.output_max);
        let u = clamp(
            (y - p.offset - self.model.h) / p.k,
            s.input_min,
            s.input_max,
        );
        self.model.step(u);
        u
    }

    /// The compensator's internal forward model.
    pub fn model(&self) -> &BoucWen {
        &self.model
    }
}

/// A biquad in `f64`, direct form I (`a₀ = 1`): the reference the fixed-point
/// [`twinstack::notch::Notch`] is checked against.
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
