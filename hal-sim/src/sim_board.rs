//! `SimBoard`: the emulated board — DAC(s), amplifiers, plant, position sensor, sensor ADC —
//! behind the library's [`DualDac`] and [`SensorAdc`], so the control tick drives it exactly
//! as it drives the real board.
//!
//! [`SimBoard::split`] gives the DAC and the ADC as two handles for code that takes them
//! separately, as the control tick does; the board itself implements both traits too.
//!
//! Each [`DualDac::write_both`] writes the codes (through the SPI driver and the emulated chip,
//! for the external variant), passes the DAC outputs through the amplifiers, advances the plant
//! one control period, and presents the new displacement, through the sensor, at the ADC's
//! input. [`SensorAdc::read`] returns what the ADC returns: the conversion of the previous
//! period (one sample of latency).
//!
//! That is the board's discrete loop ([`twinstack::board::sample_to_output_s`]): there the DAC
//! latches a tick's drive at the next timer event and holds it one period, and the tick after
//! that reads the sample taken just before its own event — the drive of tick `k` is first seen
//! by tick `k + 2`, here as there. The simulated periods are the board's shifted by one (here a
//! write drives the period that follows it at once), and the simulation samples at the period's
//! boundary, without the board's 2 µs lead ([`twinstack::board::SAMPLE_LEAD_NS`]).
//!
//! Two variants:
//! * [`InternalBoard`]: the STM32's 12-bit DAC (3.3 V reference) and a 12-bit ADC over
//!   0–3.3 V.
//! * [`ExternalBoard`]: the library's [`Dac856x`] driver on an emulated DAC8562 (gain 2 on its
//!   2.5 V reference: 0–5 V), and its [`Ads8689`] driver on an emulated ADS8689 (±10.24 V) with a
//!   ±10 V sensor.

use crate::analog_source::SetpointInput;
use crate::converters::{
    Ads8689FrameError, Amplifier, AmplifierConfig, AnalogDualDac, AnalogSensorAdc,
    Dac856xFrameError, Dac856xVariant, EmulatedAds8689, EmulatedDac856x, InternalAdc,
    InternalAdcError, InternalDac, PositionSensor,
};
use crate::plant::{Configuration, Plant, PlantConfig, PlantError};
use core::cell::Cell;
use twinstack::board::{AdcCode, DacCode, DualDac, SensorAdc};
use twinstack::converters::{Ads8689, Ads8689Error, Dac856x, Gain, InputRange};

/// The board with the internal converters.
pub type InternalBoard = SimBoard<InternalDac, InternalAdc>;
/// The board with the external SPI converters (driver → emulated chip).
pub type ExternalBoard = SimBoard<Dac856x<EmulatedDac856x>, Ads8689<EmulatedAds8689>>;

/// Settings of a simulated board beyond the plant.
#[derive(Clone, Debug, PartialEq)]
pub struct BoardConfig {
    /// The plant.
    pub plant: PlantConfig,
    /// Stage displacement the sensor's output range covers, µm `(min, max)`.
    pub sensor_range_um: (f64, f64),
    /// Sensor noise, µm rms.
    pub sensor_noise_um: f64,
    /// Amplifier slew limit, V/s.
    pub slew_volts_per_second: f64,
    /// Amplifier output noise, V rms.
    pub amplifier_noise_volts: f64,
    /// Seed of every noise source on the board.
    pub seed: u64,
}

impl BoardConfig {
    /// The paper's stage in `configuration` with the default converters: sensor range
    /// ±45 µm (differential) or −5…70 µm (unidirectional), 2 nm rms sensor noise,
    /// 1 V/µs slew, 1 mV rms amplifier noise.
    pub fn paper(configuration: Configuration) -> Self {
        Self {
            plant: PlantConfig::paper(configuration),
            sensor_range_um: match configuration {
                Configuration::Differential => (-45.0, 45.0),
                Configuration::Unidirectional => (-5.0, 70.0),
            },
            sensor_noise_um: 0.002,
            slew_volts_per_second: 1.0e6,
            amplifier_noise_volts: 1.0e-3,
            seed: 1,
        }
    }

