//! The frame layer under good and bad input: round trips, every refusal reason, resync, and
//! random bytes (no panic; a good frame after junk still decodes).

use proptest::prelude::*;
use twinstack::config::settings::{
    representative_duhem, DriveSettings, FeedbackSettings, Model, NotchDesign, PreviewDesign,
    SensorSettings, Settings,
};
use twinstack::protocol::decoder::FrameDecoder;
use twinstack::protocol::frame::{
    decode_body, encode, encode_body_bytes, FrameError, FRAME_CRC, MAX_BODY, MAX_ENCODED,
    PROTOCOL_VERSION,
};
use twinstack::protocol::messages::*;
use twinstack::PiParams;

fn frame_of(req: &Request) -> Vec<u8> {
    let mut out = vec![0u8; MAX_ENCODED + 1];
    let n = encode(req, &mut out).expect("fits");
    out.truncate(n);
    out
}

/// Feeds bytes, collecting every decoded request or refusal.
fn feed(decoder: &mut FrameDecoder, bytes: &[u8]) -> Vec<Result<Request, FrameError>> {
    let mut out = Vec::new();
    for &b in bytes {
        if let Some(r) = decoder.push(b) {
            out.push(r.and_then(decode_body::<Request>));
        }
    }
    out
}

fn request() -> impl Strategy<Value = Request> {
    prop_oneof![
        Just(Request::Status),
        Just(Request::WatchdogDrill),
        (
            any::<u16>(),
            prop::collection::vec(any::<i16>(), 0..=MAX_BATCH)
        )
            .prop_map(|(seq, s)| {
                Request::Setpoints(SetpointBatch {
                    seq,
                    samples: heapless::Vec::from_slice(&s).unwrap(),
                })
            }),
        any::<u16>().prop_map(|divider| Request::Stream(StreamControl::Rate { divider })),
        (
            any::<i16>(),
            any::<i16>(),
            any::<u32>(),
            proptest::option::of((any::<u16>(), any::<u16>()))
        )
            .prop_map(|(offset, amplitude, f, decay)| {
                Request::Waveform(Waveform {
                    shape: WaveShape::Sine,
                    offset,
                    amplitude,
                    frequency_mhz: f,
                    decay: decay.map(|(hold_cycles, keep)| WaveDecay { hold_cycles, keep }),
                })
            }),
        (prop::collection::vec(0.0f64..150.0, 0..=32), -1.0f64..1.0).prop_map(|(r, a0)| {
            let n = r.len();
            // Any f64 the wire carries, valid or not: the frame layer does not validate.
            Request::LoadParams(Settings {
                ranges: twinstack::Scaling {
                    input_min: 0.0,
                    input_max: 140.0,
                    output_min: -1.0,
                    output_max: 20.0,
                },
                compensator: Some(Model::PrandtlIshlinskii(PiParams {
                    a0,
                    offset: 0.5,
                    thresholds: heapless::Vec::from_slice(&r).unwrap(),
                    weights: heapless::Vec::from_slice(&vec![0.01; n]).unwrap(),
                })),
                observer: Some(representative_duhem()),
                drive: DriveSettings::DEFAULT,
                sensor: Some(SensorSettings {
                    displacement_at_zero: -1.0,
                    displacement_at_full_scale: 20.0,
                    drift_limit: Some(0.02),
                }),
                feedback: Some(FeedbackSettings {
                    notch: Some(NotchDesign {
                        frequency_hz: 21_800.0,
                        q: 2.0,
                        depth: 0.0,
                    }),
                    ..FeedbackSettings::pi(0.1, 500.0, 0.2)
                }),
                mode: Mode::OpenLoop,
                creep: None,
                shaping: None,
                preview: (a0 > 0.0).then_some(PreviewDesign {
                    frequency_hz: 3_500.0,
                    damping: a0,
                }),
                output_map: (a0 < -0.5).then(|| {
                    twinstack::config::settings::DeadZoneParams::new(
                        9.5,
                        1.0,
                        &[-5.0, 5.0],
                        &[a0 * 0.1, -0.1],
                    )
                    .unwrap()
                }),
            })
        }),
        prop_oneof![
            Just(Mode::Bypass),
            Just(Mode::OpenLoop),
            Just(Mode::ClosedLoop)
        ]
        .prop_map(|boot_mode| Request::StoreParams { boot_mode }),
        any::<u32>().prop_map(|offset| Request::ReadRecord { offset }),
        (
            any::<u8>(),
            any::<u32>(),
            any::<u32>(),
            prop_oneof![
                Just(Trigger::Now),
                Just(Trigger::StreamStart),
                Just(Trigger::WaveformStart),
                Just(Trigger::ScanStart),
                Just(Trigger::External)
            ],
            any::<u16>()
        )
            .prop_map(|(signals, samples, pre_trigger, trigger, decimation)| {
                Request::Capture(CaptureRequest {
                    signals,
                    samples,
                    pre_trigger,
                    trigger,
                    decimation,
                })
            }),
        Just(Request::CaptureStatus),
        (any::<u32>(), any::<u16>())
            .prop_map(|(offset, count)| Request::ReadCapture { offset, count }),
        (any::<u8>(), any::<u16>()).prop_map(|(signals, decimation)| {
            Request::Telemetry(TelemetryRequest::Start {
                signals,
                decimation,
            })
        }),
        Just(Request::Telemetry(TelemetryRequest::Stop)),
        (
            any::<u16>(),
            any::<u16>(),
            any::<u16>(),
            -2.0f64..2.0,
            any::<u16>(),
            any::<bool>()
        )
            .prop_map(
                |(lines, pixels, turn_ticks, amplitude, frames, on_trigger)| {
                    // Any values the wire carries: the frame layer does not validate.
                    Request::Scan(ScanRequest {
                        pattern: ScanPattern::Raster(RasterScan {
                            lines,
                            pixels,
                            turn_ticks,
                            offset: 0.1,
                            amplitude,
                            y_offset: -0.2,
                            y_amplitude: amplitude,
                        }),
                        ticks_per_pixel: pixels / 3,
                        frames,
                        on_trigger,
                    })
                }
            ),
        (0.0f64..1e4, any::<u16>(), any::<u16>()).prop_map(|(f, nx, turns)| {
            Request::Scan(ScanRequest {
                pattern: if nx % 2 == 0 {
                    ScanPattern::Lissajous(LissajousScan {
                        frame_hz: f,
                        x_cycles: nx,
                        y_cycles: turns,
                        y_phase_deg: 90.0,
                        offset: 0.0,
                        amplitude: 0.5,
                        y_offset: 0.0,
                        y_amplitude: 0.5,
                    })
                } else {
                    ScanPattern::Spiral(SpiralScan {
                        turn_hz: f,
                        turns,
                        offset: 0.0,
                        amplitude: 0.5,
                        y_offset: 0.0,
                    })
                },
                ticks_per_pixel: 4,
                frames: 0,
                on_trigger: false,
            })
        }),
        (
            any::<u16>(),
            prop_oneof![
                Just(TriggerEdge::Off),
                Just(TriggerEdge::Rising),
                Just(TriggerEdge::Falling)
            ],
            any::<bool>()
        )
            .prop_map(|(pulse_ticks, input, start_stream)| {
                Request::Trigger(TriggerConfig {
                    pulse_ticks,
                    input,
                    start_stream,
                })
            }),
        (
            prop_oneof![Just(TriggerEdge::Rising), Just(TriggerEdge::Falling)],
            any::<f32>(),
            any::<u16>(),
            0u8..3
        )
            .prop_map(|(edge, window, settle_ticks, which)| {
                Request::Sequence(match which {
                    0 => SequenceRequest::Arm(SequenceConfig {
                        edge,
                        // NaN ≠ NaN: the round trip is compared with `==`.
                        window: if window.is_nan() { 0.0 } else { window },
                        settle_ticks,
                    }),
                    1 => SequenceRequest::Stop,
                    _ => SequenceRequest::Status,
                })
            }),
        prop::collection::vec(any::<u8>(), 0..=MAX_ECHO)
            .prop_map(|bytes| Request::Echo(heapless::Vec::from_slice(&bytes).unwrap())),
        (
            (any::<f32>(), any::<f32>(), any::<Option<f32>>()),
            (any::<f32>(), any::<f32>(), any::<bool>(), any::<f32>()),
            (any::<bool>(), 0u8..3)
        )
            .prop_map(
                |((gain, offset, corner), (lost, over, ramp, rate), (boot, which))| {
                    // NaN ≠ NaN: the round trip is compared with `==`.
                    let n = |x: f32| if x.is_nan() { 0.0 } else { x };
                    Request::Analog(match which {
                        0 => AnalogRequest::Start(AnalogInputConfig {
                            gain: n(gain),
                            offset: n(offset),
                            corner_hz: corner.map(n),
                            lost_below: n(lost),
                            over_above: n(over),
                            on_fault: if ramp {
                                OnFault::RampToRest
                            } else {
                                OnFault::Hold
                            },
                            rate: n(rate),
                            start_at_boot: boot,
                        }),
                        1 => AnalogRequest::Stop,
                        _ => AnalogRequest::Status,
                    })
                }
            ),
    ]
}

