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
//! **Telemetry** runs as on the board: after each tick the control loop's tap puts the
//! selected signals on the telemetry queue, and the sending side hands the command
//! handler's packed frames to the board → host line whenever one of the board's two
//! transmit buffers is free (a frame occupies a buffer until its last byte has left: one on
//! the line, one waiting, as the firmware's double-buffered DMA). Responses go first, in the
//! same line. [`SimDevice::line`] counts the bytes each way, so a test can check telemetry
//! and a 50 k/s setpoint stream against the line's byte budget.
//!
//! ```
//! use std::time::Duration;
//! use twinstack_link::Transport;
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

use twinstack::board::{Hardware, WATCHDOG_TIMEOUT_MS};
use twinstack::command_handler::{start_services, CommandHandler, Parts};
use twinstack::config::param_store::{
    self, RamStorage, RecordStorage, StorageError, StoredRecord, MAX_RECORD,
};
use twinstack::config::settings::{pi_model, FeedbackSettings, Mode, SensorSettings, Settings};
use twinstack::control::{Controller, TickReport};
use twinstack::control_loop::{ControlLoop, SetpointQueue};
use twinstack::dual_stage::{CoarseLimits, CoarseStatus};
use twinstack::protocol::messages::{Request, Response};
use twinstack::refusal::Refusal;
use twinstack::services::consumer::Services;

use twinstack::services::recorder::CAPTURE_SLOTS;
use twinstack::services::snapshot::SnapshotRing;
use twinstack::services::telemetry::TelemetryQueue;
use twinstack::sources::analog_input::AnalogInputConfig;
use twinstack::sources::sequence::SETTLED;
use twinstack::Scaling;

use crate::converters::{AnalogDualDac, AnalogSensorAdc, InternalAdc, InternalDac};
use crate::plant::Configuration;
use crate::sim_board::{BoardConfig, BoardError, SimBoard};
use crate::sim_camera::{CameraConfig, SimCamera};
use twinstack_link::Transport;

mod config;
mod line;

pub use config::{hardware, LinkDelay, SimDeviceConfig, SimDeviceError};
use line::{Delays, LinkErrors, TxLine};
pub use line::{LineCounters, MAX_BACKLOG};

/// A coarse axis run between the ticks, as the firmware's coarse task runs between them (the
/// dual-stage board's, [`crate::coarse_rig::CoarseRig`]). The device holds it by this trait,
/// so that the rig, which builds devices, sits above this module.
pub trait CoarseAxisSim: std::any::Any + Send {
    /// The axis's travel limits, attached to the control loop at boot.
    fn limits(&self) -> CoarseLimits;
    /// The axis's status now.
    fn status(&self) -> CoarseStatus;
    /// Runs before a control tick (the coarse tick and its exchange with the loop).
    fn before_tick(&mut self, control: &mut ControlLoop<Box<Controller>>);
    /// Runs after a control tick: `piezo_um` the piezo's displacement now, `report` the tick's.
    fn after_tick(&mut self, piezo_um: f64, report: &TickReport);
    /// The axis as [`std::any::Any`], to reach its own type.
    fn as_any(&self) -> &dyn std::any::Any;
    /// The axis as [`std::any::Any`], mutably.
    fn as_any_mut(&mut self) -> &mut dyn std::any::Any;
}

