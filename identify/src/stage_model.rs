//! A stage's identified model as the board runs it: the hysteresis model, the scaling onto
//! the fixed-point ranges, the sensor's sign and its lag — and whole-record runs of it, in the
//! library's fixed point (the code the firmware runs) and in the `f64` reference.
//!
//! Conventions shared by `identify`, `predict` and `compensate`:
//! * the model's output is the *sign-corrected* output: `sensor reading = output_sign × y`;
//!   the scaling's output range is in those units (an inverted sensor needs no `max < min`);
//! * the sensor lags the drive by `sensor_lag_s`, a whole or a half number `λ` of samples of
//!   the record being run: the reading at sample `k` is the model's output at sample `k − λ`,
//!   between two samples the outputs around it interpolated there (a drive held for a sample
//!   acts on the stage as at the middle of its hold, half a sample before the reading of its
//!   end: [`between_samples`]);
//! * forward runs start at rest at the first drive value: on the major loop's ascending
//!   branch, as a stage in use rests (every model's `state_at_rest`; the book's "At rest");
//!   inverse runs start at rest where their model gives the first desired output;
//! * with creep, the creep operator runs after the hysteresis model (`predict`) and its
//!   inverse before the inverse model (`compensate`), discretised at the record's sample
//!   period (the median interval), its modes at rest at the first value they see;
//! * with an output map, the map runs between the hysteresis model and the creep, as the
//!   board runs it (`twinstack::models::dispatch`): `drive → H → S → creep → reading` in
//!   `predict`, `reading → creep⁻¹ → S⁻¹ → H⁻¹ → drive` in `compensate`, the inverse model at
//!   rest where it gives `S⁻¹` of the first desired output.

use crate::reference;
use twinstack::control::feedback::SENSOR_DELAY_TICKS;
use twinstack::fixed_point::{
    clamp_full_scale, gain_from_f64, saturate_i64, signal_from_f64, signal_to_f64, GAIN_FRAC_BITS,
};
use twinstack::models::bouc_wen::{BoucWen, InverseBoucWen};
use twinstack::models::creep::{Creep, CreepParams, CreepState};
use twinstack::models::duhem::{Duhem, InverseDuhem};
use twinstack::models::generalised_pi::{GeneralisedPi, GpiParams, InverseGeneralisedPi};
use twinstack::models::output_map::{DeadZoneParams, OutputMap};
use twinstack::models::play_operator::play;
use twinstack::models::prandtl_ishlinskii::{InversePrandtlIshlinskii, PrandtlIshlinskii};
use twinstack::models::Rest;
use twinstack::{BoucWenParams, DuhemParams, ParamError, PiParams, Scaling};

/// The hysteresis model of a stage, in physical units. (Built once per command, so the
/// size difference between the variants does not matter.)
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq)]
pub enum Hysteresis {
    /// Prandtl–Ishlinskii.
    Pi(PiParams),
    /// Duhem.
    Duhem(DuhemParams),
    /// Generalised (asymmetric) P–I: a P–I followed by a dead-zone map.
    GeneralisedPi(GpiParams),
    /// Generalised (asymmetric) Bouc–Wen.
    BoucWen(BoucWenParams),
}

/// Everything needed to run a stage's model on a record.
#[derive(Clone, Debug, PartialEq)]
pub struct StageModel {
    /// The hysteresis model (volts in, sign-corrected output units out).
    pub hysteresis: Hysteresis,
    /// Input and (sign-corrected) output ranges onto the normalised Q2.30 signals.
    pub scaling: Scaling,
    /// `+1` or `−1`: the sensor reads `output_sign × y`.
    pub output_sign: f64,
    /// Sensor lag behind the drive, seconds (`≥ 0`).
    pub sensor_lag_s: f64,
    /// The stage's creep, in series after the hysteresis model and its output map (`None`:
    /// no creep).
    pub creep: Option<CreepParams>,
    /// A static output map between the hysteresis model and the creep
    /// (`twinstack::models::output_map`: output units, its centre and thresholds as the
    /// board takes them; `None`: no map). The board takes one after a Bouc–Wen model only
    /// (`twinstack::config::settings::Settings::build` refuses it with another, and so does
    /// loading a parameter file); here it runs after any model.
    pub output_map: Option<DeadZoneParams>,
}

/// The value midway between `b` and `c` of four consecutive samples `a, b, c, d`: the cubic
/// through the four, `(9·(b + c) − (a + d)) / 16` — the rule the tick takes the target of a
/// reading's instant by (`twinstack::control::instant::between_holds`, in fixed point).
///
/// ```
/// use twinstack_identify::stage_model::between;
/// assert_eq!(between(0.0, 1.0, 4.0, 9.0), 2.25);
/// ```
pub fn between(a: f64, b: f64, c: f64, d: f64) -> f64 {
    (9.0 * (b + c) - (a + d)) / 16.0
}

/// The values midway between consecutive samples: element `k` lies between `x[k]` and
/// `x[k + 1]` ([`between`]; at the ends the first and last samples stand for those beyond,
/// and the last element is `x`'s last).
///
/// Each drive sample is held until the next (the board's DAC, a DAQ's output), and acts on
/// the stage as at the middle of its hold, half a sample before the reading of its end: with
/// a half lag a model is fitted to, and its compensator aims at, the readings' values between
/// samples. Fitted to the readings at the holds' ends, a model carries that half sample as
/// hysteresis width that fits only the rate it was identified at; `identify` finds the half
/// lag where the data show it.
///
/// ```
/// use twinstack_identify::stage_model::between_samples;
/// assert_eq!(between_samples(&[0.0, 1.0, 4.0, 9.0, 16.0]), vec![0.3125, 2.25, 6.25, 12.8125, 16.0]);
/// ```
pub fn between_samples(x: &[f64]) -> Vec<f64> {
    let n = x.len() as isize;
    let at = |k: isize| x[k.clamp(0, n - 1) as usize];
    (0..n)
        .map(|k| {
            if k + 1 >= n {
                at(k)
            } else {
                between(at(k - 1), at(k), at(k + 1), at(k + 2))
            }
        })
        .collect()
}

/// [`between_samples`] of one period of a periodic signal: element `k` lies between `x[k]`
/// and `x[k + 1]`, the period wrapping round (the last element between the last sample and
/// the first).
///
/// ```
/// use twinstack_identify::stage_model::between_periodic;
/// assert_eq!(between_periodic(&[0.0, 1.0, 0.0, -1.0]), vec![0.625, 0.625, -0.625, -0.625]);
/// ```
pub fn between_periodic(x: &[f64]) -> Vec<f64> {
    let n = x.len() as isize;
    let at = |k: isize| x[k.rem_euclid(n) as usize];
    (0..n)
        .map(|k| between(at(k - 1), at(k), at(k + 1), at(k + 2)))
        .collect()
}

