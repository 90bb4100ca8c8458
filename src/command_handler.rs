//! The board's command handler: received bytes in, one response frame out per request.
//!
//! It runs in the low-priority task (the firmware's decoder task; the simulator's receive
//! path) and owns everything that is not the tick's: the frame decoder, the settings in force
//! (physical units), the hardware facts, the parameter storage, the batch sequence number and
//! the frame-error counters. It reaches the tick side ([`ControlLoop`]) in two ways only:
//!
//! * setpoint batches go into the lock-free setpoint queue (`heapless::spsc` producer); the
//!   credits in every `Ack` are that queue's free slots;
//! * everything else is one short critical section through [`Locks`] (RTIC's resource locks
//!   on the board, plain borrows on the host, [`Parts`]): on the control loop a few stores or
//!   moving a pointer; on the services (the recorder, telemetry's tap) a chunk's piece copied,
//!   under a lock that never masks the tick.
//!
//! A load is validated whole ([`Settings::build`]) and *prepared* here, outside any lock, in the
//! spare controller ([`ControlLoop::spare`], [`Controller::prepare`]: models relaxed at the
//! stacks' present voltages); the tick swaps it in, in O(1). A mode switch is O(1) in the tick
//! itself ([`Controller::set_mode`]). Rules (see the book's protocol chapter): every request
//! gets exactly one response; a refused request changes nothing and loses nothing already
//! queued, and its NACK names the field and the rule it broke.

use core::ops::DerefMut;

use heapless::spsc::{Producer, Queue};

use crate::board::Hardware;
use crate::config::param_store::{RecordStorage, StorageError, StoredRecord, MAX_RECORD};
use crate::config::settings::{Mode, Settings};
use crate::config::tick_budget::ServicesLoad;
use crate::control::{ControlConfig, Controller};
use crate::control_loop::ControlLoop;
use crate::dual_stage::{CoarseCommand, CoarseLimits, CoarseRefusal, CoarseStatus};
use crate::refusal::{Field, Refusal, Rule};
use crate::services::consumer::Services;
use crate::services::learning::{self, LearnState, LearnTask, Service};
use crate::services::observer::ObserverBelow;
use crate::services::recorder::{in_pieces, RecordError, SampleStore};
use crate::services::snapshot::{SnapshotConsumer, SnapshotRing};
use crate::services::telemetry::{self, TelemetryPacker, TelemetrySample};
use crate::sources::analog_input::{AnalogInputConfig, AnalogRequest, AnalogStatus, PreparedInput};
use crate::sources::scan::{ScanGenerator, ScanRequest, TriggerConfig};
use crate::sources::sequence::{SequenceRequest, SequenceStatus};
use crate::sources::setpoint_stream::setpoint_from_wire;
use crate::sources::waveform::{Shape, WaveformError, WaveformGenerator};
use crate::sources::SetpointSource;

use crate::protocol::decoder::FrameDecoder;
use crate::protocol::frame::{self, FrameError, MAX_ENCODED};
use crate::protocol::messages::{
    CaptureRequest, CaptureStatus, Image, LearnRequest, LearnStatus, NackReason, RecordRequest,
    Request, Response, SetpointBatch, StatusReport, StreamControl, TelemetryRequest, WaveShape,
    Waveform,
};
use heapless::spsc::Consumer;

/// How the command handler reaches the board's two halves, each behind its own lock.
///
/// * The control loop ([`ControlLoop`], the tick's resource): its lock masks the tick, so it
///   is held for a few stores, a pointer swap or one short copy.
/// * The services ([`Services`]: the recorder and telemetry's tap, the snapshot consumer's
///   resource): their lock masks only the consumer, never the tick. Taking it first serves
///   every snapshot the tick has pushed, so what the handler reads or arms is up to date with
///   the ticks before it.
///
/// On the board both are RTIC resources (`hardware::tick::BoardLocks`); on the host
/// plain borrows ([`Parts`]).
pub trait Locks {
    /// The loop's handle on a controller.
    type Controller: DerefMut<Target = Controller>;
    /// The recorder's buffer.
    type Store: SampleStore;
    /// Runs `f` on the control loop, the tick kept out.
    fn lock<R>(&mut self, f: impl FnOnce(&mut ControlLoop<Self::Controller>) -> R) -> R;
    /// Runs `f` on the services, the snapshot ring served first, the consumer kept out.
    fn lock_services<R>(&mut self, f: impl FnOnce(&mut Services<Self::Store>) -> R) -> R;
    /// Runs `f` on the services as they stand, the ring left to the consumer (up to a batch
    /// behind the tick): for what a few ticks' lag does not change — the status's counts,
    /// what runs — so that a host polling the status does not serve the ring in the command
    /// task a tick at a time.
    fn peek_services<R>(&mut self, f: impl FnOnce(&Services<Self::Store>) -> R) -> R;
}

/// The board's two halves on the host (the simulator, tests): plain borrows of the loop and
/// the services, and the queues' ends the services use. Taking the services serves the
/// snapshot ring first, as the board's lock does.
pub struct Parts<'a, C, B, const T: usize> {
    /// The control loop.
    pub control: &'a mut ControlLoop<C>,
    /// The services.
    pub services: &'a mut Services<B>,
    /// The snapshot ring's consumer end.
    pub snapshots: SnapshotConsumer<'a>,
    /// The telemetry queue's producer end.
    pub telemetry: Producer<'a, TelemetrySample, T>,
}

impl<'a, C, B, const T: usize> Parts<'a, C, B, T> {
    /// The halves over `control` and `services`, with the consumer end of `snapshots` and the
    /// producer end of `telemetry`.
    pub fn new(
        control: &'a mut ControlLoop<C>,
        services: &'a mut Services<B>,
        snapshots: &'a mut SnapshotRing,
        telemetry: &'a mut Queue<TelemetrySample, T>,
    ) -> Self {
        Self {
            control,
            services,
            snapshots: snapshots.split().1,
            telemetry: telemetry.split().0,
        }
    }
}

