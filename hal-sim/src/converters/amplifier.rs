//! The piezo amplifier between a DAC output and a stack: voltage gain and offset, output
//! rails, a slew-rate limit and output noise.
//!
//! Per control period the output moves toward `offset + gain · input`, by at most
//! `slew · dt`, and is then held (the plant sees a zero-order hold); noise is added to what the
//! stack sees, not to the amplifier's state; the result is clamped to the rails.

use super::noise::GaussianNoise;

/// An amplifier's settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AmplifierConfig {
    /// Voltage gain, V/V.
    pub gain: f64,
    /// Output offset, volts.
    pub offset_volts: f64,
    /// Output rails `(min, max)`, volts.
    pub rails_volts: (f64, f64),
    /// Slew-rate limit, V/s.
    pub slew_volts_per_second: f64,
    /// Output noise, V rms (per sample).
    pub noise_rms_volts: f64,
}

impl AmplifierConfig {
    /// An amplifier that maps `0 … full_scale_input` volts onto the 0–150 V stack range, with
    /// a 1 V/µs slew limit (a 750 Hz, 70 V sine needs 0.33 V/µs) and 1 mV rms noise.
    pub fn for_input_span(full_scale_input_volts: f64) -> Self {
        Self {
            gain: 150.0 / full_scale_input_volts,
            offset_volts: 0.0,
            rails_volts: (0.0, 150.0),
            slew_volts_per_second: 1.0e6,
            noise_rms_volts: 1.0e-3,
        }
    }
}

/// One amplifier channel with its state.
#[derive(Clone, Debug, PartialEq)]
pub struct Amplifier {
    config: AmplifierConfig,
    output: f64,
    noise: GaussianNoise,
}

impl Amplifier {
    /// A channel at its lower rail, noise seeded with `seed`.
    pub fn new(config: AmplifierConfig, seed: u64) -> Self {
        Self {
            output: config.rails_volts.0,
            config,
            noise: GaussianNoise::new(seed),
        }
    }

    /// One control period of `dt` seconds with the DAC at `input_volts`: returns the voltage
    /// the stack sees for the period.
    #[inline]
    pub fn drive(&mut self, input_volts: f64, dt: f64) -> f64 {
        let c = &self.config;
        let target = c.offset_volts + c.gain * input_volts;
        let max_step = c.slew_volts_per_second * dt;
        self.output += (target - self.output).clamp(-max_step, max_step);
        self.output = self.output.clamp(c.rails_volts.0, c.rails_volts.1);
        (self.output + self.noise.sample(c.noise_rms_volts)).clamp(c.rails_volts.0, c.rails_volts.1)
    }

    /// The noiseless output, volts.
    pub fn output_volts(&self) -> f64 {
        self.output
    }

    /// The settings.
    pub fn config(&self) -> &AmplifierConfig {
        &self.config
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quiet() -> AmplifierConfig {
        AmplifierConfig {
            noise_rms_volts: 0.0,
            ..AmplifierConfig::for_input_span(5.0)
        }
    }

    #[test]
    fn gain_maps_the_dac_span_onto_the_stack_range_within_the_rails() {
        let mut a = Amplifier::new(quiet(), 1);
        let dt = 1.0; // no slew limit in one long period
        assert_eq!(a.drive(2.5, dt), 75.0);
        assert_eq!(a.drive(5.0, dt), 150.0);
        assert_eq!(a.drive(6.0, dt), 150.0, "clamped at the upper rail");
        assert_eq!(a.drive(-1.0, dt), 0.0, "clamped at the lower rail");
    }

    #[test]
    fn a_full_scale_step_is_slew_limited() {
        let mut a = Amplifier::new(quiet(), 1);
        let dt = 2e-5; // 20 V per period at 1 V/µs
        assert!((a.drive(5.0, dt) - 20.0).abs() < 1e-9);
        assert!((a.drive(5.0, dt) - 40.0).abs() < 1e-9);
        for _ in 0..10 {
            a.drive(5.0, dt);
        }
        assert_eq!(a.output_volts(), 150.0);
    }
}
