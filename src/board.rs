//! The board as the control tick sees it: a dual DAC that updates both stacks at once, and a
//! sensor ADC. `embedded-hal` 1.0 has no DAC or ADC trait, so these are ours; the firmware
//! implements them over the STM32's registers (or the external SPI converters), and `hal-sim`
//! over its emulated converters.
//!
//! The coarse stage of a dual-actuated axis adds two more: a step/direction output
//! ([`StepDir`]) and quadrature encoder inputs ([`QuadratureEncoder`]).

/// What the board's hardware fixes, whatever the settings say: the amplifier, the DAC, the
/// sensor's ADC and the control rate. One value per board, in one place
/// ([`Hardware::driver_board`] for the STM32F405 driver board); settings are validated
/// against it.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Hardware {
    /// Amplifier output at DAC full scale, volts (the amplifier's gain times the DAC's span).
    pub amplifier_full_scale: f64,
    /// Full-scale DAC code (4095 for the STM32's 12-bit DAC, 65535 for a 16-bit one).
    pub dac_full_scale: u16,
    /// The position sensor's ADC resolution in bits (1…30), or `None`: no sensor input.
    pub sensor_adc_bits: Option<u8>,
    /// Control (tick) rate, Hz.
    pub control_rate_hz: f64,
}

impl Hardware {
    /// Slowest control rate the board runs, Hz.
    pub const MIN_CONTROL_RATE_HZ: u32 = 10_000;
    /// Fastest control rate the board runs, Hz.
    pub const MAX_CONTROL_RATE_HZ: u32 = 100_000;
    /// The default control rate, Hz.
    pub const DEFAULT_CONTROL_RATE_HZ: u32 = 50_000;

    /// The STM32F405 driver board at `control_rate_hz`: a 150 V amplifier on the 12-bit DAC,
    /// the sensor on a 12-bit ADC input.
    ///
    /// ```
    /// let hw = twinstack::board::Hardware::driver_board(50_000.0);
    /// assert_eq!(hw.dac_full_scale, 4095);
    /// ```
    pub const fn driver_board(control_rate_hz: f64) -> Self {
        Self {
            amplifier_full_scale: 150.0,
            dac_full_scale: 4095,
            sensor_adc_bits: Some(12),
            control_rate_hz,
        }
    }
}

/// How long before each tick's timer event the sensor (and the analog setpoint input) is
/// sampled, ns: TIM2's channel 2 compare starts the conversions this early, so that a
/// conversion (≈ 1.3 µs with the trigger's synchronisation) is complete before the control
/// interrupt starts, whatever the interrupt's start latency and however long the tick takes
/// to reach its sensor read. The reading a tick uses is then always the sample taken
/// [`SAMPLE_LEAD_NS`] before its own timer event — never, depending on the configuration, the
/// one a period older.
pub const SAMPLE_LEAD_NS: u32 = 2_000;

/// The board's timing at `control_rate_hz`, s: from the instant the sensor is sampled to the
/// instant the drive computed from that sample appears at both DAC outputs.
///
/// The DAC's outputs are latched by the timer's update event (TIM2 `TRGO` triggers the
/// transfer of both holding registers at once), so a tick's drive goes out at the **next**
/// timer event: the output instant is set by hardware, with no jitter from the interrupt's
/// start or from what the tick runs. The sample was taken [`SAMPLE_LEAD_NS`] before the tick's
/// own event, so the latency is one period plus that lead: 22 µs at 50 kHz, 12 µs at 100 kHz.
///
/// ```
/// let l = twinstack::board::sample_to_output_s(100_000.0);
/// assert!((l - 12e-6).abs() < 1e-12);
/// ```
pub fn sample_to_output_s(control_rate_hz: f64) -> f64 {
    1.0 / control_rate_hz + SAMPLE_LEAD_NS as f64 * 1e-9
}

/// The board's independent watchdog timeout, ms: a tick that stops feeding it (a hung
/// interrupt, a fault loop, or [`crate::protocol::messages::Request::WatchdogDrill`]) resets
/// the MCU within this time. The board's IWDG (`hardware::watchdog`) and the simulated
/// board's model of it both use it.
pub const WATCHDOG_TIMEOUT_MS: u32 = 20;

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

    /// The analog setpoint input's most recent conversion ([`crate::sources::analog_input`]),
    /// converted on the same trigger as the sensor: a fraction of the input's span, UQ0.16
    /// (0 = 0 V at the pin, 65535 = full scale; a 12-bit code shifted left by 4). `None`: the
    /// board has no such input (the default) or the conversion failed — a lost input.
    #[inline(always)]
    fn setpoint_input(&mut self) -> Option<u16> {
        None
    }
}

