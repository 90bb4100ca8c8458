//! The coarse stage: a stepper motor turning a ball screw whose nut pushes the carriage that
//! carries the piezo stage.
//!
//! ```text
//!   J θ̈ = T_m − b_m θ̇ − (L/2π) F_n               motor + screw (inertia J, viscous b_m)
//!   T_m = −T_h sin(N_p (θ − θ_cmd))                hybrid stepper, ideal microstepping
//!   M ẍ = F_n − b_c ẋ − F_c sgn(ẋ)                carriage (mass M, viscous b_c, Coulomb F_c)
//!   F_n = k (g ∓ δ/2) + c ġ   for |g| > δ/2, else 0,   g = (L/2π) θ − x      (nut, backlash δ)
//! ```
//!
//! `θ_cmd` is the microstep position the driver has received (`2π / (full steps · microsteps)`
//! per pulse); `N_p = full steps / 4` (a 200-step motor has 50 rotor teeth). The Coulomb
//! friction sticks (Karnopp): a carriage at rest stays at rest while the nut's force is below
//! `F_c`, and a moving one stops where its velocity would change sign. The motor encoder is
//! quantised to `4 × lines` counts per revolution of `θ`.
//!
//! Integration: semi-implicit Euler in substeps of at most 5 µs (the stiffest mode, the nut
//! contact against the carriage, is about 1.1 kHz: `ω h ≈ 0.04`). The piezo stage rides on the
//! carriage; the force its 2.7 g exert back on a 1 kg carriage, and the carriage's acceleration
//! seen by the 21.8 kHz piezo mode (≤ 1e-11 m at 0.4 m/s²), are neglected.

use std::f64::consts::PI;

/// Constants of the ball-screw stage (SI units).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BallScrewParams {
    /// Screw lead, m per revolution.
    pub lead_m: f64,
    /// Full steps per motor revolution.
    pub full_steps: u32,
    /// Microsteps per full step.
    pub microsteps: u32,
    /// Holding torque, N·m.
    pub holding_torque_nm: f64,
    /// Rotor + screw + coupling inertia, kg·m².
    pub inertia_kg_m2: f64,
    /// Viscous damping of the motor and screw bearings, N·m·s/rad.
    pub motor_damping: f64,
    /// Carriage mass (with the piezo stage), kg.
    pub carriage_mass_kg: f64,
    /// Viscous friction of the carriage's guides, N·s/m.
    pub carriage_damping: f64,
    /// Coulomb friction of the carriage's guides, N.
    pub coulomb_friction_n: f64,
    /// Backlash (total play of the nut), m.
    pub backlash_m: f64,
    /// Axial stiffness of the nut in contact, N/m.
    pub nut_stiffness: f64,
    /// Damping ratio of the nut contact against the carriage.
    pub nut_damping_ratio: f64,
    /// Motor encoder lines per revolution (4 × lines counts).
    pub encoder_lines: u32,
}

impl BallScrewParams {
    /// A precision ball-screw stage: 1 mm lead, 200-step motor at 16 microsteps (0.3125 µm per
    /// microstep), 0.4 N·m holding torque, J = 7e-6 kg·m², 1 kg carriage, 4 N Coulomb and
    /// 20 N·s/m viscous friction, 2 µm backlash, 50 N/µm nut stiffness, 1000-line encoder.
    pub fn precision_stage() -> Self {
        Self {
            lead_m: 1e-3,
            full_steps: 200,
            microsteps: 16,
            holding_torque_nm: 0.4,
            inertia_kg_m2: 7e-6,
            motor_damping: 3e-3,
            carriage_mass_kg: 1.0,
            carriage_damping: 20.0,
            coulomb_friction_n: 4.0,
            backlash_m: 2e-6,
            nut_stiffness: 5e7,
            nut_damping_ratio: 0.1,
            encoder_lines: 1000,
        }
    }

    /// Carriage travel per microstep, µm.
    pub fn step_um(&self) -> f64 {
        self.lead_m * 1e6 / (self.full_steps as f64 * self.microsteps as f64)
    }

    /// Carriage travel per motor-encoder count, µm.
    pub fn encoder_count_um(&self) -> f64 {
        self.lead_m * 1e6 / (4.0 * self.encoder_lines as f64)
    }
}

/// Why ball-screw constants were refused.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum BallScrewError {
    /// A constant that must be finite and positive is not (its name).
    NotPositive(&'static str),
    /// A constant that must be finite and non-negative is not (its name).
    Negative(&'static str),
    /// Full steps not a positive multiple of 4, or no microsteps or encoder lines.
    Counts,
    /// The time step is not finite and positive.
    TimeStep(f64),
}

impl core::fmt::Display for BallScrewError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::NotPositive(n) => write!(f, "ball screw: `{n}` must be finite and positive"),
            Self::Negative(n) => write!(f, "ball screw: `{n}` must be finite and ≥ 0"),
            Self::Counts => write!(
                f,
                "ball screw: full steps must be a positive multiple of 4, microsteps and encoder lines ≥ 1"
            ),
            Self::TimeStep(dt) => write!(f, "ball screw: time step {dt} s must be finite and positive"),
        }
    }
}

impl std::error::Error for BallScrewError {}

