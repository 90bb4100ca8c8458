//! The board's command handler against every request and every NACK reason, on the same
//! control loop the firmware runs (fake converters): each request gets one response; a
//! refused one applies nothing and loses nothing queued; a load is swapped in between ticks.

use rtic_core::Exclusive;
use twinstack::board::fakes::{FixedAdc, RecordingDac};
use twinstack::board::{AdcCode, DacCode};
use twinstack::control_loop::{ControlLoop, SetpointQueue, SETPOINT_CAPACITY};
use twinstack::default_config::{board_profile, boot_param_set};
use twinstack::drive::{DriveError, SafeState};
use twinstack::param_store::{
    BoardSettings, RamStorage, ReadOnlyStorage, RecordStorage, StorageError,
};
use twinstack::params::ParamError;
use twinstack::protocol::decoder::FrameDecoder;
use twinstack::protocol::frame::{self, FrameError, MAX_ENCODED, PROTOCOL_VERSION};
use twinstack::protocol::handler::CommandHandler;
use twinstack::protocol::messages::*;
use twinstack::protocol::param_load::BoardProfile;
use twinstack::settings::Mode;

/// Storage whose writes always fail (a flash that does not program).
struct BrokenFlash([u8; 16]);
impl RecordStorage for BrokenFlash {
    fn read(&self) -> &[u8] {
        &self.0
    }
    fn write(&mut self, _: &[u8]) -> Result<(), StorageError> {
        Err(StorageError::WriteFailed)
    }
}

const RATE: u32 = 50_000;

/// A board: handler, control loop, queue, converters.
struct Board<S> {
    handler: CommandHandler<S>,
    control: ControlLoop<Vec<i32>>,
    queue: &'static mut SetpointQueue,
    dac: RecordingDac,
    adc: FixedAdc,
}

fn board_with<S: RecordStorage>(storage: S, profile: BoardProfile) -> Board<S> {
    let settings = BoardSettings {
        tick_rate_hz: RATE,
        safe_state: SafeState::Bias,
    };
    let (handler, tick) = CommandHandler::boot(
        profile,
        settings,
        storage,
        boot_param_set(SafeState::Bias).unwrap(),
    )
    .expect("boot parameters valid");
    Board {
        handler,
        control: ControlLoop::new(tick, RATE, vec![0; 4096]),
        queue: Box::leak(Box::new(SetpointQueue::new())),
        dac: RecordingDac::default(),
        adc: FixedAdc(Some(AdcCode(2048))),
    }
}

fn board() -> Board<RamStorage> {
    board_with(RamStorage::default(), board_profile(RATE as f64))
}

impl<S: RecordStorage> Board<S> {
    fn handle(&mut self, request: Request) -> Response {
        let (mut p, _) = self.queue.split();
        self.handler
            .handle(request, &mut p, &mut Exclusive(&mut self.control))
    }

    /// Bytes in, response frames out (decoded).
    fn bytes(&mut self, bytes: &[u8]) -> Vec<Response> {
        let (mut p, _) = self.queue.split();
        let mut frames = Vec::new();
        self.handler
            .receive(bytes, &mut p, &mut Exclusive(&mut self.control), |f| {
                frames.push(f.to_vec())
            });
        frames.iter().map(|f| decode_response(f)).collect()
    }

    fn ticks(&mut self, n: usize) {
        for _ in 0..n {
            let (_, mut c) = self.queue.split();
            self.control.tick(&mut c, &mut self.adc, &mut self.dac);
        }
    }

    fn status(&mut self) -> StatusReport {
        match self.handle(Request::Status) {
            Response::Status(s) => s,
            r => panic!("{r:?}"),
        }
    }

    fn queued(&mut self) -> Vec<i16> {
        self.queue.iter().copied().collect()
    }
}

fn decode_response(frame: &[u8]) -> Response {
    let mut d = FrameDecoder::new();
    let (&last, rest) = frame.split_last().unwrap();
    assert_eq!(last, 0, "a response frame ends with its delimiter");
    for &b in rest {
        assert!(d.push(b).is_none(), "one frame per response");
    }
    frame::decode_body(d.push(0).unwrap().unwrap()).unwrap()
}

fn encoded(r: &Request) -> Vec<u8> {
    let mut out = vec![0u8; MAX_ENCODED + 1];
    let n = frame::encode(r, &mut out).unwrap();
    out.truncate(n);
    out
}

