//! A TI ADS8689 emulated at the wire level.
//!
//! Each `SpiDevice` transaction is one CONVST/CS-low frame. While the frame runs, SDO shifts
//! out the output word fixed at its start: the 16 bits of the last conversion (straight
//! binary over the selected range) or, if the frame before was a register read, that
//! register's bits; the remaining bits are 0. At CS's rising edge the emulator decodes the
//! 32 bits clocked in (7-bit opcode, 9-bit address, 16 data bits), executes the command, and
//! samples its analog input for the next conversion.
//!
//! A frame shorter than 32 bits carries no command (the chip treats it as a NOP); the
//! emulator accepts it when every bit clocked in is 0 — a plain data read — and reports it
//! otherwise, since the command in it would be silently dropped. Unknown opcodes, addresses
//! that are not a register half-word, writes to read-only registers, reserved RANGE_SEL codes
//! or bits, and frames longer than 32 bits are reported too, and not executed. Reports fail the
//! transaction with an [`Ads8689FrameError`] and are kept in [`EmulatedAds8689::errors`]. The
//! decoding is written from the datasheet independently of the library's driver.

use super::internal_adc::straight_binary;
use embedded_hal::spi::{ErrorKind, ErrorType, Operation, SpiDevice};
use twinstack::converters::ads8689::{InputRange, RANGE_SEL_MASK};

/// A malformed frame, as the emulator saw it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Ads8689FrameError {
    /// More than 32 bits were clocked in.
    TooLong {
        /// Bits clocked in.
        bits: usize,
    },
    /// A frame shorter than 32 bits carried a non-zero command (which the chip ignores).
    ShortFrameCommand {
        /// Bits clocked in.
        bits: usize,
    },
    /// The opcode is not one of the datasheet's.
    UnknownOpcode {
        /// The 7-bit opcode.
        opcode: u8,
    },
    /// The address is not a register half-word (or byte, for the byte commands).
    UnknownAddress {
        /// The 9-bit address.
        address: u16,
    },
    /// A write to a read-only register.
    ReadOnly {
        /// The 9-bit address.
        address: u16,
    },
    /// RANGE_SEL_REG written with a reserved range code or reserved bits set.
    InvalidRange {
        /// The value that would have resulted.
        value: u16,
    },
}

impl embedded_hal::spi::Error for Ads8689FrameError {
    fn kind(&self) -> ErrorKind {
        ErrorKind::Other
    }
}

/// Registers by half-word: `(address, read-only)`. 32-bit registers occupy two half-words.
const HALF_WORDS: [(u16, bool); 18] = [
    (0x00, true),  // DEVICE_ID_REG 15–0
    (0x02, false), // DEVICE_ID_REG 31–16 (device address for daisy chain)
    (0x04, false), // RST_PWRCTL_REG
    (0x06, true),
    (0x08, false), // SDI_CTL_REG
    (0x0A, true),
    (0x0C, false), // SDO_CTL_REG
    (0x0E, true),
    (0x10, false), // DATAOUT_CTL_REG
    (0x12, true),
    (0x14, false), // RANGE_SEL_REG
    (0x16, true),
    (0x20, true), // ALARM_REG
    (0x22, true),
    (0x24, false), // ALARM_H_TH_REG
    (0x26, false),
    (0x28, false), // ALARM_L_TH_REG
    (0x2A, false),
];

const RANGE_SEL: u16 = 0x14;

/// The emulated chip.
#[derive(Clone, Debug, PartialEq)]
pub struct EmulatedAds8689 {
    registers: [u16; HALF_WORDS.len()],
    input_volts: f64,
    /// Result of the conversion started at the end of the last frame.
    conversion: u16,
    /// A register read requested by the last frame, output in the next one.
    readback: Option<u16>,
    frames: u64,
    errors: Vec<Ads8689FrameError>,
}

impl Default for EmulatedAds8689 {
    fn default() -> Self {
        Self::new()
    }
}

impl EmulatedAds8689 {
    /// A chip after power-up: all registers 0 (range ±3 × V_ref, internal reference on),
    /// input at 0 V.
    pub fn new() -> Self {
        let mut registers = [0; HALF_WORDS.len()];
        // ALARM_H_TH_REG resets to FFFFh in its threshold half.
        registers[Self::index(0x24).unwrap_or(0)] = 0xFFFF;
        Self {
            registers,
            input_volts: 0.0,
            conversion: 0,
            readback: None,
            frames: 0,
            errors: Vec::new(),
        }
    }

    fn index(address: u16) -> Option<usize> {
        HALF_WORDS.iter().position(|&(a, _)| a == address)
    }

    /// Sets the voltage at the analog input (sampled at the end of the next frame).
    pub fn set_input_volts(&mut self, volts: f64) {
        self.input_volts = volts;
    }

    /// The selected input range.
    pub fn range(&self) -> InputRange {
        // Writes are validated, so the field always holds a defined range.
        let bits = self.registers[Self::index(RANGE_SEL).unwrap_or(0)] & 0xF;
        InputRange::from_bits(bits).unwrap_or(InputRange::Bipolar3)
    }

