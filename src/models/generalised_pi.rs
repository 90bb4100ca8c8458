//! The generalised (asymmetric) Prandtl–Ishlinskii model in fixed point: Kuhnen's *modified*
//! P–I, a P–I followed by a static monotone map of one-sided dead-zone operators, and its
//! analytic inverse.
//!
//! A P–I model's loops are point-symmetric (every branch is a scaled copy of the loading
//! curve), so it cannot fit a stage whose loop is fatter at one end than the other. Passing
//! its output through a monotone piecewise-linear map bends the loops asymmetrically and keeps
//! the model invertible:
//!
//! * forward (observer): `z = PI[u]` (the P–I of [`crate::models::prandtl_ishlinskii`], offset
//!   included, output units), then
//!   `y = S[z] = c + g_0·(z − c) + Σ_j g_j · S_{d_j}(z − c)`
//! * inverse (compensator): `u = PI⁻¹[S⁻¹[y]]`, with
//!   `S⁻¹[y] = c + h_0·(y − c) + Σ_j h_j · S_{e_j}(y − c)`
//!
//! where the one-sided dead-zone operator is `S_d(x) = max(x − d, 0)` for `d > 0` and
//! `min(x − d, 0)` for `d < 0` (the `d = 0` operator is the linear gain `g_0`).
//!
//! **Where the thresholds live.** The thresholds `d_j` are in *output units relative to the
//! map's centre* `c` (itself in output units, a parameter: identification puts it at the centre
//! of the measured output), so a [`DeadZoneParams`] means the same whatever ranges the board
//! normalises with. On the board, normalised by the output range (`Y` its half span, `y_mid`
//! its centre): `c → (c − y_mid)/Y`, `d_j → d_j / Y`, gains unchanged.
//!
//! **The inverse's closed form.** `S` is piecewise linear with breakpoints at the `d_j`. Its
//! slope on a segment is `σ = g_0 + Σ g_j` over the dead zones between the centre and that
//! segment (validated positive: [`ParamError::DeadZoneSlopeNotPositive`]), so `S` is strictly
//! increasing and `S⁻¹` is again a dead-zone superposition:
//!
//! ```text
//! e_j = S(c + d_j) − c                      the breakpoint's image
//! h_0 = 1 / g_0
//! h_j = 1/σ_j − 1/σ_{j−1} = −g_j / (σ_j·σ_{j−1})
//! ```
//!
//! with `σ_j` the slope just beyond `d_j` (away from the centre) and `σ_{j−1}` the slope just
//! before it. Computed once, off the tick ([`DeadZoneParams::inverse`]).
//!
//! Formats: signals Q2.30 normalised; thresholds and the centre Q2.30 normalised; gains Q8.24;
//! the sum accumulates in Q10.54 (`i64`) and is brought back to Q2.30 once, rounding toward −∞
//! and saturating. A step costs the same whatever the input does and whatever the map's size:
//! the map is a table of its segments, found by a branchless binary search and evaluated by
//! one `SMLAL` ([`DeadZoneBank`]), bit for bit the zone-by-zone sum.

use crate::fixed_point::{
    clamp_full_scale, gain_from_f64, q54_to_signal_floor, signal_from_f64, GAIN_FRAC_BITS,
    MAX_GAIN_SUM,
};
use crate::models::params::{
    ParamError, PiParams, MAX_CANONICAL_OPERATORS, MAX_NORM_THRESHOLD, MAX_NORM_WEIGHT,
};
use crate::models::prandtl_ishlinskii::bank_cycles;
use crate::models::prandtl_ishlinskii::{InversePrandtlIshlinskii, PiState, PrandtlIshlinskii};
use crate::models::{Forward, Hysteresis, Inverse, Rest};
use crate::scaling::Scaling;
use heapless::Vec;

// Defined with the parameters that are checked against it (params sits below this module).
pub use crate::models::params::MAX_DEAD_ZONES;
// `DeadZoneBank::apply`'s search takes four halving steps: at most 8 breakpoints.
const _: () = assert!(MAX_DEAD_ZONES == 8);

/// The one-sided dead-zone operator in `f64`: `max(x − d, 0)` for `d > 0`, `min(x − d, 0)` for
/// `d < 0`, `x` for `d = 0`.
pub fn dead_zone(x: f64, d: f64) -> f64 {
    if d > 0.0 {
        (x - d).max(0.0)
    } else if d < 0.0 {
        (x - d).min(0.0)
    } else {
        x
    }
}

/// A static dead-zone map in physical units:
/// `y = centre + linear·(z − centre) + Σ_j weights_j · S_{thresholds_j}(z − centre)`.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeadZoneParams {
    /// Centre `c` of the map, output units: `S(c) = c`, and the thresholds are relative to it.
    pub centre: f64,
    /// Linear gain `g_0` (the `d = 0` operator), `> 0`.
    pub linear: f64,
    /// Thresholds `d_j`, output units relative to `centre`: non-zero, strictly increasing.
    pub thresholds: Vec<f64, MAX_DEAD_ZONES>,
    /// Weights `g_j` (dimensionless).
    pub weights: Vec<f64, MAX_DEAD_ZONES>,
}