fn batch(seq: u16, samples: &[i16]) -> Request {
    Request::Setpoints(SetpointBatch {
        seq,
        samples: heapless::Vec::from_slice(samples).unwrap(),
    })
}

fn nack(reason: NackReason) -> Response {
    Response::Nack { reason }
}

/// Refused requests leave everything as it was: the queue, the settings, the sequence.
fn assert_nothing_changed<S: RecordStorage>(b: &mut Board<S>, queued: &[i16], params: &ParamSet) {
    assert_eq!(b.queued(), queued, "queued setpoints lost or added");
    assert_eq!(b.handler.params(), params, "parameters changed");
    assert!(
        !b.control.telemetry().config_pending,
        "a configuration was posted"
    );
}

#[test]
fn setpoint_batches_need_the_next_sequence_number_and_room() {
    let mut b = board();
    assert_eq!(
        b.handle(batch(0, &[1, 2, 3])),
        Response::Ack {
            credits: SETPOINT_CAPACITY as u16 - 3
        }
    );
    let params = b.handler.params().clone();
    // Out of sequence: refused, nothing queued.
    assert_eq!(
        b.handle(batch(7, &[9; 10])),
        nack(NackReason::OutOfSequence { expected: 1 })
    );
    assert_nothing_changed(&mut b, &[1, 2, 3], &params);
    // Fill to the brim, then one over: refused whole.
    let mut seq = 1;
    let mut queued = vec![1, 2, 3];
    while queued.len() + MAX_BATCH <= SETPOINT_CAPACITY {
        assert!(matches!(
            b.handle(batch(seq, &[5; MAX_BATCH])),
            Response::Ack { .. }
        ));
        queued.extend([5; MAX_BATCH]);
        seq += 1;
    }
    let free = SETPOINT_CAPACITY - queued.len();
    assert_eq!(
        b.handle(batch(seq, &vec![6; free + 1])),
        nack(NackReason::QueueFull)
    );
    assert_nothing_changed(&mut b, &queued, &params);
    assert_eq!(
        b.handle(batch(seq, &vec![6; free])),
        Response::Ack { credits: 0 }
    );
    // The sequence number wraps.
    let mut b = board();
    for seq in 0..=u16::MAX {
        assert!(matches!(b.handle(batch(seq, &[])), Response::Ack { .. }));
    }
    assert!(matches!(b.handle(batch(0, &[])), Response::Ack { .. }));
}

#[test]
fn stream_control_starts_stops_sets_the_rate_and_the_underrun_policy() {
    let mut b = board();
    assert!(matches!(
        b.handle(batch(0, &[1000, 2000])),
        Response::Ack { .. }
    ));
    assert_eq!(
        b.handle(Request::Stream(StreamControl::Rate { divider: 0 })),
        nack(NackReason::OutOfRange)
    );
    assert!(matches!(
        b.handle(Request::Stream(StreamControl::Rate { divider: 2 })),
        Response::Ack { .. }
    ));
    b.ticks(3);
    assert_eq!(b.queued(), vec![1000, 2000], "stopped: nothing consumed");
    assert!(matches!(
        b.handle(Request::Stream(StreamControl::Start)),
        Response::Ack { .. }
    ));
    b.ticks(4);
    assert_eq!(b.control.controller().setpoint(), 2000 << 15);
    let s = b.status();
    assert!(s.has(StatusReport::STREAMING));
    assert_eq!((s.underruns, s.queue_fill), (0, 0));
    // Dry: hold counts underruns and keeps the last setpoint.
    b.ticks(5);
    assert_eq!(b.status().underruns, 5);
    assert_eq!(b.control.controller().setpoint(), 2000 << 15);
    // Ramp to the bias: walks towards the rest position and counts.
    assert!(matches!(
        b.handle(Request::Stream(StreamControl::Underrun(
            UnderrunPolicy::RampToBias
        ))),
        Response::Ack { .. }
    ));
    let rest = b.control.controller().rest_setpoint();
    b.ticks(10);
    assert_eq!(b.status().underruns, 15);
    let d = (b.control.controller().setpoint() as i64 - rest as i64).abs();
    assert!(
        d < ((2000i64 << 15) - rest as i64).abs(),
        "moved towards rest"
    );
    b.ticks(2000);
    assert_eq!(b.control.controller().setpoint(), rest);
    assert!(matches!(
        b.handle(Request::Stream(StreamControl::Stop)),
        Response::Ack { .. }
    ));
    assert!(!b.status().has(StatusReport::STREAMING));
}