impl<C, B, const T: usize> Locks for Parts<'_, C, B, T>
where
    C: DerefMut<Target = Controller>,
    B: SampleStore,
{
    type Controller = C;
    type Store = B;

    fn lock<R>(&mut self, f: impl FnOnce(&mut ControlLoop<C>) -> R) -> R {
        f(self.control)
    }

    fn lock_services<R>(&mut self, f: impl FnOnce(&mut Services<B>) -> R) -> R {
        self.services
            .consume(&mut self.snapshots, &mut self.telemetry);
        f(self.services)
    }

    fn peek_services<R>(&mut self, f: impl FnOnce(&Services<B>) -> R) -> R {
        f(self.services)
    }
}

/// The control loop's lock alone, as an [`rtic_core::Mutex`] (what the learning's service
/// takes: it needs the loop, not the services).
struct LoopOf<'a, L>(&'a mut L);

impl<L: Locks> rtic_core::Mutex for LoopOf<'_, L> {
    type T = ControlLoop<L::Controller>;

    fn lock<R>(&mut self, f: impl FnOnce(&mut Self::T) -> R) -> R {
        self.0.lock(f)
    }
}

/// Largest response frame, delimiter included.
pub const MAX_RESPONSE: usize = MAX_ENCODED + 1;

/// The low-priority half of the board's protocol endpoint. `S` is the parameter storage.
#[derive(Debug)]
pub struct CommandHandler<S> {
    decoder: FrameDecoder,
    hardware: Hardware,
    /// The settings in force (or waiting for the next tick), physical units.
    settings: Settings,
    /// The settings are the compiled-in defaults (no valid stored record).
    defaults: bool,
    storage: S,
    next_seq: u16,
    crc_errors: u32,
    frame_errors: u32,
    tx: [u8; MAX_RESPONSE],
    /// Continuous telemetry's packer (the tick's tap is in the control loop).
    telemetry: TelemetryPacker,
    /// The learning's task half ([`crate::services::learning`]): its table and the ILC law.
    learn: LearnTask,
    /// The analog input's settings last started (or loaded from the stored record): what
    /// `StoreParams` stores with the settings.
    analog: Option<AnalogInputConfig>,
    /// The board last started from a watchdog reset (the status flag).
    watchdog_reset: bool,
}

impl<S: RecordStorage> CommandHandler<S> {
    /// A handler whose settings in force are `settings` (already running in the tick, built
    /// on `hardware`); `defaults` says they are the compiled-in ones.
    pub fn new(hardware: Hardware, settings: Settings, defaults: bool, storage: S) -> Self {
        let mut learn = LearnTask::new();
        learn.set_resolution(settings.sensor_quantum(&hardware));
        Self {
            decoder: FrameDecoder::new(),
            hardware,
            settings,
            defaults,
            storage,
            next_seq: 0,
            crc_errors: 0,
            frame_errors: 0,
            tx: [0; MAX_RESPONSE],
            telemetry: TelemetryPacker::new(),
            learn,
            analog: None,
            watchdog_reset: false,
        }
    }

    /// Says whether the board started from a watchdog reset (the firmware reads the MCU's
    /// reset flags at boot; the simulated board knows when its model of the watchdog fired):
    /// reported in the status until the next reset
    /// ([`crate::protocol::messages::StatusReport::WATCHDOG_RESET`]).
    pub fn set_watchdog_reset(&mut self, watchdog_reset: bool) {
        self.watchdog_reset = watchdog_reset;
    }

    /// The analog input's settings from the stored record the board booted on (`None` for
    /// a board on its defaults): kept for the next `StoreParams`, and prepared at the
    /// control rate when they say `start_at_boot` — the caller starts the input with them
    /// ([`ControlLoop::start_analog`]) before the first tick, so the board runs stand-alone
    /// from power-up. Settings the rate refuses are dropped (the record's were checked at
    /// its own rate, which is the rate the board runs), and so is a start that would take
    /// the tick over its budget ([`crate::config::tick_budget::ANALOG_CYCLES`]) beside `config`, the
    /// configuration the board booted on (passed in, not built again: at power-up the
    /// board's stack already holds it, and a second one would cost as much stack again).
    pub fn boot_analog(
        &mut self,
        stored: Option<AnalogInputConfig>,
        config: &ControlConfig,
    ) -> Option<PreparedInput> {
        let prepared = stored?.prepare(self.hardware.control_rate_hz).ok()?;
        self.analog = stored;
        let beside = crate::config::tick_budget::Beside {
            source: SetpointSource::Analog,
            ..Default::default()
        };
        let fits =
            crate::config::tick_budget::check_with(config, self.hardware.control_rate_hz, beside)
                .is_ok();
        stored.filter(|a| a.start_at_boot && fits).map(|_| prepared)
    }

    /// Feeds one received byte. When it completes a frame, the request is handled and the
    /// response frame (delimiter included) is returned, to be sent as it is.
    pub fn push_byte<const N: usize, L>(
        &mut self,
        byte: u8,
        queue: &mut Producer<'_, i16, N>,
        control: &mut L,
    ) -> Option<&[u8]>
    where
        L: Locks,
    {
        let decoded = match self.decoder.push(byte)? {
            Ok(body) => frame::decode_body::<Request>(body),
            Err(e) => Err(e),
        };
        let response = match decoded {
            Ok(request) => self.handle(request, queue, control),
            Err(e) => {
                if e == FrameError::BadCrc {
                    self.crc_errors = self.crc_errors.wrapping_add(1);
                } else {
                    self.frame_errors = self.frame_errors.wrapping_add(1);
                }
                nack(NackReason::Frame(e))
            }
        };
        // Every response fits a frame (the largest, a full record chunk, is under MAX_BODY).
        let n = frame::encode(&response, &mut self.tx).ok()?;
        self.tx.get(..n)
    }

    /// Feeds received bytes, passing each response frame to `send`.
    pub fn receive<const N: usize, L>(
        &mut self,
        bytes: &[u8],
        queue: &mut Producer<'_, i16, N>,
        control: &mut L,
        mut send: impl FnMut(&[u8]),
    ) where
        L: Locks,
    {
        for &b in bytes {
            if let Some(frame) = self.push_byte(b, queue, control) {
                send(frame);
            }
        }
    }