impl DeadZoneParams {
    /// A map from its centre (output units), linear gain, thresholds (output units relative to
    /// the centre) and weights. Lengths are checked here, the rest by [`Self::validate`].
    pub fn new(
        centre: f64,
        linear: f64,
        thresholds: &[f64],
        weights: &[f64],
    ) -> Result<Self, ParamError> {
        let too_many = |count| ParamError::TooManyDeadZones { count };
        if weights.len() != thresholds.len() {
            return Err(ParamError::DeadZoneLengthMismatch {
                thresholds: thresholds.len(),
                weights: weights.len(),
            });
        }
        Ok(Self {
            centre,
            linear,
            thresholds: Vec::from_slice(thresholds).map_err(|_| too_many(thresholds.len()))?,
            weights: Vec::from_slice(weights).map_err(|_| too_many(weights.len()))?,
        })
    }

    /// The identity map (`g_0 = 1`, no dead zone): the generalised P–I is then the plain P–I.
    pub fn identity() -> Self {
        Self {
            centre: 0.0,
            linear: 1.0,
            thresholds: Vec::new(),
            weights: Vec::new(),
        }
    }

    /// Checks the map is well formed and invertible: finite, thresholds non-zero and strictly
    /// increasing, `g_0 > 0` and every segment's slope positive. Errors name the dead zone
    /// (1-based).
    pub fn validate(&self) -> Result<(), ParamError> {
        if self.weights.len() != self.thresholds.len() {
            return Err(ParamError::DeadZoneLengthMismatch {
                thresholds: self.thresholds.len(),
                weights: self.weights.len(),
            });
        }
        let finite = self.centre.is_finite()
            && self.linear.is_finite()
            && self
                .thresholds
                .iter()
                .chain(self.weights.iter())
                .all(|v| v.is_finite());
        if !finite {
            return Err(ParamError::NotFinite);
        }
        for (i, &d) in self.thresholds.iter().enumerate() {
            if d == 0.0 || (i > 0 && d <= self.thresholds[i - 1]) {
                return Err(ParamError::DeadZoneThresholdsNotIncreasing { dead_zone: i + 1 });
            }
        }
        if self.linear <= 0.0 {
            return Err(ParamError::DeadZoneLinearNotPositive);
        }
        self.slopes().map(|_| ())
    }

    /// For each dead zone `j` (0-based), the slopes `(σ_before, σ_after)` of the map on either
    /// side of its threshold, `before` being the side towards the centre. Refuses a
    /// non-positive slope with the dead zone it follows.
    fn slopes(&self) -> Result<[(f64, f64); MAX_DEAD_ZONES], ParamError> {
        let mut out = [(0.0, 0.0); MAX_DEAD_ZONES];
        let n = self.thresholds.len().min(MAX_DEAD_ZONES);
        // Above the centre, outward = ascending; below it, outward = descending.
        let mut sigma = self.linear;
        for j in (0..n).filter(|&j| self.thresholds[j] > 0.0) {
            let before = sigma;
            sigma += self.weights[j];
            if sigma <= 0.0 {
                return Err(ParamError::DeadZoneSlopeNotPositive { dead_zone: j + 1 });
            }
            out[j] = (before, sigma);
        }
        let mut sigma = self.linear;
        for j in (0..n).rev().filter(|&j| self.thresholds[j] < 0.0) {
            let before = sigma;
            sigma += self.weights[j];
            if sigma <= 0.0 {
                return Err(ParamError::DeadZoneSlopeNotPositive { dead_zone: j + 1 });
            }
            out[j] = (before, sigma);
        }
        Ok(out)
    }

    /// The map at `z` (output units), in `f64` (off the tick: validation, references, tests).
    pub fn apply(&self, z: f64) -> f64 {
        let x = z - self.centre;
        let sum: f64 = self
            .thresholds
            .iter()
            .zip(self.weights.iter())
            .map(|(&d, &g)| g * dead_zone(x, d))
            .sum();
        self.centre + self.linear * x + sum
    }

    /// The inverse map in closed form (see the module doc): same centre, `h_0 = 1/g_0`,
    /// `e_j = S(c + d_j) − c`, `h_j = 1/σ_after − 1/σ_before`.
    pub fn inverse(&self) -> Result<DeadZoneParams, ParamError> {
        self.validate()?;
        let slopes = self.slopes()?;
        let mut thresholds = Vec::new();
        let mut weights = Vec::new();
        for (j, &d) in self.thresholds.iter().enumerate() {
            let (before, after) = slopes[j];
            // Capacity MAX_DEAD_ZONES holds every dead zone of the forward map.
            let _ = thresholds.push(self.apply(self.centre + d) - self.centre);
            let _ = weights.push(1.0 / after - 1.0 / before);
        }
        Ok(DeadZoneParams {
            centre: self.centre,
            linear: 1.0 / self.linear,
            thresholds,
            weights,
        })
    }

    /// The map in the normalised coordinates of `scaling`'s output range:
    /// `c → (c − y_mid)/Y`, `d → d/Y`, gains unchanged.
    pub fn normalized(&self, scaling: &Scaling) -> Result<DeadZoneParams, ParamError> {
        self.validate()?;
        let y = scaling.output_half_span();
        let mut thresholds = Vec::new();
        for &d in &self.thresholds {
            let _ = thresholds.push(d / y);
        }
        Ok(DeadZoneParams {
            centre: (self.centre - scaling.output_mid()) / y,
            linear: self.linear,
            thresholds,
            weights: self.weights.clone(),
        })
    }