/// Direction of travel of the coarse stage's motor (the step/dir driver's DIR line).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum StepDirection {
    /// Towards increasing position (DIR high).
    Forward,
    /// Towards decreasing position (DIR low).
    Reverse,
}

/// A burst of step pulses for the coarse stage's motor driver, spread evenly over the next
/// coarse period.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct StepBurst {
    /// DIR level for the whole burst.
    pub direction: StepDirection,
    /// Number of STEP pulses (microsteps), at most the output's `max_steps_per_burst`.
    pub steps: u16,
}

/// The coarse stage's step/direction output (a timer generating the STEP pulses, a GPIO for
/// DIR).
pub trait StepDir {
    /// Why a burst was refused (e.g. the previous one is still running).
    type Error;
    /// Most pulses one burst may hold.
    fn max_steps_per_burst(&self) -> u16;
    /// Sets DIR and starts the burst; its pulses are spread evenly over the coarse period.
    /// On error nothing was emitted.
    fn emit(&mut self, burst: StepBurst) -> Result<(), Self::Error>;
}

/// A quadrature encoder input (a timer in encoder mode, ×4 counting): the raw 16-bit counter,
/// which wraps; [`crate::dual_stage::coarse_axis::EncoderCounter`] extends it.
pub trait QuadratureEncoder {
    /// The counter now.
    fn count(&mut self) -> u16;

    /// Whether the input saw an edge it could not count (both lines changing at once, or the
    /// encoder's own error output) since the last call. Inputs that cannot tell answer `false`
    /// (the default); the coarse supervisor treats `true` as a lost encoder.
    fn missed_edges(&mut self) -> bool {
        false
    }
}

/// The coarse stage's switches, as read at one coarse tick (`true`: active).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Switches {
    /// The limit switch at the low end of the travel.
    pub lower: bool,
    /// The limit switch at the high end of the travel.
    pub upper: bool,
    /// The home reference: a switch, or the encoder's index pulse latched by the input until
    /// it is read.
    pub home: bool,
}

/// The coarse stage's limit and home switch inputs (GPIOs on the board).
pub trait LimitSwitches {
    /// The switches now (the home input's latched index pulse is cleared by the read).
    fn read(&mut self) -> Switches;
}

/// An STM32F4 USART's baud-rate divider (RM0090 §30.3.4): the `BRR` value, whether it needs
/// oversampling by 8 (`CR1.OVER8`), and the rate it gives.
///
/// `BRR` is `USARTDIV` in fixed point: a 12-bit mantissa above a 4-bit fraction (16×
/// oversampling) or a 3-bit one (8×, bit 3 zero), with `USARTDIV = f_PCLK / (oversampling ×
/// baud)`. 16× tolerates more clock error at the receiver (RM0090, "USART receiver tolerance
/// to clock deviation"), so it is chosen whenever `USARTDIV ≥ 1` allows it; below that, only
/// 8× reaches the rate.
///
/// ```
/// use twinstack::board::UartDivider;
/// // The driver board: USART1 on the 84 MHz APB2, 3 Mbaud exact at 16× (USARTDIV 1.75).
/// let d = UartDivider::for_rate(84_000_000, 3_000_000).unwrap();
/// assert_eq!((d.brr, d.over8, d.baud_hz), (28, false, 3_000_000));
/// // The Feather: USART3 on the 42 MHz APB1, where 16× cannot go below 2.625 Mbaud; at 8×,
/// // USARTDIV 1.75 = mantissa 1, fraction 6/8: exact.
/// let d = UartDivider::for_rate(42_000_000, 3_000_000).unwrap();
/// assert_eq!((d.brr, d.over8, d.baud_hz), (0x16, true, 3_000_000));
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct UartDivider {
    /// The `BRR` register's value.
    pub brr: u16,
    /// Oversampling by 8 (`CR1.OVER8 = 1`).
    pub over8: bool,
    /// The rate this divider gives, Hz (rounded down).
    pub baud_hz: u32,
}

