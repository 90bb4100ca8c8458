//! [`DualStage`]: the coarse tick of the dual-actuated stage.
//!
//! Once per coarse period (`fine_ticks` piezo ticks) the coarse tick
//!
//! 1. reads the linear encoder (total position `x`, pm) and takes the piezo's last measured
//!    displacement `p` from its controller, so the carriage is at `ĉ = x − p`;
//! 2. advances the total setpoint `r` (a planned trapezoidal move, a streamed trajectory, or a
//!    hold), clamped to the travel limits;
//! 3. centring: the piezo's share `o = r − ĉ − centre` beyond the dead band is integrated into
//!    a correction of the coarse target, so the coarse stage takes it over;
//! 4. the coarse target (low-frequency part of `r` + correction) goes through the coarse
//!    stage's trapezoidal limits and becomes a burst of steps;
//! 5. the fine setpoint for the end of the coarse period is the residual
//!    `r_next − ĉ_predicted`, clamped to the window around mid-stroke, scaled by the hand-over
//!    ramp `λ` (0 coarse only … 1 dual), slope-limited, in Q2.30 of the piezo controller's range;
//!    the fine ticks ramp linearly to it from where the last period ended.
//!
//! Nothing here allocates, panics or loops: all arithmetic saturates.

use super::carriage_tracker::CarriageTracker;
use super::split_filter::SplitFilter;
use super::trapezoid::{PreparedLimits, TrapezoidalProfile};
use super::DualStageConfig;
use crate::board::{QuadratureEncoder, StepDir};
use crate::divisor::Divisor;
use crate::dual_stage::coarse_axis::{EncoderCounter, StepGenerator};
use crate::fixed_point::{limit_i64, saturate_i64, SIGNAL_FRAC_BITS};

/// What the tick needs of the configuration, prepared once when the controller is built: its
/// divisors ([`Divisor`]: the tick divides by multiplication, with no 64-bit library
/// division; each is a validated positive setting, and a 0 would divide to 0, no panic path)
/// and its motion limits' braking arithmetic ([`PreparedLimits`]).
#[derive(Clone, Copy, Debug)]
struct Prepared {
    /// The microstep, pm.
    step: Divisor,
    /// The piezo's half-span, pm (to Q2.30).
    half_span: Divisor,
    /// The hand-over's length, coarse ticks.
    handover: Divisor,
    /// The coarse stage's limits (the follower's).
    coarse_limits: PreparedLimits,
    /// A planned move's default limits.
    move_limits: PreparedLimits,
}

impl Prepared {
    fn new(c: &DualStageConfig) -> Self {
        Self {
            step: Divisor::new(c.step_pm.max(0) as u64),
            half_span: Divisor::new(c.fine_half_span_pm.max(0) as u64),
            handover: Divisor::new(u64::from(c.handover_ticks)),
            coarse_limits: c.coarse_limits.prepare(),
            move_limits: c.move_limits.prepare(),
        }
    }
}

/// Who positions the stage.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum DualMode {
    /// The coarse stage alone (closed on the linear encoder); the piezo is held at mid-stroke.
    CoarseOnly,
    /// Both: the piezo takes the residual.
    Dual,
}

/// Where the total setpoint comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Reference {
    /// Hold where it is.
    Hold,
    /// A planned move to `target` (pm).
    Move {
        profile: TrapezoidalProfile,
        target: i64,
    },
    /// The latest streamed sample (pm), the setpoint at the end of the next coarse period.
    Stream(i64),
}

/// The piezo's setpoints for the fine ticks of one coarse period: a linear ramp, Q2.30 of the
/// piezo controller's output range.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FineSetpoints {
    /// Setpoint before the period (where the last one ended), Q2.30.
    pub from: i32,
    /// Setpoint at the period's last fine tick, Q2.30.
    pub to: i32,
    /// Fine ticks in the period (≥ 1).
    pub ticks: u32,
}

impl FineSetpoints {
    /// The setpoint of fine tick `j` (1…ticks) of the period, Q2.30.
    pub fn at(&self, j: u32) -> i32 {
        let span = self.to as i64 - self.from as i64;
        let j = j.min(self.ticks) as i64;
        saturate_i64(self.from as i64 + span * j / self.ticks.max(1) as i64)
    }
}