proptest! {
    #[test]
    fn every_request_survives_the_wire(reqs in prop::collection::vec(request(), 1..8)) {
        let mut d = FrameDecoder::new();
        let bytes: Vec<u8> = reqs.iter().flat_map(frame_of).collect();
        let got = feed(&mut d, &bytes);
        prop_assert_eq!(got, reqs.into_iter().map(Ok).collect::<Vec<_>>());
    }

    /// Any single corrupted byte is caught (CRC-32 detects every burst up to 32 bits), and the
    /// next frame decodes: nothing after the damage is lost.
    #[test]
    fn a_corrupted_byte_is_refused_and_the_next_frame_still_decodes(
        req in request(), at in any::<prop::sample::Index>(), flip in 1u8..=255,
    ) {
        let mut bad = frame_of(&req);
        let i = at.index(bad.len() - 1); // keep the delimiter
        bad[i] ^= flip;
        let good = frame_of(&Request::Status);
        let mut d = FrameDecoder::new();
        let got = feed(&mut d, &[bad, good].concat());
        prop_assert!(!got.is_empty());
        let (last, before) = got.split_last().unwrap();
        prop_assert_eq!(last, &Ok(Request::Status));
        for r in before {
            prop_assert!(r.is_err(), "a corrupted frame was accepted: {:?}", r);
        }
    }

    /// Random bytes never panic the decoder; after a delimiter, a good frame decodes.
    #[test]
    fn random_bytes_never_panic_and_resync_at_the_delimiter(junk in prop::collection::vec(any::<u8>(), 0..2000)) {
        let mut d = FrameDecoder::new();
        let _ = feed(&mut d, &junk);
        let mut tail = vec![0u8];
        tail.extend(frame_of(&Request::StoreParams {
            boot_mode: Mode::Bypass,
        }));
        let got = feed(&mut d, &tail);
        prop_assert_eq!(
            got.last(),
            Some(&Ok(Request::StoreParams {
                boot_mode: Mode::Bypass
            }))
        );
    }
}

