//! The discrete-time feedback loop as the tick runs it, in `f64`: a linear plant (normalised
//! drive → normalised sensor reading, with the converters' delay), the library's feedback
//! (notch, PI, derivative) and what a design is judged by — margins, closed-loop bandwidth,
//! closed-loop poles (stability) and the ringing after a step.
//!
//! **Timing** (as in `SimBoard` and on the board): the tick reads the sensor, computes
//! `u_k = feedforward + C(e)`, `e_k = r̄_k − y_k` (`r̄_k` the target between `r_{k−2}` and `r_{k−1}`, `twinstack::control::instant`) ([`twinstack::control::feedback::SENSOR_DELAY_TICKS`]),
//! and writes the DAC, which holds `u_k` over the next period. The stage advances by the exact
//! zero-order hold `x_{k+1} = Φ x_k + Γ u_k`; the reading of tick `k` is `y_k = c·x_{k−d}`
//! (`d = 1` on the simulated board: the ADC returns the previous conversion). So the loop
//! transfer is `L(z) = C(z) · P(z)`, `P(z) = c (zI − Φ)⁻¹ Γ z^{−d}`, with no other delay.
//!
//! **The controller** is the tick's own structure ([`twinstack::control::feedback`]): the notch on the
//! error, `N(z) = (b₀ + b₁z⁻¹ + b₂z⁻²)/(1 + a₁z⁻¹ + a₂z⁻²)` (the library's design for the rate),
//! then `kp + ki_t / (1 − z⁻¹) + kd_t · s (1 − z⁻¹) / (1 − (1 − s) z⁻¹)` with `ki_t = ki / f_s`,
//! `kd_t = kd · f_s`, `s = 1 − e^{−2π f_c / f_s}`. The fixed-point tick rounds these to
//! Q2.30/Q0.32/Q4.28; the loop is judged on the exact values (rounding moves the poles by
//! about 1e-9).

use crate::stage_model::at_reading;
use crate::zero_order_hold::ZeroOrderHold;
use std::f64::consts::PI;
use twinstack::control::feedback::{FeedbackSettings, SENSOR_DELAY_TICKS};

/// A complex number (the little arithmetic the loop needs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct C64 {
    /// Real part.
    pub re: f64,
    /// Imaginary part.
    pub im: f64,
}

impl C64 {
    /// `re + j im`.
    pub const fn new(re: f64, im: f64) -> Self {
        Self { re, im }
    }
    /// `e^{jθ}`.
    pub fn cis(theta: f64) -> Self {
        Self::new(theta.cos(), theta.sin())
    }
    /// Sum.
    pub fn plus(self, o: Self) -> Self {
        Self::new(self.re + o.re, self.im + o.im)
    }
    /// Difference.
    pub fn minus(self, o: Self) -> Self {
        Self::new(self.re - o.re, self.im - o.im)
    }
    /// Product.
    pub fn times(self, o: Self) -> Self {
        Self::new(
            self.re * o.re - self.im * o.im,
            self.re * o.im + self.im * o.re,
        )
    }
    /// Times a real.
    pub fn scale(self, k: f64) -> Self {
        Self::new(self.re * k, self.im * k)
    }
    /// Quotient (`o ≠ 0`; a zero divisor gives infinities, never a panic).
    pub fn over(self, o: Self) -> Self {
        let d = o.re * o.re + o.im * o.im;
        Self::new(
            (self.re * o.re + self.im * o.im) / d,
            (self.im * o.re - self.re * o.im) / d,
        )
    }
    /// Magnitude.
    pub fn abs(self) -> f64 {
        self.re.hypot(self.im)
    }
    /// Phase, radians in (−π, π].
    pub fn arg(self) -> f64 {
        self.im.atan2(self.re)
    }
}

/// A polynomial in `z`, coefficients in ascending powers (`p[0] + p[1] z + …`).
pub type Poly = Vec<f64>;

fn poly_mul(a: &[f64], b: &[f64]) -> Poly {
    let mut out = vec![0.0; a.len() + b.len() - 1];
    for (i, &x) in a.iter().enumerate() {
        for (j, &y) in b.iter().enumerate() {
            out[i + j] += x * y;
        }
    }
    out
}

fn poly_add(a: &[f64], b: &[f64]) -> Poly {
    let mut out = vec![0.0; a.len().max(b.len())];
    for (i, &x) in a.iter().enumerate() {
        out[i] += x;
    }
    for (i, &y) in b.iter().enumerate() {
        out[i] += y;
    }
    out
}