#[test]
fn a_parameter_load_is_validated_whole_and_swapped_in_between_two_ticks() {
    let mut b = board();
    b.ticks(10);
    let mut p = boot_param_set(SafeState::Zero).unwrap();
    p.mode = Mode::OpenLoop;
    assert!(matches!(
        b.handle(Request::LoadParams(p.clone())),
        Response::Ack { .. }
    ));
    // Posted, not yet applied: the tick in force still runs the old configuration.
    assert!(b.control.telemetry().config_pending);
    assert_eq!(b.control.controller().mode(), Mode::ClosedLoop);
    let s = b.status();
    assert!(s.has(StatusReport::CONFIG_PENDING) && s.mode() == Mode::OpenLoop);
    b.ticks(1);
    assert!(!b.control.telemetry().config_pending);
    // Open loop now (the feedback stays configured, idle, so a later mode switch needs no
    // new parameters).
    assert_eq!(b.control.controller().mode(), Mode::OpenLoop);
    assert_eq!(
        b.control.safe_codes(),
        (DacCode(0), DacCode(0)),
        "safe state: zero"
    );
    assert_eq!(b.handler.params(), &p);
}

#[test]
fn refused_parameter_loads_name_their_reason_and_apply_nothing() {
    let mut b = board();
    assert!(matches!(b.handle(batch(0, &[7; 20])), Response::Ack { .. }));
    let queued = b.queued();
    let params = b.handler.params().clone();
    let good = boot_param_set(SafeState::Bias).unwrap();

    let mut not_invertible = good.clone();
    if let ModelParams::PrandtlIshlinskii { weights, .. } = &mut not_invertible.model {
        weights[0] = -0.5;
    }
    assert!(matches!(
        b.handle(Request::LoadParams(not_invertible)),
        Response::Nack {
            reason: NackReason::InvalidParams(ParamError::FirstWeightNotPositive)
        }
    ));
    assert_nothing_changed(&mut b, &queued, &params);

    let mut bias_outside = good.clone();
    bias_outside.bias = 145.0;
    assert_eq!(
        b.handle(Request::LoadParams(bias_outside)),
        nack(NackReason::InvalidDrive(DriveError::BiasOutsideRange))
    );
    assert_nothing_changed(&mut b, &queued, &params);

    let mut nan = good.clone();
    nan.input_range[1] = f32::NAN;
    assert_eq!(
        b.handle(Request::LoadParams(nan)),
        nack(NackReason::InvalidParams(ParamError::EmptyInputRange))
    );
    let mut gains = good.clone();
    gains.feedback = gains.feedback.map(|f| FeedbackParams {
        kp: f32::INFINITY,
        ..f
    });
    assert_eq!(
        b.handle(Request::LoadParams(gains)),
        nack(NackReason::OutOfRange)
    );
    let mut no_gains = good.clone();
    no_gains.feedback = None; // closed loop without gains
    assert_eq!(
        b.handle(Request::LoadParams(no_gains)),
        nack(NackReason::Unsupported)
    );
    assert_nothing_changed(&mut b, &queued, &params);
    b.ticks(1);
    assert_eq!(
        b.queued().len(),
        queued.len(),
        "stopped stream: nothing consumed"
    );
}

#[test]
fn mode_changes_rebuild_the_configuration_and_closed_loop_needs_a_sensor() {
    let mut b = board();
    for mode in [Mode::Bypass, Mode::OpenLoop, Mode::ClosedLoop] {
        assert!(matches!(
            b.handle(Request::Mode(mode)),
            Response::Ack { .. }
        ));
        b.ticks(1);
        assert_eq!(b.status().mode(), mode);
        assert_eq!(b.handler.params().mode, mode);
    }
    // A board without a sensor boots open loop and refuses closed loop.
    let mut profile = board_profile(RATE as f64);
    profile.sensor = None;
    let mut open = boot_param_set(SafeState::Bias).unwrap();
    open.mode = Mode::OpenLoop;
    let (handler, tick) = CommandHandler::new(
        profile,
        BoardSettings::DEFAULT,
        open.clone(),
        RamStorage::default(),
    )
    .unwrap();
    let mut b = Board {
        handler,
        control: ControlLoop::new(tick, RATE, vec![0; 16]),
        queue: Box::leak(Box::new(SetpointQueue::new())),
        dac: RecordingDac::default(),
        adc: FixedAdc(Some(AdcCode(0))),
    };
    assert_eq!(
        b.handle(Request::Mode(Mode::ClosedLoop)),
        nack(NackReason::Unsupported)
    );
    assert_nothing_changed(&mut b, &[], &open);
}