/// The board in-process: [`SimBoard`] + the library's [`ControlLoop`] and
/// [`CommandHandler`], on a modelled UART. See the module doc for the time model.
///
/// The converters are the STM32's by default ([`SimDevice::new`]); the dual-stage board
/// ([`SimDevice::dual_stage`], [`crate::coarse_rig`]) has the external SPI converters and a
/// coarse axis on a simulated ball screw.
pub struct SimDevice<D = InternalDac, A = InternalAdc> {
    board: SimBoard<D, A>,
    /// The coarse axis (dual-stage board), run between the ticks as the firmware's coarse
    /// task runs between them.
    coarse: Option<Box<dyn CoarseAxisSim>>,
    control: ControlLoop<Box<Controller>>,
    /// The services below the tick (the recorder, telemetry's tap, the observer where there is
    /// a sensor), served when the tick says a batch is due, as the firmware's services task
    /// is.
    services: Services<Vec<i16>>,
    handler: CommandHandler<SimFlash>,
    queue: Box<SetpointQueue>,
    snapshots: Box<SnapshotRing>,
    telemetry: Box<TelemetryQueue>,
    /// Simulated time, ns.
    now_ns: u64,
    tick_ns: u64,
    byte_ns: u64,
    ticks: u64,
    /// Host → board bytes and their arrival times (ns).
    rx: VecDeque<(u64, u8)>,
    rx_line_free_ns: u64,
    /// The adapter's delays on the host → board way.
    rx_delays: Delays,
    /// Board → host bytes and their arrival times (ns).
    tx: TxLine,
    last_report: Option<TickReport>,
    /// The external trigger input's level (protocol v6 trigger I/O).
    trigger_input: bool,
    /// A simulated camera driving the trigger input (its TTL output ORed onto it).
    camera: Option<SimCamera>,
    /// The link's byte corruption, both ways.
    errors: LinkErrors,
    /// The watchdog is armed (the firmware starts it at boot).
    watchdog: bool,
    /// How long the tick has not fed the watchdog, ns.
    starved_ns: u64,
}

/// The simulated board's "flash": [`RamStorage`], whose writes can be made to fail
/// ([`SimDeviceConfig::failing_flash`]).
#[derive(Clone, Debug, Default)]
pub struct SimFlash {
    ram: RamStorage,
    /// Every write fails, leaving the sector erased (the erase went through, the programming
    /// did not).
    pub fail_writes: bool,
}

impl RecordStorage for SimFlash {
    fn read(&self) -> &[u8] {
        self.ram.read()
    }

    fn write(&mut self, record: &[u8]) -> Result<(), StorageError> {
        if self.fail_writes {
            self.ram = RamStorage::default();
            return Err(StorageError::WriteFailed);
        }
        self.ram.write(record)
    }
}

impl SimDevice {
    /// Builds the device at simulated time 0.
    pub fn new(config: SimDeviceConfig) -> Result<Self, SimDeviceError> {
        if config.baud == 0 {
            return Err(SimDeviceError::Baud);
        }
        if !(config.link_error_rate.is_finite() && (0.0..=1.0).contains(&config.link_error_rate)) {
            return Err(SimDeviceError::ErrorRate(config.link_error_rate));
        }
        let mut board = SimBoard::internal(&config.board).map_err(SimDeviceError::Board)?;
        board.set_loopback(config.loopback);
        board
            .set_sensor_latency(config.sensor_latency)
            .map_err(SimDeviceError::Board)?;
        // The control rate is a whole number of hertz, as the firmware's timer runs it (and
        // as the status report and the stored record carry it); `1 / dt` is not exactly one.
        let rate_hz = (1.0 / board.plant().dt()).round();
        let mut device = SimDevice::build(
            board,
            hardware(rate_hz),
            config.stored.map(|s| (s, config.stored_analog)),
            config.baud,
            config.link,
            None,
        )?;
        device.set_camera(config.camera);
        device.handler.storage_mut().fail_writes = config.failing_flash;
        device.set_watchdog(config.watchdog);
        device.set_analog_input(config.analog_input);
        device.set_link_errors(config.link_error_rate);
        Ok(device)
    }
}

