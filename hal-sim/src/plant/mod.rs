//! The plant: a dual-stack piezo stage (see the book, docs/src/reference/physics.md) with "truth" hysteresis per stack.
//!
//! * [`stage`] — the paper's figures and the physical constants derived from them.
//! * [`coupled`] — the 3-DOF coupled model (stack tips, stage, contact `K_0`).
//! * [`reduced`] — its `K_0 → ∞` 1-DOF reduction.
//! * [`hysteresis`] — Duhem or P–I hysteresis per stack, with a skew option.
//! * [`twinstack_identify::zero_order_hold`] — the exact discretisation both mechanical models are advanced with.
//! * [`lab_stage`] — a single-input laboratory stage built *outside* the project's model family
//!   (asymmetric Preisach hysteresis, logarithmic creep, flexure nonlinearity, resonance,
//!   sensor noise): the plant the tracking harness (`twinstack lab-stage`) evaluates models
//!   on.
//! * [`ball_screw`] — the coarse stage of a dual-actuated axis (stepper, screw, backlash,
//!   friction, encoder) that carries the piezo stage.
//!
//! [`Plant`] puts them together: each control period it takes the two amplifier output
//! voltages, passes each through its stack's hysteresis (`e = u − v^h`), holds the effective
//! voltages for one period `dt` through the exact zero-order hold of the linear part, and
//! returns the stage displacement in µm.

pub mod ball_screw;
pub mod coupled;
pub mod hysteresis;
pub mod lab_stage;
pub mod reduced;
pub mod stage;

pub use coupled::{CoupledModel, DEFAULT_CONTACT_STIFFNESS};
pub use hysteresis::{HysteresisConfig, HysteresisError, HysteresisModel, StackHysteresis};
pub use lab_stage::{
    BoucWenClass, LabStage, LabStageConfig, LabStageError, PreisachDensity, SetFieldError,
    StageHysteresis, SETTABLE_FIELDS,
};
pub use reduced::ReducedModel;
pub use stage::{Configuration, SecondOrder, StageParams};

use twinstack::Scaling;

/// The default control period: 50 kHz.
pub const DEFAULT_DT: f64 = 1.0 / 50_000.0;
/// Drive range of the amplifier and of the stacks, volts.
pub const DRIVE_RANGE_VOLTS: (f64, f64) = (0.0, 150.0);

/// Which mechanical model the plant integrates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Mechanics {
    /// The coupled 3-DOF model with contact stiffness `K_0` (N/m).
    Coupled {
        /// `K_0`, N/m; must exceed the stack stiffness `K_I`.
        contact_stiffness: f64,
    },
    /// The `K_0 → ∞` reduction.
    Reduced,
}

/// Which stack a setting or an error is about.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Stack {
    /// The left (pushing) stack.
    Left,
    /// The right (pulling) stack.
    Right,
}

/// Everything that defines a plant.
#[derive(Clone, Debug, PartialEq)]
pub struct PlantConfig {
    /// Unidirectional or differential.
    pub configuration: Configuration,
    /// Coupled or reduced mechanics.
    pub mechanics: Mechanics,
    /// Stage and stack constants.
    pub stage: StageParams,
    /// Hysteresis of the left stack.
    pub left: HysteresisConfig,
    /// Hysteresis of the right stack (unused in the unidirectional configuration).
    pub right: HysteresisConfig,
    /// Control period, seconds.
    pub dt: f64,
}

impl PlantConfig {
    /// The paper's stage in `configuration`: coupled mechanics with the default contact, default
    /// (skewed Duhem) hysteresis on both stacks, 50 kHz.
    pub fn paper(configuration: Configuration) -> Self {
        Self {
            configuration,
            mechanics: Mechanics::Coupled {
                contact_stiffness: DEFAULT_CONTACT_STIFFNESS,
            },
            stage: StageParams::paper(),
            left: HysteresisConfig::default(),
            right: HysteresisConfig::default(),
            dt: DEFAULT_DT,
        }
    }

    /// The same plant without hysteresis (the linear stage alone).
    pub fn without_hysteresis(mut self) -> Self {
        let linear = HysteresisConfig {
            model: HysteresisModel::None,
            skew: 0.0,
        };
        self.left = linear.clone();
        self.right = linear;
        self
    }
}