/// The value of the present reading's instant from a history of the last ticks' values,
/// newest first, this tick's included: the end of the hold of
/// [`SENSOR_DELAY_TICKS`] ticks ago, between
/// the values of the holds' middles around it — the tick's
/// `twinstack::control::instant::ReadingInstant`, in `f64`.
pub fn at_reading(history: &[f64; SENSOR_DELAY_TICKS + 2]) -> f64 {
    let d = SENSOR_DELAY_TICKS;
    between(history[d + 1], history[d], history[d - 1], history[d - 2])
}

/// The sample rate of a record with times `t`: one over the median interval (`None` for fewer
/// than two samples or a non-increasing median).
pub fn sample_rate(t: &[f64]) -> Option<f64> {
    let mut dt: Vec<f64> = t.windows(2).map(|w| w[1] - w[0]).collect();
    dt.sort_by(f64::total_cmp);
    match dt.get(dt.len() / 2) {
        Some(&d) if d > 0.0 && d.is_finite() => Some(1.0 / d),
        _ => None,
    }
}

/// A creep operator run over a record in fixed point, its modes at rest at the first value.
struct CreepRun {
    creep: Creep,
    state: Option<CreepState>,
}

impl CreepRun {
    fn forward(&mut self, y: i32) -> i32 {
        let s = self
            .state
            .get_or_insert_with(|| self.creep.state_at_rest(y));
        self.creep.forward_step(s, y)
    }

    fn inverse(&mut self, x: i32) -> i32 {
        let s = self
            .state
            .get_or_insert_with(|| self.creep.state_at_rest(x));
        self.creep.inverse_step(s, x)
    }
}

/// A creep operator run over a record in `f64`, its modes at rest at the first value.
struct CreepReference {
    params: CreepParams,
    rate_hz: f64,
    run: Option<reference::Creep>,
}

impl CreepReference {
    fn run(&mut self, v: f64) -> Result<&mut reference::Creep, ParamError> {
        if self.run.is_none() {
            self.run = Some(reference::Creep::new(&self.params, self.rate_hz, v)?);
        }
        self.run.as_mut().ok_or(ParamError::NotFinite)
    }
}

impl StageModel {
    /// The fixed-point creep for a record with times `t` (at its sample rate), if any.
    fn creep_run(&self, t: &[f64]) -> Result<Option<CreepRun>, ParamError> {
        let Some(p) = &self.creep else {
            return Ok(None);
        };
        let rate = sample_rate(t).ok_or(ParamError::Creep(
            twinstack::models::creep::CreepError::NotFinite { mode: 0 },
        ))?;
        Ok(Some(CreepRun {
            creep: Creep::new(p, rate)?,
            state: None,
        }))
    }

    /// The `f64` creep for a record with times `t`, if any.
    fn creep_reference(&self, t: &[f64]) -> Result<Option<CreepReference>, ParamError> {
        let Some(p) = &self.creep else {
            return Ok(None);
        };
        let rate_hz = sample_rate(t).ok_or(ParamError::Creep(
            twinstack::models::creep::CreepError::NotFinite { mode: 0 },
        ))?;
        p.check(rate_hz)?;
        Ok(Some(CreepReference {
            params: p.clone(),
            rate_hz,
            run: None,
        }))
    }

    /// The lag in half samples for a record with times `t` (rounded to the median interval).
    pub fn lag_half_samples(&self, t: &[f64]) -> usize {
        let mut dt: Vec<f64> = t.windows(2).map(|w| w[1] - w[0]).collect();
        dt.sort_by(f64::total_cmp);
        match dt.get(dt.len() / 2) {
            Some(&d) if d > 0.0 => (2.0 * self.sensor_lag_s / d).round().max(0.0) as usize,
            _ => 0,
        }
    }

    /// The whole samples a drive sample's reading lies ahead of it, for a record with times
    /// `t`: the lag rounded up (a half lag's reading needs the sample after).
    pub fn lag_samples(&self, t: &[f64]) -> usize {
        self.lag_half_samples(t).div_ceil(2)
    }

    /// How many drive samples in `u` sit at an end of the input range (within a millionth of
    /// its span): where a compensator's drive ran into it.
    ///
    /// ```
    /// use twinstack::{PiParams, Scaling};
    /// use twinstack_identify::stage_model::{Hysteresis, StageModel};
    /// let m = StageModel {
    ///     hysteresis: Hysteresis::Pi(PiParams::new(0.0, 0.5, &[0.0, 30.0], &[0.08, 0.03]).unwrap()),
    ///     scaling: Scaling::new(0.0, 140.0, -20.0, 21.0).unwrap(),
    ///     output_sign: 1.0,
    ///     sensor_lag_s: 0.0,
    ///     creep: None,
    ///     output_map: None,
    /// };
    /// assert_eq!(m.drive_at_range_end(&[0.0, 70.0, 140.0, 139.9]), 2);
    /// ```
    pub fn drive_at_range_end(&self, u: &[f64]) -> usize {
        let s = &self.scaling;
        let near = 1e-6 * (s.input_max - s.input_min);
        u.iter()
            .filter(|&&v| v <= s.input_min + near || v >= s.input_max - near)
            .count()
    }

    /// How many drive samples in `u` lie outside the input range (the models clamp them).
    pub fn drive_outside_range(&self, u: &[f64]) -> usize {
        let s = &self.scaling;
        u.iter()
            .filter(|&&v| v < s.input_min || v > s.input_max)
            .count()
    }

    /// How many readings in `x` lie outside the output range once sign-corrected (the
    /// compensator clamps them).
    pub fn reading_outside_range(&self, x: &[f64]) -> usize {
        let (lo, hi) = self.reading_range();
        x.iter().filter(|&&v| v < lo || v > hi).count()
    }

    /// The output range as the sensor reads it (before the sign correction): `lo ≤ hi`.
    pub fn reading_range(&self) -> (f64, f64) {
        let s = &self.scaling;
        let (a, b) = (
            self.output_sign * s.output_min,
            self.output_sign * s.output_max,
        );
        (a.min(b), a.max(b))
    }

    /// Checks the library accepts the model for both the observer and the compensator, and
    /// its output map where it has one.
    pub fn check(&self) -> Result<(), ParamError> {
        match &self.hysteresis {
            Hysteresis::Pi(p) => {
                PrandtlIshlinskii::new(p, &self.scaling)?;
                InversePrandtlIshlinskii::new(p, &self.scaling)?;
            }
            Hysteresis::Duhem(p) => {
                InverseDuhem::new(p, &self.scaling)?;
            }
            Hysteresis::GeneralisedPi(p) => {
                GeneralisedPi::new(p, &self.scaling)?;
                InverseGeneralisedPi::new(p, &self.scaling)?;
            }
            Hysteresis::BoucWen(p) => {
                InverseBoucWen::new(p, &self.scaling)?;
            }
        }
        self.output_map_run()?;
        Ok(())
    }

    /// The fixed-point output map on this model's scaling, if any (refused as the board
    /// refuses it: not increasing, or beyond the fixed-point formats).
    fn output_map_run(&self) -> Result<Option<OutputMap>, ParamError> {
        self.output_map
            .as_ref()
            .map(|m| OutputMap::new(m, &self.scaling))
            .transpose()
    }

