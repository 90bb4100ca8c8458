//! Why the MCU last started: the reset flags of `RCC_CSR` (RM0090 §7.3.21), read once at
//! boot and then cleared (`RMVF`), so the next start reports its own cause. The firmware
//! reports a watchdog reset in its status
//! ([`crate::protocol::messages::StatusReport::WATCHDOG_RESET`]).

use stm32f4xx_hal::pac::RCC;

/// The cause of the last reset, the most specific flag first (a watchdog or software reset
/// also pulls the reset pin, so `PINRSTF` is set beside it).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ResetCause {
    /// The independent watchdog (the tick stopped feeding it).
    IndependentWatchdog,
    /// The window watchdog (not used by the firmware).
    WindowWatchdog,
    /// Low-power management (entering standby or stop with the option bytes set so).
    LowPower,
    /// A software reset (`SYSRESETREQ`: a debugger or a probe).
    Software,
    /// Power on, or a brown-out.
    PowerOn,
    /// The NRST pin (the reset button, a probe).
    Pin,
    /// No flag set (QEMU models no reset flags).
    Unknown,
}

impl ResetCause {
    /// The cause the flags in `RCC_CSR`'s bits 24–31 give.
    pub fn from_csr(csr: u32) -> Self {
        const LPWRRSTF: u32 = 1 << 31;
        const WWDGRSTF: u32 = 1 << 30;
        const IWDGRSTF: u32 = 1 << 29;
        const SFTRSTF: u32 = 1 << 28;
        const PORRSTF: u32 = 1 << 27;
        const PINRSTF: u32 = 1 << 26;
        const BORRSTF: u32 = 1 << 25;
        if csr & IWDGRSTF != 0 {
            ResetCause::IndependentWatchdog
        } else if csr & WWDGRSTF != 0 {
            ResetCause::WindowWatchdog
        } else if csr & LPWRRSTF != 0 {
            ResetCause::LowPower
        } else if csr & SFTRSTF != 0 {
            ResetCause::Software
        } else if csr & (PORRSTF | BORRSTF) != 0 {
            ResetCause::PowerOn
        } else if csr & PINRSTF != 0 {
            ResetCause::Pin
        } else {
            ResetCause::Unknown
        }
    }

    /// The cause in a few words, for the boot log.
    pub fn as_str(self) -> &'static str {
        match self {
            ResetCause::IndependentWatchdog => "independent watchdog",
            ResetCause::WindowWatchdog => "window watchdog",
            ResetCause::LowPower => "low-power management",
            ResetCause::Software => "software (a debugger or probe)",
            ResetCause::PowerOn => "power on or brown-out",
            ResetCause::Pin => "the reset pin",
            ResetCause::Unknown => "unknown (no flag set)",
        }
    }

    /// Whether a watchdog reset the MCU.
    pub fn is_watchdog(self) -> bool {
        matches!(
            self,
            ResetCause::IndependentWatchdog | ResetCause::WindowWatchdog
        )
    }

    /// Reads the flags and clears them (`RMVF`), so the next start reports its own cause.
    /// Called once, in `init`.
    pub fn take(rcc: &RCC) -> Self {
        let cause = Self::from_csr(rcc.csr().read().bits());
        rcc.csr().modify(|_, w| w.rmvf().set_bit());
        cause
    }
}
