//! The board under a protocol fuzzer that knows the frame format: frames of **every** request
//! type with any field values (a valid request of each type, its encoded fields mutated and
//! the CRC recomputed, so that the frame gets past the CRC to the handler), junk, cut and
//! corrupted frames, sent at random moments to the in-process board (the firmware's command
//! handler, tick, telemetry packer and learning service, over the modelled UART) while it
//! runs whatever it was last told. Whatever arrives:
//! - nothing panics, and every frame gets exactly one response (telemetry frames aside);
//! - every tick keeps both stacks inside the voltage limits of some settings the board
//!   accepted, and no DAC step exceeds the largest slew limit the board accepted, from one
//!   tick to the next of the same boot: a watchdog reset (after a drill, never otherwise) is a
//!   discontinuity the firmware does not drive (the MCU's reset turns the DAC off until the
//!   booted firmware starts it at its boot codes), so no slew is measured across it;
//! - the setpoint queue's fill and credits add up to its capacity.
//!
//! `tests/command_handler.rs` fuzzes the handler alone, with a fixed handful of request types.

use std::time::Duration;

use hal_sim::coarse_rig::{DualStageDevice, DualStageDeviceConfig};
use hal_sim::converters::{
    AnalogDualDac, AnalogSensorAdc, EmulatedAds8689, EmulatedDac856x, InternalAdc, InternalDac,
};
use hal_sim::sim_device::{SimDevice, SimDeviceConfig};
use proptest::prelude::*;
use twinstack::config::settings::Mode;
use twinstack::control_loop::SETPOINT_CAPACITY;
use twinstack::protocol::decoder::FrameDecoder;
use twinstack::protocol::frame::{self, MAX_ENCODED};
use twinstack::protocol::messages::*;
use twinstack::services::learning::{LearnSettings, LearnState};
use twinstack::services::recorder::{Signal, Trigger};
use twinstack::sources::scan::{
    LissajousScan, RasterScan, ScanPattern, ScanRequest, SpiralScan, TriggerConfig, TriggerEdge,
};
use twinstack::sources::setpoint_stream::UnderrunPolicy;
use twinstack_link::Transport;

/// The dual-stage board's converters (external, on SPI).
type DualDacs = twinstack::converters::Dac856x<EmulatedDac856x>;
type DualAdc = twinstack::converters::Ads8689<EmulatedAds8689>;