/// Why a plant configuration was refused.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PlantError {
    /// A stage constant is not finite and positive (its field name).
    InvalidStage(&'static str),
    /// `K_0` does not exceed `K_I` (or is not finite): the coupled constants have no solution.
    ContactTooSoft {
        /// The contact stiffness given, N/m.
        contact_stiffness: f64,
        /// The stack stiffness it must exceed, N/m.
        stack_stiffness: f64,
    },
    /// The control period is not finite and positive.
    InvalidTimeStep(f64),
    /// A stack's hysteresis configuration is invalid.
    Hysteresis {
        /// Which stack.
        stack: Stack,
        /// What is wrong with it.
        error: HysteresisError,
    },
}

impl core::fmt::Display for PlantError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::InvalidStage(field) => write!(f, "stage constant `{field}` must be finite and positive"),
            Self::ContactTooSoft {
                contact_stiffness,
                stack_stiffness,
            } => write!(
                f,
                "contact stiffness K_0 = {contact_stiffness} N/m must exceed the stack stiffness {stack_stiffness} N/m"
            ),
            Self::InvalidTimeStep(dt) => write!(f, "control period {dt} s must be finite and positive"),
            Self::Hysteresis { stack, error } => write!(f, "{stack:?} stack hysteresis: {error:?}"),
        }
    }
}

impl std::error::Error for PlantError {}

// Inline on purpose: stepped every period, no heap and no indirection.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq)]
enum Dynamics {
    Coupled(CoupledModel),
    Reduced(ReducedModel),
}

/// The simulated stage with its stacks, advanced one control period per [`Plant::step`].
#[derive(Clone, Debug, PartialEq)]
pub struct Plant {
    configuration: Configuration,
    dynamics: Dynamics,
    hysteresis: [StackHysteresis; 2],
    capacitance: f64,
    dt: f64,
    /// Last drive `[u_l, u_r]`, volts.
    drive: [f64; 2],
    /// Last effective voltages `[e_l, e_r]`, volts.
    effective: [f64; 2],
}

impl Plant {
    /// A plant from `config`, at rest with both stacks at 0 V.
    pub fn new(config: &PlantConfig) -> Result<Self, PlantError> {
        config.stage.validate().map_err(PlantError::InvalidStage)?;
        if !(config.dt.is_finite() && config.dt > 0.0) {
            return Err(PlantError::InvalidTimeStep(config.dt));
        }
        // Volts in, volts out, over the amplifier's range.
        let range = Scaling {
            input_min: DRIVE_RANGE_VOLTS.0,
            input_max: DRIVE_RANGE_VOLTS.1,
            output_min: DRIVE_RANGE_VOLTS.0,
            output_max: DRIVE_RANGE_VOLTS.1,
        };
        let stack = |which: Stack, cfg: &HysteresisConfig| {
            StackHysteresis::new(cfg, &range, 0.0).map_err(|error| PlantError::Hysteresis {
                stack: which,
                error,
            })
        };
        let hysteresis = [
            stack(Stack::Left, &config.left)?,
            stack(Stack::Right, &config.right)?,
        ];
        let dynamics = match config.mechanics {
            Mechanics::Coupled { contact_stiffness } => {
                let stack_stiffness = config.stage.stack_stiffness;
                if !(contact_stiffness.is_finite() && contact_stiffness > stack_stiffness) {
                    return Err(PlantError::ContactTooSoft {
                        contact_stiffness,
                        stack_stiffness,
                    });
                }
                Dynamics::Coupled(CoupledModel::new(
                    &config.stage,
                    contact_stiffness,
                    config.configuration,
                    config.dt,
                ))
            }
            Mechanics::Reduced => Dynamics::Reduced(ReducedModel::new(
                &config.stage,
                config.configuration,
                config.dt,
            )),
        };
        Ok(Self {
            configuration: config.configuration,
            dynamics,
            hysteresis,
            capacitance: config.stage.capacitance,
            dt: config.dt,
            drive: [0.0; 2],
            effective: [0.0; 2],
        })
    }