impl UartDivider {
    /// The divider nearest `baud_hz` from a `pclk_hz` peripheral clock; `None` when even 8×
    /// oversampling cannot reach it (`USARTDIV < 1`) or the mantissa would not fit 12 bits.
    pub const fn for_rate(pclk_hz: u32, baud_hz: u32) -> Option<Self> {
        if baud_hz == 0 {
            return None;
        }
        // USARTDIV × 16 (or × 8), rounded to nearest: the register's fixed-point value.
        let div16 = (pclk_hz as u64 + baud_hz as u64 / 2) / baud_hz as u64;
        if div16 >= 16 && div16 < 1 << 16 {
            return Some(Self {
                brr: div16 as u16,
                over8: false,
                baud_hz: (pclk_hz as u64 / div16) as u32,
            });
        }
        let div8 = (pclk_hz as u64 + baud_hz as u64 / 2) / baud_hz as u64;
        if div8 < 8 || div8 >= 1 << 15 {
            return None;
        }
        Some(Self {
            brr: ((div8 >> 3) << 4 | (div8 & 7)) as u16,
            over8: true,
            baud_hz: (pclk_hz as u64 / div8) as u32,
        })
    }

    /// The rate's error against `baud_hz`, parts per million (signed: positive is fast).
    pub const fn error_ppm(&self, baud_hz: u32) -> i64 {
        (self.baud_hz as i64 - baud_hz as i64) * 1_000_000 / baud_hz as i64
    }
}

/// Test doubles of the board traits, for tests of code that drives converters: the library's
/// unit tests, and — with the cargo feature `fakes` — any crate's tests (hal-sim's enable it
/// with `twinstack = { path = "..", features = ["fakes"] }` under `[dev-dependencies]`).
///
/// Not built into the firmware: the module exists only under `cfg(test)` or the `fakes`
/// feature.
///
/// ```
/// use twinstack::board::fakes::{FixedAdc, RecordingDac};
/// use twinstack::board::{AdcCode, DacCode, DualDac, SensorAdc};
///
/// let mut dac = RecordingDac::default();
/// dac.write_both(DacCode(1), DacCode(2)).unwrap();
/// assert_eq!((dac.left, dac.right, dac.writes), (DacCode(1), DacCode(2), 1));
///
/// assert_eq!(FixedAdc(Some(AdcCode(7))).read(), Ok(AdcCode(7)));
/// assert!(FixedAdc(None).read().is_err());
/// ```
#[cfg(any(test, feature = "fakes"))]
pub mod fakes {
    use super::*;

    /// A 16-bit DAC that remembers the last pair written and counts the writes; it never fails.
    #[derive(Debug, Default)]
    pub struct RecordingDac {
        /// The last left-channel code written.
        pub left: DacCode,
        /// The last right-channel code written.
        pub right: DacCode,
        /// How many pairs were written.
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

    /// A 16-bit ADC that always returns the same result (`None`: the read fails).
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

    /// Switches that read what the test puts in them.
    #[derive(Debug, Default)]
    pub struct FixedSwitches(pub Switches);

    impl LimitSwitches for FixedSwitches {
        fn read(&mut self) -> Switches {
            self.0
        }
    }

    /// A quadrature encoder whose counter reads the value the test puts in it.
    #[derive(Debug)]
    pub struct FixedEncoder(pub u16);

    impl QuadratureEncoder for FixedEncoder {
        fn count(&mut self) -> u16 {
            self.0
        }
    }
}

#[cfg(test)]
mod tests {
    use super::UartDivider;

    #[test]
    fn the_link_rate_is_exact_on_both_boards_and_refused_where_no_divider_reaches_it() {
        // Driver board (APB2 84 MHz, 16×) and Feather (APB1 42 MHz, 8×): 3 Mbaud, 0 ppm.
        for (pclk, over8) in [(84_000_000, false), (42_000_000, true)] {
            let d = UartDivider::for_rate(pclk, 3_000_000).unwrap();
            assert_eq!((d.over8, d.error_ppm(3_000_000)), (over8, 0), "{d:?}");
        }
        // 16× at 42 MHz would need USARTDIV 0.875 (< 1): the 8× divider is the only one.
        assert_eq!(
            UartDivider::for_rate(42_000_000, 3_000_000).unwrap().brr,
            0x16
        );
        // The emulator's 16 MHz HSI cannot reach 3 Mbaud at all (USARTDIV×8 = 5.3 < 8).
        assert_eq!(UartDivider::for_rate(16_000_000, 3_000_000), None);
        assert_eq!(UartDivider::for_rate(16_000_000, 0), None);
        // A rate that does not divide: 115 200 baud from 42 MHz at 16×, BRR 365 (22.8125),
        // 115 068 baud, −1 145 ppm.
        let d = UartDivider::for_rate(42_000_000, 115_200).unwrap();
        assert_eq!((d.brr, d.over8, d.baud_hz), (365, false, 115_068));
        assert_eq!(d.error_ppm(115_200), -1_145);
    }
}
