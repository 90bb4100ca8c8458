//! TI DAC8562 / DAC8563: dual 16-bit voltage-output DAC with a 2.5 V internal reference
//! (datasheet SLAS719). Both parts speak the same protocol; they differ only in the power-on
//! code (DAC8562: zero scale, DAC8563: mid scale). The board uses the DAC8562, so the stacks
//! sit at 0 V until the firmware drives them.
//!
//! ## Wire format
//! One 24-bit frame per SYNC-low period, MSB first, data latched on SCLK falling edges
//! (SPI mode 1, up to 50 MHz):
//!
//! | bits | 23–22 | 21–19 | 18–16 | 15–0 |
//! |---|---|---|---|---|
//! | field | don't care (sent as 0) | command C2–C0 | address A2–A0 | data |
//!
//! Commands used here: `000` write input register, `010` write input register and update
//! all DAC registers, `100` power up/down (DB5–4 mode, DB1–0 channels), `101` software reset
//! (DB0 = 1: all registers), `110` LDAC register (DB1–0 = 1: channel ignores the LDAC pin),
//! `111` internal reference (DB0 = 1: on, gain reset to 2). Address `000` = DAC-A,
//! `001` = DAC-B, `111` = both, `010` = gain register (with command `000`; DB1 = DAC-B,
//! DB0 = DAC-A, a 1 selects gain 1).
//!
//! ## Channels
//! DAC-A drives the left stack's amplifier, DAC-B the right one. [`Dac856x::write_both`]
//! writes A's input register, then B's with "write and update all": both outputs change on
//! the 24th clock edge of the second frame, together.

use crate::board::{DacCode, DualDac};
use embedded_hal::spi::SpiDevice;

/// Command field C2–C0 (frame bits 21–19).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(u8)]
pub enum Command {
    /// Write to input register n.
    WriteInput = 0b000,
    /// Software LDAC: update DAC register n from its input register.
    UpdateDac = 0b001,
    /// Write to input register n and update all DAC registers.
    WriteInputUpdateAll = 0b010,
    /// Write to input register n and update DAC register n.
    WriteInputUpdateDac = 0b011,
    /// Set DAC power-up / power-down mode.
    PowerMode = 0b100,
    /// Software reset.
    SoftwareReset = 0b101,
    /// Set the LDAC register.
    LdacRegister = 0b110,
    /// Enable / disable the internal reference.
    InternalReference = 0b111,
}

/// Address field A2–A0 (frame bits 18–16).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(u8)]
pub enum Address {
    /// DAC-A (left stack).
    DacA = 0b000,
    /// DAC-B (right stack).
    DacB = 0b001,
    /// The gain register (with [`Command::WriteInput`] only).
    Gain = 0b010,
    /// DAC-A and DAC-B.
    Both = 0b111,
}

/// Output amplifier gain of both channels: `V_out = V_ref · gain · code / 2^16`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Gain {
    /// Gain 1: 0 … 2.5 V with the internal reference.
    One,
    /// Gain 2: 0 … 5 V with the internal reference (the chip's default once it is enabled).
    Two,
}

/// The 3 bytes of one frame: `command`, `address`, 16 data bits, MSB first.
pub const fn frame(command: Command, address: Address, data: u16) -> [u8; 3] {
    let [hi, lo] = data.to_be_bytes();
    [((command as u8) << 3) | address as u8, hi, lo]
}

/// Software reset of all registers (power-on state).
pub const RESET_ALL: [u8; 3] = frame(Command::SoftwareReset, Address::DacA, 0x0001);
/// Power up DAC-A and DAC-B (mode 00 = normal, DB1–0 = both channels).
pub const POWER_UP_BOTH: [u8; 3] = frame(Command::PowerMode, Address::DacA, 0x0003);
/// Internal 2.5 V reference on (also resets both gains to 2).
pub const INTERNAL_REFERENCE_ON: [u8; 3] = frame(Command::InternalReference, Address::DacA, 0x0001);
/// LDAC pin inactive for both channels: outputs move only on the software update commands.
pub const LDAC_PIN_INACTIVE: [u8; 3] = frame(Command::LdacRegister, Address::DacA, 0x0003);

/// Driver of a DAC8562/DAC8563 on an SPI device (chip select = SYNC).
#[derive(Debug)]
pub struct Dac856x<SPI> {
    spi: SPI,
}

impl<SPI: SpiDevice> Dac856x<SPI> {
    /// The driver; call [`Dac856x::init`] before the first write.
    pub fn new(spi: SPI) -> Self {
        Self { spi }
    }

    /// Reset, power up both channels, internal reference on, `gain` on both channels, LDAC pin
    /// ignored. Leaves both outputs at the power-on code.
    pub fn init(&mut self, gain: Gain) -> Result<(), SPI::Error> {
        let gain_bits = match gain {
            Gain::One => 0b11,
            Gain::Two => 0b00,
        };
        for f in [
            RESET_ALL,
            POWER_UP_BOTH,
            INTERNAL_REFERENCE_ON,
            frame(Command::WriteInput, Address::Gain, gain_bits),
            LDAC_PIN_INACTIVE,
        ] {
            self.spi.write(&f)?;
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

impl<SPI: SpiDevice> DualDac for Dac856x<SPI> {
    type Error = SPI::Error;

    fn full_scale(&self) -> DacCode {
        DacCode(u16::MAX)
    }

    /// Left → DAC-A input register; right → DAC-B with "update all": both outputs change
    /// together at the end of the second frame.
    fn write_both(&mut self, left: DacCode, right: DacCode) -> Result<(), Self::Error> {
        self.spi
            .write(&frame(Command::WriteInput, Address::DacA, left.0))?;
        self.spi
            .write(&frame(Command::WriteInputUpdateAll, Address::DacB, right.0))
    }
}
