//! The control tick: the one function the firmware's timer interrupt and the simulator both call.
//!
//! Read top to bottom, one tick is:
//!
//! 1. the next setpoint (Q2.30 normalised displacement; on underrun the last one is held);
//! 2. the compensator (inverse P–I, inverse Duhem, inverse Bouc–Wen, or none)
//!    turns it into a drive command (after the inverse creep, when the stage has creep:
//!    [`crate::models::creep`]); the learned correction is added ([`crate::services::learning`]) and, with input
//!    shaping, the sum goes through the feedforward's notch (not in bypass;
//!    [`ControlConfig::shaping`]);
//! 3. with a sensor, the reading is kept and, in closed loop, the PI(D) controller on the
//!    measured error adds its correction
//!    ([`crate::control::feedback`]); a mode switch's fading offset is added ([`crate::control::mode_switch`]);
//! 4. the differential drive clamps the command to the stacks' range and slew limits and splits
//!    it into both stacks' DAC codes (`u_l = ū + v`, `u_r = ū − v`), written at once;
//!
//! The forward observer is not in the tick: nothing in it needs the estimate (the feedback
//! acts on the sensor), and the observer only has to see every drive sample the stacks were
//! given, in order. It runs below the tick on the tick's snapshots, with its drift check
//! against the sensor ([`crate::services::observer`]); the tick's report carries the applied
//! drive and the measurement it needs.
//!
//! Configuration ([`ControlConfig`]) is built and validated off the tick path
//! ([`crate::config::settings::Settings::build`]) and prepared there ([`Controller::prepare`]); the tick
//! swaps it in O(1) ([`Controller::take_over`]). Nothing here allocates, panics or loops
//! without bound.
//!
//! The parts of the control law, each in its own module: [`sensor`] (the position sensor),
//! [`feedback`] (PI(D) with anti-windup, the drift check), [`notch`] (the resonance notch),
//! [`mode_switch`] (bumpless switching and reloads) and [`drive`] (the differential drive and
//! the limits that hold through everything).

pub mod drive;
pub mod feedback;
pub mod instant;
pub mod mode_switch;
pub mod notch;
pub mod preview;
pub mod sensor;

use crate::board::{AdcCode, DacCode, DualDac, SensorAdc};
use crate::control::drive::{DifferentialDrive, StackVoltages};
use crate::control::feedback::FeedbackState;
pub use crate::control::feedback::{Derivative, Feedback};
pub use crate::control::mode_switch::Mode;
use crate::control::mode_switch::{BumplessTransfer, ModeError};
use crate::control::notch::{Notch, NotchState};
use crate::control::preview::{Preview, PreviewLine};
pub use crate::control::sensor::Sensor;
use crate::fixed_point::clamp_full_scale;
use crate::models::creep::Creep;
pub use crate::models::{Compensator, Observer};
use crate::models::{CompensatorRun, ObserverRun};

/// The observer a preparation relaxed ([`Controller::prepare`]): the tick's form of the
/// configuration's forward model (and its creep), its state relaxed at the drive the stacks
/// hold, and its output there. The controller derives its compensator's state from it and
/// hands it out, so that the observer below the tick starts from the same state
/// ([`crate::services::observer::ObserverBelow::from_relaxed`]) without relaxing the model a
/// second time. Only a preparation makes one, so the state and its output always belong
/// together.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RelaxedObserver {
    /// The observer as the tick would run it, relaxed ([`ObserverRun::NONE`] without a model).
    pub(crate) run: ObserverRun,
    /// Its output there, Q2.30 normalised displacement (the drive itself without a model):
    /// the setpoint the controller is prepared at.
    pub(crate) output: i32,
}

/// Everything the tick needs, validated and in fixed point (built by
/// [`crate::config::settings::Settings::build`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ControlConfig {
    /// Feedforward compensator.
    pub compensator: Compensator,
    /// Forward observer.
    pub observer: Observer,
    /// The position sensor, if the stage has one: read once per tick in every mode.
    pub sensor: Option<Sensor>,
    /// Feedback on the sensor's error (closed loop).
    pub feedback: Option<Feedback>,
    /// The differential drive and its limits.
    pub drive: DifferentialDrive,
    /// The mode to run in (switch later with [`Controller::set_mode`]).
    pub mode: Mode,
    /// The stage's creep, in series after the hysteresis: inverted before the compensator's
    /// model, run after the observer's (not applied where there is no model).
    pub creep: Option<Creep>,
    /// Input shaping: a notch on the feedforward (the compensator's output plus the learned
    /// correction), before the range and slew limits, in every mode but bypass, so that the
    /// drive does not excite the stage's resonance ([`crate::config::settings::Settings::shaping`]).
    pub shaping: Option<Notch>,
    /// The preview: every setpoint shaped for the stage's resonance before the compensator,
    /// the feedback aiming at the setpoint itself, [`preview::PREVIEW_DELAY_TICKS`] ticks late
    /// ([`crate::control::preview`]; [`crate::config::settings::Settings::preview`]).
    pub preview: Option<Preview>,
}

/// Bit flags of what happened in one tick.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct TickFlags(pub u8);

impl TickFlags {
    /// No new setpoint: the last one was held.
    pub const UNDERRUN: u8 = 1 << 0;
    /// The range limit clipped the drive.
    pub const RANGE_LIMIT: u8 = 1 << 1;
    /// The slew limit clipped the drive.
    pub const SLEW_LIMIT: u8 = 1 << 2;
    /// The sensor ADC read failed (feedback held its integrator).
    pub const ADC_ERROR: u8 = 1 << 3;
    /// The DAC write failed.
    pub const DAC_ERROR: u8 = 1 << 4;
    /// The sensor and the observer disagree by more than the drift limit: the model has
    /// drifted from the stage (set by the drift check below the tick,
    /// [`crate::services::observer::ObserverBelow::observe`], not by the tick).
    pub const DRIFT: u8 = 1 << 5;
    /// A reload is settling: the drive is gliding from where the stacks were to the new
    /// command (a fading offset) under the stricter of the old and the new slew limit.
    pub const SETTLING: u8 = 1 << 6;

    /// Whether `flag` is set.
    pub fn contains(self, flag: u8) -> bool {
        self.0 & flag != 0
    }
}

