//! The position sensor: its calibration ([`SensorSettings`], physical units) and the
//! fixed-point form the tick reads it with ([`Sensor`]), with the drift check's limit (the
//! check itself runs below the tick: [`crate::services::observer`]).
//!
//! The sensor is apart from the feedback: a stage with a sensor has it read once per tick in
//! every mode (for the recorder, the drift check and, in closed loop, the feedback); the
//! feedback ([`crate::control::feedback`]) only adds a controller on its error.

use crate::board::AdcCode;
use crate::fixed_point::{q4_28_from_f64, signal_from_f64};
use crate::refusal::{finite, Field, Refusal, Rule};
use crate::scaling::Scaling;

/// The sensor's calibration: ADC code → displacement, in the output range's units.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorSettings {
    /// Displacement at ADC code 0, output units.
    pub displacement_at_zero: f64,
    /// Displacement at the ADC's full-scale code, output units (below `displacement_at_zero`
    /// for an inverted sensor).
    pub displacement_at_full_scale: f64,
    /// Drift limit: largest low-passed |measured − observer estimate| as a fraction of the
    /// output range (0…1], or `None` for no drift check (it also needs an observer).
    pub drift_limit: Option<f64>,
}

/// The sensor in the tick's fixed point.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Sensor {
    /// ADC resolution, bits (1…30): the code is read as a fraction of full scale.
    pub adc_bits: u32,
    /// Displacement at ADC code 0, Q4.28 normalised displacement.
    pub offset: i32,
    /// Displacement per ADC full scale, Q4.28 normalised (negative for an inverted sensor).
    pub gain: i32,
    /// Largest low-passed |measured − estimate| before the drift flag, Q2.30 normalised
    /// displacement (`u32::MAX`: no check).
    pub drift_limit: u32,
}

impl SensorSettings {
    /// Validates the calibration for an ADC of `adc_bits` (`None`: the board has no sensor
    /// input) and the output range of `scaling`, and builds the tick's sensor. `observed`
    /// says whether an observer runs (the drift check needs one).
    ///
    /// ```
    /// use twinstack::control::sensor::SensorSettings;
    /// use twinstack::Scaling;
    /// let ranges = Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap();
    /// let cal = SensorSettings { displacement_at_zero: 0.0, displacement_at_full_scale: 70.0, drift_limit: None };
    /// let sensor = cal.build(Some(12), &ranges, false).unwrap();
    /// assert_eq!(sensor.displacement(twinstack::board::AdcCode(0)), -(1 << 30));
    /// ```
    pub fn build(
        &self,
        adc_bits: Option<u8>,
        scaling: &Scaling,
        observed: bool,
    ) -> Result<Sensor, Refusal> {
        let bits = adc_bits.ok_or(Refusal::new(Field::Sensor, Rule::NoHardware))? as u32;
        if !(1..=30).contains(&bits) {
            return Err(Refusal::new(Field::Sensor, Rule::NoHardware));
        }
        finite(Field::SensorCalibration, self.displacement_at_zero)?;
        finite(Field::SensorCalibration, self.displacement_at_full_scale)?;
        let at_zero = scaling.output_to_norm(self.displacement_at_zero);
        let at_full = scaling.output_to_norm(self.displacement_at_full_scale);
        let gain = at_full - at_zero;
        // The reading is formed in Q4.28 (|x| < 8) before it saturates to Q2.30.
        if gain == 0.0 {
            return Err(Refusal::new(Field::SensorCalibration, Rule::Empty));
        }
        if !(at_zero.abs() < 7.5 && at_full.abs() < 7.5 && gain.abs() < 7.5) {
            return Err(Refusal::new(
                Field::SensorCalibration,
                Rule::BeyondFixedPoint,
            ));
        }
        let drift_limit = match self.drift_limit {
            Some(d) => {
                finite(Field::DriftLimit, d)?;
                if d <= 0.0 {
                    return Err(Refusal::new(Field::DriftLimit, Rule::Above(0.0)));
                }
                if d > 1.0 {
                    return Err(Refusal::new(Field::DriftLimit, Rule::AtMost(1.0)));
                }
                if observed {
                    signal_from_f64(d * 2.0) as u32
                } else {
                    u32::MAX
                }
            }
            None => u32::MAX,
        };
        Ok(Sensor {
            adc_bits: bits,
            offset: q4_28_from_f64(at_zero),
            gain: q4_28_from_f64(gain),
            drift_limit,
        })
    }
}

/// `(a · b) >> shift` with a 64-bit product, for products that provably fit 32 bits.
#[inline(always)]
fn mul_shift(a: i32, b: i32, shift: u32) -> i32 {
    ((a as i64 * b as i64) >> shift) as i32
}