impl<D: AnalogDualDac, A: AnalogSensorAdc> SimDevice<D, A> {
    /// A device on `board` (its hardware facts `hw`), booting from `stored` as the firmware
    /// boots from flash, with an optional coarse axis.
    pub(crate) fn build(
        board: SimBoard<D, A>,
        hw: Hardware,
        stored: Option<(Settings, Option<AnalogInputConfig>)>,
        baud: u32,
        link: LinkDelay,
        coarse: Option<Box<dyn CoarseAxisSim>>,
    ) -> Result<Self, SimDeviceError> {
        if baud == 0 {
            return Err(SimDeviceError::Baud);
        }
        if link.jitter > link.latency {
            return Err(SimDeviceError::Jitter {
                latency: link.latency,
                jitter: link.jitter,
            });
        }
        let rate_hz = hw.control_rate_hz;
        // The "flash": erased, or holding the stored settings at this rate; the board boots
        // from it exactly as the firmware does.
        let mut storage = SimFlash::default();
        if let Some((settings, analog)) = stored {
            let record = StoredRecord {
                control_rate_hz: rate_hz.round() as u32,
                settings,
                analog,
            };
            let mut bytes = [0u8; MAX_RECORD];
            let n = record
                .encode(&mut bytes)
                .map_err(|_| SimDeviceError::Stored)?;
            storage
                .write(&bytes[..n])
                .map_err(|_| SimDeviceError::Stored)?;
        }
        let (control, services, handler) = boot(storage, hw, coarse.as_deref())?;
        Ok(Self {
            board,
            coarse,
            control,
            services,
            handler,
            queue: Box::new(SetpointQueue::new()),
            snapshots: Box::new(SnapshotRing::new()),
            telemetry: Box::new(TelemetryQueue::new()),
            now_ns: 0,
            tick_ns: (board_dt_ns(rate_hz)).max(1),
            byte_ns: (10_000_000_000 / baud as u64).max(1),
            ticks: 0,
            rx: VecDeque::new(),
            rx_line_free_ns: 0,
            rx_delays: Delays::new(link),
            tx: TxLine {
                bytes: VecDeque::new(),
                free_ns: 0,
                delivered_ns: 0,
                // Another stream of jitter than the other way's.
                delays: Delays::new(LinkDelay {
                    seed: link.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1,
                    ..link
                }),
                frame_ends: VecDeque::new(),
                byte_ns: (10_000_000_000 / baud as u64).max(1),
                counters: LineCounters::default(),
            },
            last_report: None,
            trigger_input: false,
            camera: None,
            errors: LinkErrors::new(0.0, link.seed),
            watchdog: true,
            starved_ns: 0,
        })
    }

    /// With its watchdog running (`true`, as built) or without (`false`: a drill or a hang
    /// never resets it, as a board whose watchdog was not started).
    pub fn set_watchdog(&mut self, armed: bool) {
        self.watchdog = armed;
    }

    /// The watchdog's reset: the board starts again from its flash as at power-up (the
    /// stored settings, or the defaults), its queues empty and its counters at zero, and
    /// reports the watchdog as the cause. The stage, the converters and the bytes already on
    /// the line are physical and stay.
    fn reset_by_watchdog(&mut self) {
        let storage = self.handler.storage().clone();
        let hw = *self.handler.hardware();
        match boot(storage, hw, self.coarse.as_deref()) {
            Ok((control, services, mut handler)) => {
                handler.set_watchdog_reset(true);
                self.control = control;
                self.services = services;
                self.handler = handler;
            }
            // The flash booted once and the defaults always build: unreachable, but a
            // board that cannot boot stays as it is rather than panicking.
            Err(_) => return,
        }
        *self.queue = SetpointQueue::new();
        *self.snapshots = SnapshotRing::new();
        *self.telemetry = TelemetryQueue::new();
        self.starved_ns = 0;
        self.last_report = None;
    }

    /// Runs simulated time forward by `duration` (ticks, received bytes, responses), without
    /// reading the responses (they wait for [`Transport::receive`]).
    pub fn run_for(&mut self, duration: Duration) {
        let end = self.now_ns.saturating_add(duration.as_nanos() as u64);
        while self.now_ns + self.tick_ns <= end {
            self.step();
        }
    }

    /// One tick period (see [`SimDevice::run_for`]): what a test steps tick by tick.
    pub fn tick(&mut self) {
        self.step();
    }

    /// Hands `request` to the command handler between two ticks, as the decoder task does
    /// with a frame that arrived, bypassing the modelled UART: for tests that must know the
    /// exact tick a command takes effect before.
    pub fn handle(&mut self, request: &Request) -> Response {
        let (mut producer, _) = self.queue.split();
        self.handler.handle(
            request.clone(),
            &mut producer,
            &mut Parts::new(
                &mut self.control,
                &mut self.services,
                &mut self.snapshots,
                &mut self.telemetry,
            ),
        )
    }

