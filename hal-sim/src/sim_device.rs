//! [`SimDevice`]: the whole board in-process — the simulated converters and stage
//! ([`SimBoard`]), the library's control loop and the library's command handler, exactly as
//! the firmware wires them — behind [`Transport`], so the host's protocol client talks to it
//! as it talks to a serial port, with no emulator.
//!
//! **Time is simulated.** Nothing runs between calls. [`Transport::send`] queues bytes on the
//! host → board line; they arrive one every `10 / baud` seconds (8N1: ten bits a byte) after
//! the line is free. [`Transport::receive`] advances simulated time tick by tick (at the
//! control rate, 50 kHz by default) for up to `timeout` of *simulated* time: before each tick,
//! the bytes that have arrived are fed to the command handler (the firmware's decoder task runs
//! between ticks); its responses leave on the board → host line at the same byte rate; the
//! call returns as soon as response bytes have arrived (with all that have arrived by then,
//! up to the buffer's size), or `Ok(0)` once `timeout` has passed. So a client's throughput,
//! credits and underruns are those of a board on a UART at that baud rate.
//!
//! ```
//! use std::time::Duration;
//! use hal_sim::link::Transport;
//! use hal_sim::sim_device::{SimDevice, SimDeviceConfig};
//! use twinstack::protocol::frame;
//! use twinstack::protocol::messages::{Request, Response};
//!
//! let mut dev = SimDevice::new(SimDeviceConfig::paper()).unwrap();
//! let mut out = [0u8; 512];
//! let n = frame::encode(&Request::Status, &mut out).unwrap();
//! dev.send(&out[..n]).unwrap();
//! let mut reply = Vec::new();
//! while !reply.ends_with(&[0]) {
//!     let mut buf = [0u8; 64];
//!     let got = dev.receive(&mut buf, Duration::from_millis(10)).unwrap();
//!     assert!(got > 0, "no reply");
//!     reply.extend_from_slice(&buf[..got]);
//! }
//! let mut decoder = twinstack::protocol::decoder::FrameDecoder::new();
//! let (&delimiter, rest) = reply.split_last().unwrap();
//! rest.iter().for_each(|&b| assert!(decoder.push(b).is_none()));
//! let body = decoder.push(delimiter).unwrap().unwrap();
//! let response: Response = frame::decode_body(body).unwrap();
//! assert!(matches!(response, Response::Status(_)));
//! ```

use std::collections::VecDeque;
use std::io;
use std::time::Duration;

use rtic_core::Exclusive;
use twinstack::board::Hardware;
use twinstack::control::{Controller, TickReport};
use twinstack::control_loop::{ControlLoop, SetpointQueue};
use twinstack::param_store::{self, RamStorage, RecordStorage, StoredRecord, MAX_RECORD};
use twinstack::protocol::handler::CommandHandler;
use twinstack::recorder::CAPTURE_SLOTS;
use twinstack::refusal::Refusal;
use twinstack::settings::{pi_model, FeedbackSettings, Mode, SensorSettings, Settings};
use twinstack::Scaling;

use crate::link::Transport;
use crate::plant::Configuration;
use crate::sim_board::{BoardConfig, BoardError, InternalBoard, SimBoard};

/// Everything a simulated device is built from.
#[derive(Clone, Debug)]
pub struct SimDeviceConfig {
    /// The board: stage, converters, noise. Its plant's `dt` sets the control rate.
    pub board: BoardConfig,
    /// UART baud rate, both directions (10 bits per byte).
    pub baud: u32,
    /// What the "flash" holds at power-up: `None` (erased: the board boots on the compiled-in
    /// defaults, bypass, no model) or settings stored as the board would store them (it boots
    /// in their mode).
    pub stored: Option<Settings>,
}

impl SimDeviceConfig {
    /// The paper's differential stage on the STM32's internal converters (12-bit DAC, 12-bit
    /// sensor ADC spanning ±45 µm), 50 kHz, 2 Mbaud, with [`SimDeviceConfig::paper_settings`]
    /// stored to boot in bypass.
    pub fn paper() -> Self {
        Self {
            board: BoardConfig::paper(Configuration::Differential),
            baud: 2_000_000,
            stored: Some(Self::paper_settings(Mode::Bypass)),
        }
    }

