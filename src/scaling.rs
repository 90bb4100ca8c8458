//! The affine map between physical units and the normalised fixed-point signals.
//!
//! The tick works on normalised signals (Q2.30, see [`crate::fixed_point`]): the configured
//! input range (drive volts) and output range (displacement, µm or sensor units) each map onto
//! [-1, 1]. `Scaling` holds those two ranges and converts both ways.

/// Why ranges were refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum RangeError {
    /// The input (drive) range is empty or not finite.
    EmptyInput,
    /// The output (displacement) range is empty or not finite.
    EmptyOutput,
}

impl core::fmt::Display for RangeError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            RangeError::EmptyInput => write!(f, "input range is empty or not finite"),
            RangeError::EmptyOutput => write!(f, "output range is empty or not finite"),
        }
    }
}

impl core::error::Error for RangeError {}

/// Physical ranges of a model's input (drive voltage) and output (displacement).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scaling {
    /// Lowest drive voltage, volts (maps to −1).
    pub input_min: f64,
    /// Highest drive voltage, volts (maps to +1).
    pub input_max: f64,
    /// Lowest displacement, output units (maps to −1).
    pub output_min: f64,
    /// Highest displacement, output units (maps to +1).
    pub output_max: f64,
}

impl Scaling {
    /// A scaling from an input range `[input_min, input_max]` (volts) and an output range
    /// `[output_min, output_max]` (µm or sensor units). Each range must be finite and non-empty.
    ///
    /// ```
    /// use twinstack::Scaling;
    ///
    /// // 0…150 V drive, 0…30 µm travel: the middle of each range is 0, the ends are ±1.
    /// let s = Scaling::new(0.0, 150.0, 0.0, 30.0).unwrap();
    /// assert_eq!(s.input_to_norm(75.0), 0.0);
    /// assert_eq!(s.input_to_norm(150.0), 1.0);
    /// assert_eq!(s.norm_to_output(-1.0), 0.0);
    /// // An empty or reversed range is refused.
    /// assert!(Scaling::new(0.0, 150.0, 30.0, 30.0).is_err());
    /// ```
    pub fn new(
        input_min: f64,
        input_max: f64,
        output_min: f64,
        output_max: f64,
    ) -> Result<Self, RangeError> {
        let ok = |lo: f64, hi: f64| lo.is_finite() && hi.is_finite() && hi > lo;
        if !ok(input_min, input_max) {
            return Err(RangeError::EmptyInput);
        }
        if !ok(output_min, output_max) {
            return Err(RangeError::EmptyOutput);
        }
        Ok(Self {
            input_min,
            input_max,
            output_min,
            output_max,
        })
    }

    /// Centre of the input range, volts.
    pub fn input_mid(&self) -> f64 {
        0.5 * (self.input_min + self.input_max)
    }
    /// Half-width of the input range, volts (the physical value of normalised 1.0).
    pub fn input_half_span(&self) -> f64 {
        0.5 * (self.input_max - self.input_min)
    }
    /// Centre of the output range, output units.
    pub fn output_mid(&self) -> f64 {
        0.5 * (self.output_min + self.output_max)
    }
    /// Half-width of the output range, output units.
    pub fn output_half_span(&self) -> f64 {
        0.5 * (self.output_max - self.output_min)
    }
    /// Volts → normalised input (−1 … 1 over the input range).
    pub fn input_to_norm(&self, volts: f64) -> f64 {
        (volts - self.input_mid()) / self.input_half_span()
    }
    /// Normalised input → volts.
    pub fn norm_to_input(&self, norm: f64) -> f64 {
        self.input_mid() + norm * self.input_half_span()
    }
    /// Output units → normalised output.
    pub fn output_to_norm(&self, x: f64) -> f64 {
        (x - self.output_mid()) / self.output_half_span()
    }
    /// Normalised output → output units.
    pub fn norm_to_output(&self, norm: f64) -> f64 {
        self.output_mid() + norm * self.output_half_span()
    }
    /// Ratio that turns a physical gain (output units per volt) into a normalised one.
    pub fn gain_to_norm(&self) -> f64 {
        self.input_half_span() / self.output_half_span()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_map_onto_minus_one_to_one_and_back() {
        let s = Scaling::new(0.0, 150.0, -2.0, 18.0).unwrap();
        assert_eq!(s.input_to_norm(0.0), -1.0);
        assert_eq!(s.input_to_norm(150.0), 1.0);
        assert_eq!(s.output_to_norm(8.0), 0.0);
        assert!((s.norm_to_input(s.input_to_norm(42.0)) - 42.0).abs() < 1e-12);
    }

    #[test]
    fn empty_or_non_finite_ranges_are_refused() {
        assert_eq!(
            Scaling::new(1.0, 1.0, 0.0, 1.0),
            Err(RangeError::EmptyInput)
        );
        assert_eq!(
            Scaling::new(0.0, 1.0, f64::NAN, 1.0),
            Err(RangeError::EmptyOutput)
        );
    }
}
