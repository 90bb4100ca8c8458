//! Where the coarse task, the piezo tick and the command handler meet on the board: a
//! [`CoarseLink`] inside the control loop (attached in the dual-stage images), reached by each
//! through the tick's lock, a few stores at a time.
//!
//! * The **coarse task** (once per coarse period) first takes the handler's pending command
//!   and the piezo's position as the tick knows it
//!   ([`crate::control_loop::ControlLoop::take_coarse`]), runs its tick, then posts the
//!   piezo's setpoints for the coming period (a [`FineRamp`], prepared here — the one division
//!   is off the tick) and its status ([`crate::control_loop::ControlLoop::post_coarse`]). The
//!   first post makes the ramp the loop's setpoint source.
//! * The **piezo handed back** ([`CoarseLink::release_piezo`], the handler's
//!   `Request::CoarseRelease`, the axis at rest): the coarse task runs on (the encoders, the
//!   switches, the status; the carriage held where it is), but its posts carry only its status,
//!   and the piezo takes its setpoint from its own sources again. The next motion command the
//!   task takes (home, move, jog) engages the piezo again: the task is told where the piezo's
//!   setpoint is ([`CoarseTake::resume_fine`]), so its slope-limited ramp continues from there.
//! * The **piezo tick** takes its setpoint from the ramp ([`FineRamp::next_setpoint`]: an add and a
//!   compare, no division) instead of the setpoint stream, as it would from any other source,
//!   and stores nothing for the coarse task.
//! * The **command handler** validates a request against the latest status and the limits
//!   ([`super::CoarseLimits`]), answers at once, and leaves the command for the coarse task.

use super::controller::FineSetpoints;
use super::supervisor::{CoarseCommand, CoarseLimits, CoarseStatus, CoarseSupervisor};
use crate::board::{LimitSwitches, QuadratureEncoder, StepDir};

/// The coarse task's two exchanges with the control loop in a coarse period
/// ([`CoarseSupervisor::period`]): on the board each is one short lock of the control tick
/// (the firmware's `hardware::setup::CoarseStage::run`); on a bench or in the simulator, which
/// own the loop, a plain call ([`crate::control_loop::ControlLoop`] implements it).
pub trait LoopExchange {
    /// The handler's pending command and the piezo's position
    /// ([`crate::control_loop::ControlLoop::take_coarse`]).
    fn take(&mut self) -> CoarseTake;
    /// The period's fine setpoints and the status
    /// ([`crate::control_loop::ControlLoop::post_coarse`]).
    fn post(&mut self, fine: &FineSetpoints, status: CoarseStatus);
}

impl CoarseSupervisor {
    /// One coarse period as the firmware's coarse task runs it: the handler's pending command
    /// and the piezo's position taken from the control loop (`exchange`'s first call: one
    /// short lock of the tick on the board), the piezo engaged again from its setpoint where
    /// the command takes it back, the command (a refusal now — the state changed since the
    /// handler's check — leaves the status to say what the axis does), [`CoarseSupervisor::tick`],
    /// then the period's fine setpoints and the status posted (the second call). Without
    /// `measures_piezo` (the emulator, whose ADC reads nothing), the loop's reading is not
    /// taken: the task takes its own last fine setpoint. Returns the fine setpoints.
    ///
    /// The board, the simulator and the tick bench all run this, so the bench's cost of a
    /// coarse period is the firmware's (less the lock's `BASEPRI` writes and the timer's
    /// acknowledgement).
    pub fn period<S, M, L, W>(
        &mut self,
        (step_dir, motor, linear, switches): (&mut S, &mut M, &mut L, &mut W),
        exchange: &mut impl LoopExchange,
        measures_piezo: bool,
    ) -> FineSetpoints
    where
        S: StepDir,
        M: QuadratureEncoder,
        L: QuadratureEncoder,
        W: LimitSwitches,
    {
        let take = exchange.take();
        if let Some(q) = take.resume_fine {
            // The piezo comes back from its own sources: the fine ramp leaves from where they
            // left its setpoint.
            self.resume_fine_from(q);
        }
        if let Some(command) = take.command {
            let _ = self.command(command);
        }
        let measured = if measures_piezo { take.measured } else { None };
        let fine = self.tick(step_dir, motor, linear, switches, measured);
        exchange.post(&fine, self.status());
        fine
    }
}

