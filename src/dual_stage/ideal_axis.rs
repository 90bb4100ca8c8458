//! [`IdealAxis`]: a model of the coarse stage's peripherals behind the board traits — the
//! step/dir output, the motor and linear encoders and the switches — for the emulator image
//! (QEMU models neither TIM1 nor TIM8, nor the GPIOs), so that a move commanded over the UART
//! runs through the firmware's real coarse task and supervisor.
//!
//! The carriage follows the accepted step pulses at once (a stiff screw, no backlash); the
//! motor encoder counts its position, the linear one the total position, carriage plus the
//! piezo's setpoint (the emulator has no piezo plant: [`IdealAxis::set_piezo_pm`] says where
//! it would be, and the coarse tick is told it has no measurement); the switches are active
//! beyond fixed carriage positions. One model, four handles
//! ([`IdealAxis::step_dir`], [`IdealAxis::motor`], [`IdealAxis::linear`],
//! [`IdealAxis::switches`]) that share it through atomics (one task owns them all; atomics
//! rather than `Cell`s so the model can sit in a `static` the firmware's task reaches).

use core::sync::atomic::{AtomicI32, AtomicU32, Ordering::Relaxed};

use crate::board::{LimitSwitches, QuadratureEncoder, StepBurst, StepDir, StepDirection, Switches};
use crate::divisor::Divisor;

/// The modelled axis (positions of the carriage, pm).
#[derive(Debug)]
pub struct IdealAxis {
    step_pm: i64,
    /// The motor encoder's resolution, pm per count, prepared for division (the emulator's
    /// coarse task reads the encoders every coarse tick: no 64-bit library division there).
    motor_count: Divisor,
    /// The linear encoder's resolution, pm per count, prepared likewise.
    linear_count: Divisor,
    /// Carriage at or below: the lower limit switch is active.
    lower_pm: i64,
    /// Carriage at or above: the upper limit switch is active.
    upper_pm: i64,
    /// Carriage at or below: the home switch is active.
    home_pm: i64,
    /// Microsteps (±2^31: ±670 m of travel at 0.3 µm).
    steps: AtomicI32,
    pulses: AtomicU32,
    /// The piezo's displacement, pm (±2.1 mm).
    piezo_pm: AtomicI32,
}

impl IdealAxis {
    /// An axis at carriage 0 with `step_pm` per microstep, the encoders' resolutions, and
    /// the lower limit, home and upper limit switches at `switches_pm` (`lower < home < upper`
    /// is not checked: any positions model some wiring). An encoder's resolution of 0 or less
    /// counts nothing (it reads 0).
    ///
    /// ```
    /// use twinstack::board::{QuadratureEncoder, StepBurst, StepDir, StepDirection};
    /// use twinstack::dual_stage::ideal_axis::IdealAxis;
    /// let axis = IdealAxis::new(312_500, 250_000, 5_000, (-2_000_000_000, -1_000_000_000, 2_000_000_000));
    /// axis.step_dir().emit(StepBurst { direction: StepDirection::Forward, steps: 16 }).unwrap();
    /// assert_eq!(axis.carriage_pm(), 5_000_000);
    /// assert_eq!(axis.linear().count(), 1000);
    /// ```
    pub fn new(
        step_pm: i64,
        motor_count_pm: i64,
        linear_count_pm: i64,
        switches_pm: (i64, i64, i64),
    ) -> Self {
        let resolution = |pm: i64| Divisor::new(u64::try_from(pm).unwrap_or(0));
        Self {
            step_pm,
            motor_count: resolution(motor_count_pm),
            linear_count: resolution(linear_count_pm),
            lower_pm: switches_pm.0,
            home_pm: switches_pm.1,
            upper_pm: switches_pm.2,
            steps: AtomicI32::new(0),
            pulses: AtomicU32::new(0),
            piezo_pm: AtomicI32::new(0),
        }
    }

    /// Carriage position, pm.
    pub fn carriage_pm(&self) -> i64 {
        (self.steps.load(Relaxed) as i64).saturating_mul(self.step_pm)
    }