#[test]
fn store_and_recall_round_trip_through_the_storage_and_refuse_when_they_cannot() {
    let mut b = board();
    assert_eq!(
        b.handle(Request::RecallParams),
        nack(NackReason::NothingStored)
    );
    let mut p = boot_param_set(SafeState::Bias).unwrap();
    p.bias = 60.0;
    p.mode = Mode::Bypass;
    assert!(matches!(
        b.handle(Request::LoadParams(p.clone())),
        Response::Ack { .. }
    ));
    assert!(matches!(
        b.handle(Request::StoreParams),
        Response::Ack { .. }
    ));
    assert!(matches!(
        b.handle(Request::Mode(Mode::OpenLoop)),
        Response::Ack { .. }
    ));
    assert!(matches!(
        b.handle(Request::RecallParams),
        Response::Ack { .. }
    ));
    assert_eq!(b.handler.params(), &p);
    // A board booting on that storage starts on the stored set, not the defaults.
    let storage = b.handler.storage().clone();
    let mut again = board_with(storage, board_profile(RATE as f64));
    assert_eq!(again.handler.params(), &p);
    assert!(!again.status().has(StatusReport::DEFAULTS));
    assert!(board().status().has(StatusReport::DEFAULTS));
    // Storing while the stream runs would stall the tick: refused.
    assert!(matches!(
        b.handle(Request::Stream(StreamControl::Start)),
        Response::Ack { .. }
    ));
    assert_eq!(b.handle(Request::StoreParams), nack(NackReason::Busy));
    // Read-only and failing storage.
    let mut ro = board_with(ReadOnlyStorage(&[0xFF; 64]), board_profile(RATE as f64));
    assert_eq!(
        ro.handle(Request::StoreParams),
        nack(NackReason::Unsupported)
    );
    let mut broken = board_with(BrokenFlash([0xFF; 16]), board_profile(RATE as f64));
    assert_eq!(
        broken.handle(Request::StoreParams),
        nack(NackReason::StoreFailed)
    );
}

#[test]
fn the_waveform_generator_runs_and_out_of_range_waveforms_are_refused() {
    let mut b = board();
    let w = |frequency_mhz, amplitude| {
        Request::Waveform(Waveform {
            shape: WaveShape::Triangle,
            offset: 0,
            amplitude,
            frequency_mhz,
        })
    };
    assert_eq!(b.handle(w(30_000_000, 1000)), nack(NackReason::OutOfRange)); // 30 kHz ≥ Nyquist
    assert_eq!(b.handle(w(0, 1000)), nack(NackReason::OutOfRange));
    assert!(!b.status().has(StatusReport::WAVEFORM));
    assert!(matches!(b.handle(w(750_000, 16384)), Response::Ack { .. }));
    assert!(b.status().has(StatusReport::WAVEFORM));
    // 750 Hz at 50 kHz: the triangle's crest (offset + amplitude) after a quarter period.
    let mut top = i32::MIN;
    for _ in 0..(50_000 / 750) {
        b.ticks(1);
        top = top.max(b.control.controller().setpoint());
    }
    assert!(
        (top - (16384 << 15)).abs() < (16384 << 15) / 50,
        "crest {top}"
    );
    assert!(matches!(
        b.handle(Request::Stream(StreamControl::Stop)),
        Response::Ack { .. }
    ));
    assert!(!b.status().has(StatusReport::WAVEFORM));
}