/// One valid request of every type (and of every variant of the nested requests), the
/// seeds the mutations start from.
fn seeds() -> Vec<Request> {
    let open = SimDeviceConfig::paper_settings(Mode::OpenLoop);
    let mut closed = SimDeviceConfig::paper_settings(Mode::ClosedLoop);
    closed.drive.bias = 40.0;
    vec![
        Request::Status,
        Request::Setpoints(SetpointBatch {
            seq: 0,
            samples: heapless::Vec::from_slice(&[0, 8000, -8000, 32767, -32768, 100]).unwrap(),
        }),
        Request::Stream(StreamControl::Start),
        Request::Stream(StreamControl::Stop),
        Request::Stream(StreamControl::Rate { divider: 7 }),
        Request::Stream(StreamControl::Underrun(UnderrunPolicy::RampToBias)),
        Request::Stream(StreamControl::Underrun(UnderrunPolicy::Hold)),
        Request::Mode(Mode::Bypass),
        Request::Mode(Mode::OpenLoop),
        Request::Mode(Mode::ClosedLoop),
        Request::LoadParams(open),
        Request::LoadParams(closed),
        Request::StoreParams {
            boot_mode: Mode::OpenLoop,
        },
        Request::RecallParams,
        Request::Waveform(Waveform {
            shape: WaveShape::Sine,
            offset: 0,
            amplitude: 12_000,
            frequency_mhz: 250_000,
            decay: Some(WaveDecay {
                hold_cycles: 2,
                keep: 30_000,
            }),
        }),
        Request::Record(RecordRequest {
            signal: Signal::Drive,
            count: 300,
            decimation: 1,
        }),
        Request::ReadRecord { offset: 0 },
        Request::ReadParams,
        Request::Capture(CaptureRequest {
            signals: 0x7f,
            samples: 200,
            pre_trigger: 20,
            trigger: Trigger::StreamStart,
            decimation: 2,
        }),
        Request::CaptureStatus,
        Request::ReadCapture {
            offset: 0,
            count: 256,
        },
        Request::Telemetry(TelemetryRequest::Start {
            signals: 0x0b,
            decimation: 25,
        }),
        Request::Telemetry(TelemetryRequest::Stop),
        Request::CoarseHome,
        Request::CoarseMove(CoarseMove {
            target_mm: 1.0,
            velocity_mm_s: 2.0,
            acceleration_mm_s2: 10.0,
        }),
        Request::CoarseJog { velocity_mm_s: 1.0 },
        Request::CoarseStop,
        Request::CoarseStatus,
        Request::Learn(LearnRequest::Configure(LearnSettings::for_period(500))),
        Request::Learn(LearnRequest::State(LearnState::Learning)),
        Request::Learn(LearnRequest::State(LearnState::Frozen)),
        Request::Learn(LearnRequest::Reset),
        Request::Learn(LearnRequest::Status),
        Request::Learn(LearnRequest::ReadTable { offset: 0 }),
        Request::Learn(LearnRequest::WriteTable {
            offset: 0,
            values: heapless::Vec::from_slice(&[1 << 20, -(1 << 20), 0, i32::MAX]).unwrap(),
        }),
        Request::Learn(LearnRequest::PostTable),
        Request::Scan(ScanRequest {
            pattern: ScanPattern::Raster(RasterScan::centred(4, 16, 20, 0.5)),
            ticks_per_pixel: 4,
            frames: 1,
            on_trigger: false,
        }),
        Request::Trigger(TriggerConfig {
            pulse_ticks: 2,
            input: TriggerEdge::Rising,
            start_stream: true,
        }),
        Request::Scan(ScanRequest {
            pattern: ScanPattern::Lissajous(LissajousScan {
                frame_hz: 20.0,
                x_cycles: 4,
                y_cycles: 5,
                y_phase_deg: 90.0,
                offset: 0.0,
                amplitude: 0.5,
                y_offset: 0.0,
                y_amplitude: 0.5,
            }),
            ticks_per_pixel: 4,
            frames: 2,
            on_trigger: true,
        }),
        Request::Scan(ScanRequest {
            pattern: ScanPattern::Spiral(SpiralScan {
                turn_hz: 100.0,
                turns: 6,
                offset: 0.1,
                amplitude: 0.6,
                y_offset: 0.0,
            }),
            ticks_per_pixel: 4,
            frames: 0,
            on_trigger: false,
        }),
        Request::PackedSetpoints(PackedBatch {
            seq: 1,
            samples: heapless::Vec::from_slice(&[0, 16_000, -16_000, 32_767, -32_768, 7]).unwrap(),
        }),
        Request::Sequence(SequenceRequest::Arm(SequenceConfig {
            edge: TriggerEdge::Rising,
            window: 0.01,
            settle_ticks: 3,
        })),
        Request::Sequence(SequenceRequest::Stop),
        Request::Sequence(SequenceRequest::Status),
        Request::Analog(AnalogRequest::Start(AnalogInputConfig {
            gain: 2.0,
            offset: -1.0,
            corner_hz: Some(500.0),
            lost_below: 0.02,
            over_above: 0.98,
            on_fault: OnFault::RampToRest,
            rate: 10.0,
            start_at_boot: false,
        })),
        Request::Analog(AnalogRequest::Stop),
        Request::Analog(AnalogRequest::Status),
        Request::Echo(heapless::Vec::from_slice(&[1, 2, 3, 0, 255]).unwrap()),
        // The dual-stage board hands the piezo back to the sources above, and its moves take
        // it again.
        Request::CoarseRelease,
    ]
}

/// A frame around `message` (postcard bytes, tag first) with a correct CRC.
fn framed(message: &[u8]) -> Vec<u8> {
    let mut out = vec![0u8; MAX_ENCODED + 1];
    let n = frame::encode_message_bytes(message, &mut out).expect("a message fits a frame");
    out.truncate(n);
    out
}

fn encoded(r: &Request) -> Vec<u8> {
    let mut out = vec![0u8; MAX_ENCODED + 1];
    let n = frame::encode(r, &mut out).expect("a seed fits a frame");
    out.truncate(n);
    out
}

/// The message bytes (tag first) inside a seed's frame.
fn message_of(seed: &[u8]) -> Vec<u8> {
    let mut d = FrameDecoder::new();
    for &b in seed {
        if let Some(body) = d.push(b) {
            let body = body.expect("a seed's frame is sound");
            return frame::message_bytes(body)
                .expect("a seed's frame checks")
                .to_vec();
        }
    }
    panic!("a seed is one frame")
}

/// One change to a message's bytes.
#[derive(Clone, Debug)]
enum Mutation {
    Set(prop::sample::Index, u8),
    Insert(prop::sample::Index, u8),
    Remove(prop::sample::Index),
}

