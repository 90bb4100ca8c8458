//! [`CoarseSupervisor`]: the coarse axis's state machine around [`DualStage`] — homing, moves,
//! jogs, stops and faults — run once per coarse tick, with no register in sight (the step/dir
//! output, the encoders and the switches come in through the board traits).
//!
//! ```text
//!            home                 reference found, stopped
//!  Unhomed ─────────► Homing ───────────────────────────────► Idle ◄──────────────┐
//!     ▲                 │ timeout, limit before the reference    │ move / jog      │ at rest
//!     │                 ▼                                        ▼                 │
//!     │   home        Fault ◄── following error, limit switch ── Moving / Jogging ─┘
//!     └─────────────── (latched)    in the direction of travel,    │ stop
//!                                    lost encoder                   ▼
//!                                                                Stopping ──► Idle (Unhomed
//!                                                                              if not homed)
//! ```
//!
//! * **Homing** seeks the home reference (a switch, or the encoder's index pulse latched by the
//!   input) at the homing speed, in the configured direction; if the reference is already
//!   active it first backs off until it is not. The linear encoder's reading at the tick the
//!   reference becomes active is the home position (`home_position_um`): the axis brakes to
//!   rest, the travel limits are set in its coordinates, and the piezo is handed in (dual
//!   mode, over the hand-over ramp). Not found within the timeout, or a limit switch in the
//!   seek direction reached first: a fault (`HOMING_TIMEOUT`, `HOMING_LIMIT`).
//! * **Moves** (to a position, with their own speed and acceleration, validated against the
//!   travel and the coarse stage's limits: [`CoarseLimits::check_move`]) and **jogs** (toward
//!   the soft travel limit at a speed, until stopped) need a homed axis. **Stop** is a
//!   controlled stop: the move brakes at its acceleration (no step lost).
//! * **Faults** stop the coarse axis *at once*: the coarse tick no longer runs, so no further
//!   burst is emitted (the one already started, one coarse period of steps, completes). A
//!   stalled motor or a lost encoder means the step count no longer says where the carriage
//!   is, and a limit switch means it is at the end of its travel: braking would only push
//!   further. The fault is latched in [`CoarseStatus::faults`] and the axis is unhomed until
//!   it is homed again. The piezo **holds**: its setpoint stays where the last coarse period
//!   left it ([`FineSetpoints`] with `from == to`), and its own loop keeps it there, so its
//!   DAC does not jump.
//!   * following error: `|coarse command − carriage estimate| > following_limit_um` (a stalled
//!     motor: steps go out, the carriage does not follow);
//!   * limit switch: the switch at the end the axis moves toward becomes active while moving;
//!   * lost encoder: an input reports a missed edge, or the linear encoder has not changed
//!     while steps worth `lost_encoder_um` went out *and* the motor encoder turned by half
//!     that (the motor moves, the scale says nothing; a stall moves neither and is a
//!     following error).
//!
//! Positions on the wire are the user's (`user = controller + offset`, the offset fixed by
//! homing); the [`DualStage`] keeps the coordinates it booted with.

use serde::{Deserialize, Serialize};

use super::controller::{DualMode, DualStage, FineSetpoints};
use super::trapezoid::PreparedLimits;
use super::{DualStageConfig, DualStageError, MotionLimits, PM_PER_UM};
use crate::board::{LimitSwitches, QuadratureEncoder, StepDir, Switches};
use crate::fixed_point::limit_i64;
use crate::refusal::{Field, Refusal, Rule};

/// Travel limits while homing, pm: ±1 m, the widest the settings accept.
const HOMING_TRAVEL_PM: (i64, i64) = (-1_000_000_000_000, 1_000_000_000_000);

/// The coarse axis's state. Wire-stable (it travels in [`CoarseStatus`]): append only.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum CoarseState {
    /// Not homed (power-up, an aborted homing, or after a fault was cleared by a new homing
    /// that was stopped): only `home` is accepted.
    #[default]
    Unhomed,
    /// Seeking the home reference.
    Homing,
    /// Homed, at rest.
    Idle,
    /// A planned move.
    Moving,
    /// A jog (until stopped or at the soft travel limit).
    Jogging,
    /// Braking to rest after a stop.
    Stopping,
    /// Stopped by a fault (latched in [`CoarseStatus::faults`]); `home` clears it.
    Fault,
}

impl CoarseState {
    /// Whether the axis is in motion (homing, a move, a jog or braking): the states in which
    /// the piezo's fine share is part of the motion.
    pub const fn is_moving(self) -> bool {
        matches!(
            self,
            Self::Homing | Self::Moving | Self::Jogging | Self::Stopping
        )
    }

    /// The name the host prints.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Unhomed => "unhomed",
            Self::Homing => "homing",
            Self::Idle => "idle",
            Self::Moving => "moving",
            Self::Jogging => "jogging",
            Self::Stopping => "stopping",
            Self::Fault => "fault",
        }
    }
}

/// The coarse axis's status, as the wire carries it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct CoarseStatus {
    /// The state.
    pub state: CoarseState,
    /// Whether the axis is homed (positions are then relative to the home reference).
    pub homed: bool,
    /// Faults latched since the last homing ([`CoarseStatus::FOLLOWING_ERROR`], …).
    pub faults: u16,
    /// Switches at the last coarse tick ([`CoarseStatus::LOWER_LIMIT`], …).
    pub switches: u8,
    /// Total position (linear encoder), pm.
    pub position_pm: i64,
    /// Total setpoint, pm.
    pub setpoint_pm: i64,
    /// Coarse command − carriage estimate at the last coarse tick, pm.
    pub following_error_pm: i64,
    /// The piezo's setpoint, Q2.30 of its controller's range.
    pub fine_setpoint: i32,
    /// Coarse ticks run.
    pub ticks: u32,
}

