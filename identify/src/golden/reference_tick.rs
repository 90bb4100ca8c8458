//! The whole tick in `f64`, and the check that stored vectors agree with it.
//!
//! The reference composes the `f64` models (`crate::reference`) with the tick's
//! other steps written out in real arithmetic from their documented semantics (`src/control/mod.rs`,
//! `src/control/sensor.rs`, `src/control/feedback.rs`, `src/control/drive.rs`, the README's "Closed loop"): setpoint
//! clamp and hold, the compensator (stepped in every mode; in bypass its output is unused and
//! the drive follows the setpoint; with creep, the inverse creep before it; with an output
//! map, its inverse between the two), the observer (with an output map, the map after it;
//! with creep, the creep after that), the creep's modes at rest at the start's setpoint, the sensor reading and the drift check (whenever a sensor
//! is configured, in every mode), the PI feedback (closed loop only), range and slew limits per
//! stack, the differential split, the observer. It runs on the stored inputs alone, so it
//! checks the stored outputs independently of the fixed-point code.
//!
//! The start: the controller starts with both stacks at the configuration's **safe state**
//! voltages (both at the bias, or both at 0 V), the models relaxed at the drive the left stack's
//! voltage amounts to (within the drive window), the setpoint where the observer puts the stage
//! (the drive itself without an observer; with an output map, the map of the observer's
//! output), the compensator's model at rest at the map's inverse of it.
//!
//! The drive, per tick: the command is limited to the drive window (model-normalised), turned
//! into the left stack's voltage `u_l`, and `u_l` is slew-limited against the left stack's
//! previous voltage (`slew_rate / control rate` volts per tick); the right stack's target is
//! `2ū − u_l` clamped to the voltage limits (differential) or `min_voltage` (unidirectional),
//! slew-limited against the right stack's own previous voltage. The applied drive is the
//! ranged command when the left stack was not slew-limited, else the drive of the left stack's
//! voltage; the slew flag is set when either stack was slew-limited.
//!
//! The sensor, per tick with a sensor configured:
//!
//! * the reading `measured = at_zero + gain · code / 2^bits` (code masked to the ADC's bits)
//!   is [`SENSOR_DELAY_TICKS`] ticks old; a failed read raises the ADC flag in every mode;
//! * drift: `δ ← δ + (measured − ē − δ) / 2^DRIFT_FILTER_SHIFT`, `ē` the estimate of the
//!   reading's instant: the end of the hold of SENSOR_DELAY_TICKS ago, between the estimates
//!   of the holds' middles around it (`twinstack::control::instant`),
//!   flagged when `|δ|` exceeds the drift limit (only with an observer and a drift limit).
//!
//! The feedback, per closed-loop tick:
//!
//! * the reading is compared with the **target of its instant**: the end of the hold of
//!   [`SENSOR_DELAY_TICKS`] ticks ago, between the targets of the holds' middles around it
//!   (`twinstack::control::instant`) — whether
//!   or not the reads in between succeeded (the delay is the converter's);
//! * integral: `i ← clamp(i + ki/f_s · e, ±limit)`, **held** while the previous tick's command
//!   (feedforward + correction) was cut by the range or slew limit in the direction `e`
//!   pushes (`clip = command − applied` of that tick, `clip · e > 0`);
//! * proportional: `kp · clamp(e, ±limit / kp)` — the P term alone is limited to ±limit;
//! * correction `clamp(P + i, ±limit)`, added to the feedforward; on a failed read the
//!   integrator alone (held).
//!
//! Signals that the tick holds in Q2.30 (error, reading, command) saturate at ±2 here too.
//! The golden sets have no derivative or notch and start in their mode with no mode switch or
//! reload, so the bumpless-transfer offset is always 0 in them: the check refuses a closed-loop
//! recipe with a derivative or a notch, or input shaping outside bypass, rather than ignore
//! it. The preview is modelled: its taps ([`PreviewDesign::taps`]) on the last nine
//! setpoints, the feedback and bypass on the setpoint four ticks ago. So is the output map
//! (`twinstack::models::output_map`), in output units: the observer's output mapped by
//! [`reference::dead_zone_map`] (saturated at ±2 normalised, as the tick's Q2.30), the
//! compensator's desired output, clamped to the output range, mapped back by
//! [`reference::dead_zone_map_inverse`] (bisection, independent of the library's closed-form
//! inverse); neither applied without a model. Bounds:
//!
//! * **drive** (applied, model-normalised): within [`DRIVE_BOUND_LSB16`] of the reference
//!   chain — the inverse models' documented bound (README, "Fixed point");
//! * **estimate**: within [`ESTIMATE_BOUND_LSB16`] of the reference observer fed the stored
//!   drive — the forward models' documented bound;
//! * **DAC codes**: the left code is the stored drive's exact code rounded to nearest (the left
//!   stack stays within the drive window, so the stored drive is its voltage); the right code
//!   is that of the right stack as the split makes it from the stored left voltage (mirror or
//!   idle, limits, its own slew limit); each within [`CODE_BOUND`] code, clamped to the
//!   converter's range;
//! * **flags**: equal to the reference's, except a range flag where the reference's command
//!   lies within the drive bound of the window, a slew flag where a stack's target lies within
//!   the drive bound (in volts) of its slew limit, or a drift flag where the reference's
//!   low-passed difference lies within [`DRIFT_BOUND_LSB16`] of the drift limit (counted as
//!   ambiguous).
//!
//! LSB16 = one LSB of a 16-bit converter over the normalised range: `2 / 65536`.