/// What one tick did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TickReport {
    /// Left stack's DAC code.
    pub left: DacCode,
    /// Right stack's DAC code.
    pub right: DacCode,
    /// Observer's estimated displacement, Q2.30 normalised: 0 from the tick, filled in below
    /// it ([`crate::services::observer::ObserverBelow::observe`]).
    pub estimate: i32,
    /// Measured displacement, Q2.30 normalised (0 without a sensor); it is
    /// [`crate::control::feedback::SENSOR_DELAY_TICKS`] ticks older than `estimate`.
    pub measured: i32,
    /// Model-normalised drive applied, Q2.30.
    pub drive: i32,
    /// What happened.
    pub flags: TickFlags,
    /// The trigger outputs' levels and the trigger input's ([`crate::sources::scan`]: bit 0 pixel,
    /// 1 line, 2 frame, 3 input); 0 from the controller, set by the control loop.
    pub triggers: u8,
}

/// Counters of one controller since it was prepared (the control loop adds those of the
/// controllers before it); they wrap after 2^32 events.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ControlCounters {
    /// Ticks run.
    pub ticks: u32,
    /// Ticks without a new setpoint.
    pub underruns: u32,
    /// Ticks the range limit clipped.
    pub range_limits: u32,
    /// Ticks the slew limit clipped.
    pub slew_limits: u32,
    /// Failed ADC reads.
    pub adc_errors: u32,
    /// Failed DAC writes.
    pub dac_errors: u32,
}

impl ControlCounters {
    /// Counts what one tick's `flags` say happened (every counter but `ticks` is one flag's).
    #[inline(always)]
    pub fn count(&mut self, flags: TickFlags) {
        let f = flags.0;
        let add = |c: &mut u32, bit: u8| *c = c.wrapping_add(((f & bit) != 0) as u32);
        add(&mut self.underruns, TickFlags::UNDERRUN);
        add(&mut self.range_limits, TickFlags::RANGE_LIMIT);
        add(&mut self.slew_limits, TickFlags::SLEW_LIMIT);
        add(&mut self.adc_errors, TickFlags::ADC_ERROR);
        add(&mut self.dac_errors, TickFlags::DAC_ERROR);
    }

    /// Both counts added (wrapping).
    pub fn plus(self, o: Self) -> Self {
        Self {
            ticks: self.ticks.wrapping_add(o.ticks),
            underruns: self.underruns.wrapping_add(o.underruns),
            range_limits: self.range_limits.wrapping_add(o.range_limits),
            slew_limits: self.slew_limits.wrapping_add(o.slew_limits),
            adc_errors: self.adc_errors.wrapping_add(o.adc_errors),
            dac_errors: self.dac_errors.wrapping_add(o.dac_errors),
        }
    }
}

/// The controller: configuration plus every piece of state the tick keeps.
///
/// Its lifecycle keeps all heavy work off the tick: a new configuration is **prepared**
/// ([`Controller::prepare`]: models relaxed at the stacks' present voltages, their states
/// derived) in a spare controller by the low-priority task, then **swapped** in by the tick
/// in O(1) ([`Controller::take_over`]: the stacks' voltages, counters and slew limit carry
/// over). The stacks' voltages are remembered in board units, so the drive is continuous across
/// any reload; the first tick after a swap or a mode switch hands the difference between the
/// new command and the present drive to a fading offset ([`crate::control::mode_switch`]), and until
/// that has faded the slew limit is the stricter of the old and the new one.
#[derive(Clone, Debug)]
pub struct Controller {
    compensator: CompensatorRun,
    sensor: Option<Sensor>,
    feedback: Option<Feedback>,
    /// What the tick runs, from the mode and the parts present: one tag, one compare.
    run: Run,
    drive_limits: DifferentialDrive,
    mode: Mode,
    setpoint: i32,
    /// Where the stacks are, board units (the slew limiter's memory).
    stacks: StackVoltages,
    /// The slew step in force (stricter while a reload or mode switch settles).
    slew: i32,
    /// The next tick starts a transfer from the present drive to the new command.
    rebase: bool,
    /// A reload is settling: the stricter slew limit is in force until the transfer fades.
    reloading: bool,
    /// The drive the stacks held at the swap, in this configuration's normalisation (the
    /// transfer's starting point; computed by [`Controller::take_over`], off the tick).
    held: i32,
    /// The observer's displacement with the drive at rest (the underrun ramp's target).
    rest_setpoint: i32,
    feedback_state: FeedbackState,
    transfer: BumplessTransfer,
    counters: ControlCounters,
    /// The learned correction for this tick, Q2.30 normalised drive, added to the feedforward
    /// ([`crate::services::learning`]; set by the control loop before each tick, 0 without learning).
    learned: i32,
    /// The feedforward's notch ([`ControlConfig::shaping`]).
    shaping: Option<Notch>,
    /// Its memory, Q2.30 normalised drive: settled at the drive the stacks hold when the
    /// configuration is prepared, and at the feedforward of the first tick after a swap or a
    /// mode switch (whose transfer then starts from the drive held, as without shaping).
    shaping_state: NotchState,
    /// The preview ([`ControlConfig::preview`]).
    preview: Option<Preview>,
    /// Its line of the last setpoints, Q2.30.
    preview_line: PreviewLine,
}

/// What the sensor step does this mode.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Run {
    /// Closed loop, PI only (no derivative, no notch).
    ClosedPi,
    /// Closed loop with a derivative or a notch.
    Closed,
    /// A sensor, read for the recorder and the drift check only.
    Monitor,
    /// No sensor.
    Blind,
}

impl Run {
    fn of(mode: Mode, sensor: &Option<Sensor>, feedback: &Option<Feedback>) -> Self {
        match (sensor, feedback, mode) {
            (None, _, _) => Run::Blind,
            (Some(_), Some(fb), Mode::ClosedLoop)
                if fb.notch.is_none() && fb.derivative.is_none() =>
            {
                Run::ClosedPi
            }
            (Some(_), Some(_), Mode::ClosedLoop) => Run::Closed,
            (Some(_), _, _) => Run::Monitor,
        }
    }
}

