//! A laboratory stage that is deliberately **not** a member of the project's model family: the
//! plant the tracking harness (`twinstack lab-stage`) identifies and then tracks on, open loop.
//!
//! The models the project fits are the symmetric Prandtl–Ishlinskii (P–I), Duhem, a
//! generalised P–I (P–I followed by a piecewise-linear dead-zone output map), Bouc–Wen, and a
//! creep operator of up to six first-order modes (ms to 100 s) in series. A stage built from
//! any of them would flatter the models; this one is built from physics none of them can
//! represent exactly, so what the harness measures is how well they *approximate* a real
//! stage. One input, the drive `u` (volts, clamped to `0 … drive_max_volts`), one output, the
//! sensor's reading (µm), one sample period per [`LabStage::step`]. The signal chain:
//!
//! ```text
//! u ──► Preisach h(v) ──► p = r·v + (1−r)·h ──► creep c(t) ──► flexure N ──► resonance G ──► sensor
//!       v = u/u_max          (normalised)        x_free = S·(p + Σ w_i z_i)     (µm)          + noise, LSB
//! ```
//!
//! ## Hysteresis: a Preisach model with an asymmetric density
//! `h(t) = ∬_{β ≤ α} μ(α, β) γ_{αβ}[v](t) dα dβ`, where `γ_{αβ}` is a relay that switches to 1
//! when `v ≥ α` and to 0 when `v < β`, over the normalised input `v ∈ [0, 1]`. The density is
//!
//! `μ(α, β) ∝ exp(−(α − β)/w) · (1 − a α²) · (1 − b (1 − β)²)`
//!
//! on a triangular grid of `n` levels (`n(n+1)/2` cells, each a block of relays whose
//! thresholds are spread uniformly over the cell, i.e. a piecewise-constant density; the output
//! has no staircase). `1 − a α²` thins the relays that switch up near the top (the rising
//! branch saturates there), `1 − b (1 − β)²` thins those that switch down near the bottom, and
//! `a ≠ b`: rising and falling branches saturate differently. A P–I operator is the Preisach
//! operator whose density depends on `α − β` alone (its loops are point-symmetric); this
//! density is not, so no P–I — nor a P–I followed by any output map fitted to the major loop —
//! reproduces both branches and the minor loops. The model is run exactly through its memory
//! (the staircase of dominant input extrema, with the wiping-out rule) and the Everett
//! function `E(α′, β′) = ∬_{β′ ≤ β ≤ α ≤ α′} μ`, evaluated in O(1) from prefix sums: a step
//! costs O(1) amortised. A fraction `r` of the stroke is reversible (`r·v`).
//!
//! The rest state at `u0` ([`LabStage::rest`]) is the one a unipolar actuator is in after
//! being raised slowly from 0 V (where every relay is off) to `u0` and held until the creep has
//! settled.
//!
//! ## Or: a Bouc–Wen-class hysteresis
//! With [`LabStageConfig::hysteresis`] set to [`StageHysteresis::BoucWen`] the Preisach block
//! is replaced by a Bouc–Wen-class operator outside the family's Bouc–Wen (exponent 1.5, a
//! rising branch that saturates sooner than the falling one, non-congruent minor loops,
//! integrated in the input; [`BoucWenClass`]), its major loop mapped onto the same 0 … 1; the
//! rest of the chain is the same.
//!
//! ## Creep over decades
//! `x_free = S (p + Σ_i w_i z_i)`, `τ_i ż_i = p − z_i`, with `τ_i` log-spaced from
//! `creep_fastest_s` (0.1 ms) to `creep_slowest_s` (10⁴ s), `m` modes per decade and equal
//! weights `w_i = γ/m`. After a step of `p` the modes add `γ log10(t/τ_fastest)` of the step
//! for `τ_fastest ≪ t ≪ τ_slowest`: the logarithmic creep law of piezo stacks, `γ` ≈ 1–2 % per
//! decade in manufacturers' data (default 1.5 %). Seventeen modes over eight decades, driven
//! by the Preisach output: not the family's creep operator (≤ 6 modes, ms to 100 s), and its
//! creep never ends within any record a user takes. Each mode is discretised exactly with `p`
//! held over the period.
//!
//! ## Static nonlinearity: the flexure
//! The flexure guide stiffens at large deflection; the static deflection is
//! `N(x) = X tanh(x / X)` of the free stroke (`X = flexure_saturation_um`, 200 µm by default:
//! about 5 % short at 80 µm). Smooth, odd, saturating: not piecewise linear (the generalised
//! P–I's output map), and applied before the dynamics.
//!
//! ## Resonance
//! `G(s) = ω_n² / (s² + 2ζ ω_n s + ω_n²)`, `f_n` = 3.5 kHz, `ζ` = 0.03 by default, integrated
//! exactly with the input held over the period ([`twinstack_identify::zero_order_hold`]): stable and
//! exact at any sample rate.
//!
//! ## Sensor
//! The reading is the position plus Gaussian white noise (`noise_rms_nm`, 2 nm RMS by default,
//! seeded: [`crate::converters::GaussianNoise`]) rounded to the sensor's resolution
//! (`sensor_lsb_nm`, 2 nm; 0 for none). The same seed gives the same record, bit for bit.