    /// Checks a normalised map fits the fixed-point formats: centre within the output range
    /// (so that `x = y − c` of any `|y| ≤ 1` fits Q2.30's ±2), thresholds
    /// within the normalised span, gains within Q8.24, `Σ|g| + |c|` within [`MAX_GAIN_SUM`].
    pub fn check_fixed_point_range(&self) -> Result<(), ParamError> {
        if !(self.centre.is_finite() && self.centre.abs() <= 1.0) {
            return Err(ParamError::DeadZoneCentreOutOfRange);
        }
        if !self.linear.is_finite() || self.linear.abs() > MAX_NORM_WEIGHT {
            return Err(ParamError::DeadZoneWeightOutOfRange { dead_zone: 0 });
        }
        let mut sum = self.centre.abs() + self.linear.abs();
        for (j, (&d, &g)) in self.thresholds.iter().zip(self.weights.iter()).enumerate() {
            if !(d.is_finite() && d.abs() <= MAX_NORM_THRESHOLD) {
                return Err(ParamError::DeadZoneThresholdOutOfRange { dead_zone: j + 1 });
            }
            if !(g.is_finite() && g.abs() <= MAX_NORM_WEIGHT) {
                return Err(ParamError::DeadZoneWeightOutOfRange { dead_zone: j + 1 });
            }
            sum += g.abs();
        }
        if sum > MAX_GAIN_SUM {
            return Err(ParamError::DeadZoneGainSumTooLarge);
        }
        Ok(())
    }
}

/// A generalised P–I model in physical units: the P–I `pi` (volts in, output units out)
/// followed by the dead-zone map `dead_zones` (output units to output units).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GpiParams {
    /// The P–I part, `z = PI[u]`.
    pub pi: PiParams,
    /// The output map, `y = S[z]`.
    pub dead_zones: DeadZoneParams,
}

impl GpiParams {
    /// Checks both parts (the P–I first).
    pub fn validate(&self) -> Result<(), ParamError> {
        self.pi.validate()?;
        self.dead_zones.validate()
    }
}

/// A dead-zone map in fixed point, as a table of its segments.
///
/// The map `y = c + g_0·x + Σ_j g_j · S_{d_j}(x)`, `x = z − c`, is piecewise linear with a
/// breakpoint at each `d_j`. On the segment where exactly `k` breakpoints lie at or below `x`,
/// the dead zones above the centre that are open are those below `x`, and those below the
/// centre that are open are those above it, so the map is one line there:
/// `y = σ_k·x + b_k` with `σ_k = g_0 + Σ_{open} g_j` and `b_k = c − Σ_{open} g_j·d_j`.
/// The table holds `σ_k` and `b_k` for every segment, built once off the tick; a step finds
/// its segment by a branchless binary search over the sorted breakpoints (four compares, each
/// a conditional add, whatever the map's size and whatever the input does) and is then one
/// multiply-accumulate.
///
/// The result is bit for bit the zone-by-zone sum `c + g_0·x + Σ_j g_j·clamp(x − d_j, …)`
/// (Q10.54 in `i64`, exact, then rounded once): a zone that contributes is never saturated
/// (`x ≥ d_j > 0` or `x ≤ d_j ≤ 0` keep `x − d_j` within `(−2, 2)`), and a sum of exact
/// products regrouped is the same integer. The tests check it against that sum.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DeadZoneBank {
    len: usize,
    /// Centre `c`, Q2.30 normalised.
    centre: i32,
    /// Breakpoints `d_j`, Q2.30 normalised, relative to the centre, increasing; `i32::MAX`
    /// past the map's dead zones.
    breakpoints: [i32; MAX_DEAD_ZONES],
    /// Each segment's slope `σ_k`, Q8.24 (`|σ_k| ≤ Σ|g| ≤ MAX_GAIN_SUM` fits); segments past
    /// the map's dead zones repeat its last.
    slopes: [i32; MAX_DEAD_ZONES + 1],
    /// Each segment's intercept `b_k`, Q10.54, as its two 32-bit words (low, high): an
    /// 8-byte-aligned field would move the tick's other state, as the creep states' note says.
    intercepts: [[u32; 2]; MAX_DEAD_ZONES + 1],
}

impl DeadZoneBank {
    /// The fixed-point form of a normalised map (range-checked first).
    pub(crate) fn from_normalized(n: &DeadZoneParams) -> Result<Self, ParamError> {
        n.check_fixed_point_range()?;
        let len = n.thresholds.len().min(MAX_DEAD_ZONES);
        let centre = signal_from_f64(n.centre);
        // Each zone in fixed point: (d_j, g_j, opens above the centre).
        let mut zones = [(i32::MAX, 0i32, true); MAX_DEAD_ZONES];
        for (zone, (&d, &g)) in zones.iter_mut().zip(n.thresholds.iter().zip(&n.weights)) {
            *zone = (signal_from_f64(d), gain_from_f64(g), d > 0.0);
        }
        // Validation keeps the thresholds increasing; sorting here makes the search's order
        // hold whatever built the map.
        zones[..len].sort_unstable_by_key(|z| z.0);
        let mut bank = Self {
            len,
            centre,
            breakpoints: [i32::MAX; MAX_DEAD_ZONES],
            slopes: [0; MAX_DEAD_ZONES + 1],
            intercepts: [[0; 2]; MAX_DEAD_ZONES + 1],
        };
        for (k, slot) in bank.breakpoints.iter_mut().enumerate().take(len) {
            *slot = zones[k].0;
        }
        for k in 0..=MAX_DEAD_ZONES {
            // Segment k: exactly k breakpoints at or below x (past `len`, the last segment).
            let below = k.min(len);
            let mut slope = gain_from_f64(n.linear) as i64;
            let mut intercept = (centre as i64) << GAIN_FRAC_BITS;
            for (j, &(d, g, above_centre)) in zones[..len].iter().enumerate() {
                let open = if above_centre { j < below } else { j >= below };
                if open {
                    slope += g as i64;
                    intercept -= g as i64 * d as i64;
                }
            }
            // |σ| ≤ Σ|g| ≤ MAX_GAIN_SUM · 2^24 = 2^30: validated, so this never clamps.
            bank.slopes[k] = slope.clamp(i32::MIN as i64, i32::MAX as i64) as i32;
            bank.intercepts[k] = [intercept as u32, (intercept >> 32) as u32];
        }
        Ok(bank)
    }