    /// The readings the model's outputs `y` give: reading `k` is output `k − λ` (between two
    /// outputs, the value between them, [`between_samples`]; before the first, the first).
    fn delay(&self, t: &[f64], y: Vec<f64>) -> Vec<f64> {
        let h = self.lag_half_samples(t);
        let (whole, half) = (h / 2, h % 2 == 1);
        let mid = if half {
            between_samples(&y)
        } else {
            Vec::new()
        };
        (0..y.len())
            .map(|k| {
                let j = k.saturating_sub(whole);
                let v = match (half, j) {
                    (false, _) | (true, 0) => y[j],
                    (true, j) => mid[j - 1],
                };
                self.output_sign * v
            })
            .collect()
    }

    /// The output each drive sample is to give, from the readings wanted `x`: the reading
    /// `λ` samples on (between two readings, the value between them, [`between_samples`];
    /// past the last, the last).
    fn advance(&self, t: &[f64], x: &[f64]) -> Vec<f64> {
        let h = self.lag_half_samples(t);
        let (whole, half) = (h / 2, h % 2 == 1);
        let last = x.len().saturating_sub(1);
        let mid = if half { between_samples(x) } else { Vec::new() };
        (0..x.len())
            .map(|k| {
                let j = (k + whole).min(last);
                self.output_sign * if half { mid[j] } else { x[j] }
            })
            .collect()
    }

    /// Forward model on drive `u` (volts) at times `t`, in the library's fixed point:
    /// the sensor reading it predicts at each sample.
    pub fn predict(&self, t: &[f64], u: &[f64]) -> Result<Vec<f64>, ParamError> {
        Ok(self.delay(t, self.hold_outputs(t, u)?))
    }

    /// [`StageModel::predict`] as `identify` fits it: element `k` is the (sign-applied)
    /// output of drive `k − ⌊λ⌋`, which `identify` pairs with the reading `k` (with a half
    /// lag, the value between readings `k` and `k + 1`).
    pub fn predict_targets(&self, t: &[f64], u: &[f64]) -> Result<Vec<f64>, ParamError> {
        let y = self.hold_outputs(t, u)?;
        let whole = self.lag_half_samples(t) / 2;
        Ok((0..y.len())
            .map(|k| self.output_sign * y[k.saturating_sub(whole)])
            .collect())
    }

    /// The model's output for each drive sample, fixed point.
    fn hold_outputs(&self, t: &[f64], u: &[f64]) -> Result<Vec<f64>, ParamError> {
        let s = &self.scaling;
        let u_norm = |v: f64| signal_from_f64(s.input_to_norm(v));
        let y_phys = |q: i32| s.norm_to_output(signal_to_f64(q));
        let u0 = u.first().copied().unwrap_or(0.0);
        let mut creep = self.creep_run(t)?;
        let map = self.output_map_run()?;
        // After the model: the map, then the creep (`twinstack::models::dispatch::ObserverRun`).
        let mut creep = |z: i32| {
            let q = map.as_ref().map_or(z, |m| m.forward(z));
            match creep.as_mut() {
                Some(c) => c.forward(q),
                None => q,
            }
        };
        let y: Vec<f64> = match &self.hysteresis {
            Hysteresis::Pi(p) => {
                let m = PrandtlIshlinskii::new(p, s)?;
                let mut st = m.state_at_rest(u_norm(u0));
                u.iter()
                    .map(|&v| y_phys(creep(m.step(&mut st, u_norm(v)))))
                    .collect()
            }
            Hysteresis::Duhem(p) => {
                let m = Duhem::new(p, s)?;
                let mut st = m.state_at_rest(u_norm(u0));
                u.iter()
                    .map(|&v| y_phys(creep(m.step(&mut st, u_norm(v)))))
                    .collect()
            }
            Hysteresis::GeneralisedPi(p) => {
                let m = GeneralisedPi::new(p, s)?;
                let mut st = m.state_at_rest(u_norm(u0));
                u.iter()
                    .map(|&v| y_phys(creep(m.step(&mut st, u_norm(v)))))
                    .collect()
            }
            Hysteresis::BoucWen(p) => {
                let m = BoucWen::new(p, s)?;
                let mut st = m.state_at_rest(u_norm(u0));
                u.iter()
                    .map(|&v| y_phys(creep(m.step(&mut st, u_norm(v)))))
                    .collect()
            }
        };
        Ok(y)
    }

    /// The slope a [`NoiseBand`] passes what it holds back through, normalised: the
    /// anhysteretic slope of a Duhem (`β`) or Bouc–Wen (`k`); `None` for the P–I family,
    /// whose inverse takes a measured trajectory as it comes (see [`NoiseBand`]).
    fn band_slope(&self) -> Result<Option<f64>, ParamError> {
        let s = &self.scaling;
        Ok(match &self.hysteresis {
            Hysteresis::Duhem(p) => Some(p.normalized(s)?.beta),
            Hysteresis::BoucWen(p) => Some(p.normalized(s)?.k),
            Hysteresis::Pi(_) | Hysteresis::GeneralisedPi(_) => None,
        })
    }

    /// The noise band [`Self::compensate_measured`] follows the measured readings `x` at
    /// times `t` through (taken on what the hysteresis inverse is given: after the inverse
    /// creep, whose gain above 1 passes the noise on larger); `None` for a P–I or generalised
    /// P–I, which takes them as they come.
    pub fn noise_band(&self, t: &[f64], x: &[f64]) -> Result<Option<NoiseBand>, ParamError> {
        let s = &self.scaling;
        let Some(slope) = self.band_slope()? else {
            return Ok(None);
        };
        let (_, targets) = self.hysteresis_targets(t, x)?;
        Ok(Some(NoiseBand::of(&given_of(&targets, s), slope, s)))
    }

    /// [`Self::predict`] computed by the `f64` reference models.
    pub fn predict_reference(&self, t: &[f64], u: &[f64]) -> Result<Vec<f64>, ParamError> {
        let s = &self.scaling;
        let u0 = u.first().copied().unwrap_or(0.0);
        let mut y: Vec<f64> = match &self.hysteresis {
            Hysteresis::Pi(p) => {
                let mut m = reference::PrandtlIshlinskii::new(p, s, u0)?;
                u.iter().map(|&v| m.step(v)).collect()
            }
            Hysteresis::Duhem(p) => {
                let mut m = reference::Duhem::at_rest(p, s, u0)?;
                u.iter().map(|&v| m.step(v)).collect()
            }
            Hysteresis::GeneralisedPi(p) => {
                let mut m = reference::GeneralisedPi::new(p, s, u0)?;
                u.iter().map(|&v| m.step(v)).collect()
            }
            Hysteresis::BoucWen(p) => {
                let mut m = reference::BoucWen::at_rest(p, s, u0)?;
                u.iter().map(|&v| m.step(v)).collect()
            }
        };
        if let Some(map) = &self.output_map {
            map.validate()?;
            for v in y.iter_mut() {
                *v = reference::dead_zone_map(map, *v);
            }
        }
        if let Some(mut c) = self.creep_reference(t)? {
            for v in y.iter_mut() {
                *v = c.run(*v)?.step(*v);
            }
        }
        Ok(self.delay(t, y))
    }