use crate::converters::GaussianNoise;
use twinstack_identify::zero_order_hold::ZeroOrderHold;

mod bouc_wen;
use bouc_wen::BoucWenStage;
pub use bouc_wen::{BoucWenClass, MAX_SUBSTEP};

/// Which hysteresis the stage has: the Preisach operator (the default) or the Bouc–Wen-class
/// one ([`BoucWenClass`], see the module `bouc_wen`'s doc), each outside the model family.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum StageHysteresis {
    /// The Preisach operator with the asymmetric density ([`LabStageConfig::preisach`]).
    #[default]
    Preisach,
    /// The Bouc–Wen-class operator ([`LabStageConfig::bouc_wen`]).
    BoucWen,
}

impl StageHysteresis {
    /// The prefix of its fields in [`SETTABLE_FIELDS`].
    pub fn prefix(self) -> &'static str {
        match self {
            Self::Preisach => "preisach.",
            Self::BoucWen => "bouc_wen.",
        }
    }
}

/// The Preisach density `μ(α, β) ∝ exp(−(α − β)/w) (1 − a α²) (1 − b (1 − β)²)` and its grid.
#[derive(Clone, Debug, PartialEq)]
pub struct PreisachDensity {
    /// Grid levels `n` over the input range (4 … 400).
    pub levels: usize,
    /// Fraction `r` of the stroke that is reversible (`0 ≤ r < 1`).
    pub reversible: f64,
    /// `w`: how far from the diagonal the density reaches, in units of the input range
    /// (sets the loop width; `> 0`).
    pub width: f64,
    /// `a`: thinning of the up-switching thresholds near the top (`0 ≤ a < 1`).
    pub top_saturation: f64,
    /// `b`: thinning of the down-switching thresholds near the bottom (`0 ≤ b < 1`).
    pub bottom_saturation: f64,
}

impl PreisachDensity {
    /// The unnormalised density at `(α, β)` (0 where `β > α`).
    pub fn density(&self, alpha: f64, beta: f64) -> f64 {
        if beta > alpha {
            return 0.0;
        }
        let d = 1.0 - beta;
        (-(alpha - beta) / self.width).exp()
            * (1.0 - self.top_saturation * alpha * alpha)
            * (1.0 - self.bottom_saturation * d * d)
    }
}

impl Default for PreisachDensity {
    /// 50 levels, 40 % reversible, `w` = 0.15, `a` = 0.6, `b` = 0.2.
    fn default() -> Self {
        Self {
            levels: 50,
            reversible: 0.4,
            width: 0.15,
            top_saturation: 0.6,
            bottom_saturation: 0.2,
        }
    }
}