    /// Number of dead zones besides the linear gain.
    pub fn dead_zones(&self) -> usize {
        self.len
    }

    /// The map at `z` (Q2.30 normalised) → Q2.30, rounded toward −∞ and saturated. Constant
    /// time: four compares find the segment, one multiply-accumulate evaluates it (see the
    /// type's doc). The sum fits `i64` exactly: `|x| < 2`, `|σ| + |b|` are bounded by the
    /// validated `Σ|g| + |c| ≤ MAX_GAIN_SUM`.
    ///
    /// One copy in flash (not inlined): written out into each of the tick's model variants,
    /// it made the whole handler's other code dearer (more registers spilled), whatever the
    /// model.
    #[inline(never)]
    pub fn apply(&self, z: i32) -> i32 {
        let x = z.saturating_sub(self.centre);
        let t = &self.breakpoints;
        // Branchless lower bound: k = #{j : d_j ≤ x}, 0 … 8, in four halving steps.
        let mut k = ((t[3] <= x) as usize) << 2;
        k += ((t[k + 1] <= x) as usize) << 1;
        k += (t[k] <= x) as usize;
        k += (t[k] <= x) as usize;
        let [lo, hi] = self.intercepts[k];
        let intercept = ((hi as i64) << 32) | lo as i64;
        q54_to_signal_floor(self.slopes[k] as i64 * x as i64 + intercept)
    }
}

/// Forward generalised P–I in fixed point, `y = S[PI[u]]` (the observer).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GeneralisedPi {
    pi: PrandtlIshlinskii,
    map: DeadZoneBank,
}

impl GeneralisedPi {
    /// Play operators and dead zones the tick runs (the operators set its cost; the map costs
    /// the same at any number of dead zones).
    pub fn size(&self) -> (usize, usize) {
        (self.pi.operators(), self.map.dead_zones())
    }

    /// Validates `params` (physical units) and converts them, normalised by `scaling`, into
    /// the fixed-point form the tick runs.
    ///
    /// ```
    /// use twinstack::models::generalised_pi::{DeadZoneParams, GeneralisedPi, GpiParams};
    /// use twinstack::{PiParams, Scaling};
    /// // 0…140 V onto 0…70 µm by a P–I, then a map that steepens above 50 µm (centre 35 µm).
    /// let params = GpiParams {
    ///     pi: PiParams::new(0.0, 0.0, &[0.0, 70.0], &[0.3, 0.1]).unwrap(),
    ///     dead_zones: DeadZoneParams::new(35.0, 1.0, &[15.0], &[0.5]).unwrap(),
    /// };
    /// let model = GeneralisedPi::new(&params, &Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap()).unwrap();
    /// let mut s = model.state_at_rest(-(1 << 30)); // relaxed at 0 V
    /// // Up to 140 V: z = 0.3·140 + 0.1·70 = 49 µm (below 50: the map is the identity there).
    /// let y = model.step(&mut s, (1 << 30) - 1);
    /// // (within one LSB16, 2^-15: the operators run on a Q1.15 grid)
    /// assert!((y as f64 / (1 << 30) as f64 - (49.0 - 35.0) / 35.0).abs() < 1.0 / 32768.0);
    /// ```
    #[inline(never)] // configuration, off the tick path: one copy in flash
    pub fn new(params: &GpiParams, scaling: &Scaling) -> Result<Self, ParamError> {
        let pi = PrandtlIshlinskii::new(&params.pi, scaling)?;
        let map = DeadZoneBank::from_normalized(&params.dead_zones.normalized(scaling)?)?;
        Ok(Self { pi, map })
    }

    /// The P–I part.
    pub fn pi(&self) -> &PrandtlIshlinskii {
        &self.pi
    }

    /// The output map.
    pub fn map(&self) -> &DeadZoneBank {
        &self.map
    }

    /// The relaxed state after resting at input `u` (Q2.30): the P–I's operators all at `u`.
    pub fn state_at_rest(&self, u: i32) -> PiState {
        self.pi.state_at_rest(u)
    }

    /// One sample: input `u` (Q2.30 normalised drive, clamped to [-1, 1]) → output `y`
    /// (Q2.30 normalised displacement, saturated).
    #[inline(always)]
    pub fn step(&self, state: &mut PiState, u: i32) -> i32 {
        self.map.apply(self.pi.step(state, u))
    }
}

