//! The library's SPI drivers (`twinstack::converters`) against the wire-level chip emulators
//! (`hal_sim::converters`): round trips through the datasheet protocol, and malformed command
//! words detected by the emulators.

use embedded_hal::spi::{ErrorType, Operation, SpiDevice};
use hal_sim::converters::{
    Ads8689FrameError, Dac856xFrameError, Dac856xVariant, EmulatedAds8689, EmulatedDac856x,
};
use proptest::prelude::*;
use twinstack::board::{DacCode, DualDac, SensorAdc};
use twinstack::converters::{Ads8689, Ads8689Error, Dac856x, Gain, InputRange};

fn dac() -> Dac856x<EmulatedDac856x> {
    let mut d = Dac856x::new(EmulatedDac856x::new(Dac856xVariant::Dac8562, 0.0));
    d.init(Gain::Two).unwrap();
    d
}

fn adc(range: InputRange) -> Ads8689<EmulatedAds8689> {
    let mut a = Ads8689::new(EmulatedAds8689::new());
    a.init(range).unwrap();
    a
}

#[test]
fn dac_init_leaves_the_chip_configured_as_documented() {
    let d = dac();
    let chip = d.device();
    assert!(chip.errors().is_empty(), "{:?}", chip.errors());
    assert_eq!(chip.frames(), 5);
    assert!(chip.internal_reference());
    assert_eq!(chip.gains(), [2, 2]);
    assert_eq!(chip.ldac_pin_ignored(), [true, true]);
    assert_eq!(chip.powered_up(), [true, true]);
    assert_eq!(chip.dac_codes(), [0, 0], "DAC8562 resets to zero scale");
    assert_eq!(chip.output_volts(), [0.0, 0.0]);

    let mut g1 = Dac856x::new(EmulatedDac856x::new(Dac856xVariant::Dac8563, 0.0));
    g1.init(Gain::One).unwrap();
    assert_eq!(g1.device().gains(), [1, 1]);
    assert_eq!(
        g1.device().dac_codes(),
        [0x8000, 0x8000],
        "DAC8563 resets to mid scale"
    );
}

/// A probe between driver and chip that records the chip's DAC registers after every frame.
struct Probe {
    chip: EmulatedDac856x,
    after_each_frame: Vec<[u16; 2]>,
}

impl ErrorType for Probe {
    type Error = Dac856xFrameError;
}