    /// Answers one request (already decoded).
    pub fn handle<const N: usize, L>(
        &mut self,
        request: Request,
        queue: &mut Producer<'_, i16, N>,
        control: &mut L,
    ) -> Response
    where
        L: Locks,
    {
        let done = match request {
            Request::Status => return Response::Status(self.status(queue, control)),
            // A drill was accepted on an idle board so that its reset cuts off no motion: a
            // source start, or an input edge armed to start the stream, waits for the reset.
            ref r if starts_source(r) && drilling(control) => Err(NackReason::Busy),
            // Where the coarse axis owns the piezo's setpoint (a dual-stage image, its task
            // running), no other source ever plays: refused, so that nothing accepted is
            // dropped (setpoints queued for a stream that cannot start, a scan's trigger
            // pulses with the stage not scanning).
            ref r
                if (starts_source(r)
                    || matches!(r, Request::Setpoints(_) | Request::PackedSetpoints(_)))
                    && coarse_owns_setpoint(control) =>
            {
                Err(NackReason::Unsupported)
            }
            Request::Setpoints(batch) => self.setpoints(batch, queue),
            Request::PackedSetpoints(batch) => self.setpoints(batch.into(), queue),
            Request::Stream(StreamControl::Start) if analog_running(control) => {
                Err(NackReason::Busy)
            }
            Request::Stream(c) => stream(c, control),
            Request::Mode(mode) => self.mode(mode, control),
            Request::LoadParams(p) => self.load(p, control),
            Request::StoreParams { boot_mode } => self.store(boot_mode, control),
            Request::RecallParams => self.recall(control),
            Request::Waveform(_) if analog_running(control) => Err(NackReason::Busy),
            Request::Waveform(w) => self.waveform(w, control),
            Request::Record(r) => record(r, control, |c| {
                self.listen(c, |l| ServicesLoad {
                    capture_decimation: Some(r.decimation),
                    capture_pre_trigger: false,
                    ..l
                })
            }),
            Request::ReadRecord { offset } => {
                // Piece by piece, a lock each: a tick falling due waits for one piece's copy.
                let mut values = heapless::Vec::new();
                let read = in_pieces(&mut values, |v| {
                    control.lock_services(|c| c.recorder().read_piece(offset, v))
                });
                return match read {
                    Ok(()) => Response::RecordChunk { offset, values },
                    // The limit is what the recorder holds now.
                    Err(_) => nack(refused(
                        Field::RecordOffset,
                        Rule::AtMost(control.lock_services(|c| c.recorder().recorded()) as f64),
                    )),
                };
            }
            Request::ReadParams => return Response::Params(self.settings.clone()),
            Request::Capture(r) => capture(r, control, |c| {
                self.listen(c, |l| ServicesLoad {
                    capture_decimation: Some(r.decimation),
                    capture_pre_trigger: r.pre_trigger > 0,
                    ..l
                })
            }),
            Request::CaptureStatus => return Response::Capture(self.capture_status(control)),
            Request::Learn(r) => match self.learn(r, control) {
                Ok(Some(response)) => return response,
                Ok(None) => Ok(()),
                Err(reason) => Err(reason),
            },
            Request::ReadCapture { offset, count } => {
                // Piece by piece, a lock each (a complete capture stays as it is until this
                // handler arms another): a tick falling due waits for one piece's copy.
                let mut values = heapless::Vec::new();
                let read = in_pieces(&mut values, |v| {
                    control.lock_services(|c| c.recorder().read_capture_piece(offset, count, v))
                });
                return match read {
                    Ok(()) => Response::CaptureChunk { offset, values },
                    Err(RecordError::NotDone) => nack(NackReason::Busy),
                    Err(_) => nack(refused(
                        Field::RecordOffset,
                        Rule::AtMost(
                            control
                                .lock_services(|c| c.recorder().capture_info())
                                .window_slots() as f64,
                        ),
                    )),
                };
            }
            Request::Telemetry(t) => self.telemetry(t, control),
            Request::CoarseHome => coarse(control, |_, s| CoarseLimits::check_home(s)),
            Request::CoarseMove(m) => coarse(control, |l, s| {
                l.check_move(s, m.target_mm, m.velocity_mm_s, m.acceleration_mm_s2)
            }),
            Request::CoarseJog { velocity_mm_s } => {
                coarse(control, |l, s| l.check_jog(s, velocity_mm_s))
            }
            Request::CoarseStop => coarse(control, |_, _| Ok(CoarseCommand::Stop)),
            Request::CoarseRelease => coarse_release(control),
            Request::CoarseStatus => {
                return match coarse_snapshot(control) {
                    Ok((_, status)) => Response::Coarse(status),
                    Err(reason) => nack(reason),
                }
            }
            Request::Scan(_) if analog_running(control) => Err(NackReason::Busy),
            Request::Scan(r) => self.scan(r, control),
            Request::Echo(bytes) => return Response::Echo(bytes),
            Request::WatchdogDrill => watchdog_drill(control),
            Request::Trigger(t) => self.trigger(t, control),
            Request::Sequence(r) => match self.sequence(r, control) {
                Ok(Some(status)) => return Response::Sequence(status),
                Ok(None) => Ok(()),
                Err(reason) => Err(reason),
            },
            Request::Analog(r) => match self.analog(r, control) {
                Ok(Some(status)) => return Response::Analog(status),
                Ok(None) => Ok(()),
                Err(reason) => Err(reason),
            },
        };
        match done {
            Ok(()) => Response::Ack {
                credits: credits(queue),
            },
            Err(reason) => nack(reason),
        }
    }

