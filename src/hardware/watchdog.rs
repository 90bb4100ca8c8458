//! The independent watchdog (IWDG, on the 32 kHz LSI), fed from the control tick: if the tick
//! stops (a hung interrupt, a fault loop) the MCU resets within [`TIMEOUT_MS`].

use stm32f4xx_hal::pac::{DBGMCU, IWDG};

/// Watchdog timeout, ms (LSI 32 kHz / 8 = 4 kHz counter, reload 4 × 20 − 1).
pub const TIMEOUT_MS: u32 = 20;

const KEY_UNLOCK: u16 = 0x5555;
const KEY_FEED: u16 = 0xAAAA;
const KEY_START: u16 = 0xCCCC;

/// The running watchdog.
pub struct Watchdog {
    iwdg: IWDG,
}

impl Watchdog {
    /// Starts the IWDG with [`TIMEOUT_MS`]. It cannot be stopped again (until reset). While
    /// a debugger holds the core halted (a breakpoint), the watchdog's counter is frozen too,
    /// so debugging does not reset the board.
    pub fn start(iwdg: IWDG, dbgmcu: &DBGMCU) -> Self {
        dbgmcu.apb1_fz().modify(|_, w| w.dbg_iwdg_stop().set_bit());
        iwdg.kr().write(|w| unsafe { w.key().bits(KEY_UNLOCK) });
        iwdg.pr().write(|w| unsafe { w.pr().bits(0b001) }); // /8
        iwdg.rlr()
            .write(|w| unsafe { w.rl().bits((TIMEOUT_MS * 4 - 1) as u16) });
        iwdg.kr().write(|w| unsafe { w.key().bits(KEY_FEED) });
        iwdg.kr().write(|w| unsafe { w.key().bits(KEY_START) });
        Self { iwdg }
    }

    /// Reloads the counter (one store).
    #[inline(always)]
    pub fn feed(&mut self) {
        self.iwdg.kr().write(|w| unsafe { w.key().bits(KEY_FEED) });
    }
}