impl CoarseStatus {
    /// Fault: the carriage did not follow the command (a stalled motor).
    pub const FOLLOWING_ERROR: u16 = 1 << 0;
    /// Fault: a limit switch became active in the direction of travel.
    pub const LIMIT_SWITCH: u16 = 1 << 1;
    /// Fault: an encoder stopped counting (or reported a missed edge).
    pub const ENCODER_LOST: u16 = 1 << 2;
    /// Fault: homing did not find the reference in time.
    pub const HOMING_TIMEOUT: u16 = 1 << 3;
    /// Fault: homing reached a limit switch before the reference.
    pub const HOMING_LIMIT: u16 = 1 << 4;
    /// Switch: the lower limit is active.
    pub const LOWER_LIMIT: u8 = 1 << 0;
    /// Switch: the upper limit is active.
    pub const UPPER_LIMIT: u8 = 1 << 1;
    /// Switch: the home reference is active.
    pub const HOME: u8 = 1 << 2;

    /// The names of the faults set in `faults`.
    pub fn fault_names(faults: u16) -> impl Iterator<Item = &'static str> {
        [
            (Self::FOLLOWING_ERROR, "following-error"),
            (Self::LIMIT_SWITCH, "limit-switch"),
            (Self::ENCODER_LOST, "encoder-lost"),
            (Self::HOMING_TIMEOUT, "homing-timeout"),
            (Self::HOMING_LIMIT, "homing-limit"),
        ]
        .into_iter()
        .filter(move |&(bit, _)| faults & bit != 0)
        .map(|(_, name)| name)
    }

    /// The names of the switches set in `switches`.
    pub fn switch_names(switches: u8) -> impl Iterator<Item = &'static str> {
        [
            (Self::LOWER_LIMIT, "lower-limit"),
            (Self::UPPER_LIMIT, "upper-limit"),
            (Self::HOME, "home"),
        ]
        .into_iter()
        .filter(move |&(bit, _)| switches & bit != 0)
        .map(|(_, name)| name)
    }
}

fn switch_bits(s: Switches) -> u8 {
    let bit = |on: bool, b: u8| if on { b } else { 0 };
    bit(s.lower, CoarseStatus::LOWER_LIMIT)
        | bit(s.upper, CoarseStatus::UPPER_LIMIT)
        | bit(s.home, CoarseStatus::HOME)
}

/// What the coarse axis is asked to do, validated and in integers.
///
/// Its tag is a word (`repr(u32)`), so that the fields after it start word-aligned: a
/// command moved from the handler to the coarse task is copied a word at a time. With a
/// one-byte tag the move copied the 55 bytes behind it, misaligned, through the library's
/// `memcpy` byte path: several hundred instructions of the task's dearest period, half of
/// them under the control tick's lock.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u32)]
pub enum CoarseCommand {
    /// Home (clears a fault).
    Home,
    /// Move to `target_pm` (user coordinates) with `limits` (pm per coarse tick (²)).
    MoveTo {
        /// Target, pm.
        target_pm: i64,
        /// Speed and acceleration, prepared where the command is checked (the command
        /// handler), not on the coarse task that takes it.
        limits: PreparedLimits,
    },
    /// Jog toward the soft travel limit (`forward`: the upper one) at `limits`.
    Jog {
        /// Toward the upper limit.
        forward: bool,
        /// Speed and acceleration, prepared as a move's.
        limits: PreparedLimits,
    },
    /// Controlled stop.
    Stop,
}

/// Why a coarse command was refused.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CoarseRefusal {
    /// Not now: homing, or braking after a stop.
    Busy,
    /// A field and the rule it broke.
    Refused(Refusal),
}

fn refuse(field: Field, rule: Rule) -> CoarseRefusal {
    CoarseRefusal::Refused(Refusal::new(field, rule))
}

/// What the command handler needs to validate a coarse request: the travel, the coarse
/// stage's limits and its rate. Set once at boot from the built configuration.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CoarseLimits {
    /// Soft travel limits of the homed axis (user coordinates), pm.
    pub travel_pm: (i64, i64),
    /// The coarse stage's speed and acceleration limits, pm per coarse tick (²).
    pub coarse: MotionLimits,
    /// A jog's acceleration (the planned moves' default), pm per coarse tick².
    pub jog_acceleration: i64,
    /// Coarse ticks per second.
    pub coarse_rate_hz: f64,
}

impl CoarseLimits {
    fn speed(&self, field: Field, mm_s: f64, max: i64, per: f64) -> Result<i64, CoarseRefusal> {
        let max_mm_s = max as f64 * per / 1e9;
        if !mm_s.is_finite() {
            return Err(refuse(field, Rule::NotFinite));
        }
        if mm_s <= 0.0 {
            return Err(refuse(field, Rule::Above(0.0)));
        }
        if mm_s > max_mm_s * (1.0 + 1e-9) {
            return Err(refuse(field, Rule::AtMost(max_mm_s)));
        }
        Ok(libm::round(mm_s * 1e9 / per).max(1.0).min(max as f64) as i64)
    }