/// What one coarse tick did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CoarseReport {
    /// The piezo's setpoints for the next coarse period.
    pub fine: FineSetpoints,
    /// Total setpoint at the end of the next period, pm.
    pub setpoint_pm: i64,
    /// Linear encoder reading (total position), pm.
    pub measured_pm: i64,
    /// Carriage estimate `ĉ = x − p`, pm.
    pub carriage_pm: i64,
    /// Motor encoder position, pm of carriage travel.
    pub motor_pm: i64,
    /// Coarse command (carriage), pm.
    pub coarse_command_pm: i64,
    /// Steps emitted this tick (signed).
    pub steps: i32,
    /// The residual did not fit the fine window (the piezo got the window's edge).
    pub fine_clamped: bool,
}

/// Counters since start.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DualStageCounters {
    /// Coarse ticks run.
    pub ticks: u32,
    /// Ticks whose residual exceeded the fine window.
    pub fine_clamps: u32,
    /// Ticks whose fine setpoint hit the slope limit.
    pub fine_slew_limits: u32,
    /// Bursts the step output refused (their steps stay owed).
    pub refused_bursts: u32,
    /// Setpoints clamped to the travel limits.
    pub travel_clamps: u32,
}

/// The dual-stage controller's state (see the module doc).
#[derive(Clone, Debug)]
pub struct DualStage {
    config: DualStageConfig,
    prepared: Prepared,
    mode: DualMode,
    reference: Reference,
    /// Total setpoint at the start of the coming coarse period, pm.
    setpoint: i64,
    split: SplitFilter,
    follower: TrapezoidalProfile,
    /// Centring correction of the coarse target, pm.
    correction: i64,
    steps: StepGenerator,
    motor: EncoderCounter,
    linear: EncoderCounter,
    /// Total position at linear-encoder count 0, pm.
    origin: i64,
    /// Coarse ticks into the hand-over ramp (0…handover_ticks).
    engaged: u32,
    /// Last fine setpoint handed out, pm and Q2.30.
    fine_pm: i64,
    fine_q: i32,
    /// Coarse command at the last tick, pm, and its velocity, pm per tick.
    last_command: i64,
    last_command_velocity: i64,
    tracker: CarriageTracker,
    /// Coarse ticks since the coarse command last moved.
    still_ticks: u32,
    counters: DualStageCounters,
}

impl DualStage {
    /// At rest: the total position is `position_pm` at the encoders' present readings, the
    /// piezo at mid-stroke, the motor at step 0, mode coarse only.
    pub fn new(config: DualStageConfig, position_pm: i64, motor_raw: u16, linear_raw: u16) -> Self {
        // The piezo at mid-stroke and no count yet; the rest as `reset_at` sets it.
        let prepared = Prepared::new(&config);
        let mut stage = Self {
            config,
            prepared,
            mode: DualMode::CoarseOnly,
            reference: Reference::Hold,
            setpoint: 0,
            split: SplitFilter::new(config.split, 0),
            follower: TrapezoidalProfile::prepared(0, prepared.coarse_limits),
            correction: 0,
            steps: StepGenerator::new(0, config.backlash_steps, config.max_steps_per_burst),
            motor: EncoderCounter::new(0),
            linear: EncoderCounter::new(0),
            origin: 0,
            engaged: 0,
            fine_pm: config.fine_centre_pm,
            fine_q: Self::to_q(&config, &prepared, config.fine_centre_pm),
            last_command: 0,
            last_command_velocity: 0,
            tracker: CarriageTracker::new(config.carriage_alpha, config.carriage_alpha_at_rest, 0),
            still_ticks: 0,
            counters: DualStageCounters::default(),
        };
        stage.reset_at(position_pm, motor_raw, linear_raw);
        stage
    }

    /// At rest, coarse only, at total position `position_pm` with the encoders' present
    /// readings and the carriage where the piezo at mid-stroke puts it: every field but the
    /// configuration, the piezo's setpoint, the hand-over ramp and the counters, set in place
    /// (the coarse task's tick calls it through [`DualStage::restart`]: no copy of the whole
    /// controller).
    fn reset_at(&mut self, position_pm: i64, motor_raw: u16, linear_raw: u16) {
        let c = &self.config;
        let carriage = position_pm.saturating_sub(c.fine_centre_pm);
        self.mode = DualMode::CoarseOnly;
        self.reference = Reference::Hold;
        self.setpoint = position_pm;
        self.split = SplitFilter::new(c.split, carriage);
        self.follower = TrapezoidalProfile::prepared(carriage, self.prepared.coarse_limits);
        self.correction = 0;
        self.steps = StepGenerator::new(
            self.prepared.step.trunc(carriage),
            c.backlash_steps,
            c.max_steps_per_burst,
        );
        self.motor = EncoderCounter::new(motor_raw);
        self.linear = EncoderCounter::new(linear_raw);
        self.origin = position_pm;
        self.last_command = carriage;
        self.last_command_velocity = 0;
        self.tracker.reset(carriage);
        self.still_ticks = 0;
    }