    fn status<const N: usize, L>(
        &self,
        queue: &Producer<'_, i16, N>,
        control: &mut L,
    ) -> StatusReport
    where
        L: Locks,
    {
        // A capture or a record that has completed stops the tick's snapshots.
        settle_listening(control);
        let t = control.lock(|c| c.telemetry());
        let (recording, recorded, lost, below, drifts) = control.peek_services(|s| {
            (
                s.recorder().is_capturing(),
                s.recorder().recorded(),
                s.lost(),
                s.observer().map(|o| o.estimate()),
                s.drifts(),
            )
        });
        let mut flags = match self.settings.mode {
            Mode::Bypass => 0,
            Mode::OpenLoop => 1,
            Mode::ClosedLoop => 2,
        } << StatusReport::MODE_SHIFT
            | Image::THIS.code() << StatusReport::IMAGE_SHIFT;
        for (on, flag) in [
            (self.defaults, StatusReport::DEFAULTS),
            (t.streaming, StatusReport::STREAMING),
            (t.waveform, StatusReport::WAVEFORM),
            (recording, StatusReport::RECORDING),
            (self.telemetry.is_active(), StatusReport::TELEMETRY),
            (t.scanning, StatusReport::SCANNING),
            (t.trigger_armed, StatusReport::TRIGGER_ARMED),
            (t.sequence, StatusReport::SEQUENCE),
            (t.analog, StatusReport::ANALOG),
            (t.analog_fault, StatusReport::ANALOG_FAULT),
            (self.watchdog_reset, StatusReport::WATCHDOG_RESET),
            (t.coarse, StatusReport::COARSE),
        ] {
            if on {
                flags |= flag;
            }
        }
        StatusReport {
            ticks: t.ticks,
            queue_fill: queue.len() as u16,
            credits: credits(queue),
            underruns: t.underruns,
            overruns: t.overruns.wrapping_add(lost),
            crc_errors: self.crc_errors,
            frame_errors: self.frame_errors,
            limit_hits: t.limit_hits,
            // The observer runs below the tick: its estimate as of the services' last batch
            // (up to a batch behind the tick); 0 without one.
            estimate: below.unwrap_or(0),
            next_seq: self.next_seq,
            tick_rate_hz: self.hardware.control_rate_hz as u32,
            recorded,
            flags,
            // The drift check runs below the tick too: its count as of the same batch.
            drifts,
        }
    }

    fn setpoints<const N: usize>(
        &mut self,
        batch: SetpointBatch,
        queue: &mut Producer<'_, i16, N>,
    ) -> Result<(), NackReason> {
        if batch.seq != self.next_seq {
            return Err(NackReason::OutOfSequence {
                expected: self.next_seq,
            });
        }
        if batch.samples.len() > credits(queue) as usize {
            return Err(NackReason::QueueFull);
        }
        for &s in &batch.samples {
            // Room was checked above and only this task enqueues, so this cannot fail.
            let _ = queue.enqueue(s);
        }
        self.next_seq = self.next_seq.wrapping_add(1);
        Ok(())
    }

    /// Validates `settings` whole, prepares them in the spare controller at the stacks'
    /// present voltages (outside any lock) and posts it to the tick.
    #[inline(never)] // rare and large: one copy, not one per caller
    fn load<L>(&mut self, settings: Settings, control: &mut L) -> Result<(), NackReason>
    where
        L: Locks,
    {
        let config = settings
            .build(&self.hardware)
            .map_err(NackReason::Refused)?;
        // What the tick runs beside the new configuration: the learning, a scan.
        let beside = beside_now(control);
        crate::config::tick_budget::check_with(&config, self.hardware.control_rate_hz, beside)
            .map_err(NackReason::Refused)?;
        let (spare, stacks) = control.lock(|c| (c.spare(), c.stacks()));
        // Two controllers cycle between the tick and this task: the spare is always there.
        let Some(mut spare) = spare else {
            return Err(NackReason::Busy);
        };
        // The heavy part, outside any lock: the tick runs meanwhile. The observer the
        // preparation relaxed is the one below the tick: relaxed once.
        let relaxed = spare.prepare(config, stacks);
        let observer = ObserverBelow::from_relaxed(&config, relaxed);
        // The observer runs below the tick: the services take it over at the new controller's
        // first snapshot, staged first, the tick handing them its snapshots.
        let below = observer.is_some();
        control.lock_services(|s| s.stage_observer(observer));
        if below {
            control.lock(|c| c.listen(true));
        }
        // O(1) under the lock: the stacks' voltages as they are now carry over.
        control.lock(|c| c.post(spare));
        self.learn
            .set_resolution(config.sensor.as_ref().map(|s| s.quantum()));
        self.settings = settings;
        self.defaults = false;
        Ok(())
    }

    #[inline(never)]
    fn mode<L>(&mut self, mode: Mode, control: &mut L) -> Result<(), NackReason>
    where
        L: Locks,
    {
        self.settings
            .check_mode(mode)
            .map_err(NackReason::Refused)?;
        control
            .lock(|c| c.set_mode(mode))
            .map_err(|_| refused(Field::Mode, Rule::Required))?;
        self.settings.mode = mode;
        Ok(())
    }

    #[inline(never)] // rare and large: one copy, not one per caller
    fn store<L>(&mut self, boot_mode: Mode, control: &mut L) -> Result<(), NackReason>
    where
        L: Locks,
    {
        self.settings
            .check_mode(boot_mode)
            .map_err(NackReason::Refused)?;
        if control.lock(|c| c.is_running()) {
            return Err(NackReason::Busy);
        }
        let record = StoredRecord {
            control_rate_hz: self.hardware.control_rate_hz as u32,
            settings: Settings {
                mode: boot_mode,
                ..self.settings.clone()
            },
            analog: self.analog,
        };
        let mut bytes = [0u8; MAX_RECORD];
        let n = record
            .encode(&mut bytes)
            .map_err(|_| NackReason::StoreFailed)?;
        let bytes = bytes.get(..n).ok_or(NackReason::StoreFailed)?;
        self.storage.write(bytes).map_err(|e| match e {
            StorageError::Unavailable => NackReason::NoStorage,
            StorageError::WriteFailed => NackReason::StoreFailed,
        })
    }

    #[inline(never)] // rare and large: one copy, not one per caller
    fn recall<L>(&mut self, control: &mut L) -> Result<(), NackReason>
    where
        L: Locks,
    {
        let record = StoredRecord::decode(self.storage.read(), &self.hardware)
            .map_err(|_| NackReason::NothingStored)?;
        if record.control_rate_hz as f64 != self.hardware.control_rate_hz {
            // The rate is fixed at boot: the record's settings may not hold at this one.
            return Err(NackReason::NothingStored);
        }
        self.load(record.settings, control)
    }