use crate::accuracy::LSB16;
use crate::reference;
use crate::stage_model::at_reading;
use twinstack::config::settings::{DeadZoneParams, Mode, Model};
use twinstack::control::drive::{Configuration, DriveSettings, SafeState};
use twinstack::control::feedback::{DRIFT_FILTER_SHIFT, SENSOR_DELAY_TICKS};
use twinstack::control::preview::{PreviewDesign, PreviewError, PREVIEW_DELAY_TICKS, PREVIEW_TAPS};
use twinstack::control::TickFlags;
use twinstack::fixed_point::signal_to_f64;
use twinstack::models::Rest;
use twinstack::Scaling;
use twinstack_golden::{Recipe, VectorSet};

/// Largest |stored drive − reference drive|, LSB16. The P–I banks run their operators on a
/// Q1.15 grid (1 LSB16 a step; see `twinstack_identify::accuracy`): an inverse's error is up to its
/// gain `Σ|w'|` LSB16 in the worst case; on the sets' identified models it measures 1.07
/// (`cargo run --release -p twinstack-cli -- golden`), and 1.5 leaves a margin. The scalar models
/// (Duhem, Bouc–Wen, creep) stay below 0.03.
pub const DRIVE_BOUND_LSB16: f64 = 1.5;
/// Largest |stored estimate − reference observer|, LSB16: the P–I observers' Q1.15 grid (half
/// a step of the drive and of each threshold, times the model's slope): 0.57 measured, 0.75
/// allowed; the scalar observers stay below 0.003.
pub const ESTIMATE_BOUND_LSB16: f64 = 0.75;
/// Largest |stored code − exact code|, codes (half a code for rounding, plus the split's
/// Q17.15 arithmetic: the voltage is rounded to 2^-15 code before it is rounded to a code,
/// and the slew step and the bias are held to 2^-15 code).
pub const CODE_BOUND: f64 = 0.5 + 1e-3;
/// How far the stored drift filter may be from the reference's, LSB16: the estimate's bound
/// (the filter has gain 1) plus the sensor scaling's and the filter's rounding (< 0.01).
pub const DRIFT_BOUND_LSB16: f64 = ESTIMATE_BOUND_LSB16 + 0.01;

/// How far one set's stored outputs are from the reference.
#[derive(Clone, Debug, PartialEq)]
pub struct Agreement {
    /// Set name.
    pub name: String,
    /// Ticks compared.
    pub ticks: usize,
    /// Largest drive error, LSB16.
    pub drive_lsb16: f64,
    /// Largest estimate error, LSB16.
    pub estimate_lsb16: f64,
    /// Largest DAC code error, codes (before rounding's half code is subtracted).
    pub code_error: f64,
    /// Ticks whose flags differ from the reference's where the reference is unambiguous.
    pub flag_mismatches: usize,
    /// First tick with a flag mismatch.
    pub first_flag_mismatch: Option<(usize, u8, u8)>,
    /// Ticks where a range or slew decision lies within the drive bound of its limit, or the
    /// drift filter within the drift bound of the drift limit.
    pub ambiguous: usize,
    /// First tick whose drive, estimate or code exceeds its bound.
    pub first_violation: Option<usize>,
    /// Ticks the reference held the integrator (anti-windup) against a non-zero error.
    pub integrator_holds: usize,
}