    /// The configuration.
    pub fn config(&self) -> &DualStageConfig {
        &self.config
    }

    /// Switches between coarse only and dual; the piezo's share ramps in or out over the
    /// hand-over time.
    pub fn set_mode(&mut self, mode: DualMode) {
        self.mode = mode;
    }

    /// The mode.
    pub fn mode(&self) -> DualMode {
        self.mode
    }

    /// Plans a trapezoidal move of the total setpoint to `target_pm` (clamped to the travel),
    /// from where the setpoint is now.
    pub fn move_to(&mut self, target_pm: i64) {
        let target = self.clamp_travel(target_pm);
        let profile = match self.reference {
            Reference::Move { profile, .. } => profile,
            _ => TrapezoidalProfile::prepared(self.setpoint, self.prepared.move_limits),
        };
        self.reference = Reference::Move { profile, target };
    }

    /// Plans a trapezoidal move to `target_pm` (clamped to the travel) with its own speed and
    /// acceleration (`limits`, pm per coarse tick (²), valid and within the coarse stage's: the
    /// caller checks), prepared off the coarse tick ([`super::MotionLimits::prepare`]: by the
    /// command handler for a move or a jog, with the supervisor's settings for homing). A move
    /// already under way is re-targeted from its present velocity.
    pub fn move_to_prepared(&mut self, target_pm: i64, limits: PreparedLimits) {
        let target = self.clamp_travel(target_pm);
        let profile = match self.reference {
            Reference::Move { mut profile, .. } => {
                profile.set_prepared(limits);
                profile
            }
            _ => TrapezoidalProfile::prepared(self.setpoint, limits),
        };
        self.reference = Reference::Move { profile, target };
    }

    /// A controlled stop: a planned move brakes at its acceleration to where it comes to rest
    /// (no step is lost); a streamed setpoint holds where it is.
    pub fn stop(&mut self) {
        match &mut self.reference {
            Reference::Move { profile, target } => *target = profile.stopping_point(),
            _ => self.reference = Reference::Hold,
        }
    }

    /// Moves the travel limits of the total position (pm, `lo < hi`; an empty range is
    /// ignored): the coarse supervisor widens them while homing and sets the homed travel in
    /// this controller's coordinates afterwards.
    pub fn set_travel(&mut self, travel_pm: (i64, i64)) {
        if travel_pm.0 < travel_pm.1 {
            self.config.travel_pm = travel_pm;
        }
    }

    /// Starts again at rest at total position `position_pm` with the encoders' present
    /// readings (as [`DualStage::new`], coarse only), but keeps the piezo's setpoint where it
    /// is (the hand-over ramp walks it back to mid-stroke, slope-limited: no jump), the travel
    /// limits and the counters. Used after a fault, whose stop left the follower's and the
    /// step generator's state behind the stage's.
    pub fn restart(&mut self, position_pm: i64, motor_raw: u16, linear_raw: u16) {
        // The carriage is where the total position less the piezo's share puts it (not at
        // `position − centre`, as `new` assumes of a piezo at mid-stroke): the setpoint starts
        // there plus mid-stroke, so the coarse command and the carriage agree.
        let share = self.fine_pm.saturating_sub(self.config.fine_centre_pm);
        self.reset_at(position_pm.saturating_sub(share), motor_raw, linear_raw);
        self.origin = position_pm;
    }

    /// Reads the linear encoder only (the total position, pm), without moving anything: for a
    /// stopped axis whose coarse tick does not run.
    pub fn read_position<L: QuadratureEncoder>(&mut self, linear_encoder: &mut L) -> i64 {
        let linear = self.linear.update(linear_encoder.count());
        self.origin
            .saturating_add(linear.saturating_mul(self.config.linear_count_pm))
    }

    /// Continues the fine ramp from `q` (Q2.30 of the piezo controller's range: where the
    /// piezo's setpoint is after its own sources moved it), so that the next periods' fine
    /// setpoints leave from there at the slope limit, with no jump.
    pub fn resume_fine_from(&mut self, q: i32) {
        self.fine_q = q;
        self.fine_pm = self.fine_to_pm(q);
    }