#[test]
fn the_recorder_captures_the_chosen_signal_and_reads_back_in_chunks() {
    let mut b = board();
    let arm = |signal, count, decimation| {
        Request::Record(RecordRequest {
            signal,
            count,
            decimation,
        })
    };
    assert_eq!(
        b.handle(arm(Signal::Drive, 0, 1)),
        nack(NackReason::OutOfRange)
    );
    assert_eq!(
        b.handle(arm(Signal::Drive, 10, 0)),
        nack(NackReason::OutOfRange)
    );
    assert_eq!(
        b.handle(arm(Signal::Drive, 5000, 1)),
        nack(NackReason::OutOfRange)
    );
    assert_eq!(
        b.handle(Request::ReadRecord { offset: 1 }),
        nack(NackReason::OutOfRange)
    );
    // Bypass, so the sensor is read for the recorder only.
    assert!(matches!(
        b.handle(Request::Mode(Mode::Bypass)),
        Response::Ack { .. }
    ));
    assert!(matches!(
        b.handle(arm(Signal::Sensor, 100, 3)),
        Response::Ack { .. }
    ));
    b.ticks(150);
    let s = b.status();
    assert_eq!(s.recorded, 50);
    assert!(s.has(StatusReport::RECORDING));
    b.ticks(200);
    assert_eq!(b.status().recorded, 100);
    let mut all = Vec::new();
    while all.len() < 100 {
        match b.handle(Request::ReadRecord {
            offset: all.len() as u32,
        }) {
            Response::RecordChunk { offset, values } => {
                assert_eq!(offset as usize, all.len());
                assert!(values.len() <= MAX_CHUNK);
                all.extend(values);
            }
            r => panic!("{r:?}"),
        }
    }
    // Code 2048 of 4096 over 0…70 µm is mid-stroke: normalised 0.
    assert!(all.iter().all(|&v| v == 0), "{all:?}");
    assert_eq!(
        b.handle(Request::ReadRecord { offset: 100 }),
        Response::RecordChunk {
            offset: 100,
            values: heapless::Vec::new()
        }
    );
}

#[test]
fn every_frame_error_is_nacked_with_its_reason_and_counted() {
    let mut b = board();
    assert!(matches!(b.handle(batch(0, &[3; 4])), Response::Ack { .. }));
    let params = b.handler.params().clone();
    let raw = |body: &[u8]| {
        use twinstack::protocol::{cobs, frame::FRAME_CRC};
        let mut v = body.to_vec();
        v.extend(FRAME_CRC.checksum(body).to_le_bytes());
        let mut out = vec![0u8; cobs::max_encoded_len(v.len()) + 1];
        let n = cobs::encode(&v, &mut out).unwrap();
        out.truncate(n);
        out.push(0);
        out
    };
    let mut corrupt = encoded(&batch(1, &[4; 8]));
    corrupt[5] ^= 0x22;
    let mut oversize = vec![0x41u8; MAX_ENCODED + 10];
    oversize.push(0);
    let cases: Vec<(Vec<u8>, FrameError)> = vec![
        (corrupt, FrameError::BadCrc),
        (oversize, FrameError::Oversize),
        (vec![0x02, 0x07, 0x00], FrameError::Truncated),
        (vec![0x09, 0x01, 0x00], FrameError::BadStuffing),
        (
            raw(&[PROTOCOL_VERSION + 1, 0]),
            FrameError::BadVersion {
                got: PROTOCOL_VERSION + 1,
            },
        ),
        (raw(&[PROTOCOL_VERSION, 99]), FrameError::UnknownType),
        (raw(&[PROTOCOL_VERSION, 0, 1]), FrameError::Malformed),
    ];
    for (bytes, reason) in cases {
        assert_eq!(b.bytes(&bytes), vec![nack(NackReason::Frame(reason))]);
        assert_nothing_changed(&mut b, &[3; 4], &params);
    }
    let s = b.status();
    assert_eq!((s.crc_errors, s.frame_errors, s.next_seq), (1, 6, 1));
    // Junk without a delimiter, then a good frame after one: resynchronised.
    let mut bytes = vec![0x13u8; 40];
    bytes.push(0);
    bytes.extend(encoded(&batch(1, &[4; 8])));
    assert_eq!(
        b.bytes(&bytes),
        vec![
            nack(NackReason::Frame(FrameError::BadStuffing)),
            Response::Ack {
                credits: SETPOINT_CAPACITY as u16 - 12
            }
        ]
    );
}

// ---- Fuzz: random bytes and mutated valid frames into the handler ----

use proptest::prelude::*;