    #[inline(never)] // rare and large: one copy, not one per caller
    fn waveform<L>(&mut self, w: Waveform, control: &mut L) -> Result<(), NackReason>
    where
        L: Locks,
    {
        let shape = match w.shape {
            WaveShape::Sine => Shape::Sine,
            WaveShape::Triangle => Shape::Triangle,
        };
        let generator = WaveformGenerator::new(
            shape,
            setpoint_from_wire(w.offset),
            setpoint_from_wire(w.amplitude),
            w.frequency_mhz as f64 / 1000.0,
            self.hardware.control_rate_hz,
        )
        .map_err(|e| match e {
            WaveformError::FrequencyOutOfRange if w.frequency_mhz == 0 => {
                refused(Field::WaveformFrequency, Rule::Above(0.0))
            }
            WaveformError::FrequencyOutOfRange => refused(
                Field::WaveformFrequency,
                Rule::Below(self.hardware.control_rate_hz / 2.0),
            ),
            WaveformError::AmplitudeOutOfRange => {
                refused(Field::WaveformAmplitude, Rule::AtMost(1.0))
            }
        })?;
        let generator = match w.decay {
            Some(d) => generator.with_decay(d.hold_cycles, d.keep),
            None => generator,
        };
        control.lock(|c| c.play(generator));
        Ok(())
    }

    /// Validates a scan (outside any lock) against the control rate, the drive's slew limit
    /// and the trigger pulse width, then starts it (or leaves it waiting for the trigger) in
    /// one short lock.
    #[inline(never)] // rare and large: one copy, not one per caller
    fn scan<L>(&mut self, r: ScanRequest, control: &mut L) -> Result<(), NackReason>
    where
        L: Locks,
    {
        let rate = self.hardware.control_rate_hz;
        let pulse = control.lock(|c| c.trigger_pulse_ticks());
        let generator = ScanGenerator::new(&r, rate, self.max_scan_step(), pulse)
            .map_err(NackReason::Refused)?;
        // The scan ends the analog input or a sequence (other sources).
        let beside = crate::config::tick_budget::Beside {
            source: SetpointSource::Scan,
            ..beside_now(control)
        };
        if let Some(refusal) = self.over_budget(beside) {
            return Err(NackReason::Refused(refusal));
        }
        control.lock(|c| c.scan(generator, r.on_trigger));
        Ok(())
    }

    /// Applies trigger I/O settings; arming the input is refused if its edge's tick would not
    /// fit the control period beside what runs ([`crate::config::tick_budget::TRIGGER_CYCLES`]).
    fn trigger<L>(&mut self, t: TriggerConfig, control: &mut L) -> Result<(), NackReason>
    where
        L: Locks,
    {
        if t.input != crate::sources::scan::TriggerEdge::Off {
            let beside = crate::config::tick_budget::Beside {
                trigger: true,
                ..beside_now(control)
            };
            if let Some(refusal) = self.over_budget(beside) {
                return Err(NackReason::Refused(refusal));
            }
        }
        control.lock(|c| c.set_trigger(t));
        Ok(())
    }

    /// Arms (settings checked outside any lock), stops or reads a TTL-stepped sequence.
    #[inline(never)] // rare: one copy, not one per caller
    fn sequence<L>(
        &mut self,
        r: SequenceRequest,
        control: &mut L,
    ) -> Result<Option<SequenceStatus>, NackReason>
    where
        L: Locks,
    {
        match r {
            SequenceRequest::Arm(_) if analog_running(control) => Err(NackReason::Busy),
            SequenceRequest::Arm(config) => {
                config.check().map_err(NackReason::Refused)?;
                // The sequence ends a scan (another source); its ticks are charged.
                let beside = crate::config::tick_budget::Beside {
                    source: SetpointSource::Sequence,
                    ..beside_now(control)
                };
                if let Some(refusal) = self.over_budget(beside) {
                    return Err(NackReason::Refused(refusal));
                }
                let step = crate::sources::sequence::move_step(self.max_scan_step());
                let prepared = config.prepare(step);
                control.lock(|c| c.arm_sequence(&prepared));
                Ok(None)
            }
            SequenceRequest::Stop => {
                control.lock(|c| c.stop());
                Ok(None)
            }
            SequenceRequest::Status => Ok(Some(control.lock(|c| c.sequence_status()))),
        }
    }

    /// Starts (settings checked and prepared outside any lock; refused while another source
    /// runs), stops or reads the analog setpoint input.
    #[inline(never)] // rare: one copy, not one per caller
    fn analog<L>(
        &mut self,
        r: AnalogRequest,
        control: &mut L,
    ) -> Result<Option<AnalogStatus>, NackReason>
    where
        L: Locks,
    {
        match r {
            AnalogRequest::Start(config) => {
                let prepared = config
                    .prepare(self.hardware.control_rate_hz)
                    .map_err(NackReason::Refused)?;
                // The input ends a scan or a sequence (other sources).
                let beside = crate::config::tick_budget::Beside {
                    source: SetpointSource::Analog,
                    ..beside_now(control)
                };
                if let Some(refusal) = self.over_budget(beside) {
                    return Err(NackReason::Refused(refusal));
                }
                control.lock(|c| {
                    if c.other_source_running() {
                        Err(NackReason::Busy)
                    } else {
                        c.start_analog(prepared);
                        Ok(())
                    }
                })?;
                self.analog = Some(config);
                Ok(None)
            }
            AnalogRequest::Stop => {
                control.lock(|c| {
                    if c.analog_status().running {
                        c.stop();
                    }
                });
                Ok(None)
            }
            AnalogRequest::Status => Ok(Some(control.lock(|c| c.analog_status()))),
        }
    }

    /// The largest setpoint step per tick (Q2.30) the drive's slew limit follows: the
    /// normalised stroke (2.0) spans the voltage range, as in bypass.
    fn max_scan_step(&self) -> i32 {
        let d = &self.settings.drive;
        crate::sources::scan::slew_step(
            d.slew_rate,
            d.min_voltage,
            d.max_voltage,
            self.hardware.control_rate_hz,
        )
    }

    fn capture_status<L>(&self, control: &mut L) -> CaptureStatus
    where
        L: Locks,
    {
        let (info, capacity) =
            control.lock_services(|c| (c.recorder().capture_info(), c.recorder().capacity()));
        CaptureStatus {
            state: info.state,
            signals: info.signals,
            samples: info.samples,
            pre_trigger: info.pre_trigger,
            pre_available: info.pre_available,
            captured: info.captured,
            window_slots: info.window_slots(),
            decimation: info.decimation,
            capacity: capacity as u32,
            tick_rate_hz: self.hardware.control_rate_hz as u32,
            dac_full_scale: self.hardware.dac_full_scale,
            amplifier_full_scale: self.hardware.amplifier_full_scale as f32,
        }
    }