impl Agreement {
    /// Whether every tick is within its bound.
    pub fn holds(&self) -> bool {
        self.first_violation.is_none() && self.flag_mismatches == 0
    }
}

enum Feedforward {
    None,
    InversePi(Box<reference::InversePrandtlIshlinskii>),
    InverseDuhem(reference::InverseDuhem),
    InverseGpi(Box<reference::InverseGeneralisedPi>),
    InverseBoucWen(reference::InverseBoucWen),
}

enum Estimator {
    None,
    Pi(Box<reference::PrandtlIshlinskii>),
    Duhem(reference::Duhem),
    Gpi(Box<reference::GeneralisedPi>),
    BoucWen(reference::BoucWen),
}

/// The position sensor in real arithmetic (see the module doc), with the drift check's memory.
struct ReferenceSensor {
    /// Displacement at code 0 and per ADC full scale, normalised.
    at_zero: f64,
    gain: f64,
    /// ADC bits.
    bits: u32,
    /// Drift limit, normalised displacement (`None`: no check).
    drift_limit: Option<f64>,
    /// The observer's estimates of the last ticks, newest first.
    estimates: [f64; SENSOR_DELAY_TICKS + 2],
    /// Low-passed measured − estimate.
    drift: f64,
}

/// What the drift check found one tick.
#[derive(Default)]
struct Drift {
    /// The drift flag, and whether the reference's filter lies within the drift bound of the
    /// limit (the stored flag may go either way).
    flagged: bool,
    ambiguous: bool,
}

impl ReferenceSensor {
    fn new(recipe: &Recipe, at_rest: f64) -> anyhow::Result<Option<Self>> {
        let st = &recipe.settings;
        let Some(sensor) = &st.sensor else {
            return Ok(None);
        };
        let bits = recipe
            .hardware
            .sensor_adc_bits
            .ok_or_else(|| anyhow::anyhow!("a sensor on a board without a sensor ADC"))?;
        let s = &st.ranges;
        let at_zero = s.output_to_norm(sensor.displacement_at_zero);
        // The drift check compares the sensor with the observer: none without one.
        let observed = st.observer.is_some();
        Ok(Some(Self {
            at_zero,
            gain: s.output_to_norm(sensor.displacement_at_full_scale) - at_zero,
            bits: u32::from(bits).min(30),
            // Fractions of the range; the normalised range is 2 wide.
            drift_limit: sensor.drift_limit.filter(|_| observed).map(|d| 2.0 * d),
            estimates: [at_rest; SENSOR_DELAY_TICKS + 2],
            drift: 0.0,
        }))
    }

    /// Reads `code`: the measurement, normalised.
    fn read(&self, code: u16) -> f64 {
        let mask = (1u32 << self.bits) - 1;
        let fraction = (code as u32 & mask) as f64 / (1u64 << self.bits) as f64;
        saturate(self.at_zero + self.gain * fraction)
    }

    /// End of a tick: the observer's `estimate` into the history, then the drift check of the
    /// tick's `measured` (`None`: the read failed, no check) against the estimate of the
    /// reading's instant (the end of the hold of SENSOR_DELAY_TICKS ago, between the estimates
    /// of the middles around it).
    fn observed(&mut self, estimate: f64, measured: Option<f64>, drift_tol: f64) -> Drift {
        self.estimates.rotate_right(1);
        self.estimates[0] = estimate;
        let Some(measured) = measured else {
            return Drift::default();
        };
        let difference = saturate(measured - at_reading(&self.estimates));
        self.drift += (difference - self.drift) / (1u32 << DRIFT_FILTER_SHIFT) as f64;
        match self.drift_limit {
            Some(l) => Drift {
                flagged: self.drift.abs() > l,
                ambiguous: (self.drift.abs() - l).abs() < drift_tol,
            },
            None => Drift::default(),
        }
    }
}

/// The PI feedback in real arithmetic (see the module doc), with its memory.
struct ReferenceFeedback {
    /// Proportional gain; integral gain per tick; correction (and integrator) limit,
    /// normalised drive.
    kp: f64,
    ki: f64,
    limit: f64,
    /// Integrator.
    integrator: f64,
    /// The previous tick's command minus the drive applied.
    clip: f64,
    /// Targets of the last ticks, newest first.
    targets: [f64; SENSOR_DELAY_TICKS + 2],
}

