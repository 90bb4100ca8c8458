//! The control tick: the one function the firmware's timer interrupt and the simulator both call.
//!
//! Read top to bottom, one tick is:
//!
//! 1. the next setpoint (Q2.30 normalised displacement; on underrun the last one is held);
//! 2. the compensator (inverse P–I, inverse Duhem, or none) turns it into a drive command;
//! 3. with a sensor, the reading is checked against the observer (drift flag) and, in closed
//!    loop, the PI(D) controller on the measured error adds its correction
//!    ([`crate::feedback`]); a mode switch's fading offset is added ([`crate::mode_switch`]);
//! 4. the differential drive clamps the command to the stacks' range and slew limits and splits
//!    it into both stacks' DAC codes (`u_l = ū + v`, `u_r = ū − v`), written at once;
//! 5. the forward observer, fed the drive actually applied, gives the estimated displacement.
//!
//! Configuration ([`ControlConfig`]) is built and validated off the tick path and swapped in
//! whole; state lives in [`Controller`]. Nothing here allocates, panics or loops without bound.

use crate::board::{AdcCode, DacCode, DualDac, SensorAdc};
use crate::drive::DifferentialDrive;
use crate::duhem::{Duhem, DuhemState, InverseDuhem};
use crate::feedback::FeedbackState;
pub use crate::feedback::{Derivative, Feedback};
use crate::fixed_point::{clamp_full_scale, limit};
use crate::mode_switch::{BumplessTransfer, ModeError};
use crate::prandtl_ishlinskii::{InversePrandtlIshlinskii, PiState, PrandtlIshlinskii};
pub use crate::settings::Mode;

/// The feedforward compensator: desired displacement → drive.
// The variants differ in size by design: there is no heap on the board, and the configuration
// lives in a static, so boxing the large variant is neither possible nor wanted.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Compensator {
    /// No compensation: the drive is the setpoint, range onto range (bypass).
    None,
    /// Analytic inverse Prandtl–Ishlinskii.
    InversePi(InversePrandtlIshlinskii),
    /// Inverse Duhem.
    InverseDuhem(InverseDuhem),
}

/// The forward observer: applied drive → estimated displacement.
#[allow(clippy::large_enum_variant)] // as for `Compensator`
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Observer {
    /// No observer (estimate reads 0).
    None,
    /// Forward Prandtl–Ishlinskii.
    Pi(PrandtlIshlinskii),
    /// Forward Duhem.
    Duhem(Duhem),
}

/// Everything the tick needs, validated and in fixed point.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ControlConfig {
    /// Feedforward compensator.
    pub compensator: Compensator,
    /// Forward observer.
    pub observer: Observer,
    /// Sensor feedback, if the stage has a sensor and closed loop is wanted.
    pub feedback: Option<Feedback>,
    /// The differential drive and its limits.
    pub drive: DifferentialDrive,
    /// The mode the controller starts in (switch later with [`Controller::set_mode`]).
    pub mode: Mode,
}

impl ControlConfig {
    /// Bypass: no compensator, no observer, no feedback — the drive follows the setpoint.
    pub fn bypass(drive: DifferentialDrive) -> Self {
        Self {
            compensator: Compensator::None,
            observer: Observer::None,
            feedback: None,
            drive,
            mode: Mode::Bypass,
        }
    }
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
    /// drifted from the stage.
    pub const DRIFT: u8 = 1 << 5;

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
    /// Observer's estimated displacement, Q2.30 normalised.
    pub estimate: i32,
    /// Measured displacement, Q2.30 normalised (0 without a sensor); it is
    /// [`crate::feedback::SENSOR_DELAY_TICKS`] ticks older than `estimate`.
    pub measured: i32,
    /// Model-normalised drive applied, Q2.30.
    pub drive: i32,
    /// What happened.
    pub flags: TickFlags,
}

/// Counters since start-up; they wrap after 2^32 events.
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
    /// Ticks the drift check flagged.
    pub drifts: u32,
}

/// The controller: configuration plus every piece of state the tick keeps.
#[derive(Clone, Debug)]
pub struct Controller {
    compensator: CompensatorRun,
    observer: ObserverRun,
    /// Sensor feedback, if any, as the mode uses it.
    feedback: FeedbackRun,
    drive_limits: DifferentialDrive,
    mode: Mode,
    setpoint: i32,
    drive: i32,
    feedback_state: FeedbackState,
    transfer: BumplessTransfer,
    counters: ControlCounters,
}