/// Everything that defines a [`LabStage`].
#[derive(Clone, Debug, PartialEq)]
pub struct LabStageConfig {
    /// Sample period, seconds (the drive is held over it).
    pub sample_period_s: f64,
    /// Seed of the sensor noise.
    pub seed: u64,
    /// The amplifier's upper rail, volts (the drive is clamped to `0 …` this).
    pub drive_max_volts: f64,
    /// `S`: free stroke of the stack at full drive before creep and the flexure, µm.
    pub stroke_um: f64,
    /// Which hysteresis the stage has; the other's parameters are not used.
    pub hysteresis: StageHysteresis,
    /// The Preisach hysteresis (where [`Self::hysteresis`] is `Preisach`).
    pub preisach: PreisachDensity,
    /// The Bouc–Wen-class hysteresis (where [`Self::hysteresis`] is `BoucWen`).
    pub bouc_wen: BoucWenClass,
    /// `γ`: creep per decade of time, fraction of a step (`≥ 0`; 0 for none).
    pub creep_per_decade: f64,
    /// Fastest creep mode, seconds.
    pub creep_fastest_s: f64,
    /// Slowest creep mode, seconds.
    pub creep_slowest_s: f64,
    /// Creep modes per decade (1 … 10).
    pub creep_modes_per_decade: usize,
    /// `X` of the flexure's `X tanh(x/X)`, µm (`f64::INFINITY` for a linear flexure).
    pub flexure_saturation_um: f64,
    /// Natural frequency of the resonance, Hz.
    pub resonance_hz: f64,
    /// Damping ratio of the resonance (`0 < ζ < 1`).
    pub damping_ratio: f64,
    /// Sensor noise, nm RMS (`≥ 0`).
    pub noise_rms_nm: f64,
    /// Sensor resolution, nm (`≥ 0`; 0 for none).
    pub sensor_lsb_nm: f64,
}

impl LabStageConfig {
    /// The default stage sampled at `sample_rate_hz` with noise seed `seed`: 0…150 V,
    /// 80 µm free stroke, the default [`PreisachDensity`], 1.5 %/decade creep from 0.1 ms to
    /// 10⁴ s (two modes per decade), a 200 µm flexure saturation, a 3.5 kHz resonance with
    /// `ζ` = 0.03, 2 nm RMS noise and a 2 nm sensor resolution.
    ///
    /// ```
    /// use hal_sim::plant::{LabStage, LabStageConfig};
    /// let mut stage = LabStage::new(&LabStageConfig::new(10_000.0, 7)).unwrap();
    /// let x = (0..1000).map(|_| stage.step(150.0)).last().unwrap();
    /// assert!(x > 60.0 && x < 100.0, "full drive gives most of the stroke: {x} µm");
    /// ```
    pub fn new(sample_rate_hz: f64, seed: u64) -> Self {
        Self {
            sample_period_s: 1.0 / sample_rate_hz,
            seed,
            drive_max_volts: 150.0,
            stroke_um: 80.0,
            hysteresis: StageHysteresis::Preisach,
            preisach: PreisachDensity::default(),
            bouc_wen: BoucWenClass::default(),
            creep_per_decade: 0.015,
            creep_fastest_s: 1e-4,
            creep_slowest_s: 1e4,
            creep_modes_per_decade: 2,
            flexure_saturation_um: 200.0,
            resonance_hz: 3500.0,
            damping_ratio: 0.03,
            noise_rms_nm: 2.0,
            sensor_lsb_nm: 2.0,
        }
    }
}

/// A [`LabStageConfig`] field that is out of range.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
#[error("lab stage: `{field}` = {value:?}: {rule}")]
pub struct LabStageError {
    /// The field's name.
    pub field: &'static str,
    /// The value given.
    pub value: f64,
    /// What it must be.
    pub rule: &'static str,
}

fn check(
    field: &'static str,
    value: f64,
    ok: bool,
    rule: &'static str,
) -> Result<(), LabStageError> {
    if ok && !value.is_nan() {
        Ok(())
    } else {
        Err(LabStageError { field, value, rule })
    }
}

/// The fields [`LabStageConfig::set`] takes, by the names [`LabStageConfig::validate`] gives
/// them (one name per quantity, in the units the field's doc gives).
pub const SETTABLE_FIELDS: [&str; 21] = [
    "drive_max_volts",
    "stroke_um",
    "preisach.levels",
    "preisach.reversible",
    "preisach.width",
    "preisach.top_saturation",
    "preisach.bottom_saturation",
    "bouc_wen.alpha",
    "bouc_wen.beta",
    "bouc_wen.gamma",
    "bouc_wen.rising",
    "bouc_wen.exponent",
    "creep_per_decade",
    "creep_fastest_s",
    "creep_slowest_s",
    "creep_modes_per_decade",
    "flexure_saturation_um",
    "resonance_hz",
    "damping_ratio",
    "noise_rms_nm",
    "sensor_lsb_nm",
];

/// Why [`LabStageConfig::set`] refused a field.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SetFieldError {
    /// No field of that name.
    #[error("lab stage: no field `{0}` (the fields: {fields})", fields = SETTABLE_FIELDS.join(", "))]
    Unknown(String),
    /// A count given a value that is not a whole number.
    #[error("lab stage: `{field}` = {value}: a count, must be a whole number")]
    NotWhole {
        /// The field's name.
        field: &'static str,
        /// The value given.
        value: f64,
    },
}