impl ReferenceFeedback {
    /// The feedback of a closed-loop recipe (`None` in the other modes: it does not run).
    fn new(recipe: &Recipe, at_rest: f64) -> anyhow::Result<Option<Self>> {
        let st = &recipe.settings;
        let Some(fb) = st.feedback.filter(|_| st.mode == Mode::ClosedLoop) else {
            return Ok(None);
        };
        if fb.kd != 0.0 || fb.notch.is_some() {
            anyhow::bail!("the reference tick models PI feedback without derivative or notch");
        }
        Ok(Some(Self {
            kp: fb.kp,
            ki: fb.ki / recipe.hardware.control_rate_hz,
            // Fractions of the drive range; the normalised range is 2 wide.
            limit: 2.0 * fb.limit,
            integrator: 0.0,
            clip: 0.0,
            targets: [at_rest; SENSOR_DELAY_TICKS + 2],
        }))
    }

    /// One tick's correction: `measured` the reading (`None`: the read failed), `target`
    /// this tick's. Also says whether the integrator was held against a non-zero error.
    fn correction(&mut self, target: f64, measured: Option<f64>) -> (f64, bool) {
        // This tick's target into the history, then the target of the reading's instant.
        self.targets.rotate_right(1);
        self.targets[0] = target;
        let reference = at_reading(&self.targets);
        let Some(measured) = measured else {
            return (self.integrator, false);
        };
        let error = saturate(reference - measured);
        let held = self.clip * error > 0.0;
        if !held {
            self.integrator = (self.integrator + self.ki * error).clamp(-self.limit, self.limit);
        }
        let p = if self.kp > 0.0 {
            self.kp * error.clamp(-self.limit / self.kp, self.limit / self.kp)
        } else {
            0.0
        };
        ((p + self.integrator).clamp(-self.limit, self.limit), held)
    }
}

/// A Q2.30 quantity's range: the tick saturates at ±2.
fn saturate(x: f64) -> f64 {
    x.clamp(-2.0, 2.0)
}

/// Where the board's models start: by the drive's configuration, as `Controller::prepare`
/// starts them (`Configuration::rest`).
fn rest(recipe: &Recipe) -> Rest {
    recipe.settings.drive.configuration.rest()
}

/// The reference observer at rest at `u0` volts and its output there (output units), or
/// `None` without an observer.
fn observer_at_rest(recipe: &Recipe, u0: f64) -> anyhow::Result<(Estimator, Option<f64>)> {
    let s = &recipe.settings.ranges;
    let rest = rest(recipe);
    Ok(match &recipe.settings.observer {
        None => (Estimator::None, None),
        Some(Model::PrandtlIshlinskii(p)) => {
            let m = reference::PrandtlIshlinskii::with_rest(p, s, u0, rest)?;
            let y = m.clone().step(u0);
            (Estimator::Pi(Box::new(m)), Some(y))
        }
        Some(Model::Duhem(d)) => {
            let m = reference::Duhem::with_rest(d, s, u0, rest)?;
            let y = m.y;
            (Estimator::Duhem(m), Some(y))
        }
        Some(Model::GeneralisedPi(p)) => {
            let m = reference::GeneralisedPi::with_rest(p, s, u0, rest)?;
            let y = m.clone().step(u0);
            (Estimator::Gpi(Box::new(m)), Some(y))
        }
        Some(Model::BoucWen(p)) => {
            let m = reference::BoucWen::with_rest(p, s, u0, rest)?;
            let y = m.output();
            (Estimator::BoucWen(m), Some(y))
        }
    })
}