    /// One tick period: feed the bytes that have arrived to the handler, then tick, then
    /// hand due telemetry frames to the line while a transmit buffer is free.
    fn step(&mut self) {
        self.now_ns += self.tick_ns;
        let (mut producer, _) = self.queue.split();
        while let Some(&(at, byte)) = self.rx.front() {
            if at > self.now_ns {
                break;
            }
            self.rx.pop_front();
            let mut control = Parts::new(
                &mut self.control,
                &mut self.services,
                &mut self.snapshots,
                &mut self.telemetry,
            );
            if let Some(frame) = self.handler.push_byte(byte, &mut producer, &mut control) {
                self.tx.transmit(frame, at);
            }
        }
        if let Some(rig) = self.coarse.as_mut() {
            rig.before_tick(&mut self.control);
        }
        // The learning's work at period boundaries, in the same low-priority context.
        self.handler.service_learning(&mut Parts::new(
            &mut self.control,
            &mut self.services,
            &mut self.snapshots,
            &mut self.telemetry,
        ));
        let (_, mut consumer) = self.queue.split();
        let (mut dac, mut adc) = self.board.split();
        let camera = match self.camera.as_mut() {
            Some(c) => {
                // Started by the acquisition program once the stage is ready for it: a
                // sequence armed, or a scan or the stream waiting for the input's edge.
                let armed =
                    self.control.sequence_status().armed || self.control.waits_for_trigger();
                c.step(armed, self.control.trigger_levels() & SETTLED != 0)
            }
            None => false,
        };
        self.control.set_trigger_input(self.trigger_input | camera);
        let (mut snapshots_in, mut snapshots_out) = self.snapshots.split();
        let report = self
            .control
            .tick(&mut consumer, &mut snapshots_in, &mut adc, &mut dac);
        let (mut samples_in, mut samples_out) = self.telemetry.split();
        // The services' task, woken once a batch of snapshots (the firmware's EXTI2).
        if self.control.services_due() {
            self.services.consume(&mut snapshots_out, &mut samples_in);
        }
        if let Some(rig) = self.coarse.as_mut() {
            rig.after_tick(self.board.plant().stage_um(), &report);
        }
        self.last_report = Some(report);
        self.ticks += 1;
        // The watchdog (the tick feeds it unless a drill stopped it).
        if self.control.feeds_watchdog() {
            self.starved_ns = 0;
        } else {
            self.starved_ns += self.tick_ns;
            if self.watchdog && self.starved_ns >= u64::from(WATCHDOG_TIMEOUT_MS) * 1_000_000 {
                self.reset_by_watchdog();
                return;
            }
        }
        // The sending side, after the tick (the firmware's command task, woken between ticks).
        while self.handler.telemetry_due(&samples_out) && self.tx.buffer_free(self.now_ns) {
            let Some(frame) = self.handler.pack_telemetry(&mut samples_out) else {
                break;
            };
            self.tx.counters.telemetry_bytes_out += frame.len() as u64;
            self.tx.counters.telemetry_frames += 1;
            self.tx.transmit(frame, self.now_ns);
        }
    }

    /// Drives the board's external trigger input (PA6 on the board) to `level` from the next
    /// tick on: what a lab's camera or function generator does to the pin.
    pub fn set_trigger_input(&mut self, level: bool) {
        self.trigger_input = level;
    }

    /// Drives the board's analog setpoint input's pin with `source` from the next tick on
    /// ([`crate::analog_source`]): what a lab's controller or function generator does to it.
    pub fn set_analog_input(&mut self, source: crate::analog_source::AnalogSource) {
        self.board
            .set_setpoint_input(crate::analog_source::SetpointInput::new(source));
    }

    /// Puts a simulated camera on the trigger input (its TTL output ORed with the level
    /// [`SimDevice::set_trigger_input`] sets), or takes it off.
    pub fn set_camera(&mut self, camera: Option<CameraConfig>) {
        self.camera = camera.map(SimCamera::new);
    }

    /// The simulated camera, if there is one.
    pub fn camera(&self) -> Option<&SimCamera> {
        self.camera.as_ref()
    }

    /// Corrupts `rate` of the bytes on the link from now on, each way (0: a sound link);
    /// clamped to 0…1.
    pub fn set_link_errors(&mut self, rate: f64) {
        self.errors = LinkErrors::new(rate, self.errors.state);
    }

    /// Bytes the modelled UART carried each way so far.
    pub fn line(&self) -> LineCounters {
        self.tx.counters
    }

    /// The coarse axis (dual-stage board; its own type: [`SimDevice::coarse_rig`]).
    pub fn coarse_axis(&self) -> Option<&dyn CoarseAxisSim> {
        self.coarse.as_deref()
    }