/// The piezo's setpoint over one coarse period: a linear ramp from where the tick is to the
/// period's end value, one step per fine tick; it holds the end value if the next period's
/// ramp is late.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FineRamp {
    engaged: bool,
    /// Setpoint of the last tick, Q2.30.
    current: i32,
    /// End of the ramp, Q2.30.
    to: i32,
    /// Change per tick, Q2.30.
    step: i32,
    /// Ticks left.
    remaining: u32,
}

impl FineRamp {
    /// Not engaged: nothing posted yet (the loop takes its setpoint from another source).
    ///
    /// ```
    /// use twinstack::dual_stage::{FineRamp, FineSetpoints};
    /// let mut ramp = FineRamp::new();
    /// assert!(!ramp.is_engaged());
    /// ramp.post(0, &FineSetpoints { from: 0, to: 1000, ticks: 10 });
    /// assert_eq!(ramp.next_setpoint(), 100);
    /// ```
    pub const fn new() -> Self {
        Self {
            engaged: false,
            current: 0,
            to: 0,
            step: 0,
            remaining: 0,
        }
    }

    /// A new period's ramp, from the setpoint the tick uses now (`current`, Q2.30: the last
    /// ramp's, or the stream's before the first) to `fine.to` over `fine.ticks` ticks. Off the
    /// tick (it divides), but under the tick's lock: one 32-bit division (a hardware `SDIV`,
    /// not a 64-bit library call); a span beyond `i32` saturates, so its steps fall short and
    /// the last tick lands on `fine.to` all the same.
    pub fn post(&mut self, current: i32, fine: &FineSetpoints) {
        let from = if self.engaged { self.current } else { current };
        let ticks = fine.ticks.clamp(1, i32::MAX as u32);
        let span = fine.to.saturating_sub(from);
        self.step = span.checked_div(ticks as i32).unwrap_or(0);
        self.current = from;
        self.to = fine.to;
        self.remaining = ticks;
        self.engaged = true;
    }

    /// The setpoint of this tick (Q2.30; 0 before the first post). The last tick of a ramp
    /// lands on its end exactly.
    #[inline(always)]
    pub fn next_setpoint(&mut self) -> i32 {
        if self.remaining > 1 {
            self.remaining -= 1;
            self.current = self.current.saturating_add(self.step);
        } else {
            self.remaining = 0;
            self.current = self.to;
        }
        self.current
    }

    /// Whether a ramp has been posted.
    pub fn is_engaged(&self) -> bool {
        self.engaged
    }
}

/// A coarse task ready to attach to the control loop
/// ([`crate::control_loop::ControlLoop::attach_coarse`]): its limits, its status and its share
/// of each fine tick ([`crate::config::tick_budget::coarse_task_share`] at its coarse rate and
/// the loop's control rate), prepared off the tick's lock (the share's conversion and division
/// are not for a critical section).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PreparedCoarse {
    limits: CoarseLimits,
    status: CoarseStatus,
    share: u32,
}

impl PreparedCoarse {
    /// The task with `limits` and `status`, at the fine `control_rate_hz`.
    pub fn new(limits: CoarseLimits, status: CoarseStatus, control_rate_hz: u32) -> Self {
        let coarse_rate = if limits.coarse_rate_hz.is_finite() && limits.coarse_rate_hz > 0.0 {
            libm::ceil(limits.coarse_rate_hz).min(u32::MAX as f64) as u32
        } else {
            0
        };
        Self {
            limits,
            status,
            share: crate::config::tick_budget::coarse_task_share(coarse_rate, control_rate_hz),
        }
    }

    /// The task's share of each fine tick, cycles at 5 WS: what the tick budget charges
    /// while it is attached.
    pub fn share(&self) -> u32 {
        self.share
    }
}

