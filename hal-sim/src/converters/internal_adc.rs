//! A sensor ADC: `bits` of resolution over an input range, and a pipeline of `latency`
//! samples (a read returns the conversion started `latency` reads earlier; 1 on the board:
//! the conversion triggered by the control timer is read in the next period).

use super::AnalogSensorAdc;
use twinstack::board::{AdcCode, SensorAdc};

/// Longest pipeline the emulation holds.
pub const MAX_LATENCY: usize = 4;

/// Straight-binary code of `volts` on a converter spanning `[lo, hi)` with codes
/// `0 ..= full_scale`: `floor((v − lo)/(hi − lo) · (full_scale + 1))`, clamped to the codes
/// (NaN reads as 0).
pub fn straight_binary(volts: f64, (lo, hi): (f64, f64), full_scale: u32) -> u32 {
    let x = ((volts - lo) / (hi - lo) * (full_scale as f64 + 1.0)).floor();
    if x.is_nan() {
        0
    } else {
        x.clamp(0.0, full_scale as f64) as u32
    }
}

/// Why an ADC could not be built.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum InternalAdcError {
    /// Resolution outside 1…18 bits.
    Bits(u32),
    /// Input range empty or not finite.
    Range(f64, f64),
    /// Latency above [`MAX_LATENCY`].
    Latency(usize),
}

/// The emulated ADC. Reads never fail.
#[derive(Clone, Debug, PartialEq)]
pub struct InternalAdc {
    full_scale: u32,
    range_volts: (f64, f64),
    latency: usize,
    /// Ring of the last `latency + 1` conversions.
    pipeline: [u32; MAX_LATENCY + 1],
    head: usize,
    input_volts: f64,
}

impl InternalAdc {
    /// A `bits`-bit converter over `range_volts` with a `latency`-sample pipeline, its
    /// pipeline holding code 0.
    pub fn new(
        bits: u32,
        range_volts: (f64, f64),
        latency: usize,
    ) -> Result<Self, InternalAdcError> {
        if !(1..=18).contains(&bits) {
            return Err(InternalAdcError::Bits(bits));
        }
        let (lo, hi) = range_volts;
        if !(lo.is_finite() && hi.is_finite() && hi > lo) {
            return Err(InternalAdcError::Range(lo, hi));
        }
        if latency > MAX_LATENCY {
            return Err(InternalAdcError::Latency(latency));
        }
        Ok(Self {
            full_scale: (1u32 << bits) - 1,
            range_volts,
            latency,
            pipeline: [0; MAX_LATENCY + 1],
            head: 0,
            input_volts: lo,
        })
    }

    /// Quantises `volts` (see [`straight_binary`]).
    pub fn quantise(&self, volts: f64) -> u32 {
        straight_binary(volts, self.range_volts, self.full_scale)
    }
}

impl SensorAdc for InternalAdc {
    type Error = core::convert::Infallible;

    fn full_scale(&self) -> AdcCode {
        AdcCode(self.full_scale)
    }

    /// Converts the present input into the pipeline and returns the conversion from
    /// `latency` reads ago.
    fn read(&mut self) -> Result<AdcCode, Self::Error> {
        let len = self.latency + 1;
        self.head = (self.head + 1) % len;
        self.pipeline[self.head] = self.quantise(self.input_volts);
        Ok(AdcCode(self.pipeline[(self.head + 1) % len]))
    }
}

impl AnalogSensorAdc for InternalAdc {
    fn set_input_volts(&mut self, volts: f64) {
        self.input_volts = volts;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_lag_by_the_configured_latency() {
        for latency in 0..=MAX_LATENCY {
            let mut adc = InternalAdc::new(12, (0.0, 4.096), latency).unwrap();
            let mut out = Vec::new();
            for k in 0..10u32 {
                adc.set_input_volts(k as f64 * 0.1);
                out.push(adc.read().unwrap().0);
            }
            for (k, &code) in out.iter().enumerate().skip(latency) {
                assert_eq!(
                    code,
                    adc.quantise((k - latency) as f64 * 0.1),
                    "latency {latency}"
                );
            }
        }
    }

    #[test]
    fn quantisation_clamps_at_both_ends_and_bad_settings_are_refused() {
        let adc = InternalAdc::new(16, (-10.24, 10.24), 1).unwrap();
        assert_eq!(adc.quantise(0.0), 32768);
        assert_eq!(adc.quantise(-20.0), 0);
        assert_eq!(adc.quantise(20.0), 65535);
        assert_eq!(adc.quantise(f64::NAN), 0);
        assert_eq!(
            InternalAdc::new(0, (0.0, 1.0), 1),
            Err(InternalAdcError::Bits(0))
        );
        assert_eq!(
            InternalAdc::new(12, (1.0, 1.0), 1),
            Err(InternalAdcError::Range(1.0, 1.0))
        );
        assert_eq!(
            InternalAdc::new(12, (0.0, 1.0), 9),
            Err(InternalAdcError::Latency(9))
        );
    }
}