impl Sensor {
    /// One ADC code's displacement, Q2.30 normalised (`|gain| / 2^bits`, at least 1): the
    /// sensor's resolution, below which an error is not measured.
    ///
    /// ```
    /// use twinstack::control::sensor::SensorSettings;
    /// use twinstack::Scaling;
    /// let ranges = Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap();
    /// let cal = SensorSettings { displacement_at_zero: 0.0, displacement_at_full_scale: 70.0, drift_limit: None };
    /// // 12 bits over the whole range (2 in normalised units): 2 / 2^12 = 2^-11, Q2.30 2^19.
    /// assert_eq!(cal.build(Some(12), &ranges, false).unwrap().quantum(), 1 << 19);
    /// ```
    pub fn quantum(&self) -> i32 {
        // Q4.28 → Q2.30 is ×4; |gain| < 8, so the product fits 64 bits and the shifted
        // result 32 (for bits ≥ 3; fewer saturate).
        let q = ((self.gain as i64).unsigned_abs() << 2) >> self.adc_bits.min(63);
        q.clamp(1, i32::MAX as u64) as i32
    }

    /// ADC code → normalised displacement (Q2.30, saturated): `offset + gain · code / 2^bits`.
    /// The code is masked to `adc_bits` and read as a Q1.31 fraction in [0, 1); the Q4.28
    /// product and sum fit 32 bits, and the final ×4 to Q2.30 saturates.
    #[inline(always)]
    pub fn displacement(&self, code: AdcCode) -> i32 {
        // Shifting the code's top bit to bit 31 drops the stray bits above `adc_bits`; one
        // more shift back down makes it a Q1.31 fraction in [0, 1). Two shifts, no mask.
        // `adc_bits` is validated to 1…30; out of that range the shift amounts wrap (no
        // panic) and the reading is still a fraction in [0, 1).
        let fraction = (code.0.wrapping_shl(32u32.wrapping_sub(self.adc_bits)) >> 1) as i32;
        // Q4.28 × Q1.31 >> 31 = Q4.28; |gain| < 8 and fraction < 1, so it fits.
        let x = self
            .offset
            .saturating_add(mul_shift(self.gain, fraction, 31));
        let x = x.saturating_add(x);
        x.saturating_add(x)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed_point::{signal_from_f64, signal_to_f64};

    fn sensor() -> Sensor {
        Sensor {
            adc_bits: 16,
            offset: q4_28_from_f64(-1.0),
            gain: q4_28_from_f64(2.0),
            drift_limit: signal_from_f64(0.01) as u32,
        }
    }

    #[test]
    fn sensor_codes_map_onto_the_output_range_and_stray_bits_are_masked() {
        let s = sensor();
        assert_eq!(s.displacement(AdcCode(0)), signal_from_f64(-1.0));
        assert_eq!(s.displacement(AdcCode(32768)), 0);
        let top = signal_to_f64(s.displacement(AdcCode(65535)));
        assert!((top - (1.0 - 2.0 / 65536.0)).abs() < 1e-8, "{top}");
        // A code with bits above the ADC's 16 reads as its low 16 bits, never beyond range.
        assert_eq!(s.displacement(AdcCode(0x1_8000)), 0);
        // A sensor spanning beyond ±2 saturates instead of wrapping.
        let wide = Sensor {
            offset: q4_28_from_f64(-7.0),
            gain: q4_28_from_f64(7.9),
            ..s
        };
        assert_eq!(wide.displacement(AdcCode(0)), i32::MIN);
        let top = signal_to_f64(wide.displacement(AdcCode(65535)));
        assert!(
            (top - (-7.0 + 7.9 * 65535.0 / 65536.0)).abs() < 1e-7,
            "{top}"
        );
    }

    #[test]
    fn refusals_name_the_field() {
        let ranges = Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap();
        let mut cal = SensorSettings {
            displacement_at_zero: 0.0,
            displacement_at_full_scale: 70.0,
            drift_limit: Some(f64::NAN),
        };
        assert_eq!(
            cal.build(Some(12), &ranges, true),
            Err(Refusal::new(Field::DriftLimit, Rule::NotFinite))
        );
        cal.drift_limit = None;
        assert_eq!(
            cal.build(None, &ranges, true),
            Err(Refusal::new(Field::Sensor, Rule::NoHardware))
        );
        cal.displacement_at_full_scale = f64::NEG_INFINITY;
        assert_eq!(
            cal.build(Some(12), &ranges, true),
            Err(Refusal::new(Field::SensorCalibration, Rule::NotFinite))
        );
    }
}
