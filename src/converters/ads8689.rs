//! TI ADS8689: 16-bit, 100 kSPS single-channel SAR ADC with bipolar and unipolar input ranges
//! and a 4.096 V internal reference (datasheet SBAS781). It digitises the position sensor.
//!
//! ## Wire format
//! Every frame is 32 bits, MSB first (SPI mode 0): a 7-bit opcode, a 9-bit register address,
//! 16 data bits. The rising edge of CONVST/CS ends the frame, executes its command and starts
//! a conversion; the *next* frame shifts that conversion's 16-bit result out on SDO (straight
//! binary), unless the frame before was a register read, in which case the register's 16 bits
//! come out instead. So a conversion is read one frame after it is sampled: the board's one
//! sample of sensor latency.
//!
//! | opcode | command | used here |
//! |---|---|---|
//! | `0000000` | NOP | every sample |
//! | `1101000` | WRITE (16 bits) | range at init |
//! | `1100100` | READ_HWORD | range check at init |
//! | `1100000`, `1101100`, `1101001`, `1101010`, `0100100` | CLEAR_HWORD, SET_HWORD, WRITE MS/LS byte, READ byte | — |
//!
//! Registers are 32 bits wide at byte addresses `0x00, 0x04, …`; a half-word command addresses
//! bits 15–0 at the register's address and bits 31–16 at address + 2. RANGE_SEL_REG (`0x14`):
//! bits 3–0 the range, bit 6 INTREF_DIS (0: internal reference on).

use crate::board::{AdcCode, SensorAdc};
use embedded_hal::spi::SpiDevice;

/// Opcodes (frame bits 31–25).
pub mod opcode {
    /// No operation: the frame only reads the last conversion.
    pub const NOP: u8 = 0b000_0000;
    /// Clear the bits set in the data field.
    pub const CLEAR_HWORD: u8 = 0b110_0000;
    /// Read 16 bits: output in the next frame.
    pub const READ_HWORD: u8 = 0b110_0100;
    /// Read 8 bits: output in the next frame.
    pub const READ: u8 = 0b010_0100;
    /// Write 16 bits.
    pub const WRITE: u8 = 0b110_1000;
    /// Write the upper byte of the half-word.
    pub const WRITE_MSB: u8 = 0b110_1001;
    /// Write the lower byte of the half-word.
    pub const WRITE_LSB: u8 = 0b110_1010;
    /// Set the bits set in the data field.
    pub const SET_HWORD: u8 = 0b110_1100;
}

/// Register addresses.
pub mod register {
    /// DEVICE_ID_REG.
    pub const DEVICE_ID: u16 = 0x00;
    /// RST_PWRCTL_REG.
    pub const RST_PWRCTL: u16 = 0x04;
    /// SDI_CTL_REG (SPI mode).
    pub const SDI_CTL: u16 = 0x08;
    /// SDO_CTL_REG.
    pub const SDO_CTL: u16 = 0x0C;
    /// DATAOUT_CTL_REG.
    pub const DATAOUT_CTL: u16 = 0x10;
    /// RANGE_SEL_REG.
    pub const RANGE_SEL: u16 = 0x14;
    /// ALARM_REG.
    pub const ALARM: u16 = 0x20;
    /// ALARM_H_TH_REG.
    pub const ALARM_H_TH: u16 = 0x24;
    /// ALARM_L_TH_REG.
    pub const ALARM_L_TH: u16 = 0x28;
}

/// RANGE_SEL_REG bits the driver writes (range and INTREF_DIS).
pub const RANGE_SEL_MASK: u16 = 0x004F;
/// The internal reference, volts.
pub const REFERENCE_VOLTS: f64 = 4.096;

/// Input range (RANGE_SEL_REG bits 3–0), in multiples of the 4.096 V reference.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(u16)]
pub enum InputRange {
    /// ±3 × V_ref = ±12.288 V.
    Bipolar3 = 0x0,
    /// ±2.5 × V_ref = ±10.24 V (a ±10 V capacitive-sensor output).
    Bipolar2p5 = 0x1,
    /// ±1.5 × V_ref = ±6.144 V.
    Bipolar1p5 = 0x2,
    /// ±1.25 × V_ref = ±5.12 V.
    Bipolar1p25 = 0x3,
    /// ±0.625 × V_ref = ±2.56 V.
    Bipolar0p625 = 0x4,
    /// 0 … 3 × V_ref = 12.288 V.
    Unipolar3 = 0x8,
    /// 0 … 2.5 × V_ref = 10.24 V.
    Unipolar2p5 = 0x9,
    /// 0 … 1.5 × V_ref = 6.144 V.
    Unipolar1p5 = 0xA,
    /// 0 … 1.25 × V_ref = 5.12 V.
    Unipolar1p25 = 0xB,
}