fn any_mutation() -> impl Strategy<Value = Mutation> {
    // Boundary bytes half the time: varint edges, bools and enum tags just out of range.
    let byte = prop_oneof![
        any::<u8>(),
        prop::sample::select(vec![0u8, 1, 2, 3, 0x7f, 0x80, 0xfe, 0xff])
    ];
    prop_oneof![
        3 => (any::<prop::sample::Index>(), byte.clone()).prop_map(|(i, b)| Mutation::Set(i, b)),
        1 => (any::<prop::sample::Index>(), byte).prop_map(|(i, b)| Mutation::Insert(i, b)),
        1 => any::<prop::sample::Index>().prop_map(Mutation::Remove),
    ]
}

/// What the fuzzer sends next.
#[derive(Clone, Debug)]
enum Chunk {
    /// A seed as it is.
    Valid(usize),
    /// A seed with its fields mutated, the CRC made to match.
    Mutated(usize, Vec<Mutation>),
    /// A seed's frame cut short (no delimiter: the next chunk's bytes run on into it).
    Cut(usize, prop::sample::Index),
    /// A seed's frame with one byte flipped after the CRC was taken.
    Corrupt(usize, prop::sample::Index, u8),
    /// Junk.
    Junk(Vec<u8>),
}

fn any_chunk(n: usize) -> impl Strategy<Value = Chunk> {
    prop_oneof![
        2 => (0..n).prop_map(Chunk::Valid),
        6 => (0..n, prop::collection::vec(any_mutation(), 1..4))
            .prop_map(|(i, m)| Chunk::Mutated(i, m)),
        1 => (0..n, any::<prop::sample::Index>()).prop_map(|(i, at)| Chunk::Cut(i, at)),
        1 => (0..n, any::<prop::sample::Index>(), 1u8..=255)
            .prop_map(|(i, at, x)| Chunk::Corrupt(i, at, x)),
        1 => prop::collection::vec(any::<u8>(), 0..64).prop_map(Chunk::Junk),
    ]
}

fn bytes_of(chunk: &Chunk, seeds: &[Request]) -> Vec<u8> {
    let message = |i: usize| message_of(&encoded(&seeds[i]));
    match chunk {
        Chunk::Valid(i) => encoded(&seeds[*i]),
        Chunk::Mutated(i, mutations) => {
            let mut m = message(*i);
            for mutation in mutations {
                match mutation {
                    Mutation::Set(at, b) if !m.is_empty() => {
                        let k = at.index(m.len());
                        m[k] = *b;
                    }
                    Mutation::Insert(at, b) => {
                        let k = at.index(m.len() + 1);
                        m.insert(k, *b);
                    }
                    Mutation::Remove(at) if m.len() > 1 => {
                        m.remove(at.index(m.len()));
                    }
                    _ => {}
                }
            }
            framed(&m)
        }
        Chunk::Cut(i, at) => {
            let mut f = encoded(&seeds[*i]);
            f.truncate(at.index(f.len()));
            f
        }
        Chunk::Corrupt(i, at, x) => {
            let mut f = encoded(&seeds[*i]);
            let k = at.index(f.len() - 1); // never the delimiter
            f[k] ^= x;
            f
        }
        Chunk::Junk(b) => b.clone(),
    }
}

/// Frames the board must answer in `bytes`: runs of non-zero bytes ended by a delimiter.
fn frames_in(bytes: &[u8], run: &mut usize) -> usize {
    let mut frames = 0;
    for &b in bytes {
        if b == 0 {
            if *run > 0 {
                frames += 1;
            }
            *run = 0;
        } else {
            *run += 1;
        }
    }
    frames
}

/// The board under test and what the test has seen of it: the envelope of what it may do
/// (the union of the voltage limits of every settings it accepted, the largest slew limit in
/// volts per tick), its last outputs, and the responses it sent.
struct Watch<D = InternalDac, A = InternalAdc> {
    dev: SimDevice<D, A>,
    rate_hz: f64,
    volts_per_code: f64,
    min_voltage: f64,
    max_voltage: f64,
    slew_per_tick: f64,
    last: Option<(f64, f64)>,
    /// Watchdog resets seen (each after a drill).
    resets: usize,
    decoder: FrameDecoder,
    /// Responses other than telemetry frames.
    answered: usize,
    /// The last status report among them.
    status: Option<StatusReport>,
}

impl Watch {
    /// The piezo-only board, on its defaults.
    fn new() -> Self {
        Self::of(SimDevice::new(SimDeviceConfig::paper()).expect("device"))
    }
}