fn poly_eval(p: &[f64], z: C64) -> C64 {
    p.iter().rev().fold(C64::new(0.0, 0.0), |acc, &c| {
        acc.times(z).plus(C64::new(c, 0.0))
    })
}

/// The roots of `p` (Durand–Kerner, a bounded number of sweeps); `None` if it did not
/// converge or `p` is degenerate.
pub fn roots(p: &[f64]) -> Option<Vec<C64>> {
    let mut p: Vec<f64> = p.to_vec();
    while p.len() > 1 && p.last().is_some_and(|&c| c.abs() < 1e-300) {
        p.pop();
    }
    let n = p.len().checked_sub(1)?;
    if n == 0 || !p.iter().all(|c| c.is_finite()) {
        return None;
    }
    let lead = p[n];
    let monic: Vec<f64> = p.iter().map(|c| c / lead).collect();
    let radius = 1.0 + monic[..n].iter().fold(0.0f64, |m, c| m.max(c.abs()));
    let mut z: Vec<C64> = (0..n)
        .map(|k| C64::cis(2.0 * PI * k as f64 / n as f64 + 0.4).scale(0.9 * radius.min(4.0)))
        .collect();
    for _ in 0..2000 {
        let mut change = 0.0f64;
        for i in 0..n {
            let mut den = C64::new(1.0, 0.0);
            for j in 0..n {
                if i != j {
                    den = den.times(z[i].minus(z[j]));
                }
            }
            let step = poly_eval(&monic, z[i]).over(den);
            if !(step.re.is_finite() && step.im.is_finite()) {
                return None;
            }
            z[i] = z[i].minus(step);
            change = change.max(step.abs());
        }
        if change < 1e-14 {
            return Some(z);
        }
    }
    // Multiple roots converge slowly; accept what the residual says are roots.
    let ok = z
        .iter()
        .all(|&r| poly_eval(&monic, r).abs() < 1e-8 * (1.0 + r.abs().powi(n as i32)));
    ok.then_some(z)
}

/// A linear plant in normalised units as the tick sees it: `x_{k+1} = Φ x_k + Γ u_k`,
/// reading `y_k = c·x_{k−delay}`.
#[derive(Clone, Debug, PartialEq)]
pub struct LinearPlant {
    /// Control rate, Hz.
    pub rate: f64,
    /// DC gain, normalised sensor per normalised drive.
    pub gain: f64,
    /// Resonance, Hz.
    pub resonance_hz: f64,
    /// Its damping ratio.
    pub zeta: f64,
    /// Ticks between the state after a write and the reading that shows it.
    pub delay: usize,
    phi: [[f64; 2]; 2],
    gamma: [f64; 2],
}

impl LinearPlant {
    /// `gain · ω² / (s² + 2ζω s + ω²)` held by the DAC, read `delay` ticks late, at `rate` Hz.
    ///
    /// ```
    /// use twinstack_identify::tune::loop_model::LinearPlant;
    /// let p = LinearPlant::resonance(0.8, 21_800.0, 0.017, 1, 50_000.0);
    /// assert!((p.response(1.0).abs() - 0.8).abs() < 1e-3);
    /// ```
    pub fn resonance(gain: f64, resonance_hz: f64, zeta: f64, delay: usize, rate: f64) -> Self {
        let w = 2.0 * PI * resonance_hz;
        let a = [[0.0, 1.0], [-w * w, -2.0 * zeta * w]];
        let b = [[0.0], [gain * w * w]];
        let zoh = ZeroOrderHold::new(&a, &b, 1.0 / rate);
        let g = zoh.gamma();
        Self {
            rate,
            gain,
            resonance_hz,
            zeta,
            delay,
            phi: *zoh.phi(),
            gamma: [g[0][0], g[1][0]],
        }
    }

    /// The transfer function `num / den` in `z` (ascending powers).
    pub fn polynomials(&self) -> (Poly, Poly) {
        let [[p11, p12], [p21, p22]] = self.phi;
        let [g1, g2] = self.gamma;
        // det(zI − Φ) and the first row of adj(zI − Φ) times Γ.
        let den = vec![p11 * p22 - p12 * p21, -(p11 + p22), 1.0];
        let num = vec![p12 * g2 - p22 * g1, g1];
        let mut den_d = vec![0.0; self.delay];
        den_d.extend_from_slice(&den);
        (num, den_d)
    }

