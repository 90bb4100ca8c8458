//! The source of the control interrupt.
//!
//! **Board:** TIM2 counts the 84 MHz timer clock with `ARR = f / rate − 1`. Three things hang
//! on it, each set by the hardware at a fixed instant of the period:
//!
//! * its channel 2 (PWM mode 2, no pin) rises [`SAMPLE_LEAD_NS`] before the update: that edge
//!   (`TIM2_CC2`) starts the sensor's conversion (and the analog input's), which is complete
//!   before the tick reads it;
//! * its update event raises the `TIM2` interrupt (the tick);
//! * the same update, as `TRGO` (`MMS = update`), latches the DAC's holding registers into
//!   both outputs at once ([`super::dac`]): the drive the previous tick wrote goes out at the
//!   period's first instant.
//!
//! **Emulator:** QEMU models TIM2's counter but not its update interrupt, so SysTick raises
//! the tick instead (the ADC is then not triggered; QEMU returns its data register as is).
//!
//! Either way the shell calls [`ControlTimer::acknowledge`] first in the interrupt and
//! [`ControlTimer::next_tick_already_due`] last: if the next tick became due while this one ran,
//! the tick overran its period.

use super::clocks::BusClocks;
#[cfg(not(feature = "emulator"))]
use crate::board::SAMPLE_LEAD_NS;

/// Period in timer counts for `rate_hz`, at least 1.
fn period_counts(clock_hz: u32, rate_hz: u32) -> u32 {
    (clock_hz / rate_hz.max(1)).max(1)
}

/// [`SAMPLE_LEAD_NS`] in timer counts (rounded up), at most half the period `counts`: at the
/// board's rates (≤ 100 kHz, 840 counts at 84 MHz) it is 168 counts, never capped.
#[cfg(not(feature = "emulator"))]
fn sample_lead_counts(clock_hz: u32, counts: u32) -> u32 {
    let lead = (clock_hz as u64 * SAMPLE_LEAD_NS as u64).div_ceil(1_000_000_000) as u32;
    lead.min(counts / 2).max(1)
}

/// The control tick's timer (TIM2 on the board).
#[cfg(not(feature = "emulator"))]
pub struct ControlTimer {
    tim: stm32f4xx_hal::pac::TIM2,
    rate_hz: u32,
}

#[cfg(not(feature = "emulator"))]
impl ControlTimer {
    /// Starts TIM2 at `rate_hz` (the tick rate, validated by the caller to 10–100 kHz) with
    /// its update interrupt, TRGO on update (the DAC's latch) and channel 2's compare
    /// [`SAMPLE_LEAD_NS`] before it (the ADCs' trigger). Returns the timer and the rate actually
    /// set (the clock divided by a whole number of counts). The DAC and the ADCs are set up
    /// after it, at the board's initial codes ([`super::dac::InternalDac::new`]): until the
    /// first tick writes, each update latches those codes again.
    pub fn start(
        tim: stm32f4xx_hal::pac::TIM2,
        rcc: &stm32f4xx_hal::pac::RCC,
        clocks: &BusClocks,
        rate_hz: u32,
    ) -> Self {
        rcc.apb1enr().modify(|_, w| w.tim2en().set_bit());
        let counts = period_counts(clocks.tim2_hz, rate_hz);
        tim.cr1().write(|w| w.cen().clear_bit());
        tim.psc().write(|w| unsafe { w.bits(0) });
        tim.arr().write(|w| unsafe { w.bits(counts - 1) });
        // MMS = 010: the update event is TRGO (latches the DAC's outputs).
        tim.cr2().write(|w| unsafe { w.mms().bits(0b010) });
        // Channel 2 in PWM mode 2: its reference is low below CCR2 and high from it to the
        // update, so it rises `lead` counts before each update: the ADCs' trigger edge
        // (`TIM2_CC2`). Enabled (CC2E) for the trigger; no pin is in TIM2's alternate function.
        let lead = sample_lead_counts(clocks.tim2_hz, counts);
        tim.ccmr1_output()
            .write(|w| w.oc2m().pwm_mode2().oc2pe().enabled());
        tim.ccr2().write(|w| unsafe { w.bits(counts - lead) });
        tim.ccer().write(|w| w.cc2e().set_bit());
        // Load PSC/ARR now, then drop the update flag that load raised.
        tim.egr().write(|w| w.ug().set_bit());
        tim.sr().write(|w| unsafe { w.bits(0) });
        tim.dier().write(|w| w.uie().set_bit());
        tim.cr1().write(|w| w.urs().set_bit().cen().set_bit());
        Self {
            tim,
            rate_hz: clocks.tim2_hz / counts,
        }
    }

    /// Clears the update flag that raised this interrupt. First thing in the tick.
    #[inline(always)]
    pub fn acknowledge(&mut self) {
        // UIF is rc_w0: writing 0 clears it (the other flags are unused).
        self.tim.sr().write(|w| unsafe { w.bits(0) });
    }

    /// Whether the next update already happened while this tick ran (an overrun). Last
    /// thing in the tick; the pending interrupt then runs the late tick at once.
    #[inline(always)]
    pub fn next_tick_already_due(&self) -> bool {
        self.tim.sr().read().uif().bit_is_set()
    }

    /// The tick rate actually running, Hz.
    pub fn rate_hz(&self) -> u32 {
        self.rate_hz
    }
}

/// The control tick's timer (SysTick in the emulator).
#[cfg(feature = "emulator")]
pub struct ControlTimer {
    _syst: cortex_m::peripheral::SYST,
    rate_hz: u32,
}

#[cfg(feature = "emulator")]
impl ControlTimer {
    /// Starts SysTick at `rate_hz` on the core clock with its exception enabled.
    pub fn start(mut syst: cortex_m::peripheral::SYST, clocks: &BusClocks, rate_hz: u32) -> Self {
        use cortex_m::peripheral::syst::SystClkSource;
        let counts = period_counts(clocks.systick_hz, rate_hz).min(1 << 24);
        syst.disable_counter();
        syst.set_clock_source(SystClkSource::Core);
        syst.set_reload(counts - 1);
        syst.clear_current();
        syst.enable_interrupt();
        syst.enable_counter();
        Self {
            _syst: syst,
            rate_hz: clocks.systick_hz / counts,
        }
    }

    /// Nothing to clear: taking the SysTick exception clears its pending state.
    #[inline(always)]
    pub fn acknowledge(&mut self) {}

    /// Whether SysTick became pending again while this tick ran (an overrun).
    #[inline(always)]
    pub fn next_tick_already_due(&self) -> bool {
        cortex_m::peripheral::SCB::is_pendst_pending()
    }

    /// The tick rate actually running, Hz.
    pub fn rate_hz(&self) -> u32 {
        self.rate_hz
    }
}