    /// One control period: the stacks are driven with `u_left`, `u_right` (volts, held for the
    /// period; `u_right` is ignored in the unidirectional configuration). Returns the stage
    /// displacement at the end of the period, µm.
    #[inline]
    pub fn step(&mut self, u_left_volts: f64, u_right_volts: f64) -> f64 {
        let u_right_volts = match self.configuration {
            Configuration::Unidirectional => 0.0,
            Configuration::Differential => u_right_volts,
        };
        self.drive = [u_left_volts, u_right_volts];
        self.effective = [
            self.hysteresis[0].effective_volts(u_left_volts),
            self.hysteresis[1].effective_volts(u_right_volts),
        ];
        match &mut self.dynamics {
            Dynamics::Coupled(m) => m.step(self.effective),
            Dynamics::Reduced(m) => m.step(self.effective),
        }
        self.stage_um()
    }

    /// Stage displacement `x_s`, µm.
    pub fn stage_um(&self) -> f64 {
        match &self.dynamics {
            Dynamics::Coupled(m) => m.stage_m() * 1e6,
            Dynamics::Reduced(m) => m.stage_m() * 1e6,
        }
    }

    /// Stack tips `[x_l, x_r]`, µm (at the stage in the reduced model; the absent right stack
    /// of the unidirectional configuration stays at 0).
    pub fn tips_um(&self) -> [f64; 2] {
        match &self.dynamics {
            Dynamics::Coupled(m) => m.tips_m().map(|x| x * 1e6),
            Dynamics::Reduced(m) => {
                let x = m.stage_m() * 1e6;
                match self.configuration {
                    Configuration::Unidirectional => [x, 0.0],
                    Configuration::Differential => [x, x],
                }
            }
        }
    }

    /// The force factor `T` of the integrated model, N/V (C/m).
    pub fn force_factor(&self) -> f64 {
        match &self.dynamics {
            Dynamics::Coupled(m) => m.force_factor(),
            Dynamics::Reduced(m) => m.force_factor(),
        }
    }

    /// Stack charges `[Q_l, Q_r]`, coulombs: `Q_l = C e_l + T x_l`, `Q_r = C e_r − T x_r`
    /// (0 for the absent right stack of the unidirectional configuration).
    pub fn charges_coulombs(&self) -> [f64; 2] {
        let t = self.force_factor();
        let [xl, xr] = self.tips_um().map(|x| x * 1e-6);
        let ql = self.capacitance * self.effective[0] + t * xl;
        let qr = match self.configuration {
            Configuration::Unidirectional => 0.0,
            Configuration::Differential => self.capacitance * self.effective[1] - t * xr,
        };
        [ql, qr]
    }

    /// Hysteresis voltages `[v_l^h, v_r^h] = u − e`, volts, of the last period.
    pub fn hysteresis_volts(&self) -> [f64; 2] {
        [
            self.drive[0] - self.effective[0],
            self.drive[1] - self.effective[1],
        ]
    }

    /// Effective voltages `[e_l, e_r]`, volts, of the last period.
    pub fn effective_volts(&self) -> [f64; 2] {
        self.effective
    }

    /// The drive `[u_l, u_r]` of the last period, volts.
    pub fn drive_volts(&self) -> [f64; 2] {
        self.drive
    }

    /// The configuration.
    pub fn configuration(&self) -> Configuration {
        self.configuration
    }

    /// The control period, seconds.
    pub fn dt(&self) -> f64 {
        self.dt
    }
}

/// The paper stage's true small-signal plant on the simulated board, as the tick sees it:
/// the `K_0 → ∞` model of `stage` (the coupled model's first mode is within 0.1 % of it), in
/// normalised units for an input half span of `input_half_span_volts` on the left stack and
/// an output half span of `output_half_span_um`, read one tick late, at `rate` Hz. The
/// hysteresis is left out: it only ever lowers the small-signal gain.
pub fn true_plant(
    stage: &StageParams,
    input_half_span_volts: f64,
    output_half_span_um: f64,
    rate: f64,
) -> twinstack_identify::tune::loop_model::LinearPlant {
    let s = stage.second_order(Configuration::Differential);
    twinstack_identify::tune::loop_model::LinearPlant::resonance(
        s.a0_um_per_volt * input_half_span_volts / output_half_span_um,
        s.omega_n / (2.0 * std::f64::consts::PI),
        s.zeta,
        1,
        rate,
    )
}