    fn finite(field: Field, value: f64) -> Result<(), CoarseRefusal> {
        if value.is_finite() {
            Ok(())
        } else {
            Err(refuse(field, Rule::NotFinite))
        }
    }

    fn state_allows_motion(state: CoarseState) -> Result<(), CoarseRefusal> {
        match state {
            CoarseState::Idle | CoarseState::Moving | CoarseState::Jogging => Ok(()),
            CoarseState::Homing | CoarseState::Stopping => Err(CoarseRefusal::Busy),
            CoarseState::Unhomed | CoarseState::Fault => {
                Err(refuse(Field::CoarseAxis, Rule::NotHomed))
            }
        }
    }

    /// A move to `target_mm` at `velocity_mm_s` and `acceleration_mm_s2`: refused when the
    /// axis is not homed (or faulted), busy homing or stopping, the target is outside the
    /// travel, the speed or acceleration is not positive or beyond the coarse stage's, or the
    /// move heads into an active limit switch (`status` is the axis's latest).
    pub fn check_move(
        &self,
        status: &CoarseStatus,
        target_mm: f64,
        velocity_mm_s: f64,
        acceleration_mm_s2: f64,
    ) -> Result<CoarseCommand, CoarseRefusal> {
        // A value that is no number is the request's fault whatever the axis's state: named
        // first, before "not homed" or "busy".
        Self::finite(Field::CoarseTarget, target_mm)?;
        Self::finite(Field::CoarseVelocity, velocity_mm_s)?;
        Self::finite(Field::CoarseAcceleration, acceleration_mm_s2)?;
        Self::state_allows_motion(status.state)?;
        let (lo, hi) = self.travel_pm;
        let (lo_mm, hi_mm) = (lo as f64 / 1e9, hi as f64 / 1e9);
        if target_mm < lo_mm {
            return Err(refuse(Field::CoarseTarget, Rule::AtLeast(lo_mm)));
        }
        if target_mm > hi_mm {
            return Err(refuse(Field::CoarseTarget, Rule::AtMost(hi_mm)));
        }
        let rate = self.coarse_rate_hz;
        let velocity = self.speed(
            Field::CoarseVelocity,
            velocity_mm_s,
            self.coarse.velocity,
            rate,
        )?;
        let acceleration = self.speed(
            Field::CoarseAcceleration,
            acceleration_mm_s2,
            self.coarse.acceleration,
            rate * rate,
        )?;
        let target_pm = libm::round(target_mm * 1e9) as i64;
        let forward = target_pm > status.position_pm;
        Self::toward_free_end(status.switches, forward)?;
        Ok(CoarseCommand::MoveTo {
            target_pm: limit_i64(target_pm, lo, hi),
            limits: MotionLimits {
                velocity,
                acceleration: acceleration.min(velocity),
            }
            .prepare(),
        })
    }

    /// A jog at `velocity_mm_s` (signed: positive toward the upper limit), at the planned
    /// moves' acceleration; refused as [`CoarseLimits::check_move`] refuses.
    pub fn check_jog(
        &self,
        status: &CoarseStatus,
        velocity_mm_s: f64,
    ) -> Result<CoarseCommand, CoarseRefusal> {
        Self::finite(Field::CoarseVelocity, velocity_mm_s)?;
        Self::state_allows_motion(status.state)?;
        let velocity = self.speed(
            Field::CoarseVelocity,
            velocity_mm_s.abs(),
            self.coarse.velocity,
            self.coarse_rate_hz,
        )?;
        let forward = velocity_mm_s > 0.0;
        Self::toward_free_end(status.switches, forward)?;
        Ok(CoarseCommand::Jog {
            forward,
            limits: MotionLimits {
                velocity,
                acceleration: limit_i64(self.jog_acceleration, 1, velocity),
            }
            .prepare(),
        })
    }

    /// Homing: refused while a move, a jog, a homing or a stop is under way.
    pub fn check_home(status: &CoarseStatus) -> Result<CoarseCommand, CoarseRefusal> {
        match status.state {
            CoarseState::Unhomed | CoarseState::Idle | CoarseState::Fault => {
                Ok(CoarseCommand::Home)
            }
            _ => Err(CoarseRefusal::Busy),
        }
    }

    fn toward_free_end(switches: u8, forward: bool) -> Result<(), CoarseRefusal> {
        let blocked = if forward {
            CoarseStatus::UPPER_LIMIT
        } else {
            CoarseStatus::LOWER_LIMIT
        };
        if switches & blocked != 0 {
            return Err(refuse(Field::CoarseTarget, Rule::LimitSwitch));
        }
        Ok(())
    }
}

/// The supervisor in physical units (µm, µm/s, µm/s², s).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SupervisorSettings {
    /// Homing speed, µm/s (at most the coarse stage's).
    pub home_velocity_um_s: f64,
    /// Homing acceleration, µm/s².
    pub home_acceleration_um_s2: f64,
    /// Seek the reference toward the upper end (`false`: toward the lower end).
    pub home_forward: bool,
    /// Total position at the home reference, µm (inside the travel).
    pub home_position_um: f64,
    /// Longest a homing may take, s.
    pub home_timeout_s: f64,
    /// Largest |coarse command − carriage| before a following-error fault, µm.
    pub following_limit_um: f64,
    /// Carriage travel commanded with no linear-encoder count (while the motor encoder turns)
    /// before the encoder counts as lost, µm.
    pub lost_encoder_um: f64,
}

