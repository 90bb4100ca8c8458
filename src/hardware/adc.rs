//! The position sensor on ADC1 as the board's [`SensorAdc`]: channel
//! [`super::profile::SENSOR_CHANNEL`] (0, PA0, on the driver board; 6, PA6 — the Feather's
//! A2).
//!
//! The conversion is started by hardware on TIM2's channel 2 compare,
//! [`crate::board::SAMPLE_LEAD_NS`] before the update event that fires the control interrupt
//! ([`super::control_timer`]): sampling is jitter-free, and the conversion is complete when the
//! tick reads the data register, however soon after its start it does. (Started on the update
//! itself, the conversion would still run during the tick's first 1.3 µs: a tick that reached
//! its sensor read sooner — a small model — would read the previous period's sample, a larger
//! one this period's, and the loop's delay would depend on the configuration.)

use core::convert::Infallible;

use stm32f4xx_hal::pac::{ADC1, ADC_COMMON, RCC};

use crate::board::{AdcCode, SensorAdc};

/// Largest 12-bit code.
pub const FULL_SCALE: u32 = 4095;

/// ADC `EXTSEL` value for TIM2's channel 2 compare (RM0090, ADC_CR2): the edge
/// [`crate::board::SAMPLE_LEAD_NS`] before each tick ([`super::control_timer`]).
const EXTSEL_TIM2_CC2: u8 = 0b0011;
/// `EXTEN`: trigger on the rising edge.
const EXTEN_RISING: u8 = 0b01;
/// Sample time 15 ADC cycles (`SMP = 001`); with the 21 MHz ADC clock a conversion takes
/// (15 + 12) / 21 MHz ≈ 1.3 µs.
const SMP_15_CYCLES: u32 = 0b001;
/// ADC clock, Hz: PCLK2 (84 MHz) / 4 (`ADCPRE = 01`).
const ADC_CLOCK_HZ: u64 = 21_000_000;
/// A conversion from its trigger edge, ns, rounded up: the trigger's synchronisation (up to two
/// ADC clocks), the sample time (15) and the 12-bit conversion (12).
pub const CONVERSION_NS: u32 = ((2 + 15 + 12) * 1_000_000_000u64).div_ceil(ADC_CLOCK_HZ) as u32;
// The conversion started `SAMPLE_LEAD_NS` before the tick is complete when the tick starts.
const _: () = assert!(CONVERSION_NS < crate::board::SAMPLE_LEAD_NS);
/// The sensor's channel (0…9: its sample time is in `SMPR2`).
const CHANNEL: u8 = super::profile::SENSOR_CHANNEL;
#[allow(clippy::absurd_extreme_comparisons)] // 0 on the driver board
const _: () = assert!(CHANNEL <= 9);

/// ADC1 converting the sensor's channel on each TIM2 channel 2 compare (and, when added, the analog
/// setpoint input on ADC2: [`SensorInput::with_setpoint_input`]).
pub struct SensorInput {
    adc: ADC1,
    setpoint: Option<super::setpoint_adc::SetpointChannel>,
}

impl SensorInput {
    /// Enables ADC1 (clock PCLK2 / 4 = 21 MHz), one-channel regular sequence on the sensor's
    /// channel, external trigger TIM2's channel 2 compare on the rising edge. Its pin must already be in
    /// analog mode.
    pub fn new(adc: ADC1, common: &ADC_COMMON, rcc: &RCC) -> Self {
        rcc.apb2enr().modify(|_, w| w.adc1en().set_bit());
        common.ccr().modify(|_, w| unsafe { w.adcpre().bits(0b01) });
        let shift = 3 * CHANNEL as u32;
        adc.smpr2().modify(|r, w| unsafe {
            w.bits(r.bits() & !(0b111 << shift) | SMP_15_CYCLES << shift)
        });
        adc.sqr1().modify(|_, w| unsafe { w.l().bits(0) });
        adc.sqr3().modify(|_, w| unsafe { w.sq1().bits(CHANNEL) });
        adc.cr2().modify(|_, w| unsafe {
            w.extsel()
                .bits(EXTSEL_TIM2_CC2)
                .exten()
                .bits(EXTEN_RISING)
                .adon()
                .set_bit()
        });
        Self {
            adc,
            setpoint: None,
        }
    }

    /// Adds the analog setpoint input ([`crate::sources::analog_input`]) converted beside the sensor.
    pub fn with_setpoint_input(self, input: super::setpoint_adc::SetpointChannel) -> Self {
        Self {
            setpoint: Some(input),
            ..self
        }
    }
}

impl SensorAdc for SensorInput {
    type Error = Infallible;

    fn full_scale(&self) -> AdcCode {
        AdcCode(FULL_SCALE)
    }

    #[inline(always)]
    fn read(&mut self) -> Result<AdcCode, Infallible> {
        Ok(AdcCode(self.adc.dr().read().bits() & FULL_SCALE))
    }

    #[inline(always)]
    fn setpoint_input(&mut self) -> Option<u16> {
        self.setpoint.as_ref().map(|s| s.read())
    }
}