/// Analytic inverse of the generalised P–I in fixed point, `u = PI⁻¹[S⁻¹[y]]` (the
/// compensator).
///
/// The inverse P–I clamps its input to the normalised range, so `S⁻¹[y]` (the P–I's output
/// `z`) must stay within the output range for the desired outputs: identification widens the
/// output range until it does.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct InverseGeneralisedPi {
    /// `S⁻¹`, the inverse dead-zone map.
    map: DeadZoneBank,
    pi: InversePrandtlIshlinskii,
    /// The forward map, to recognise the forward model ([`Self::inverts`]).
    forward_map: DeadZoneBank,
}

impl InverseGeneralisedPi {
    /// Play operators and dead zones the tick runs (the operators set its cost; the map costs
    /// the same at any number of dead zones).
    pub fn size(&self) -> (usize, usize) {
        (self.pi.operators(), self.map.dead_zones())
    }

    /// Builds the inverse of the forward model `params` (physical units), normalised by
    /// `scaling`. Refuses a non-invertible P–I or map, naming the operator or dead zone, and
    /// inverses that do not fit the fixed-point formats.
    ///
    /// ```
    /// use twinstack::models::generalised_pi::{DeadZoneParams, GeneralisedPi, GpiParams, InverseGeneralisedPi};
    /// use twinstack::{PiParams, Scaling};
    /// let params = GpiParams {
    ///     pi: PiParams::new(0.0, 0.0, &[0.0, 70.0], &[0.3, 0.1]).unwrap(),
    ///     dead_zones: DeadZoneParams::new(35.0, 1.0, &[-20.0, 10.0], &[-0.4, 0.5]).unwrap(),
    /// };
    /// let ranges = Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap();
    /// let (forward, inverse) = (
    ///     GeneralisedPi::new(&params, &ranges).unwrap(),
    ///     InverseGeneralisedPi::new(&params, &ranges).unwrap(),
    /// );
    /// // The drive the inverse asks for makes the forward model reach the target.
    /// // Both at rest at 0 V: the inverse at the forward's output there.
    /// let mut f = forward.state_at_rest(-(1 << 30));
    /// let y0 = forward.step(&mut f, -(1 << 30));
    /// let mut i = inverse.state_at_rest(y0);
    /// for target in [1 << 28, -(1 << 29), 3 << 27] {
    ///     let drive = inverse.step(&mut i, target);
    ///     assert!((forward.step(&mut f, drive) - target).abs() < 1 << 15); // one LSB16
    /// }
    /// // A slope that falls to zero beyond a dead zone has no inverse: refused, naming it.
    /// let flat = GpiParams { dead_zones: DeadZoneParams::new(35.0, 1.0, &[10.0], &[-1.0]).unwrap(), ..params };
    /// assert!(InverseGeneralisedPi::new(&flat, &ranges).is_err());
    /// ```
    #[inline(never)] // configuration, off the tick path: one copy in flash
    pub fn new(params: &GpiParams, scaling: &Scaling) -> Result<Self, ParamError> {
        let pi = InversePrandtlIshlinskii::new(&params.pi, scaling)?;
        let forward = params.dead_zones.normalized(scaling)?;
        let forward_map = DeadZoneBank::from_normalized(&forward)?;
        let map = DeadZoneBank::from_normalized(&forward.inverse()?)?;
        Ok(Self {
            map,
            pi,
            forward_map,
        })
    }

    /// Whether this is the inverse of `forward` (the same P–I and the same map): only then
    /// does [`Self::state_from_forward`] of `forward`'s state describe this compensator.
    pub fn inverts(&self, forward: &GeneralisedPi) -> bool {
        self.pi.inverts(forward.pi()) && self.forward_map == *forward.map()
    }

    /// The inverse P–I part.
    pub fn pi(&self) -> &InversePrandtlIshlinskii {
        &self.pi
    }

    /// The inverse map `S⁻¹`.
    pub fn map(&self) -> &DeadZoneBank {
        &self.map
    }

    /// The inverse's state matching the forward model's P–I operator outputs `p` (the map is
    /// static: only the P–I has memory). Off the tick path.
    pub fn state_from_forward(&self, p: &[i32; MAX_CANONICAL_OPERATORS]) -> PiState {
        self.pi.state_from_forward(p)
    }

    /// The relaxed state after resting at desired output `y` (Q2.30).
    pub fn state_at_rest(&self, y: i32) -> PiState {
        self.pi.state_at_rest(self.map.apply(clamp_full_scale(y)))
    }

    /// One sample: desired displacement `y` (Q2.30 normalised, clamped to [-1, 1]) → drive `u`
    /// (Q2.30 normalised, saturated; the caller clamps it to the drive's limits).
    #[inline(always)]
    pub fn step(&self, state: &mut PiState, y: i32) -> i32 {
        self.pi.step(state, self.map.apply(clamp_full_scale(y)))
    }
}

/// A generalised P–I's dead-zone map (the call to its one copy: the segment's search and
/// its multiply-accumulate), cycles at 5 wait states (see [`Hysteresis::cycles`]), whatever
/// its number of dead zones; the P–I part costs as a P–I
/// ([`crate::models::prandtl_ishlinskii::bank_cycles`]).
pub const DEAD_ZONE_MAP_CYCLES: u32 = 60;

/// A generalised P–I of `operators` operators in the tick (its map costs the same at any size).
fn gpi_cycles(operators: usize) -> u32 {
    bank_cycles(operators) + DEAD_ZONE_MAP_CYCLES
}