    /// The response at `frequency_hz`, `P(e^{jωT})`.
    pub fn response(&self, frequency_hz: f64) -> C64 {
        let (num, den) = self.polynomials();
        let z = C64::cis(2.0 * PI * frequency_hz / self.rate);
        poly_eval(&num, z).over(poly_eval(&den, z))
    }

    /// One tick: the reading of this tick from the history, then the state advanced by `u`.
    fn step(&self, s: &mut PlantState, u: f64) -> f64 {
        let reading = s.history.first().copied().unwrap_or(s.x[0]);
        let [[p11, p12], [p21, p22]] = self.phi;
        if self.delay > 0 {
            s.history.remove(0);
            s.history.push(s.x[0]);
        }
        s.x = [
            p11 * s.x[0] + p12 * s.x[1] + self.gamma[0] * u,
            p21 * s.x[0] + p22 * s.x[1] + self.gamma[1] * u,
        ];
        reading
    }
}

#[derive(Clone, Debug)]
struct PlantState {
    x: [f64; 2],
    /// The last `delay` positions, oldest first.
    history: Vec<f64>,
}

/// The feedback as the tick runs it, in `f64` (see the module doc).
#[derive(Clone, Debug, PartialEq)]
pub struct LoopController {
    /// Proportional gain.
    pub kp: f64,
    /// Integral gain per tick.
    pub ki: f64,
    /// Derivative gain per tick (`kd · f_s`).
    pub kd: f64,
    /// The derivative's low-pass coefficient.
    pub smoothing: f64,
    /// Notch numerator `b₀, b₁, b₂` and denominator `1, a₁, a₂` (in `z⁻¹`), or none.
    pub notch: Option<([f64; 3], [f64; 2])>,
}

impl LoopController {
    /// The controller `settings` build at `rate` Hz; `None` if the library refuses them.
    pub fn new(settings: &FeedbackSettings, rate: f64) -> Option<Self> {
        settings.build(rate).ok()?;
        let notch = match &settings.notch {
            Some(d) => {
                let c = d.coefficients(rate).ok()?;
                Some((c.b, c.a))
            }
            None => None,
        };
        Some(Self {
            kp: settings.kp,
            ki: settings.ki / rate,
            kd: settings.kd * rate,
            smoothing: 1.0 - (-2.0 * PI * settings.derivative_cutoff_hz / rate).exp(),
            notch,
        })
    }

    /// `C(z) = num / den`, ascending powers of `z`.
    pub fn polynomials(&self) -> (Poly, Poly) {
        // PI: kp + ki z/(z − 1) = ((kp + ki) z − kp) / (z − 1).
        let mut num = vec![-self.kp, self.kp + self.ki];
        let mut den = vec![-1.0, 1.0];
        if self.kd != 0.0 {
            // D: kd s (z − 1) / (z − (1 − s)).
            let dn = vec![-self.kd * self.smoothing, self.kd * self.smoothing];
            let dd = vec![-(1.0 - self.smoothing), 1.0];
            num = poly_add(&poly_mul(&num, &dd), &poly_mul(&dn, &den));
            den = poly_mul(&den, &dd);
        }
        if let Some((b, a)) = self.notch {
            // In z: (b₀z² + b₁z + b₂) / (z² + a₁z + a₂).
            num = poly_mul(&num, &[b[2], b[1], b[0]]);
            den = poly_mul(&den, &[a[1], a[0], 1.0]);
        }
        (num, den)
    }

    /// The response at `frequency_hz` for a tick at `rate`.
    pub fn response(&self, frequency_hz: f64, rate: f64) -> C64 {
        let (num, den) = self.polynomials();
        let z = C64::cis(2.0 * PI * frequency_hz / rate);
        poly_eval(&num, z).over(poly_eval(&den, z))
    }

    /// One tick on the error `e`: the correction.
    fn step(&self, s: &mut ControllerState, e: f64) -> f64 {
        let e = match self.notch {
            Some((b, a)) => {
                let y = b[0] * e + b[1] * s.x1 + b[2] * s.x2 - a[0] * s.y1 - a[1] * s.y2;
                s.x2 = s.x1;
                s.x1 = e;
                s.y2 = s.y1;
                s.y1 = y;
                y
            }
            None => e,
        };
        s.integrator += self.ki * e;
        let mut c = self.kp * e + s.integrator;
        if self.kd != 0.0 {
            let change = e - s.previous;
            s.derivative += self.smoothing * (change - s.derivative);
            c += self.kd * s.derivative;
        }
        s.previous = e;
        c
    }
}

