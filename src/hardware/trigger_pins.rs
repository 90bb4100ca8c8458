//! The trigger I/O pins ([`crate::sources::scan`]): pixel, line and frame clock outputs on pins 1, 2, 3
//! (push-pull), a sequence's settled output on pin 7 (push-pull, [`crate::sources::sequence`]), the
//! external trigger input on pin 6 (pull-down, 3.3 V logic; 5 V tolerant as an FT pin) of the
//! board profile's trigger port ([`super::profile::TRIGGER_PORT`]: PA1–PA3, PA6, PA7 on the
//! driver board; PC1–PC3, PC6, PC7 — D13, D12, D11, D6, D5 — on the Feather). All five on one
//! port, so the tick writes the four outputs in one `BSRR` store
//! ([`crate::sources::scan::bsrr_word`]) and reads the input in one `IDR` load: constant time, every
//! tick (the outputs are written even when they do not change).
//!
//! QEMU's `netduinoplus2` models no GPIO: the stores land in an unimplemented-device region
//! (logged with `-d unimp`, which is how the emulator test sees them) and `IDR` reads 0. So
//! that the tick an input edge fires on is measured too, the emulator images read the input
//! from a word in RAM instead ([`EMULATED_INPUT`], one load as the `IDR`'s): low unless the
//! image drives it, as the whole-interrupt bench's image does.

use stm32f4xx_hal::gpio::{Input, Output, Pin, PushPull};

#[cfg(feature = "emulator")]
use core::sync::atomic::{AtomicBool, Ordering};

use super::profile::{trigger_port, TRIGGER_PORT as P};
use crate::sources::scan::bsrr_word;
#[cfg(not(feature = "emulator"))]
use crate::sources::scan::INPUT_PIN;

/// The external trigger input's level in the emulator images (QEMU models no GPIO): what
/// [`TriggerPins::input`] reads there instead of the port's `IDR`. Low at reset; an image that
/// measures the trigger's tick sets it between ticks.
#[cfg(feature = "emulator")]
pub static EMULATED_INPUT: AtomicBool = AtomicBool::new(false);

/// The four pins, configured; the tick's handle on them.
pub struct TriggerPins {
    _pixel: Pin<P, 1, Output<PushPull>>,
    _line: Pin<P, 2, Output<PushPull>>,
    _frame: Pin<P, 3, Output<PushPull>>,
    _input: Pin<P, 6, Input>,
    _settled: Pin<P, 7, Output<PushPull>>,
}

impl TriggerPins {
    /// Takes the configured pins (outputs low, input pulled down).
    pub fn new(
        pixel: Pin<P, 1, Output<PushPull>>,
        line: Pin<P, 2, Output<PushPull>>,
        frame: Pin<P, 3, Output<PushPull>>,
        input: Pin<P, 6, Input>,
        settled: Pin<P, 7, Output<PushPull>>,
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
        // sets or resets, and no other code writes the port's BSRR from an interrupt.
        trigger_port()
            .bsrr()
            .write(|w| unsafe { w.bits(bsrr_word(levels)) });
    }

    /// The input's level: one `IDR` load (in the emulator images, one load of
    /// [`EMULATED_INPUT`]).
    #[inline(always)]
    pub fn input(&self) -> bool {
        #[cfg(feature = "emulator")]
        {
            EMULATED_INPUT.load(Ordering::Relaxed)
        }
        // A read of the input data register has no side effect.
        #[cfg(not(feature = "emulator"))]
        {
            trigger_port().idr().read().bits() & (1 << INPUT_PIN) != 0
        }
    }
}
