//! The board's command handler: received bytes in, one response frame out per request.
//!
//! It runs in the low-priority task (the firmware's decoder task; the simulator's receive
//! path) and owns everything that is not the tick's: the frame decoder, the active settings
//! in physical units, the parameter storage, the batch sequence number and the frame-error
//! counters. It reaches the tick side ([`ControlLoop`]) in two ways only:
//!
//! * setpoint batches go into the lock-free setpoint queue (`heapless::spsc` producer); the
//!   credits in every `Ack` are that queue's free slots;
//! * everything else is one short critical section through an [`rtic_core::Mutex`] (RTIC's
//!   resource lock on the board, `rtic_core::Exclusive` in the simulator): a few stores, a
//!   chunk copy, or the copy of a configuration that was validated *before* the lock.
//!
//! Rules (see the README's protocol chapter): every request gets exactly one response; a
//! refused request changes nothing and loses nothing already queued; a batch must carry the
//! next sequence number and fit the credits; parameter loads are built and validated whole
//! ([`Settings::build`]) and swapped in by the tick between two ticks.

use heapless::spsc::Producer;
use rtic_core::Mutex;

use crate::control_loop::{ControlLoop, TickConfig};
use crate::param_store::{BoardSettings, RecordStorage, StorageError, MAX_RECORD};
use crate::setpoint_stream::setpoint_from_wire;
use crate::settings::{Mode, Settings};
use crate::waveform::{Shape, WaveformGenerator};

use super::decoder::FrameDecoder;
use super::frame::{self, FrameError, MAX_ENCODED};
use super::messages::{
    NackReason, ParamSet, RecordRequest, Request, Response, SetpointBatch, StatusReport,
    StreamControl, WaveShape, Waveform,
};
use super::param_load::{
    decode_record, encode_record, nack_reason, sensor_calibration, settings_from_params,
    BoardProfile,
};

/// Largest response frame, delimiter included.
pub const MAX_RESPONSE: usize = MAX_ENCODED + 1;

/// The low-priority half of the board's protocol endpoint. `S` is the parameter storage.
#[derive(Debug)]
pub struct CommandHandler<S> {
    decoder: FrameDecoder,
    profile: BoardProfile,
    board: BoardSettings,
    /// The settings in force (or pending), physical units.
    settings: Settings,
    /// The parameter set they came from: what `StoreParams` writes.
    params: ParamSet,
    /// The parameters are the compiled-in defaults (no valid stored set).
    defaults: bool,
    storage: S,
    next_seq: u16,
    crc_errors: u32,
    frame_errors: u32,
    tx: [u8; MAX_RESPONSE],
}

impl<S: RecordStorage> CommandHandler<S> {
    /// A handler on `params`, with the configuration the tick starts on; refused if `params`
    /// does not validate on this board.
    pub fn new(
        profile: BoardProfile,
        board: BoardSettings,
        params: ParamSet,
        storage: S,
    ) -> Result<(Self, TickConfig), NackReason> {
        let settings = settings_from_params(&params, &profile)?;
        let control = settings.build().map_err(nack_reason)?;
        let tick = TickConfig {
            control,
            sensor: sensor_calibration(&settings),
        };
        let handler = Self {
            decoder: FrameDecoder::new(),
            profile,
            board,
            settings,
            params,
            defaults: false,
            storage,
            next_seq: 0,
            crc_errors: 0,
            frame_errors: 0,
            tx: [0; MAX_RESPONSE],
        };
        Ok((handler, tick))
    }

    /// Start-up: the parameter set stored in `storage` if there is a valid one, otherwise
    /// `defaults` (and the status flag [`StatusReport::DEFAULTS`]). Fails only if `defaults`
    /// itself does not validate on this board.
    pub fn boot(
        profile: BoardProfile,
        board: BoardSettings,
        storage: S,
        defaults: ParamSet,
    ) -> Result<(Self, TickConfig), NackReason> {
        let stored = decode_record(storage.read())
            .and_then(|p| settings_from_params(&p, &profile).ok().map(|s| (p, s)))
            .and_then(|(p, s)| s.build().ok().map(|_| p));
        match stored {
            Some(p) => Self::new(profile, board, p, storage),
            None => {
                let (mut h, tick) = Self::new(profile, board, defaults, storage)?;
                h.defaults = true;
                Ok((h, tick))
            }
        }
    }

