//! The lab stage's other hysteresis: a Bouc–Wen-class operator outside the family's Bouc–Wen.
//!
//! The displacement lags the drive by a hysteretic state `h` (the form piezo stacks are
//! usually given, `p = v − h` before normalisation), with `v ∈ [0, 1]` the normalised drive:
//!
//! ```text
//! dh/dv = α − |h|ⁿ · (β·sgn(v̇·h) + γ + φ·[v̇ > 0 and h ≥ 0])
//! ```
//!
//! with `0 ≤ γ ≤ β`, so that on a reversal the state relaxes toward zero at least at the
//! rate `α`, and saturates only moving away from it.
//!
//! * `n ≠ 1` (1.5 by default): the family's Bouc–Wen has `n = 1`, so the branches bend as
//!   none of its members' do;
//! * `φ`, charged only where the state saturates on rising input: the rising branch
//!   saturates at a lower `|h|` than the falling one (`(α/(β+γ+φ))^(1/n)` against
//!   `(α/(β+γ))^(1/n)`; the family's asymmetric term is `ψ·du·h`, linear in `h`);
//! * like every Duhem-class operator its minor loops are not congruent: a loop's shape
//!   depends on the state it starts from, which no P–I (and no Preisach model with a
//!   congruency property) reproduces.
//!
//! The equation is integrated in the input, not in time (rate-independent, as hysteresis is):
//! over each sample the drive moves in a straight line, in substeps of at most
//! [`MAX_SUBSTEP`] of the range, each a classical Runge–Kutta step.
//!
//! The stack is conditioned, as a stack in use is: cycled over the full range
//! ([`CONDITIONING_CYCLES`] times) before it is brought to rest, so that its state lies on the
//! major loop (a virgin Bouc–Wen state never returns: after one cycle the loop's bottom sits
//! above the virgin start, out of reach of the drive). The output is normalised so that the
//! major loop spans 0 … 1.

/// Largest input step of one Runge–Kutta substep, fraction of the input range.
pub const MAX_SUBSTEP: f64 = 0.002;

/// Full cycles over the range before the stage is brought to rest.
pub const CONDITIONING_CYCLES: usize = 8;

/// The operator's parameters (normalised input and state).
#[derive(Clone, Debug, PartialEq)]
pub struct BoucWenClass {
    /// `α`: the state's slope on a reversal (`0 < α < 1`); the loop's width grows with it.
    pub alpha: f64,
    /// `β`: the saturation that depends on the direction relative to the state (`> 0`).
    pub beta: f64,
    /// `γ`: the saturation that does not (`0 ≤ γ ≤ β`).
    pub gamma: f64,
    /// `φ`: the rising branch's extra saturation (`≥ 0`).
    pub rising: f64,
    /// `n`: the exponent of `|h|` (1 … 4).
    pub exponent: f64,
}

impl Default for BoucWenClass {
    /// `α` = 0.3, `β` = 3, `γ` = 1, `φ` = 10, `n` = 1.5: a major loop about 12 % of the stroke
    /// wide, the rising branch saturating at 43 % of the falling one's `|h|`.
    fn default() -> Self {
        Self {
            alpha: 0.3,
            beta: 3.0,
            gamma: 1.0,
            rising: 10.0,
            exponent: 1.5,
        }
    }
}

impl BoucWenClass {
    /// `dh/dv` at state `h`, the input rising (`rising`) or falling.
    fn slope(&self, h: f64, rising: bool) -> f64 {
        let same = (h >= 0.0) == rising;
        let magnitude = h.abs().powf(self.exponent);
        let saturation = if same {
            self.beta + self.gamma + if rising { self.rising } else { 0.0 }
        } else {
            self.gamma - self.beta
        };
        self.alpha - magnitude * saturation
    }

    /// The state after the input moves from `from` to `to` (straight, in substeps).
    pub fn advance(&self, h: f64, from: f64, to: f64) -> f64 {
        let dv = to - from;
        if dv == 0.0 || !dv.is_finite() {
            return h;
        }
        let rising = dv > 0.0;
        // At most 500 substeps over the whole range: |dv| ≤ 1.
        let steps = (dv.abs() / MAX_SUBSTEP)
            .ceil()
            .clamp(1.0, 1.0 / MAX_SUBSTEP) as usize;
        let d = dv / steps as f64;
        let mut h = h;
        for _ in 0..steps {
            let k1 = self.slope(h, rising);
            let k2 = self.slope(h + 0.5 * d * k1, rising);
            let k3 = self.slope(h + 0.5 * d * k2, rising);
            let k4 = self.slope(h + d * k3, rising);
            h += d / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4);
        }
        h
    }
}

/// The operator running: its parameters, state and the input it is at.
#[derive(Clone, Debug)]
pub struct BoucWenStage {
    params: BoucWenClass,
    /// The state at 0 after conditioning: the major loop's bottom.
    conditioned: f64,
    /// `v − h` at the major loop's bottom (0) and top (1): the output's normalisation.
    low: f64,
    high: f64,
    h: f64,
    v: f64,
}