    /// Settings for the paper's differential stage in `mode`: 0…140 V on the left stack onto
    /// the sensor's ±45 µm (its calibration), bias 70 V, 0…140 V limits, 0.9 V/µs slew, a
    /// representative 8-operator P–I model (total slope ≈ 0.4 µm/V) as compensator and
    /// observer (not identified: load
    /// the identification's settings for accuracy), PI gains kp 0.2, ki 500 /s, correction
    /// within a tenth of the drive range.
    pub fn paper_settings(mode: Mode) -> Settings {
        let n = 8;
        let thresholds: Vec<f64> = (0..n).map(|i| i as f64 * 140.0 / n as f64).collect();
        // Total slope ≈ 0.4 µm/V, the first operator carrying most of it.
        let weights: Vec<f64> = (0..n)
            .map(|i| if i == 0 { 0.25 } else { 0.15 / (n - 1) as f64 })
            .collect();
        let model = pi_model(0.0, -28.0, &thresholds, &weights)
            .expect("8 increasing thresholds and positive weights form a model");
        let mut drive = twinstack::drive::DriveSettings::DEFAULT;
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
            feedback: Some(FeedbackSettings::pi(0.2, 500.0, 0.1)),
            mode,
            creep: None,
        }
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
}

impl std::fmt::Display for SimDeviceError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Board(e) => write!(f, "simulated board: {e}"),
            Self::Stored => write!(f, "the stored settings do not fit a flash record"),
            Self::Defaults(r) => write!(f, "compiled-in settings refused: {r}"),
            Self::Baud => write!(f, "baud rate must be positive"),
        }
    }
}

impl std::error::Error for SimDeviceError {}

/// The simulated board's hardware facts at `rate_hz`: the driver board's 150 V amplifier, 12-bit
/// DAC and 12-bit sensor ADC.
pub fn hardware(rate_hz: f64) -> Hardware {
    Hardware::driver_board(rate_hz)
}

/// The board in-process: [`SimBoard`] + the library's [`ControlLoop`] and
/// [`CommandHandler`], on a modelled UART. See the module doc for the time model.
pub struct SimDevice {
    board: InternalBoard,
    control: ControlLoop<Vec<i16>, Box<Controller>>,
    handler: CommandHandler<RamStorage>,
    queue: Box<SetpointQueue>,
    /// Simulated time, ns.
    now_ns: u64,
    tick_ns: u64,
    byte_ns: u64,
    ticks: u64,
    /// Host → board bytes and their arrival times (ns).
    rx: VecDeque<(u64, u8)>,
    rx_line_free_ns: u64,
    /// Board → host bytes and their arrival times (ns).
    tx: VecDeque<(u64, u8)>,
    tx_line_free_ns: u64,
    last_report: Option<TickReport>,
}

impl SimDevice {
    /// Builds the device at simulated time 0.
    pub fn new(config: SimDeviceConfig) -> Result<Self, SimDeviceError> {
        if config.baud == 0 {
            return Err(SimDeviceError::Baud);
        }
        let board = SimBoard::internal(&config.board).map_err(SimDeviceError::Board)?;
        // The control rate is a whole number of hertz, as the firmware's timer runs it (and
        // as the status report and the stored record carry it); `1 / dt` is not exactly one.
        let rate_hz = (1.0 / board.plant().dt()).round();
        let hw = hardware(rate_hz);
        // The "flash": erased, or holding the stored settings at this rate; the board boots
        // from it exactly as the firmware does.
        let mut storage = RamStorage::default();
        if let Some(settings) = config.stored {
            let record = StoredRecord {
                control_rate_hz: rate_hz.round() as u32,
                settings,
            };
            let mut bytes = [0u8; MAX_RECORD];
            let n = record
                .encode(&mut bytes)
                .map_err(|_| SimDeviceError::Stored)?;
            storage
                .write(&bytes[..n])
                .map_err(|_| SimDeviceError::Stored)?;
        }
        let (record, source) = param_store::load_record(storage.read(), &hw);
        let (settings, boot, defaults) =
            param_store::boot(record, source, &hw).map_err(SimDeviceError::Defaults)?;
        let control = ControlLoop::new(
            Box::new(Controller::new(boot)),
            Box::new(Controller::new(boot)),
            rate_hz.round() as u32,
            vec![0; CAPTURE_SLOTS],
        );
        let handler = CommandHandler::new(hw, settings, defaults, storage);
        Ok(Self {
            board,
            control,
            handler,
            queue: Box::new(SetpointQueue::new()),
            now_ns: 0,
            tick_ns: (board_dt_ns(rate_hz)).max(1),
            byte_ns: (10_000_000_000 / config.baud as u64).max(1),
            ticks: 0,
            rx: VecDeque::new(),
            rx_line_free_ns: 0,
            tx: VecDeque::new(),
            tx_line_free_ns: 0,
            last_report: None,
        })
    }