impl LabStageConfig {
    /// Sets one field by its name (one of [`SETTABLE_FIELDS`], as [`Self::validate`] names
    /// it) to `value`: a stage other than the default, for checking that what was tuned on the
    /// default also holds off it. The range is checked by [`Self::validate`] (and so by
    /// [`LabStage::new`]), not here; a count (`preisach.levels`, `creep_modes_per_decade`)
    /// must be a whole number.
    ///
    /// ```
    /// use hal_sim::plant::LabStageConfig;
    /// let mut c = LabStageConfig::new(10_000.0, 1);
    /// c.set("preisach.bottom_saturation", 0.6).unwrap();
    /// assert_eq!(c.preisach.bottom_saturation, 0.6);
    /// assert!(c.set("preisach.levels", 2.5).is_err());
    /// assert!(c.set("stiffness", 1.0).is_err());
    /// ```
    pub fn set(&mut self, field: &str, value: f64) -> Result<(), SetFieldError> {
        let whole = |field: &'static str| {
            if value.fract() == 0.0 && (0.0..=1e6).contains(&value) {
                Ok(value as usize)
            } else {
                Err(SetFieldError::NotWhole { field, value })
            }
        };
        let p = &mut self.preisach;
        match field {
            "drive_max_volts" => self.drive_max_volts = value,
            "stroke_um" => self.stroke_um = value,
            "preisach.levels" => p.levels = whole("preisach.levels")?,
            "preisach.reversible" => p.reversible = value,
            "preisach.width" => p.width = value,
            "preisach.top_saturation" => p.top_saturation = value,
            "preisach.bottom_saturation" => p.bottom_saturation = value,
            "bouc_wen.alpha" => self.bouc_wen.alpha = value,
            "bouc_wen.beta" => self.bouc_wen.beta = value,
            "bouc_wen.gamma" => self.bouc_wen.gamma = value,
            "bouc_wen.rising" => self.bouc_wen.rising = value,
            "bouc_wen.exponent" => self.bouc_wen.exponent = value,
            "creep_per_decade" => self.creep_per_decade = value,
            "creep_fastest_s" => self.creep_fastest_s = value,
            "creep_slowest_s" => self.creep_slowest_s = value,
            "creep_modes_per_decade" => {
                self.creep_modes_per_decade = whole("creep_modes_per_decade")?
            }
            "flexure_saturation_um" => self.flexure_saturation_um = value,
            "resonance_hz" => self.resonance_hz = value,
            "damping_ratio" => self.damping_ratio = value,
            "noise_rms_nm" => self.noise_rms_nm = value,
            "sensor_lsb_nm" => self.sensor_lsb_nm = value,
            other => return Err(SetFieldError::Unknown(other.to_string())),
        }
        Ok(())
    }

    /// Checks every field; the first one out of range is named.
    pub fn validate(&self) -> Result<(), LabStageError> {
        let c = self;
        let p = &c.preisach;
        let pos = |v: f64| v.is_finite() && v > 0.0;
        let frac = |v: f64| (0.0..1.0).contains(&v);
        check(
            "sample_period_s",
            c.sample_period_s,
            pos(c.sample_period_s),
            "finite and positive",
        )?;
        check(
            "drive_max_volts",
            c.drive_max_volts,
            pos(c.drive_max_volts),
            "finite and positive",
        )?;
        check(
            "stroke_um",
            c.stroke_um,
            pos(c.stroke_um),
            "finite and positive",
        )?;
        let b = &c.bouc_wen;
        let weight = |v: f64| v.is_finite() && (0.0..=1000.0).contains(&v);
        check(
            "bouc_wen.alpha",
            b.alpha,
            b.alpha > 0.0 && b.alpha < 1.0,
            "within 0 … 1 (exclusive)",
        )?;
        check(
            "bouc_wen.beta",
            b.beta,
            weight(b.beta) && b.beta > 0.0,
            "within 0 … 1000, not 0",
        )?;
        check(
            "bouc_wen.gamma",
            b.gamma,
            b.gamma >= 0.0 && b.gamma <= b.beta,
            "within 0 … bouc_wen.beta (on a reversal the state relaxes)",
        )?;
        check(
            "bouc_wen.rising",
            b.rising,
            weight(b.rising),
            "within 0 … 1000",
        )?;
        check(
            "bouc_wen.exponent",
            b.exponent,
            (1.0..=4.0).contains(&b.exponent),
            "within 1 … 4",
        )?;
        check(
            "preisach.levels",
            p.levels as f64,
            (4..=400).contains(&p.levels),
            "4 … 400",
        )?;
        check(
            "preisach.reversible",
            p.reversible,
            frac(p.reversible),
            "0 ≤ r < 1",
        )?;
        check(
            "preisach.width",
            p.width,
            pos(p.width),
            "finite and positive",
        )?;
        check(
            "preisach.top_saturation",
            p.top_saturation,
            frac(p.top_saturation),
            "0 ≤ a < 1",
        )?;
        check(
            "preisach.bottom_saturation",
            p.bottom_saturation,
            frac(p.bottom_saturation),
            "0 ≤ b < 1",
        )?;
        check(
            "creep_per_decade",
            c.creep_per_decade,
            c.creep_per_decade.is_finite() && c.creep_per_decade >= 0.0,
            "finite and ≥ 0",
        )?;
        check(
            "creep_fastest_s",
            c.creep_fastest_s,
            (1e-9..=1e9).contains(&c.creep_fastest_s),
            "from 1e-9 to 1e9 s",
        )?;
        check(
            "creep_slowest_s",
            c.creep_slowest_s,
            c.creep_slowest_s >= c.creep_fastest_s
                && c.creep_slowest_s <= MAX_CREEP_DECADES_RATIO * c.creep_fastest_s,
            "≥ creep_fastest_s and at most 12 decades above it",
        )?;
        check(
            "creep_modes_per_decade",
            c.creep_modes_per_decade as f64,
            (1..=10).contains(&c.creep_modes_per_decade),
            "1 … 10",
        )?;
        check(
            "flexure_saturation_um",
            c.flexure_saturation_um,
            c.flexure_saturation_um > 0.0,
            "positive (infinite for a linear flexure)",
        )?;
        check(
            "resonance_hz",
            c.resonance_hz,
            pos(c.resonance_hz),
            "finite and positive",
        )?;
        check(
            "damping_ratio",
            c.damping_ratio,
            c.damping_ratio > 0.0 && c.damping_ratio < 1.0,
            "0 < ζ < 1",
        )?;
        check(
            "noise_rms_nm",
            c.noise_rms_nm,
            c.noise_rms_nm.is_finite() && c.noise_rms_nm >= 0.0,
            "finite and ≥ 0",
        )?;
        check(
            "sensor_lsb_nm",
            c.sensor_lsb_nm,
            c.sensor_lsb_nm.is_finite() && c.sensor_lsb_nm >= 0.0,
            "finite and ≥ 0",
        )
    }
}