impl Watch<DualDacs, DualAdc> {
    /// The dual-stage board (the coarse axis's task beside the tick, unhomed at power-up).
    fn dual_stage() -> Self {
        Self::of(DualStageDevice::dual_stage(&DualStageDeviceConfig::paper()).expect("device"))
    }
}

impl<D: AnalogDualDac, A: AnalogSensorAdc> Watch<D, A> {
    fn of(dev: SimDevice<D, A>) -> Self {
        let hw = *dev.handler().hardware();
        let mut w = Self {
            dev,
            rate_hz: hw.control_rate_hz,
            volts_per_code: hw.amplifier_full_scale / hw.dac_full_scale as f64,
            min_voltage: f64::MAX,
            max_voltage: f64::MIN,
            slew_per_tick: 0.0,
            last: None,
            resets: 0,
            decoder: FrameDecoder::new(),
            answered: 0,
            status: None,
        };
        w.widen();
        w
    }

    /// Takes the settings in force into the envelope.
    fn widen(&mut self) {
        let d = &self.dev.handler().settings().drive;
        self.min_voltage = self.min_voltage.min(d.min_voltage);
        self.max_voltage = self.max_voltage.max(d.max_voltage);
        self.slew_per_tick = self.slew_per_tick.max(d.slew_rate / self.rate_hz);
    }

    /// Runs `ticks` ticks, checking each tick's outputs and collecting what the board sent.
    fn ticks(&mut self, ticks: u32) -> Result<(), TestCaseError> {
        let tick = Duration::from_secs_f64(1.0 / self.rate_hz);
        let lsb = self.volts_per_code;
        let mut buf = [0u8; 4096];
        for _ in 0..ticks {
            let drilling = !self.dev.control().feeds_watchdog();
            self.dev.run_for(tick);
            self.widen();
            let Some(report) = self.dev.last_report() else {
                // The tick that ends in the watchdog's reset reports nothing: the board starts
                // again from its flash. A reset with no drill on would be a hang.
                prop_assert!(
                    drilling,
                    "a reset with no watchdog drill on at tick {}",
                    self.dev.ticks()
                );
                // The outputs between the last tick before the reset and the first after it
                // are not the firmware's: the reset turns the DAC off, and the booted firmware
                // starts it at its boot codes (checked against the range like every tick's).
                // A slew measured across the reset would compare two boots, not a step the
                // limiter let through.
                self.last = None;
                self.resets += 1;
                continue;
            };
            let v = (report.left.0 as f64 * lsb, report.right.0 as f64 * lsb);
            for x in [v.0, v.1] {
                prop_assert!(
                    x >= self.min_voltage - lsb && x <= self.max_voltage + lsb,
                    "{x} V outside every accepted range [{}, {}] at tick {}",
                    self.min_voltage,
                    self.max_voltage,
                    self.dev.ticks()
                );
            }
            if let Some(p) = self.last {
                let step = (v.0 - p.0).abs().max((v.1 - p.1).abs());
                prop_assert!(
                    step <= self.slew_per_tick + 2.0 * lsb,
                    "a {step} V step (slew limit {} V per tick) at tick {}",
                    self.slew_per_tick,
                    self.dev.ticks()
                );
            }
            self.last = Some(v);
            let n = self
                .dev
                .receive(&mut buf, Duration::ZERO)
                .expect("the line reads");
            for &b in &buf[..n] {
                let Some(body) = self.decoder.push(b) else {
                    continue;
                };
                let body =
                    body.map_err(|e| TestCaseError::fail(format!("a broken frame: {e:?}")))?;
                match frame::decode_body(body) {
                    Ok(Response::Telemetry(_)) => {}
                    Ok(response) => {
                        self.answered += 1;
                        if let Response::Status(s) = response {
                            self.status = Some(s);
                        }
                    }
                    Err(e) => return Err(TestCaseError::fail(format!("undecodable: {e:?}"))),
                }
            }
        }
        Ok(())
    }
}

/// Sends each frame run (`bytes`, then `ticks` ticks) to a fresh board under watch, then the
/// closing checks: every frame answered, the queue's accounting whole. Returns the watch.
fn replay(frames: &[(Vec<u8>, u32)]) -> Result<Watch, TestCaseError> {
    replay_on(Watch::new(), frames)
}

