//! Clock tree: the board's HSE crystal ([`super::profile::HSE_HZ`]: 8 MHz on the driver board,
//! 12 MHz on the Feather) → PLL → 168 MHz SYSCLK, or the reset HSI (emulator).
//!
//! The HAL picks the PLL's dividers (`stm32f4xx-hal` 0.23, `rcc/f4/pll.rs`, `fast_setup`): the
//! smallest M that brings the crystal to the VCO input's 2 MHz top, N for a 336 MHz VCO, P = 2,
//! and Q for the 48 MHz clock at or below 48 MHz:
//!
//! | crystal | M | VCO in | N | VCO out | P | SYSCLK | Q | 48 MHz clock (USB, SDIO, RNG) |
//! |---|---:|---:|---:|---:|---:|---:|---:|---:|
//! | 8 MHz (driver board) | 4 | 2 MHz | 168 | 336 MHz | 2 | 168 MHz | 7 | 48 MHz |
//! | 12 MHz (Feather) | 6 | 2 MHz | 168 | 336 MHz | 2 | 168 MHz | 7 | 48 MHz |
//!
//! The image logs the PLL configuration it reads back from `RCC_PLLCFGR` at boot ([`Pll`]), so
//! the table is checked on the board by `probe-rs run`'s output. The image uses no USB; the
//! 48 MHz figure is what the Feather's DFU bootloader and any later USB link would have.

use stm32f4xx_hal::pac::RCC;
#[cfg(not(feature = "emulator"))]
use stm32f4xx_hal::prelude::*;
use stm32f4xx_hal::rcc::{Rcc, RccExt};

/// The bus clocks the firmware's peripherals are set up from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BusClocks {
    /// Core clock, Hz.
    pub sysclk_hz: u32,
    /// APB1 clock (USART3: the Feather's host link), Hz.
    pub pclk1_hz: u32,
    /// APB2 clock (USART1: the driver board's host link; ADC), Hz.
    pub pclk2_hz: u32,
    /// TIM2's kernel clock (APB1 timer clock), Hz.
    pub tim2_hz: u32,
    /// Clock that SysTick counts (emulator tick source), Hz.
    pub systick_hz: u32,
}

/// The main PLL's dividers, as `RCC_PLLCFGR` holds them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Pll {
    /// Input divider M (2…63).
    pub m: u32,
    /// VCO multiplier N (50…432).
    pub n: u32,
    /// System clock divider P (2, 4, 6 or 8).
    pub p: u32,
    /// 48 MHz clock divider Q (2…15).
    pub q: u32,
}

impl Pll {
    /// The dividers the clock set-up left in `RCC_PLLCFGR`.
    pub fn read_back() -> Self {
        // SAFETY: a read of a configuration register, after `configure` has written it.
        let cfg = unsafe { &*RCC::ptr() }.pllcfgr().read().bits();
        Self {
            m: cfg & 0x3F,
            n: (cfg >> 6) & 0x1FF,
            p: 2 * (((cfg >> 16) & 0b11) + 1),
            q: (cfg >> 24) & 0xF,
        }
    }
}

/// Board: the HSE crystal ([`super::profile::HSE_HZ`]), PLL to SYSCLK 168 MHz, AHB 168 MHz,
/// APB1 42 MHz (timers 84 MHz), APB2 84 MHz. The HAL sets the flash wait states to match.
#[cfg(not(feature = "emulator"))]
pub fn configure(rcc: RCC) -> (Rcc, BusClocks) {
    let rcc = rcc.freeze(
        stm32f4xx_hal::rcc::Config::hse(super::profile::HSE_HZ.Hz())
            .sysclk(168.MHz())
            .hclk(168.MHz())
            .pclk1(42.MHz())
            .pclk2(84.MHz()),
    );
    let c = rcc.clocks;
    let clocks = BusClocks {
        sysclk_hz: c.sysclk().raw(),
        pclk1_hz: c.pclk1().raw(),
        pclk2_hz: c.pclk2().raw(),
        tim2_hz: c.timclk1().raw(),
        systick_hz: c.hclk().raw(),
    };
    (rcc, clocks)
}

/// Emulator: the reset clock (HSI 16 MHz) is kept, because QEMU does not model RCC and a PLL
/// set-up would poll ready bits forever. QEMU clocks SysTick at its fixed 168 MHz model
/// frequency whatever RCC says, so the SysTick rate is computed from that.
#[cfg(feature = "emulator")]
pub fn configure(rcc: RCC) -> (Rcc, BusClocks) {
    let rcc = rcc.constrain();
    let clocks = BusClocks {
        sysclk_hz: 16_000_000,
        pclk1_hz: 16_000_000,
        pclk2_hz: 16_000_000,
        tim2_hz: 16_000_000,
        systick_hz: 168_000_000,
    };
    (rcc, clocks)
}
