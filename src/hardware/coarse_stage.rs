//! The coarse stage's peripherals: step/dir output to the ball screw's motor driver, the motor
//! encoder, the linear encoder of the total position, and the coarse tick's timer.
//!
//! | signal | pin | peripheral |
//! |--------|-----|------------|
//! | STEP | PA8 | TIM1 CH1 (AF1): PWM mode 2, one-pulse mode, `RCR = steps − 1` |
//! | DIR | PB0 | GPIO push-pull |
//! | motor encoder A / B | PC6 / PC7 | TIM8 CH1 / CH2 (AF3), encoder mode 3 (×4) |
//! | linear encoder A / B | PB6 / PB7 | TIM4 CH1 / CH2 (AF2), encoder mode 3 (×4) |
//! | coarse tick | – | TIM3 update interrupt (default 5 kHz) |
//! | lower limit / upper limit / home | PC0 / PC1 / PC2 | GPIO inputs, pull-up, active low (switch to GND) |
//!
//! **Step bursts without an interrupt per step.** TIM1 is an advanced timer with a repetition
//! counter: in one-pulse mode its update event — which stops the counter — comes only after
//! `RCR + 1` periods, so one write of PSC/ARR/CCR1/RCR and one enable emit exactly `steps`
//! pulses (at most 256) spread over the coarse period ([`StepTiming`]), then stop. PWM mode 2
//! keeps STEP low while the counter is below CCR1, so the line idles low when the counter stops
//! at 0, and each pulse comes at the end of its period: DIR is set at least half a step period
//! (≥ 10 µs at 10 steps per 200 µs) before the first rising edge.
//!
//! **Encoders.** TIM8 and TIM4 count every edge of A and B (×4), up or down; their 16-bit
//! counters wrap and the library's [`crate::dual_stage::coarse_axis::EncoderCounter`] extends them (valid
//! while they move less than 32768 counts per coarse tick: 160 mm/s at 5 nm, 5 kHz). Inputs
//! are filtered over 8 timer clocks.
//!
//! QEMU models none of TIM1/TIM8 (writes ignored, reads 0) and TIM3's update interrupt is
//! unreliable there (`EMULATOR.md`): in the emulator image the coarse stage is configured but
//! its task may never run.

use stm32f4xx_hal::gpio::{Input, Output, Pin, PushPull};
use stm32f4xx_hal::pac::{RCC, TIM1, TIM3, TIM4, TIM8};

use super::clocks::BusClocks;
use crate::board::{LimitSwitches, QuadratureEncoder, StepBurst, StepDir, StepDirection, Switches};
use crate::dual_stage::coarse_axis::{BurstTiming, StepTiming};

/// Shortest STEP high time the driver needs, ns.
pub const MIN_STEP_PULSE_NS: u32 = 2_000;
/// Most pulses one burst holds (the 8-bit repetition counter).
pub const MAX_STEPS_PER_BURST: u16 = 256;

/// The kernel clock of the APB2 timers (TIM1, TIM8): twice PCLK2 when APB2 is divided (as on
/// the board: 84 MHz → 168 MHz), PCLK2 itself otherwise (emulator: 16 MHz).
fn apb2_timer_hz(clocks: &BusClocks) -> u32 {
    if clocks.pclk2_hz < clocks.sysclk_hz {
        2 * clocks.pclk2_hz
    } else {
        clocks.pclk2_hz
    }
}

/// Why a burst was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum StepOutputError {
    /// The previous burst is still running.
    Busy,
    /// More than [`MAX_STEPS_PER_BURST`] pulses.
    TooManySteps,
}

/// STEP on TIM1 CH1 (PA8), DIR on PB0.
pub struct StepOutput {
    tim: TIM1,
    dir: Pin<'B', 0, Output<PushPull>>,
    /// The bursts' timing, prepared here: a burst costs the coarse task one division.
    timing: BurstTiming,
}

impl StepOutput {
    /// Sets TIM1 up for bursts (PWM mode 2 on CH1, one-pulse mode, main output on), STEP idle
    /// low. PA8 must be in AF1; `dir` is PB0 as a push-pull output.
    pub fn new(
        tim: TIM1,
        dir: Pin<'B', 0, Output<PushPull>>,
        rcc: &RCC,
        clocks: &BusClocks,
        coarse_rate_hz: u32,
    ) -> Self {
        rcc.apb2enr().modify(|_, w| w.tim1en().set_bit());
        tim.cr1().write(|w| w.cen().clear_bit());
        tim.ccmr1_output()
            .write(|w| w.oc1m().pwm_mode2().oc1pe().enabled());
        tim.ccer().write(|w| w.cc1e().set_bit());
        tim.bdtr().write(|w| w.moe().set_bit());
        Self {
            tim,
            dir,
            timing: BurstTiming::new(apb2_timer_hz(clocks), coarse_rate_hz, MIN_STEP_PULSE_NS),
        }
    }
}

impl StepDir for StepOutput {
    type Error = StepOutputError;

    fn max_steps_per_burst(&self) -> u16 {
        MAX_STEPS_PER_BURST
    }

