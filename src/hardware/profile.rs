//! The board profile: which STM32F405 board the image runs on — its crystal, which pins carry
//! the stacks' drives, the sensor, the host link and the trigger I/O, and which USART and DMA
//! streams the link uses. Everything else (the control tick, the converters' drivers, the
//! watchdog, the parameter sector, the RTIC shell) is the same code on every board.
//!
//! **The driver board** (default): the project's own board, an STM32F405RG with an 8 MHz
//! crystal, its pins in the table of [`super`].
//!
//! **Adafruit Feather STM32F405 Express** (feature `feather`; images `twinstack-feather` and, for
//! QEMU, `twinstack-feather-emu`): the same chip (STM32F405RGT6: 1 MiB flash, 128 KiB SRAM and 64
//! KiB CCM) on a dev board with a 12 MHz crystal. Its header pins A0 and A1 are PA4 and PA5, the
//! chip's own DAC outputs, so the drives stay on the internal DAC (no extra hardware: a resistor
//! and a capacitor make a first load); the sensor moves to A2 (PA6, ADC1 channel 6), because
//! PA0–PA2 are not connected and PA3 measures the battery; the host link is USART3 on the TX/RX
//! pins (PB10/PB11), and the trigger I/O moves to port C, where D13, D12, D11, D6 and D5 are PC1,
//! PC2, PC3, PC6 and PC7 — the same pin numbers as PA1–PA3, PA6 and PA7 on the driver board, so
//! the tick's one-store write ([`crate::sources::scan::bsrr_word`]) is unchanged.
//!
//! | signal | driver board | Feather pin (MCU pin) | peripheral |
//! |--------|--------------|-----------------------|------------|
//! | left stack drive `u_l` | PA4 | A0 (PA4) | DAC channel 1 |
//! | right stack drive `u_r` | PA5 | A1 (PA5) | DAC channel 2 |
//! | position sensor | PA0 | A2 (PA6) | ADC1 channel 0 / channel 6, started by TIM2 TRGO |
//! | host link TX / RX | PA9 / PA10 (USART1) | TX / RX (PB10 / PB11, USART3) | AF7 |
//! | pixel / line / frame clock out | PA1 / PA2 / PA3 | D13 / D12 / D11 (PC1 / PC2 / PC3) | GPIO push-pull |
//! | external trigger in | PA6 | D6 (PC6) | GPIO input, pull-down |
//! | settled out | PA7 | D5 (PC7) | GPIO push-pull |
//!
//! The Feather's pins as checked against its public definitions (MicroPython's
//! `ports/stm32/boards/ADAFRUIT_F405_EXPRESS/pins.csv` and `mpconfigboard.h`): the book's
//! bring-up chapter lists them. D13 also lights the board's red LED (a few mA), which then
//! shows the pixel clock. The dual-stage coarse axis needs pins the Feather does not bring
//! out (TIM8's PC6/PC7 are the trigger I/O here): the `feather` and `dual-stage` features are
//! refused together.

use stm32f4xx_hal::pac;

#[cfg(all(feature = "feather", feature = "dual-stage"))]
compile_error!(
    "the Feather profile has no coarse axis: its TIM8 encoder pins (PC6/PC7) carry the trigger \
     I/O and its TIM1/TIM4 pins are not all on the header; build the dual stage for the \
     driver board (`cargo build-fw-dual`)"
);

/// The board's name, in the start-up log.
#[cfg(not(feature = "feather"))]
pub const NAME: &str = "driver board";
/// The board's name, in the start-up log.
#[cfg(feature = "feather")]
pub const NAME: &str = "Adafruit Feather STM32F405 Express";

/// The HSE crystal, Hz: 8 MHz on the driver board.
#[cfg(not(feature = "feather"))]
pub const HSE_HZ: u32 = 8_000_000;
/// The HSE crystal, Hz: 12 MHz on the Feather.
#[cfg(feature = "feather")]
pub const HSE_HZ: u32 = 12_000_000;

/// The sensor's ADC1 channel: 0 (PA0) on the driver board.
#[cfg(not(feature = "feather"))]
pub const SENSOR_CHANNEL: u8 = 0;
/// The sensor's ADC1 channel: 6 (PA6, the Feather's A2).
#[cfg(feature = "feather")]
pub const SENSOR_CHANNEL: u8 = 6;

/// The GPIO port of the trigger I/O: A on the driver board.
#[cfg(not(feature = "feather"))]
pub const TRIGGER_PORT: char = 'A';
/// The GPIO port of the trigger I/O: C on the Feather (D13, D12, D11, D6, D5).
#[cfg(feature = "feather")]
pub const TRIGGER_PORT: char = 'C';

/// The trigger port's registers.
#[cfg(not(feature = "feather"))]
pub(crate) fn trigger_port() -> &'static pac::gpioa::RegisterBlock {
    // SAFETY: a shared reference to memory-mapped registers; the callers write only BSRR
    // (atomic per bit, for the pins they own) and read IDR.
    unsafe { &*pac::GPIOA::ptr() }
}
/// The trigger port's registers.
#[cfg(feature = "feather")]
pub(crate) fn trigger_port() -> &'static pac::gpioi::RegisterBlock {
    // SAFETY: as above, for GPIOC.
    unsafe { &*pac::GPIOC::ptr() }
}

/// The host link's USART: USART1 on the driver board.
#[cfg(not(feature = "feather"))]
pub type LinkUsart = pac::USART1;
/// The host link's USART: USART3 on the Feather (its TX/RX header pins).
#[cfg(feature = "feather")]
pub type LinkUsart = pac::USART3;

/// The DMA controller serving the link: DMA2 for USART1 (RM0090, table 43).
#[cfg(not(feature = "feather"))]
pub type LinkDma = pac::DMA2;
/// The DMA controller serving the link: DMA1 for USART3 (RM0090, table 42).
#[cfg(feature = "feather")]
pub type LinkDma = pac::DMA1;

/// The host link's USART and DMA controller, out of the device's peripherals: USART1 and DMA2
/// on the driver board (the others stay unused).
#[cfg(not(feature = "feather"))]
pub fn link_peripherals(
    usart1: pac::USART1,
    _usart3: pac::USART3,
    _dma1: pac::DMA1,
    dma2: pac::DMA2,
) -> (LinkUsart, LinkDma) {
    (usart1, dma2)
}

/// The host link's USART and DMA controller: USART3 and DMA1 on the Feather.
#[cfg(feature = "feather")]
pub fn link_peripherals(
    _usart1: pac::USART1,
    usart3: pac::USART3,
    dma1: pac::DMA1,
    _dma2: pac::DMA2,
) -> (LinkUsart, LinkDma) {
    (usart3, dma1)
}

/// The DMA streams carrying the link's receive and transmit, and their channel: USART1_RX is
/// DMA2 stream 2, USART1_TX stream 7, both channel 4.
#[cfg(not(feature = "feather"))]
pub const LINK_DMA: LinkStreams = LinkStreams {
    rx: 2,
    tx: 7,
    channel: 4,
};
/// USART3_RX is DMA1 stream 1, USART3_TX stream 3, both channel 4.
#[cfg(feature = "feather")]
pub const LINK_DMA: LinkStreams = LinkStreams {
    rx: 1,
    tx: 3,
    channel: 4,
};

/// The link's DMA streams and channel.
#[derive(Clone, Copy, Debug)]
pub struct LinkStreams {
    /// The stream that receives.
    pub rx: usize,
    /// The stream that transmits.
    pub tx: usize,
    /// The channel both select.
    pub channel: u8,
}
