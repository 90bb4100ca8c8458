//! Emulated converters of the board, and the analog side they connect to.
//!
//! * [`internal_dac`] — the STM32's 12-bit dual DAC.
//! * [`amplifier`] — the piezo amplifier: gain to 0–150 V, rails, slew limit, noise.
//! * [`position_sensor`] — displacement (µm) to sensor volts, with noise.
//! * [`internal_adc`] — a sensor ADC: resolution, range, pipeline latency.
//! * [`dac856x_chip`], [`ads8689_chip`] — the external SPI converters, emulated at the wire
//!   level: they implement `embedded_hal::spi::SpiDevice`, decode the datasheet's command
//!   words, and report malformed frames.
//! * [`noise`] — the seeded Gaussian source every noisy element draws from.
//!
//! [`AnalogDualDac`] and [`AnalogSensorAdc`] are the two seams a simulated board needs beyond
//! the library's [`DualDac`] and [`SensorAdc`]: the DAC's output voltages, and the ADC's
//! analog input.

pub mod ads8689_chip;
pub mod amplifier;
pub mod dac856x_chip;
pub mod internal_adc;
pub mod internal_dac;
pub mod noise;
pub mod position_sensor;

pub use ads8689_chip::{Ads8689FrameError, EmulatedAds8689};
pub use amplifier::{Amplifier, AmplifierConfig};
pub use dac856x_chip::{Dac856xFrameError, Dac856xVariant, EmulatedDac856x};
pub use internal_adc::{InternalAdc, InternalAdcError};
pub use internal_dac::{InternalDac, InternalDacError};
pub use noise::GaussianNoise;
pub use position_sensor::PositionSensor;

use twinstack::board::{DualDac, SensorAdc};
use twinstack::converters::{Ads8689, Dac856x};

/// A dual DAC whose analog outputs the simulator can read.
pub trait AnalogDualDac: DualDac {
    /// The two output voltages `[left, right]`, volts.
    fn output_volts(&self) -> [f64; 2];
}

/// A sensor ADC whose analog input the simulator drives.
pub trait AnalogSensorAdc: SensorAdc {
    /// Sets the voltage at the ADC input (sampled at the next conversion).
    fn set_input_volts(&mut self, volts: f64);
}

impl AnalogDualDac for Dac856x<EmulatedDac856x> {
    /// DAC-A drives the left stack, DAC-B the right one.
    fn output_volts(&self) -> [f64; 2] {
        self.device().output_volts()
    }
}

impl AnalogSensorAdc for Ads8689<EmulatedAds8689> {
    fn set_input_volts(&mut self, volts: f64) {
        self.device_mut().set_input_volts(volts);
    }
}