    /// Inverse model: the drive (volts) that makes the sensor read `x` at times `t`, in the
    /// library's fixed point, every sample inverted exactly, as the board inverts its
    /// setpoints: `x` is a planned trajectory. With a sensor lag of `L` samples the drive
    /// leads by `L`.
    pub fn compensate(&self, t: &[f64], x: &[f64]) -> Result<Vec<f64>, ParamError> {
        Ok(self.inverse_run(t, x, false)?.0)
    }

    /// [`Self::compensate`] of a *measured* trajectory `x` (a sensor's record, with its
    /// noise): followed through its [`NoiseBand`], so that the sensor's noise is not taken
    /// for motion. What identification scores a candidate's inverse by.
    pub fn compensate_measured(&self, t: &[f64], x: &[f64]) -> Result<Vec<f64>, ParamError> {
        Ok(self.inverse_run(t, x, true)?.0)
    }

    /// [`Self::compensate_measured`] and the [`NoiseBand`] it followed the readings through
    /// (`None` for a P–I or generalised P–I, which takes them as they come): one estimate of
    /// the noise for both.
    pub fn compensate_measured_with_band(
        &self,
        t: &[f64],
        x: &[f64],
    ) -> Result<(Vec<f64>, Option<NoiseBand>), ParamError> {
        self.inverse_run(t, x, true)
    }

    /// What the fixed-point hysteresis inverse is given for the desired readings `x` at times
    /// `t`: the first desired output of the model (output units: with a map, the map's
    /// inverse of the first desired reading, where the board rests the model), and the
    /// trajectory, advanced by the sensor's lag, through the inverse creep and the map's
    /// inverse, normalised.
    fn hysteresis_targets(&self, t: &[f64], x: &[f64]) -> Result<(f64, Vec<i32>), ParamError> {
        let s = &self.scaling;
        let y_norm = |v: f64| signal_from_f64(s.output_to_norm(v));
        let desired = self.advance(t, x);
        let y0 = desired.first().copied().unwrap_or(0.0);
        let mut creep = self.creep_run(t)?;
        let map = self.output_map_run()?;
        let y0 = match &map {
            Some(m) => s.norm_to_output(signal_to_f64(m.inverse(y_norm(y0)))),
            None => y0,
        };
        let targets = desired
            .iter()
            .map(|&v| {
                let q = match creep.as_mut() {
                    Some(c) => c.inverse(y_norm(v)),
                    None => y_norm(v),
                };
                map.as_ref().map_or(q, |m| m.inverse(q))
            })
            .collect();
        Ok((y0, targets))
    }

    /// [`Self::compensate`], or with `measured` [`Self::compensate_measured`]; and the band
    /// a measured trajectory was followed through, if any.
    fn inverse_run(
        &self,
        t: &[f64],
        x: &[f64],
        measured: bool,
    ) -> Result<(Vec<f64>, Option<NoiseBand>), ParamError> {
        let s = &self.scaling;
        let u_phys = |q: i32| s.norm_to_input(signal_to_f64(q));
        let (y0, targets) = self.hysteresis_targets(t, x)?;
        // The noise band of a measured trajectory is taken on what the inverse is given: the
        // inverse creep's gain above 1 passes the sensor's noise on larger.
        let given = || given_of(&targets, s);
        Ok(match &self.hysteresis {
            Hysteresis::Pi(p) => {
                let m = InversePrandtlIshlinskii::new(p, s)?;
                let mut st = m.state_at_rest(signal_from_f64(s.output_to_norm(y0)));
                // Every sample to its memory, measured or not: see `NoiseBand`.
                let u = targets
                    .iter()
                    .map(|&y| u_phys(m.step(&mut st, y)))
                    .collect();
                (u, None)
            }
            Hysteresis::Duhem(p) => {
                let m = InverseDuhem::new(p, s)?;
                let y0 = y0.clamp(s.output_min, s.output_max);
                let u_norm = |u: f64| signal_from_f64(s.input_to_norm(u));
                let at_rest = |u: f64| m.model().state_at_rest(u_norm(u));
                let u0 = reference::drive_at_rest(s, y0, |u| {
                    s.norm_to_output(signal_to_f64(at_rest(u).y))
                });
                let y0_norm = signal_from_f64(s.output_to_norm(y0));
                let mut st = at_rest(u0);
                let band = NoiseBand::if_measured(measured, given, self.band_slope()?, s);
                let u =
                    NoiseBand::invert(band.clone(), &targets, y0_norm, s, |y| m.step(&mut st, y));
                (u, band)
            }
            Hysteresis::GeneralisedPi(p) => {
                let m = InverseGeneralisedPi::new(p, s)?;
                let mut st = m.state_at_rest(signal_from_f64(s.output_to_norm(y0)));
                let u = targets
                    .iter()
                    .map(|&y| u_phys(m.step(&mut st, y)))
                    .collect();
                (u, None)
            }
            Hysteresis::BoucWen(p) => {
                let m = InverseBoucWen::new(p, s)?;
                let y0 = y0.clamp(s.output_min, s.output_max);
                let u_norm = |u: f64| signal_from_f64(s.input_to_norm(u));
                let at_rest = |u: f64| m.model().state_at_rest(u_norm(u));
                let u0 = reference::drive_at_rest(s, y0, |u| {
                    s.norm_to_output(signal_to_f64(m.model().output(&at_rest(u))))
                });
                let mut st = at_rest(u0);
                let band = NoiseBand::if_measured(measured, given, self.band_slope()?, s);
                let y0_norm = signal_from_f64(s.output_to_norm(y0));
                let u =
                    NoiseBand::invert(band.clone(), &targets, y0_norm, s, |y| m.step(&mut st, y));
                (u, band)
            }
        })
    }

    /// [`Self::compensate`] computed by the `f64` reference models.
    pub fn compensate_reference(&self, t: &[f64], x: &[f64]) -> Result<Vec<f64>, ParamError> {
        self.inverse_reference(t, x, false)
    }

    /// [`Self::compensate_measured`] computed by the `f64` reference models.
    pub fn compensate_measured_reference(
        &self,
        t: &[f64],
        x: &[f64],
    ) -> Result<Vec<f64>, ParamError> {
        self.inverse_reference(t, x, true)
    }

