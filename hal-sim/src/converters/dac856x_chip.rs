//! A TI DAC8562/DAC8563 emulated at the wire level.
//!
//! Each `SpiDevice` transaction is one SYNC-low period. The emulator collects the bits clocked
//! in, and at SYNC's rising edge decodes the 24-bit word as the datasheet lays it out (bits
//! 23–22 don't care, 21–19 command, 18–16 address, 15–0 data) and acts on it: input and DAC
//! registers, software LDAC, gain register, power modes, reset, LDAC register, internal
//! reference. The LDAC pin is taken as tied high (the board's wiring), so outputs move only
//! on software updates.
//!
//! The decoding is written from the datasheet independently of the library's driver, so the
//! driver is tested against the protocol, not against itself. A frame the chip would ignore or
//! misread — not 24 bits, a reserved address, a set bit in a field the datasheet leaves unused —
//! is not executed, is recorded, and fails the transaction with a [`Dac856xFrameError`], so that
//! a driver bug shows up as an error rather than as a silently wrong voltage. (The real chip
//! has no way to report it; the emulator is stricter on purpose.)

use embedded_hal::spi::{ErrorKind, ErrorType, Operation, SpiDevice};

/// Which part: they differ only in the code the registers reset to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dac856xVariant {
    /// Resets to zero scale (the board's choice: stacks at 0 V at power-up).
    Dac8562,
    /// Resets to mid scale.
    Dac8563,
}

/// A malformed frame, as the emulator saw it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dac856xFrameError {
    /// SYNC went high after a number of bits other than 24 (the chip ignores such a frame).
    Length {
        /// Bits clocked in.
        bits: usize,
    },
    /// Bits 23–22 are not zero.
    DontCareBitsSet {
        /// The 24-bit word.
        word: u32,
    },
    /// The address field is reserved for this command.
    ReservedAddress {
        /// Command field C2–C0.
        command: u8,
        /// Address field A2–A0.
        address: u8,
    },
    /// Data bits the command does not use are set (their value is undefined for the chip).
    UnusedDataBitsSet {
        /// Command field C2–C0.
        command: u8,
        /// The data field.
        data: u16,
    },
    /// The frame tried to read: the DAC has no data output.
    ReadAttempted,
}

impl embedded_hal::spi::Error for Dac856xFrameError {
    fn kind(&self) -> ErrorKind {
        ErrorKind::Other
    }
}

/// The emulated chip.
#[derive(Clone, Debug, PartialEq)]
pub struct EmulatedDac856x {
    variant: Dac856xVariant,
    external_reference_volts: f64,
    input: [u16; 2],
    dac: [u16; 2],
    gain: [u8; 2],
    internal_reference: bool,
    powered_up: [bool; 2],
    ldac_pin_ignored: [bool; 2],
    frames: u64,
    errors: Vec<Dac856xFrameError>,
}

const INTERNAL_REFERENCE_VOLTS: f64 = 2.5;

impl EmulatedDac856x {
    /// A chip just powered up, with `external_reference_volts` at its VREF pin (used while
    /// the internal reference is off; 0 if nothing is connected).
    pub fn new(variant: Dac856xVariant, external_reference_volts: f64) -> Self {
        let mut chip = Self {
            variant,
            external_reference_volts,
            input: [0; 2],
            dac: [0; 2],
            gain: [1; 2],
            internal_reference: false,
            powered_up: [true; 2],
            ldac_pin_ignored: [false; 2],
            frames: 0,
            errors: Vec::new(),
        };
        chip.power_on_reset();
        chip
    }

    fn reset_code(&self) -> u16 {
        match self.variant {
            Dac856xVariant::Dac8562 => 0,
            Dac856xVariant::Dac8563 => 0x8000,
        }
    }

    fn power_on_reset(&mut self) {
        let code = self.reset_code();
        self.input = [code; 2];
        self.dac = [code; 2];
        self.gain = [1; 2];
        self.internal_reference = false;
        self.powered_up = [true; 2];
        self.ldac_pin_ignored = [false; 2];
    }

    /// Output voltages `[A, B]`: `V_ref · gain · code / 65536`, 0 for a powered-down channel.
    pub fn output_volts(&self) -> [f64; 2] {
        let vref = if self.internal_reference {
            INTERNAL_REFERENCE_VOLTS
        } else {
            self.external_reference_volts
        };
        core::array::from_fn(|n| {
            if self.powered_up[n] {
                vref * self.gain[n] as f64 * self.dac[n] as f64 / 65536.0
            } else {
                0.0
            }
        })
    }

    /// DAC registers `[A, B]` (what the outputs show).
    pub fn dac_codes(&self) -> [u16; 2] {
        self.dac
    }

    /// Input registers `[A, B]` (written, not necessarily output yet).
    pub fn input_codes(&self) -> [u16; 2] {
        self.input
    }

    /// Gains `[A, B]` (1 or 2).
    pub fn gains(&self) -> [u8; 2] {
        self.gain
    }

    /// Whether the internal reference is on.
    pub fn internal_reference(&self) -> bool {
        self.internal_reference
    }

    /// Whether each channel ignores the LDAC pin.
    pub fn ldac_pin_ignored(&self) -> [bool; 2] {
        self.ldac_pin_ignored
    }