    fn amplifiers(&self, dac_span_volts: f64) -> [Amplifier; 2] {
        let config = AmplifierConfig {
            slew_volts_per_second: self.slew_volts_per_second,
            noise_rms_volts: self.amplifier_noise_volts,
            ..AmplifierConfig::for_input_span(dac_span_volts)
        };
        [
            Amplifier::new(config, self.seed.wrapping_mul(3)),
            Amplifier::new(config, self.seed.wrapping_mul(3).wrapping_add(1)),
        ]
    }

    fn sensor(&self, volts: (f64, f64)) -> PositionSensor {
        let volts_per_um = (volts.1 - volts.0) / (self.sensor_range_um.1 - self.sensor_range_um.0);
        PositionSensor::spanning(
            self.sensor_range_um,
            volts,
            self.sensor_noise_um * volts_per_um,
            self.seed.wrapping_mul(3).wrapping_add(2),
        )
    }
}

/// Why a simulated board could not be built.
#[derive(Debug, PartialEq)]
pub enum BoardError {
    /// The plant configuration is invalid.
    Plant(PlantError),
    /// The sensor range is empty or not finite.
    SensorRange((f64, f64)),
    /// The DAC driver's initialisation failed on the emulated chip.
    DacInit(Dac856xFrameError),
    /// The ADC driver's initialisation failed on the emulated chip.
    AdcInit(Ads8689Error<Ads8689FrameError>),
    /// The internal ADC's settings are invalid.
    Adc(InternalAdcError),
}

impl core::fmt::Display for BoardError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Plant(e) => write!(f, "plant: {e}"),
            Self::SensorRange((lo, hi)) => write!(f, "sensor range {lo}…{hi} µm is empty"),
            Self::DacInit(e) => write!(f, "DAC8562 initialisation: {e:?}"),
            Self::AdcInit(e) => write!(f, "ADS8689 initialisation: {e:?}"),
            Self::Adc(e) => write!(f, "internal ADC: {e:?}"),
        }
    }
}

impl std::error::Error for BoardError {}

/// The emulated board.
#[derive(Debug)]
pub struct SimBoard<D, A> {
    chain: DriveChain<D>,
    adc: A,
    /// The wire from the sensor's output to the ADC's input, volts.
    sensor_node: Cell<f64>,
    /// The analog setpoint input's pin and ADC channel.
    setpoint_input: SetpointInput,
}

/// Everything from the DAC codes to the sensor's output voltage.
#[derive(Debug)]
struct DriveChain<D> {
    dac: D,
    amplifiers: [Amplifier; 2],
    plant: Plant,
    sensor: PositionSensor,
    periods: u64,
    /// A jumper from the left DAC channel to the ADC's input in place of the sensor.
    loopback: bool,
}

impl<D: AnalogDualDac> DriveChain<D> {
    /// Writes the codes, runs the amplifiers and one plant period; returns the sensor's output.
    fn write_and_advance(&mut self, left: DacCode, right: DacCode) -> Result<f64, D::Error> {
        self.dac.write_both(left, right)?;
        let dt = self.plant.dt();
        let [vl, vr] = self.dac.output_volts();
        let ul = self.amplifiers[0].drive(vl, dt);
        let ur = self.amplifiers[1].drive(vr, dt);
        let x = self.plant.step(ul, ur);
        self.periods += 1;
        let sensor = self.sensor.volts(x);
        Ok(if self.loopback { vl } else { sensor })
    }
}

/// The board's DAC side as its own [`DualDac`] (from [`SimBoard::split`]): a write advances
/// the board one control period.
#[derive(Debug)]
pub struct BoardDac<'a, D> {
    chain: &'a mut DriveChain<D>,
    sensor_node: &'a Cell<f64>,
}

/// The board's sensor ADC as its own [`SensorAdc`] (from [`SimBoard::split`]).
#[derive(Debug)]
pub struct BoardAdc<'a, A> {
    adc: &'a mut A,
    sensor_node: &'a Cell<f64>,
    setpoint_input: &'a SetpointInput,
    /// The control period about to run (what the setpoint input converts).
    period: u64,
    dt: f64,
}