impl SpiDevice for Probe {
    fn transaction(&mut self, ops: &mut [Operation<'_, u8>]) -> Result<(), Self::Error> {
        let r = self.chip.transaction(ops);
        self.after_each_frame.push(self.chip.dac_codes());
        r
    }
}

#[test]
fn write_both_changes_both_outputs_in_the_same_frame() {
    let mut d = Dac856x::new(Probe {
        chip: EmulatedDac856x::new(Dac856xVariant::Dac8562, 0.0),
        after_each_frame: Vec::new(),
    });
    d.init(Gain::Two).unwrap();
    d.device_mut().after_each_frame.clear();
    d.write_both(DacCode(0x1234), DacCode(0xBEEF)).unwrap();
    assert_eq!(
        d.device().after_each_frame,
        vec![[0, 0], [0x1234, 0xBEEF]],
        "nothing moves after the first frame, both after the second"
    );
}

proptest! {
    #[test]
    fn any_code_pair_reaches_the_outputs(left in any::<u16>(), right in any::<u16>()) {
        let mut d = dac();
        d.write_both(DacCode(left), DacCode(right)).unwrap();
        let chip = d.device();
        prop_assert_eq!(chip.dac_codes(), [left, right]);
        let [vl, vr] = chip.output_volts();
        prop_assert!((vl - 5.0 * left as f64 / 65536.0).abs() < 1e-12);
        prop_assert!((vr - 5.0 * right as f64 / 65536.0).abs() < 1e-12);
        prop_assert!(chip.errors().is_empty());
    }

    /// Whatever bytes arrive, the DAC emulator never panics, and a frame either executes or
    /// is reported (and recorded).
    #[test]
    fn dac_emulator_reports_or_executes_any_frame(bytes in proptest::collection::vec(any::<u8>(), 0..6)) {
        let mut chip = EmulatedDac856x::new(Dac856xVariant::Dac8562, 0.0);
        let result = chip.write(&bytes);
        prop_assert_eq!(result.is_err(), chip.errors().len() == 1);
        if bytes.len() != 3 {
            prop_assert_eq!(result, Err(Dac856xFrameError::Length { bits: 8 * bytes.len() }));
        }
    }

    /// A voltage at the input comes back, one frame later, as the straight-binary code of the
    /// selected range.
    #[test]
    fn adc_reads_the_input_one_frame_later(v0 in -10.2f64..10.2, v1 in -10.2f64..10.2) {
        let mut a = adc(InputRange::Bipolar2p5);
        a.device_mut().set_input_volts(v0);
        let _ = a.read().unwrap(); // outputs the conversion from init; samples v0
        a.device_mut().set_input_volts(v1);
        let c0 = a.read().unwrap().0; // outputs v0; samples v1
        let c1 = a.read().unwrap().0; // outputs v1
        let lsb = 20.48 / 65536.0;
        prop_assert!(((c0 as f64 + 0.5) * lsb - 10.24 - v0).abs() <= lsb);
        prop_assert!(((c1 as f64 + 0.5) * lsb - 10.24 - v1).abs() <= lsb);
        prop_assert!(a.device().errors().is_empty());
    }

    /// Whatever bytes arrive, the ADC emulator never panics and never changes its range
    /// unless the frame was a well-formed command.
    #[test]
    fn adc_emulator_reports_or_executes_any_frame(bytes in proptest::collection::vec(any::<u8>(), 0..6)) {
        let mut chip = EmulatedAds8689::new();
        let result = chip.write(&bytes);
        prop_assert_eq!(result.is_err(), chip.errors().len() == 1);
        if result.is_err() {
            prop_assert_eq!(chip.range(), InputRange::Bipolar3);
        }
    }
}

#[test]
fn malformed_dac_frames_are_detected_and_not_executed() {
    let mut d = dac();
    d.write_both(DacCode(1000), DacCode(2000)).unwrap();
    let chip = d.device_mut();
    let cases: [(&[u8], Dac856xFrameError); 7] = [
        (&[0x00, 0x12], Dac856xFrameError::Length { bits: 16 }),
        (
            &[0x00, 0x12, 0x34, 0x56],
            Dac856xFrameError::Length { bits: 32 },
        ),
        (
            &[0x40, 0x12, 0x34],
            Dac856xFrameError::DontCareBitsSet { word: 0x40_1234 },
        ),
        // Write input register at a reserved address (011).
        (
            &[0x03, 0x12, 0x34],
            Dac856xFrameError::ReservedAddress {
                command: 0,
                address: 3,
            },
        ),
        // Gain register with a bit other than DB1–0.
        (
            &[0x02, 0x00, 0x04],
            Dac856xFrameError::UnusedDataBitsSet {
                command: 0,
                data: 4,
            },
        ),
        // Internal reference command with an address.
        (
            &[0x39, 0x00, 0x01],
            Dac856xFrameError::ReservedAddress {
                command: 7,
                address: 1,
            },
        ),
        // Power command with a mode bit pattern outside DB5–4 / DB1–0.
        (
            &[0x20, 0x01, 0x00],
            Dac856xFrameError::UnusedDataBitsSet {
                command: 4,
                data: 0x0100,
            },
        ),
    ];
    for (bytes, expected) in cases {
        assert_eq!(chip.write(bytes), Err(expected), "{bytes:02x?}");
    }
    let mut buf = [0x00, 0x12, 0x34];
    assert_eq!(
        chip.transfer_in_place(&mut buf),
        Err(Dac856xFrameError::ReadAttempted)
    );
    assert_eq!(chip.errors().len(), 8);
    assert_eq!(
        chip.dac_codes(),
        [1000, 2000],
        "no malformed frame was executed"
    );
    assert_eq!(chip.input_codes(), [1000, 2000]);
    assert_eq!(chip.gains(), [2, 2]);
    assert!(chip.internal_reference());
}

#[test]
fn adc_init_selects_and_verifies_the_range() {
    for range in [InputRange::Bipolar2p5, InputRange::Unipolar1p25] {
        let a = adc(range);
        assert_eq!(a.device().range(), range);
        assert_eq!(a.device().register(0x14), Some(range.bits()));
        assert_eq!(a.device().frames(), 3);
        assert!(a.device().errors().is_empty());
    }
}

/// A bus with nothing on it: MISO reads 0.
struct NoChip;

impl ErrorType for NoChip {
    type Error = core::convert::Infallible;
}

impl SpiDevice for NoChip {
    fn transaction(&mut self, ops: &mut [Operation<'_, u8>]) -> Result<(), Self::Error> {
        for op in ops {
            match op {
                Operation::Read(b) | Operation::TransferInPlace(b) => b.fill(0),
                Operation::Transfer(r, _) => r.fill(0),
                _ => {}
            }
        }
        Ok(())
    }
}

#[test]
fn adc_init_notices_a_missing_chip() {
    let mut a = Ads8689::new(NoChip);
    assert_eq!(
        a.init(InputRange::Bipolar2p5),
        Err(Ads8689Error::RangeNotApplied { wrote: 1, read: 0 })
    );
}

#[test]
fn malformed_adc_frames_are_detected_and_not_executed() {
    let mut a = adc(InputRange::Bipolar2p5);
    let chip = a.device_mut();
    let cases: [(&[u8], Ads8689FrameError); 7] = [
        (
            &[0xD0, 0x14],
            Ads8689FrameError::ShortFrameCommand { bits: 16 },
        ),
        (&[0, 0, 0, 0, 0], Ads8689FrameError::TooLong { bits: 40 }),
        (
            &[0xFE, 0x14, 0x00, 0x09],
            Ads8689FrameError::UnknownOpcode { opcode: 0x7F },
        ),
        (
            &[0xD0, 0x18, 0x00, 0x09],
            Ads8689FrameError::UnknownAddress { address: 0x18 },
        ),
        (
            &[0xD0, 0x20, 0x00, 0x01],
            Ads8689FrameError::ReadOnly { address: 0x20 },
        ),
        // Reserved range code 0101.
        (
            &[0xD0, 0x14, 0x00, 0x05],
            Ads8689FrameError::InvalidRange { value: 0x05 },
        ),
        // A reserved RANGE_SEL bit (bit 8).
        (
            &[0xD0, 0x14, 0x01, 0x09],
            Ads8689FrameError::InvalidRange { value: 0x0109 },
        ),
    ];
    for (bytes, expected) in cases {
        assert_eq!(chip.write(bytes), Err(expected), "{bytes:02x?}");
    }
    assert_eq!(chip.errors().len(), 7);
    assert_eq!(
        chip.range(),
        InputRange::Bipolar2p5,
        "no malformed frame was executed"
    );
    // A short all-zero frame is a plain data read, and is fine.
    let mut two = [0u8; 2];
    assert_eq!(chip.transfer_in_place(&mut two), Ok(()));
}

#[test]
fn adc_register_read_replaces_one_conversion_in_the_next_frame() {
    let mut a = adc(InputRange::Bipolar2p5);
    let chip = a.device_mut();
    chip.set_input_volts(5.12);
    // READ_HWORD of RANGE_SEL: the next frame carries the register, not a conversion.
    chip.write(&[0xC8, 0x14, 0x00, 0x00]).unwrap();
    let mut f = [0u8; 4];
    chip.transfer_in_place(&mut f).unwrap();
    assert_eq!(
        u16::from_be_bytes([f[0], f[1]]),
        InputRange::Bipolar2p5.bits()
    );
    // The frame after that carries the conversion of 5.12 V: 3/4 of the ±10.24 V span.
    let mut f = [0u8; 4];
    chip.transfer_in_place(&mut f).unwrap();
    assert_eq!(u16::from_be_bytes([f[0], f[1]]), 0xC000);
}
