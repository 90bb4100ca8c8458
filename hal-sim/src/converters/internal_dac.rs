//! The STM32's internal 12-bit dual DAC (both channels written with one register access,
//! `DHR12RD`): `V = V_ref · code / 4096`.

use super::AnalogDualDac;
use twinstack::board::{DacCode, DualDac};

/// Largest 12-bit code.
pub const FULL_SCALE: u16 = 4095;

/// A code the 12-bit DAC cannot hold: the hardware would drop its upper bits, so the emulator
/// refuses the write (the outputs keep their previous codes) and says which channel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InternalDacError {
    /// The left channel's code exceeds 4095.
    LeftOutOfRange(u16),
    /// The right channel's code exceeds 4095.
    RightOutOfRange(u16),
}

/// The emulated internal DAC.
#[derive(Clone, Debug, PartialEq)]
pub struct InternalDac {
    reference_volts: f64,
    codes: [u16; 2],
}

impl InternalDac {
    /// A DAC with reference `reference_volts` (the STM32's VREF+, 3.3 V on the board), both
    /// channels at code 0.
    pub fn new(reference_volts: f64) -> Self {
        Self {
            reference_volts,
            codes: [0; 2],
        }
    }

    /// The codes last written `[left, right]`.
    pub fn codes(&self) -> [u16; 2] {
        self.codes
    }
}

impl DualDac for InternalDac {
    type Error = InternalDacError;

    fn full_scale(&self) -> DacCode {
        DacCode(FULL_SCALE)
    }

    fn write_both(&mut self, left: DacCode, right: DacCode) -> Result<(), Self::Error> {
        if left.0 > FULL_SCALE {
            return Err(InternalDacError::LeftOutOfRange(left.0));
        }
        if right.0 > FULL_SCALE {
            return Err(InternalDacError::RightOutOfRange(right.0));
        }
        self.codes = [left.0, right.0];
        Ok(())
    }
}

impl AnalogDualDac for InternalDac {
    fn output_volts(&self) -> [f64; 2] {
        self.codes
            .map(|c| self.reference_volts * c as f64 / (FULL_SCALE as f64 + 1.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_map_onto_the_reference_and_out_of_range_codes_are_refused() {
        let mut d = InternalDac::new(3.3);
        d.write_both(DacCode(2048), DacCode(4095)).unwrap();
        let [l, r] = d.output_volts();
        assert!((l - 1.65).abs() < 1e-12);
        assert!((r - 3.3 * 4095.0 / 4096.0).abs() < 1e-12);
        assert_eq!(
            d.write_both(DacCode(4096), DacCode(0)),
            Err(InternalDacError::LeftOutOfRange(4096))
        );
        assert_eq!(d.codes(), [2048, 4095], "a refused write changes nothing");
    }
}