#[derive(Clone, Copy, Debug, Default)]
struct ControllerState {
    x1: f64,
    x2: f64,
    y1: f64,
    y2: f64,
    integrator: f64,
    previous: f64,
    derivative: f64,
}

/// What a design is judged by.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct LoopFigures {
    /// All closed-loop poles inside the unit circle.
    pub stable: bool,
    /// Largest closed-loop pole magnitude.
    pub spectral_radius: f64,
    /// Phase margin, degrees (smallest over the gain crossovers; 180 with none).
    pub phase_margin_deg: f64,
    /// Frequency of that crossover, Hz.
    pub crossover_hz: f64,
    /// Gain margin, dB (smallest over the phase crossovers below which the loop gain is above
    /// the crossover's; +∞ with none).
    pub gain_margin_db: f64,
    /// Disturbance-rejection bandwidth: the lowest frequency at which `|1/(1 + L)|` rises
    /// through −3 dB, Hz (below it the loop rejects what the model got wrong).
    pub bandwidth_hz: f64,
    /// Closed-loop (tracking) bandwidth: the lowest frequency at which `|L/(1 + L)|` falls
    /// below −3 dB, Hz.
    pub closed_loop_bandwidth_hz: f64,
    /// Largest `|1/(1 + L)|`, dB (the modulus margin's inverse).
    pub sensitivity_peak_db: f64,
    /// Step of the setpoint through feedforward + feedback on this plant: the largest
    /// `|x − final|` from 1 to 3 ms after it, % of the step.
    pub ringing_pct: f64,
    /// The same step's overshoot, % of the step.
    pub overshoot_pct: f64,
}

/// The loop's frequency response `L = C P` over a grid of `points` frequencies from
/// `lowest_hz` to just below Nyquist, logarithmic.
pub fn loop_response(
    plant: &LinearPlant,
    controller: &LoopController,
    lowest_hz: f64,
    points: usize,
) -> Vec<(f64, C64)> {
    let (pn, pd) = plant.polynomials();
    let (cn, cd) = controller.polynomials();
    let num = poly_mul(&pn, &cn);
    let den = poly_mul(&pd, &cd);
    let top = 0.4999 * plant.rate;
    (0..points)
        .map(|i| {
            let f = lowest_hz * (top / lowest_hz).powf(i as f64 / (points - 1).max(1) as f64);
            let z = C64::cis(2.0 * PI * f / plant.rate);
            (f, poly_eval(&num, z).over(poly_eval(&den, z)))
        })
        .collect()
}

/// The closed-loop characteristic polynomial `den_P den_C + num_P num_C`.
pub fn characteristic(plant: &LinearPlant, controller: &LoopController) -> Poly {
    let (pn, pd) = plant.polynomials();
    let (cn, cd) = controller.polynomials();
    poly_add(&poly_mul(&pd, &cd), &poly_mul(&pn, &cn))
}

/// Judges `controller` on `plant` (see [`LoopFigures`]).
///
/// ```
/// use twinstack_identify::tune::loop_model::{judge, LinearPlant, LoopController, StepTest};
/// use twinstack::control::feedback::FeedbackSettings;
/// let plant = LinearPlant::resonance(0.8, 21_800.0, 0.017, 1, 50_000.0);
/// let c = LoopController::new(&FeedbackSettings::pi(0.0, 1000.0, 0.25), 50_000.0).unwrap();
/// let step = StepTest::study(0.9e6, 70.0, 50_000.0);
/// let f = judge(&plant, &c, &step);
/// assert!(f.stable && f.gain_margin_db > 6.0 && f.phase_margin_deg > 45.0);
/// ```
pub fn judge(plant: &LinearPlant, controller: &LoopController, step: &StepTest) -> LoopFigures {
    judge_with(plant, controller, step, 3000)
}