/// The Preisach operator on `v ∈ [0, 1]`: the density's cell masses, the prefix sums that
/// give the Everett function in O(1), and the memory (staircase of dominant extrema).
#[derive(Clone, Debug, PartialEq)]
struct Preisach {
    n: usize,
    /// Cell masses `w(i, j)`, `j ≤ i`, at `i(i+1)/2 + j`; they sum to 1.
    cells: Vec<f64>,
    /// `R(i, j) = Σ_{j′<j} w(i, j′)`, `j ∈ 0..=n`, at `i(n+1) + j`.
    row_prefix: Vec<f64>,
    /// `C(j, i) = Σ_{j ≤ i′ < i} w(i′, j)`, `i ∈ 0..=n`, at `j(n+1) + i`.
    col_prefix: Vec<f64>,
    /// `F(I, J) = Σ_{J ≤ j ≤ i ≤ I} w(i, j)` at `I n + J` (0 for `J > I`).
    full: Vec<f64>,
    /// Turning points `p_0 = 0, p_1 (max), p_2 (min), …`.
    turns: Vec<f64>,
    /// `sums[k]`: the Everett terms fixed by `turns[..=k]`.
    sums: Vec<f64>,
    /// The current input.
    v: f64,
}

impl Preisach {
    fn new(d: &PreisachDensity) -> Self {
        let n = d.levels;
        let h = 1.0 / n as f64;
        let mut cells = Vec::with_capacity(n * (n + 1) / 2);
        for i in 0..n {
            for j in 0..=i {
                let (a, b) = ((i as f64 + 0.5) * h, (j as f64 + 0.5) * h);
                // Diagonal cells are half squares, with their centroid inside.
                let (a, b, area) = if i == j {
                    (a + h / 6.0, b - h / 6.0, 0.5 * h * h)
                } else {
                    (a, b, h * h)
                };
                cells.push(d.density(a, b) * area);
            }
        }
        let total: f64 = cells.iter().sum();
        cells.iter_mut().for_each(|w| *w /= total);
        let w = |i: usize, j: usize| cells[i * (i + 1) / 2 + j];
        let mut row_prefix = vec![0.0; n * (n + 1)];
        let mut col_prefix = vec![0.0; n * (n + 1)];
        for i in 0..n {
            for j in 0..n {
                let cell = if j <= i { w(i, j) } else { 0.0 };
                row_prefix[i * (n + 1) + j + 1] = row_prefix[i * (n + 1) + j] + cell;
            }
        }
        for j in 0..n {
            for i in 0..n {
                let cell = if j <= i { w(i, j) } else { 0.0 };
                col_prefix[j * (n + 1) + i + 1] = col_prefix[j * (n + 1) + i] + cell;
            }
        }
        let mut full = vec![0.0; n * n];
        for jj in 0..n {
            let mut acc = 0.0;
            for ii in jj..n {
                acc += row_prefix[ii * (n + 1) + ii + 1] - row_prefix[ii * (n + 1) + jj];
                full[ii * n + jj] = acc;
            }
        }
        let mut p = Self {
            n,
            cells,
            row_prefix,
            col_prefix,
            full,
            turns: Vec::new(),
            sums: Vec::new(),
            v: 0.0,
        };
        p.rest(0.0);
        p
    }