    /// The coarse axis, mutably.
    pub fn coarse_axis_mut(&mut self) -> Option<&mut dyn CoarseAxisSim> {
        self.coarse.as_deref_mut()
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
    pub fn board(&self) -> &SimBoard<D, A> {
        &self.board
    }

    /// The tick side (controller, counters, sources).
    pub fn control(&self) -> &ControlLoop<Box<Controller>> {
        &self.control
    }

    /// The services below the tick (recorder, telemetry's tap), as the last batch left them.
    pub fn services(&self) -> &Services<Vec<i16>> {
        &self.services
    }

    /// The command handler (settings in force, sequence number, storage).
    pub fn handler(&self) -> &CommandHandler<SimFlash> {
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

    /// A client hung up and another is connecting: the adapter's buffers are emptied both
    /// ways, as when a serial port is closed and opened again. What the earlier client sent
    /// and the board has not received is dropped, and so is everything the board sent that
    /// has not been read, arrived or still on its way (a late answer to the earlier client's
    /// last request would otherwise be taken for the answer to the new client's first).
    /// Returns the bytes dropped, host → board and board → host.
    pub fn hang_up(&mut self) -> (usize, usize) {
        let dropped = (self.rx.len(), self.tx.bytes.len());
        self.rx.clear();
        self.tx.bytes.clear();
        // The line is free now: the dropped bytes' time on it is not the next client's wait
        // (after a flood of 3 MB the next client's requests were scheduled 9 s and more on).
        self.rx_line_free_ns = self.now_ns;
        self.tx.delivered_ns = self.tx.delivered_ns.min(self.now_ns);
        dropped
    }
}

/// The board's boot from its flash, as the firmware's `init`: the stored settings if they
/// hold at the board's rate (else the defaults), the two controllers, the control loop (with
/// the coarse axis attached), the services (with the observer below the tick, where the
/// settings have a sensor), the command handler, and the stored analog input started before
/// the first tick.
#[allow(clippy::type_complexity)]
fn boot(
    storage: SimFlash,
    hw: Hardware,
    coarse: Option<&dyn CoarseAxisSim>,
) -> Result<
    (
        ControlLoop<Box<Controller>>,
        Services<Vec<i16>>,
        CommandHandler<SimFlash>,
    ),
    SimDeviceError,
> {
    let (record, source) = param_store::load_record(storage.read(), &hw);
    let stored_analog = record.analog;
    let (settings, boot, defaults) =
        param_store::boot(record, source, &hw).map_err(SimDeviceError::Defaults)?;
    let mut control = ControlLoop::new(
        Box::new(Controller::new(boot)),
        Box::new(Controller::new(boot)),
        hw.control_rate_hz.round() as u32,
    );
    // As the firmware: the coarse axis attached only if the configuration in force leaves its
    // task its share of each tick.
    if let Some(rig) = coarse {
        let task = twinstack::dual_stage::PreparedCoarse::new(
            rig.limits(),
            rig.status(),
            control.control_rate_hz(),
        );
        let beside = twinstack::config::tick_budget::Beside {
            source: twinstack::sources::SetpointSource::Coarse,
            coarse_task: task.share(),
            ..Default::default()
        };
        if twinstack::config::tick_budget::check_with(&boot, hw.control_rate_hz, beside).is_ok() {
            control.attach_coarse(&task);
        }
    }
    let mut services = Services::new(vec![0; CAPTURE_SLOTS]);
    start_services(&boot, &mut control, &mut services);
    let mut handler = CommandHandler::new(hw, settings, defaults, storage);
    if !defaults {
        if let Some(prepared) = handler.boot_analog(stored_analog, &boot) {
            control.start_analog(prepared);
        }
    }
    Ok((control, services, handler))
}

fn board_dt_ns(rate_hz: f64) -> u64 {
    (1e9 / rate_hz).round() as u64
}

/// A triangle over 95 % of the setpoint range, `n` setpoints of `period` each cycle (from the
/// bottom): a stream whose samples mostly need three bytes as varints and two packed, what
/// the link measurements send.
pub fn full_range_triangle(n: usize, period: usize) -> Vec<i16> {
    let period = period.max(1);
    (0..n)
        .map(|i| {
            let phase = (i % period) as f64 / period as f64;
            let x = if phase < 0.5 {
                4.0 * phase - 1.0
            } else {
                3.0 - 4.0 * phase
            };
            (0.95 * x * 32767.0).round() as i16
        })
        .collect()
}