impl SupervisorSettings {
    /// Homing toward the lower end at 5 mm/s (100 mm/s²), the reference 24 mm below the
    /// travel's centre (1 mm inside the paper stage's −25 mm soft limit), 30 s to find it;
    /// following error 12 µm (the carriage's lag behind the command is about 4 µm at 10 mm/s
    /// on the simulated screw, the backlash 2 µm; a fault must be seen before the piezo, which
    /// takes the residual at up to 30 mm/s, has run far into its ±25 µm window); an encoder is
    /// lost after 8 µm of steps without a count.
    pub fn paper_stage() -> Self {
        Self {
            home_velocity_um_s: 5_000.0,
            home_acceleration_um_s2: 100_000.0,
            home_forward: false,
            home_position_um: -24_000.0,
            home_timeout_s: 30.0,
            following_limit_um: 12.0,
            lost_encoder_um: 8.0,
        }
    }

    /// Validates the settings against the dual stage's built configuration (`rate_hz`: its
    /// coarse rate) and turns them into integers.
    pub fn build(
        &self,
        dual: &DualStageConfig,
        rate_hz: f64,
    ) -> Result<SupervisorConfig, DualStageError> {
        let pm = |um: f64| {
            let x = um * PM_PER_UM;
            (x.is_finite() && x.abs() < 1e15).then(|| libm::round(x) as i64)
        };
        if !(rate_hz.is_finite() && rate_hz > 0.0) {
            return Err(DualStageError::Rates);
        }
        let home_limits = MotionLimits {
            velocity: pm(self.home_velocity_um_s / rate_hz).ok_or(DualStageError::Homing)?,
            acceleration: pm(self.home_acceleration_um_s2 / (rate_hz * rate_hz))
                .ok_or(DualStageError::Homing)?,
        };
        if !home_limits.is_valid() || home_limits.velocity > dual.coarse_limits.velocity {
            return Err(DualStageError::Homing);
        }
        let home_position_pm = pm(self.home_position_um).ok_or(DualStageError::Homing)?;
        let (lo, hi) = dual.travel_pm;
        if !(lo..=hi).contains(&home_position_pm) {
            return Err(DualStageError::Homing);
        }
        let timeout = self.home_timeout_s * rate_hz;
        if !(timeout >= 1.0 && timeout <= u32::MAX as f64) {
            return Err(DualStageError::Homing);
        }
        let following_limit_pm = pm(self.following_limit_um)
            .filter(|&p| p > 0)
            .ok_or(DualStageError::FaultLimits)?;
        let lost_encoder_pm = pm(self.lost_encoder_um)
            .filter(|&p| p >= dual.step_pm)
            .ok_or(DualStageError::FaultLimits)?;
        Ok(SupervisorConfig {
            home_limits,
            home_forward: self.home_forward,
            home_position_pm,
            home_timeout_ticks: timeout as u32,
            following_limit_pm,
            lost_encoder_pm,
            limits: CoarseLimits {
                travel_pm: dual.travel_pm,
                coarse: dual.coarse_limits,
                jog_acceleration: dual.move_limits.acceleration,
                coarse_rate_hz: rate_hz,
            },
        })
    }
}

/// The supervisor's settings in integers (see [`SupervisorSettings`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SupervisorConfig {
    /// Homing speed and acceleration, pm per coarse tick (²).
    pub home_limits: MotionLimits,
    /// Seek toward the upper end.
    pub home_forward: bool,
    /// User position at the reference, pm.
    pub home_position_pm: i64,
    /// Coarse ticks a homing may take.
    pub home_timeout_ticks: u32,
    /// Following-error limit, pm.
    pub following_limit_pm: i64,
    /// Steps' travel without a linear count before the encoder is lost, pm.
    pub lost_encoder_pm: i64,
    /// What the command handler validates requests against.
    pub limits: CoarseLimits,
}

/// Where a homing is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum HomePhase {
    /// The reference was active at the start: moving away from it.
    BackOff,
    /// Moving toward it.
    Seek,
    /// Found: braking to rest.
    Brake,
}

/// The coarse axis's state machine around a [`DualStage`] (see the module doc).
#[derive(Clone, Debug)]
pub struct CoarseSupervisor {
    dual: DualStage,
    config: SupervisorConfig,
    /// `config.home_limits`, prepared once: homing's jogs start on the coarse tick.
    home_limits: PreparedLimits,
    state: CoarseState,
    homed: bool,
    faults: u16,
    /// User position − controller position, pm (fixed by homing).
    offset_pm: i64,
    phase: HomePhase,
    home_ticks: u32,
    pending_home: bool,
    switches: Switches,
    position_pm: i64,
    following_pm: i64,
    last_command_pm: i64,
    /// Encoder-loss watch: the total position at the last linear count change, the motor
    /// encoder then, and the steps' travel since, pm.
    last_measured_pm: i64,
    motor_at_change_pm: i64,
    steps_since_change: i64,
    ticks: u32,
}

