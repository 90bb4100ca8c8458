//! What a [`SimDevice`](super::SimDevice) is built from: the board, the link's baud rate and
//! the adapter's delays, the settings it boots with; and why a build fails.

use super::*;

/// Everything a simulated device is built from.
#[derive(Clone, Debug)]
pub struct SimDeviceConfig {
    /// The board: stage, converters, noise. Its plant's `dt` sets the control rate.
    pub board: BoardConfig,
    /// UART baud rate, both directions (10 bits per byte).
    pub baud: u32,
    /// The USB–serial adapter between host and UART: each transfer's latency and jitter.
    pub link: LinkDelay,
    /// What the "flash" holds at power-up: `None` (erased: the board boots on the compiled-in
    /// defaults, bypass, no model) or settings stored as the board would store them (it boots
    /// in their mode).
    pub stored: Option<Settings>,
    /// A simulated camera on the trigger input ([`crate::sim_camera`]), or none (the input
    /// stays where [`SimDevice::set_trigger_input`] puts it).
    pub camera: Option<CameraConfig>,
    /// Fraction of bytes the link corrupts, each way (one bit flipped, at random from a
    /// seeded generator): a bad cable, a ground loop, a wrong baud rate. 0: a sound link.
    pub link_error_rate: f64,
    /// A jumper from the left DAC channel to the sensor ADC's input in place of the sensor
    /// (`twinstack selftest`'s loopback): the ADC reads the DAC's output volts.
    pub loopback: bool,
    /// Conversions the sensor ADC's reading lags
    /// ([`crate::sim_board::SENSOR_LATENCY`], the board's timing, unless a test rehearses
    /// converters timed otherwise: [`crate::sim_board::InternalBoard::set_sensor_latency`]).
    pub sensor_latency: usize,
    /// Every flash write fails (the erase goes through, the programming does not: the
    /// sector is left erased), as a worn or locked flash would.
    pub failing_flash: bool,
    /// The watchdog runs (as the firmware starts it at boot): a tick that stops feeding it
    /// (a [`twinstack::protocol::messages::Request::WatchdogDrill`]) resets the board within
    /// [`WATCHDOG_TIMEOUT_MS`]. `false`: a board whose watchdog never fires.
    pub watchdog: bool,
    /// What drives the analog setpoint input's pin ([`crate::analog_source`]); by default
    /// nothing (the pull-down's 0 V).
    pub analog_input: crate::analog_source::AnalogSource,
    /// The analog setpoint input's settings stored with `stored` (ignored without it): with
    /// `start_at_boot`, the board starts the input at power-up as the firmware does.
    pub stored_analog: Option<AnalogInputConfig>,
}

impl SimDeviceConfig {
    /// The paper's differential stage on the STM32's internal converters (12-bit DAC, 12-bit
    /// sensor ADC spanning ±45 µm), 50 kHz, 3 Mbaud, with [`SimDeviceConfig::paper_settings`]
    /// stored to boot in bypass.
    pub fn paper() -> Self {
        Self {
            board: BoardConfig::paper(Configuration::Differential),
            baud: twinstack::protocol::LINK_BAUD,
            link: LinkDelay::IDEAL,
            stored: Some(Self::paper_settings(Mode::Bypass)),
            camera: None,
            link_error_rate: 0.0,
            loopback: false,
            sensor_latency: crate::sim_board::SENSOR_LATENCY,
            failing_flash: false,
            watchdog: true,
            analog_input: crate::analog_source::AnalogSource::Disconnected,
            stored_analog: None,
        }
    }

    /// [`SimDeviceConfig::paper`] at `rate_hz` ticks a second, behind a link of `baud` with
    /// `link`'s latency: the board a link measurement streams to.
    ///
    /// ```
    /// use hal_sim::sim_device::{LinkDelay, SimDeviceConfig};
    /// let config = SimDeviceConfig::paper_at(100e3, 3_000_000, LinkDelay::ADAPTER);
    /// assert_eq!(config.board.plant.dt, 1e-5);
    /// ```
    pub fn paper_at(rate_hz: f64, baud: u32, link: LinkDelay) -> Self {
        let mut config = Self {
            baud,
            link,
            ..Self::paper()
        };
        config.board.plant.dt = 1.0 / rate_hz;
        config
    }