impl<D: AnalogDualDac> DualDac for BoardDac<'_, D> {
    type Error = D::Error;

    fn full_scale(&self) -> DacCode {
        self.chain.dac.full_scale()
    }

    /// Writes the codes, then advances the board one control period.
    fn write_both(&mut self, left: DacCode, right: DacCode) -> Result<(), Self::Error> {
        let volts = self.chain.write_and_advance(left, right)?;
        self.sensor_node.set(volts);
        Ok(())
    }
}

impl<A: AnalogSensorAdc> SensorAdc for BoardAdc<'_, A> {
    type Error = A::Error;

    fn full_scale(&self) -> AdcCode {
        self.adc.full_scale()
    }

    /// Converts what the sensor shows now; returns what the ADC returns (the previous
    /// period's conversion).
    fn read(&mut self) -> Result<AdcCode, Self::Error> {
        self.adc.set_input_volts(self.sensor_node.get());
        self.adc.read()
    }

    /// The setpoint input's conversion at the start of this period (converted on the same
    /// trigger, before the tick).
    fn setpoint_input(&mut self) -> Option<u16> {
        self.setpoint_input.reading(self.period, self.dt)
    }
}

fn checked_sensor_range(config: &BoardConfig) -> Result<(), BoardError> {
    let (lo, hi) = config.sensor_range_um;
    if lo.is_finite() && hi.is_finite() && hi > lo {
        Ok(())
    } else {
        Err(BoardError::SensorRange(config.sensor_range_um))
    }
}

impl InternalBoard {
    /// The board with the STM32's converters: 12-bit DAC on 3.3 V, 12-bit ADC over 0–3.3 V.
    pub fn internal(config: &BoardConfig) -> Result<Self, BoardError> {
        checked_sensor_range(config)?;
        let plant = Plant::new(&config.plant).map_err(BoardError::Plant)?;
        let adc = internal_adc(SENSOR_LATENCY)?;
        Ok(SimBoard::new(
            InternalDac::new(3.3),
            config.amplifiers(3.3),
            plant,
            config.sensor((0.0, 3.3)),
            adc,
        ))
    }

    /// The sensor ADC's reading `latency` conversions late instead of
    /// [`SENSOR_LATENCY`]: a board whose converters are timed otherwise than the firmware's
    /// (0: the reading one tick sooner, as when the conversion started on the tick's own timer
    /// event and finished before a short tick read it), for rehearsing the fault that
    /// `twinstack selftest`'s loopback check measures. At most
    /// [`crate::converters::internal_adc::MAX_LATENCY`].
    pub fn set_sensor_latency(&mut self, latency: usize) -> Result<(), BoardError> {
        self.adc = internal_adc(latency)?;
        Ok(())
    }
}

/// The STM32's sensor ADC: 12 bits over 0–3.3 V, its reading `latency` conversions late.
fn internal_adc(latency: usize) -> Result<InternalAdc, BoardError> {
    InternalAdc::new(12, (0.0, 3.3), latency).map_err(BoardError::Adc)
}

/// Conversions the internal sensor ADC's reading lags: 1, the board's timing — the tick reads
/// the sample taken just before its own timer event, which sees the drive the DAC latched at
/// the previous event, i.e. the one written two ticks before
/// ([`twinstack::control::feedback::SENSOR_DELAY_TICKS`]).
pub const SENSOR_LATENCY: usize = 1;

impl ExternalBoard {
    /// The board with the external converters: the library's drivers initialise the emulated
    /// DAC8562 (gain 2: 0–5 V) and ADS8689 (±10.24 V) over SPI; the sensor spans ±10 V.
    pub fn external(config: &BoardConfig) -> Result<Self, BoardError> {
        checked_sensor_range(config)?;
        let plant = Plant::new(&config.plant).map_err(BoardError::Plant)?;
        let mut dac = Dac856x::new(EmulatedDac856x::new(Dac856xVariant::Dac8562, 0.0));
        dac.init(Gain::Two).map_err(BoardError::DacInit)?;
        let mut adc = Ads8689::new(EmulatedAds8689::new());
        adc.init(InputRange::Bipolar2p5)
            .map_err(BoardError::AdcInit)?;
        Ok(SimBoard::new(
            dac,
            config.amplifiers(5.0),
            plant,
            config.sensor((-10.0, 10.0)),
            adc,
        ))
    }
}

