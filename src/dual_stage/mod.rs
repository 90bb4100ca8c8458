//! The dual-actuated stage: a ball-screw (stepper, step/dir) coarse stage carrying the piezo
//! fine stage, under one controller (the second paper's system).
//!
//! ```text
//!   move_to / follow ─► total setpoint r ─┬─► split filter (low-frequency part) ─► + centring
//!                                         │        ─► trapezoidal follower ─► step generator ─► STEP/DIR
//!                                         │
//!   linear encoder (total x) ─► − piezo sensor ─► carriage estimate ĉ
//!                                         ▼
//!                        r − ĉ (the residual) ─► window clamp ─► hand-over ramp ─► fine setpoints
//!                                                         (the piezo `Controller::tick` tracks them)
//! ```
//!
//! * [`trapezoid`] — the trapezoidal velocity profile (planned moves, and the coarse follower).
//! * [`split_filter`] — the low-frequency part of the setpoint, for the coarse stage.
//! * [`controller`] — [`DualStage`]: one coarse tick (e.g. 1 kHz) reads both encoders, moves
//!   the coarse stage, and hands the piezo's [`crate::control::Controller`] the residual as a
//!   ramp of fine setpoints ([`FineSetpoints`]) for the fine ticks of the next coarse period.
//! * [`supervisor`] — [`CoarseSupervisor`]: the coarse axis's state machine (homing, moves,
//!   jogs, stops, faults) around the [`DualStage`]; [`link`] — where the coarse task, the piezo
//!   tick and the command handler meet on the board.
//! * [`DualStageSettings`] — everything in physical units, validated and turned into the
//!   integer [`DualStageConfig`] off the tick path.
//!
//! The piezo is steered back toward mid-stroke while the coarse stage moves: whatever the
//! piezo holds beyond a dead band is added, integrated, to the coarse target, so the coarse
//! stage takes it over and the piezo never runs into the end of its stroke on a long move.
//! The residual is clamped to a window inside the stroke, and the fine setpoint is a
//! continuous, piecewise-linear ramp (each coarse period starts where the last one ended, and
//! its slope is limited), so the hand-over between the stages has no jump.
//!
//! Units: positions in picometres (`i64`), the piezo's setpoints and readings in Q2.30 of the
//! fine controller's output range (as [`crate::control::Controller::tick`] takes them).

pub mod carriage_tracker;
pub mod coarse_axis;
pub mod controller;
pub mod ideal_axis;
pub mod link;
pub mod split_filter;
pub mod supervisor;
pub mod trapezoid;

use carriage_tracker::CarriageTracker;
pub use controller::{CoarseReport, DualMode, DualStage, DualStageCounters, FineSetpoints};
pub use link::{CoarseLink, CoarseTake, FineRamp, LoopExchange, PreparedCoarse};
pub use split_filter::{SplitCoefficients, SplitFilter};
pub use supervisor::{
    CoarseCommand, CoarseLimits, CoarseRefusal, CoarseState, CoarseStatus, CoarseSupervisor,
    SupervisorConfig, SupervisorSettings,
};
pub use trapezoid::{MotionLimits, PreparedLimits, TrapezoidalProfile};

/// Picometres per micrometre.
pub const PM_PER_UM: f64 = 1e6;

/// The dual stage in physical units (µm, µm/s, µm/s², Hz, s).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DualStageSettings {
    /// Coarse tick rate, Hz (100…10 000).
    pub coarse_rate_hz: f64,
    /// Fine (piezo) tick rate, Hz: a whole multiple (1…1000) of the coarse rate.
    pub fine_rate_hz: f64,
    /// Carriage travel per microstep, µm (lead / (full steps × microsteps)).
    pub step_um: f64,
    /// Carriage travel per motor-encoder count, µm (lead / (4 × lines)).
    pub motor_count_um: f64,
    /// Resolution of the linear encoder on the total position, µm per count.
    pub linear_count_um: f64,
    /// Soft travel limits of the total position, µm `(min, max)`: setpoints beyond are clamped.
    pub travel_um: (f64, f64),
    /// Speed of planned moves, µm/s.
    pub move_velocity_um_s: f64,
    /// Acceleration of planned moves, µm/s².
    pub move_acceleration_um_s2: f64,
    /// Speed limit of the coarse stage, µm/s (at or above the moves').
    pub coarse_velocity_um_s: f64,
    /// Acceleration limit of the coarse stage, µm/s².
    pub coarse_acceleration_um_s2: f64,
    /// Bandwidth of the split: the coarse stage follows the setpoint below it, Hz (0: all).
    pub split_hz: f64,
    /// The piezo controller's output range, µm `(min, max)` (Q2.30 −1…1 of its setpoints).
    pub fine_range_um: (f64, f64),
    /// Mid-stroke of the piezo, µm (where it is steered back to).
    pub fine_centre_um: f64,
    /// Largest residual the piezo is given, ± µm around mid-stroke (inside its stroke).
    pub fine_window_um: f64,
    /// Fastest the fine setpoint may move, µm/s.
    pub fine_velocity_um_s: f64,
    /// Residual the piezo may hold before the coarse stage takes it over, µm.
    pub centring_deadband_um: f64,
    /// Time constant of that take-over, s.
    pub centring_time_s: f64,
    /// Duration of the hand-over ramp when the piezo is switched in or out, s.
    pub handover_s: f64,
    /// Gain α of the carriage tracker, (0, 1]: 1 takes each estimate as it is, smaller values
    /// filter the sensors' noise more and follow changes of speed more slowly.
    pub carriage_alpha: f64,
    /// Gain α of the carriage tracker once the coarse command has stood still for
    /// `settle_s`, (0, 1].
    pub carriage_alpha_at_rest: f64,
    /// Time the coarse command must stand still before the resting gain applies, s.
    pub settle_s: f64,
    /// Backlash of the screw, µm (taken up by extra steps at reversals; 0: none).
    pub backlash_um: f64,
    /// Most step pulses the step/dir output takes per coarse period.
    pub max_steps_per_burst: u16,
}