fn any_request() -> impl Strategy<Value = Request> {
    let samples = prop::collection::vec(any::<i16>(), 0..=MAX_BATCH);
    prop_oneof![
        Just(Request::Status),
        (0u16..4, samples).prop_map(|(seq, s)| batch(seq, &s)),
        prop_oneof![
            Just(StreamControl::Start),
            Just(StreamControl::Stop),
            any::<u16>().prop_map(|divider| StreamControl::Rate { divider }),
            Just(StreamControl::Underrun(UnderrunPolicy::RampToBias)),
        ]
        .prop_map(Request::Stream),
        prop_oneof![
            Just(Mode::Bypass),
            Just(Mode::OpenLoop),
            Just(Mode::ClosedLoop)
        ]
        .prop_map(Request::Mode),
        (any::<i16>(), any::<i16>(), any::<u32>()).prop_map(|(offset, amplitude, f)| {
            Request::Waveform(Waveform {
                shape: WaveShape::Sine,
                offset,
                amplitude,
                frequency_mhz: f,
            })
        }),
        (any::<u32>(), any::<u16>()).prop_map(|(count, decimation)| {
            Request::Record(RecordRequest {
                signal: Signal::Estimate,
                count: count % 5000,
                decimation: decimation % 4,
            })
        }),
        any::<u32>().prop_map(|o| Request::ReadRecord { offset: o % 200 }),
        (-10.0f32..160.0, -1.0f32..1.0).prop_map(|(bias, w)| {
            let mut p = boot_param_set(SafeState::Bias).unwrap();
            p.bias = bias;
            if let ModelParams::PrandtlIshlinskii { weights, .. } = &mut p.model {
                weights[1] = w;
            }
            Request::LoadParams(p)
        }),
        Just(Request::StoreParams),
        Just(Request::RecallParams),
    ]
}

/// A piece of input: junk, a valid frame, or a valid frame with bytes changed or cut.
fn any_chunk() -> impl Strategy<Value = Vec<u8>> {
    prop_oneof![
        prop::collection::vec(any::<u8>(), 0..300),
        any_request().prop_map(|r| encoded(&r)),
        (any_request(), any::<prop::sample::Index>(), any::<u8>()).prop_map(|(r, at, x)| {
            let mut f = encoded(&r);
            let i = at.index(f.len());
            f[i] ^= x;
            f
        }),
        (any_request(), any::<prop::sample::Index>()).prop_map(|(r, at)| {
            let mut f = encoded(&r);
            f.truncate(at.index(f.len()));
            f
        }),
    ]
}

proptest! {
    // Bounded so CI spends seconds here; deterministic (work is counted, not timed).
    #![proptest_config(ProptestConfig { cases: 96, ..ProptestConfig::default() })]

    /// Whatever arrives: no panic, one well-formed response per frame, at most
    /// `MAX_ENCODED + 1` decoder steps for any byte and two per byte on average, and the
    /// queue's fill and credits always add up to its capacity.
    #[test]
    fn fuzz_any_input_gets_one_response_per_frame_with_bounded_work(
        chunks in prop::collection::vec(any_chunk(), 1..24),
    ) {
        let mut b = board();
        let bytes: Vec<u8> = chunks.concat();
        let (mut frames, mut run) = (0usize, 0usize);
        let mut responses = 0usize;
        let mut worst = 0u32;
        let start = b.handler.decoder_steps();
        for (i, &byte) in bytes.iter().enumerate() {
            if byte == 0 {
                if run > 0 {
                    frames += 1;
                }
                run = 0;
            } else {
                run += 1;
            }
            let before = b.handler.decoder_steps();
            responses += b.bytes(&[byte]).len(); // each response decodes (or the test fails)
            worst = worst.max(b.handler.decoder_steps().wrapping_sub(before));
            if i % 50 == 0 {
                b.ticks(1);
            }
        }
        prop_assert_eq!(responses, frames);
        prop_assert!(worst as usize <= MAX_ENCODED + 1, "one byte cost {} steps", worst);
        let total = b.handler.decoder_steps().wrapping_sub(start) as usize;
        prop_assert!(total <= 2 * bytes.len(), "{} steps for {} bytes", total, bytes.len());
        let s = b.status();
        prop_assert_eq!(s.queue_fill as usize + s.credits as usize, SETPOINT_CAPACITY);
        prop_assert_eq!(s.queue_fill as usize, b.queued().len());
    }
}