/// The compensator as the tick runs it: model and state in one enum, so that one tag says
/// which model runs (the tick pays one compare, not one for the configuration and another for
/// the state).
#[allow(clippy::large_enum_variant)] // as for `Compensator`: no heap, the state is in a static
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum CompensatorRun {
    InversePi(InversePrandtlIshlinskii, PiState),
    InverseDuhem(InverseDuhem, DuhemState),
    /// Not running: none configured, or parked while in bypass (kept for the way back).
    Off(Compensator),
}

/// The observer as the tick runs it (see [`CompensatorRun`]).
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ObserverRun {
    Duhem(Duhem, DuhemState),
    Pi(PrandtlIshlinskii, PiState),
    None,
}

/// The sensor feedback as the tick runs it: the configuration and what the mode makes of it
/// in one tag, so the tick pays one compare for "is there a sensor, is the loop closed, does it
/// have a derivative or a notch".
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum FeedbackRun {
    /// Closed loop, PI only (no derivative, no notch): the common case, without their checks.
    ClosedPi(Feedback),
    /// Closed loop with a derivative or a notch.
    Closed(Feedback),
    /// Open loop or bypass with a sensor: read for the drift check only.
    Monitor(Feedback),
    /// No sensor.
    Off,
}

impl FeedbackRun {
    fn new(feedback: Option<Feedback>, mode: Mode) -> Self {
        match (feedback, mode) {
            (None, _) => Self::Off,
            (Some(fb), Mode::ClosedLoop) if fb.notch.is_none() && fb.derivative.is_none() => {
                Self::ClosedPi(fb)
            }
            (Some(fb), Mode::ClosedLoop) => Self::Closed(fb),
            (Some(fb), _) => Self::Monitor(fb),
        }
    }

    fn config(&self) -> Option<&Feedback> {
        match self {
            Self::ClosedPi(fb) | Self::Closed(fb) | Self::Monitor(fb) => Some(fb),
            Self::Off => None,
        }
    }
}

impl CompensatorRun {
    /// The configured compensator (running or parked).
    fn model(&self) -> Compensator {
        match self {
            Self::InversePi(m, _) => Compensator::InversePi(*m),
            Self::InverseDuhem(m, _) => Compensator::InverseDuhem(*m),
            Self::Off(c) => *c,
        }
    }
}

impl ObserverRun {
    /// The configured observer.
    fn model(&self) -> Observer {
        match self {
            Self::Duhem(m, _) => Observer::Duhem(*m),
            Self::Pi(m, _) => Observer::Pi(*m),
            Self::None => Observer::None,
        }
    }
}

impl Controller {
    /// A controller at rest: drive at the bias, models relaxed there, setpoint where the
    /// observer puts the stage.
    pub fn new(config: ControlConfig) -> Self {
        let mut c = Self {
            compensator: CompensatorRun::Off(config.compensator),
            observer: ObserverRun::None,
            feedback: FeedbackRun::new(config.feedback, config.mode),
            drive_limits: config.drive,
            mode: config.mode,
            setpoint: 0,
            drive: 0,
            feedback_state: FeedbackState::default(),
            transfer: BumplessTransfer::default(),
            counters: ControlCounters::default(),
        };
        c.relax_at(config.observer, c.drive_limits.rest_drive());
        c
    }

    /// Puts the models in the relaxed state at `drive` (clamped to the drive's limits): the
    /// observer's estimate there becomes the setpoint, and the compensator's state is derived
    /// from the observer's, so the compensator starts out agreeing with the stage.
    fn relax_at(&mut self, observer: Observer, drive: i32) {
        let (lo, hi) = self.drive_limits.drive_range();
        let drive = limit(drive, lo, hi);
        self.drive = drive;
        self.transfer = BumplessTransfer::default();
        let (run, y) = match observer {
            Observer::None => (ObserverRun::None, drive),
            Observer::Pi(m) => {
                let mut s = m.state_at_rest(drive);
                let y = m.step(&mut s, drive);
                (ObserverRun::Pi(m, s), y)
            }
            Observer::Duhem(m) => {
                let y = m.anhysteretic(drive);
                (ObserverRun::Duhem(m, m.state_at(drive, y)), y)
            }
        };
        self.observer = run;
        self.setpoint = y;
        let compensator = self.compensator.model();
        // Bypass runs no compensator: it stays parked.
        self.compensator = if self.mode == Mode::Bypass {
            CompensatorRun::Off(compensator)
        } else {
            self.compensator_from_observer(compensator)
        };
        self.feedback_state = FeedbackState::at_rest(y);
    }