/// [`judge`] on a grid of `points` frequencies (the search judges on a coarser one).
pub fn judge_with(
    plant: &LinearPlant,
    controller: &LoopController,
    step: &StepTest,
    points: usize,
) -> LoopFigures {
    let spectral_radius = roots(&characteristic(plant, controller))
        .map(|r| r.iter().fold(0.0f64, |m, z| m.max(z.abs())))
        .unwrap_or(f64::INFINITY);
    let stable = spectral_radius < 1.0 - 1e-9;
    let l = loop_response(plant, controller, 1.0, points);
    // Phase unwrapped from the lowest frequency (where the integrator gives about −90°).
    let mut phase = Vec::with_capacity(l.len());
    let mut previous = l[0].1.arg();
    let mut offset = 0.0;
    for &(_, v) in &l {
        let a = v.arg();
        let mut d = a - previous;
        while d > PI {
            d -= 2.0 * PI;
            offset -= 2.0 * PI;
        }
        while d < -PI {
            d += 2.0 * PI;
            offset += 2.0 * PI;
        }
        previous = a;
        phase.push(a + offset);
    }
    let (mut pm, mut crossover_hz) = (180.0f64, 0.0);
    let mut gm = f64::INFINITY;
    for i in 1..l.len() {
        let (m0, m1) = (l[i - 1].1.abs(), l[i].1.abs());
        if (m0 - 1.0) * (m1 - 1.0) <= 0.0 && m0 != m1 {
            let t = (1.0 - m0) / (m1 - m0);
            let ph = phase[i - 1] + t * (phase[i] - phase[i - 1]);
            // Distance of the phase from −180° (mod 360°).
            let margin = (ph.to_degrees() + 180.0).rem_euclid(360.0);
            let margin = if margin > 180.0 {
                margin - 360.0
            } else {
                margin
            };
            // The angular distance to the critical point, whichever side.
            if margin.abs() < pm {
                pm = margin.abs();
                crossover_hz = l[i - 1].0 + t * (l[i].0 - l[i - 1].0);
            }
        }
        // Phase crossovers: the unwrapped phase crosses −180° + k·360°.
        let (a0, a1) = (
            (phase[i - 1].to_degrees() + 180.0) / 360.0,
            (phase[i].to_degrees() + 180.0) / 360.0,
        );
        if a0.floor() != a1.floor() {
            let k = a0.floor().max(a1.floor());
            let t = ((k - a0) / (a1 - a0)).clamp(0.0, 1.0);
            let m = m0 + t * (m1 - m0);
            gm = gm.min(-20.0 * m.log10());
        }
    }
    // Bandwidth: where |S| = |1/(1 + L)| first rises through −3 dB (disturbances below it are
    // rejected); the sensitivity peak over the whole grid.
    let one = C64::new(1.0, 0.0);
    let mut bandwidth_hz = l.last().map_or(0.0, |v| v.0);
    let mut s_peak = 0.0f64;
    let mut closed_loop_bandwidth_hz = bandwidth_hz;
    let (mut found, mut found_t) = (false, false);
    for &(f, v) in &l {
        let s = one.over(one.plus(v)).abs();
        s_peak = s_peak.max(s);
        if !found && s > std::f64::consts::FRAC_1_SQRT_2 {
            bandwidth_hz = f;
            found = true;
        }
        if !found_t && v.over(one.plus(v)).abs() < std::f64::consts::FRAC_1_SQRT_2 {
            closed_loop_bandwidth_hz = f;
            found_t = true;
        }
    }
    let (ringing_pct, overshoot_pct) = if stable {
        step_figures(plant, controller, step)
    } else {
        (f64::INFINITY, f64::INFINITY)
    };
    LoopFigures {
        stable,
        spectral_radius,
        phase_margin_deg: if stable { pm } else { pm.min(0.0) },
        crossover_hz,
        gain_margin_db: if stable { gm } else { gm.min(0.0) },
        bandwidth_hz,
        closed_loop_bandwidth_hz,
        sensitivity_peak_db: 20.0 * s_peak.log10(),
        ringing_pct,
        overshoot_pct,
    }
}

/// The setpoint step a design's ringing is judged on: its size and the drive's slew limit.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct StepTest {
    /// Step of the setpoint, normalised output (0.8: 30 → 70 % of the stroke).
    pub size: f64,
    /// The drive's slew limit, normalised drive per tick.
    pub slew_per_tick: f64,
}

impl StepTest {
    /// The closed-loop study's step (30 → 70 % of the stroke) under a slew limit of
    /// `slew_volts_per_second` on a drive of `input_half_span_volts` per normalised unit, at
    /// `rate` Hz.
    pub fn study(slew_volts_per_second: f64, input_half_span_volts: f64, rate: f64) -> Self {
        Self {
            size: 0.8,
            slew_per_tick: slew_volts_per_second / input_half_span_volts / rate,
        }
    }
}