impl Controller {
    /// A controller on `config`, with the stacks in the configuration's safe state (where the
    /// board's DAC starts): the models relaxed there, the setpoint where the observer puts the
    /// stage.
    ///
    /// ```
    /// use twinstack::control::Controller;
    /// use twinstack::config::settings::{Hardware, Settings};
    /// let config = Settings::default().build(&Hardware::driver_board(50_000.0)).unwrap();
    /// let c = Controller::new(config);
    /// assert_eq!(c.stacks(), config.drive.safe_stacks());
    /// ```
    pub fn new(config: ControlConfig) -> Self {
        let mut c = Self {
            compensator: CompensatorRun::NONE,
            sensor: None,
            feedback: None,
            run: Run::Blind,
            drive_limits: config.drive,
            mode: Mode::Bypass,
            setpoint: 0,
            stacks: StackVoltages::default(),
            slew: 1,
            rebase: false,
            reloading: false,
            held: 0,
            rest_setpoint: 0,
            feedback_state: FeedbackState::default(),
            transfer: BumplessTransfer::default(),
            counters: ControlCounters::default(),
            learned: 0,
            shaping: None,
            shaping_state: NotchState::default(),
            preview: None,
            preview_line: PreviewLine::at(0),
        };
        c.prepare(config, config.drive.safe_stacks());
        c
    }

    /// Prepares this controller to take over on `config` with the stacks at `stacks` (board
    /// units; the running controller's [`Controller::stacks`]): the models at rest at the
    /// drive those voltages amount to (within the new limits; on their loop's ascending branch
    /// for the single-ended stack, relaxed for the differential pair:
    /// [`crate::control::drive::Configuration::rest`]), the compensator's state derived
    /// from the observer's, the setpoint where the observer puts the stage. This is the heavy
    /// part of a reload (thousands of instructions for a large P–I): it runs in the
    /// low-priority task, never in the tick. Returns the observer it relaxed, for the
    /// observer below the tick to start from ([`RelaxedObserver`]).
    pub fn prepare(&mut self, config: ControlConfig, stacks: StackVoltages) -> RelaxedObserver {
        let d = &config.drive;
        let drive = d.drive_of(stacks.left);
        // The observer relaxed at the drive the stacks hold; the compensator's state from the
        // observer's where it inverts the observer's model, otherwise relaxed where the
        // observer puts the stage. With creep, its modes settled where the models are relaxed:
        // at the observer's output (which is also the setpoint), so it passes that through.
        let rest = d.rest();
        let (observer, y) = config.observer.prepare(config.creep, drive, rest);
        let compensator = config
            .compensator
            .prepare(&observer, config.creep, drive, y, rest);
        let rest_setpoint = config.observer.output_at_rest(d.rest_drive(), rest);
        // The observer runs below the tick ([`crate::services::observer`]): this one prepared
        // the compensator's state and is handed out for it, relaxed once.
        *self = Self {
            compensator,
            sensor: config.sensor,
            feedback: config.feedback,
            run: Run::of(config.mode, &config.sensor, &config.feedback),
            drive_limits: config.drive,
            mode: config.mode,
            setpoint: y,
            stacks,
            slew: d.slew(),
            rebase: false,
            reloading: false,
            held: drive,
            rest_setpoint,
            feedback_state: FeedbackState::at_rest(y),
            transfer: BumplessTransfer::default(),
            counters: ControlCounters::default(),
            learned: 0,
            shaping: config.shaping,
            // Settled at the drive held: the shaped feedforward starts where the stacks are.
            shaping_state: Notch::state_at(drive),
            preview: config.preview,
            // As if the setpoint had been held: the preview passes it as it is.
            preview_line: PreviewLine::at(y),
        };
        RelaxedObserver {
            run: observer,
            output: y,
        }
    }

    /// Takes over from `old` between two ticks, in O(1): the stacks' voltages and the stricter
    /// of the two slew limits carry over, and the next tick starts from the drive the stacks
    /// hold. (Counters stay with each controller; the control loop adds them up off the tick.)
    #[inline(always)]
    pub fn take_over(&mut self, old: &Controller) {
        self.stacks = old.stacks;
        self.held = self.drive_limits.drive_of(old.stacks.left);
        self.slew = self.drive_limits.slew().min(old.slew);
        self.rebase = true;
        self.reloading = true;
        // The preview goes on from the setpoints given, or starts as if the one in force had
        // been held.
        self.preview_line = if old.preview.is_some() {
            old.preview_line
        } else {
            PreviewLine::at(old.setpoint)
        };
    }

    /// Switches between bypass, open loop and closed loop between two ticks, in O(1) and
    /// without a bump in the drive (see [`crate::control::mode_switch`]). Refused, changing nothing,
    /// when the configuration lacks what the mode needs.
    pub fn set_mode(&mut self, mode: Mode) -> Result<(), ModeError> {
        match mode {
            Mode::OpenLoop if self.compensator.is_bypass() => return Err(ModeError::NoCompensator),
            Mode::ClosedLoop if self.sensor.is_none() || self.feedback.is_none() => {
                return Err(ModeError::NoSensor)
            }
            _ => {}
        }
        if mode == self.mode {
            return Ok(());
        }
        if mode == Mode::ClosedLoop {
            self.feedback_state.enter_closed_loop(self.setpoint);
        }
        self.held = self.drive_limits.drive_of(self.stacks.left);
        self.mode = mode;
        self.run = Run::of(mode, &self.sensor, &self.feedback);
        self.rebase = true;
        Ok(())
    }

    /// The mode in effect.
    pub fn mode(&self) -> Mode {
        self.mode
    }

    /// The feedback's memory (integrator, drift filter, last measurement).
    pub fn feedback_state(&self) -> &FeedbackState {
        &self.feedback_state
    }

    /// The setpoint in force (the last one given, or held), Q2.30 normalised displacement:
    /// where a setpoint source goes on from.
    pub fn setpoint(&self) -> i32 {
        self.setpoint
    }

    /// The setpoint the last tick aimed the stage at (Q2.30): the setpoint in force, or with
    /// the preview the one given [`preview::PREVIEW_DELAY_TICKS`] ticks before it — what a
    /// measurement is compared with.
    #[inline(always)]
    pub fn target(&self) -> i32 {
        if self.preview.is_some() {
            self.preview_line.target()
        } else {
            self.setpoint
        }
    }