impl BoucWenStage {
    /// Conditioned ([`CONDITIONING_CYCLES`]) and at rest at 0.
    pub fn new(params: &BoucWenClass) -> Self {
        let (mut bottom, mut top) = (0.0, 0.0);
        for _ in 0..CONDITIONING_CYCLES {
            top = params.advance(bottom, 0.0, 1.0);
            bottom = params.advance(top, 1.0, 0.0);
        }
        Self {
            params: params.clone(),
            conditioned: bottom,
            low: -bottom,
            high: 1.0 - top,
            h: bottom,
            v: 0.0,
        }
    }

    /// Conditioned, then raised slowly from 0 to `v0`.
    pub fn rest(&mut self, v0: f64) {
        self.h = self.params.advance(self.conditioned, 0.0, v0);
        self.v = v0;
    }

    /// The input moves to `v`.
    pub fn set(&mut self, v: f64) {
        self.h = self.params.advance(self.h, self.v, v);
        self.v = v;
    }

    /// The normalised output: `v − h`, the major loop mapped onto 0 … 1.
    pub fn output(&self) -> f64 {
        (self.v - self.h - self.low) / (self.high - self.low)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The output along `path` from the stage at rest at 0.
    fn outputs(stage: &mut BoucWenStage, path: impl IntoIterator<Item = f64>) -> Vec<f64> {
        path.into_iter()
            .map(|v| {
                stage.set(v);
                stage.output()
            })
            .collect()
    }

    #[test]
    fn the_state_is_integrated_in_the_input_not_in_time() {
        // One move of 0.6 and the same move in 600 samples end in the same state: the
        // operator is rate-independent (the substeps depend on the input's path only).
        let p = BoucWenClass::default();
        let one = p.advance(0.0, 0.1, 0.7);
        let mut many = 0.0;
        for k in 0..600 {
            let v = 0.1 + 0.001 * k as f64;
            many = p.advance(many, v, v + 0.001);
        }
        assert!((one - many).abs() < 1e-9, "{one} vs {many}");
        // No move, no change; a non-finite input changes nothing.
        assert_eq!(p.advance(0.05, 0.3, 0.3), 0.05);
        assert_eq!(p.advance(0.05, 0.3, f64::NAN), 0.05);
    }

    #[test]
    fn the_major_loop_spans_zero_to_one_and_its_branches_differ() {
        let mut s = BoucWenStage::new(&BoucWenClass::default());
        s.rest(0.0);
        assert!(s.output().abs() < 1e-9, "the loop's bottom: {}", s.output());
        let n = 1000;
        let up = outputs(&mut s, (1..=n).map(|k| k as f64 / n as f64));
        assert!(
            (up[n - 1] - 1.0).abs() < 1e-6,
            "the loop's top: {}",
            up[n - 1]
        );
        let down = outputs(&mut s, (0..n).rev().map(|k| k as f64 / n as f64));
        // down[i] is at (n − 1 − i)/n, up[k − 1] at k/n.
        let width = |k: usize| down[n - 1 - k] - up[k - 1];
        let w = (1..n).map(width).fold(0.0, f64::max);
        assert!(
            (0.05..0.2).contains(&w),
            "a loop of a piezo stack's width: {w}"
        );
        assert!(
            (1..n).all(|k| width(k) > 0.0),
            "the falling branch lies above"
        );
        // Without the rising branch's extra saturation the loop is point-symmetric about its
        // centre (falling at v mirrors rising at 1 − v); with it, it is not.
        let asymmetry = |p: &BoucWenClass| {
            let mut s = BoucWenStage::new(p);
            s.rest(0.0);
            let up = outputs(&mut s, (1..=n).map(|k| k as f64 / n as f64));
            let down = outputs(&mut s, (0..n).rev().map(|k| k as f64 / n as f64));
            (1..n)
                .map(|k| (down[n - 1 - k] - (1.0 - up[n - k - 1])).abs())
                .fold(0.0, f64::max)
        };
        let symmetric = BoucWenClass {
            rising: 0.0,
            ..BoucWenClass::default()
        };
        let (with, without) = (asymmetry(&BoucWenClass::default()), asymmetry(&symmetric));
        assert!(without < 1e-6, "symmetric branches: {without}");
        assert!(with > 0.01, "the rising branch saturates first: {with}");
    }

    #[test]
    fn minor_loops_over_the_same_inputs_are_not_congruent() {
        // The same minor loop (0.4 → 0.6 → 0.4) entered from the rising branch and from the
        // falling one: a Preisach model with the congruency property (every P–I) gives two
        // loops of the same height; this operator does not.
        let p = BoucWenClass::default();
        let height = |from_above: bool| {
            let mut s = BoucWenStage::new(&p);
            s.rest(0.0);
            if from_above {
                s.set(1.0);
            }
            s.set(0.4);
            let low = s.output();
            s.set(0.6);
            s.output() - low
        };
        let (rising, falling) = (height(false), height(true));
        assert!(
            (rising - falling).abs() > 0.01 * rising.max(falling),
            "heights {rising} and {falling}"
        );
    }
}