    /// Starts or stops telemetry: validated against the control rate (refusals name the
    /// field and its limit), then the tick's tap and the packer start (or stop) together.
    #[inline(never)] // rare: one copy, not one per caller
    fn telemetry<L>(&mut self, t: TelemetryRequest, control: &mut L) -> Result<(), NackReason>
    where
        L: Locks,
    {
        let rate = self.hardware.control_rate_hz as u32;
        match t {
            TelemetryRequest::Start {
                signals,
                decimation,
            } => {
                telemetry::check_request(signals, decimation, rate).map_err(NackReason::Refused)?;
                let wake = telemetry::frame_target(signals, decimation, rate) as u16;
                self.listen(control, |l| ServicesLoad {
                    telemetry_decimation: Some(decimation),
                    ..l
                })?;
                let first = control
                    .lock_services(|c| c.start_telemetry(signals, decimation, wake))
                    .ok_or(refused(Field::TelemetrySignals, Rule::AtMost(127.0)))?;
                self.telemetry.start(signals, decimation, first, rate);
            }
            TelemetryRequest::Stop => {
                let end = control.lock_services(|c| c.stop_telemetry());
                self.telemetry.stop(end);
                settle_listening(control);
            }
        }
        Ok(())
    }

    /// Whether a telemetry frame is due (see [`TelemetryPacker::due`]): the board's sending
    /// side asks after the responses, whenever a frame would fit on the line.
    pub fn telemetry_due<const N: usize>(&self, queue: &Consumer<'_, TelemetrySample, N>) -> bool {
        self.telemetry.due(queue)
    }

    /// The next telemetry frame (delimiter included), packed from `queue`, or `None` when
    /// there is nothing to send (see [`crate::protocol::messages::encode_telemetry`]). Uses the response buffer:
    /// send the frame before the next byte is pushed.
    pub fn pack_telemetry<const N: usize>(
        &mut self,
        queue: &mut Consumer<'_, TelemetrySample, N>,
    ) -> Option<&[u8]> {
        let n =
            crate::protocol::messages::encode_telemetry(&mut self.telemetry, queue, &mut self.tx)?;
        self.tx.get(..n)
    }

    /// Continuous telemetry's packer (its state: running, samples lost).
    pub fn telemetry_packer(&self) -> &TelemetryPacker {
        &self.telemetry
    }

    /// The learning's work at period boundaries ([`learning::service`]): call it whenever the
    /// low-priority task runs (the tick pends it at each boundary); it returns at once when no
    /// period has completed.
    pub fn service_learning<L>(&mut self, control: &mut L) -> Service
    where
        L: Locks,
    {
        learning::service(&mut self.learn, &mut LoopOf(control))
    }

    /// The learning's task half (its table, counters, last period).
    pub fn learning(&self) -> &LearnTask {
        &self.learn
    }

    /// Whether the loaded settings (built again here, off the tick) with `beside` would take
    /// the tick over its budget: the refusal if so.
    fn over_budget(
        &self,
        beside: crate::config::tick_budget::Beside,
    ) -> Option<crate::refusal::Refusal> {
        let config = self.settings.build(&self.hardware).ok()?;
        crate::config::tick_budget::check_with(&config, self.hardware.control_rate_hz, beside).err()
    }

    /// Has the tick hand the services its snapshots (before a capture, a record or telemetry
    /// is armed, so that the tick that arms it is served), unless the services' load once
    /// armed (`with` the load now) would take the tick over its budget beside what runs
    /// ([`crate::config::tick_budget::ServicesLoad`]): then the refusal.
    fn listen<L>(
        &self,
        control: &mut L,
        with: impl FnOnce(ServicesLoad) -> ServicesLoad,
    ) -> Result<(), NackReason>
    where
        L: Locks,
    {
        let now = beside_now(control);
        let beside = crate::config::tick_budget::Beside {
            services: with(now.services),
            ..now
        };
        if let Some(refusal) = self.over_budget(beside) {
            return Err(NackReason::Refused(refusal));
        }
        control.lock(|c| c.listen(true));
        Ok(())
    }

    #[inline(never)] // rare and large: one copy, not one per caller
    fn learn<L>(&mut self, r: LearnRequest, control: &mut L) -> Result<Option<Response>, NackReason>
    where
        L: Locks,
    {
        let period = self.learn.config().map_or(0, |c| c.period());
        match r {
            LearnRequest::Configure(s) => match s.build(self.hardware.control_rate_hz) {
                Ok(config) => {
                    learning::configure(&mut self.learn, config, &mut LoopOf(control));
                    Ok(())
                }
                Err(refusal) => Err(NackReason::Refused(refusal)),
            },
            LearnRequest::State(state) => {
                if state != LearnState::Off && self.learn.config().is_none() {
                    Err(refused(Field::LearnPeriod, Rule::Required))
                } else if state == LearnState::Learning && self.settings.sensor.is_none() {
                    Err(refused(Field::Sensor, Rule::Required))
                } else if let Some(refusal) = (state != LearnState::Off)
                    .then(|| {
                        let beside = crate::config::tick_budget::Beside {
                            learning: true,
                            ..beside_now(control)
                        };
                        self.over_budget(beside)
                    })
                    .flatten()
                {
                    Err(NackReason::Refused(refusal))
                } else {
                    control.lock(|c| c.set_learning(state));
                    Ok(())
                }
            }
            LearnRequest::Reset => {
                self.learn.set_table(&[]);
                learning::post_table(&self.learn, &mut LoopOf(control));
                Ok(())
            }
            LearnRequest::Status => {
                let (state, periods) =
                    control.lock(|c| (c.learning().state(), c.learning().periods()));
                return Ok(Some(Response::Learn(LearnStatus {
                    state,
                    period_ticks: period as u16,
                    periods,
                    updates: self.learn.updates(),
                    missed: self.learn.missed(),
                    last: self.learn.last_error(),
                })));
            }
            LearnRequest::ReadTable { offset } => {
                let from = offset as usize;
                if from > period {
                    Err(refused(Field::RecordOffset, Rule::AtMost(period as f64)))
                } else {
                    let end = from
                        .saturating_add(crate::services::recorder::MAX_CHUNK)
                        .min(period);
                    let mut values = heapless::Vec::new();
                    for &v in self.learn.table().get(from..end).unwrap_or(&[]) {
                        let _ = values.push(v);
                    }
                    return Ok(Some(Response::RecordChunk { offset, values }));
                }
            }
            LearnRequest::WriteTable { offset, values } => {
                // In u32 and checked, so that an offset near 2^32 cannot wrap past the bound on
                // the 32-bit board (nor pass it on a 64-bit host): the same answer on both.
                let last = learning::MAX_BINS - values.len(); // values: at most MAX_CHUNK
                match offset.checked_add(values.len() as u32) {
                    Some(end) if end as usize <= learning::MAX_BINS => {
                        self.learn.write_entries(offset as usize, &values);
                        Ok(())
                    }
                    _ => Err(refused(Field::RecordOffset, Rule::AtMost(last as f64))),
                }
            }
            LearnRequest::PostTable => {
                learning::post_table(&self.learn, &mut LoopOf(control));
                Ok(())
            }
        }
        .map(|()| None)
    }

