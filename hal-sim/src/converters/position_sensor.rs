//! The position sensor: stage displacement (µm) to volts at the ADC input, with noise.

use super::noise::GaussianNoise;

/// A linear displacement sensor `V = offset + gain · x + noise`.
#[derive(Clone, Debug, PartialEq)]
pub struct PositionSensor {
    volts_per_um: f64,
    offset_volts: f64,
    noise_rms_volts: f64,
    noise: GaussianNoise,
}

impl PositionSensor {
    /// A sensor mapping `[min_um, max_um]` linearly onto `[min_volts, max_volts]`, with
    /// `noise_rms_volts` of white noise (seeded with `seed`).
    pub fn spanning(
        (min_um, max_um): (f64, f64),
        (min_volts, max_volts): (f64, f64),
        noise_rms_volts: f64,
        seed: u64,
    ) -> Self {
        let volts_per_um = (max_volts - min_volts) / (max_um - min_um);
        Self {
            volts_per_um,
            offset_volts: min_volts - volts_per_um * min_um,
            noise_rms_volts,
            noise: GaussianNoise::new(seed),
        }
    }

    /// The sensor's output for a displacement of `x_um`.
    #[inline]
    pub fn volts(&mut self, x_um: f64) -> f64 {
        self.offset_volts + self.volts_per_um * x_um + self.noise.sample(self.noise_rms_volts)
    }

    /// Sensitivity, V/µm.
    pub fn volts_per_um(&self) -> f64 {
        self.volts_per_um
    }

    /// Output at zero displacement, volts.
    pub fn offset_volts(&self) -> f64 {
        self.offset_volts
    }
}