    /// Where the piezo is, pm (saturated to ±2.1 mm): the linear encoder sees the carriage
    /// plus this.
    pub fn set_piezo_pm(&self, pm: i64) {
        self.piezo_pm
            .store(pm.clamp(i32::MIN as i64, i32::MAX as i64) as i32, Relaxed);
    }

    /// Pulses accepted so far.
    pub fn pulses(&self) -> u32 {
        self.pulses.load(Relaxed)
    }

    /// The step/dir output.
    pub fn step_dir(&self) -> AxisSteps<'_> {
        AxisSteps(self)
    }

    /// The motor encoder.
    pub fn motor(&self) -> AxisEncoder<'_> {
        AxisEncoder(self, self.motor_count, false)
    }

    /// The linear encoder.
    pub fn linear(&self) -> AxisEncoder<'_> {
        AxisEncoder(self, self.linear_count, true)
    }

    /// The switches.
    pub fn switches(&self) -> AxisSwitches<'_> {
        AxisSwitches(self)
    }
}

/// The model's step/dir output.
#[derive(Debug)]
pub struct AxisSteps<'a>(&'a IdealAxis);

impl StepDir for AxisSteps<'_> {
    type Error = ();

    fn max_steps_per_burst(&self) -> u16 {
        256
    }

    fn emit(&mut self, burst: StepBurst) -> Result<(), ()> {
        if burst.steps > 256 {
            return Err(());
        }
        let n = burst.steps as i32;
        let axis = self.0;
        let steps = axis.steps.load(Relaxed);
        axis.steps.store(
            match burst.direction {
                StepDirection::Forward => steps.saturating_add(n),
                StepDirection::Reverse => steps.saturating_sub(n),
            },
            Relaxed,
        );
        axis.pulses.store(
            axis.pulses.load(Relaxed).wrapping_add(burst.steps as u32),
            Relaxed,
        );
        Ok(())
    }
}

/// One of the model's encoders (its resolution, pm per count; whether it sees the piezo too):
/// the 16-bit counter of a timer in encoder mode.
#[derive(Debug)]
pub struct AxisEncoder<'a>(&'a IdealAxis, Divisor, bool);

impl QuadratureEncoder for AxisEncoder<'_> {
    fn count(&mut self) -> u16 {
        let piezo = if self.2 {
            self.0.piezo_pm.load(Relaxed) as i64
        } else {
            0
        };
        // Rounded down, as a counter counting from position 0 reads.
        self.1.floor(self.0.carriage_pm().saturating_add(piezo)) as u16
    }
}

/// The model's switches.
#[derive(Debug)]
pub struct AxisSwitches<'a>(&'a IdealAxis);

impl LimitSwitches for AxisSwitches<'_> {
    fn read(&mut self) -> Switches {
        let c = self.0.carriage_pm();
        Switches {
            lower: c <= self.0.lower_pm,
            upper: c >= self.0.upper_pm,
            home: c <= self.0.home_pm,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The encoders count the position rounded down, as `div_euclid` (a counter from 0 reads
    /// one less on the first edge below it), the linear one with the piezo's displacement.
    #[test]
    fn the_encoders_count_the_position_rounded_down() {
        let axis = IdealAxis::new(312_500, 250_000, 5_000, (-1, 0, 1));
        for steps in [-3_000_001i32, -17, -1, 0, 1, 15, 4_000_003] {
            for piezo in [-2_500i64, 0, 4_999, 5_000] {
                axis.steps.store(steps, Relaxed);
                axis.set_piezo_pm(piezo);
                let carriage = steps as i64 * 312_500;
                assert_eq!(
                    axis.motor().count(),
                    carriage.div_euclid(250_000) as u16,
                    "{steps}"
                );
                assert_eq!(
                    axis.linear().count(),
                    (carriage + piezo).div_euclid(5_000) as u16,
                    "{steps}, {piezo}"
                );
            }
        }
        // A resolution of 0 counts nothing.
        assert_eq!(IdealAxis::new(312_500, 0, 0, (-1, 0, 1)).motor().count(), 0);
    }
}