    /// The settings in force (or waiting for the next tick).
    pub fn settings(&self) -> &Settings {
        &self.settings
    }

    /// The hardware the settings are validated against.
    pub fn hardware(&self) -> &Hardware {
        &self.hardware
    }

    /// The sequence number the next batch must carry.
    pub fn next_seq(&self) -> u16 {
        self.next_seq
    }

    /// Frames refused for their CRC.
    pub fn crc_errors(&self) -> u32 {
        self.crc_errors
    }

    /// The frame decoder's work so far (see [`FrameDecoder::steps`]).
    pub fn decoder_steps(&self) -> u32 {
        self.decoder.steps()
    }

    /// The parameter storage.
    pub fn storage(&self) -> &S {
        &self.storage
    }

    /// The parameter storage, mutably (a simulated board injecting a flash fault).
    pub fn storage_mut(&mut self) -> &mut S {
        &mut self.storage
    }
}

fn nack(reason: NackReason) -> Response {
    Response::Nack { reason }
}

fn refused(field: Field, rule: Rule) -> NackReason {
    NackReason::Refused(Refusal::new(field, rule))
}

fn credits<const N: usize>(queue: &Producer<'_, i16, N>) -> u16 {
    queue.capacity().saturating_sub(queue.len()) as u16
}

/// Whether `request` starts a setpoint source: the stream, the waveform generator, a scan, a
/// sequence, the analog input, or an input edge armed to start the stream.
fn starts_source(request: &Request) -> bool {
    matches!(
        request,
        Request::Stream(StreamControl::Start)
            | Request::Waveform(_)
            | Request::Scan(_)
            | Request::Sequence(SequenceRequest::Arm(_))
            | Request::Analog(AnalogRequest::Start(_))
            | Request::Trigger(TriggerConfig {
                start_stream: true,
                ..
            })
    )
}

/// Whether a watchdog drill is on (the board resets within the watchdog's timeout): a source
/// start is refused until then.
fn drilling<L>(control: &mut L) -> bool
where
    L: Locks,
{
    control.lock(|c| !c.feeds_watchdog())
}

/// Starts a watchdog drill ([`ControlLoop::drill_watchdog`]) on an idle board with a
/// watchdog: refused while a setpoint source drives the outputs (the reset would cut it off
/// mid-motion), and by the emulator image, whose QEMU machine has no watchdog.
fn watchdog_drill<L>(control: &mut L) -> Result<(), NackReason>
where
    L: Locks,
{
    if Image::THIS == Image::Emulator {
        return Err(NackReason::Unsupported);
    }
    control.lock(|c| {
        if c.is_running() {
            Err(NackReason::Busy)
        } else {
            c.drill_watchdog();
            Ok(())
        }
    })
}

/// Whether the coarse axis owns the piezo's setpoint ([`ControlLoop::coarse_owns_setpoint`]:
/// the other sources are refused).
fn coarse_owns_setpoint<L>(control: &mut L) -> bool
where
    L: Locks,
{
    control.lock(|c| c.coarse_owns_setpoint())
}

/// Whether the analog input is the setpoint source (another source's start is refused).
fn analog_running<L>(control: &mut L) -> bool
where
    L: Locks,
{
    control.lock(|c| c.analog_status().running)
}

fn stream<L>(c: StreamControl, control: &mut L) -> Result<(), NackReason>
where
    L: Locks,
{
    match c {
        StreamControl::Start => control.lock(|c| c.start()),
        StreamControl::Stop => control.lock(|c| c.stop()),
        StreamControl::Finish => control.lock(|c| c.finish()),
        StreamControl::Rate { divider } => {
            if !control.lock(|c| c.set_divider(divider)) {
                return Err(refused(Field::Divider, Rule::AtLeast(1.0)));
            }
        }
        StreamControl::Underrun(policy) => control.lock(|c| c.set_underrun(policy)),
    }
    Ok(())
}

/// Arms a v3 `Record` (checked first; `listen` then has the tick hand the services its
/// snapshots, or refuses the services' cost beside what runs).
fn record<L>(
    r: RecordRequest,
    control: &mut L,
    listen: impl FnOnce(&mut L) -> Result<(), NackReason>,
) -> Result<(), NackReason>
where
    L: Locks,
{
    let capacity = control.lock_services(|c| c.recorder().record_capacity());
    if r.decimation == 0 {
        return Err(refused(Field::RecordDecimation, Rule::AtLeast(1.0)));
    }
    if r.count == 0 {
        return Err(refused(Field::RecordCount, Rule::AtLeast(1.0)));
    }
    if r.count as usize > capacity {
        return Err(refused(Field::RecordCount, Rule::AtMost(capacity as f64)));
    }
    listen(control)?;
    control
        .lock_services(|c| c.recorder_mut().arm(r.signal, r.count, r.decimation))
        .map_err(|_| refused(Field::RecordCount, Rule::AtMost(capacity as f64)))
}