/// Which setting was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum DualStageError {
    /// Coarse rate outside 100…10 000 Hz, or the fine rate not a whole multiple (1…1000) of it.
    Rates,
    /// A step, encoder count or resolution that is not a positive number of picometres.
    Resolution,
    /// Travel limits empty, not finite, or beyond ±1 m.
    Travel,
    /// Move or coarse velocity / acceleration not positive, too large, or the moves faster
    /// than the coarse stage.
    MotionLimits,
    /// The coarse speed needs more steps per period than a burst holds.
    BurstTooSmall,
    /// Split bandwidth negative, or too high for the coarse rate (`ωT > 0.5`).
    SplitBandwidth,
    /// Fine range empty or over 2 mm, window not positive or outside the range around the centre.
    FineRange,
    /// Fine velocity, dead band, centring time or hand-over not a positive finite number.
    Timing,
    /// Backlash negative or more than 1000 steps.
    Backlash,
    /// Homing speed or acceleration not valid or beyond the coarse stage's, the home position
    /// outside the travel, or the timeout not a positive number of coarse ticks.
    Homing,
    /// Following-error limit not positive, or the lost-encoder travel below one step.
    FaultLimits,
}

impl DualStageError {
    /// A one-word reason, for logs and status lines.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Rates => "rates",
            Self::Resolution => "resolution",
            Self::Travel => "travel",
            Self::MotionLimits => "motion-limits",
            Self::BurstTooSmall => "burst-too-small",
            Self::SplitBandwidth => "split-bandwidth",
            Self::FineRange => "fine-range",
            Self::Timing => "timing",
            Self::Backlash => "backlash",
            Self::Homing => "homing",
            Self::FaultLimits => "fault-limits",
        }
    }
}

/// The settings in the integer units the coarse tick runs in (see the field docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DualStageConfig {
    /// Fine ticks per coarse tick (≥ 1).
    pub fine_ticks: u32,
    /// Carriage travel per microstep, pm.
    pub step_pm: i64,
    /// Carriage travel per motor-encoder count, pm.
    pub motor_count_pm: i64,
    /// Linear encoder resolution, pm per count.
    pub linear_count_pm: i64,
    /// Travel limits of the total position, pm.
    pub travel_pm: (i64, i64),
    /// Limits of planned moves, pm per coarse tick (²).
    pub move_limits: MotionLimits,
    /// Limits of the coarse stage, pm per coarse tick (²).
    pub coarse_limits: MotionLimits,
    /// Split filter coefficients.
    pub split: SplitCoefficients,
    /// Middle of the fine controller's output range (Q2.30 zero), pm.
    pub fine_mid_pm: i64,
    /// Half the fine controller's output range (Q2.30 one), pm.
    pub fine_half_span_pm: i64,
    /// Mid-stroke, pm.
    pub fine_centre_pm: i64,
    /// Largest residual around mid-stroke, pm.
    pub fine_window_pm: i64,
    /// Largest change of the fine setpoint per coarse tick, pm.
    pub fine_step_pm: i64,
    /// Residual the piezo holds before centring acts, pm.
    pub centring_deadband_pm: i64,
    /// Centring gain per coarse tick, Q8.24 (`T / τ`).
    pub centring_gain: i64,
    /// Coarse ticks of the hand-over ramp (≥ 1).
    pub handover_ticks: u32,
    /// Carriage tracker gain α while moving, Q8.24.
    pub carriage_alpha: i64,
    /// Carriage tracker gain α at rest, Q8.24.
    pub carriage_alpha_at_rest: i64,
    /// Coarse ticks of standstill before the resting gain applies.
    pub settle_ticks: u32,
    /// Backlash take-up, microsteps.
    pub backlash_steps: u16,
    /// Most steps per burst.
    pub max_steps_per_burst: u16,
}

