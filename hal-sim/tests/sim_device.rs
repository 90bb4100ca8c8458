//! The in-process board ([`SimDevice`]) driven over its [`Transport`] as the host drives the
//! real one: frames in, one response frame per request, simulated UART timing.

use std::time::Duration;

use hal_sim::sim_device::{SimDevice, SimDeviceConfig};
use twinstack::config::settings::{Mode, Model};
use twinstack::control_loop::SETPOINT_CAPACITY;
use twinstack::protocol::decoder::FrameDecoder;
use twinstack::protocol::frame::{self, MAX_ENCODED};
use twinstack::protocol::messages::*;
use twinstack::refusal::{Field, ModelField, Refusal, Rule};
use twinstack_link::Transport;

/// A stop-and-wait client: one request, one response.
struct Client {
    dev: SimDevice,
    decoder: FrameDecoder,
}

impl Client {
    fn new(config: SimDeviceConfig) -> Self {
        Self {
            dev: SimDevice::new(config).expect("device"),
            decoder: FrameDecoder::new(),
        }
    }

    fn send_raw(&mut self, bytes: &[u8]) {
        self.dev.send(bytes).unwrap();
    }

    fn send(&mut self, req: &Request) {
        let mut out = [0u8; MAX_ENCODED + 1];
        let n = frame::encode(req, &mut out).expect("fits a frame");
        self.send_raw(&out[..n]);
    }

    /// The next response frame (within 50 ms of simulated time).
    fn response(&mut self) -> Response {
        let mut buf = [0u8; 64];
        loop {
            let n = self
                .dev
                .receive(&mut buf, Duration::from_millis(50))
                .unwrap();
            assert!(n > 0, "no response within 50 ms");
            let mut body = None;
            for (i, &b) in buf[..n].iter().enumerate() {
                if let Some(r) = self.decoder.push(b) {
                    assert_eq!(i, n - 1, "one response at a time");
                    body = Some(r.map(|s| s.to_vec()).expect("response frame sound"));
                }
            }
            if let Some(body) = body {
                return frame::decode_body(&body).expect("response decodes");
            }
        }
    }

    fn request(&mut self, req: &Request) -> Response {
        self.send(req);
        self.response()
    }

    fn status(&mut self) -> StatusReport {
        match self.request(&Request::Status) {
            Response::Status(s) => s,
            other => panic!("not a status: {other:?}"),
        }
    }
}

fn batch(seq: u16, samples: &[i16]) -> Request {
    Request::Setpoints(SetpointBatch {
        seq,
        samples: twinstack::heapless::Vec::from_slice(samples).unwrap(),
    })
}

/// Streams `samples` in batches within the credits; returns the batches sent.
fn stream(c: &mut Client, samples: &[i16], start_after: usize) -> u16 {
    let mut credits = SETPOINT_CAPACITY;
    let mut seq = 0u16;
    for (i, chunk) in samples.chunks(MAX_BATCH).enumerate() {
        // Wait for room (the credits only grow while the tick drains the queue).
        while chunk.len() > credits {
            credits = c.status().credits as usize;
        }
        match c.request(&batch(seq, chunk)) {
            Response::Ack { credits: k } => credits = k as usize,
            other => panic!("batch {seq} refused: {other:?}"),
        }
        seq += 1;
        if i + 1 == start_after {
            assert_eq!(
                c.request(&Request::Stream(StreamControl::Start)),
                Response::Ack {
                    credits: credits as u16
                }
            );
        }
    }
    seq
}