/// Arms a capture (checked first; `listen` then has the tick hand the services its
/// snapshots, or refuses the services' cost beside what runs).
#[inline(never)] // rare: one copy, not one per caller
fn capture<L>(
    r: CaptureRequest,
    control: &mut L,
    listen: impl FnOnce(&mut L) -> Result<(), NackReason>,
) -> Result<(), NackReason>
where
    L: Locks,
{
    let signals = r.signals.count_ones();
    let max_frames = control.lock_services(|c| c.recorder().max_frames(signals));
    if r.signals == 0 {
        return Err(refused(Field::RecordSignals, Rule::AtLeast(1.0)));
    }
    if r.signals >> crate::services::recorder::CHANNELS != 0 {
        // Bit 7 names no signal: the mask is at most 0b111_1111.
        return Err(refused(Field::RecordSignals, Rule::AtMost(127.0)));
    }
    if r.samples == 0 {
        return Err(refused(Field::RecordCount, Rule::AtLeast(1.0)));
    }
    if r.samples > max_frames {
        // The limit in samples per signal for this many signals.
        return Err(refused(Field::RecordCount, Rule::AtMost(max_frames as f64)));
    }
    if r.trigger == crate::services::recorder::Trigger::Now && r.pre_trigger != 0 {
        return Err(refused(Field::RecordPreTrigger, Rule::AtMost(0.0)));
    }
    if r.pre_trigger >= r.samples {
        return Err(refused(
            Field::RecordPreTrigger,
            Rule::Below(r.samples as f64),
        ));
    }
    if r.decimation == 0 {
        return Err(refused(Field::RecordDecimation, Rule::AtLeast(1.0)));
    }
    listen(control)?;
    control
        .lock_services(|c| {
            c.recorder_mut().arm_capture(
                r.signals,
                r.samples,
                r.pre_trigger,
                r.trigger,
                r.decimation,
            )
        })
        .map_err(|_| refused(Field::RecordCount, Rule::AtMost(max_frames as f64)))
}

/// What runs beside the configuration now, as the tick budget charges it: the loop's, and
/// what the services run, their listening settled first ([`settle_listening`]), so that a
/// capture that has completed is no longer charged.
fn beside_now<L>(control: &mut L) -> crate::config::tick_budget::Beside
where
    L: Locks,
{
    settle_listening(control);
    let services = control.peek_services(|s| s.load());
    crate::config::tick_budget::Beside {
        services,
        ..control.lock(|c| c.beside())
    }
}

/// Starts the services beside the configuration the tick runs from power-up (`config`, its
/// controller prepared at the drive's safe state, as [`Controller::new`] prepares it): its
/// observer below the tick, if it has one, in force at once, and the tick handing the
/// services its snapshots if so. The board, the simulator and the tests boot through it.
pub fn start_services<C, B>(
    config: &ControlConfig,
    control: &mut ControlLoop<C>,
    services: &mut Services<B>,
) where
    C: DerefMut<Target = Controller>,
    B: SampleStore,
{
    let observer = ObserverBelow::prepare(config, config.drive.safe_stacks());
    control.listen(observer.is_some());
    services.start_observer(observer);
}

/// Stops the tick's snapshots once the services are idle (no capture or record armed or
/// running, telemetry stopped). Only this task arms them, so they stay idle until it does.
fn settle_listening<L>(control: &mut L)
where
    L: Locks,
{
    if control.lock(|c| c.is_listening()) && !control.peek_services(|s| s.is_active()) {
        control.lock(|c| c.listen(false));
    }
}

/// The coarse axis's limits and latest status, read in one short lock; refused when the image
/// has no coarse axis (built without `dual-stage`, or its settings refused at boot, or the
/// configuration in force at boot leaving its task no share of the tick).
fn coarse_snapshot<L>(control: &mut L) -> Result<(CoarseLimits, CoarseStatus), NackReason>
where
    L: Locks,
{
    // Without the feature no coarse task attaches, and the checks below (floating-point
    // work, several kilobytes) stay out of the image.
    #[cfg(feature = "dual-stage")]
    {
        let (limits, status) = control.lock(|c| (c.coarse().limits(), c.coarse().status()));
        limits
            .map(|l| (l, status))
            .ok_or(refused(Field::CoarseAxis, Rule::NoHardware))
    }
    #[cfg(not(feature = "dual-stage"))]
    {
        let _ = control;
        Err(refused(Field::CoarseAxis, Rule::NoHardware))
    }
}

/// A coarse request: validated (outside any lock: it is floating-point work) against the
/// axis's latest status, then left for the coarse task in one short lock. The coarse task
/// checks it again against the state it is in when it takes it.
#[inline(never)] // rare: one copy, not one per caller
fn coarse<L>(
    control: &mut L,
    check: impl FnOnce(&CoarseLimits, &CoarseStatus) -> Result<CoarseCommand, CoarseRefusal>,
) -> Result<(), NackReason>
where
    L: Locks,
{
    let (limits, status) = coarse_snapshot(control)?;
    let command = check(&limits, &status).map_err(|r| match r {
        CoarseRefusal::Busy => NackReason::Busy,
        CoarseRefusal::Refused(r) => NackReason::Refused(r),
    })?;
    // A motion command takes a handed-back piezo again: not while one of its own sources
    // runs or waits for its edge (it would be cut off). Checked and left in one lock, so no
    // source starts between the two.
    let engages = !matches!(command, CoarseCommand::Stop);
    control.lock(|c| {
        if engages && c.coarse().is_piezo_released() && c.piezo_source_busy() {
            return Err(NackReason::Busy);
        }
        c.coarse().request(command);
        Ok(())
    })
}

/// Hands the piezo back from the coarse axis ([`Request::CoarseRelease`]): only with the axis
/// at rest (unhomed, idle or faulted: its fine share is not part of a motion), checked on the
/// latest status and again in the lock against a motion command the task has not taken yet
/// (the status may be a coarse period old).
#[inline(never)] // rare: kept out of the handler's common path
fn coarse_release<L>(control: &mut L) -> Result<(), NackReason>
where
    L: Locks,
{
    let (_, status) = coarse_snapshot(control)?;
    if status.state.is_moving() {
        return Err(NackReason::Busy);
    }
    control.lock(|c| {
        if c.coarse().motion_pending() {
            return Err(NackReason::Busy);
        }
        c.release_piezo();
        Ok(())
    })
}