impl<D: AnalogDualDac, A: AnalogSensorAdc> SimBoard<D, A> {
    /// A board from its parts; the ADC input starts at the plant's present displacement.
    pub fn new(
        dac: D,
        amplifiers: [Amplifier; 2],
        plant: Plant,
        mut sensor: PositionSensor,
        adc: A,
    ) -> Self {
        let sensor_node = Cell::new(sensor.volts(plant.stage_um()));
        Self {
            chain: DriveChain {
                dac,
                amplifiers,
                plant,
                sensor,
                periods: 0,
                loopback: false,
            },
            adc,
            sensor_node,
            setpoint_input: SetpointInput::default(),
        }
    }

    /// What drives the analog setpoint input's pin from now on.
    pub fn set_setpoint_input(&mut self, input: SetpointInput) {
        self.setpoint_input = input;
    }

    /// The analog setpoint input's pin.
    pub fn setpoint_input(&self) -> &SetpointInput {
        &self.setpoint_input
    }

    /// The DAC and the ADC as two handles, for code that takes them separately (the control
    /// tick: `controller.tick(setpoint, &mut adc, &mut dac)`).
    pub fn split(&mut self) -> (BoardDac<'_, D>, BoardAdc<'_, A>) {
        let (period, dt) = (self.chain.periods, self.chain.plant.dt());
        (
            BoardDac {
                chain: &mut self.chain,
                sensor_node: &self.sensor_node,
            },
            BoardAdc {
                adc: &mut self.adc,
                sensor_node: &self.sensor_node,
                setpoint_input: &self.setpoint_input,
                period,
                dt,
            },
        )
    }

    /// Fits (`true`) or removes a jumper from the left DAC channel's output to the sensor
    /// ADC's input, in place of the sensor: the ADC then reads the DAC's volts (from the
    /// next write on), which `twinstack selftest` checks the converters with. The stage is
    /// still driven.
    pub fn set_loopback(&mut self, fitted: bool) {
        self.chain.loopback = fitted;
    }

    /// The plant (displacement, tips, charges, hysteresis voltages).
    pub fn plant(&self) -> &Plant {
        &self.chain.plant
    }

    /// The DAC (or its driver, whose `device()` is the emulated chip).
    pub fn dac(&self) -> &D {
        &self.chain.dac
    }

    /// The ADC (or its driver).
    pub fn adc(&self) -> &A {
        &self.adc
    }

    /// The position sensor.
    pub fn sensor(&self) -> &PositionSensor {
        &self.chain.sensor
    }

    /// Amplifier outputs `[left, right]` (noiseless), volts.
    pub fn amplifier_volts(&self) -> [f64; 2] {
        self.chain.amplifiers.each_ref().map(|a| a.output_volts())
    }

    /// Control periods simulated so far.
    pub fn periods(&self) -> u64 {
        self.chain.periods
    }

    /// Simulated time, seconds.
    pub fn time_seconds(&self) -> f64 {
        self.chain.periods as f64 * self.chain.plant.dt()
    }
}

impl<D: AnalogDualDac, A: AnalogSensorAdc> DualDac for SimBoard<D, A> {
    type Error = D::Error;

    fn full_scale(&self) -> DacCode {
        self.chain.dac.full_scale()
    }

    /// Writes the codes, then advances the board one control period.
    fn write_both(&mut self, left: DacCode, right: DacCode) -> Result<(), Self::Error> {
        self.split().0.write_both(left, right)
    }
}

impl<D: AnalogDualDac, A: AnalogSensorAdc> SensorAdc for SimBoard<D, A> {
    type Error = A::Error;

    fn full_scale(&self) -> AdcCode {
        self.adc.full_scale()
    }

    fn read(&mut self) -> Result<AdcCode, Self::Error> {
        self.split().1.read()
    }

    fn setpoint_input(&mut self) -> Option<u16> {
        self.split().1.setpoint_input()
    }
}