/// The reference compensator at rest for the start, as `Controller::prepare` starts it
/// without an observer of its model: an inverse P–I at the desired output `y0`
/// (normalised), an inverse Duhem or Bouc–Wen its own model at the present drive `u0`.
fn compensator_at_rest(recipe: &Recipe, u0: f64, y0: f64) -> anyhow::Result<Feedforward> {
    let s = &recipe.settings.ranges;
    let rest = rest(recipe);
    Ok(match &recipe.settings.compensator {
        None => Feedforward::None,
        Some(Model::PrandtlIshlinskii(p)) => {
            // At rest at the desired output the start gives: the forward model at rest at u
            // outputs c + Σw·u, so u = (y − c) / Σw.
            let c = p.canonical()?;
            let total: f64 = c.weights.iter().sum();
            let u = (s.norm_to_output(y0) - c.offset) / total;
            Feedforward::InversePi(Box::new(reference::InversePrandtlIshlinskii::with_rest(
                p, s, u, rest,
            )?))
        }
        Some(Model::Duhem(m)) => {
            Feedforward::InverseDuhem(reference::InverseDuhem::with_rest(m, s, u0, rest)?)
        }
        Some(Model::GeneralisedPi(p)) => {
            // As the P–I, with the P–I part at rest at z = S⁻¹[y].
            let c = p.pi.canonical()?;
            let total: f64 = c.weights.iter().sum();
            let z =
                reference::InverseGeneralisedPi::new(p, s, 0.0)?.map_inverse(s.norm_to_output(y0));
            Feedforward::InverseGpi(Box::new(reference::InverseGeneralisedPi::with_rest(
                p,
                s,
                (z - c.offset) / total,
                rest,
            )?))
        }
        Some(Model::BoucWen(m)) => {
            Feedforward::InverseBoucWen(reference::InverseBoucWen::with_rest(m, s, u0, rest)?)
        }
    })
}

/// The drive window (model-normalised, within ±1) from the left stack's voltage window, as
/// `DriveSettings::build` specifies it.
fn window(d: &DriveSettings, s: &Scaling) -> (f64, f64) {
    let (lo, hi) = match d.configuration {
        Configuration::Differential => (
            d.min_voltage.max(2.0 * d.bias - d.max_voltage),
            d.max_voltage.min(2.0 * d.bias - d.min_voltage),
        ),
        Configuration::Unidirectional => (d.min_voltage, d.max_voltage),
    };
    (s.input_to_norm(lo).max(-1.0), s.input_to_norm(hi).min(1.0))
}

/// The right stack's target for the left stack at `left` volts: the mirror about the bias
/// within the voltage limits, or the idle voltage (`min_voltage`).
fn right_target(d: &DriveSettings, left: f64) -> f64 {
    match d.configuration {
        Configuration::Differential => (2.0 * d.bias - left).clamp(d.min_voltage, d.max_voltage),
        Configuration::Unidirectional => d.min_voltage,
    }
}

/// `x` limited to `previous ± step`.
fn slewed(x: f64, previous: f64, step: f64) -> f64 {
    x.clamp(previous - step, previous + step)
}

fn exact_code(volts: f64, full_scale_volts: f64, full_scale_code: u16) -> f64 {
    (volts * full_scale_code as f64 / full_scale_volts).clamp(0.0, full_scale_code as f64)
}

fn norm(s: &Scaling, y_phys: f64) -> f64 {
    s.output_to_norm(y_phys)
}

/// The output map in `f64` (`twinstack::models::output_map`), as the tick runs it between the
/// model and the creep.
struct ReferenceOutputMap<'a> {
    params: &'a DeadZoneParams,
    scaling: Scaling,
}

impl ReferenceOutputMap<'_> {
    /// `S`: the observer's model output (output units) → the displacement before the creep,
    /// normalised and saturated at ±2 (the tick's Q2.30).
    fn forward(&self, z: f64) -> f64 {
        saturate(norm(
            &self.scaling,
            reference::dead_zone_map(self.params, z),
        ))
    }

    /// `S⁻¹`: a desired displacement (normalised, clamped to full scale as the tick clamps
    /// it) → what the compensator's model is to give, output units (within the tick's ±2
    /// normalised).
    fn inverse(&self, y: f64) -> f64 {
        let s = &self.scaling;
        let y = s.norm_to_output(y.clamp(-1.0, 1.0));
        let z = reference::dead_zone_map_inverse(self.params, y);
        s.norm_to_output(saturate(norm(s, z)))
    }
}

/// The preview in `f64`: the taps [`PreviewDesign::taps`] designs, on the last nine setpoints
/// (`twinstack::control::preview`).
struct ReferencePreview {
    taps: [f64; PREVIEW_TAPS],
    line: [f64; PREVIEW_TAPS],
}

impl ReferencePreview {
    fn new(design: &PreviewDesign, rate_hz: f64, at: f64) -> Result<Self, PreviewError> {
        Ok(Self {
            taps: design.taps(rate_hz)?,
            line: [at; PREVIEW_TAPS],
        })
    }