    /// Swaps in a new configuration whole, between two ticks. The drive stays where it is
    /// (within the new limits) and the models are relaxed there, so the output does not jump
    /// to the rest position; counters carry on.
    /// In closed loop the integrator takes over whatever separates the new feedforward from
    /// the drive, as on a mode switch.
    pub fn reconfigure(&mut self, config: ControlConfig) {
        let measured = self.feedback_state.measured();
        self.compensator = CompensatorRun::Off(config.compensator);
        self.feedback = FeedbackRun::new(config.feedback, config.mode);
        self.drive_limits = config.drive;
        self.mode = config.mode;
        self.relax_at(config.observer, self.drive);
        self.feedback_state = self.feedback_state.with_measurement(measured);
        self.begin_transfer();
    }

    /// Switches between bypass, open loop (compensated) and closed loop between two ticks,
    /// without a bump in the drive (see [`crate::mode_switch`]). Refused, changing nothing,
    /// when the configuration lacks what the mode needs.
    pub fn set_mode(&mut self, mode: Mode) -> Result<(), ModeError> {
        let compensator = self.compensator.model();
        match mode {
            Mode::OpenLoop if matches!(compensator, Compensator::None) => {
                return Err(ModeError::NoCompensator)
            }
            Mode::ClosedLoop if self.feedback.config().is_none() => {
                return Err(ModeError::NoSensor)
            }
            _ => {}
        }
        if mode == self.mode {
            return Ok(());
        }
        self.mode = mode;
        self.feedback = FeedbackRun::new(self.feedback.config().copied(), mode);
        if mode == Mode::Bypass {
            self.compensator = CompensatorRun::Off(compensator);
        } else if matches!(self.compensator, CompensatorRun::Off(_)) {
            self.compensator = self.compensator_from_observer(compensator);
        }
        self.begin_transfer();
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

    /// `compensator`, running, from where the observer says the stage is.
    fn compensator_from_observer(&self, compensator: Compensator) -> CompensatorRun {
        match (compensator, &self.observer) {
            (Compensator::None, _) => CompensatorRun::Off(Compensator::None),
            (Compensator::InversePi(m), ObserverRun::Pi(observer, fs)) => {
                CompensatorRun::InversePi(m, m.state_from_forward(&observer.bank().outputs(fs)))
            }
            (Compensator::InversePi(m), _) => {
                CompensatorRun::InversePi(m, m.state_at_rest(self.setpoint))
            }
            (Compensator::InverseDuhem(m), ObserverRun::Duhem(o, os)) if o == m.model() => {
                CompensatorRun::InverseDuhem(m, *os)
            }
            (Compensator::InverseDuhem(m), _) => {
                let model = m.model();
                let state = model.state_at(self.drive, model.anhysteretic(self.drive));
                CompensatorRun::InverseDuhem(m, state)
            }
        }
    }

    /// What the feedforward would be for the present setpoint (the state is not advanced).
    fn peek_feedforward(&self) -> i32 {
        let target = self.setpoint;
        match self.compensator {
            CompensatorRun::InversePi(m, mut s) => m.step(&mut s, target),
            CompensatorRun::InverseDuhem(m, mut s) => m.step(&mut s, target),
            CompensatorRun::Off(_) => target,
        }
    }

    /// Makes the next command continue from the present drive: the integrator (closed loop)
    /// or the fading transfer offset takes up the difference.
    fn begin_transfer(&mut self) {
        let wanted = self.drive.saturating_sub(self.peek_feedforward());
        let rest = match &self.feedback {
            FeedbackRun::ClosedPi(fb) | FeedbackRun::Closed(fb) => {
                fb.hand_over(&mut self.feedback_state, self.setpoint, wanted)
            }
            FeedbackRun::Monitor(_) | FeedbackRun::Off => wanted,
        };
        self.transfer.start(rest);
    }

    /// The setpoint in force (the last one given, or held), Q2.30 normalised displacement.
    pub fn setpoint(&self) -> i32 {
        self.setpoint
    }

    /// The rest position: the observer's displacement with the drive at rest (the bias),
    /// Q2.30 normalised (the drive itself without an observer). Computed from the configuration
    /// alone; the controller's state is not touched.
    pub fn rest_setpoint(&self) -> i32 {
        let (lo, hi) = self.drive_limits.drive_range();
        let drive = limit(self.drive_limits.rest_drive(), lo, hi);
        match &self.observer {
            ObserverRun::None => drive,
            ObserverRun::Pi(m, _) => {
                let mut s = m.state_at_rest(drive);
                m.step(&mut s, drive)
            }
            ObserverRun::Duhem(m, _) => m.anhysteretic(drive),
        }
    }

    /// The active configuration (the models as configured, the mode in effect), rebuilt from
    /// the parts the controller runs; it is large (the models' tables), so prefer the
    /// accessors for single parts.
    pub fn config(&self) -> ControlConfig {
        ControlConfig {
            compensator: self.compensator.model(),
            observer: self.observer.model(),
            feedback: self.feedback.config().copied(),
            drive: self.drive_limits,
            mode: self.mode,
        }
    }

    /// The sensor feedback's configuration, if there is a sensor.
    pub fn feedback_config(&self) -> Option<&Feedback> {
        self.feedback.config()
    }

    /// The drive and its limits.
    pub fn drive_config(&self) -> &DifferentialDrive {
        &self.drive_limits
    }

    /// Counters since start-up.
    pub fn counters(&self) -> ControlCounters {
        self.counters
    }

    /// DAC codes of the safe state, for the fault handlers.
    pub fn safe_codes(&self) -> (DacCode, DacCode) {
        self.drive_limits.safe_codes()
    }

    /// One control tick (see the module doc). `setpoint` is the next desired displacement
    /// (Q2.30 normalised), `None` on underrun. Reads the sensor (when feedback is on), writes
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
        let counters = &mut self.counters;
        counters.ticks = counters.ticks.wrapping_add(1);

        // 1. Setpoint.
        match setpoint {
            Some(s) => self.setpoint = clamp_full_scale(s),
            None => {
                flags |= TickFlags::UNDERRUN;
                counters.underruns = counters.underruns.wrapping_add(1);
            }
        }
        let target = self.setpoint;

        // 2. Feedforward.
        let feedforward = match &mut self.compensator {
            CompensatorRun::InversePi(m, s) => m.step(s, target),
            CompensatorRun::InverseDuhem(m, s) => m.step(s, target),
            CompensatorRun::Off(_) => target,
        };

        // 3. Sensor: drift check, and in closed loop the feedback correction.
        let fs = &mut self.feedback_state;
        let (command, measured) = match &self.feedback {
            FeedbackRun::ClosedPi(fb) => {
                sense::<_, true, false>(fb, fs, io, target, feedforward, &mut flags, counters)
            }
            FeedbackRun::Closed(fb) => {
                sense::<_, true, true>(fb, fs, io, target, feedforward, &mut flags, counters)
            }
            FeedbackRun::Monitor(fb) => {
                sense::<_, false, true>(fb, fs, io, target, feedforward, &mut flags, counters)
            }
            FeedbackRun::Off => (feedforward, 0),
        };
        let command = self.transfer.apply(command);

        // 4. Limits, split, both DACs at once.
        let out = self.drive_limits.split(command, self.drive);
        self.drive = out.applied;
        if out.range_limited {
            flags |= TickFlags::RANGE_LIMIT;
            counters.range_limits = counters.range_limits.wrapping_add(1);
        }
        if out.slew_limited {
            flags |= TickFlags::SLEW_LIMIT;
            counters.slew_limits = counters.slew_limits.wrapping_add(1);
        }
        if io.write(out.left, out.right).is_err() {
            flags |= TickFlags::DAC_ERROR;
            counters.dac_errors = counters.dac_errors.wrapping_add(1);
        }
        // What the limits cut, kept now: the command need not live on through the observer.
        self.feedback_state.limited(command, out.applied);
        let mut report = TickReport {
            left: out.left,
            right: out.right,
            estimate: 0,
            measured,
            drive: out.applied,
            flags: TickFlags(flags),
        };

        // 5. Observer on the applied drive.
        // The Duhem observer is tested first: the configuration the tick is tuned for.
        report.estimate = if let ObserverRun::Duhem(m, s) = &mut self.observer {
            m.step(s, out.applied)
        } else if let ObserverRun::Pi(m, s) = &mut self.observer {
            m.step(s, out.applied)
        } else {
            0
        };
        self.feedback_state.observed(report.estimate);
        report
    }
}

