//! The analog setpoint input ([`crate::sources::analog_input`]) on ADC2, 0–3.3 V, converted on the same
//! TIM2 channel 2 compare as the sensor on ADC1: both conversions start together,
//! [`crate::board::SAMPLE_LEAD_NS`] before the control interrupt that reads them, so the input's
//! value just before the period's start is what that period's tick computes (and the DAC puts
//! out at the next timer event).
//!
//! | board | pin | ADC2 channel |
//! |-------|-----|--------------|
//! | driver board | PC3 | 13 |
//! | Feather STM32F405 (feature `feather`) | A3 (PA7) | 7 |
//!
//! ADC2 rather than an injected channel of ADC1: an injected conversion triggered with the
//! regular one would interrupt the sensor's conversion and delay it; two ADCs convert in
//! parallel and the sensor's timing is unchanged.

use stm32f4xx_hal::pac::{ADC2, RCC};

/// ADC `EXTSEL` value for TIM2's channel 2 compare (RM0090, ADC_CR2): the edge
/// [`crate::board::SAMPLE_LEAD_NS`] before each tick ([`super::control_timer`]).
const EXTSEL_TIM2_CC2: u8 = 0b0011;
/// `EXTEN`: trigger on the rising edge.
const EXTEN_RISING: u8 = 0b01;
/// Sample time 15 ADC cycles (`SMP = 001`), as the sensor's: (15 + 12) / 21 MHz ≈ 1.3 µs.
const SMP_15_CYCLES: u32 = 0b001;

/// The input's GPIO port (0 A … 2 C: its `AHB1ENR` bit and its register block's index),
/// pin and ADC channel: PC3, ADC123_IN13, on the driver board.
#[cfg(not(feature = "feather"))]
const INPUT: (u32, u32, u8) = (2, 3, 13);
/// On the Feather: A3, PA7, ADC12_IN7 (PC3 is its frame clock D11).
#[cfg(feature = "feather")]
const INPUT: (u32, u32, u8) = (0, 7, 7);

/// GPIOA's base address; the ports follow every 0x400 bytes (RM0090, memory map).
const GPIO_BASE: usize = 0x4002_0000;

/// ADC2 converting the input's channel on each TIM2 channel 2 compare (the ADC clock prescaler is the
/// common one [`super::adc::SensorInput::new`] sets).
pub struct SetpointChannel {
    adc: ADC2,
}

impl SetpointChannel {
    /// Puts the input's pin in analog mode, enables ADC2, one-channel regular sequence on
    /// the input's channel, external trigger TIM2's channel 2 compare on the rising edge. Called after every
    /// `split()` of the pin's port (which resets it): the pin is set by its own `MODER`
    /// bits, so the other pins of that port stay as they are.
    pub fn new(adc: ADC2, rcc: &RCC) -> Self {
        let (port, pin, channel) = INPUT;
        rcc.ahb1enr()
            .modify(|r, w| unsafe { w.bits(r.bits() | (1 << port)) });
        // SAFETY: one read-modify-write of the pin's two MODER bits (offset 0 of its port)
        // during init, before any interrupt runs; no other code owns this pin.
        unsafe {
            let moder = (GPIO_BASE + 0x400 * port as usize) as *mut u32;
            moder.write_volatile(moder.read_volatile() | (0b11 << (2 * pin)));
        }
        rcc.apb2enr().modify(|_, w| w.adc2en().set_bit());
        if channel < 10 {
            let shift = 3 * channel as u32;
            adc.smpr2().modify(|r, w| unsafe {
                w.bits((r.bits() & !(0b111 << shift)) | (SMP_15_CYCLES << shift))
            });
        } else {
            let shift = 3 * (channel as u32 - 10);
            adc.smpr1().modify(|r, w| unsafe {
                w.bits((r.bits() & !(0b111 << shift)) | (SMP_15_CYCLES << shift))
            });
        }
        adc.sqr1().modify(|_, w| unsafe { w.l().bits(0) });
        adc.sqr3().modify(|_, w| unsafe { w.sq1().bits(channel) });
        adc.cr2().modify(|_, w| unsafe {
            w.extsel()
                .bits(EXTSEL_TIM2_CC2)
                .exten()
                .bits(EXTEN_RISING)
                .adon()
                .set_bit()
        });
        Self { adc }
    }

    /// The most recent conversion as UQ0.16 of the span (the 12-bit code shifted left by 4).
    #[inline(always)]
    pub fn read(&self) -> u16 {
        ((self.adc.dr().read().bits() & 0x0fff) << 4) as u16
    }
}