    /// Feeds one received byte. When it completes a frame, the request is handled and the
    /// response frame (delimiter included) is returned, to be sent as it is.
    pub fn push_byte<const N: usize, B, L>(
        &mut self,
        byte: u8,
        queue: &mut Producer<'_, i16, N>,
        control: &mut L,
    ) -> Option<&[u8]>
    where
        B: AsRef<[i32]> + AsMut<[i32]>,
        L: Mutex<T = ControlLoop<B>>,
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
    pub fn receive<const N: usize, B, L>(
        &mut self,
        bytes: &[u8],
        queue: &mut Producer<'_, i16, N>,
        control: &mut L,
        mut send: impl FnMut(&[u8]),
    ) where
        B: AsRef<[i32]> + AsMut<[i32]>,
        L: Mutex<T = ControlLoop<B>>,
    {
        for &b in bytes {
            if let Some(frame) = self.push_byte(b, queue, control) {
                send(frame);
            }
        }
    }

    /// Answers one request (already decoded).
    pub fn handle<const N: usize, B, L>(
        &mut self,
        request: Request,
        queue: &mut Producer<'_, i16, N>,
        control: &mut L,
    ) -> Response
    where
        B: AsRef<[i32]> + AsMut<[i32]>,
        L: Mutex<T = ControlLoop<B>>,
    {
        let done = match request {
            Request::Status => return Response::Status(self.status(queue, control)),
            Request::Setpoints(batch) => self.setpoints(batch, queue),
            Request::Stream(c) => stream(c, control),
            Request::Mode(mode) => self.mode(mode, control),
            Request::LoadParams(p) => self.load(p, control),
            Request::StoreParams => self.store(control),
            Request::RecallParams => self.recall(control),
            Request::Waveform(w) => self.waveform(w, control),
            Request::Record(r) => record(r, control),
            Request::ReadRecord { offset } => {
                let mut values = heapless::Vec::new();
                return match control.lock(|c| c.read_record(offset, &mut values)) {
                    Ok(()) => Response::RecordChunk { offset, values },
                    Err(_) => nack(NackReason::OutOfRange),
                };
            }
        };
        match done {
            Ok(()) => Response::Ack {
                credits: credits(queue),
            },
            Err(reason) => nack(reason),
        }
    }