    /// The last fine setpoint handed out (Q2.30 of the piezo controller's range): where the
    /// piezo holds when the coarse tick stops.
    pub fn fine_setpoint(&self) -> i32 {
        self.fine_q
    }

    /// The total setpoint at the start of the coming period, pm.
    pub fn setpoint_pm(&self) -> i64 {
        self.setpoint
    }

    /// Whether the coarse stage is still moving: a planned move not done, or the coarse
    /// follower still moving by more than a microstep per coarse tick (at rest it may hunt by
    /// one step as the centring trims the last fraction of a step: that is not motion).
    pub fn is_moving(&self) -> bool {
        !self.move_done() || self.follower.velocity().abs() > self.config.step_pm
    }

    /// Streams the total setpoint: `setpoint_pm` is where the stage should be at the end of the
    /// next coarse period (clamped to the travel).
    pub fn follow(&mut self, setpoint_pm: i64) {
        self.reference = Reference::Stream(self.clamp_travel(setpoint_pm));
    }

    /// Holds the present setpoint.
    pub fn hold(&mut self) {
        self.reference = Reference::Hold;
    }

    /// Whether a planned move has reached its target.
    pub fn move_done(&self) -> bool {
        match self.reference {
            Reference::Move { profile, target } => {
                profile.position() == target && profile.velocity() == 0
            }
            _ => true,
        }
    }

    /// Counters since start.
    pub fn counters(&self) -> DualStageCounters {
        self.counters
    }

    /// The hand-over ramp, 0…1 as a fraction `(engaged, of)`.
    pub fn handover(&self) -> (u32, u32) {
        (self.engaged, self.config.handover_ticks)
    }

    fn clamp_travel(&mut self, x: i64) -> i64 {
        let (lo, hi) = self.config.travel_pm;
        let c = limit_i64(x, lo, hi);
        if c != x {
            self.counters.travel_clamps = self.counters.travel_clamps.wrapping_add(1);
        }
        c
    }

    /// Piezo displacement (pm) → Q2.30 of the fine controller's range, saturated.
    fn to_q(config: &DualStageConfig, prepared: &Prepared, p: i64) -> i32 {
        let d = p.saturating_sub(config.fine_mid_pm);
        let span = config.fine_half_span_pm;
        let d = limit_i64(d, -2 * span, 2 * span);
        saturate_i64(prepared.half_span.trunc(d << SIGNAL_FRAC_BITS))
    }

    /// Q2.30 of the fine controller's range → piezo displacement, pm.
    pub fn fine_to_pm(&self, q: i32) -> i64 {
        self.config.fine_mid_pm + ((q as i64 * self.config.fine_half_span_pm) >> SIGNAL_FRAC_BITS)
    }