fn pm(um: f64) -> Option<i64> {
    let x = um * PM_PER_UM;
    (x.is_finite() && x.abs() < 1e15).then(|| libm::round(x) as i64)
}

fn positive_pm(um: f64) -> Option<i64> {
    pm(um).filter(|&p| p > 0)
}

impl DualStageSettings {
    /// A ball-screw stage with a 1 mm lead, a 200-step motor at 16 microsteps (0.3125 µm per
    /// step), a 1000-line motor encoder (0.25 µm per count) and a 5 nm linear encoder, carrying
    /// the paper's differential piezo stage (controller range ±40 µm, ±37 µm stroke); moves at
    /// 10 mm/s and 200 mm/s², coarse loop at 5 kHz under a 50 kHz piezo tick.
    pub fn paper_stage() -> Self {
        Self {
            coarse_rate_hz: 5000.0,
            fine_rate_hz: 50_000.0,
            step_um: 0.3125,
            motor_count_um: 0.25,
            linear_count_um: 0.005,
            travel_um: (-25_000.0, 25_000.0),
            move_velocity_um_s: 10_000.0,
            move_acceleration_um_s2: 200_000.0,
            coarse_velocity_um_s: 15_000.0,
            coarse_acceleration_um_s2: 400_000.0,
            split_hz: 20.0,
            fine_range_um: (-40.0, 40.0),
            fine_centre_um: 0.0,
            fine_window_um: 25.0,
            fine_velocity_um_s: 30_000.0,
            centring_deadband_um: 3.0,
            centring_time_s: 0.05,
            handover_s: 0.02,
            carriage_alpha: 1.0,
            carriage_alpha_at_rest: 0.05,
            settle_s: 0.01,
            backlash_um: 2.0,
            max_steps_per_burst: 255,
        }
    }