/// The ball-screw stage's state.
#[derive(Clone, Debug, PartialEq)]
pub struct BallScrew {
    p: BallScrewParams,
    dt: f64,
    substeps: u32,
    /// Motor angle, rad; velocity, rad/s.
    theta: f64,
    omega: f64,
    /// Carriage position, m; velocity, m/s.
    x: f64,
    v: f64,
    /// Nut contact damping, N·s/m.
    nut_damping: f64,
    /// Commanded microstep position.
    microsteps: i64,
}

impl BallScrew {
    /// At rest with the motor on microstep 0, the nut centred in its play and the carriage at 0.
    /// `dt` is the period of [`BallScrew::step`].
    pub fn new(p: &BallScrewParams, dt: f64) -> Result<Self, BallScrewError> {
        use BallScrewError as E;
        let positive = [
            ("lead_m", p.lead_m),
            ("holding_torque_nm", p.holding_torque_nm),
            ("inertia_kg_m2", p.inertia_kg_m2),
            ("carriage_mass_kg", p.carriage_mass_kg),
            ("nut_stiffness", p.nut_stiffness),
        ];
        for (name, x) in positive {
            if !(x.is_finite() && x > 0.0) {
                return Err(E::NotPositive(name));
            }
        }
        let non_negative = [
            ("motor_damping", p.motor_damping),
            ("carriage_damping", p.carriage_damping),
            ("coulomb_friction_n", p.coulomb_friction_n),
            ("backlash_m", p.backlash_m),
            ("nut_damping_ratio", p.nut_damping_ratio),
        ];
        for (name, x) in non_negative {
            if !(x.is_finite() && x >= 0.0) {
                return Err(E::Negative(name));
            }
        }
        if p.full_steps == 0
            || !p.full_steps.is_multiple_of(4)
            || p.microsteps == 0
            || p.encoder_lines == 0
        {
            return Err(E::Counts);
        }
        if !(dt.is_finite() && dt > 0.0) {
            return Err(E::TimeStep(dt));
        }
        let substeps = (dt / 5e-6).ceil().clamp(1.0, 1e6) as u32;
        Ok(Self {
            p: *p,
            dt,
            substeps,
            theta: 0.0,
            omega: 0.0,
            x: 0.0,
            v: 0.0,
            nut_damping: 2.0 * p.nut_damping_ratio * (p.nut_stiffness * p.carriage_mass_kg).sqrt(),
            microsteps: 0,
        })
    }

    /// The constants.
    pub fn params(&self) -> &BallScrewParams {
        &self.p
    }

    /// Advances one period `dt` with the driver at microstep position `microsteps`; returns the
    /// carriage position, µm.
    pub fn step(&mut self, microsteps: i64) -> f64 {
        self.microsteps = microsteps;
        let p = &self.p;
        let h = self.dt / self.substeps as f64;
        let per_step = 2.0 * PI / (p.full_steps as f64 * p.microsteps as f64);
        let theta_cmd = microsteps as f64 * per_step;
        let teeth = p.full_steps as f64 / 4.0;
        let r = p.lead_m / (2.0 * PI);
        let half_play = p.backlash_m / 2.0;
        for _ in 0..self.substeps {
            // Nut force on the carriage (positive pushes it forward).
            let gap = r * self.theta - self.x;
            let gap_rate = r * self.omega - self.v;
            let f_nut = if gap > half_play {
                (p.nut_stiffness * (gap - half_play) + self.nut_damping * gap_rate).max(0.0)
            } else if gap < -half_play {
                (p.nut_stiffness * (gap + half_play) + self.nut_damping * gap_rate).min(0.0)
            } else {
                0.0
            };
            // Motor.
            let torque = -p.holding_torque_nm * (teeth * (self.theta - theta_cmd)).sin();
            let alpha = (torque - p.motor_damping * self.omega - r * f_nut) / p.inertia_kg_m2;
            self.omega += h * alpha;
            self.theta += h * self.omega;
            // Carriage, with sticking Coulomb friction.
            let f = f_nut - p.carriage_damping * self.v;
            let fc = p.coulomb_friction_n;
            if self.v == 0.0 && f.abs() <= fc {
                // Stuck.
            } else {
                let direction = if self.v != 0.0 {
                    self.v.signum()
                } else {
                    f.signum()
                };
                let v_new = self.v + h * (f - fc * direction) / p.carriage_mass_kg;
                self.v = if self.v != 0.0 && v_new.signum() != self.v.signum() {
                    0.0
                } else {
                    v_new
                };
            }
            self.x += h * self.v;
        }
        self.carriage_um()
    }

    /// Carriage position, µm.
    pub fn carriage_um(&self) -> f64 {
        self.x * 1e6
    }

    /// Carriage velocity, µm/s.
    pub fn carriage_um_per_s(&self) -> f64 {
        self.v * 1e6
    }

    /// Nut position (`L θ / 2π`), µm: where the carriage would be without play.
    pub fn nut_um(&self) -> f64 {
        self.p.lead_m / (2.0 * PI) * self.theta * 1e6
    }

    /// Motor encoder position, counts (`⌊θ / 2π · 4 · lines⌋`).
    pub fn encoder_counts(&self) -> i64 {
        (self.theta / (2.0 * PI) * 4.0 * self.p.encoder_lines as f64).floor() as i64
    }

    /// The microstep position last commanded.
    pub fn commanded_microsteps(&self) -> i64 {
        self.microsteps
    }
}