    /// Whether each channel is powered up.
    pub fn powered_up(&self) -> [bool; 2] {
        self.powered_up
    }

    /// Frames received (well formed or not).
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Every malformed frame seen so far, oldest first.
    pub fn errors(&self) -> &[Dac856xFrameError] {
        &self.errors
    }

    /// Channels an address selects, for the data commands.
    fn channels(command: u8, address: u8) -> Result<&'static [usize], Dac856xFrameError> {
        match address {
            0b000 => Ok(&[0]),
            0b001 => Ok(&[1]),
            0b111 => Ok(&[0, 1]),
            _ => Err(Dac856xFrameError::ReservedAddress { command, address }),
        }
    }

    /// Decodes and executes one 24-bit word.
    fn execute(&mut self, word: u32) -> Result<(), Dac856xFrameError> {
        if word >> 22 != 0 {
            return Err(Dac856xFrameError::DontCareBitsSet { word });
        }
        let command = ((word >> 19) & 0b111) as u8;
        let address = ((word >> 16) & 0b111) as u8;
        let data = (word & 0xFFFF) as u16;
        let unused = |mask: u16| {
            if data & !mask != 0 {
                Err(Dac856xFrameError::UnusedDataBitsSet { command, data })
            } else {
                Ok(())
            }
        };
        let no_address = || {
            if address != 0 {
                Err(Dac856xFrameError::ReservedAddress { command, address })
            } else {
                Ok(())
            }
        };
        match command {
            // Write to input register n (or, at address 010, the gain register).
            0b000 if address == 0b010 => {
                unused(0b11)?;
                self.gain = [
                    if data & 0b01 != 0 { 1 } else { 2 },
                    if data & 0b10 != 0 { 1 } else { 2 },
                ];
            }
            0b000 => {
                for &n in Self::channels(command, address)? {
                    self.input[n] = data;
                }
            }
            // Software LDAC: update DAC register n.
            0b001 => {
                let channels = Self::channels(command, address)?;
                unused(0)?;
                for &n in channels {
                    self.dac[n] = self.input[n];
                }
            }
            // Write input register n and update all DAC registers.
            0b010 => {
                for &n in Self::channels(command, address)? {
                    self.input[n] = data;
                }
                self.dac = self.input;
            }
            // Write input register n and update DAC register n.
            0b011 => {
                for &n in Self::channels(command, address)? {
                    self.input[n] = data;
                    self.dac[n] = data;
                }
            }
            // Power up/down: DB5–4 mode (00 = up), DB1–0 channels.
            0b100 => {
                no_address()?;
                unused(0b11_0011)?;
                let up = (data >> 4) & 0b11 == 0;
                for n in 0..2 {
                    if data & (1 << n) != 0 {
                        self.powered_up[n] = up;
                    }
                }
            }
            // Software reset: DB0 = 1 all registers, 0 input and DAC registers only.
            0b101 => {
                no_address()?;
                unused(0b1)?;
                if data & 1 != 0 {
                    self.power_on_reset();
                } else {
                    let code = self.reset_code();
                    self.input = [code; 2];
                    self.dac = [code; 2];
                }
            }
            // LDAC register: DB1 = B, DB0 = A; 1 = the channel ignores the LDAC pin.
            0b110 => {
                no_address()?;
                unused(0b11)?;
                self.ldac_pin_ignored = [data & 0b01 != 0, data & 0b10 != 0];
            }
            // Internal reference: DB0 = 1 on (gains reset to 2), 0 off (gains reset to 1).
            _ => {
                no_address()?;
                unused(0b1)?;
                self.internal_reference = data & 1 != 0;
                self.gain = if self.internal_reference {
                    [2; 2]
                } else {
                    [1; 2]
                };
            }
        }
        Ok(())
    }
}

impl ErrorType for EmulatedDac856x {
    type Error = Dac856xFrameError;
}

impl SpiDevice for EmulatedDac856x {
    fn transaction(&mut self, operations: &mut [Operation<'_, u8>]) -> Result<(), Self::Error> {
        let mut word: u32 = 0;
        let mut bits = 0usize;
        let mut read = false;
        let mut clock_in = |byte: u8| {
            word = (word << 8) | byte as u32;
            bits += 8;
        };
        for op in operations.iter_mut() {
            match op {
                Operation::Write(bytes) => bytes.iter().for_each(|&b| clock_in(b)),
                Operation::Transfer(rx, tx) => {
                    read = true;
                    for i in 0..rx.len().max(tx.len()) {
                        clock_in(tx.get(i).copied().unwrap_or(0));
                    }
                    rx.fill(0);
                }
                Operation::TransferInPlace(buf) => {
                    read = true;
                    buf.iter().for_each(|&b| clock_in(b));
                    buf.fill(0);
                }
                Operation::Read(buf) => {
                    read = true;
                    buf.iter().for_each(|_| clock_in(0));
                    buf.fill(0);
                }
                Operation::DelayNs(_) => {}
            }
        }
        self.frames += 1;
        let result = if read {
            Err(Dac856xFrameError::ReadAttempted)
        } else if bits != 24 {
            Err(Dac856xFrameError::Length { bits })
        } else {
            self.execute(word & 0x00FF_FFFF)
        };
        if let Err(e) = result {
            self.errors.push(e);
        }
        result
    }
}