impl Hysteresis for GeneralisedPi {
    type State = PiState;

    #[inline(always)]
    fn step(&self, state: &mut PiState, u: i32) -> i32 {
        GeneralisedPi::step(self, state, u)
    }

    fn cycles(&self) -> u32 {
        gpi_cycles(self.pi.operators())
    }
}

impl Forward for GeneralisedPi {
    fn at_rest(&self, u: i32, rest: Rest) -> (PiState, i32) {
        // The map is static: only the P–I part has memory.
        let mut s = Forward::at_rest(&self.pi, u, rest).0;
        let y = GeneralisedPi::step(self, &mut s, u);
        (s, y)
    }
}

impl Hysteresis for InverseGeneralisedPi {
    type State = PiState;

    #[inline(always)]
    fn step(&self, state: &mut PiState, y: i32) -> i32 {
        InverseGeneralisedPi::step(self, state, y)
    }

    fn cycles(&self) -> u32 {
        gpi_cycles(self.pi.operators())
    }
}

impl Inverse for InverseGeneralisedPi {
    /// As the P–I's, at the map's output of `y`.
    fn at_rest(&self, u: i32, y: i32, rest: Rest) -> PiState {
        Inverse::at_rest(&self.pi, u, self.map.apply(clamp_full_scale(y)), rest)
    }

    /// As for the P–I: the map is static, so only the P–I part's operators carry over.
    type Forward = GeneralisedPi;

