//! Clock tree: 8 MHz HSE → PLL → 168 MHz SYSCLK (board), or the reset HSI (emulator).

use stm32f4xx_hal::pac::RCC;
#[cfg(not(feature = "emulator"))]
use stm32f4xx_hal::prelude::*;
use stm32f4xx_hal::rcc::{Rcc, RccExt};

/// The bus clocks the firmware's peripherals are set up from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BusClocks {
    /// Core clock, Hz.
    pub sysclk_hz: u32,
    /// APB2 clock (USART1, ADC), Hz.
    pub pclk2_hz: u32,
    /// TIM2's kernel clock (APB1 timer clock), Hz.
    pub tim2_hz: u32,
    /// Clock that SysTick counts (emulator tick source), Hz.
    pub systick_hz: u32,
}

/// Board: HSE 8 MHz crystal, PLL to SYSCLK 168 MHz, AHB 168 MHz, APB1 42 MHz (timers 84 MHz),
/// APB2 84 MHz. The HAL sets the flash wait states to match.
#[cfg(not(feature = "emulator"))]
pub fn configure(rcc: RCC) -> (Rcc, BusClocks) {
    let rcc = rcc.freeze(
        stm32f4xx_hal::rcc::Config::hse(8.MHz())
            .sysclk(168.MHz())
            .hclk(168.MHz())
            .pclk1(42.MHz())
            .pclk2(84.MHz()),
    );
    let c = rcc.clocks;
    let clocks = BusClocks {
        sysclk_hz: c.sysclk().raw(),
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
        pclk2_hz: 16_000_000,
        tim2_hz: 16_000_000,
        systick_hz: 168_000_000,
    };
    (rcc, clocks)
}
