//! Drivers for the board's external SPI converters, over `embedded-hal` 1.0's
//! [`SpiDevice`](embedded_hal::spi::SpiDevice) (one device transaction = one frame with chip
//! select / SYNC held low).
//!
//! * [`dac856x`] — TI DAC8562/DAC8563, dual 16-bit DAC: the two stacks' drive, both channels
//!   updated by one command. Implements [`DualDac`](crate::board::DualDac).
//! * [`ads8689`] — TI ADS8689, 16-bit 100 kSPS SAR ADC: the position sensor. Implements
//!   [`SensorAdc`](crate::board::SensorAdc).
//!
//! Both are `no_std` and allocation-free; the per-sample calls (`write_both`, `read`) are one or
//! two fixed-size SPI transactions with no panic path.

pub mod ads8689;
pub mod dac856x;

pub use ads8689::{Ads8689, Ads8689Error, InputRange};
pub use dac856x::{Dac856x, Gain};