    /// [`Self::compensate_reference`], or with `measured`
    /// [`Self::compensate_measured_reference`].
    fn inverse_reference(
        &self,
        t: &[f64],
        x: &[f64],
        measured: bool,
    ) -> Result<Vec<f64>, ParamError> {
        let s = &self.scaling;
        let mut desired = self.advance(t, x);
        if let Some(mut c) = self.creep_reference(t)? {
            for v in desired.iter_mut() {
                *v = c.run(*v)?.inverse_step(*v);
            }
        }
        // The map's inverse after the creep's, the desired output clamped to the output range
        // as the fixed-point map clamps it to full scale.
        if let Some(map) = &self.output_map {
            map.validate()?;
            for v in desired.iter_mut() {
                *v = reference::dead_zone_map_inverse(map, v.clamp(s.output_min, s.output_max));
            }
        }
        let y0 = desired
            .first()
            .copied()
            .unwrap_or(0.0)
            .clamp(s.output_min, s.output_max);
        Ok(match &self.hysteresis {
            Hysteresis::Pi(p) => {
                let c = p.canonical()?;
                let total: f64 = c.weights.iter().sum();
                let mut m =
                    reference::InversePrandtlIshlinskii::new(p, s, (y0 - c.offset) / total)?;
                desired.iter().map(|&v| m.step(v)).collect()
            }
            Hysteresis::Duhem(p) => {
                let at_rest = |u: f64| reference::Duhem::at_rest(p, s, u).map(|m| m.y);
                p.validate()?;
                let u0 = reference::drive_at_rest(s, y0, |u| at_rest(u).unwrap_or(f64::NAN));
                let mut m = reference::InverseDuhem::with_rest(p, s, u0, Rest::Ascending)?;
                // The band on what the inverse is given (after the inverse creep), as the
                // fixed-point `compensate_measured` takes it.
                let band = NoiseBand::if_measured(measured, || &desired, self.band_slope()?, s);
                NoiseBand::invert_reference(band, &desired, y0, p.beta, s, |y| m.step(y))
            }
            Hysteresis::GeneralisedPi(p) => {
                // Relaxed where the P–I part's output is S⁻¹[y0], as for the P–I.
                let c = p.pi.canonical()?;
                let total: f64 = c.weights.iter().sum();
                let mut m = reference::InverseGeneralisedPi::new(p, s, 0.0)?;
                let z0 = m.map_inverse(y0);
                m = reference::InverseGeneralisedPi::new(p, s, (z0 - c.offset) / total)?;
                desired.iter().map(|&v| m.step(v)).collect()
            }
            Hysteresis::BoucWen(p) => {
                let at_rest = |u: f64| reference::BoucWen::at_rest(p, s, u).map(|m| m.output());
                p.validate()?;
                let u0 = reference::drive_at_rest(s, y0, |u| at_rest(u).unwrap_or(f64::NAN));
                let mut m = reference::InverseBoucWen::with_rest(p, s, u0, Rest::Ascending)?;
                let band = NoiseBand::if_measured(measured, || &desired, self.band_slope()?, s);
                NoiseBand::invert_reference(band, &desired, y0, p.k, s, |y| m.step(y))
            }
        })
    }
}

/// Normalised targets `targets` in output units (what a noise band is estimated on).
fn given_of(targets: &[i32], s: &Scaling) -> Vec<f64> {
    targets
        .iter()
        .map(|&q| s.norm_to_output(signal_to_f64(q)))
        .collect()
}

/// Band widths in units of the trajectory's noise RMS: reversals smaller than this are noise.
pub const NOISE_BAND_SIGMAS: f64 = 3.0;

/// The noise band of a measured trajectory given to the inverse Duhem or Bouc–Wen
/// ([`StageModel::compensate_measured`]).
///
/// A Duhem or Bouc–Wen model relaxes towards its anhysteretic curve whenever its input moves,
/// whichever way: dithered, it forgets its hysteresis. Its exact inverse, given a *measured*
/// trajectory, treats every sample of sensor noise as a reversal of the desired motion and
/// ratchets its drive towards the anhysteretic curve (12.9 % on the bipolar set for Duhem).
/// So the inverse's memory follows the trajectory through a play operator of half-width `3σ`
/// (`σ` the trajectory's noise RMS, estimated from its second differences, robustly: corners
/// of a triangle do not count), and what the band holds back passes straight through at the
/// anhysteretic slope (`1/β` for Duhem, `1/k` for Bouc–Wen).
///
/// A P–I's or generalised P–I's memory closes every loop the noise makes (no ratchet), and
/// its inverse is steepest just after a reversal, where a band would hold back the start of
/// every real reversal too: it gets none. (Tried at the major loop's mean slope, a band made
/// one shipped record's P–I inverses better and the other's generalised P–I inverse worse:
/// what it holds back of each real reversal passes at the mean slope, not the steep one.)
///
/// A planned trajectory (the board's setpoints, a `compensate` of a desired path) gets no
/// band: [`StageModel::compensate`] inverts every sample exactly. The estimate cannot tell
/// noise from a smooth trajectory sampled coarsely (a sine at 20 samples a period has second
/// differences of 10 % of its amplitude, which a band of `3σ` would hold back as noise), so
/// the band is asked for, never guessed.
#[derive(Clone, Debug, PartialEq)]
pub struct NoiseBand {
    /// Noise RMS of the trajectory, output units.
    pub noise_rms: f64,
    /// Half-width of the band, normalised output units.
    pub width_norm: f64,
    /// The inverse of the anhysteretic slope, normalised (input span per output span).
    pub inverse_slope_norm: f64,
}

impl NoiseBand {
    /// The band for trajectory `x` (output units) on `scaling`, for a model whose
    /// anhysteretic slope is `slope_norm` (normalised: Duhem's `β`, Bouc–Wen's `k`).
    pub fn of(x: &[f64], slope_norm: f64, scaling: &Scaling) -> Self {
        let noise_rms = noise_rms(x);
        Self {
            noise_rms,
            width_norm: (NOISE_BAND_SIGMAS * noise_rms / scaling.output_half_span()).min(1.0),
            inverse_slope_norm: 1.0 / slope_norm,
        }
    }

    /// The band of the trajectory `x()` (output units) if it is `measured`; `None` (every
    /// sample inverted exactly) for a planned one.
    fn if_measured<X: AsRef<[f64]>>(
        measured: bool,
        x: impl FnOnce() -> X,
        slope_norm: Option<f64>,
        scaling: &Scaling,
    ) -> Option<Self> {
        let slope_norm = slope_norm.filter(|_| measured)?;
        Some(Self::of(x().as_ref(), slope_norm, scaling))
    }

    /// The drive, volts, for the normalised `targets` through `band` ([`Self::around`]), or
    /// without one, each target inverted exactly by `step`.
    fn invert(
        band: Option<Self>,
        targets: &[i32],
        y0: i32,
        scaling: &Scaling,
        mut step: impl FnMut(i32) -> i32,
    ) -> Vec<f64> {
        match band {
            Some(b) => b.around(targets, y0, scaling, step),
            None => targets
                .iter()
                .map(|&y| scaling.norm_to_input(signal_to_f64(step(y))))
                .collect(),
        }
    }

    /// [`Self::invert`] in `f64` and physical units ([`Self::around_reference`]).
    fn invert_reference(
        band: Option<Self>,
        desired: &[f64],
        y0: f64,
        slope: f64,
        scaling: &Scaling,
        mut step: impl FnMut(f64) -> f64,
    ) -> Vec<f64> {
        match band {
            Some(b) => b.around_reference(desired, y0, slope, scaling, step),
            None => desired.iter().map(|&v| step(v)).collect(),
        }
    }

