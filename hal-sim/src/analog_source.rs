//! The simulated board's analog setpoint input ([`twinstack::sources::analog_input`]): the voltage a
//! lab's controller puts on the board's input pin, tick by tick, converted as the board's
//! 12-bit ADC converts it (0–3.3 V, on the control timer's trigger before each tick).
//!
//! ```
//! use hal_sim::analog_source::{AnalogSource, SetpointInput};
//! let input = SetpointInput::new(AnalogSource::Step { before: 0.0, after: 3.3, at_tick: 10 });
//! assert_eq!(input.reading(9, 2e-5), Some(0));
//! assert_eq!(input.reading(10, 2e-5), Some(4095 << 4));
//! ```

/// The ADC's reference: full scale at the pin, volts.
pub const INPUT_FULL_SCALE_VOLTS: f64 = 3.3;
/// The ADC's resolution, bits.
pub const INPUT_BITS: u32 = 12;

/// What drives the input pin.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum AnalogSource {
    /// Nothing: the pin's pull-down holds it at 0 V (what an open input or a cut cable reads).
    Disconnected,
    /// A constant voltage at the pin.
    Constant(f64),
    /// `before` until tick `at_tick`, then `after` (volts at the pin).
    Step {
        /// Volts before the step.
        before: f64,
        /// Volts from tick `at_tick` on.
        after: f64,
        /// The first tick that converts `after`.
        at_tick: u64,
    },
    /// `offset + amplitude · sin(2π f t)` volts.
    Sine {
        /// Mean, volts.
        offset: f64,
        /// Amplitude, volts.
        amplitude: f64,
        /// Frequency, Hz.
        frequency_hz: f64,
    },
    /// No conversion at all (the ADC's result missing): the tick gets `None`.
    NoConversion,
}

impl std::str::FromStr for AnalogSource {
    type Err = String;

    /// `open` (nothing on the pin), `V` (a constant voltage) or `sine:MEAN,AMPLITUDE,HZ`
    /// (volts, volts, Hz): what `twinstack virtual-board --analog-input` takes.
    ///
    /// ```
    /// use hal_sim::analog_source::AnalogSource;
    /// assert_eq!("1.65".parse(), Ok(AnalogSource::Constant(1.65)));
    /// assert!("sine:1.65,1,2".parse::<AnalogSource>().is_ok());
    /// assert!("sine:1.65,1".parse::<AnalogSource>().is_err());
    /// ```
    fn from_str(s: &str) -> Result<Self, String> {
        let number = |x: &str, what: &str| -> Result<f64, String> {
            match x.trim().parse::<f64>() {
                Ok(v) if v.is_finite() => Ok(v),
                _ => Err(format!("{what} {x:?} is not a finite number")),
            }
        };
        if s == "open" {
            return Ok(AnalogSource::Disconnected);
        }
        if let Some(rest) = s.strip_prefix("sine:") {
            let parts: Vec<&str> = rest.split(',').collect();
            let [mean, amplitude, hz] = parts[..] else {
                return Err(format!(
                    "{s:?}: give sine:MEAN,AMPLITUDE,HZ (three numbers, volts, volts, Hz)"
                ));
            };
            let frequency_hz = number(hz, "the frequency")?;
            if frequency_hz < 0.0 {
                return Err(format!("the frequency {hz} Hz is negative"));
            }
            return Ok(AnalogSource::Sine {
                offset: number(mean, "the mean")?,
                amplitude: number(amplitude, "the amplitude")?,
                frequency_hz,
            });
        }
        number(s, "the voltage")
            .map(AnalogSource::Constant)
            .map_err(|e| format!("{e}: give open, a voltage (e.g. 1.65) or sine:MEAN,AMPLITUDE,HZ"))
    }
}

/// The input pin and its ADC channel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SetpointInput {
    /// What drives the pin.
    pub source: AnalogSource,
}

impl Default for SetpointInput {
    fn default() -> Self {
        Self::new(AnalogSource::Disconnected)
    }
}

impl SetpointInput {
    /// The input driven by `source`.
    pub fn new(source: AnalogSource) -> Self {
        Self { source }
    }

    /// Volts at the pin at tick `tick` (`dt` the control period, s); `None` without a
    /// conversion.
    pub fn volts(&self, tick: u64, dt: f64) -> Option<f64> {
        match self.source {
            AnalogSource::Disconnected => Some(0.0),
            AnalogSource::Constant(v) => Some(v),
            AnalogSource::Step {
                before,
                after,
                at_tick,
            } => Some(if tick >= at_tick { after } else { before }),
            AnalogSource::Sine {
                offset,
                amplitude,
                frequency_hz,
            } => Some(
                offset
                    + amplitude
                        * (2.0 * std::f64::consts::PI * frequency_hz * tick as f64 * dt).sin(),
            ),
            AnalogSource::NoConversion => None,
        }
    }

    /// The conversion the tick `tick` reads: the 12-bit code of the pin's voltage (clipped
    /// to the ADC's range) as UQ0.16 of the span, what [`twinstack::board::SensorAdc::setpoint_input`]
    /// returns.
    pub fn reading(&self, tick: u64, dt: f64) -> Option<u16> {
        let v = self.volts(tick, dt)?;
        let max = ((1u32 << INPUT_BITS) - 1) as f64;
        let code = (v / INPUT_FULL_SCALE_VOLTS * max).round();
        let code = if code.is_nan() {
            0.0
        } else {
            code.clamp(0.0, max)
        } as u16;
        Some(code << (16 - INPUT_BITS))
    }
}