#[test]
fn a_stream_within_the_credits_runs_without_underrun_and_the_output_follows() {
    let mut c = Client::new(SimDeviceConfig::paper());
    // 0.41 s of a 25 Hz sine over ±0.8 of the stroke, one setpoint per tick (50 000 /s),
    // ending on its crest.
    let n = 20_500;
    let samples: Vec<i16> = (0..n)
        .map(|k| {
            let x = 0.8 * (2.0 * std::f64::consts::PI * 25.0 * k as f64 / 50_000.0).sin();
            (x * 32767.0).round() as i16
        })
        .collect();
    assert_eq!(
        c.request(&Request::Record(RecordRequest {
            signal: Signal::Setpoint,
            count: 1000,
            decimation: 20,
        })),
        Response::Ack {
            credits: SETPOINT_CAPACITY as u16
        }
    );
    let batches = stream(&mut c, &samples, 4);
    let s = c.status();
    assert_eq!(s.next_seq, batches);
    assert_eq!(s.underruns, 0, "{s:?}");
    // Let the queue drain; then the stream runs dry and underruns are counted (hold).
    c.dev.run_for(
        Duration::from_secs_f64(s.queue_fill as f64 / 50_000.0) + Duration::from_millis(30),
    );
    let s = c.status();
    assert_eq!(s.queue_fill, 0);
    assert!(s.underruns > 0, "{s:?}");
    assert!(s.has(StatusReport::STREAMING));

    // The recorder saw the stream's setpoints, in order, exactly (Q1.15 << 15).
    let mut recorded = Vec::new();
    while recorded.len() < 1000 {
        match c.request(&Request::ReadRecord {
            offset: recorded.len() as u32,
        }) {
            Response::RecordChunk { offset, values } => {
                assert_eq!(offset as usize, recorded.len());
                assert!(!values.is_empty());
                recorded.extend_from_slice(&values);
            }
            other => panic!("{other:?}"),
        }
    }
    // Find where the stream started in the record, then every 20th sample follows.
    let first = recorded
        .iter()
        .position(|&v| v != recorded[0])
        .expect("the setpoint moved");
    let k0 = samples
        .iter()
        .position(|&s| (s as i32) << 15 == recorded[first])
        .unwrap();
    for (j, &v) in recorded[first..].iter().enumerate() {
        let k = k0 + 20 * j;
        if k < samples.len() {
            assert_eq!(v, (samples[k] as i32) << 15, "recorded value {j}");
        }
    }
    // The output followed: held on the last setpoint (0.8), bypass puts the left stack at
    // 70 + 0.8 · 70 V and the right at 70 − 0.8 · 70 V (12-bit DAC, 150 V amplifier).
    let [left, right] = c.dev.board().amplifier_volts();
    assert!(
        (left - 126.0).abs() < 0.5 && (right - 14.0).abs() < 0.5,
        "{left} {right}"
    );
    let x_rest = {
        let rest = Client::new(SimDeviceConfig::paper());
        rest.dev.board().plant().stage_um()
    };
    let x = c.dev.board().plant().stage_um();
    assert!(
        (x - x_rest).abs() > 5.0,
        "stage at {x} µm, rest {x_rest} µm"
    );
}

#[test]
fn out_of_sequence_and_over_credit_batches_are_refused_and_nothing_queued_is_lost() {
    let mut c = Client::new(SimDeviceConfig::paper());
    assert!(matches!(
        c.request(&batch(0, &[1; 90])),
        Response::Ack { credits } if credits as usize == SETPOINT_CAPACITY - 90
    ));
    assert_eq!(
        c.request(&batch(5, &[2; 10])),
        Response::Nack {
            reason: NackReason::OutOfSequence { expected: 1 }
        }
    );
    // Full batches until less than one fits: 90 + k·96 queued, 37 free.
    let k = ((SETPOINT_CAPACITY - 90) / 96) as u16;
    assert_eq!((SETPOINT_CAPACITY - 90) % 96, 37);
    for seq in 1..=k {
        assert!(matches!(
            c.request(&batch(seq, &[3; 96])),
            Response::Ack { .. }
        ));
    }
    let queued = 90 + k * 96;
    // A full batch is refused, whole.
    assert_eq!(
        c.request(&batch(k + 1, &[4; 96])),
        Response::Nack {
            reason: NackReason::QueueFull
        }
    );
    let s = c.status();
    assert_eq!((s.queue_fill, s.credits, s.next_seq), (queued, 37, k + 1));
    // A corrupted frame is NACKed and counted; the next one is handled.
    let mut out = [0u8; MAX_ENCODED + 1];
    let n = frame::encode(&batch(k + 1, &[5; 8]), &mut out).unwrap();
    out[3] ^= 0x10;
    c.send_raw(&out[..n]);
    assert_eq!(
        c.response(),
        Response::Nack {
            reason: NackReason::Frame(frame::FrameError::BadCrc)
        }
    );
    assert!(matches!(
        c.request(&batch(k + 1, &[5; 8])),
        Response::Ack { credits: 29 }
    ));
    assert_eq!(c.status().crc_errors, 1);
}

