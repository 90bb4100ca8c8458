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
use twinstack::control::TickReport;
use twinstack::control_loop::{ControlLoop, SetpointQueue};
use twinstack::drive::{Configuration as DriveConfiguration, SafeState};
use twinstack::param_store::{BoardSettings, RamStorage};
use twinstack::protocol::handler::CommandHandler;
use twinstack::protocol::messages::{ModelParams, NackReason, ParamSet};
use twinstack::protocol::param_load::BoardProfile;
use twinstack::recorder::RECORD_CAPACITY;
use twinstack::settings::{Mode, SensorSettings};

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
    /// The parameter set the device boots on (the "flash" starts erased).
    pub params: ParamSet,
    /// Safe state written into a stored record.
    pub safe_state: SafeState,
}

impl SimDeviceConfig {
    /// The paper's differential stage on the STM32's internal converters (12-bit DAC, 12-bit
    /// sensor ADC spanning ±45 µm), 50 kHz, 2 Mbaud, booting in bypass on
    /// [`SimDeviceConfig::paper_params`].
    pub fn paper() -> Self {
        Self {
            board: BoardConfig::paper(Configuration::Differential),
            baud: 2_000_000,
            params: Self::paper_params(Mode::Bypass),
            safe_state: SafeState::Bias,
        }
    }

    /// A parameter set for the paper's differential stage in `mode`: 0…140 V on the left stack
    /// onto the sensor's ±45 µm, bias 70 V, 0…140 V limits, 0.9 V/µs slew, a representative
    /// 8-operator P–I model (not identified: load the identification's set for accuracy),
    /// PI gains kp 0.2, ki 0.01 per tick, correction within a tenth of the drive range.
    pub fn paper_params(mode: Mode) -> ParamSet {
        let n = 8usize;
        let thresholds = (0..n).map(|i| i as f32 * 140.0 / n as f32).collect();
        // Total slope ≈ 0.4 µm/V, the first operator carrying most of it.
        let weights = (0..n)
            .map(|i| if i == 0 { 0.25 } else { 0.15 / (n - 1) as f32 })
            .collect();
        ParamSet {
            model: ModelParams::PrandtlIshlinskii {
                a0: 0.0,
                offset: -28.0,
                thresholds,
                weights,
            },
            input_range: [0.0, 140.0],
            output_range: [-45.0, 45.0],
            configuration: DriveConfiguration::Differential,
            bias: 70.0,
            voltage_limits: [0.0, 140.0],
            slew_rate: 0.9e6,
            safe_state: SafeState::Bias,
            feedback: Some(twinstack::protocol::messages::FeedbackParams {
                kp: 0.2,
                ki: 500.0,
                kd: 0.0,
                derivative_cutoff_hz: 1.0,
                limit: 0.1,
                notch: None,
                drift_limit: None,
            }),
            mode,
        }
    }
}

/// Why a simulated device could not be built.
#[derive(Debug)]
pub enum SimDeviceError {
    /// The board.
    Board(BoardError),
    /// The boot parameter set was refused (the reason a load would get).
    Params(NackReason),
    /// Baud rate zero.
    Baud,
}

impl std::fmt::Display for SimDeviceError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Board(e) => write!(f, "simulated board: {e}"),
            Self::Params(r) => write!(f, "boot parameters refused: {r:?}"),
            Self::Baud => write!(f, "baud rate must be positive"),
        }
    }
}

impl std::error::Error for SimDeviceError {}

/// The board in-process: [`SimBoard`] + the library's [`ControlLoop`] and
/// [`CommandHandler`], on a modelled UART. See the module doc for the time model.
pub struct SimDevice {
    board: InternalBoard,
    control: ControlLoop<Vec<i32>>,
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
        let rate_hz = 1.0 / board.plant().dt();
        let (lo, hi) = config.board.sensor_range_um;
        let profile = BoardProfile {
            amplifier_full_scale: 150.0,
            dac_full_scale: 4095,
            control_rate_hz: rate_hz,
            sensor: Some(SensorSettings {
                adc_bits: 12,
                displacement_at_zero: lo,
                displacement_at_full_scale: hi,
            }),
        };
        let board_settings = BoardSettings {
            tick_rate_hz: rate_hz.round() as u32,
            safe_state: config.safe_state,
        };
        let (handler, tick_config) = CommandHandler::boot(
            profile,
            board_settings,
            RamStorage::default(),
            config.params,
        )
        .map_err(SimDeviceError::Params)?;
        let control = ControlLoop::new(
            tick_config,
            board_settings.tick_rate_hz,
            vec![0; RECORD_CAPACITY],
        );
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
    pub fn control(&self) -> &ControlLoop<Vec<i32>> {
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