impl InputRange {
    /// The RANGE_SEL field.
    pub const fn bits(self) -> u16 {
        self as u16
    }

    /// The range for a RANGE_SEL field, `None` for the reserved codes.
    pub const fn from_bits(bits: u16) -> Option<Self> {
        Some(match bits {
            0x0 => Self::Bipolar3,
            0x1 => Self::Bipolar2p5,
            0x2 => Self::Bipolar1p5,
            0x3 => Self::Bipolar1p25,
            0x4 => Self::Bipolar0p625,
            0x8 => Self::Unipolar3,
            0x9 => Self::Unipolar2p5,
            0xA => Self::Unipolar1p5,
            0xB => Self::Unipolar1p25,
            _ => return None,
        })
    }

    /// `(min, max)` input voltage with the internal reference; code 0 is `min`, code 65535 is
    /// one LSB below `max` (straight binary).
    pub fn volts(self) -> (f64, f64) {
        let k = match self {
            Self::Bipolar3 | Self::Unipolar3 => 3.0,
            Self::Bipolar2p5 | Self::Unipolar2p5 => 2.5,
            Self::Bipolar1p5 | Self::Unipolar1p5 => 1.5,
            Self::Bipolar1p25 | Self::Unipolar1p25 => 1.25,
            Self::Bipolar0p625 => 0.625,
        };
        let span = k * REFERENCE_VOLTS;
        if self.bits() & 0x8 == 0 {
            (-span, span)
        } else {
            (0.0, span)
        }
    }
}

/// The 4 bytes of one command frame.
pub const fn frame(opcode: u8, address: u16, data: u16) -> [u8; 4] {
    let word = ((opcode as u32) << 25) | (((address & 0x1FF) as u32) << 16) | data as u32;
    word.to_be_bytes()
}

/// Why initialisation failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Ads8689Error<E> {
    /// The SPI transfer failed.
    Spi(E),
    /// RANGE_SEL_REG read back differently from what was written: the chip is absent, not
    /// listening, or wired wrong.
    RangeNotApplied {
        /// The RANGE_SEL bits written.
        wrote: u16,
        /// The RANGE_SEL bits read back.
        read: u16,
    },
}

/// Driver of an ADS8689 on an SPI device (chip select = CONVST/CS).
#[derive(Debug)]
pub struct Ads8689<SPI> {
    spi: SPI,
}

impl<SPI: SpiDevice> Ads8689<SPI> {
    /// The driver; call [`Ads8689::init`] before the first read.
    pub fn new(spi: SPI) -> Self {
        Self { spi }
    }

    /// Selects `range` with the internal reference, and reads the register back to check it.
    pub fn init(&mut self, range: InputRange) -> Result<(), Ads8689Error<SPI::Error>> {
        let wrote = range.bits();
        let mut reply = [0u8; 4];
        for f in [
            frame(opcode::WRITE, register::RANGE_SEL, wrote),
            frame(opcode::READ_HWORD, register::RANGE_SEL, 0),
            frame(opcode::NOP, 0, 0),
        ] {
            reply = f;
            self.spi
                .transfer_in_place(&mut reply)
                .map_err(Ads8689Error::Spi)?;
        }
        let read = u16::from_be_bytes([reply[0], reply[1]]) & RANGE_SEL_MASK;
        if read != wrote {
            return Err(Ads8689Error::RangeNotApplied { wrote, read });
        }
        Ok(())
    }

    /// The SPI device (for a simulator to look at the emulated chip).
    pub fn device(&self) -> &SPI {
        &self.spi
    }

    /// The SPI device, mutably.
    pub fn device_mut(&mut self) -> &mut SPI {
        &mut self.spi
    }

    /// Gives the SPI device back.
    pub fn release(self) -> SPI {
        self.spi
    }
}

impl<SPI: SpiDevice> SensorAdc for Ads8689<SPI> {
    type Error = SPI::Error;

    fn full_scale(&self) -> AdcCode {
        AdcCode(u16::MAX as u32)
    }

    /// One NOP frame: returns the conversion sampled at the end of the previous frame and
    /// starts the next one.
    fn read(&mut self) -> Result<AdcCode, Self::Error> {
        let mut buf = frame(opcode::NOP, 0, 0);
        self.spi.transfer_in_place(&mut buf)?;
        Ok(AdcCode(u16::from_be_bytes([buf[0], buf[1]]) as u32))
    }
}