    fn emit(&mut self, burst: StepBurst) -> Result<(), StepOutputError> {
        if self.tim.cr1().read().cen().bit_is_set() {
            return Err(StepOutputError::Busy);
        }
        if burst.steps == 0 {
            return Ok(());
        }
        if burst.steps > MAX_STEPS_PER_BURST {
            return Err(StepOutputError::TooManySteps);
        }
        match burst.direction {
            StepDirection::Forward => self.dir.set_high(),
            StepDirection::Reverse => self.dir.set_low(),
        }
        let t = self.timing.burst(burst.steps);
        let tim = &self.tim;
        tim.psc().write(|w| unsafe { w.bits(t.prescaler as u32) });
        tim.arr().write(|w| unsafe { w.bits(t.period - 1) });
        // Mode 2: high from CCR1 to the end of each period.
        tim.ccr1().write(|w| unsafe { w.bits(t.period - t.pulse) });
        tim.rcr()
            .write(|w| unsafe { w.bits(burst.steps as u32 - 1) });
        // Load PSC, ARR, CCR1, RCR now (the counter restarts at 0), then go: the counter stops
        // by itself at the update event after the last pulse.
        tim.egr().write(|w| w.ug().set_bit());
        tim.sr().write(|w| unsafe { w.bits(0) });
        tim.cr1()
            .write(|w| w.opm().set_bit().urs().set_bit().cen().set_bit());
        Ok(())
    }
}

/// Sets a 16-bit timer up in encoder mode 3 (count both edges of both inputs), free running.
macro_rules! encoder_mode {
    ($tim:expr) => {{
        let tim = &$tim;
        tim.cr1().write(|w| w.cen().clear_bit());
        tim.ccmr1_input().write(|w| {
            w.cc1s()
                .ti1()
                .cc2s()
                .ti2()
                .ic1f()
                .fck_int_n8()
                .ic2f()
                .fck_int_n8()
        });
        tim.ccer().write(|w| w.cc1e().set_bit().cc2e().set_bit());
        tim.smcr().write(|w| w.sms().encoder_mode_3());
        tim.arr().write(|w| unsafe { w.bits(0xFFFF) });
        tim.cnt().write(|w| unsafe { w.bits(0) });
        tim.cr1().write(|w| w.cen().set_bit());
    }};
}

/// The motor encoder on TIM8 (PC6 / PC7 in AF3).
pub struct MotorEncoder {
    tim: TIM8,
}

impl MotorEncoder {
    /// Enables TIM8 in encoder mode.
    pub fn new(tim: TIM8, rcc: &RCC) -> Self {
        rcc.apb2enr().modify(|_, w| w.tim8en().set_bit());
        encoder_mode!(tim);
        Self { tim }
    }
}

impl QuadratureEncoder for MotorEncoder {
    fn count(&mut self) -> u16 {
        self.tim.cnt().read().bits() as u16
    }
}

/// The linear encoder of the total position on TIM4 (PB6 / PB7 in AF2).
pub struct LinearEncoder {
    tim: TIM4,
}

impl LinearEncoder {
    /// Enables TIM4 in encoder mode.
    pub fn new(tim: TIM4, rcc: &RCC) -> Self {
        rcc.apb1enr().modify(|_, w| w.tim4en().set_bit());
        encoder_mode!(tim);
        Self { tim }
    }
}

impl QuadratureEncoder for LinearEncoder {
    fn count(&mut self) -> u16 {
        self.tim.cnt().read().bits() as u16
    }
}

/// TIM3: the coarse tick's update interrupt.
pub struct CoarseTimer {
    tim: TIM3,
    rate_hz: u32,
}

impl CoarseTimer {
    /// Starts TIM3 at `rate_hz` (≥ 100 Hz: one period fits the 16-bit counter at the 84 MHz
    /// APB1 timer clock with prescaler 15) with its update interrupt.
    pub fn start(tim: TIM3, rcc: &RCC, clocks: &BusClocks, rate_hz: u32) -> Self {
        rcc.apb1enr().modify(|_, w| w.tim3en().set_bit());
        let prescaler = StepTiming::prescaler_for(clocks.tim2_hz, rate_hz);
        let tick_hz = clocks.tim2_hz / (prescaler as u32 + 1);
        let counts = (tick_hz / rate_hz.max(1)).clamp(1, 65_536);
        tim.cr1().write(|w| w.cen().clear_bit());
        tim.psc().write(|w| unsafe { w.bits(prescaler as u32) });
        tim.arr().write(|w| unsafe { w.bits(counts - 1) });
        tim.egr().write(|w| w.ug().set_bit());
        tim.sr().write(|w| unsafe { w.bits(0) });
        tim.dier().write(|w| w.uie().set_bit());
        tim.cr1().write(|w| w.urs().set_bit().cen().set_bit());
        Self {
            tim,
            rate_hz: tick_hz / counts,
        }
    }

    /// Clears the update flag that raised this interrupt.
    #[inline(always)]
    pub fn acknowledge(&mut self) {
        self.tim.sr().write(|w| unsafe { w.bits(0) });
    }

    /// The coarse rate actually running, Hz.
    pub fn rate_hz(&self) -> u32 {
        self.rate_hz
    }
}

/// The limit and home switches: PC0 (lower), PC1 (upper), PC2 (home), inputs with pull-ups,
/// a switch closing to ground is active. (An encoder index pulse on the home input would need
/// an EXTI latch to be seen at 5 kHz: not wired yet.)
pub struct BoardSwitches {
    lower: Pin<'C', 0, Input>,
    upper: Pin<'C', 1, Input>,
    home: Pin<'C', 2, Input>,
}

impl BoardSwitches {
    /// The three inputs, already configured as pull-up inputs.
    pub fn new(
        lower: Pin<'C', 0, Input>,
        upper: Pin<'C', 1, Input>,
        home: Pin<'C', 2, Input>,
    ) -> Self {
        Self { lower, upper, home }
    }
}

impl LimitSwitches for BoardSwitches {
    fn read(&mut self) -> Switches {
        Switches {
            lower: self.lower.is_low(),
            upper: self.upper.is_low(),
            home: self.home.is_low(),
        }
    }
}