#[test]
fn truncated_frame_is_refused() {
    let mut d = FrameDecoder::new();
    // A frame cut short: its first half, then the delimiter.
    let f = frame_of(&Request::Setpoints(SetpointBatch {
        seq: 7,
        samples: heapless::Vec::from_slice(&[1, 2, 3, 4, 5, 6, 7, 8]).unwrap(),
    }));
    let mut cut = f[..f.len() / 2].to_vec();
    cut.push(0);
    let got = feed(&mut d, &cut);
    assert_eq!(got.len(), 1);
    assert!(got[0].is_err());
    // Shorter than version + CRC.
    assert_eq!(
        feed(&mut d, &[0x03, 0x01, 0x02, 0x00]),
        vec![Err(FrameError::Truncated)]
    );
}

#[test]
fn oversize_frame_is_refused_once_then_the_decoder_resyncs() {
    let mut d = FrameDecoder::new();
    let mut bytes = vec![0x55u8; MAX_ENCODED + 50];
    bytes.push(0);
    bytes.extend(frame_of(&Request::Status));
    assert_eq!(
        feed(&mut d, &bytes),
        vec![Err(FrameError::Oversize), Ok(Request::Status)]
    );
}

/// Builds a frame from a raw body (version + payload) with a correct CRC.
fn raw_frame(body: &[u8]) -> Vec<u8> {
    let mut out = vec![0u8; MAX_ENCODED + 1];
    let n = encode_body_bytes(body, &mut out).unwrap();
    out.truncate(n);
    out
}