    fn cell(&self, i: usize, j: usize) -> f64 {
        self.cells[i * (i + 1) / 2 + j]
    }

    /// Cell index and fraction within it of `x ∈ [0, 1]`.
    fn locate(&self, x: f64) -> (usize, f64) {
        let s = x * self.n as f64;
        let i = (s.floor() as usize).min(self.n - 1);
        (i, s - i as f64)
    }

    /// The Everett function: mass of `{b ≤ β ≤ α ≤ a}`.
    fn everett(&self, a: f64, b: f64) -> f64 {
        if a <= b {
            return 0.0;
        }
        let n1 = self.n + 1;
        let (ia, fa) = self.locate(a);
        let (jb, fb) = self.locate(b);
        if ia == jb {
            let d = fa - fb;
            return d * d * self.cell(ia, ia);
        }
        // ia > jb: whole cells, the partial row ia, the partial column jb, the corner, and
        // the two partial diagonal cells.
        let whole = if jb + 1 < ia {
            self.full[(ia - 1) * self.n + jb + 1]
        } else {
            0.0
        };
        let row = fa * (self.row_prefix[ia * n1 + ia] - self.row_prefix[ia * n1 + jb + 1]);
        let col = (1.0 - fb) * (self.col_prefix[jb * n1 + ia] - self.col_prefix[jb * n1 + jb + 1]);
        let corner = fa * (1.0 - fb) * self.cell(ia, jb);
        let diagonal = fa * fa * self.cell(ia, ia) + (1.0 - fb) * (1.0 - fb) * self.cell(jb, jb);
        whole + row + col + corner + diagonal
    }

    /// Raised from 0 to `v0`.
    fn rest(&mut self, v0: f64) {
        self.turns.clear();
        self.sums.clear();
        self.turns.push(0.0);
        self.sums.push(0.0);
        self.v = v0.clamp(0.0, 1.0);
    }

    fn push(&mut self, x: f64) {
        let k = self.turns.len() - 1;
        let s = self.sums[k]
            + if k & 1 == 1 {
                self.everett(self.turns[k], self.turns[k - 1]) - self.everett(self.turns[k], x)
            } else {
                0.0
            };
        self.turns.push(x);
        self.sums.push(s);
    }

    fn truncate(&mut self, len: usize) {
        self.turns.truncate(len);
        self.sums.truncate(len);
    }