impl CoarseSupervisor {
    /// Unhomed, at rest, around `dual` (freshly built: [`DualStage::new`]).
    ///
    /// ```
    /// use twinstack::dual_stage::{CoarseState, CoarseSupervisor, DualStage, DualStageSettings, SupervisorSettings};
    /// let settings = DualStageSettings::paper_stage();
    /// let dual = DualStage::new(settings.build().unwrap(), 0, 0, 0);
    /// let config = SupervisorSettings::paper_stage()
    ///     .build(dual.config(), settings.coarse_rate_hz)
    ///     .unwrap();
    /// let axis = CoarseSupervisor::new(dual, config);
    /// assert_eq!(axis.status().state, CoarseState::Unhomed);
    /// ```
    pub fn new(dual: DualStage, config: SupervisorConfig) -> Self {
        let position = dual.setpoint_pm();
        Self {
            dual,
            home_limits: config.home_limits.prepare(),
            config,
            state: CoarseState::Unhomed,
            homed: false,
            faults: 0,
            offset_pm: 0,
            phase: HomePhase::Seek,
            home_ticks: 0,
            pending_home: false,
            switches: Switches::default(),
            position_pm: position,
            following_pm: 0,
            last_command_pm: 0,
            last_measured_pm: position,
            motor_at_change_pm: 0,
            steps_since_change: 0,
            ticks: 0,
        }
    }

    /// The limits requests are validated against.
    pub fn limits(&self) -> CoarseLimits {
        self.config.limits
    }

    /// The dual-stage controller.
    pub fn dual(&self) -> &DualStage {
        &self.dual
    }

    /// The piezo comes back from its own sources with its setpoint at `q` (Q2.30): the fine
    /// ramp continues from there ([`DualStage::resume_fine_from`]). The coarse task calls it
    /// before the tick that takes the command engaging it
    /// ([`crate::dual_stage::CoarseTake::resume_fine`]).
    pub fn resume_fine_from(&mut self, q: i32) {
        self.dual.resume_fine_from(q);
    }

    /// The status (user coordinates).
    pub fn status(&self) -> CoarseStatus {
        CoarseStatus {
            state: self.state,
            homed: self.homed,
            faults: self.faults,
            switches: switch_bits(self.switches),
            position_pm: self.position_pm.saturating_add(self.offset_pm),
            setpoint_pm: self.dual.setpoint_pm().saturating_add(self.offset_pm),
            following_error_pm: self.following_pm,
            fine_setpoint: self.dual.fine_setpoint(),
            ticks: self.ticks,
        }
    }

    /// Takes a command (validated by the handler on a status that may be one period old:
    /// checked again here against the present state).
    pub fn command(&mut self, command: CoarseCommand) -> Result<(), CoarseRefusal> {
        let status = self.status();
        match command {
            CoarseCommand::Home => {
                CoarseLimits::check_home(&status)?;
                self.pending_home = true;
            }
            CoarseCommand::MoveTo { target_pm, limits } => {
                CoarseLimits::state_allows_motion(self.state)?;
                let (lo, hi) = self.config.limits.travel_pm;
                // Not `i64::clamp`, which panics on an empty range: no panic path.
                let target = limit_i64(target_pm, lo, hi);
                self.dual
                    .move_to_prepared(target.saturating_sub(self.offset_pm), limits);
                self.state = CoarseState::Moving;
            }
            CoarseCommand::Jog { forward, limits } => {
                CoarseLimits::state_allows_motion(self.state)?;
                let (lo, hi) = self.config.limits.travel_pm;
                let edge = if forward { hi } else { lo };
                self.dual
                    .move_to_prepared(edge.saturating_sub(self.offset_pm), limits);
                self.state = CoarseState::Jogging;
            }
            CoarseCommand::Stop => match self.state {
                CoarseState::Moving | CoarseState::Jogging | CoarseState::Homing => {
                    self.dual.stop();
                    self.state = CoarseState::Stopping;
                }
                _ => self.pending_home = false,
            },
        }
        Ok(())
    }

    fn fault(&mut self, flags: u16) {
        self.faults |= flags;
        self.state = CoarseState::Fault;
        self.homed = false;
    }

    fn start_homing<M: QuadratureEncoder, L: QuadratureEncoder>(
        &mut self,
        motor: &mut M,
        linear: &mut L,
    ) {
        self.pending_home = false;
        let position = self.dual.read_position(linear);
        self.dual.restart(position, motor.count(), linear.count());
        self.dual.set_travel(HOMING_TRAVEL_PM);
        self.dual.set_mode(DualMode::CoarseOnly);
        self.homed = false;
        self.faults = 0;
        self.offset_pm = 0;
        self.home_ticks = 0;
        self.steps_since_change = 0;
        self.last_measured_pm = position;
        self.last_command_pm = position;
        self.state = CoarseState::Homing;
        let toward = self.config.home_forward;
        self.phase = if self.switches.home {
            HomePhase::BackOff
        } else {
            HomePhase::Seek
        };
        let forward = if self.phase == HomePhase::BackOff {
            !toward
        } else {
            toward
        };
        self.jog_raw(forward, self.home_limits);
    }

    fn jog_raw(&mut self, forward: bool, limits: PreparedLimits) {
        let edge = if forward {
            HOMING_TRAVEL_PM.1
        } else {
            HOMING_TRAVEL_PM.0
        };
        self.dual.move_to_prepared(edge, limits);
    }