    /// Validates everything and builds the integer configuration.
    pub fn build(&self) -> Result<DualStageConfig, DualStageError> {
        use DualStageError as E;
        let rate = self.coarse_rate_hz;
        if !(100.0..=10_000.0).contains(&rate) || !self.fine_rate_hz.is_finite() {
            return Err(E::Rates);
        }
        let ratio = self.fine_rate_hz / rate;
        let fine_ticks = libm::round(ratio);
        if !(1.0..=1000.0).contains(&fine_ticks) || (ratio - fine_ticks).abs() > 1e-9 {
            return Err(E::Rates);
        }
        let step_pm = positive_pm(self.step_um).ok_or(E::Resolution)?;
        let motor_count_pm = positive_pm(self.motor_count_um).ok_or(E::Resolution)?;
        let linear_count_pm = positive_pm(self.linear_count_um).ok_or(E::Resolution)?;

        let travel_pm = match (pm(self.travel_um.0), pm(self.travel_um.1)) {
            (Some(lo), Some(hi))
                if lo < hi && lo >= -1_000_000_000_000 && hi <= 1_000_000_000_000 =>
            {
                (lo, hi)
            }
            _ => return Err(E::Travel),
        };

        let per_tick = |um_s: f64| pm(um_s / rate);
        let per_tick2 = |um_s2: f64| pm(um_s2 / (rate * rate));
        let limits = |v: f64, a: f64| -> Result<MotionLimits, DualStageError> {
            let l = MotionLimits {
                velocity: per_tick(v).ok_or(E::MotionLimits)?,
                acceleration: per_tick2(a).ok_or(E::MotionLimits)?,
            };
            l.is_valid().then_some(l).ok_or(E::MotionLimits)
        };
        let move_limits = limits(self.move_velocity_um_s, self.move_acceleration_um_s2)?;
        let coarse_limits = limits(self.coarse_velocity_um_s, self.coarse_acceleration_um_s2)?;
        if move_limits.velocity > coarse_limits.velocity {
            return Err(E::MotionLimits);
        }
        let backlash = self.backlash_um / self.step_um;
        if !(0.0..=1000.0).contains(&backlash) {
            return Err(E::Backlash);
        }
        let backlash_steps = libm::round(backlash) as u16;
        // The fastest coarse tick plus a whole take-up must fit one burst... or at least the
        // cruise speed must: the take-up may spread over a few bursts.
        if coarse_limits.velocity / step_pm + 1 > self.max_steps_per_burst as i64 {
            return Err(E::BurstTooSmall);
        }
        let split = SplitCoefficients::new(self.split_hz, rate).ok_or(E::SplitBandwidth)?;

        let (lo, hi) = self.fine_range_um;
        let fine_mid_pm = pm((lo + hi) / 2.0).ok_or(E::FineRange)?;
        let fine_half_span_pm = pm((hi - lo) / 2.0)
            .filter(|&h| h > 0 && h <= 1_000_000_000)
            .ok_or(E::FineRange)?;
        let fine_centre_pm = pm(self.fine_centre_um).ok_or(E::FineRange)?;
        let fine_window_pm = positive_pm(self.fine_window_um).ok_or(E::FineRange)?;
        if fine_centre_pm - fine_window_pm < fine_mid_pm - fine_half_span_pm
            || fine_centre_pm + fine_window_pm > fine_mid_pm + fine_half_span_pm
        {
            return Err(E::FineRange);
        }

        let fine_step_pm = per_tick(self.fine_velocity_um_s)
            .filter(|&s| s > 0)
            .ok_or(E::Timing)?;
        let centring_deadband_pm = pm(self.centring_deadband_um)
            .filter(|&d| d >= 0 && d < fine_window_pm)
            .ok_or(E::Timing)?;
        let ticks = self.centring_time_s * rate;
        if !(ticks >= 1.0 && ticks.is_finite()) {
            return Err(E::Timing);
        }
        let centring_gain = libm::round((1i64 << 24) as f64 / ticks) as i64;
        let handover = self.handover_s * rate;
        if !(0.0..=1e6).contains(&handover) {
            return Err(E::Timing);
        }
        let carriage_alpha =
            CarriageTracker::alpha_from_f64(self.carriage_alpha).ok_or(E::Timing)?;
        let carriage_alpha_at_rest =
            CarriageTracker::alpha_from_f64(self.carriage_alpha_at_rest).ok_or(E::Timing)?;
        let settle = self.settle_s * rate;
        if !(0.0..=1e6).contains(&settle) {
            return Err(E::Timing);
        }
        Ok(DualStageConfig {
            carriage_alpha,
            carriage_alpha_at_rest,
            settle_ticks: libm::round(settle) as u32,
            fine_ticks: fine_ticks as u32,
            step_pm,
            motor_count_pm,
            linear_count_pm,
            travel_pm,
            move_limits,
            coarse_limits,
            split,
            fine_mid_pm,
            fine_half_span_pm,
            fine_centre_pm,
            fine_window_pm,
            fine_step_pm,
            centring_deadband_pm,
            centring_gain,
            handover_ticks: (libm::round(handover) as u32).max(1),
            backlash_steps,
            max_steps_per_burst: self.max_steps_per_burst,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_stage_builds_into_the_expected_integers() {
        let c = DualStageSettings::paper_stage().build().unwrap();
        assert_eq!(c.fine_ticks, 10);
        assert_eq!(c.step_pm, 312_500);
        assert_eq!(c.linear_count_pm, 5_000);
        assert_eq!(c.move_limits.velocity, 2_000_000); // 10 mm/s = 2 µm per 200 µs tick
        assert_eq!(c.move_limits.acceleration, 8_000); // 200 mm/s² = 8 nm per tick²
        assert_eq!(c.backlash_steps, 6);
        assert_eq!(c.handover_ticks, 100);
        assert_eq!(c.centring_gain, 67_109); // 2^24 / 250, rounded
    }

    #[test]
    fn every_bad_setting_is_refused_with_its_reason() {
        let ok = DualStageSettings::paper_stage();
        type Spoil = fn(&mut DualStageSettings);
        let cases: [(Spoil, DualStageError); 12] = [
            (|s| s.fine_rate_hz = 49_999.0, DualStageError::Rates),
            (|s| s.coarse_rate_hz = f64::NAN, DualStageError::Rates),
            (|s| s.step_um = 0.0, DualStageError::Resolution),
            (|s| s.linear_count_um = -1.0, DualStageError::Resolution),
            (|s| s.travel_um = (5.0, 5.0), DualStageError::Travel),
            (
                |s| s.move_velocity_um_s = 20_000.0,
                DualStageError::MotionLimits,
            ),
            (
                |s| s.coarse_acceleration_um_s2 = f64::INFINITY,
                DualStageError::MotionLimits,
            ),
            (|s| s.max_steps_per_burst = 5, DualStageError::BurstTooSmall),
            (|s| s.split_hz = 500.0, DualStageError::SplitBandwidth),
            (|s| s.fine_window_um = 45.0, DualStageError::FineRange),
            (|s| s.centring_time_s = 0.0, DualStageError::Timing),
            (|s| s.backlash_um = -1.0, DualStageError::Backlash),
        ];
        for (spoil, reason) in cases {
            let mut s = ok;
            spoil(&mut s);
            assert_eq!(s.build(), Err(reason), "{s:?}");
        }
    }
}