    /// The 16-bit register half-word at `address`, if there is one.
    pub fn register(&self, address: u16) -> Option<u16> {
        Self::index(address).map(|i| self.registers[i])
    }

    /// Straight-binary code of `volts` over the selected range.
    pub fn code(&self, volts: f64) -> u16 {
        // Clamped to 0..=65535, so the narrowing is exact.
        straight_binary(volts, self.range().volts(), u16::MAX as u32) as u16
    }

    /// Frames received (well formed or not).
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Every malformed frame seen so far, oldest first.
    pub fn errors(&self) -> &[Ads8689FrameError] {
        &self.errors
    }

    /// Decodes and executes one 32-bit command word.
    fn execute(&mut self, word: u32) -> Result<(), Ads8689FrameError> {
        let opcode = (word >> 25) as u8;
        let address = ((word >> 16) & 0x1FF) as u16;
        let data = (word & 0xFFFF) as u16;
        const NOP: u8 = 0b000_0000;
        const CLEAR_HWORD: u8 = 0b110_0000;
        const READ_HWORD: u8 = 0b110_0100;
        const READ_BYTE: u8 = 0b010_0100;
        const WRITE_HWORD: u8 = 0b110_1000;
        const WRITE_MSB: u8 = 0b110_1001;
        const WRITE_LSB: u8 = 0b110_1010;
        const SET_HWORD: u8 = 0b110_1100;
        match opcode {
            NOP => return Ok(()),
            CLEAR_HWORD | READ_HWORD | READ_BYTE | WRITE_HWORD | WRITE_MSB | WRITE_LSB
            | SET_HWORD => {}
            _ => return Err(Ads8689FrameError::UnknownOpcode { opcode }),
        }
        // Byte commands address either byte of a half-word; half-word commands its first byte.
        let byte_command = matches!(opcode, READ_BYTE);
        let half_word = if byte_command { address & !1 } else { address };
        let i = Self::index(half_word).ok_or(Ads8689FrameError::UnknownAddress { address })?;
        let read_only = HALF_WORDS[i].1;
        let old = self.registers[i];
        let new = match opcode {
            READ_HWORD => {
                self.readback = Some(old);
                return Ok(());
            }
            READ_BYTE => {
                let byte = if address & 1 == 0 {
                    old & 0xFF
                } else {
                    old >> 8
                };
                self.readback = Some(byte << 8);
                return Ok(());
            }
            WRITE_HWORD => data,
            WRITE_MSB => (old & 0x00FF) | (data & 0xFF00),
            WRITE_LSB => (old & 0xFF00) | (data & 0x00FF),
            SET_HWORD => old | data,
            _ => old & !data, // CLEAR_HWORD
        };
        if read_only {
            return Err(Ads8689FrameError::ReadOnly { address });
        }
        if half_word == RANGE_SEL
            && (new & !RANGE_SEL_MASK != 0 || InputRange::from_bits(new & 0xF).is_none())
        {
            return Err(Ads8689FrameError::InvalidRange { value: new });
        }
        self.registers[i] = new;
        Ok(())
    }
}

impl ErrorType for EmulatedAds8689 {
    type Error = Ads8689FrameError;
}

impl SpiDevice for EmulatedAds8689 {
    fn transaction(&mut self, operations: &mut [Operation<'_, u8>]) -> Result<(), Self::Error> {
        // The output word is fixed when the frame starts.
        let out = (self.readback.take().unwrap_or(self.conversion) as u32) << 16;
        let out_bytes = out.to_be_bytes();
        let mut word: u32 = 0;
        let mut bits = 0usize;
        let mut any_set = false;
        let mut clock = |mosi: u8| -> u8 {
            let miso = out_bytes.get(bits / 8).copied().unwrap_or(0);
            word = (word << 8) | mosi as u32;
            any_set |= mosi != 0;
            bits += 8;
            miso
        };
        for op in operations.iter_mut() {
            match op {
                Operation::Write(bytes) => bytes.iter().for_each(|&b| {
                    clock(b);
                }),
                Operation::Read(buf) => buf.iter_mut().for_each(|b| *b = clock(0)),
                Operation::Transfer(rx, tx) => {
                    for i in 0..rx.len().max(tx.len()) {
                        let miso = clock(tx.get(i).copied().unwrap_or(0));
                        if let Some(r) = rx.get_mut(i) {
                            *r = miso;
                        }
                    }
                }
                Operation::TransferInPlace(buf) => buf.iter_mut().for_each(|b| *b = clock(*b)),
                Operation::DelayNs(_) => {}
            }
        }
        self.frames += 1;
        let result = if bits > 32 {
            Err(Ads8689FrameError::TooLong { bits })
        } else if bits < 32 {
            if any_set {
                Err(Ads8689FrameError::ShortFrameCommand { bits })
            } else {
                Ok(())
            }
        } else {
            self.execute(word)
        };
        if let Err(e) = result {
            self.errors.push(e);
        }
        // CS rising edge: a new conversion samples the input (whatever the frame held).
        self.conversion = self.code(self.input_volts);
        result
    }
}