    /// The drive, volts, for the normalised `targets` (starting from `y0`, normalised): the
    /// fixed-point inverse `step`'s memory follows them through the band (a play operator of
    /// the band's half-width), what the band holds back passes through the anhysteretic
    /// slope, and the sum is clamped to full scale.
    fn around(
        &self,
        targets: &[i32],
        y0: i32,
        scaling: &Scaling,
        mut step: impl FnMut(i32) -> i32,
    ) -> Vec<f64> {
        let width = signal_from_f64(self.width_norm);
        let through = gain_from_f64(self.inverse_slope_norm);
        let mut filtered = y0;
        targets
            .iter()
            .map(|&y| {
                filtered = play(y, width, filtered);
                let rest = (y as i64 - filtered as i64) * through as i64;
                let u = step(filtered) as i64 + (rest >> GAIN_FRAC_BITS);
                scaling.norm_to_input(signal_to_f64(clamp_full_scale(saturate_i64(u))))
            })
            .collect()
    }

    /// [`NoiseBand::around`] in `f64` and physical units: `targets` and `y0` output units,
    /// `slope` the anhysteretic slope (output units per volt), the `f64` inverse `step`.
    fn around_reference(
        &self,
        targets: &[f64],
        y0: f64,
        slope: f64,
        scaling: &Scaling,
        mut step: impl FnMut(f64) -> f64,
    ) -> Vec<f64> {
        let width = self.width_norm * scaling.output_half_span();
        let mut filtered = y0;
        targets
            .iter()
            .map(|&v| {
                filtered = reference::play(v, width, filtered);
                (step(filtered) + (v - filtered) / slope)
                    .clamp(scaling.input_min, scaling.input_max)
            })
            .collect()
    }
}