#[test]
fn a_parameter_load_takes_effect_between_ticks_and_a_bad_one_changes_nothing() {
    let mut c = Client::new(SimDeviceConfig::paper());
    let ticks_before = c.dev.ticks();
    let mut bad = SimDeviceConfig::paper_settings(Mode::OpenLoop);
    if let Some(Model::PrandtlIshlinskii(p)) = &mut bad.compensator {
        p.weights[0] = -0.1; // not invertible
    }
    assert_eq!(
        c.request(&Request::LoadParams(bad)),
        Response::Nack {
            reason: NackReason::Refused(Refusal::new(
                Field::Compensator(ModelField::Weight(1)),
                Rule::NotInvertible
            ))
        }
    );
    assert_eq!(c.status().mode(), Mode::Bypass);
    let good = SimDeviceConfig::paper_settings(Mode::OpenLoop);
    assert!(matches!(
        c.request(&Request::LoadParams(good.clone())),
        Response::Ack { .. }
    ));
    let s = c.status();
    assert_eq!(s.mode(), Mode::OpenLoop);
    assert!(c.dev.ticks() > ticks_before);
    // Open loop runs (the tick's controller refuses it without a compensator), and the
    // settings read back are the ones loaded.
    assert_eq!(c.dev.control().controller().mode(), Mode::OpenLoop);
    assert_eq!(
        c.request(&Request::ReadParams),
        Response::Params(good.clone())
    );
    // Store, then switch, then recall: the stored settings are back, in the stored mode.
    assert!(matches!(
        c.request(&Request::StoreParams {
            boot_mode: Mode::OpenLoop
        }),
        Response::Ack { .. }
    ));
    assert!(matches!(
        c.request(&Request::Mode(Mode::Bypass)),
        Response::Ack { .. }
    ));
    assert_eq!(c.status().mode(), Mode::Bypass);
    assert!(matches!(
        c.request(&Request::RecallParams),
        Response::Ack { .. }
    ));
    assert_eq!(c.status().mode(), Mode::OpenLoop);
    assert_eq!(c.dev.handler().settings(), &good);
}