    /// One coarse tick: reads the switches, runs the dual stage (unless stopped by a fault),
    /// watches for faults, advances homing and the state; returns the piezo's setpoints for
    /// the coming period (held where they are once a fault stopped the axis). No allocation,
    /// no panic path, no loop.
    pub fn tick<S: StepDir, M: QuadratureEncoder, L: QuadratureEncoder, W: LimitSwitches>(
        &mut self,
        step_dir: &mut S,
        motor: &mut M,
        linear: &mut L,
        switches: &mut W,
        fine_measured: Option<i32>,
    ) -> FineSetpoints {
        self.ticks = self.ticks.wrapping_add(1);
        self.switches = switches.read();
        let fine_ticks = self.dual.config().fine_ticks;
        if self.pending_home {
            self.start_homing(motor, linear);
        }
        if self.state == CoarseState::Fault {
            // Stopped: no coarse tick, no burst; the piezo holds its last setpoint.
            self.position_pm = self.dual.read_position(linear);
            let q = self.dual.fine_setpoint();
            return FineSetpoints {
                from: q,
                to: q,
                ticks: fine_ticks,
            };
        }
        let missed = motor.missed_edges() | linear.missed_edges();
        let report = self
            .dual
            .coarse_tick(step_dir, motor, linear, fine_measured);
        self.position_pm = report.measured_pm;
        self.following_pm = report.coarse_command_pm.saturating_sub(report.carriage_pm);
        let velocity = report
            .coarse_command_pm
            .saturating_sub(self.last_command_pm);
        self.last_command_pm = report.coarse_command_pm;

        // Lost encoder: a missed edge, or steps out and the motor turning while the scale
        // reports nothing.
        if report.measured_pm != self.last_measured_pm {
            self.last_measured_pm = report.measured_pm;
            self.motor_at_change_pm = report.motor_pm;
            self.steps_since_change = 0;
        } else {
            self.steps_since_change = self.steps_since_change.saturating_add(
                (report.steps.unsigned_abs() as i64).saturating_mul(self.dual.config().step_pm),
            );
        }
        let motor_turned = report
            .motor_pm
            .saturating_sub(self.motor_at_change_pm)
            .saturating_abs();
        let lost = self.config.lost_encoder_pm;
        if missed || (self.steps_since_change > lost && motor_turned > lost / 2) {
            self.fault(CoarseStatus::ENCODER_LOST);
            return report.fine;
        }
        if self.following_pm.saturating_abs() > self.config.following_limit_pm {
            // The carriage estimate did not follow. If the motor turned (by more than four
            // counts) while the scale stood still, the scale is what stopped; a stalled motor
            // turns neither.
            let scale_silent =
                self.steps_since_change > 0 && motor_turned > 4 * self.dual.config().motor_count_pm;
            self.fault(if scale_silent {
                CoarseStatus::ENCODER_LOST
            } else {
                CoarseStatus::FOLLOWING_ERROR
            });
            return report.fine;
        }
        let moving = self.dual.is_moving();
        let into_limit =
            (velocity < 0 && self.switches.lower) || (velocity > 0 && self.switches.upper);
        match self.state {
            CoarseState::Homing => self.homing(report.measured_pm, velocity),
            CoarseState::Moving | CoarseState::Jogging | CoarseState::Stopping if into_limit => {
                self.fault(CoarseStatus::LIMIT_SWITCH)
            }
            CoarseState::Moving | CoarseState::Jogging | CoarseState::Stopping if !moving => {
                self.state = if self.homed {
                    CoarseState::Idle
                } else {
                    CoarseState::Unhomed
                };
            }
            _ => {}
        }
        report.fine
    }

