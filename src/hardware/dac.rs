//! The STM32's 12-bit DAC as the board's [`DualDac`]: channel 1 (PA4) drives the left stack,
//! channel 2 (PA5) the right one.
//!
//! Both codes go in **one** 32-bit store to the dual holding register `DHR12RD`
//! (`right << 16 | left`), and both channels are triggered by TIM2's `TRGO` (the control
//! timer's update event, [`super::control_timer`]): the holding registers move to the outputs
//! together at the next timer event, three APB1 clocks after it. So the two stacks never see a
//! skewed pair, and the instant a tick's drive appears is set by the timer — the period's
//! first instant — not by when the interrupt started or how long the tick took to compute it
//! ([`crate::board::sample_to_output_s`]). The cost is latency: the drive waits for the next
//! event, a whole period after the sample it was computed from (plus the sample's lead).
//!
//! The panic and fault paths ([`force_both`]) drop the trigger first, so the safe codes go out
//! at once rather than at a timer event that may not come.

use core::convert::Infallible;

use stm32f4xx_hal::pac::{DAC, RCC};

use crate::board::{DacCode, DualDac};

/// Largest 12-bit code.
pub const FULL_SCALE: u16 = 4095;

/// Both DAC channels, written together.
pub struct InternalDac {
    dac: DAC,
}

/// Packs two codes (clamped to 12 bits) into the `DHR12RD` layout.
#[inline(always)]
fn dual_word(left: DacCode, right: DacCode) -> u32 {
    clamp_12_bits(right) << 16 | clamp_12_bits(left)
}

/// A code clamped to 12 bits (`min(code, 4095)`) in one `USAT #12`, where the compiler,
/// knowing a `u16` is never negative, would emit a compare and a conditional move.
#[inline(always)]
fn clamp_12_bits(code: DacCode) -> u32 {
    const _: () = assert!(FULL_SCALE == (1 << 12) - 1);
    let clamped: u32;
    // SAFETY: one data-processing instruction on registers: no memory, no stack.
    unsafe {
        core::arch::asm!(
            "usat {out}, #12, {code}",
            out = lateout(reg) clamped,
            code = in(reg) code.0 as u32,
            options(pure, nomem, nostack),
        )
    };
    clamped
}

impl InternalDac {
    /// Enables the DAC's clock and both channels (output buffers on), starting at `initial` on
    /// both channels, then hands their updates to TIM2's `TRGO`. PA4/PA5 must already be in
    /// analog mode; the control timer starts after this ([`super::control_timer`]).
    pub fn new(dac: DAC, rcc: &RCC, initial: (DacCode, DacCode)) -> Self {
        rcc.apb1enr().modify(|_, w| w.dacen().set_bit());
        // Load the initial codes before enabling, untriggered, so the outputs start there at
        // once (one APB1 clock later) …
        dac.dhr12rd()
            .write(|w| unsafe { w.bits(dual_word(initial.0, initial.1)) });
        dac.cr().write(|w| w.en1().set_bit().en2().set_bit());
        // … then every later write waits for the timer's update (TSEL = TIM2 TRGO).
        dac.cr().modify(|_, w| {
            w.tsel1()
                .tim2trgo()
                .ten1()
                .set_bit()
                .tsel2()
                .tim2trgo()
                .ten2()
                .set_bit()
        });
        Self { dac }
    }
}

impl DualDac for InternalDac {
    type Error = Infallible;

    fn full_scale(&self) -> DacCode {
        DacCode(FULL_SCALE)
    }

    #[inline(always)]
    fn write_both(&mut self, left: DacCode, right: DacCode) -> Result<(), Infallible> {
        self.dac
            .dhr12rd()
            .write(|w| unsafe { w.bits(dual_word(left, right)) });
        Ok(())
    }
}

/// Writes both channels without owning the DAC: for the panic and hard-fault paths only
/// ([`super::safe_state`]), after everything else has stopped.
pub(crate) fn force_both(left: DacCode, right: DacCode) {
    // SAFETY: called with interrupts disabled on the way to a halt; nothing else touches the
    // DAC any more. A single store to DHR12RD is atomic with respect to the peripheral.
    let dac = unsafe { &*DAC::ptr() };
    // Untriggered first: the codes then reach the outputs one APB1 clock after the store,
    // without waiting for a timer event.
    dac.cr()
        .modify(|_, w| w.ten1().clear_bit().ten2().clear_bit());
    dac.dhr12rd()
        .write(|w| unsafe { w.bits(dual_word(left, right)) });
}
