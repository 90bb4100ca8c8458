//! The trigger I/O pins ([`crate::scan`]): pixel, line and frame clock outputs on PA1, PA2,
//! PA3 (push-pull), a sequence's settled output on PA7 (push-pull, [`crate::sequence`]), the
//! external trigger input on PA6 (pull-down, 3.3 V logic; 5 V tolerant as an FT pin). All
//! five on GPIOA, so the tick writes the four outputs in one `BSRR` store
//! ([`crate::scan::bsrr_word`]) and reads the input in one `IDR` load: constant time, every
//! tick (the outputs are written even when they do not change).
//!
//! QEMU's `netduinoplus2` models no GPIO: the stores land in an unimplemented-device region
//! (logged with `-d unimp`, which is how the emulator test sees them) and `IDR` reads 0.

use stm32f4xx_hal::gpio::{Input, Output, Pin, PushPull};
use stm32f4xx_hal::pac;

use crate::scan::{bsrr_word, INPUT_PIN};

/// The four pins, configured; the tick's handle on them.
pub struct TriggerPins {
    _pixel: Pin<'A', 1, Output<PushPull>>,
    _line: Pin<'A', 2, Output<PushPull>>,
    _frame: Pin<'A', 3, Output<PushPull>>,
    _input: Pin<'A', 6, Input>,
    _settled: Pin<'A', 7, Output<PushPull>>,
}

impl TriggerPins {
    /// Takes the configured pins (outputs low, input pulled down).
    pub fn new(
        pixel: Pin<'A', 1, Output<PushPull>>,
        line: Pin<'A', 2, Output<PushPull>>,
        frame: Pin<'A', 3, Output<PushPull>>,
        input: Pin<'A', 6, Input>,
        settled: Pin<'A', 7, Output<PushPull>>,
    ) -> Self {
        Self {
            _pixel: pixel,
            _line: line,
            _frame: frame,
            _input: input,
            _settled: settled,
        }
    }

    /// Puts the outputs at `levels` (bit 0 pixel, 1 line, 2 frame, 4 settled): one `BSRR`
    /// store.
    #[inline(always)]
    pub fn write(&mut self, levels: u8) {
        // SAFETY: BSRR is write-only and atomic per bit; this struct owns the four pins it
        // sets or resets, and no other code writes GPIOA's BSRR from an interrupt.
        let gpioa = unsafe { &*pac::GPIOA::ptr() };
        gpioa.bsrr().write(|w| unsafe { w.bits(bsrr_word(levels)) });
    }

    /// The input's level: one `IDR` load.
    #[inline(always)]
    pub fn input(&self) -> bool {
        // SAFETY: a read of the input data register has no side effect.
        let gpioa = unsafe { &*pac::GPIOA::ptr() };
        gpioa.idr().read().bits() & (1 << INPUT_PIN) != 0
    }
}