/// The stuffed size of a body is at most `cobs::max_encoding_length` (the worst case: no zero
/// at all, one code byte per started 254), the largest body fits the receiver, and a body past
/// the largest is refused by the sender.
#[test]
fn stuffing_is_bounded_by_max_encoded_and_the_sender_refuses_what_the_receiver_would() {
    for n in [1, 5, 253, 254, 255, 508, 509, 1000, MAX_BODY - 4] {
        let body = vec![0x5Au8; n];
        let mut out = vec![0u8; MAX_ENCODED + 1];
        let len = encode_body_bytes(&body, &mut out).unwrap();
        // Body, CRC (4 bytes, which may hold zeros), delimiter.
        assert!(
            len <= cobs::max_encoding_length(n + 4) + 1,
            "{n} bytes stuffed into {len}"
        );
        assert_eq!(out[len - 1], 0);
        assert!(!out[..len - 1].contains(&0));
        let mut d = FrameDecoder::new();
        let mut decoded = None;
        for &b in &out[..len] {
            if let Some(r) = d.push(b) {
                decoded = Some(r.unwrap().to_vec());
            }
        }
        let decoded = decoded.unwrap();
        assert_eq!(&decoded[..n], &body[..]);
    }
    // 254 non-zero bytes (250 of body, a CRC without a zero): one full block, 255 stuffed bytes
    // (no empty block after it), and the delimiter.
    let fill = (1..=255u8)
        .find(|&f| !FRAME_CRC.checksum(&[f; 250]).to_le_bytes().contains(&0))
        .unwrap();
    let mut out = vec![0u8; MAX_ENCODED + 1];
    let len = encode_body_bytes(&[fill; 250], &mut out).unwrap();
    assert_eq!(len, 255 + 1);
    assert_eq!(out[0], 0xFF);
    let mut out = vec![0u8; 4 * MAX_ENCODED];
    assert_eq!(
        encode_body_bytes(&vec![0x5Au8; MAX_ENCODED], &mut out),
        Err(FrameError::TooLarge)
    );
    assert_eq!(
        encode_body_bytes(&[1, 2, 3], &mut [0u8; 4]),
        Err(FrameError::TooLarge)
    );
}

#[test]
fn unknown_type_bad_version_and_malformed_fields_each_have_their_reason() {
    let mut d = FrameDecoder::new();
    assert_eq!(
        feed(&mut d, &raw_frame(&[PROTOCOL_VERSION, 120])),
        vec![Err(FrameError::UnknownType)]
    );
    assert_eq!(
        feed(&mut d, &raw_frame(&[PROTOCOL_VERSION + 1, 0])),
        vec![Err(FrameError::BadVersion {
            got: PROTOCOL_VERSION + 1
        })]
    );
    // `Setpoints` whose length prefix promises more samples than follow.
    assert_eq!(
        feed(&mut d, &raw_frame(&[PROTOCOL_VERSION, 1, 5, 0, 10, 1, 2])),
        vec![Err(FrameError::Malformed)]
    );
    // A valid message followed by trailing bytes.
    assert_eq!(
        feed(&mut d, &raw_frame(&[PROTOCOL_VERSION, 0, 9])),
        vec![Err(FrameError::Malformed)]
    );
    // Broken stuffing: a code byte that runs past the end.
    assert_eq!(
        feed(&mut d, &[0x09, 0x01, 0x02, 0x00]),
        vec![Err(FrameError::BadStuffing)]
    );
}

#[test]
fn a_full_batch_fits_one_frame() {
    let req = Request::Setpoints(SetpointBatch {
        seq: u16::MAX,
        samples: heapless::Vec::from_slice(&[i16::MIN; MAX_BATCH]).unwrap(),
    });
    let f = frame_of(&req);
    // 2 bytes a sample (varint zigzag of i16 is ≤ 3; here the worst case), plus framing.
    assert!(f.len() <= MAX_ENCODED + 1);
}

/// The variant counts the decoder checks tags against match the enums: the last variant of
/// each decodes, one past it is an unknown type.
#[test]
fn message_variant_counts_match_the_enums() {
    use twinstack::protocol::frame::Message;
    let last = Request::CoarseRelease;
    let mut d = FrameDecoder::new();
    assert_eq!(feed(&mut d, &frame_of(&last)), vec![Ok(last)]);
    let tag = Request::VARIANTS as u8;
    assert_eq!(
        feed(&mut d, &raw_frame(&[PROTOCOL_VERSION, tag])),
        vec![Err(FrameError::UnknownType)]
    );
    let resp = Response::Analog(twinstack::protocol::messages::AnalogStatus::default());
    let mut buf = [0u8; MAX_ENCODED + 1];
    let n = encode(&resp, &mut buf).unwrap();
    let mut d = FrameDecoder::new();
    let body = buf[..n]
        .iter()
        .filter_map(|&b| d.push(b).map(|r| r.map(|s| s.to_vec())))
        .next()
        .unwrap()
        .unwrap();
    assert_eq!(decode_body::<Response>(&body), Ok(resp));
    assert_eq!(body[1] as u32 + 1, Response::VARIANTS);
}

/// The largest capture chunk (every value at the widest varint) fits a frame.
#[test]
fn a_full_capture_chunk_fits_a_frame() {
    let chunk = Response::CaptureChunk {
        offset: u32::MAX,
        values: core::iter::repeat_n(i16::MIN, MAX_CAPTURE_CHUNK).collect(),
    };
    let mut out = [0u8; MAX_ENCODED + 1];
    let n = encode(&chunk, &mut out).expect("fits");
    assert!(n > 3 * MAX_CAPTURE_CHUNK, "{n} bytes");
}