    fn homing(&mut self, measured_pm: i64, velocity: i64) {
        self.home_ticks = self.home_ticks.saturating_add(1);
        if self.home_ticks > self.config.home_timeout_ticks {
            self.fault(CoarseStatus::HOMING_TIMEOUT);
            return;
        }
        let sw = self.switches;
        if (velocity < 0 && sw.lower) || (velocity > 0 && sw.upper) {
            self.fault(CoarseStatus::HOMING_LIMIT | CoarseStatus::LIMIT_SWITCH);
            return;
        }
        match self.phase {
            HomePhase::BackOff if !sw.home => {
                self.phase = HomePhase::Seek;
                self.jog_raw(self.config.home_forward, self.home_limits);
            }
            HomePhase::Seek if sw.home => {
                self.offset_pm = self.config.home_position_pm.saturating_sub(measured_pm);
                self.dual.stop();
                self.phase = HomePhase::Brake;
            }
            HomePhase::Brake if !self.dual.is_moving() => {
                let (lo, hi) = self.config.limits.travel_pm;
                self.dual.set_travel((
                    lo.saturating_sub(self.offset_pm),
                    hi.saturating_sub(self.offset_pm),
                ));
                // The travel clamps a setpoint that braked beyond the limit back inside.
                self.dual.hold();
                self.homed = true;
                self.state = CoarseState::Idle;
                self.dual.set_mode(DualMode::Dual);
            }
            _ => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::DualStageSettings;
    use super::*;
    use crate::board::fakes::{FixedEncoder, FixedSwitches};
    use crate::board::{StepBurst, StepDirection};

    /// An ideal carriage on the step output (it moves as the pulses are accepted, unless
    /// stalled), encoders on it, switches at fixed carriage positions, faults on demand.
    struct Axis {
        steps: i64,
        stalled: bool,
        linear_lost: bool,
        frozen_linear: u16,
        force_upper: bool,
        home_at: Option<i64>,
        lower_at: i64,
        piezo_q: i32,
        pulses: u64,
    }

    impl StepDir for Axis {
        type Error = ();
        fn max_steps_per_burst(&self) -> u16 {
            255
        }
        fn emit(&mut self, b: StepBurst) -> Result<(), ()> {
            self.pulses += b.steps as u64;
            if !self.stalled {
                self.steps += match b.direction {
                    StepDirection::Forward => b.steps as i64,
                    StepDirection::Reverse => -(b.steps as i64),
                };
            }
            Ok(())
        }
    }

    fn axis() -> Axis {
        Axis {
            steps: 0,
            stalled: false,
            linear_lost: false,
            frozen_linear: 0,
            force_upper: false,
            // The reference 1 mm below the power-up position, the lower limit 2 mm below.
            home_at: Some(-1_000_000_000),
            lower_at: -2_000_000_000,
            piezo_q: 0,
            pulses: 0,
        }
    }

    fn supervisor() -> CoarseSupervisor {
        let mut s = DualStageSettings::paper_stage();
        s.backlash_um = 0.0;
        let dual = DualStage::new(s.build().unwrap(), 0, 0, 0);
        let config = SupervisorSettings::paper_stage()
            .build(dual.config(), s.coarse_rate_hz)
            .unwrap();
        CoarseSupervisor::new(dual, config)
    }

    fn tick(sup: &mut CoarseSupervisor, a: &mut Axis) -> FineSetpoints {
        let c = *sup.dual().config();
        let carriage = a.steps * c.step_pm;
        let total = carriage + sup.dual().fine_to_pm(a.piezo_q);
        let mut linear = total.div_euclid(c.linear_count_pm) as u16;
        if a.linear_lost {
            linear = a.frozen_linear;
        }
        a.frozen_linear = linear;
        let motor = carriage.div_euclid(c.motor_count_pm) as u16;
        let switches = Switches {
            lower: carriage <= a.lower_at,
            upper: a.force_upper,
            home: a.home_at.is_some_and(|h| carriage <= h),
        };
        let f = sup.tick(
            a,
            &mut FixedEncoder(motor),
            &mut FixedEncoder(linear),
            &mut FixedSwitches(switches),
            Some(a.piezo_q),
        );
        a.piezo_q = f.to;
        f
    }

    /// Ticks until `done` or `max` ticks; returns the ticks run.
    fn run_until(
        sup: &mut CoarseSupervisor,
        a: &mut Axis,
        max: u32,
        done: impl Fn(&CoarseStatus) -> bool,
    ) -> u32 {
        for n in 0..max {
            tick(sup, a);
            if done(&sup.status()) {
                return n + 1;
            }
        }
        max
    }

    fn home(sup: &mut CoarseSupervisor, a: &mut Axis) {
        sup.command(CoarseCommand::Home).unwrap();
        run_until(sup, a, 20_000, |s| s.state != CoarseState::Homing);
        assert_eq!(sup.status().state, CoarseState::Idle, "{:?}", sup.status());
    }

    fn check_move(sup: &CoarseSupervisor, mm: f64) -> Result<CoarseCommand, CoarseRefusal> {
        sup.limits().check_move(&sup.status(), mm, 10.0, 200.0)
    }

    #[test]
    fn homing_sets_the_reference_and_moves_need_it() {
        let (mut sup, mut a) = (supervisor(), axis());
        assert_eq!(
            check_move(&sup, 0.0),
            Err(refuse(Field::CoarseAxis, Rule::NotHomed))
        );
        // A value that is no number is named first, before the axis's state.
        assert_eq!(
            check_move(&sup, f64::NAN),
            Err(refuse(Field::CoarseTarget, Rule::NotFinite))
        );
        assert_eq!(
            sup.limits().check_move(&sup.status(), 0.0, f64::NAN, 200.0),
            Err(refuse(Field::CoarseVelocity, Rule::NotFinite))
        );
        assert_eq!(
            sup.limits().check_jog(&sup.status(), f64::INFINITY),
            Err(refuse(Field::CoarseVelocity, Rule::NotFinite))
        );
        home(&mut sup, &mut a);
        let s = sup.status();
        assert!(s.homed && s.faults == 0);
        // The reference is at carriage −1 mm, which is now −24 mm; the axis braked past it.
        let at_reference = s.position_pm - (a.steps * 312_500 - -1_000_000_000);
        assert!((at_reference - -24_000_000_000).abs() < 2_000_000, "{s:?}");
        let cmd = check_move(&sup, -19.0).unwrap();
        sup.command(cmd).unwrap();
        assert_eq!(sup.status().state, CoarseState::Moving);
        run_until(&mut sup, &mut a, 20_000, |s| s.state == CoarseState::Idle);
        let s = sup.status();
        assert!((s.position_pm - -19_000_000_000).abs() < 320_000, "{s:?}");
        assert_eq!(s.faults, 0);
    }

    #[test]
    fn requests_outside_the_travel_or_the_limits_are_refused_with_the_reason() {
        let (mut sup, mut a) = (supervisor(), axis());
        home(&mut sup, &mut a);
        assert_eq!(
            check_move(&sup, 25.5),
            Err(refuse(Field::CoarseTarget, Rule::AtMost(25.0)))
        );
        assert_eq!(
            check_move(&sup, -30.0),
            Err(refuse(Field::CoarseTarget, Rule::AtLeast(-25.0)))
        );
        assert_eq!(
            check_move(&sup, f64::NAN),
            Err(refuse(Field::CoarseTarget, Rule::NotFinite))
        );
        let l = sup.limits();
        assert_eq!(
            l.check_move(&sup.status(), 1.0, 20.0, 200.0),
            Err(refuse(Field::CoarseVelocity, Rule::AtMost(15.0)))
        );
        assert_eq!(
            l.check_move(&sup.status(), 1.0, 10.0, 0.0),
            Err(refuse(Field::CoarseAcceleration, Rule::Above(0.0)))
        );
        assert_eq!(
            l.check_jog(&sup.status(), -0.0),
            Err(refuse(Field::CoarseVelocity, Rule::Above(0.0)))
        );
        let mut at_upper = sup.status();
        at_upper.switches = CoarseStatus::UPPER_LIMIT;
        assert_eq!(
            l.check_jog(&at_upper, 1.0),
            Err(refuse(Field::CoarseTarget, Rule::LimitSwitch))
        );
        assert!(l.check_jog(&at_upper, -1.0).is_ok());
        // Busy while homing.
        sup.command(CoarseCommand::Home).unwrap();
        tick(&mut sup, &mut a);
        assert_eq!(check_move(&sup, 0.0), Err(CoarseRefusal::Busy));
    }

    #[test]
    fn a_homing_that_finds_nothing_times_out_or_stops_at_the_limit() {
        let (mut sup, mut a) = (supervisor(), axis());
        a.home_at = None;
        sup.command(CoarseCommand::Home).unwrap();
        run_until(&mut sup, &mut a, 200_000, |s| {
            s.state != CoarseState::Homing
        });
        let s = sup.status();
        assert_eq!(s.state, CoarseState::Fault);
        assert_eq!(
            s.faults,
            CoarseStatus::HOMING_LIMIT | CoarseStatus::LIMIT_SWITCH
        );
        assert!(!s.homed);
        // No limit within reach: the timeout (30 s = 150 000 ticks).
        let (mut sup, mut a) = (supervisor(), axis());
        a.home_at = None;
        a.lower_at = i64::MIN;
        sup.command(CoarseCommand::Home).unwrap();
        let n = run_until(&mut sup, &mut a, 200_000, |s| {
            s.state != CoarseState::Homing
        });
        assert_eq!(sup.status().faults, CoarseStatus::HOMING_TIMEOUT);
        assert_eq!(n, 150_001);
    }

    /// Moves, injects a fault mid-move, and checks: flagged, no further pulses, the piezo's
    /// setpoint continuous and then held.
    fn fault_mid_move(inject: impl Fn(&mut Axis), flag: u16) {
        let (mut sup, mut a) = (supervisor(), axis());
        home(&mut sup, &mut a);
        sup.command(check_move(&sup, -14.0).unwrap()).unwrap();
        run_until(&mut sup, &mut a, 1000, |_| false);
        inject(&mut a);
        let mut last = a.piezo_q;
        let mut n = 0;
        while sup.status().state == CoarseState::Moving {
            let f = tick(&mut sup, &mut a);
            assert_eq!(f.from, last, "continuous");
            last = f.to;
            n += 1;
            assert!(n < 100, "not detected: {:?}", sup.status());
        }
        let s = sup.status();
        assert_eq!(
            (s.state, s.faults, s.homed),
            (CoarseState::Fault, flag, false)
        );
        let pulses = a.pulses;
        for _ in 0..100 {
            let f = tick(&mut sup, &mut a);
            assert_eq!((f.from, f.to), (last, last), "the piezo holds");
        }
        assert_eq!(a.pulses, pulses, "no step after the fault");
        assert_eq!(
            check_move(&sup, 0.0),
            Err(refuse(Field::CoarseAxis, Rule::NotHomed))
        );
        // Homing clears it (with the fault removed).
        a.stalled = false;
        a.linear_lost = false;
        a.force_upper = false;
        home(&mut sup, &mut a);
        assert_eq!(sup.status().faults, 0);
    }

    #[test]
    fn a_stalled_motor_is_a_following_error() {
        fault_mid_move(|a| a.stalled = true, CoarseStatus::FOLLOWING_ERROR);
    }

    #[test]
    fn a_silent_linear_encoder_is_a_lost_encoder() {
        fault_mid_move(|a| a.linear_lost = true, CoarseStatus::ENCODER_LOST);
    }

    #[test]
    fn a_limit_switch_in_the_direction_of_travel_stops_the_axis() {
        fault_mid_move(|a| a.force_upper = true, CoarseStatus::LIMIT_SWITCH);
    }

    #[test]
    fn stop_brakes_to_rest_without_a_fault() {
        let (mut sup, mut a) = (supervisor(), axis());
        home(&mut sup, &mut a);
        sup.command(check_move(&sup, 0.0).unwrap()).unwrap();
        run_until(&mut sup, &mut a, 500, |_| false);
        sup.command(CoarseCommand::Stop).unwrap();
        assert_eq!(sup.status().state, CoarseState::Stopping);
        let n = run_until(&mut sup, &mut a, 5000, |s| s.state == CoarseState::Idle);
        // 10 mm/s at 200 mm/s²: 50 ms = 250 ticks of braking (plus the follower's settling).
        assert!(n < 400, "{n}");
        let s = sup.status();
        assert!(s.position_pm < -1_000_000_000 && s.faults == 0, "{s:?}");
    }
}