    fn status<const N: usize, B, L>(
        &self,
        queue: &Producer<'_, i16, N>,
        control: &mut L,
    ) -> StatusReport
    where
        B: AsRef<[i32]> + AsMut<[i32]>,
        L: Mutex<T = ControlLoop<B>>,
    {
        let t = control.lock(|c| c.telemetry());
        let mut flags = match self.settings.mode {
            Mode::Bypass => 0,
            Mode::OpenLoop => 1,
            Mode::ClosedLoop => 2,
        } << StatusReport::MODE_SHIFT;
        for (on, flag) in [
            (self.defaults, StatusReport::DEFAULTS),
            (t.streaming, StatusReport::STREAMING),
            (t.waveform, StatusReport::WAVEFORM),
            (t.recording, StatusReport::RECORDING),
            (t.config_pending, StatusReport::CONFIG_PENDING),
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
            overruns: t.overruns,
            crc_errors: self.crc_errors,
            frame_errors: self.frame_errors,
            limit_hits: t.limit_hits,
            estimate: t.estimate,
            next_seq: self.next_seq,
            tick_rate_hz: self.board.tick_rate_hz,
            recorded: t.recorded,
            flags,
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

    /// Validates `settings` whole and posts the result to the tick.
    #[inline(never)]
    fn post<B, L>(settings: &Settings, control: &mut L) -> Result<(), NackReason>
    where
        B: AsRef<[i32]> + AsMut<[i32]>,
        L: Mutex<T = ControlLoop<B>>,
    {
        let config = TickConfig {
            control: settings.build().map_err(nack_reason)?,
            sensor: sensor_calibration(settings),
        };
        control.lock(|c| c.post_config(config));
        Ok(())
    }

    #[inline(never)] // rare and large: one copy, not one per caller
    fn mode<B, L>(&mut self, mode: Mode, control: &mut L) -> Result<(), NackReason>
    where
        B: AsRef<[i32]> + AsMut<[i32]>,
        L: Mutex<T = ControlLoop<B>>,
    {
        if mode == Mode::ClosedLoop && self.params.feedback.is_none() {
            return Err(NackReason::Unsupported);
        }
        // The settings change in place (no copy of the models), and back if refused.
        let old = core::mem::replace(&mut self.settings.mode, mode);
        match Self::post(&self.settings, control) {
            Ok(()) => {
                self.params.mode = mode;
                Ok(())
            }
            Err(e) => {
                self.settings.mode = old;
                Err(e)
            }
        }
    }

    #[inline(never)] // rare and large: one copy, not one per caller
    fn load<B, L>(&mut self, params: ParamSet, control: &mut L) -> Result<(), NackReason>
    where
        B: AsRef<[i32]> + AsMut<[i32]>,
        L: Mutex<T = ControlLoop<B>>,
    {
        let settings = settings_from_params(&params, &self.profile)?;
        Self::post(&settings, control)?;
        self.settings = settings;
        self.params = params;
        self.defaults = false;
        Ok(())
    }

    #[inline(never)] // rare and large: one copy, not one per caller
    fn store<B, L>(&mut self, control: &mut L) -> Result<(), NackReason>
    where
        B: AsRef<[i32]> + AsMut<[i32]>,
        L: Mutex<T = ControlLoop<B>>,
    {
        if control.lock(|c| c.is_running()) {
            return Err(NackReason::Busy);
        }
        let mut record = [0u8; MAX_RECORD];
        let n = encode_record(&self.board, &self.params, &mut record)?;
        let bytes = record.get(..n).ok_or(NackReason::StoreFailed)?;
        self.storage.write(bytes).map_err(|e| match e {
            StorageError::Unavailable => NackReason::Unsupported,
            StorageError::WriteFailed => NackReason::StoreFailed,
        })
    }

    #[inline(never)] // rare and large: one copy, not one per caller
    fn recall<B, L>(&mut self, control: &mut L) -> Result<(), NackReason>
    where
        B: AsRef<[i32]> + AsMut<[i32]>,
        L: Mutex<T = ControlLoop<B>>,
    {
        let params = decode_record(self.storage.read()).ok_or(NackReason::NothingStored)?;
        self.load(params, control)
    }

    #[inline(never)] // rare and large: one copy, not one per caller
    fn waveform<B, L>(&mut self, w: Waveform, control: &mut L) -> Result<(), NackReason>
    where
        B: AsRef<[i32]> + AsMut<[i32]>,
        L: Mutex<T = ControlLoop<B>>,
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
            self.profile.control_rate_hz,
        )
        .map_err(|_| NackReason::OutOfRange)?;
        control.lock(|c| c.play(generator));
        Ok(())
    }

    /// The settings in force (or pending).
    pub fn settings(&self) -> &Settings {
        &self.settings
    }

    /// The parameter set in force (what `StoreParams` writes).
    pub fn params(&self) -> &ParamSet {
        &self.params
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
}

fn nack(reason: NackReason) -> Response {
    Response::Nack { reason }
}

fn credits<const N: usize>(queue: &Producer<'_, i16, N>) -> u16 {
    queue.capacity().saturating_sub(queue.len()) as u16
}

fn stream<B, L>(c: StreamControl, control: &mut L) -> Result<(), NackReason>
where
    B: AsRef<[i32]> + AsMut<[i32]>,
    L: Mutex<T = ControlLoop<B>>,
{
    match c {
        StreamControl::Start => control.lock(|c| c.start()),
        StreamControl::Stop => control.lock(|c| c.stop()),
        StreamControl::Rate { divider } => {
            if !control.lock(|c| c.set_divider(divider)) {
                return Err(NackReason::OutOfRange);
            }
        }
        StreamControl::Underrun(policy) => control.lock(|c| c.set_underrun(policy)),
    }
    Ok(())
}

fn record<B, L>(r: RecordRequest, control: &mut L) -> Result<(), NackReason>
where
    B: AsRef<[i32]> + AsMut<[i32]>,
    L: Mutex<T = ControlLoop<B>>,
{
    control
        .lock(|c| c.arm_recorder(r.signal, r.count, r.decimation))
        .map_err(|_| NackReason::OutOfRange)
}