    /// Settings for the paper's differential stage in `mode`: 0…140 V on the left stack onto
    /// the sensor's ±45 µm (its calibration), bias 70 V, 0…140 V limits, 0.9 V/µs slew, a
    /// representative 8-operator P–I model (total slope ≈ 0.4 µm/V) as compensator and
    /// observer (not identified: load
    /// the identification's settings for accuracy), and the shipped default feedback
    /// ([`FeedbackSettings::DEFAULT`], stable at every allowed rate; `twinstack tune` chooses
    /// faster gains).
    pub fn paper_settings(mode: Mode) -> Settings {
        let n = 8;
        let thresholds: Vec<f64> = (0..n).map(|i| i as f64 * 140.0 / n as f64).collect();
        // Total slope ≈ 0.4 µm/V, the first operator carrying most of it.
        let weights: Vec<f64> = (0..n)
            .map(|i| if i == 0 { 0.25 } else { 0.15 / (n - 1) as f64 })
            .collect();
        let model = pi_model(0.0, -28.0, &thresholds, &weights)
            .expect("8 increasing thresholds and positive weights form a model");
        let mut drive = twinstack::control::drive::DriveSettings::DEFAULT;
        drive.slew_rate = 0.9e6;
        Settings {
            ranges: Scaling {
                input_min: 0.0,
                input_max: 140.0,
                output_min: -45.0,
                output_max: 45.0,
            },
            compensator: Some(model.clone()),
            observer: Some(model),
            drive,
            sensor: Some(SensorSettings {
                displacement_at_zero: -45.0,
                displacement_at_full_scale: 45.0,
                drift_limit: None,
            }),
            feedback: Some(FeedbackSettings::DEFAULT),
            mode,
            creep: None,
            shaping: None,
            preview: None,
            output_map: None,
        }
    }
}

/// The delay a USB–serial adapter adds to each transfer, each way: the host's writes reach
/// the UART, and the UART's bytes reach the host, `latency ± jitter` later (uniform, from a
/// seeded generator: the same run every time), never out of order. An FTDI adapter's latency
/// timer holds received bytes up to 16 ms by default; [`LinkDelay::ADAPTER`] models that
/// bound both ways.
///
/// ```
/// use std::time::Duration;
/// use hal_sim::sim_device::LinkDelay;
/// let link = LinkDelay::new(Duration::from_millis(16), Duration::from_millis(4)).unwrap();
/// assert_eq!(link, LinkDelay::ADAPTER);
/// assert!(LinkDelay::new(Duration::from_millis(1), Duration::from_millis(2)).is_err());
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LinkDelay {
    /// Mean delay of a transfer.
    pub latency: Duration,
    /// Largest departure from it, either way (≤ `latency`).
    pub jitter: Duration,
    /// Seed of the jitter's generator.
    pub seed: u64,
}

impl LinkDelay {
    /// No adapter: bytes take only their time on the line.
    pub const IDEAL: LinkDelay = LinkDelay {
        latency: Duration::ZERO,
        jitter: Duration::ZERO,
        seed: 1,
    };
    /// An FTDI-like adapter at its default latency timer: 16 ms ± 4 ms each way.
    pub const ADAPTER: LinkDelay = LinkDelay {
        latency: Duration::from_millis(16),
        jitter: Duration::from_millis(4),
        seed: 1,
    };

    /// `latency ± jitter`; a jitter larger than the latency (a negative delay) is refused.
    pub fn new(latency: Duration, jitter: Duration) -> Result<Self, SimDeviceError> {
        if jitter > latency {
            return Err(SimDeviceError::Jitter { latency, jitter });
        }
        Ok(LinkDelay {
            latency,
            jitter,
            seed: 1,
        })
    }
}

/// Why a simulated device could not be built.
#[derive(Debug)]
pub enum SimDeviceError {
    /// The board.
    Board(BoardError),
    /// The stored settings could not be written (too large for the record).
    Stored,
    /// The compiled-in settings were refused on this board (its rate or converters).
    Defaults(Refusal),
    /// Baud rate zero.
    Baud,
    /// The coarse axis of the dual-stage board could not be built (which setting, why).
    Coarse(String),
    /// A link error rate outside 0…1.
    ErrorRate(f64),
    /// The link's jitter exceeds its latency.
    Jitter {
        /// The latency asked for.
        latency: Duration,
        /// The jitter asked for.
        jitter: Duration,
    },
}

impl std::fmt::Display for SimDeviceError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Board(e) => write!(f, "simulated board: {e}"),
            Self::Stored => write!(f, "the stored settings do not fit a flash record"),
            Self::Defaults(r) => write!(f, "compiled-in settings refused: {r}"),
            Self::Baud => write!(f, "baud rate must be positive"),
            Self::Coarse(e) => write!(f, "coarse axis: {e}"),
            Self::ErrorRate(r) => write!(
                f,
                "link error rate {r}: must be a fraction of bytes from 0 to 1"
            ),
            Self::Jitter { latency, jitter } => write!(
                f,
                "link jitter {jitter:?} exceeds its latency {latency:?} (a delay cannot be negative)"
            ),
        }
    }
}

impl std::error::Error for SimDeviceError {}

/// The simulated board's hardware facts at `rate_hz`: the driver board's 150 V amplifier, 12-bit
/// DAC and 12-bit sensor ADC.
pub fn hardware(rate_hz: f64) -> Hardware {
    Hardware::driver_board(rate_hz)
}