    fn matching(&self, forward: &GeneralisedPi, state: &PiState) -> Option<PiState> {
        self.inverts(forward)
            .then(|| self.state_from_forward(&forward.pi().bank().outputs(state)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed_point::{signal_to_f64, SIGNAL_ONE};
    use proptest::prelude::*;

    extern crate std;
    use std::vec::Vec as HVec;

    fn ranges() -> Scaling {
        Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap()
    }

    fn pi() -> PiParams {
        PiParams::new(
            0.0,
            0.0,
            &[0.0, 35.0, 70.0, 105.0],
            &[0.25, 0.1, 0.08, 0.05],
        )
        .unwrap()
    }

    /// A valid map from raw draws: thresholds spread either side of the centre, weights
    /// shrunk until every slope is at least 0.2.
    fn map(centre: f64, linear: f64, raw: &[(f64, f64)]) -> DeadZoneParams {
        let mut t: HVec<(f64, f64)> = raw.to_vec();
        t.sort_by(|a, b| a.0.total_cmp(&b.0));
        t.dedup_by(|a, b| (a.0 - b.0).abs() < 0.5);
        t.retain(|x| x.0.abs() >= 0.5);
        let (d, mut g): (HVec<f64>, HVec<f64>) = t.into_iter().unzip();
        loop {
            let m = DeadZoneParams::new(centre, linear, &d, &g).unwrap();
            let ok = m
                .slopes()
                .map(|s| s[..d.len()].iter().all(|&(_, a)| a >= 0.2))
                .unwrap_or(false);
            if ok {
                return m;
            }
            g.iter_mut().for_each(|w| *w *= 0.5);
        }
    }

    fn numeric_inverse(m: &DeadZoneParams, y: f64) -> f64 {
        let (mut lo, mut hi) = (-1.0e4, 1.0e4);
        for _ in 0..200 {
            let mid = 0.5 * (lo + hi);
            if m.apply(mid) < y {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        0.5 * (lo + hi)
    }

    /// The map as the zone-by-zone sum `c + g_0·x + Σ_j g_j·clamp(x − d_j, lo_j, hi_j)`
    /// (`[0, MAX]` above the centre, `[MIN, 0]` below), exact in `i64` and rounded once: what
    /// the segment table must give bit for bit.
    fn zone_by_zone(n: &DeadZoneParams, z: i32) -> i32 {
        let centre = signal_from_f64(n.centre);
        let x = z.saturating_sub(centre);
        let mut acc =
            gain_from_f64(n.linear) as i64 * x as i64 + ((centre as i64) << GAIN_FRAC_BITS);
        for (&d, &g) in n.thresholds.iter().zip(&n.weights) {
            let (lo, hi) = if d > 0.0 {
                (0, i32::MAX)
            } else {
                (i32::MIN, 0)
            };
            let zone = x.saturating_sub(signal_from_f64(d)).clamp(lo, hi);
            acc += gain_from_f64(g) as i64 * zone as i64;
        }
        q54_to_signal_floor(acc)
    }

    proptest! {
        /// The segment table is the zone-by-zone sum bit for bit: on any valid map (either
        /// side of the centre, up to the largest normalised threshold) and any input, the
        /// breakpoints themselves and their neighbours included, and for the map's inverse.
        #[test]
        fn the_segment_table_is_the_zone_by_zone_sum_bit_for_bit(
            centre in -1.0f64..1.0,
            linear in 0.3f64..3.0,
            raw in proptest::collection::vec((-1.95f64..1.95, -1.5f64..1.5), 0..=MAX_DEAD_ZONES),
            zs in proptest::collection::vec(any::<i32>(), 1..40),
        ) {
            let m = map(centre, linear, &raw.iter().map(|&(d, g)| (d * 60.0, g)).collect::<HVec<_>>());
            let m = DeadZoneParams { thresholds: m.thresholds.iter().map(|d| d / 60.0).collect(), ..m };
            prop_assume!(m.check_fixed_point_range().is_ok());
            let mut maps = HVec::from([m.clone()]);
            if let Ok(inv) = m.inverse() {
                if inv.check_fixed_point_range().is_ok() {
                    maps.push(inv);
                }
            }
            for n in &maps {
                let bank = DeadZoneBank::from_normalized(n).unwrap();
                let centre = signal_from_f64(n.centre);
                let mut inputs: HVec<i32> = zs.clone();
                for &d in &n.thresholds {
                    let at = centre.saturating_add(signal_from_f64(d));
                    inputs.extend([at.saturating_sub(1), at, at.saturating_add(1)]);
                }
                inputs.extend([i32::MIN, i32::MAX, centre, -SIGNAL_ONE, SIGNAL_ONE - 1]);
                for z in inputs {
                    prop_assert_eq!(bank.apply(z), zone_by_zone(n, z), "z = {}", z);
                }
            }
        }

        /// The closed-form inverse map agrees with a bisection on the forward map.
        #[test]
        fn the_closed_form_inverse_is_the_numeric_inverse(
            centre in -20.0f64..20.0,
            linear in 0.3f64..3.0,
            raw in proptest::collection::vec((-30.0f64..30.0, -1.5f64..1.5), 0..=MAX_DEAD_ZONES),
            ys in proptest::collection::vec(-80.0f64..80.0, 1..20),
        ) {
            let m = map(centre, linear, &raw);
            let inv = m.inverse().unwrap();
            for y in ys {
                let numeric = numeric_inverse(&m, y);
                prop_assert!((inv.apply(y) - numeric).abs() < 1e-9 * (1.0 + y.abs()),
                    "{} vs {}", inv.apply(y), numeric);
                prop_assert!((m.apply(inv.apply(y)) - y).abs() < 1e-9 * (1.0 + y.abs()));
            }
        }

        /// The fixed-point map stays within the Q8.24 gains' rounding of the `f64` map (each
        /// gain is off by up to 2^-25, times |x| < 2, over up to 9 gains: < 1e-6, i.e. 0.03 LSB
        /// of a 16-bit output), and the fixed-point inverse map undoes it as closely (the
        /// forward error divided by the smallest slope, 0.2, plus the inverse's own: < 2^13 LSB
        /// of Q2.30).
        #[test]
        fn the_fixed_point_map_tracks_f64_and_its_inverse_undoes_it(
            centre in -0.5f64..0.5,
            linear in 0.3f64..3.0,
            raw in proptest::collection::vec((-0.9f64..0.9, -1.5f64..1.5), 0..=MAX_DEAD_ZONES),
            zs in proptest::collection::vec(-1.0f64..1.0, 1..50),
        ) {
            let m = map(centre, linear, &raw.iter().map(|&(d, g)| (d * 60.0, g)).collect::<HVec<_>>());
            let m = DeadZoneParams { thresholds: m.thresholds.iter().map(|d| d / 60.0).collect(), ..m };
            let inv = m.inverse().unwrap();
            prop_assume!(m.check_fixed_point_range().is_ok() && inv.check_fixed_point_range().is_ok());
            let (fwd, back) = (DeadZoneBank::from_normalized(&m).unwrap(), DeadZoneBank::from_normalized(&inv).unwrap());
            for z in zs {
                let y = m.apply(z);
                // Q2.30 holds |z − c|, |y − c| < 2 (the inverse's input is within ±1 and the
                // centre within the output range, so on the board this holds).
                prop_assume!(y.abs() < 1.9 && (y - m.centre).abs() < 1.9 && (z - m.centre).abs() < 1.9);
                let yq = fwd.apply(signal_from_f64(z));
                prop_assert!((signal_to_f64(yq) - y).abs() < 1e-6, "{} vs {}", signal_to_f64(yq), y);
                let zq = back.apply(yq);
                prop_assert!((zq as i64 - signal_from_f64(z) as i64).abs() < 1 << 13, "{} vs {}", zq, signal_from_f64(z));
            }
        }

        /// On any drive, the inverse generalised P–I fed the forward model's output gives the
        /// drive back, up to the fixed point's rounding: the P–I banks' Q1.15 grid (half a
        /// step of the inverse's input, and of each threshold, 1 LSB16 in all) times the
        /// inverse's steepest slope, `1 / (w_1 · 0.2)` here (the P–I's first normalised weight,
        /// the map's smallest slope), plus a step of the drive.
        #[test]
        fn inverse_after_forward_is_the_identity_on_random_drives(
            centre in 25.0f64..45.0,
            linear in 0.6f64..1.5,
            raw in proptest::collection::vec((-25.0f64..25.0, -0.4f64..0.8), 0..=6),
            drive in proptest::collection::vec(-1.0f64..1.0, 1..300),
        ) {
            let params = GpiParams { pi: pi(), dead_zones: map(centre, linear, &raw) };
            // Wide enough an output range for both z = PI[u] and y = S[z].
            let s = Scaling::new(0.0, 140.0, -60.0, 130.0).unwrap();
            let (f, i) = (GeneralisedPi::new(&params, &s).unwrap(), InverseGeneralisedPi::new(&params, &s).unwrap());
            let u0 = signal_from_f64(drive[0]);
            let mut fs = f.state_at_rest(u0);
            let mut is = i.state_from_forward(&f.pi().bank().outputs(&fs));
            let w1 = 0.25 * s.input_half_span() / s.output_half_span();
            let bound = (1.0 + 1.0 / (w1 * 0.2)) * (1 << 15) as f64;
            for u in drive {
                let u = signal_from_f64(u);
                let y = f.step(&mut fs, u);
                // An output beyond the range is clamped by the inverse: no identity to check.
                prop_assume!(y > -SIGNAL_ONE && y < SIGNAL_ONE);
                let back = i.step(&mut is, y);
                prop_assert!(((back as i64 - u as i64).abs() as f64) < bound, "{} vs {}", back, u);
            }
        }
    }

    #[test]
    fn refusals_name_the_dead_zone() {
        let bad = |c: f64, l: f64, d: &[f64], g: &[f64]| {
            DeadZoneParams::new(c, l, d, g).and_then(|m| m.validate())
        };
        assert_eq!(
            DeadZoneParams::new(0.0, 1.0, &[1.0; 9], &[0.1; 9]),
            Err(ParamError::TooManyDeadZones { count: 9 })
        );
        assert_eq!(
            bad(0.0, 1.0, &[1.0], &[]),
            Err(ParamError::DeadZoneLengthMismatch {
                thresholds: 1,
                weights: 0
            })
        );
        assert_eq!(
            bad(0.0, 1.0, &[-1.0, 0.0], &[0.1, 0.1]),
            Err(ParamError::DeadZoneThresholdsNotIncreasing { dead_zone: 2 })
        );
        assert_eq!(
            bad(0.0, 1.0, &[-1.0, 2.0, 2.0], &[0.1, 0.1, 0.1]),
            Err(ParamError::DeadZoneThresholdsNotIncreasing { dead_zone: 3 })
        );
        assert_eq!(
            bad(0.0, 0.0, &[1.0], &[0.1]),
            Err(ParamError::DeadZoneLinearNotPositive)
        );
        // Below the centre, dead zone 2 (at −1) is passed first, then dead zone 1 (at −2).
        assert_eq!(
            bad(0.0, 1.0, &[-2.0, -1.0, 1.0], &[-0.6, -0.5, 0.2]),
            Err(ParamError::DeadZoneSlopeNotPositive { dead_zone: 1 })
        );
        assert_eq!(
            bad(0.0, 1.0, &[-2.0, 1.0, 3.0], &[0.5, -0.7, -0.4]),
            Err(ParamError::DeadZoneSlopeNotPositive { dead_zone: 3 })
        );
        assert_eq!(bad(f64::NAN, 1.0, &[], &[]), Err(ParamError::NotFinite));
        // Fixed-point range: a threshold beyond the output span, a steep inverse.
        let s = ranges();
        let p = |d: DeadZoneParams| GpiParams {
            pi: pi(),
            dead_zones: d,
        };
        assert_eq!(
            GeneralisedPi::new(
                &p(DeadZoneParams::new(35.0, 1.0, &[80.0], &[0.1]).unwrap()),
                &s
            ),
            Err(ParamError::DeadZoneThresholdOutOfRange { dead_zone: 1 })
        );
        assert_eq!(
            InverseGeneralisedPi::new(
                &p(DeadZoneParams::new(35.0, 1.0, &[10.0], &[-0.995]).unwrap()),
                &s
            )
            .map(|_| ()),
            Err(ParamError::DeadZoneWeightOutOfRange { dead_zone: 1 })
        );
        assert_eq!(
            GeneralisedPi::new(&p(DeadZoneParams::new(500.0, 1.0, &[], &[]).unwrap()), &s),
            Err(ParamError::DeadZoneCentreOutOfRange)
        );
        // The P–I part is checked first, with its own errors.
        let mut q = p(DeadZoneParams::identity());
        q.pi.weights[0] = -0.3;
        assert_eq!(
            InverseGeneralisedPi::new(&q, &s).map(|_| ()),
            Err(ParamError::FirstWeightNotPositive)
        );
    }

    #[test]
    fn the_identity_map_makes_it_the_plain_pi_bit_for_bit() {
        let s = ranges();
        let g = GpiParams {
            pi: pi(),
            dead_zones: DeadZoneParams {
                centre: 20.0,
                ..DeadZoneParams::identity()
            },
        };
        let (f, i) = (
            GeneralisedPi::new(&g, &s).unwrap(),
            InverseGeneralisedPi::new(&g, &s).unwrap(),
        );
        let (pf, pinv) = (
            PrandtlIshlinskii::new(&pi(), &s).unwrap(),
            InversePrandtlIshlinskii::new(&pi(), &s).unwrap(),
        );
        let (mut a, mut b) = (f.state_at_rest(0), pf.state_at_rest(0));
        let (mut c, mut d) = (i.state_at_rest(0), pinv.state_at_rest(0));
        for k in 0..2000 {
            let x: i32 = (k * 7919) % 2001 - 1000;
            let x = x * (SIGNAL_ONE / 1000);
            assert_eq!(f.step(&mut a, x), pf.step(&mut b, x));
            assert_eq!(i.step(&mut c, x), pinv.step(&mut d, x));
        }
        assert!(i.inverts(&f));
        let other = GeneralisedPi::new(
            &GpiParams {
                dead_zones: DeadZoneParams::new(20.0, 1.0, &[5.0], &[0.1]).unwrap(),
                ..g
            },
            &s,
        )
        .unwrap();
        assert!(!i.inverts(&other), "another map is not the model inverted");
    }
}