/// A setpoint step on the linear loop: the feedforward steps the drive by `size / gain` (its
/// inverse model at DC) under the slew limit, the feedback corrects against the reference of
/// the reading's instant (between those of [`SENSOR_DELAY_TICKS`] and one fewer ago). Returns the stage's ringing 1–3 ms after the step and its
/// overshoot, % of the step.
pub fn step_figures(
    plant: &LinearPlant,
    controller: &LoopController,
    step: &StepTest,
) -> (f64, f64) {
    let trace = step_trace(plant, controller, step, 0.004);
    let rate = plant.rate;
    let last = (0.0035 * rate) as usize..trace.len();
    let final_x = trace[last.clone()].iter().sum::<f64>() / last.len().max(1) as f64;
    let window = (0.001 * rate) as usize..((0.003 * rate) as usize).min(trace.len());
    let ringing = trace[window]
        .iter()
        .fold(0.0f64, |m, &v| m.max((v - final_x).abs()));
    let peak = trace.iter().fold(f64::NEG_INFINITY, |m, &v| m.max(v));
    let size = step.size.abs().max(f64::MIN_POSITIVE);
    (100.0 * ringing / size, 100.0 * (peak - final_x) / size)
}

/// The stage's position (normalised) after the setpoint step `step` for `seconds`, one value
/// a tick.
pub fn step_trace(
    plant: &LinearPlant,
    controller: &LoopController,
    step: &StepTest,
    seconds: f64,
) -> Vec<f64> {
    let ticks = (seconds * plant.rate) as usize;
    let mut ps = PlantState {
        x: [0.0; 2],
        history: vec![0.0; plant.delay],
    };
    let mut cs = ControllerState::default();
    let mut refs = [0.0f64; SENSOR_DELAY_TICKS + 2];
    let target_drive = step.size / plant.gain;
    let max_step = step.slew_per_tick.max(1e-9);
    let mut drive = 0.0f64;
    let mut out = Vec::with_capacity(ticks);
    for _ in 0..ticks {
        let reading = plant.step_reading(&ps);
        // The reference of the reading's instant, as the tick's feedback takes it
        // (`twinstack::control::instant`): this tick's into the history, then the value
        // between the holds' middles around the reading.
        refs.copy_within(0..SENSOR_DELAY_TICKS + 1, 1);
        refs[0] = step.size;
        let reference = at_reading(&refs);
        let c = controller.step(&mut cs, reference - reading);
        let command = target_drive + c;
        drive += (command - drive).clamp(-max_step, max_step);
        plant.step(&mut ps, drive);
        out.push(ps.x[0]);
    }
    out
}

impl LinearPlant {
    fn step_reading(&self, s: &PlantState) -> f64 {
        s.history.first().copied().unwrap_or(s.x[0])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn roots_of_a_known_polynomial() {
        // (z − 0.5)(z + 0.25)(z² + 1) = z⁴ − 0.25 z³ + 0.875 z² − 0.25 z − 0.125.
        let r = roots(&[-0.125, -0.25, 0.875, -0.25, 1.0]).unwrap();
        let mut m: Vec<f64> = r.iter().map(|z| z.abs()).collect();
        m.sort_by(f64::total_cmp);
        assert!((m[0] - 0.25).abs() < 1e-9 && (m[1] - 0.5).abs() < 1e-9);
        assert!((m[2] - 1.0).abs() < 1e-9 && (m[3] - 1.0).abs() < 1e-9);
    }

    #[test]
    fn the_polynomial_form_matches_the_simulated_plant() {
        // The impulse response of the difference equation against the recursion.
        let p = LinearPlant::resonance(0.8, 21_800.0, 0.017, 1, 50_000.0);
        let f = 3_000.0;
        let w = 2.0 * PI * f / p.rate;
        // Drive a sine long enough to settle; fit the reading's amplitude and phase.
        let mut s = PlantState {
            x: [0.0; 2],
            history: vec![0.0; 1],
        };
        let n = 40_000;
        let (mut c, mut q) = (C64::new(0.0, 0.0), 0usize);
        for k in 0..n {
            let y = p.step(&mut s, (w * k as f64).cos());
            if k >= n / 2 {
                c = c.plus(C64::cis(-w * k as f64).scale(y));
                q += 1;
            }
        }
        let measured = c.scale(2.0 / q as f64);
        let model = p.response(f);
        assert!(
            measured.minus(model).abs() < 1e-3 * model.abs(),
            "{measured:?} vs {model:?}"
        );
    }
}