    /// Where the stage is, as well as the tick knows it after the last tick (Q2.30
    /// normalised): the sensor's last reading, else the setpoint in force (what a sequence's
    /// settle window is checked against; the observer's estimate is computed below the tick).
    #[inline(always)]
    pub fn position(&self) -> i32 {
        if self.sensor.is_some() {
            self.feedback_state.measured
        } else {
            self.setpoint
        }
    }

    /// The rest position: the observer's displacement with the drive at rest (the bias),
    /// Q2.30 normalised (the drive itself without an observer). Computed when the
    /// configuration was prepared.
    pub fn rest_setpoint(&self) -> i32 {
        self.rest_setpoint
    }

    /// Where the stacks are now, board units.
    pub fn stacks(&self) -> StackVoltages {
        self.stacks
    }

    /// The slew step in force, Q17.15 codes per tick.
    pub fn slew(&self) -> i32 {
        self.slew
    }

    /// The sensor's configuration, if there is a sensor.
    pub fn sensor_config(&self) -> Option<&Sensor> {
        self.sensor.as_ref()
    }

    /// The feedback's configuration, if any.
    pub fn feedback_config(&self) -> Option<&Feedback> {
        self.feedback.as_ref()
    }

    /// The drive and its limits.
    pub fn drive_config(&self) -> &DifferentialDrive {
        &self.drive_limits
    }

    /// Counters since this controller was prepared.
    pub fn counters(&self) -> ControlCounters {
        self.counters
    }

    /// Hands the counters over (for the control loop's totals) and starts them again at zero.
    pub fn take_counters(&mut self) -> ControlCounters {
        core::mem::take(&mut self.counters)
    }

    /// Sets the learned correction the next ticks add to the feedforward (Q2.30 normalised
    /// drive; [`crate::services::learning`]): it goes through the same range and slew limits as the
    /// rest of the command. O(1).
    #[inline(always)]
    pub fn set_learned(&mut self, correction: i32) {
        self.learned = correction;
    }

    /// DAC codes of the safe state, for the fault handlers.
    pub fn safe_codes(&self) -> (DacCode, DacCode) {
        self.drive_limits.safe_codes()
    }

    /// One control tick (see the module doc). `setpoint` is the next desired displacement
    /// (Q2.30 normalised), `None` on underrun. Reads the sensor (when there is one), writes
    /// both DAC channels at once, and reports what it did.
    #[inline(always)]
    pub fn tick<D: DualDac, A: SensorAdc>(
        &mut self,
        setpoint: Option<i32>,
        adc: &mut A,
        dac: &mut D,
    ) -> TickReport {
        self.tick_io(setpoint, &mut SplitIo { adc, dac })
    }

    /// [`Controller::tick`] for a board that is both the DAC and the ADC (the simulated
    /// board): same code, one borrow.
    #[inline(always)]
    pub fn tick_board<B: DualDac + SensorAdc>(
        &mut self,
        setpoint: Option<i32>,
        board: &mut B,
    ) -> TickReport {
        self.tick_io(setpoint, &mut JointIo(board))
    }

    #[inline(always)]
    fn tick_io<IO: TickIo>(&mut self, setpoint: Option<i32>, io: &mut IO) -> TickReport {
        // Flags and counters are touched only on the paths where something happened: the
        // common tick pays for none of them.
        let mut flags = 0u8;
        self.counters.ticks = self.counters.ticks.wrapping_add(1);

        // 1. Setpoint.
        match setpoint {
            Some(s) => self.setpoint = clamp_full_scale(s),
            None => flags |= TickFlags::UNDERRUN,
        }
        // With the preview, the feedback aims at the setpoint of four ticks ago and the
        // compensator is given it shaped for the resonance.
        let (target, shaped) = match &self.preview {
            Some(p) => p.step(&mut self.preview_line, self.setpoint),
            None => (self.setpoint, self.setpoint),
        };

        // 2. Feedforward. The compensator runs in every mode (in bypass on the setpoint, its
        // output unused), so that a switch into open loop finds its state current; with creep,
        // the inverse creep first (setpoint → C⁻¹ → H⁻¹).
        let compensated = self.compensator.step(shaped);
        // With shaping, the feedforward (the compensator's output plus the learned
        // correction) goes through the notch, in every mode but bypass: Q2.30 normalised drive.
        let feedforward = if self.mode == Mode::Bypass {
            target.saturating_add(self.learned)
        } else {
            let ff = compensated.saturating_add(self.learned);
            match &self.shaping {
                Some(n) => {
                    // The first tick after a swap or a mode switch starts the notch settled
                    // at its input (four stores): the notch adds no transient of its own, and
                    // the transfer below glides from the drive held exactly as without it.
                    if self.rebase {
                        self.shaping_state = Notch::state_at(ff);
                    }
                    n.step(&mut self.shaping_state, ff)
                }
                None => ff,
            }
        };

        // 3. Sensor: drift check, and in closed loop the feedback correction.
        let fs = &mut self.feedback_state;
        let (command, measured) = match (&self.run, &self.sensor, &self.feedback) {
            (Run::ClosedPi, Some(sn), Some(fb)) => {
                sense::<_, true, false>(sn, Some(fb), fs, io, target, feedforward, &mut flags)
            }
            (Run::Closed, Some(sn), Some(fb)) => {
                sense::<_, true, true>(sn, Some(fb), fs, io, target, feedforward, &mut flags)
            }
            (Run::Monitor, Some(sn), _) => {
                sense::<_, false, false>(sn, None, fs, io, target, feedforward, &mut flags)
            }
            _ => (feedforward, 0),
        };

        // 4. After a swap or a mode switch: continue from the drive the stacks hold, and glide
        // to the new command under the stricter slew limit until the offset has faded.
        let mut settling = self.transfer.remaining() != 0;
        if self.rebase {
            self.rebase = false;
            settling = true;
            self.transfer.start(self.held.saturating_sub(command));
        }
        let command = if settling {
            if self.reloading {
                flags |= TickFlags::SETTLING;
            }
            self.transfer.apply(command)
        } else {
            command
        };

        // 5. Limits, split, both DACs at once.
        let out = self.drive_limits.split(command, self.stacks, self.slew);
        self.stacks = out.stacks;
        if settling && self.transfer.remaining() == 0 {
            // Settled: the configured slew limit from the next tick on.
            self.slew = self.drive_limits.slew();
            self.reloading = false;
        }
        if out.range_limited {
            flags |= TickFlags::RANGE_LIMIT;
        }
        if out.slew_limited {
            flags |= TickFlags::SLEW_LIMIT;
        }
        if io.write(out.left, out.right).is_err() {
            flags |= TickFlags::DAC_ERROR;
        }
        // The counters, from the flags, in one place (a tick with nothing to count pays one
        // compare).
        if flags & !TickFlags::SETTLING != 0 {
            self.counters.count(TickFlags(flags));
        }
        // What the limits cut, kept for the next tick's anti-windup.
        self.feedback_state.limited(command, out.applied);
        TickReport {
            left: out.left,
            right: out.right,
            estimate: 0,
            measured,
            drive: out.applied,
            flags: TickFlags(flags),
            triggers: 0,
        }
    }
}