    /// Moves the input to `v` (clamped to `[0, 1]`), updating the memory by the wiping-out rule.
    fn set(&mut self, v: f64) {
        let v = v.clamp(0.0, 1.0);
        // Each pass pushes one turning point (after which the phase agrees with the motion)
        // or removes one or two: the loop ends.
        loop {
            let k = self.turns.len() - 1;
            let last = self.turns[k];
            if k & 1 == 0 {
                // Rising from the minimum `last`.
                if v < self.v {
                    if self.v > last {
                        self.push(self.v);
                    } else if k > 0 {
                        // It never rose: still falling from the previous maximum.
                        self.truncate(k);
                    } else {
                        break;
                    }
                    continue;
                }
                if k >= 2 && v >= self.turns[k - 1] {
                    // Above the previous maximum: that loop is wiped out, and the input is
                    // where it was, rising from the minimum before it.
                    self.v = self.turns[k - 1];
                    self.truncate(k - 1);
                    continue;
                }
            } else {
                // Falling from the maximum `last`.
                if v > self.v {
                    if self.v < last {
                        self.push(self.v);
                    } else {
                        self.truncate(k);
                    }
                    continue;
                }
                if v <= self.turns[k - 1] {
                    // Below the previous minimum: likewise (at the rest point, every relay
                    // is off again).
                    self.v = self.turns[k - 1];
                    self.truncate(if k == 1 { 1 } else { k - 1 });
                    continue;
                }
            }
            break;
        }
        self.v = v;
    }

    /// The output, `0 … 1`.
    fn output(&self) -> f64 {
        let k = self.turns.len() - 1;
        let pk = self.turns[k];
        if k & 1 == 0 {
            self.sums[k] + self.everett(self.v, pk)
        } else {
            self.sums[k] + self.everett(pk, self.turns[k - 1]) - self.everett(pk, self.v)
        }
    }

    fn memory_len(&self) -> usize {
        self.turns.len()
    }
}

/// The stage's hysteresis, running.
#[derive(Clone, Debug)]
enum Hysteresis {
    Preisach(Preisach),
    BoucWen(BoucWenStage),
}

impl Hysteresis {
    /// At rest at `v0` (see [`LabStage::rest`]).
    fn rest(&mut self, v0: f64) {
        match self {
            Self::Preisach(h) => h.rest(v0),
            Self::BoucWen(h) => h.rest(v0),
        }
    }

    /// The input moves to `v`.
    fn set(&mut self, v: f64) {
        match self {
            Self::Preisach(h) => h.set(v),
            Self::BoucWen(h) => h.set(v),
        }
    }
}

/// The laboratory stage: drive volts in, sensor reading µm out, one sample period per step.
/// See the [module documentation](self) for its physics.
#[derive(Clone, Debug)]
pub struct LabStage {
    config: LabStageConfig,
    hysteresis: Hysteresis,
    /// `e^{−dt/τ_i}` of each creep mode.
    creep_decay: Vec<f64>,
    /// Weight `w_i` of each creep mode.
    creep_weight: f64,
    /// `z_i`.
    creep_state: Vec<f64>,
    resonance: ZeroOrderHold<2, 1>,
    /// `[position µm, velocity µm/s]`.
    mechanics: [f64; 2],
    noise: GaussianNoise,
}

/// The creep's span at most: its slowest mode 12 decades above its fastest (the default
/// spans 8), so that its modes (`creep_modes_per_decade` a decade) stay a bounded few.
const MAX_CREEP_DECADES_RATIO: f64 = 1e12;

impl LabStage {
    /// A stage from `config`, at rest at 0 V.
    ///
    /// ```
    /// use hal_sim::plant::{LabStage, LabStageConfig};
    /// let mut config = LabStageConfig::new(10_000.0, 1);
    /// config.damping_ratio = 1.5;
    /// let err = LabStage::new(&config).unwrap_err();
    /// assert_eq!(err.field, "damping_ratio");
    /// ```
    pub fn new(config: &LabStageConfig) -> Result<Self, LabStageError> {
        config.validate()?;
        let dt = config.sample_period_s;
        let decades = (config.creep_slowest_s / config.creep_fastest_s).log10();
        let modes = (decades * config.creep_modes_per_decade as f64).round() as usize + 1;
        let creep_decay = (0..modes)
            .map(|i| {
                let tau = config.creep_fastest_s
                    * 10f64.powf(i as f64 / config.creep_modes_per_decade as f64);
                (-dt / tau).exp()
            })
            .collect::<Vec<_>>();
        let omega = core::f64::consts::TAU * config.resonance_hz;
        let resonance = ZeroOrderHold::new(
            &[
                [0.0, 1.0],
                [-omega * omega, -2.0 * config.damping_ratio * omega],
            ],
            &[[0.0], [omega * omega]],
            dt,
        );
        let mut stage = Self {
            hysteresis: match config.hysteresis {
                StageHysteresis::Preisach => Hysteresis::Preisach(Preisach::new(&config.preisach)),
                StageHysteresis::BoucWen => {
                    Hysteresis::BoucWen(BoucWenStage::new(&config.bouc_wen))
                }
            },
            creep_weight: config.creep_per_decade / config.creep_modes_per_decade as f64,
            creep_state: vec![0.0; creep_decay.len()],
            creep_decay,
            resonance,
            mechanics: [0.0; 2],
            noise: GaussianNoise::new(config.seed),
            config: config.clone(),
        };
        stage.rest(0.0);
        Ok(stage)
    }