    /// One coarse tick (see the module doc). `fine_measured` is the piezo controller's last
    /// measured displacement (Q2.30, its `TickReport::measured`), `None` when it has no sensor
    /// reading (its last setpoint is used instead).
    pub fn coarse_tick<S: StepDir, M: QuadratureEncoder, L: QuadratureEncoder>(
        &mut self,
        step_dir: &mut S,
        motor_encoder: &mut M,
        linear_encoder: &mut L,
        fine_measured: Option<i32>,
    ) -> CoarseReport {
        let c = self.config;
        self.counters.ticks = self.counters.ticks.wrapping_add(1);

        // 1. Measure.
        let linear = self.linear.update(linear_encoder.count());
        let measured = self
            .origin
            .saturating_add(linear.saturating_mul(c.linear_count_pm));
        let motor = self
            .motor
            .update(motor_encoder.count())
            .saturating_mul(c.motor_count_pm);
        let piezo = fine_measured.map_or(self.fine_pm, |q| self.fine_to_pm(q));
        let carriage = measured.saturating_sub(piezo);

        // 2. The setpoint at the end of the coming period.
        let next = match &mut self.reference {
            Reference::Hold => self.setpoint,
            Reference::Move { profile, target } => profile.step(*target),
            Reference::Stream(r) => *r,
        };

        // 3. Centring: what the piezo must hold now beyond the dead band goes to the coarse stage.
        let share = self
            .setpoint
            .saturating_sub(carriage)
            .saturating_sub(c.fine_centre_pm);
        let deadband = match self.mode {
            DualMode::Dual => c.centring_deadband_pm,
            DualMode::CoarseOnly => c.step_pm / 2,
        };
        let beyond = share.signum() * share.saturating_abs().saturating_sub(deadband).max(0);
        let beyond = limit_i64(beyond, -c.fine_half_span_pm * 4, c.fine_half_span_pm * 4);
        let limit = c.fine_half_span_pm * 8;
        self.correction = limit_i64(
            self.correction + ((beyond * c.centring_gain) >> 24),
            -limit,
            limit,
        );

        // 4. The coarse stage: low-frequency part of the setpoint plus the correction, within
        // its trapezoidal limits, in whole steps.
        // A planned move is already within the coarse stage's limits: it follows the plan
        // itself. A streamed setpoint is split.
        let carriage_setpoint = next.saturating_sub(c.fine_centre_pm);
        let low = match self.reference {
            Reference::Move { .. } => self.split.track(carriage_setpoint),
            _ => self.split.step(carriage_setpoint),
        };
        let (lo, hi) = c.travel_pm;
        let target = limit_i64(low.saturating_add(self.correction), lo, hi);
        let command = self.follower.follow(target);
        let before = self.steps.motor_position();
        if let Some(burst) = self
            .steps
            .plan(self.prepared.step.floor(command + c.step_pm / 2))
        {
            match step_dir.emit(burst) {
                Ok(()) => self.steps.issued(burst),
                Err(_) => {
                    self.counters.refused_bursts = self.counters.refused_bursts.wrapping_add(1)
                }
            }
        }
        let steps = self.steps.motor_position() - before;

        // 5. The piezo's share at the end of the period: the residual against where the
        // carriage will be (it moves as commanded, to first order).
        let command_velocity = command - self.last_command;
        self.still_ticks = if command_velocity == 0 {
            self.still_ticks.saturating_add(1)
        } else {
            0
        };
        let resting = self.still_ticks > c.settle_ticks;
        let predicted = self.tracker.update(
            carriage,
            command_velocity - self.last_command_velocity,
            resting,
        );
        self.last_command = command;
        self.last_command_velocity = command_velocity;
        let residual = next
            .saturating_sub(predicted)
            .saturating_sub(c.fine_centre_pm);
        let window = c.fine_window_pm;
        let clamped = limit_i64(residual, -window, window);
        let fine_clamped = clamped != residual && self.mode == DualMode::Dual;
        if fine_clamped {
            self.counters.fine_clamps = self.counters.fine_clamps.wrapping_add(1);
        }
        self.engaged = match self.mode {
            DualMode::Dual => (self.engaged + 1).min(c.handover_ticks),
            DualMode::CoarseOnly => self.engaged.saturating_sub(1),
        };
        let share = self.prepared.handover.trunc(clamped * self.engaged as i64);
        let wanted = c.fine_centre_pm + share;
        let fine = limit_i64(
            wanted,
            self.fine_pm - c.fine_step_pm,
            self.fine_pm + c.fine_step_pm,
        );
        if fine != wanted {
            self.counters.fine_slew_limits = self.counters.fine_slew_limits.wrapping_add(1);
        }
        let from = self.fine_q;
        self.fine_pm = fine;
        self.fine_q = Self::to_q(&c, &self.prepared, fine);
        self.setpoint = next;

        CoarseReport {
            fine: FineSetpoints {
                from,
                to: self.fine_q,
                ticks: c.fine_ticks,
            },
            setpoint_pm: next,
            measured_pm: measured,
            carriage_pm: carriage,
            motor_pm: motor,
            coarse_command_pm: command,
            steps: steps as i32,
            fine_clamped,
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::super::DualStageSettings;
    use super::*;
    use crate::board::fakes::FixedEncoder;
    use crate::board::{StepBurst, StepDirection};
    use std::vec;
    use std::vec::Vec;

    /// A step output that moves an ideal carriage (and a linear encoder on it) at once.
    struct IdealAxis {
        steps: i64,
        refuse: bool,
    }
    impl StepDir for IdealAxis {
        type Error = ();
        fn max_steps_per_burst(&self) -> u16 {
            255
        }
        fn emit(&mut self, b: StepBurst) -> Result<(), ()> {
            if self.refuse {
                return Err(());
            }
            self.steps += match b.direction {
                StepDirection::Forward => b.steps as i64,
                StepDirection::Reverse => -(b.steps as i64),
            };
            Ok(())
        }
    }

    fn stage() -> DualStage {
        let mut s = DualStageSettings::paper_stage();
        s.backlash_um = 0.0;
        DualStage::new(s.build().unwrap(), 0, 0, 0)
    }

    /// Runs `ticks` coarse ticks on an ideal carriage with the piezo exactly at its setpoint.
    fn run(d: &mut DualStage, axis: &mut IdealAxis, ticks: usize) -> Vec<CoarseReport> {
        let c = *d.config();
        let mut out = vec![];
        let mut piezo_q = DualStage::to_q(&c, &d.prepared, c.fine_centre_pm);
        for _ in 0..ticks {
            let x = axis.steps * c.step_pm + d.fine_to_pm(piezo_q);
            let mut lin = FixedEncoder((x / c.linear_count_pm) as u16);
            let r = d.coarse_tick(axis, &mut FixedEncoder(0), &mut lin, Some(piezo_q));
            piezo_q = r.fine.to;
            out.push(r);
        }
        out
    }

    #[test]
    fn fine_setpoints_ramp_from_where_the_last_period_ended() {
        let f = FineSetpoints {
            from: -100,
            to: 400,
            ticks: 50,
        };
        assert_eq!(f.at(0), -100);
        assert_eq!(f.at(25), 150);
        assert_eq!(f.at(50), 400);
        assert_eq!(f.at(99), 400);
    }

    #[test]
    fn a_long_move_keeps_the_piezo_inside_its_window_and_ends_centred() {
        let mut d = stage();
        let mut axis = IdealAxis {
            steps: 0,
            refuse: false,
        };
        d.set_mode(DualMode::Dual);
        run(&mut d, &mut axis, 50);
        d.move_to(5_000_000_000);
        let reports = run(&mut d, &mut axis, 4000);
        let mut prev = reports[0].fine.from;
        for r in &reports {
            assert!(!r.fine_clamped);
            assert_eq!(r.fine.from, prev, "each period starts where the last ended");
            prev = r.fine.to;
        }
        assert!(d.move_done());
        let last = reports.last().unwrap();
        let piezo = d.fine_to_pm(last.fine.to);
        assert!(piezo.abs() <= d.config().centring_deadband_pm, "{piezo} pm");
        assert_eq!(d.counters().fine_clamps, 0);
    }

    #[test]
    fn refused_bursts_are_counted_and_their_steps_sent_later() {
        let mut d = stage();
        let mut axis = IdealAxis {
            steps: 0,
            refuse: true,
        };
        d.move_to(100_000_000);
        run(&mut d, &mut axis, 20);
        assert!(d.counters().refused_bursts > 0);
        axis.refuse = false;
        run(&mut d, &mut axis, 500);
        let target_steps = 100_000_000 / d.config().step_pm;
        assert!((axis.steps - target_steps).abs() <= 1, "{}", axis.steps);
    }

    #[test]
    fn a_restart_is_a_fresh_controller_that_keeps_the_piezo_the_ramp_and_the_counts() {
        let mut d = stage();
        let mut axis = IdealAxis {
            steps: 0,
            refuse: false,
        };
        d.set_mode(DualMode::Dual);
        run(&mut d, &mut axis, 40);
        d.move_to(2_000_000_000);
        run(&mut d, &mut axis, 300);
        d.follow(i64::MAX); // a travel clamp counted
        let (fine_pm, fine_q, engaged, counters) = (d.fine_pm, d.fine_q, d.engaged, d.counters);
        assert!(fine_pm != d.config.fine_centre_pm && engaged > 0);
        let config = d.config;
        let (position, motor, linear) = (1_234_567_890, 77, 4_321);
        d.restart(position, motor, linear);
        // As built afresh where the piezo's share puts the carriage, with the origin at the
        // position, and the piezo's setpoint, the hand-over and the counters as they were.
        let share = fine_pm - config.fine_centre_pm;
        let mut fresh = DualStage::new(config, position - share, motor, linear);
        fresh.origin = position;
        fresh.fine_pm = fine_pm;
        fresh.fine_q = fine_q;
        fresh.engaged = engaged;
        fresh.counters = counters;
        assert_eq!(std::format!("{d:?}"), std::format!("{fresh:?}"));
        assert_eq!(d.mode(), DualMode::CoarseOnly);
        assert_eq!(d.counters().travel_clamps, 1);
    }

    #[test]
    fn streamed_setpoints_beyond_the_travel_are_clamped() {
        let mut d = stage();
        d.follow(i64::MAX);
        assert_eq!(d.counters().travel_clamps, 1);
        let mut axis = IdealAxis {
            steps: 0,
            refuse: false,
        };
        let r = run(&mut d, &mut axis, 1);
        assert_eq!(r[0].setpoint_pm, d.config().travel_pm.1);
    }
}