/// The tick's sensor step: reads the sensor, runs the drift check and, when `CLOSED`, adds
/// the feedback correction to `feedforward` (with the derivative and notch when `FULL`, else
/// the PI alone). Returns the command and the measurement.
#[inline(always)]
fn sense<IO: TickIo, const CLOSED: bool, const FULL: bool>(
    sensor: &Sensor,
    fb: Option<&Feedback>,
    fs: &mut FeedbackState,
    io: &mut IO,
    target: i32,
    feedforward: i32,
    flags: &mut u8,
) -> (i32, i32) {
    match io.read() {
        Ok(code) => {
            let measured = sensor.displacement(code);
            fs.measured = measured;
            let command = match (CLOSED, fb) {
                (true, Some(fb)) => {
                    feedforward.saturating_add(fb.correction_with::<FULL>(fs, target, measured))
                }
                _ => feedforward,
            };
            (command, measured)
        }
        Err(_) => {
            *flags |= TickFlags::ADC_ERROR;
            let command = match (CLOSED, fb) {
                (true, Some(fb)) => feedforward.saturating_add(fb.held_correction(fs, target)),
                _ => feedforward,
            };
            (command, 0)
        }
    }
}

/// The tick's access to the converters, whether they are two objects or one.
trait TickIo {
    fn read(&mut self) -> Result<AdcCode, ()>;
    fn write(&mut self, left: DacCode, right: DacCode) -> Result<(), ()>;
}

struct SplitIo<'a, A, D> {
    adc: &'a mut A,
    dac: &'a mut D,
}

impl<A: SensorAdc, D: DualDac> TickIo for SplitIo<'_, A, D> {
    #[inline(always)]
    fn read(&mut self) -> Result<AdcCode, ()> {
        self.adc.read().map_err(|_| ())
    }
    #[inline(always)]
    fn write(&mut self, left: DacCode, right: DacCode) -> Result<(), ()> {
        self.dac.write_both(left, right).map_err(|_| ())
    }
}

struct JointIo<'a, B>(&'a mut B);