/// What the coarse task takes from the loop at the start of its period
/// ([`crate::control_loop::ControlLoop::take_coarse`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CoarseTake {
    /// The handler's pending command, if any.
    pub command: Option<CoarseCommand>,
    /// Where the piezo is (Q2.30 of its controller's range): the sensor's last reading, or,
    /// while the piezo is handed back and has no sensor, its setpoint (it moves on its own
    /// then, and the carriage estimate must not follow it); `None` otherwise (the task takes
    /// its own last fine setpoint).
    pub measured: Option<i32>,
    /// Set when this command engages the piezo again after it was handed back: the piezo's
    /// setpoint now (Q2.30), for the task to continue its fine ramp from
    /// ([`crate::dual_stage::CoarseSupervisor::resume_fine_from`]).
    pub resume_fine: Option<i32>,
}

/// The coarse axis's mailbox in the control loop (see the module doc).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CoarseLink {
    ramp: FineRamp,
    command: Option<CoarseCommand>,
    status: CoarseStatus,
    limits: Option<CoarseLimits>,
    /// The coarse task's share of each fine tick, cycles
    /// ([`crate::config::tick_budget::coarse_task_share`]), 0 until attached.
    task_share: u32,
    /// The piezo is handed back ([`CoarseLink::release_piezo`]): posts carry the status only.
    released: bool,
}

impl CoarseLink {
    /// No coarse axis yet (the handler refuses coarse requests until the coarse task
    /// [`CoarseLink::attach`]es).
    ///
    /// ```
    /// use twinstack::dual_stage::CoarseLink;
    /// let mut link = CoarseLink::new();
    /// assert!(link.limits().is_none() && !link.is_attached());
    /// ```
    pub const fn new() -> Self {
        Self {
            ramp: FineRamp::new(),
            command: None,
            status: CoarseStatus {
                state: super::CoarseState::Unhomed,
                homed: false,
                faults: 0,
                switches: 0,
                position_pm: 0,
                setpoint_pm: 0,
                following_error_pm: 0,
                fine_setpoint: 0,
                ticks: 0,
            },
            limits: None,
            task_share: 0,
            released: false,
        }
    }

    /// The coarse task is there ([`PreparedCoarse`]: its limits, its status, and the share of
    /// each fine tick the tick budget charges while it is attached).
    pub fn attach(&mut self, task: &PreparedCoarse) {
        self.limits = Some(task.limits);
        self.status = task.status;
        self.task_share = task.share;
    }

    /// Whether a coarse task is attached.
    pub fn is_attached(&self) -> bool {
        self.limits.is_some()
    }

    /// The attached coarse task's share of each fine tick, cycles (0 without one).
    pub fn task_share(&self) -> u32 {
        self.task_share
    }

    /// The limits requests are validated against, `None` without a coarse axis.
    pub fn limits(&self) -> Option<CoarseLimits> {
        self.limits
    }

    /// The latest status (at most one coarse period old).
    pub fn status(&self) -> CoarseStatus {
        self.status
    }

    /// Leaves a validated command for the coarse task (replacing one it has not taken yet).
    pub fn request(&mut self, command: CoarseCommand) {
        self.command = Some(command);
    }

    /// The coarse task's side, first, once per period: the handler's pending command, taken
    /// (the loop adds the piezo's position: [`crate::control_loop::ControlLoop::take_coarse`]),
    /// and whether it engages the piezo again: a motion command (home, move, jog) taken while
    /// the piezo is handed back ends the hand-back, and the next post ramps from the setpoint
    /// the tick uses then.
    pub fn take(&mut self) -> (Option<CoarseCommand>, bool) {
        let engages = self.is_engaging();
        // Taken only when there is one: `Option::take` of the empty slot would still copy
        // its 56 bytes (a library `memcpy` on the coarse task's every period, under the
        // tick's lock).
        let command = if self.command.is_some() {
            self.command.take()
        } else {
            None
        };
        if engages {
            self.released = false;
            self.ramp = FineRamp::new();
        }
        (command, engages)
    }

