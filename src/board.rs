//! The board as the control tick sees it: a dual DAC that updates both stacks at once, and a
//! sensor ADC. `embedded-hal` 1.0 has no DAC or ADC trait, so these are ours; the firmware
//! implements them over the STM32's registers (or the external SPI converters), and `hal-sim`
//! over its emulated converters.

/// A DAC output code, right-aligned (0…4095 for the 12-bit internal DAC, 0…65535 for a
/// 16-bit external one).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct DacCode(pub u16);

/// A sensor ADC result, right-aligned (up to 18 bits).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct AdcCode(pub u32);

/// Two DAC channels written together, so the left and right stacks never see a skewed pair
/// (`u_l = ū + v`, `u_r = ū − v` change in the same instant).
pub trait DualDac {
    /// Why a write failed (an SPI error; the internal DAC never fails).
    type Error;
    /// Largest code the converter accepts (full scale).
    fn full_scale(&self) -> DacCode;
    /// Writes both channels; they take effect at the same time.
    fn write_both(&mut self, left: DacCode, right: DacCode) -> Result<(), Self::Error>;
}

/// The position sensor's ADC.
pub trait SensorAdc {
    /// Why a read failed.
    type Error;
    /// Largest code the converter returns (full scale).
    fn full_scale(&self) -> AdcCode;
    /// The most recent conversion (started by the control timer's trigger).
    fn read(&mut self) -> Result<AdcCode, Self::Error>;
}

/// Test doubles of the board, shared by the library's unit tests.
#[cfg(test)]
pub(crate) mod fakes {
    use super::*;

    /// A DAC that remembers the last pair written and counts the writes.
    #[derive(Debug, Default)]
    pub struct RecordingDac {
        pub left: DacCode,
        pub right: DacCode,
        pub writes: u32,
    }

    impl DualDac for RecordingDac {
        type Error = ();
        fn full_scale(&self) -> DacCode {
            DacCode(65535)
        }
        fn write_both(&mut self, left: DacCode, right: DacCode) -> Result<(), ()> {
            self.left = left;
            self.right = right;
            self.writes += 1;
            Ok(())
        }
    }

    /// An ADC that always returns the same result (`None`: the read fails).
    #[derive(Debug)]
    pub struct FixedAdc(pub Option<AdcCode>);

    impl SensorAdc for FixedAdc {
        type Error = ();
        fn full_scale(&self) -> AdcCode {
            AdcCode(65535)
        }
        fn read(&mut self) -> Result<AdcCode, ()> {
            self.0.ok_or(())
        }
    }
}