/// [`replay`] on the board `w` watches.
fn replay_on<D: AnalogDualDac, A: AnalogSensorAdc>(
    mut w: Watch<D, A>,
    frames: &[(Vec<u8>, u32)],
) -> Result<Watch<D, A>, TestCaseError> {
    let (mut run, mut sent) = (0usize, 0usize);
    for (bytes, ticks) in frames {
        sent += frames_in(bytes, &mut run);
        w.dev.send(bytes).expect("the line takes bytes");
        w.ticks(*ticks)?;
    }
    // A delimiter ends a cut frame left open; then the line drains and every frame has
    // had its answer.
    sent += frames_in(&[0], &mut run);
    w.dev.send(&[0]).expect("the line takes bytes");
    w.ticks((w.rate_hz * 0.05) as u32)?;
    // Every frame has its answer, but for one a watchdog reset may take: the board starts
    // again with a fresh decoder, so a frame whose first bytes it had taken before the reset
    // and whose only byte after it is the delimiter is no frame to the new board (the bytes
    // after a reset are a frame of their own, answered).
    prop_assert!(
        w.answered <= sent && sent - w.answered <= w.resets,
        "{} responses for {sent} frames sent, {} watchdog resets",
        w.answered,
        w.resets
    );
    // The queue's accounting, through the protocol as a host sees it.
    w.dev
        .send(&encoded(&Request::Status))
        .expect("the line takes bytes");
    w.ticks((w.rate_hz * 0.01) as u32)?;
    let s = w.status.expect("a status answer");
    prop_assert_eq!(
        s.queue_fill as usize + s.credits as usize,
        SETPOINT_CAPACITY
    );
    Ok(w)
}

/// The fuzzer's chunks as frame runs: each chunk's bytes and the ticks run after them (a long
/// run now and then).
fn frames_of(chunks: &[(Chunk, u32, bool)]) -> Vec<(Vec<u8>, u32)> {
    let seeds = seeds();
    chunks
        .iter()
        .map(|(chunk, gap_ticks, long_run)| {
            (
                bytes_of(chunk, &seeds),
                if *long_run { 5_000 } else { *gap_ticks },
            )
        })
        .collect()
}

/// Cases per property: 96, or `PROPTEST_CASES` where it is set (a deeper campaign).
fn campaign_cases() -> u32 {
    std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(96)
}

proptest! {
    // Deterministic work (simulated time), bounded so CI spends seconds here; a longer
    // campaign sets `PROPTEST_CASES`.
    #![proptest_config(ProptestConfig { cases: campaign_cases(), ..ProptestConfig::default() })]

    #[test]
    fn every_request_type_with_any_fields_keeps_the_board_answering_and_its_outputs_in_limits(
        chunks in prop::collection::vec(
            (any_chunk(seeds().len()), 0u32..400, prop::bool::weighted(0.05)), 1..40),
    ) {
        replay(&frames_of(&chunks))?;
    }

    /// The same on the dual-stage board, whose coarse axis takes the piezo's setpoint from
    /// its first coarse period: the requests of the other sources are refused then, and the
    /// coarse requests (home, move, jog, stop) are served beside them.
    #[test]
    fn the_dual_stage_board_keeps_answering_and_its_outputs_in_limits(
        chunks in prop::collection::vec(
            (any_chunk(seeds().len()), 0u32..400, prop::bool::weighted(0.05)), 1..24),
    ) {
        replay_on(Watch::dual_stage(), &frames_of(&chunks))?;
    }
}

/// A case the fuzzer found: open loop, a watchdog drill (a mutated frame whose one message
/// byte is the drill's tag), a waveform started while the drill runs, closed-loop settings
/// (bias 40 V) loaded; 20 ms after the drill the watchdog resets the board, which boots on
/// its defaults (bypass, bias 70 V): the right stack's code goes from 570 to 2070, 54.9 V
/// between the last tick before the reset and the first after it. The checker takes the reset
/// as the discontinuity it is (no slew across it) and still checks every other tick.
#[test]
fn a_watchdog_reset_after_a_drill_is_not_measured_as_a_slew() {
    let seeds = seeds();
    let drill = framed(&[27]);
    assert_eq!(
        drill,
        encoded(&Request::WatchdogDrill),
        "the mutated frame is the drill"
    );
    let frames = [
        (encoded(&seeds[8]), 0),
        (drill, 63),
        (encoded(&seeds[14]), 244),
        (encoded(&seeds[11]), 0),
    ];
    assert!(matches!(seeds[8], Request::Mode(Mode::OpenLoop)));
    assert!(matches!(seeds[14], Request::Waveform(_)));
    assert!(matches!(seeds[11], Request::LoadParams(_)));
    let w = replay(&frames).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(w.resets, 1, "the drill reset the board once");
}
