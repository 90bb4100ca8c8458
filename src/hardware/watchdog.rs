//! The independent watchdog (IWDG, on the 32 kHz LSI), fed from the control tick: if the tick
//! stops (a hung interrupt, a fault loop) the MCU resets within [`TIMEOUT_MS`]. After the
//! reset, [`super::reset_cause`] tells the firmware it was the watchdog.

use stm32f4xx_hal::pac::{DBGMCU, IWDG};

/// Watchdog timeout, ms (LSI 32 kHz / 8 = 4 kHz counter, reload 4 × 20 − 1): the board's
/// [`crate::board::WATCHDOG_TIMEOUT_MS`].
pub const TIMEOUT_MS: u32 = crate::board::WATCHDOG_TIMEOUT_MS;

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

/// Timeout while a flash write stalls the tick, ms (prescaler /256: 125 Hz, reload 1000).
pub const FLASH_WRITE_TIMEOUT_MS: u32 = 8_000;

fn iwdg() -> &'static stm32f4xx_hal::pac::iwdg::RegisterBlock {
    // SAFETY: the IWDG's registers are written here only from the command handler's task
    // around a flash write, while the tick's `Watchdog::feed` writes only KR (a reload); a
    // reload between the two configuration writes reloads the old or the new value, both
    // long enough.
    unsafe { &*IWDG::ptr() }
}

/// Waits (bounded) until the IWDG has taken a new prescaler and reload value.
fn wait_updated() {
    let w = iwdg();
    for _ in 0..1_000_000 {
        let sr = w.sr().read();
        if sr.pvu().bit_is_clear() && sr.rvu().bit_is_clear() {
            return;
        }
    }
}

fn configure(prescaler: u8, reload: u16) {
    let w = iwdg();
    w.kr().write(|w| unsafe { w.key().bits(KEY_FEED) });
    wait_updated();
    w.kr().write(|w| unsafe { w.key().bits(KEY_UNLOCK) });
    w.pr().write(|w| unsafe { w.pr().bits(prescaler) });
    w.rlr().write(|w| unsafe { w.rl().bits(reload) });
    wait_updated();
    w.kr().write(|w| unsafe { w.key().bits(KEY_FEED) });
}

/// Lengthens the timeout to [`FLASH_WRITE_TIMEOUT_MS`]: a flash sector erase stalls every
/// fetch from flash, the tick (which feeds the watchdog) included, for up to 2 s.
pub fn stretch_for_flash_write() {
    configure(0b110, (FLASH_WRITE_TIMEOUT_MS / 8) as u16); // /256: 8 ms a count
}

/// Back to [`TIMEOUT_MS`] after a flash write.
pub fn restore_timeout() {
    configure(0b001, (TIMEOUT_MS * 4 - 1) as u16);
}