    /// Runs simulated time forward by `duration` (ticks, received bytes, responses), without
    /// reading the responses (they wait for [`Transport::receive`]).
    pub fn run_for(&mut self, duration: Duration) {
        let end = self.now_ns.saturating_add(duration.as_nanos() as u64);
        while self.now_ns + self.tick_ns <= end {
            self.step();
        }
    }

    /// One tick period: feed the bytes that have arrived to the handler, then tick.
    fn step(&mut self) {
        self.now_ns += self.tick_ns;
        let (mut producer, _) = self.queue.split();
        while let Some(&(at, byte)) = self.rx.front() {
            if at > self.now_ns {
                break;
            }
            self.rx.pop_front();
            let mut control = Exclusive(&mut self.control);
            if let Some(frame) = self.handler.push_byte(byte, &mut producer, &mut control) {
                let start = self.tx_line_free_ns.max(at);
                for (i, &b) in frame.iter().enumerate() {
                    self.tx
                        .push_back((start + (i as u64 + 1) * self.byte_ns, b));
                }
                self.tx_line_free_ns = start + frame.len() as u64 * self.byte_ns;
            }
        }
        // The learning's work at period boundaries, in the same low-priority context.
        self.handler
            .service_learning(&mut Exclusive(&mut self.control));
        let (_, mut consumer) = self.queue.split();
        let (mut dac, mut adc) = self.board.split();
        self.last_report = Some(self.control.tick(&mut consumer, &mut adc, &mut dac));
        self.ticks += 1;
    }

    /// Simulated time since the device was built.
    pub fn now(&self) -> Duration {
        Duration::from_nanos(self.now_ns)
    }

    /// Ticks run.
    pub fn ticks(&self) -> u64 {
        self.ticks
    }

    /// The simulated board (stage displacement, amplifier outputs, …).
    pub fn board(&self) -> &InternalBoard {
        &self.board
    }

    /// The tick side (controller, counters, recorder).
    pub fn control(&self) -> &ControlLoop<Vec<i16>, Box<Controller>> {
        &self.control
    }

    /// The command handler (settings in force, sequence number, storage).
    pub fn handler(&self) -> &CommandHandler<RamStorage> {
        &self.handler
    }

    /// What the last tick did.
    pub fn last_report(&self) -> Option<TickReport> {
        self.last_report
    }

    /// Bytes sent but not yet arrived at the board (the host → board line's backlog).
    pub fn bytes_in_flight(&self) -> usize {
        self.rx.len()
    }
}

fn board_dt_ns(rate_hz: f64) -> u64 {
    (1e9 / rate_hz).round() as u64
}

impl Transport for SimDevice {
    /// Queues `bytes` on the host → board line (returns at once; simulated time does not move).
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        let mut t = self.rx_line_free_ns.max(self.now_ns);
        for &b in bytes {
            t += self.byte_ns;
            self.rx.push_back((t, b));
        }
        self.rx_line_free_ns = t;
        Ok(())
    }

    /// Advances simulated time until response bytes have arrived (or `timeout` of simulated
    /// time has passed: `Ok(0)`), then returns those that have arrived, up to `buf.len()`.
    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        if buf.is_empty() {
            return Ok(0);
        }
        let end = self.now_ns.saturating_add(timeout.as_nanos() as u64);
        loop {
            let arrived = self.tx.front().is_some_and(|&(at, _)| at <= self.now_ns);
            if arrived {
                let mut n = 0;
                while n < buf.len() {
                    match self.tx.front() {
                        Some(&(at, b)) if at <= self.now_ns => {
                            buf[n] = b;
                            n += 1;
                            self.tx.pop_front();
                        }
                        _ => break,
                    }
                }
                return Ok(n);
            }
            if self.now_ns + self.tick_ns > end {
                return Ok(0);
            }
            self.step();
        }
    }
}