    /// The setpoint `PREVIEW_DELAY_TICKS` ago and it shaped, within full scale.
    fn step(&mut self, setpoint: f64) -> (f64, f64) {
        self.line.rotate_left(1);
        self.line[PREVIEW_TAPS - 1] = setpoint;
        let mid = self.line[PREVIEW_DELAY_TICKS];
        let shaped: f64 = self.taps.iter().zip(&self.line).map(|(h, x)| h * x).sum();
        (mid, shaped.clamp(-1.0, 1.0))
    }
}

/// Checks one stored set against the `f64` reference tick.
pub fn check(set: &VectorSet<'_>) -> anyhow::Result<Agreement> {
    let recipe = set
        .recipe()
        .map_err(|e| anyhow::anyhow!("set {}: {e:?}", set.name()))?;
    let hw = recipe.hardware;
    let st = &recipe.settings;
    if st.shaping.is_some() && st.mode != Mode::Bypass {
        anyhow::bail!(
            "set {}: the reference tick does not model input shaping (the feedforward's notch; \
             its f64 reference is control::tests::shaping_is_the_f64_notch_on_the_feedforward)",
            set.name()
        );
    }
    let s = st.ranges;
    let d = st.drive;
    let (dmin, dmax) = window(&d, &s);
    // Slew step per stack, volts per tick.
    let slew = d.slew_rate / hw.control_rate_hz;

    // The controller's start: both stacks at the safe state's voltages, the models relaxed at
    // the drive of the left stack's voltage, the setpoint at the observer's estimate there.
    let safe = match d.safe_state {
        SafeState::Bias => d.bias,
        SafeState::Zero => 0.0,
    };
    let d0 = s.input_to_norm(safe).clamp(dmin, dmax);
    let u0 = s.norm_to_input(d0);
    // The output map, between the model and the creep: where there is a model (each side
    // applies it only with its own).
    let map = st
        .output_map
        .as_ref()
        .map(|params| ReferenceOutputMap { params, scaling: s });
    let observer_map = map.as_ref().filter(|_| st.observer.is_some());
    let (mut estimator, y0) = observer_at_rest(&recipe, u0)?;
    let y0 = match (y0, observer_map) {
        (Some(y), Some(m)) => m.forward(y),
        (Some(y), None) => norm(&s, y),
        (None, _) => d0,
    };
    // The compensator's model at rest where the map's inverse puts the start's setpoint.
    let compensator_y0 = match &map {
        Some(m) => norm(&s, m.inverse(y0)),
        None => y0,
    };
    let mut feedforward = compensator_at_rest(&recipe, u0, compensator_y0)?;
    // The creep (normalised signals, at the tick's rate), at rest where the models are: its
    // inverse before the compensator's model, itself after the observer's.
    let creep_at_rest = |present: bool| -> anyhow::Result<Option<reference::Creep>> {
        match (&st.creep, present) {
            (Some(c), true) => Ok(Some(reference::Creep::new(c, hw.control_rate_hz, y0)?)),
            _ => Ok(None),
        }
    };
    let mut compensator_creep = creep_at_rest(st.compensator.is_some())?;
    let mut observer_creep = creep_at_rest(st.observer.is_some())?;
    let mut sensor = ReferenceSensor::new(&recipe, y0)?;
    let mut feedback = ReferenceFeedback::new(&recipe, y0)?;
    let bypass = st.mode == Mode::Bypass;
    let drift_tol = DRIFT_BOUND_LSB16 * LSB16;

    let mut target = y0;
    // The preview, its line at rest at the start's setpoint.
    let mut preview = match &st.preview {
        Some(p) => Some(
            ReferencePreview::new(p, hw.control_rate_hz, y0)
                .map_err(|e| anyhow::anyhow!("set {}: the preview: {e:?}", set.name()))?,
        ),
        None => None,
    };
    // The reference chain's stacks, volts.
    let (mut left, mut right) = (safe, safe);
    // The right stack as the split makes it from the stored left voltage (for its code).
    let mut right_stored = safe;
    let drive_tol = DRIVE_BOUND_LSB16 * LSB16;
    let volts_tol = drive_tol * s.input_half_span();
    let mut a = Agreement {
        name: set.name().to_string(),
        ticks: 0,
        drive_lsb16: 0.0,
        estimate_lsb16: 0.0,
        code_error: 0.0,
        flag_mismatches: 0,
        first_flag_mismatch: None,
        ambiguous: 0,
        first_violation: None,
        integrator_holds: 0,
    };
    for (k, (input, out)) in set.inputs().zip(set.outputs()).enumerate() {
        let mut flags = 0u8;
        match input.setpoint {
            Some(sp) => target = signal_to_f64(sp).clamp(-1.0, 1.0),
            None => flags |= TickFlags::UNDERRUN,
        }
        // With the preview, the feedback aims at the setpoint of four ticks ago and the
        // compensator is given it shaped.
        let (aimed, shaped) = match &mut preview {
            Some(p) => p.step(target),
            None => (target, target),
        };
        // The compensator steps in every mode; in bypass the drive follows the setpoint.
        let desired = match &mut compensator_creep {
            Some(c) => c.inverse_step(shaped),
            None => shaped,
        };
        // With an output map, the model is given its inverse of the desired output.
        let desired = match &map {
            Some(m) => m.inverse(desired),
            None => s.norm_to_output(desired),
        };
        let compensated = match &mut feedforward {
            Feedforward::None => shaped,
            Feedforward::InversePi(m) => s.input_to_norm(m.step(desired)),
            Feedforward::InverseDuhem(m) => s.input_to_norm(m.step(desired)),
            Feedforward::InverseGpi(m) => s.input_to_norm(m.step(desired)),
            Feedforward::InverseBoucWen(m) => s.input_to_norm(m.step(desired)),
        };
        let ff = if bypass { aimed } else { compensated };
        let mut command = ff;
        // Flags the stored tick may set either way (its decision lies within its bound).
        let mut loose = 0u8;
        let mut reading = None;
        if let Some(sn) = &mut sensor {
            let measured = if input.adc_fails {
                flags |= TickFlags::ADC_ERROR;
                None
            } else {
                Some(sn.read(input.adc_code))
            };
            reading = measured;
            if let Some(fb) = &mut feedback {
                let (correction, held) = fb.correction(aimed, measured);
                a.integrator_holds += usize::from(held);
                command = saturate(ff + correction);
            }
        }

        // Range limit (model-normalised), then each stack's slew limit (volts).
        let ranged = command.clamp(dmin, dmax);
        if ranged != command {
            flags |= TickFlags::RANGE_LIMIT;
        }
        if (command - dmin).abs() < drive_tol || (command - dmax).abs() < drive_tol {
            loose |= TickFlags::RANGE_LIMIT | TickFlags::SLEW_LIMIT;
        }
        let left_target = s.norm_to_input(ranged);
        let new_left = slewed(left_target, left, slew);
        let near_slew = |t: f64, previous: f64| {
            (t - (previous - slew)).abs() < volts_tol || (t - (previous + slew)).abs() < volts_tol
        };
        let r_target = right_target(&d, new_left);
        let new_right = slewed(r_target, right, slew);
        let (left_slewed, right_slewed) = (new_left != left_target, new_right != r_target);
        if left_slewed || right_slewed {
            flags |= TickFlags::SLEW_LIMIT;
        }
        // The flag is either stack's: ambiguous when a stack's decision is close and neither
        // stack is clearly slew-limited. (While the left stack slews, the right one's mirror
        // target lies exactly one slew step from its previous voltage: close, but the left
        // stack decides the flag.)
        let (left_near, right_near) = (near_slew(left_target, left), near_slew(r_target, right));
        let clearly_slewed = (left_slewed && !left_near) || (right_slewed && !right_near);
        if (left_near || right_near) && !clearly_slewed {
            loose |= TickFlags::SLEW_LIMIT;
        }
        let applied = if new_left != left_target {
            s.input_to_norm(new_left).clamp(dmin, dmax)
        } else {
            ranged
        };
        (left, right) = (new_left, new_right);
        if input.dac_fails {
            flags |= TickFlags::DAC_ERROR;
        }

        // Drive against the reference chain.
        let stored_drive = signal_to_f64(out.drive);
        let drive_err = (stored_drive - applied).abs() / LSB16;
        // Observer and codes against the stored drive.
        let u_volts = s.norm_to_input(stored_drive);
        // The model's output (output units), then the output map where there is one.
        let model_output = match &mut estimator {
            Estimator::None => None,
            Estimator::Pi(m) => Some(m.step(u_volts)),
            Estimator::Duhem(m) => Some(m.step(u_volts)),
            Estimator::Gpi(m) => Some(m.step(u_volts)),
            Estimator::BoucWen(m) => Some(m.step(u_volts)),
        };
        let estimate_ref = match (model_output, observer_map) {
            (None, _) => 0.0,
            (Some(y), Some(m)) => m.forward(y),
            (Some(y), None) => norm(&s, y),
        };
        let estimate_ref = match &mut observer_creep {
            Some(c) => c.step(estimate_ref),
            None => estimate_ref,
        };
        if let Some(sn) = &mut sensor {
            let drift = sn.observed(estimate_ref, reading, drift_tol);
            if drift.flagged {
                flags |= TickFlags::DRIFT;
            }
            if drift.ambiguous {
                loose |= TickFlags::DRIFT;
            }
        }
        if let Some(fb) = &mut feedback {
            fb.clip = command - applied;
        }
        let estimate_err = (signal_to_f64(out.estimate) - estimate_ref).abs() / LSB16;
        // The left stack stays within the drive window (it starts there and moves towards
        // ranged commands), so the stored drive is its voltage.
        right_stored = slewed(right_target(&d, u_volts), right_stored, slew);
        let code_err = [(out.left, u_volts), (out.right, right_stored)]
            .iter()
            .map(|&(code, v)| {
                (code as f64 - exact_code(v, hw.amplifier_full_scale, hw.dac_full_scale)).abs()
            })
            .fold(0.0, f64::max);

        a.ticks += 1;
        a.drive_lsb16 = a.drive_lsb16.max(drive_err);
        a.estimate_lsb16 = a.estimate_lsb16.max(estimate_err);
        a.code_error = a.code_error.max(code_err);
        if (drive_err > DRIVE_BOUND_LSB16
            || estimate_err > ESTIMATE_BOUND_LSB16
            || code_err > CODE_BOUND)
            && a.first_violation.is_none()
        {
            a.first_violation = Some(k);
        }
        if loose != 0 {
            a.ambiguous += 1;
        }
        if (flags ^ out.flags) & !loose != 0 {
            a.flag_mismatches += 1;
            a.first_flag_mismatch.get_or_insert((k, out.flags, flags));
        }
    }
    Ok(a)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::golden::{default_dir, VECTOR_FILE};
    use twinstack::config::settings::Settings;
    use twinstack_golden::format::encode_record;
    use twinstack_golden::{TickInput, TickOutput, VectorSets, MAX_RECIPE};

    /// The stored set `name`'s inputs and outputs, checked against its recipe changed by `f`.
    fn recheck(name: &str, f: &dyn Fn(&mut Settings)) -> Agreement {
        let path = default_dir().join(VECTOR_FILE);
        let file = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let set = VectorSets::new(&file)
            .map(|s| s.unwrap())
            .find(|s| s.name() == name)
            .unwrap_or_else(|| panic!("set {name}"));
        let inputs: Vec<TickInput> = set.inputs().collect();
        let outputs: Vec<TickOutput> = set.outputs().collect();
        let mut recipe = set.recipe().unwrap();
        f(&mut recipe.settings);
        let mut buf = [0u8; MAX_RECIPE];
        let recipe = recipe.encode(&mut buf).unwrap();
        let mut bytes = Vec::new();
        encode_record(
            set.name(),
            set.config_fingerprint(),
            recipe,
            &inputs,
            &outputs,
            &mut bytes,
        )
        .unwrap();
        let s = VectorSets::new(&bytes).next().unwrap().unwrap();
        check(&s).unwrap()
    }

    /// The check runs the output map where the board runs it: the map set's stored outputs
    /// hold against its recipe, and fail it without the map or with the map's gain changed by
    /// half a percent.
    #[test]
    fn the_reference_check_depends_on_the_output_map() {
        let name = "ibw-bw-map-creep-closed";
        let a = recheck(name, &|_| {});
        assert!(a.holds(), "{a:?}");
        let a = recheck(name, &|s| s.output_map = None);
        assert!(a.first_violation.is_some(), "no map: {a:?}");
        let a = recheck(name, &|s| s.output_map.as_mut().unwrap().linear *= 1.005);
        assert!(a.first_violation.is_some(), "linear: {a:?}");
    }
}