impl<B: SensorAdc + DualDac> TickIo for JointIo<'_, B> {
    #[inline(always)]
    fn read(&mut self) -> Result<AdcCode, ()> {
        self.0.read().map_err(|_| ())
    }
    #[inline(always)]
    fn write(&mut self, left: DacCode, right: DacCode) -> Result<(), ()> {
        self.0.write_both(left, right).map_err(|_| ())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::board::fakes::{FixedAdc, RecordingDac};
    use crate::board::Hardware;
    use crate::config::settings::{
        representative_duhem, representative_pi, FeedbackSettings, Settings,
    };
    use crate::fixed_point::{signal_from_f64, signal_to_f64};
    use crate::services::observer::Observed;

    fn hw() -> Hardware {
        Hardware {
            dac_full_scale: 65535,
            sensor_adc_bits: Some(16),
            ..Hardware::driver_board(50_000.0)
        }
    }

    fn bypass() -> Controller {
        let s = Settings {
            ranges: crate::Scaling::new(0.0, 140.0, 0.0, 10.0).unwrap(),
            sensor: None,
            ..Settings::default()
        };
        Controller::new(s.build(&hw()).unwrap())
    }

    fn volts(code: DacCode) -> f64 {
        code.0 as f64 / 65535.0 * 150.0
    }

    #[test]
    fn differential_split_mirrors_the_stacks_about_the_bias() {
        let mut c = bypass();
        let mut dac = RecordingDac::default();
        for &y in &[-0.5, 0.0, 0.3, 0.9] {
            // Slew allows 40 V per tick: enough ticks to arrive.
            for _ in 0..20 {
                c.tick(Some(signal_from_f64(y)), &mut FixedAdc(None), &mut dac);
            }
            let (l, r) = (volts(dac.left), volts(dac.right));
            assert!((l + r - 140.0).abs() < 0.01, "u_l + u_r = 2ū: {l} + {r}");
            assert!((l - (70.0 + 70.0 * y)).abs() < 0.01, "u_l = ū + v: {l}");
        }
    }

    #[test]
    fn underrun_holds_the_last_setpoint_and_is_counted() {
        let mut c = bypass();
        let mut dac = RecordingDac::default();
        for _ in 0..10 {
            c.tick(Some(signal_from_f64(0.5)), &mut FixedAdc(None), &mut dac);
        }
        let held = dac.left;
        let r = c.tick(None, &mut FixedAdc(None), &mut dac);
        assert!(r.flags.contains(TickFlags::UNDERRUN));
        assert_eq!(dac.left, held);
        assert_eq!(c.counters().underruns, 1);
        assert_eq!(c.counters().ticks, 11);
        assert_eq!(dac.writes, 11, "every tick writes both DACs once");
    }

    #[test]
    fn range_and_slew_limits_hold_whatever_arrives() {
        let mut s = Settings {
            ranges: crate::Scaling::new(0.0, 140.0, 0.0, 10.0).unwrap(),
            sensor: None,
            ..Settings::default()
        };
        s.drive.min_voltage = 10.0;
        s.drive.max_voltage = 130.0;
        s.drive.slew_rate = 50_000.0; // 1 V per tick
        let mut c = Controller::new(s.build(&hw()).unwrap());
        let mut dac = RecordingDac::default();
        let mut prev = (70.0, 70.0);
        let mut seed = 12345u32;
        for i in 0..5000 {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let sp = if i % 7 == 0 { None } else { Some(seed as i32) };
            let r = c.tick(sp, &mut FixedAdc(None), &mut dac);
            let (l, rv) = (volts(r.left), volts(r.right));
            for v in [l, rv] {
                assert!((10.0 - 0.01..=130.0 + 0.01).contains(&v), "range: {v}");
            }
            assert!((l - prev.0).abs() <= 1.0 + 0.01 && (rv - prev.1).abs() <= 1.0 + 0.01);
            prev = (l, rv);
        }
        assert!(c.counters().range_limits > 0 && c.counters().slew_limits > 0);
    }

    #[test]
    fn a_fresh_controller_holds_the_safe_state() {
        let c = bypass();
        let (l, r) = c.safe_codes();
        assert!((volts(l) - 70.0).abs() < 0.01 && l == r);
        let mut s = Settings {
            sensor: None,
            ..Settings::default()
        };
        s.drive.safe_state = crate::control::drive::SafeState::Zero;
        let mut c = Controller::new(s.build(&hw()).unwrap());
        assert_eq!(c.safe_codes(), (DacCode(0), DacCode(0)));
        // It starts where the DAC starts (the safe state): the left stack stays at 0 V, the
        // right one moves to its mirror (140 V) at the slew limit, never in one step.
        assert_eq!(c.stacks(), crate::control::drive::StackVoltages::default());
        let mut dac = RecordingDac::default();
        let mut last = 0.0;
        for _ in 0..10 {
            c.tick(None, &mut FixedAdc(None), &mut dac);
            assert_eq!(dac.left, DacCode(0));
            assert!(
                volts(dac.right) - last <= 40.01,
                "{last} → {}",
                volts(dac.right)
            );
            last = volts(dac.right);
        }
        assert!((last - 140.0).abs() < 0.01);
    }

    /// A mode switch and a reload each cost the tick O(1) work and move neither stack by
    /// more than the slew limit; the drive continues from where the stacks are.
    /// Every model starts where the drive's configuration leaves the stage at rest: single
    /// ended on its loop's ascending branch, the differential pair relaxed — the observer's
    /// estimate (the boot setpoint) is the model's output there, and the two differ.
    #[test]
    fn the_models_start_where_the_drive_configuration_leaves_the_stage() {
        use crate::control::drive::Configuration;
        use crate::models::{Forward, Rest};
        for model in [
            representative_pi(16).unwrap(),
            crate::config::settings::representative_gpi(16).unwrap(),
            representative_duhem(),
            crate::config::settings::representative_bouc_wen(),
        ] {
            let mut starts = [0; 2];
            for (start, (configuration, rest)) in starts.iter_mut().zip([
                (Configuration::Unidirectional, Rest::Ascending),
                (Configuration::Differential, Rest::Relaxed),
            ]) {
                let mut s = Settings {
                    compensator: Some(model.clone()),
                    observer: Some(model.clone()),
                    ..Settings::default()
                };
                s.drive.configuration = configuration;
                let config = s.build(&hw()).unwrap();
                let c = Controller::new(config);
                let u = config.drive.drive_of(config.drive.safe_stacks().left);
                let want = match config.observer {
                    Observer::Pi(m) => Forward::at_rest(&m, u, rest).1,
                    Observer::GeneralisedPi(m) => Forward::at_rest(&m, u, rest).1,
                    Observer::Duhem(m) => Forward::at_rest(&m, u, rest).1,
                    Observer::BoucWen(m) => Forward::at_rest(&m, u, rest).1,
                    Observer::None => unreachable!("an observer was given"),
                };
                assert_eq!(c.setpoint(), want, "{configuration:?}, {model:?}");
                assert_eq!(config.drive.rest(), rest);
                *start = want;
            }
            assert!(
                (starts[0] - starts[1]).abs() > 1 << 20,
                "the two rests differ: {starts:?}, {model:?}"
            );
        }
    }

    #[test]
    fn mode_switches_and_swaps_continue_from_the_present_drive() {
        let mut s = Settings {
            compensator: Some(representative_pi(16).unwrap()),
            observer: Some(representative_duhem()),
            feedback: Some(FeedbackSettings::pi(0.2, 500.0, 0.1)),
            ..Settings::default()
        };
        s.drive.slew_rate = 1.0e5; // 2 V per tick
        let config = s.build(&hw()).unwrap();
        let mut c = Controller::new(config);
        let mut adc = FixedAdc(Some(crate::board::AdcCode(30000)));
        let mut dac = RecordingDac::default();
        let mut last = (dac.left, dac.right);
        let step_ok = |a: (DacCode, DacCode), b: (DacCode, DacCode)| {
            (volts(a.0) - volts(b.0)).abs() <= 2.01 && (volts(a.1) - volts(b.1)).abs() <= 2.01
        };
        for k in 0..3000 {
            if k == 500 {
                c.set_mode(Mode::OpenLoop).unwrap();
            }
            if k == 1000 {
                c.set_mode(Mode::ClosedLoop).unwrap();
            }
            if k == 1500 {
                // A reload onto other ranges and a lower bias.
                let mut t = s.clone();
                t.ranges = crate::Scaling::new(0.0, 150.0, -5.0, 80.0).unwrap();
                t.drive.bias = 50.0;
                t.drive.max_voltage = 100.0;
                t.mode = Mode::ClosedLoop;
                let mut next = Controller::new(t.build(&hw()).unwrap());
                next.prepare(t.build(&hw()).unwrap(), c.stacks());
                next.take_over(&c);
                c = next;
            }
            let sp = signal_from_f64(0.6 * libm::sin(k as f64 * 0.01));
            c.tick(Some(sp), &mut adc, &mut dac);
            let now = (dac.left, dac.right);
            if k > 0 {
                assert!(step_ok(last, now), "tick {k}: {last:?} → {now:?}");
            }
            last = now;
        }
        assert_eq!(c.mode(), Mode::ClosedLoop);
        assert_eq!(
            c.counters().ticks,
            1500,
            "each controller counts its own ticks"
        );
        let top = volts(dac.left).max(volts(dac.right));
        assert!(top <= 100.01, "within the new limits once settled: {top}");
    }

    /// Every counter is the number of ticks whose report carried its flag; the tick never
    /// flags drift (its check runs below the tick, with the observer).
    #[test]
    fn the_counters_are_the_flags_counted() {
        let mut s = Settings {
            compensator: Some(representative_pi(8).unwrap()),
            observer: Some(representative_duhem()),
            feedback: Some(FeedbackSettings::pi(0.5, 2000.0, 0.3)),
            mode: Mode::ClosedLoop,
            ..Settings::default()
        };
        s.sensor.as_mut().unwrap().drift_limit = Some(0.01);
        s.drive.slew_rate = 2.0e5;
        let mut c = Controller::new(s.build(&hw()).unwrap());
        let mut dac = RecordingDac::default();
        let mut seen = [0u32; 8];
        let mut seed = 7u32;
        for k in 0..4000 {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let sp = (k % 5 != 0).then_some(seed as i32 >> 1);
            let mut adc = FixedAdc((k % 11 != 0).then_some(crate::board::AdcCode(seed >> 16)));
            let r = c.tick(sp, &mut adc, &mut dac);
            for (bit, n) in seen.iter_mut().enumerate() {
                *n += (r.flags.0 >> bit) as u32 & 1;
            }
        }
        let k = c.counters();
        assert_eq!(k.ticks, 4000);
        assert_eq!(
            [
                k.underruns,
                k.range_limits,
                k.slew_limits,
                k.adc_errors,
                k.dac_errors,
            ],
            [seen[0], seen[1], seen[2], seen[3], seen[4]]
        );
        assert_eq!(seen[5], 0, "the tick flagged drift");
        assert!(
            seen[..5].iter().filter(|&&n| n > 0).count() >= 4,
            "{seen:?}"
        );
    }

    fn creep_open_loop(creep: bool) -> Settings {
        let mut s = Settings {
            compensator: Some(representative_pi(8).unwrap()),
            observer: Some(representative_pi(8).unwrap()),
            sensor: None,
            mode: Mode::OpenLoop,
            creep: creep.then(|| {
                crate::models::creep::CreepParams::new(&[1e-3, 1e-2], &[0.05, 0.05]).unwrap()
            }),
            ..Settings::default()
        };
        s.drive.slew_rate = 1.0e7; // 200 V per tick: never limits
        s
    }

    /// With creep, the compensator runs the inverse creep before the inverse model and the
    /// observer the creep after the model: on a step the drive overshoots and relaxes round
    /// by round of the modes' turns (the late part of the stage's response is pre-empted),
    /// while the estimate follows the setpoint. Without creep the drive steps once and stays.
    #[test]
    fn creep_runs_in_series_with_the_compensator_and_the_observer() {
        for creep in [false, true] {
            // The tick and the observer below it.
            let mut c = Observed::new(creep_open_loop(creep).build(&hw()).unwrap());
            let mut dac = RecordingDac::default();
            let sp = signal_from_f64(0.4);
            let mut drives = [0i32; 3000];
            for (k, d) in drives.iter_mut().enumerate() {
                let r = c.tick(Some(sp), &mut FixedAdc(None), &mut dac);
                *d = r.drive;
                // Within one LSB16 (2^15 in Q2.30): the P–I banks run on a Q1.15 grid.
                if k > 2 {
                    assert!(
                        (r.estimate - sp).abs() < 1 << 15,
                        "creep {creep}, tick {k}: estimate {} vs {sp}",
                        r.estimate
                    );
                }
            }
            let settled = drives[2999];
            let overshoot = signal_to_f64(drives[3]) - signal_to_f64(settled);
            if creep {
                // 10 % arrives late: the first drive is about 10 % of the step further.
                assert!(overshoot > 0.02, "{overshoot}");
                // The two modes take turns (τ ≥ 40 ticks): each round of two ticks relaxes,
                // one mode a tick.
                let round = |r: &[i32]| r.iter().map(|&d| d as i64).sum::<i64>();
                let rounds = drives[3..].chunks_exact(2);
                assert!(rounds
                    .clone()
                    .zip(rounds.skip(1))
                    .all(|(a, b)| round(b) <= round(a)));
            } else {
                assert_eq!(drives[3], settled);
            }
        }
    }

    /// A reload re-prepares the creep at rest where the models are relaxed (at the setpoint
    /// the new controller starts from): holding that setpoint, the new controller does what
    /// the same configuration without creep, prepared at the same stacks, does (the creep adds
    /// no transient of its own), and the drive glides on from where it was.
    #[test]
    fn a_reload_with_creep_continues_where_the_stage_is() {
        let sp = signal_from_f64(-0.3);
        let with = creep_open_loop(true).build(&hw()).unwrap();
        let without = creep_open_loop(false).build(&hw()).unwrap();
        let mut c = Observed::new(with);
        let mut dac = RecordingDac::default();
        let mut before = c.tick(Some(sp), &mut FixedAdc(None), &mut dac);
        for _ in 0..20_000 {
            before = c.tick(Some(sp), &mut FixedAdc(None), &mut dac);
        }
        let after = |config: ControlConfig| -> [TickReport; 50] {
            let mut next = c.clone();
            next.reload(config);
            let mut dac = RecordingDac::default();
            // No new setpoint: the one prepared (where the observer puts the stage) is held.
            core::array::from_fn(|_| next.tick(None, &mut FixedAdc(None), &mut dac))
        };
        for (w, n) in after(with).iter().zip(&after(without)) {
            // The drive glides from where the stacks were (the relaxed models want another
            // drive for the same setpoint), within the slew limit as any reload.
            assert!(
                w.left.0.abs_diff(before.left.0) <= 64,
                "{w:?} vs {before:?}"
            );
            assert!((w.drive - n.drive).abs() <= 8, "{w:?} vs {n:?}");
            assert!((w.estimate - n.estimate).abs() <= 8, "{w:?} vs {n:?}");
        }
    }

    /// Open loop on a P–I model (compensator and observer), no sensor, with or without the
    /// feedforward's notch at the differential stage's resonance.
    fn shaped_open_loop(shaping: bool) -> Settings {
        let mut s = Settings {
            compensator: Some(representative_pi(16).unwrap()),
            observer: Some(representative_pi(16).unwrap()),
            sensor: None,
            mode: Mode::OpenLoop,
            shaping: shaping.then_some(crate::control::notch::NotchDesign {
                frequency_hz: 21_807.0,
                q: 0.5,
                depth: 0.0173,
            }),
            ..Settings::default()
        };
        s.drive.slew_rate = 1.0e9; // no slew limiting: the drive is the command
        s
    }

    /// The shaped drive is the unshaped feedforward through the `f64` biquad of the same
    /// design, started settled at the drive the stacks held: within a few LSB over a sine.
    #[test]
    fn shaping_is_the_f64_notch_on_the_feedforward() {
        let design = shaped_open_loop(true).shaping.unwrap();
        let c64 = design.coefficients(50_000.0).unwrap();
        let mut shaped = Controller::new(shaped_open_loop(true).build(&hw()).unwrap());
        let mut plain = Controller::new(shaped_open_loop(false).build(&hw()).unwrap());
        let held = signal_to_f64(shaped.drive_config().drive_of(shaped.stacks().left));
        let (mut x, mut y) = ([held; 2], [held; 2]);
        let mut dac = RecordingDac::default();
        let mut worst = 0.0f64;
        let mut moved = 0.0f64;
        for k in 0..4000 {
            let sp = signal_from_f64(0.5 * libm::sin(k as f64 * 0.094)); // 750 Hz
            let ff = signal_to_f64(plain.tick(Some(sp), &mut FixedAdc(None), &mut dac).drive);
            let out = shaped.tick(Some(sp), &mut FixedAdc(None), &mut dac).drive;
            let reference = c64.b[0] * ff + c64.b[1] * x[0] + c64.b[2] * x[1]
                - c64.a[0] * y[0]
                - c64.a[1] * y[1];
            (x, y) = ([ff, x[0]], [reference, y[0]]);
            worst = worst.max((signal_to_f64(out) - reference).abs());
            moved = moved.max((signal_to_f64(out) - ff).abs());
        }
        // Q2.30 coefficients and rounding: a few parts in 10⁸ of full scale.
        assert!(worst < 1e-7, "fixed point vs f64: {worst}");
        // And the notch does change the drive (the test would pass on no shaping otherwise).
        assert!(moved > 1e-3, "{moved}");
        // Bypass does not run it: the drive is the setpoint's, as without shaping.
        shaped.set_mode(Mode::Bypass).unwrap();
        plain.set_mode(Mode::Bypass).unwrap();
        let sp = signal_from_f64(0.2);
        for _ in 0..10_000 {
            shaped.tick(Some(sp), &mut FixedAdc(None), &mut dac);
            plain.tick(Some(sp), &mut FixedAdc(None), &mut dac);
        }
        // (Both glided from where their stacks were; now they hold the same drive.)
        let a = shaped.tick(Some(sp), &mut FixedAdc(None), &mut dac).drive;
        let b = plain.tick(Some(sp), &mut FixedAdc(None), &mut dac).drive;
        assert_eq!(a, b);
    }

    /// A reload or a mode switch with shaping on: the notch starts settled at its input, so
    /// the drive does what it does without shaping (the transfer glides from the drive held):
    /// holding the setpoint across a reload, and across open loop → bypass → open loop with
    /// the setpoint moved in bypass, the shaped and the unshaped drive agree to a few LSB, and
    /// the glide back stays between the drive held and the command.
    #[test]
    fn shaping_steps_nothing_at_a_reload_or_a_mode_switch() {
        let sp = signal_from_f64(-0.3);
        let run = |shaping: bool| -> ([i32; 200], i32, [i32; 3000]) {
            let config = shaped_open_loop(shaping).build(&hw()).unwrap();
            let mut c = Controller::new(config);
            let mut dac = RecordingDac::default();
            for k in 0..5_000 {
                let s = signal_from_f64(-0.3 + 0.2 * libm::sin(k as f64 * 0.094));
                c.tick(
                    Some(if k < 4_000 { s } else { sp }),
                    &mut FixedAdc(None),
                    &mut dac,
                );
            }
            let mut next = Controller::new(config);
            next.prepare(config, c.stacks());
            next.take_over(&c);
            let mut c = next;
            // The prepared setpoint (where the observer puts the stage) is held.
            let reload =
                core::array::from_fn(|_| c.tick(None, &mut FixedAdc(None), &mut dac).drive);
            c.set_mode(Mode::Bypass).unwrap();
            for _ in 0..100 {
                c.tick(Some(signal_from_f64(0.4)), &mut FixedAdc(None), &mut dac);
            }
            let held = c.tick(Some(sp), &mut FixedAdc(None), &mut dac).drive;
            c.set_mode(Mode::OpenLoop).unwrap();
            let back =
                core::array::from_fn(|_| c.tick(Some(sp), &mut FixedAdc(None), &mut dac).drive);
            (reload, held, back)
        };
        let (with, without) = (run(true), run(false));
        for (k, (w, n)) in with.0.iter().zip(&without.0).enumerate() {
            assert!((w - n).abs() <= 8, "reload, tick {k}: {w} vs {n}");
        }
        assert_eq!(with.1, without.1, "bypass drives the setpoint, unshaped");
        let held = with.1;
        let target = without.2[2999];
        assert!((with.2[0] - held).abs() <= 8, "starts at the drive held");
        assert!((with.2[2999] - target).abs() <= 8, "settles on the command");
        let (lo, hi) = (held.min(target), held.max(target));
        for (k, (w, n)) in with.2.iter().zip(&without.2).enumerate() {
            assert!(
                (w - n).abs() <= 8,
                "back in open loop, tick {k}: {w} vs {n}"
            );
            assert!(
                (lo - 8..=hi + 8).contains(w),
                "tick {k}: {w} outside {lo}…{hi}"
            );
        }
    }

    #[test]
    fn set_mode_refuses_what_the_configuration_lacks() {
        let mut c = bypass();
        assert_eq!(c.set_mode(Mode::OpenLoop), Err(ModeError::NoCompensator));
        assert_eq!(c.set_mode(Mode::ClosedLoop), Err(ModeError::NoSensor));
        assert_eq!(c.mode(), Mode::Bypass);
    }
}