/// The tick's sensor step: reads the sensor, runs the drift check and, when `CLOSED`, adds
/// the feedback correction to `feedforward` (with the derivative and notch when `FULL`, else
/// the PI alone). Returns the command and the measurement.
#[inline(always)]
fn sense<IO: TickIo, const CLOSED: bool, const FULL: bool>(
    fb: &Feedback,
    fs: &mut FeedbackState,
    io: &mut IO,
    target: i32,
    feedforward: i32,
    flags: &mut u8,
    counters: &mut ControlCounters,
) -> (i32, i32) {
    match io.read() {
        Ok(code) => {
            let measured = fb.displacement(code);
            if fb.drifted(fs, measured) {
                *flags |= TickFlags::DRIFT;
                counters.drifts = counters.drifts.wrapping_add(1);
            }
            let command = if CLOSED {
                feedforward.saturating_add(fb.correction_with::<FULL>(fs, target, measured))
            } else {
                feedforward
            };
            (command, measured)
        }
        Err(_) => {
            *flags |= TickFlags::ADC_ERROR;
            counters.adc_errors = counters.adc_errors.wrapping_add(1);
            let command = if CLOSED {
                feedforward.saturating_add(fb.held_correction(fs, target))
            } else {
                feedforward
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
    use crate::drive::{Configuration, DriveSettings, SafeState};
    use crate::fixed_point::signal_from_f64;
    use crate::scaling::Scaling;

    use crate::board::fakes::{FixedAdc, RecordingDac};

    pub(crate) fn paper_drive() -> DriveSettings {
        DriveSettings {
            configuration: Configuration::Differential,
            amplifier_full_scale: 150.0,
            bias: 70.0,
            right_idle: 0.0,
            min_voltage: 0.0,
            max_voltage: 140.0,
            slew_rate: 1.0e6,
            control_rate: 50_000.0,
            dac_full_scale: 65535,
            safe_state: SafeState::Bias,
        }
    }

    fn bypass() -> Controller {
        let scaling = Scaling::new(0.0, 140.0, 0.0, 10.0).unwrap();
        let drive = DifferentialDrive::new(&paper_drive(), &scaling).unwrap();
        Controller::new(ControlConfig::bypass(drive))
    }

    fn volts(code: DacCode) -> f64 {
        code.0 as f64 / 65535.0 * 150.0
    }

    #[test]
    fn differential_split_mirrors_the_stacks_about_the_bias() {
        let mut c = bypass();
        let mut dac = RecordingDac::default();
        for &y in &[-0.5, 0.0, 0.3, 0.9] {
            // Slew allows 20 V per tick: enough ticks to arrive.
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
        let scaling = Scaling::new(0.0, 140.0, 0.0, 10.0).unwrap();
        let mut settings = paper_drive();
        settings.min_voltage = 10.0;
        settings.max_voltage = 130.0;
        settings.slew_rate = 50_000.0; // 1 V per tick
        let drive = DifferentialDrive::new(&settings, &scaling).unwrap();
        let mut c = Controller::new(ControlConfig::bypass(drive));
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
    fn safe_state_is_bias_or_zero() {
        let c = bypass();
        let (l, r) = c.safe_codes();
        assert!((volts(l) - 70.0).abs() < 0.01 && l == r);
        let scaling = Scaling::new(0.0, 140.0, 0.0, 10.0).unwrap();
        let mut s = paper_drive();
        s.safe_state = SafeState::Zero;
        let c = Controller::new(ControlConfig::bypass(
            DifferentialDrive::new(&s, &scaling).unwrap(),
        ));
        assert_eq!(c.safe_codes(), (DacCode(0), DacCode(0)));
    }
}