/// Noise RMS of a sampled signal from its second differences `x_k − (x_{k−1} + x_{k+1})/2`
/// (for white noise their RMS is `σ·√1.5`), taken robustly as the median absolute value
/// over 0.6745: the few samples where a trajectory turns do not count.
pub fn noise_rms(x: &[f64]) -> f64 {
    let mut d: Vec<f64> = x
        .windows(3)
        .map(|w| (w[1] - 0.5 * (w[0] + w[2])).abs())
        .filter(|v| v.is_finite())
        .collect();
    if d.is_empty() {
        return 0.0;
    }
    let mid = d.len() / 2;
    let (_, median, _) = d.select_nth_unstable_by(mid, f64::total_cmp);
    *median / 0.6745 / 1.5f64.sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pi_model(sign: f64, lag_s: f64) -> StageModel {
        StageModel {
            hysteresis: Hysteresis::Pi(
                PiParams::new(0.0, 1.0, &[0.0, 20.0, 40.0], &[0.08, 0.03, 0.02]).unwrap(),
            ),
            scaling: Scaling::new(-100.0, 100.0, -15.0, 17.0).unwrap(),
            output_sign: sign,
            sensor_lag_s: lag_s,
            creep: None,
            output_map: None,
        }
    }

    fn record() -> (Vec<f64>, Vec<f64>) {
        let t: Vec<f64> = (0..800).map(|k| k as f64 * 0.01).collect();
        let u = t.iter().map(|&t| 90.0 * (t * 2.0).sin()).collect();
        (t, u)
    }

    #[test]
    fn fixed_point_prediction_tracks_the_f64_reference() {
        let m = pi_model(1.0, 0.0);
        let (t, u) = record();
        let fx = m.predict(&t, &u).unwrap();
        let rf = m.predict_reference(&t, &u).unwrap();
        let worst = fx
            .iter()
            .zip(&rf)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        // The packed bank's Q1.15 grid: within 1 LSB16 of the output span (see
        // docs/src/reference/fixed-point.md).
        let lsb = (m.scaling.output_max - m.scaling.output_min) / 65536.0;
        assert!(worst < lsb, "{worst} against 1 LSB16 = {lsb}");
    }

    fn duhem_model() -> StageModel {
        StageModel {
            hysteresis: Hysteresis::Duhem(DuhemParams {
                alpha: 0.03,
                beta: 0.2,
                gamma: 0.12,
                offset: 0.5,
            }),
            scaling: Scaling::new(-100.0, 100.0, -25.0, 25.0).unwrap(),
            output_sign: 1.0,
            sensor_lag_s: 0.0,
            creep: None,
            output_map: None,
        }
    }

    /// Deterministic unit-variance noise (sum of 4 uniforms from an xorshift).
    fn noise(n: usize) -> Vec<f64> {
        let mut s = 0x9e37_79b9_7f4a_7c15u64;
        (0..n)
            .map(|_| {
                let mut v = 0.0;
                for _ in 0..4 {
                    s ^= s << 13;
                    s ^= s >> 7;
                    s ^= s << 17;
                    v += (s >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
                }
                v * 3f64.sqrt()
            })
            .collect()
    }

    #[test]
    fn the_noise_estimate_sees_noise_and_not_the_trajectory() {
        let t: Vec<f64> = (0..20_000).map(|k| k as f64 * 1e-4).collect();
        // A triangle and a sine: no noise to speak of (the corners do not count).
        let triangle: Vec<f64> = t
            .iter()
            .map(|&t| 10.0 * ((t * 5.0) % 1.0 - 0.5).abs())
            .collect();
        assert!(noise_rms(&triangle) < 1e-9, "{}", noise_rms(&triangle));
        let sine: Vec<f64> = t.iter().map(|&t| 10.0 * (t * 60.0).sin()).collect();
        // (its curvature: second differences of 10·(60·1e-4)²/2 at most)
        assert!(noise_rms(&sine) < 1e-3, "{}", noise_rms(&sine));
        // Noise of RMS 0.05 on the sine is found to within 10 %.
        let noisy: Vec<f64> = sine
            .iter()
            .zip(noise(t.len()))
            .map(|(a, n)| a + 0.05 * n)
            .collect();
        let found = noise_rms(&noisy);
        assert!((found - 0.05).abs() < 0.005, "{found}");
        assert_eq!(noise_rms(&[1.0, 2.0]), 0.0);
    }

    /// A generalised Bouc–Wen model on the Duhem model's ranges: asymmetric (`γ`, `ψ`).
    fn bouc_wen_model() -> StageModel {
        StageModel {
            hysteresis: Hysteresis::BoucWen(BoucWenParams {
                k: 0.2,
                offset: 0.5,
                a: 0.05,
                beta: 0.02,
                gamma: 0.004,
                psi: 0.003,
                chi: 0.001,
            }),
            ..duhem_model()
        }
    }

    /// The library's inverse alone on `x` (output units), every sample fed to its memory:
    /// the drive, volts.
    fn exact_inverse(m: &StageModel, x: &[f64]) -> Vec<f64> {
        let s = &m.scaling;
        let norm = |x: f64| signal_from_f64(s.output_to_norm(x));
        let volts = |q: i32| s.norm_to_input(signal_to_f64(q));
        match &m.hysteresis {
            Hysteresis::Duhem(p) => {
                let inv = InverseDuhem::new(p, s).unwrap();
                let mut st = inv.model().state_at(0, norm(x[0]));
                x.iter()
                    .map(|&x| volts(inv.step(&mut st, norm(x))))
                    .collect()
            }
            Hysteresis::BoucWen(p) => {
                let inv = InverseBoucWen::new(p, s).unwrap();
                let u0 = signal_from_f64(s.input_to_norm((x[0] - p.offset) / p.k));
                let mut st = inv.model().relaxed(u0);
                x.iter()
                    .map(|&x| volts(inv.step(&mut st, norm(x))))
                    .collect()
            }
            _ => unreachable!("the models with a noise band"),
        }
    }

    /// A planned trajectory is inverted exactly by every model, however coarsely it is
    /// sampled: a sine at 20 samples a period (whose second differences a noise estimate
    /// would take for noise of 7 % of its span) compensated gives back the drive that
    /// produced it, within a few LSB16 of the input span.
    #[test]
    fn a_coarsely_sampled_planned_trajectory_is_inverted_exactly_by_every_model() {
        let t: Vec<f64> = (0..600).map(|k| k as f64 * 5e-4).collect();
        let u: Vec<f64> = t
            .iter()
            .map(|&t| 80.0 * (t * 100.0 * std::f64::consts::TAU).sin())
            .collect();
        for (name, m) in [
            ("P–I", pi_model(1.0, 0.0)),
            ("Duhem", duhem_model()),
            ("Bouc–Wen", bouc_wen_model()),
        ] {
            let x = m.predict(&t, &u).unwrap();
            // What a band would take for noise (the P–I never has one); the measured inverse
            // follows the very band `noise_band` estimates.
            let band = m.noise_band(&t, &x).unwrap();
            if let Some(band) = &band {
                assert!(
                    band.width_norm > 0.01,
                    "{name}: the estimate sees noise: {band:?}"
                );
            }
            let (measured, followed) = m.compensate_measured_with_band(&t, &x).unwrap();
            assert_eq!(followed, band, "{name}");
            assert_eq!(measured, m.compensate_measured(&t, &x).unwrap(), "{name}");
            let lsb = (m.scaling.input_max - m.scaling.input_min) / 65536.0;
            for (run, back) in [
                ("fixed point", m.compensate(&t, &x).unwrap()),
                ("reference", m.compensate_reference(&t, &x).unwrap()),
            ] {
                for (k, (back, u)) in back.iter().zip(&u).enumerate().skip(1) {
                    assert!(
                        (back - u).abs() < 8.0 * lsb,
                        "{name}, {run}, sample {k}: {back} for {u}"
                    );
                }
            }
        }
    }

    /// The inverse Duhem and Bouc–Wen on a measured (noisy) trajectory: the drive each
    /// computes stays on the true drive, where the exact inverse on the same samples ratchets
    /// away from it.
    #[test]
    fn compensate_of_a_noisy_trajectory_does_not_ratchet() {
        // With creep before it, the inverse creep's gain above 1 passes the noise on larger:
        // the band is taken on what the hysteresis inverse is given.
        let with_creep = StageModel {
            creep: Some(CreepParams::new(&[0.02, 0.2], &[0.15, 0.1]).unwrap()),
            ..duhem_model()
        };
        for (name, m) in [
            ("Duhem", duhem_model()),
            ("Bouc–Wen", bouc_wen_model()),
            ("Duhem + creep", with_creep),
        ] {
            let t: Vec<f64> = (0..30_000).map(|k| k as f64 * 2e-4).collect();
            let u: Vec<f64> = t
                .iter()
                .map(|&t| 90.0 * (t * std::f64::consts::TAU).sin())
                .collect();
            let clean = m.predict(&t, &u).unwrap();
            let span = 40.0;
            let noisy: Vec<f64> = clean
                .iter()
                .zip(noise(t.len()))
                .map(|(x, n)| x + 0.002 * span * n)
                .collect();
            let worst = |drive: &[f64]| {
                drive[5000..]
                    .iter()
                    .zip(&u[5000..])
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max)
                    / 180.0
                    * 100.0
            };
            let banded = worst(&m.compensate_measured(&t, &noisy).unwrap());
            let banded_reference = worst(&m.compensate_measured_reference(&t, &noisy).unwrap());
            let unbanded = worst(&exact_inverse(&m, &noisy));
            eprintln!("{name}: drive error, % of span: banded {banded:.4} (f64 {banded_reference:.4}), exact inverse {unbanded:.4}");
            // Noise of 0.2 % of the output span is 0.22 % of the drive span through the
            // anhysteretic slope, and its peaks reach four times that.
            assert!(banded < 2.5, "{name}: {banded}");
            assert!(banded_reference < 2.5, "{name}: {banded_reference}");
            assert!(
                unbanded > 3.0 * banded,
                "{name}: the band made no difference: {unbanded} vs {banded}"
            );
            // A clean trajectory is inverted as without the band: the band shrinks to nothing.
            let back = m.compensate(&t, &clean).unwrap();
            let worst_clean = worst(&back);
            assert!(worst_clean < 1e-3, "{name}: {worst_clean}");
        }
    }

    #[test]
    fn sign_and_lag_are_applied_to_the_prediction() {
        let (t, u) = record();
        let plain = pi_model(1.0, 0.0).predict(&t, &u).unwrap();
        let turned = pi_model(-1.0, 0.02).predict(&t, &u).unwrap();
        for k in 2..t.len() {
            assert!((turned[k] + plain[k - 2]).abs() < 1e-12);
        }
    }

    proptest::proptest! {
        /// For any invertible P–I (non-negative weights, `w_1 > 0`), any sign and lag, and any
        /// drive inside the input range, the fixed-point compensator fed the fixed-point
        /// prediction gives back the drive.
        #[test]
        fn compensate_inverts_predict_for_any_invertible_pi(
            w1 in 0.05f64..0.5,
            rest in proptest::collection::vec(0.0f64..0.2, 1..8),
            offset in -3.0f64..3.0,
            negative in proptest::bool::ANY,
            lag in 0usize..4,
            drive in proptest::collection::vec(-100.0f64..100.0, 20..200),
        ) {
            let n = rest.len() + 1;
            let thresholds: Vec<f64> = (0..n).map(|i| 100.0 * i as f64 / n as f64).collect();
            let mut weights = vec![w1];
            weights.extend(&rest);
            let reach = 100.0 * weights.iter().sum::<f64>() + offset.abs() + 1.0;
            let m = StageModel {
                hysteresis: Hysteresis::Pi(PiParams::new(0.0, offset, &thresholds, &weights).unwrap()),
                scaling: Scaling::new(-100.0, 100.0, -reach, reach).unwrap(),
                output_sign: if negative { -1.0 } else { 1.0 },
                sensor_lag_s: lag as f64 * 0.01,
                creep: None,
                output_map: None,
            };
            // Models whose inverse does not fit Q8.24 are refused (tested elsewhere).
            proptest::prop_assume!(m.check().is_ok());
            let t: Vec<f64> = (0..drive.len()).map(|k| k as f64 * 0.01).collect();
            let x = m.predict(&t, &drive).unwrap();
            let back = m.compensate(&t, &x).unwrap();
            // 16 LSB16 of the input span (the packed banks' grid), plus 4 LSB16 of the
            // output span through the inverse's steepest slope 1/w1: the prediction the
            // compensator reads is on the output grid, and a small w1 magnifies its step
            // (see twinstack_identify::accuracy's bounds). A wrong inverse is volts off.
            let lsb = 200.0 / 65536.0;
            let lsb_out = 2.0 * reach / 65536.0;
            let bound = 16.0 * lsb + 4.0 * lsb_out / w1;
            for k in 0..drive.len() - lag {
                proptest::prop_assert!((back[k] - drive[k]).abs() < bound, "k {}: {} vs {} (bound {})", k, back[k], drive[k], bound);
            }
        }
    }

    /// The generalised P–I: fixed point tracks the `f64` reference (forward and inverse), and
    /// the compensator fed the prediction gives the drive back.
    #[test]
    fn generalised_pi_tracks_its_reference_and_inverts() {
        use twinstack::models::generalised_pi::DeadZoneParams;
        let Hysteresis::Pi(pi) = pi_model(1.0, 0.0).hysteresis else {
            unreachable!()
        };
        let m = StageModel {
            hysteresis: Hysteresis::GeneralisedPi(GpiParams {
                pi,
                dead_zones: DeadZoneParams::new(1.0, 0.9, &[-6.0, 4.0], &[-0.3, 0.4]).unwrap(),
            }),
            scaling: Scaling::new(-100.0, 100.0, -18.0, 20.0).unwrap(),
            output_sign: -1.0,
            sensor_lag_s: 0.02,
            creep: None,
            output_map: None,
        };
        m.check().unwrap();
        let (t, u) = record();
        let worst = |a: &[f64], b: &[f64]| {
            a.iter()
                .zip(b)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max)
        };
        // Tolerances in LSB16 of the spans: the packed banks' Q1.15 grid.
        let lsb_out = (m.scaling.output_max - m.scaling.output_min) / 65536.0;
        let lsb_in = (m.scaling.input_max - m.scaling.input_min) / 65536.0;
        let x = m.predict(&t, &u).unwrap();
        assert!(worst(&x, &m.predict_reference(&t, &u).unwrap()) < 2.0 * lsb_out);
        let back = m.compensate(&t, &x).unwrap();
        let back_ref = m.compensate_reference(&t, &x).unwrap();
        assert!(worst(&back, &back_ref) < 16.0 * lsb_in);
        let n = t.len() - 2;
        assert!(
            worst(&back[..n], &u[..n]) < 16.0 * lsb_in,
            "{}",
            worst(&back[..n], &u[..n])
        );
    }

    /// A flexure's stiffening over the Duhem model's output range (−25 … 25, centre 0).
    fn flexure_map() -> DeadZoneParams {
        DeadZoneParams::new(
            0.5,
            1.05,
            &[-16.0, -8.0, 8.0, 16.0],
            &[-0.1, -0.08, -0.08, -0.15],
        )
        .unwrap()
    }

    /// The output map runs where the board runs it: after the model and before the creep in
    /// `predict`, its inverse after the inverse creep in `compensate`; fixed point and `f64`
    /// reference agree, and the compensator fed the prediction gives the drive back.
    #[test]
    fn an_output_map_runs_between_the_model_and_the_creep() {
        let t: Vec<f64> = (0..4000).map(|k| k as f64 * 5e-4).collect();
        let u: Vec<f64> = t
            .iter()
            .map(|&t| 85.0 * (t * 3.0 * std::f64::consts::TAU).sin() * (1.0 - 0.2 * t))
            .collect();
        let map = flexure_map();
        let creep = CreepParams::new(&[0.02, 0.2], &[0.04, 0.03]).unwrap();
        let worst = |a: &[f64], b: &[f64]| {
            a.iter()
                .zip(b)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max)
        };
        // (The board takes a map after a Bouc–Wen only; the host runs it after any model.)
        for (name, bare) in [("Duhem", duhem_model()), ("Bouc–Wen", bouc_wen_model())] {
            let mapped = StageModel {
                output_map: Some(map.clone()),
                ..bare.clone()
            };
            mapped.check().unwrap();
            // Without creep, the prediction is the map of the model's.
            let plain = bare.predict_reference(&t, &u).unwrap();
            let through = mapped.predict_reference(&t, &u).unwrap();
            for (a, b) in plain.iter().zip(&through) {
                assert!((map.apply(*a) - b).abs() < 1e-9, "{name}");
            }
            let lsb_out = (bare.scaling.output_max - bare.scaling.output_min) / 65536.0;
            let lsb_in = (bare.scaling.input_max - bare.scaling.input_min) / 65536.0;
            for (with, m) in [
                ("map", mapped.clone()),
                (
                    "map + creep",
                    StageModel {
                        creep: Some(creep.clone()),
                        sensor_lag_s: 1e-3,
                        ..mapped.clone()
                    },
                ),
            ] {
                let x = m.predict(&t, &u).unwrap();
                let x_ref = m.predict_reference(&t, &u).unwrap();
                assert!(
                    worst(&x, &x_ref) < 4.0 * lsb_out,
                    "{name} + {with}: {}",
                    worst(&x, &x_ref)
                );
                // The last lag's samples have no reading to aim at.
                let n = t.len() - 2;
                let back = m.compensate(&t, &x).unwrap();
                let back_ref = m.compensate_reference(&t, &x_ref).unwrap();
                assert!(
                    worst(&back[1..n], &u[1..n]) < 16.0 * lsb_in,
                    "{name} + {with}: {}",
                    worst(&back[1..n], &u[1..n])
                );
                assert!(
                    worst(&back_ref[1..n], &u[1..n]) < 16.0 * lsb_in,
                    "{name} + {with}, f64: {}",
                    worst(&back_ref[1..n], &u[1..n])
                );
            }
        }
        // A map that falls is refused by `check`, as the board refuses it.
        let falling = StageModel {
            output_map: Some(DeadZoneParams::new(0.0, 1.0, &[10.0], &[-1.5]).unwrap()),
            ..duhem_model()
        };
        assert!(falling.check().is_err());
    }

    #[test]
    fn compensating_the_prediction_returns_the_drive() {
        for sign in [1.0, -1.0] {
            let m = pi_model(sign, 0.02);
            let (t, u) = record();
            let x = m.predict(&t, &u).unwrap();
            let back = m.compensate(&t, &x).unwrap();
            // The last `lag` samples have no future reading to aim at.
            // 4 LSB16 of the input span (the packed banks' Q1.15 grid).
            let lsb = (m.scaling.input_max - m.scaling.input_min) / 65536.0;
            for k in 0..t.len() - 2 {
                assert!(
                    (back[k] - u[k]).abs() < 4.0 * lsb,
                    "k {k}: {} vs {}",
                    back[k],
                    u[k]
                );
            }
        }
    }
}