/// A watchdog drill is accepted only on an idle board, so that its reset cuts off no motion;
/// until the reset, a source start is refused and an input edge armed before the drill starts
/// nothing: the outputs hold where they are up to the reset. (A waveform started after the
/// drill was once cut off by the reset mid-swing.)
#[test]
fn a_watchdog_drill_refuses_source_starts_until_the_reset() {
    use twinstack::sources::analog_input::{AnalogInputConfig, AnalogRequest, OnFault};
    use twinstack::sources::scan::{
        RasterScan, ScanPattern, ScanRequest, TriggerConfig, TriggerEdge,
    };
    use twinstack::sources::sequence::{SequenceConfig, SequenceRequest};

    let mut dev = SimDevice::new(SimDeviceConfig::paper()).expect("device");
    assert!(matches!(
        dev.handle(&Request::Mode(Mode::OpenLoop)),
        Response::Ack { .. }
    ));
    // An input edge armed to start the stream, before the drill.
    let arm_stream = Request::Trigger(TriggerConfig {
        pulse_ticks: 2,
        input: TriggerEdge::Rising,
        start_stream: true,
    });
    assert!(matches!(dev.handle(&arm_stream), Response::Ack { .. }));
    assert!(matches!(
        dev.handle(&Request::WatchdogDrill),
        Response::Ack { .. }
    ));
    let starts = [
        Request::Stream(StreamControl::Start),
        Request::Waveform(Waveform {
            shape: WaveShape::Sine,
            offset: 0,
            amplitude: 12_000,
            frequency_mhz: 250_000,
            decay: None,
        }),
        Request::Scan(ScanRequest {
            pattern: ScanPattern::Raster(RasterScan::centred(4, 16, 20, 0.5)),
            ticks_per_pixel: 4,
            frames: 1,
            on_trigger: false,
        }),
        Request::Sequence(SequenceRequest::Arm(SequenceConfig {
            edge: TriggerEdge::Rising,
            window: 0.05,
            settle_ticks: 10,
        })),
        Request::Analog(AnalogRequest::Start(AnalogInputConfig {
            gain: 2.0,
            offset: -1.0,
            corner_hz: None,
            lost_below: 0.0,
            over_above: 1.0,
            on_fault: OnFault::Hold,
            rate: 10.0,
            start_at_boot: false,
        })),
        arm_stream,
    ];
    for start in &starts {
        assert_eq!(
            dev.handle(start),
            Response::Nack {
                reason: NackReason::Busy
            },
            "{start:?} during a drill"
        );
    }
    // The armed edge comes: the stream stays off, the outputs hold.
    dev.tick();
    let before = dev.last_report().expect("a tick");
    dev.set_trigger_input(true);
    for _ in 0..100 {
        dev.tick();
        assert!(
            !dev.control().is_running(),
            "a source started during a drill"
        );
        let r = dev.last_report().expect("a tick");
        assert_eq!((r.left, r.right), (before.left, before.right));
    }
    // After the reset the board takes source starts again.
    dev.run_for(Duration::from_millis(u64::from(
        twinstack::board::WATCHDOG_TIMEOUT_MS,
    )));
    assert!(dev.control().feeds_watchdog(), "the board was reset");
    assert!(matches!(
        dev.handle(&Request::Stream(StreamControl::Start)),
        Response::Ack { .. }
    ));
}

/// A script's order (as the Python package's tests and a lab's scripts do it): open loop, the
/// learning configured and switched on over the stage at rest, then the waveform it is for,
/// started after however long the link took. At rest the 12-bit sensor reads errors of zero
/// or one code, and the learning goes on through every wait (its guard does not take that
/// noise for a divergence); once the motion starts it learns it.
#[test]
fn a_learning_switched_on_at_rest_is_still_on_when_its_motion_starts() {
    use twinstack::services::learning::{LearnSettings, LearnState};
    let period = 200u16;
    for rest_periods in [0u64, 3, 6, 9, 12, 20, 40] {
        let mut dev = SimDevice::new(SimDeviceConfig::paper()).unwrap();
        for request in [
            Request::Mode(Mode::OpenLoop),
            Request::Learn(LearnRequest::Configure(LearnSettings::for_period(period))),
            Request::Learn(LearnRequest::Reset),
            Request::Learn(LearnRequest::State(LearnState::Learning)),
        ] {
            assert!(
                matches!(dev.handle(&request), Response::Ack { .. }),
                "{request:?}"
            );
        }
        for _ in 0..rest_periods * u64::from(period) + 37 {
            dev.tick();
        }
        let at_rest = dev.handler().learning().updates();
        assert!(
            matches!(
                dev.handle(&Request::Waveform(Waveform {
                    shape: WaveShape::Sine,
                    offset: 0,
                    amplitude: 16_384,
                    frequency_mhz: 750_000,
                    decay: None,
                })),
                Response::Ack { .. }
            ),
            "{rest_periods}"
        );
        for _ in 0..50 * u64::from(period) {
            dev.tick();
        }
        let task = dev.handler().learning();
        assert_eq!(
            task.guard_stops(),
            0,
            "after {rest_periods} periods at rest"
        );
        assert_eq!(
            dev.control().learning().state(),
            LearnState::Learning,
            "{rest_periods}"
        );
        assert!(task.updates() >= at_rest + 49, "{rest_periods}");
    }
}