    /// The coarse task's side, second: posts the period's fine setpoints (ramping from
    /// `current`, the tick's setpoint now) and the status after its tick; while the piezo is
    /// handed back, only the status. Returns whether the ramp was posted (the piezo follows
    /// the coarse axis).
    pub fn post(&mut self, current: i32, fine: &FineSetpoints, status: CoarseStatus) -> bool {
        self.status = status;
        if self.released {
            return false;
        }
        self.ramp.post(current, fine);
        true
    }

    /// Hands the piezo back to its own sources (the loop switches its source:
    /// [`crate::control_loop::ControlLoop::release_piezo`]): the task runs on, posting its
    /// status only, until it takes a motion command ([`CoarseLink::take`]).
    pub fn release_piezo(&mut self) {
        self.released = true;
        self.ramp = FineRamp::new();
    }

    /// Whether the piezo is handed back ([`CoarseLink::release_piezo`]).
    pub fn is_piezo_released(&self) -> bool {
        self.released
    }

    /// Whether a motion command waits for the task that will engage the piezo again when the
    /// task takes it: from the handler's acknowledgement on, the piezo is the coarse axis's.
    pub fn is_engaging(&self) -> bool {
        self.released && self.motion_pending()
    }

    /// Whether a motion command (home, move, jog) waits for the task to take it.
    pub fn motion_pending(&self) -> bool {
        self.command
            .is_some_and(|c| !matches!(c, CoarseCommand::Stop))
    }

    /// The coarse task gone (the loop handed the setpoint back to the stream): no limits, no
    /// share, and the next attached task's first post ramps from the setpoint the tick uses
    /// then, not from where this ramp was.
    pub fn release(&mut self) {
        // Field by field: a whole-struct assignment is a byte-wise copy of the status and
        // limits, hundreds of instructions under the tick's lock.
        self.limits = None;
        self.task_share = 0;
        self.command = None;
        self.released = false;
        self.ramp = FineRamp::new();
    }

    /// The tick's side: this tick's setpoint from the ramp ([`FineRamp::next_setpoint`]; the
    /// loop asks only once the coarse task has posted one).
    #[inline(always)]
    pub fn next_setpoint(&mut self) -> i32 {
        self.ramp.next_setpoint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_ramp_starts_where_the_tick_is_and_lands_on_the_end() {
        let mut r = FineRamp::new();
        assert!(!r.is_engaged());
        r.post(
            1000,
            &FineSetpoints {
                from: 0,
                to: 2003,
                ticks: 10,
            },
        );
        let v: [i32; 12] = core::array::from_fn(|_| r.next_setpoint());
        assert_eq!(v[0], 1100);
        assert_eq!(v[9], 2003);
        assert_eq!(v[11], 2003, "holds when the next ramp is late");
        for w in v.windows(2) {
            assert!((w[1] - w[0]).abs() <= 104);
        }
        // The next ramp starts from where this one is, not from the stream's setpoint.
        r.post(
            -5,
            &FineSetpoints {
                from: 0,
                to: 2003,
                ticks: 10,
            },
        );
        assert_eq!(r.next_setpoint(), 2003);
    }

    #[test]
    fn a_span_beyond_i32_saturates_and_still_lands_on_its_end() {
        let mut r = FineRamp::new();
        r.post(
            i32::MIN + 1,
            &FineSetpoints {
                from: 0,
                to: i32::MAX,
                ticks: 4,
            },
        );
        let v: [i32; 4] = core::array::from_fn(|_| r.next_setpoint());
        assert!(v.windows(2).all(|w| w[1] > w[0]), "{v:?}");
        assert_eq!(v[3], i32::MAX);
    }

    #[test]
    fn a_late_post_continues_from_the_held_value() {
        let mut r = FineRamp::new();
        let f = |to| FineSetpoints {
            from: 0,
            to,
            ticks: 4,
        };
        r.post(0, &f(400));
        for _ in 0..2 {
            r.next_setpoint();
        }
        // Posted early (the coarse period ran short): from 200, not from 400.
        r.post(0, &f(0));
        assert_eq!(r.next_setpoint(), 150);
    }
}