    /// At rest at `u0` volts: raised slowly from 0 V and held until the creep settled, not
    /// moving; the noise starts its sequence again (so a run from rest is reproducible).
    pub fn rest(&mut self, u0: f64) {
        let v0 = self.normalised(u0);
        self.hysteresis.rest(v0);
        let p = self.polarisation(v0);
        self.creep_state.iter_mut().for_each(|z| *z = p);
        self.mechanics = [self.free_position(p), 0.0];
        self.noise = GaussianNoise::new(self.config.seed);
    }

    /// At rest at 0 V, as built.
    pub fn reset(&mut self) {
        self.rest(0.0);
    }

    /// One sample period with the drive held at `u_volts` (clamped to the rails); returns the
    /// sensor's reading at the end of the period, µm.
    pub fn step(&mut self, u_volts: f64) -> f64 {
        let v = self.normalised(u_volts);
        self.hysteresis.set(v);
        let p = self.polarisation(v);
        for (z, a) in self.creep_state.iter_mut().zip(&self.creep_decay) {
            *z = a * *z + (1.0 - a) * p;
        }
        let x_static = self.free_position(p);
        self.resonance.step(&mut self.mechanics, &[x_static]);
        let lsb = self.config.sensor_lsb_nm * 1e-3;
        let reading = self.mechanics[0] + self.noise.sample(self.config.noise_rms_nm * 1e-3);
        if lsb > 0.0 {
            (reading / lsb).round() * lsb
        } else {
            reading
        }
    }

    /// The stage's position without the sensor (no noise, no rounding), µm.
    pub fn position_um(&self) -> f64 {
        self.mechanics[0]
    }

    /// The sample period, seconds.
    pub fn sample_period_s(&self) -> f64 {
        self.config.sample_period_s
    }

    /// The configuration it was built from.
    pub fn config(&self) -> &LabStageConfig {
        &self.config
    }

    /// Turning points the Preisach hysteresis remembers (including its rest point); 1 for
    /// the Bouc–Wen-class one, whose memory is its state.
    pub fn memory_len(&self) -> usize {
        match &self.hysteresis {
            Hysteresis::Preisach(h) => h.memory_len(),
            Hysteresis::BoucWen(_) => 1,
        }
    }

    /// Creep modes integrated.
    pub fn creep_modes(&self) -> usize {
        self.creep_decay.len()
    }

    fn normalised(&self, u_volts: f64) -> f64 {
        let v = u_volts / self.config.drive_max_volts;
        if v.is_nan() {
            0.0
        } else {
            v.clamp(0.0, 1.0)
        }
    }

    /// `p = r v + (1 − r) h` (Preisach), `v − h` on the major loop's 0 … 1 (Bouc–Wen class).
    fn polarisation(&self, v: f64) -> f64 {
        match &self.hysteresis {
            Hysteresis::Preisach(h) => {
                let r = self.config.preisach.reversible;
                r * v + (1.0 - r) * h.output()
            }
            Hysteresis::BoucWen(h) => h.output(),
        }
    }

    /// The flexure's static deflection for polarisation `p` and the current creep state.
    fn free_position(&self, p: f64) -> f64 {
        let creep: f64 = self.creep_state.iter().map(|z| self.creep_weight * z).sum();
        let x = self.config.stroke_um * (p + creep);
        let big_x = self.config.flexure_saturation_um;
        if big_x.is_finite() {
            big_x * (x / big_x).tanh()
        } else {
            x
        }
    }
}

#[cfg(test)]
mod tests;
