//! The example frames of the book's protocol chapter (`docs/src/reference/protocol.md`), read
//! from the chapter itself: each `frame:` line must be what the encoder writes for the message
//! the example names, and each `body:` annotation must say what the library decodes — the
//! version, the CRC, every named variant and field and every value. A wrong byte, a stale CRC
//! or version, or an annotation that names the wrong thing fails here.

use twinstack::protocol::decoder::FrameDecoder;
use twinstack::protocol::frame::{decode_body, encode, FRAME_CRC, MAX_ENCODED, PROTOCOL_VERSION};
use twinstack::protocol::messages::*;
use twinstack::refusal::{Field, Refusal, Rule};

const CHAPTER: &str = include_str!("../docs/src/reference/protocol.md");

/// A message of an example, a request or a response.
#[derive(Debug)]
enum Message {
    Request(Request),
    Response(Response),
}

impl Message {
    fn frame(&self) -> Vec<u8> {
        let mut out = vec![0u8; MAX_ENCODED + 1];
        let n = match self {
            Message::Request(r) => encode(r, &mut out),
            Message::Response(r) => encode(r, &mut out),
        }
        .expect("the example fits a frame");
        out.truncate(n);
        out
    }

    /// The message decoded from `body` as the same kind, in `Debug` form.
    fn decoded(&self, body: &[u8]) -> String {
        match self {
            Message::Request(_) => format!("{:?}", decode_body::<Request>(body).expect("decodes")),
            Message::Response(_) => {
                format!("{:?}", decode_body::<Response>(body).expect("decodes"))
            }
        }
    }
}

/// The messages the chapter's examples name, by their title line.
fn messages() -> Vec<(&'static str, Message)> {
    use Message::{Request as Q, Response as R};
    let refused = |field, rule| Response::Nack {
        reason: NackReason::Refused(Refusal::new(field, rule)),
    };
    vec![
        ("Status (request)", Q(Request::Status)),
        (
            "Setpoints { seq 1, [100, −100] }",
            Q(Request::Setpoints(SetpointBatch {
                seq: 1,
                samples: heapless::Vec::from_slice(&[100, -100]).unwrap(),
            })),
        ),
        ("Ack { credits 511 }", R(Response::Ack { credits: 511 })),
        (
            "Nack { Refused { Ki, Below(25000.0) } }",
            R(refused(Field::Ki, Rule::Below(25_000.0))),
        ),
        (
            "Capture { signals 0b011011, samples 150, pre_trigger 10, StreamStart, decimation 1 }",
            Q(Request::Capture(CaptureRequest {
                signals: 0b1_1011,
                samples: 150,
                pre_trigger: 10,
                trigger: Trigger::StreamStart,
                decimation: 1,
            })),
        ),
        (
            "ReadCapture { offset 0, count 256 }",
            Q(Request::ReadCapture {
                offset: 0,
                count: 256,
            }),
        ),
        (
            "CaptureChunk { offset 0, [100, −100, 4095] }",
            R(Response::CaptureChunk {
                offset: 0,
                values: heapless::Vec::from_slice(&[100, -100, 4095]).unwrap(),
            }),
        ),
        (
            "Telemetry(Start { signals 0b1001, decimation 5 })",
            Q(Request::Telemetry(TelemetryRequest::Start {
                signals: 0b1001,
                decimation: 5,
            })),
        ),
        (
            "Telemetry(Stop)",
            Q(Request::Telemetry(TelemetryRequest::Stop)),
        ),
        (
            "Telemetry { seq 3, first 120, signals 0b1001, lost 0, end false, [100, −100, 16384, 16000] }",
            R(Response::Telemetry(TelemetryFrame {
                seq: 3,
                first: 120,
                signals: 0b1001,
                lost: 0,
                end: false,
                values: heapless::Vec::from_slice(&[100, -100, 16384, 16000]).unwrap(),
            })),
        ),
        (
            "Nack { Refused { TelemetryDecimation, AtLeast(6.0) } }",
            R(refused(Field::TelemetryDecimation, Rule::AtLeast(6.0))),
        ),
        (
            "Waveform { Sine, offset 0, amplitude 31785, 10 Hz, decay { hold_cycles 6, keep 57000 } }",
            Q(Request::Waveform(Waveform {
                shape: WaveShape::Sine,
                offset: 0,
                amplitude: 31_785,
                frequency_mhz: 10_000,
                decay: Some(WaveDecay {
                    hold_cycles: 6,
                    keep: 57_000,
                }),
            })),
        ),
        (
            "Learn(Status)",
            Q(Request::Learn(LearnRequest::Status)),
        ),
        (
            "Scan { Raster { lines 64, pixels 100, turn_ticks 40, offset 0, amplitude 0.5, y_offset 0, y_amplitude 0.5 }, ticks_per_pixel 4, frames 1, on_trigger false }",
            Q(Request::Scan(ScanRequest {
                pattern: ScanPattern::Raster(RasterScan::centred(64, 100, 40, 0.5)),
                ticks_per_pixel: 4,
                frames: 1,
                on_trigger: false,
            })),
        ),
        (
            "Trigger { pulse_ticks 2, Rising, start_stream true }",
            Q(Request::Trigger(TriggerConfig {
                pulse_ticks: 2,
                input: TriggerEdge::Rising,
                start_stream: true,
            })),
        ),
        (
            "Sequence(Arm { Rising, window 0.005, settle_ticks 25 })",
            Q(Request::Sequence(SequenceRequest::Arm(SequenceConfig {
                edge: TriggerEdge::Rising,
                window: 0.005,
                settle_ticks: 25,
            }))),
        ),
    ]
}

/// One example of the chapter: its title, its frame, its annotated body and its COBS line.
#[derive(Debug, Default)]
struct Example {
    title: String,
    frame: String,
    body: String,
    cobs: Option<String>,
}

/// The examples of the chapter's block that follows "Examples".
fn examples(chapter: &str) -> Vec<Example> {
    let start = chapter
        .find("\nExamples, in hex.")
        .expect("the chapter has its examples");
    let block = &chapter[start..];
    let open = block.find("```text\n").expect("the examples' block") + "```text\n".len();
    let close = block[open..].find("```").expect("the block ends") + open;
    let mut out: Vec<Example> = Vec::new();
    let mut last: Option<&str> = None;
    for line in block[open..close].lines() {
        let trimmed = line.trim_start();
        let indented = line.len() != trimmed.len();
        if !indented {
            out.push(Example {
                title: line.trim_end().to_string(),
                ..Example::default()
            });
            last = None;
            continue;
        }
        let e = out
            .last_mut()
            .expect("an indented line belongs to an example");
        let (label, rest) = match trimmed.split_once(':') {
            Some((l, r)) if ["frame", "body", "COBS"].contains(&l) => (Some(l), r),
            _ => (None, trimmed),
        };
        let label = label
            .or(last)
            .expect("a continuation follows a labelled line");
        let field = match label {
            "frame" => &mut e.frame,
            "body" => &mut e.body,
            _ => e.cobs.get_or_insert_with(String::new),
        };
        field.push(' ');
        field.push_str(rest.trim());
        last = Some(label);
    }
    out
}

/// What a `body:` line holds, in order.
#[derive(Debug, PartialEq)]
enum Token {
    Byte(u8),
    /// A parenthesised annotation of the bytes before it.
    Note(String),
    /// `|` (between the version, the message and the CRC).
    Bar,
    /// `CRC`: the four bytes after it are the frame's CRC.
    Crc,
}

fn tokens(text: &str) -> Vec<Token> {
    let mut out = Vec::new();
    let mut rest = text.trim();
    while !rest.is_empty() {
        if let Some(r) = rest.strip_prefix('(') {
            let end = r
                .find(')')
                .unwrap_or_else(|| panic!("unclosed annotation in {text:?}"));
            out.push(Token::Note(r[..end].to_string()));
            rest = &r[end + 1..];
        } else if let Some(r) = rest.strip_prefix('|') {
            out.push(Token::Bar);
            rest = r;
        } else if let Some(r) = rest.strip_prefix("CRC") {
            out.push(Token::Crc);
            rest = r;
        } else {
            let end = rest.find([' ', '(', '|']).unwrap_or(rest.len());
            let word = &rest[..end];
            let byte = (word.len() == 2)
                .then(|| u8::from_str_radix(word, 16).ok())
                .flatten()
                .unwrap_or_else(|| panic!("{word:?} in {text:?} is not a hex byte"));
            out.push(Token::Byte(byte));
            rest = &rest[end..];
        }
        rest = rest.trim_start();
    }
    out
}

fn hex_bytes(text: &str) -> Vec<u8> {
    tokens(text)
        .into_iter()
        .filter_map(|t| match t {
            Token::Byte(b) => Some(b),
            Token::Bar | Token::Note(_) => None,
            other => panic!("{other:?} in a frame or COBS line: {text:?}"),
        })
        .collect()
}

fn varint(mut v: u64) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let low = (v & 0x7f) as u8;
        v >>= 7;
        if v == 0 {
            out.push(low);
            return out;
        }
        out.push(low | 0x80);
    }
}

fn zigzag(v: i64) -> u64 {
    ((v << 1) ^ (v >> 63)) as u64
}

/// The recorder's signal names, by mask bit.
const SIGNALS: [&str; 7] = [
    "setpoint", "left", "right", "sensor", "estimate", "error", "triggers",
];

/// Checks one annotation against the bytes it annotates and the decoded message.
fn check_note(note: &str, bytes: &[u8], at: usize, decoded: &str, title: &str) {
    let ctx = format!("{title}: ({note}) on {bytes:02x?}");
    assert!(!bytes.is_empty(), "{ctx}: an annotation of no bytes");
    if note == "version" {
        assert_eq!((at, bytes), (0, &[PROTOCOL_VERSION][..]), "{ctx}");
        return;
    }
    if let Some(names) = note.strip_prefix("mask:") {
        let mask = names.split(',').fold(0u8, |m, name| {
            let bit = SIGNALS
                .iter()
                .position(|s| *s == name.trim())
                .unwrap_or_else(|| panic!("{ctx}: no signal {name:?}"));
            m | 1 << bit
        });
        assert_eq!(bytes, &[mask][..], "{ctx}");
        assert!(
            decoded.contains(&format!("signals: {mask}")),
            "{ctx}: {decoded}"
        );
        return;
    }
    let is_name = |w: &str| w.chars().next().is_some_and(|c| c.is_ascii_uppercase());
    if note
        .split("::")
        .all(|w| is_name(w) && w.chars().all(char::is_alphanumeric))
    {
        // A variant: the decoded message names it (the message's own, as its first word).
        let variant = note.rsplit("::").next().unwrap();
        if at == 1 {
            assert!(
                decoded.starts_with(variant)
                    && !decoded[variant.len()..].starts_with(char::is_alphanumeric),
                "{ctx}: the message is {decoded}"
            );
        } else {
            let named = decoded
                .split(|c: char| !c.is_alphanumeric() && c != '_')
                .any(|w| w == variant);
            assert!(named, "{ctx}: {decoded} has no {variant}");
        }
        return;
    }
    // `[field][,] [zigzag] value [unit | f64 LE]`, each part optional but one.
    let words: Vec<&str> = note.split([' ', ',']).filter(|w| !w.is_empty()).collect();
    let mut words = words.as_slice();
    let field = words
        .first()
        .filter(|w| w.chars().all(|c| c.is_ascii_lowercase() || c == '_') && **w != "zigzag")
        .copied();
    if field.is_some() {
        words = &words[1..];
    }
    let zig = words.first() == Some(&"zigzag");
    if zig {
        words = &words[1..];
    }
    let value = words.first().copied();
    let unit = &words.get(1..).unwrap_or(&[]).join(" ");
    let shown = match (field, value) {
        (Some("len"), Some(v)) => {
            assert_eq!(bytes, varint(v.parse().unwrap()), "{ctx}");
            return;
        }
        (_, None) => None,
        (_, Some(v)) if unit == "f64 LE" => {
            let x: f64 = v.parse().unwrap_or_else(|_| panic!("{ctx}: {v:?}"));
            assert_eq!(bytes, x.to_le_bytes(), "{ctx}");
            Some(format!("{x:?}"))
        }
        (_, Some(v)) if unit == "f32 LE" => {
            let x: f32 = v.parse().unwrap_or_else(|_| panic!("{ctx}: {v:?}"));
            assert_eq!(bytes, x.to_le_bytes(), "{ctx}");
            Some(format!("{x:?}"))
        }
        (_, Some(b @ ("true" | "false"))) => {
            assert_eq!(bytes, [u8::from(b == "true")], "{ctx}");
            Some(b.to_string())
        }
        (_, Some(v)) => {
            let n: i64 = v
                .replace('−', "-")
                .parse()
                .unwrap_or_else(|_| panic!("{ctx}: {v:?} is not a value"));
            let wire = if zig { zigzag(n) } else { n as u64 };
            assert_eq!(bytes, varint(wire), "{ctx}");
            assert!(
                unit.is_empty() || unit == "mHz",
                "{ctx}: unknown unit {unit:?}"
            );
            Some(n.to_string())
        }
    };
    match (field, shown) {
        (Some(f), Some(v)) => assert!(decoded.contains(&format!("{f}: {v}")), "{ctx}: {decoded}"),
        (Some(f), None) => assert!(decoded.contains(&format!("{f}: ")), "{ctx}: {decoded}"),
        (None, Some(v)) => assert!(decoded.contains(&v), "{ctx}: {decoded}"),
        (None, None) => panic!("{ctx}: an annotation that says nothing checkable"),
    }
}

/// Checks an example's `body:` line: its bytes are the frame's body, every run of bytes is
/// annotated, the CRC is the body's.
fn check_body(e: &Example, body: &[u8], decoded: &str) {
    let mut bytes = Vec::new();
    let mut run_start = 0;
    let mut crc_at = None;
    let mut annotated_crc = false;
    for t in tokens(&e.body) {
        match t {
            Token::Byte(b) => bytes.push(b),
            Token::Note(note) => {
                check_note(&note, &bytes[run_start..], run_start, decoded, &e.title);
                run_start = bytes.len();
            }
            Token::Bar => assert_eq!(
                run_start,
                bytes.len(),
                "{}: bytes without an annotation before a `|`: {:02x?}",
                e.title,
                &bytes[run_start..]
            ),
            Token::Crc => {
                assert_eq!(run_start, bytes.len(), "{}: unannotated bytes", e.title);
                crc_at = Some(bytes.len());
                annotated_crc = true;
            }
        }
    }
    assert_eq!(
        bytes, body,
        "{}: the body: line is not the frame's body",
        e.title
    );
    let crc_at = crc_at.unwrap_or_else(|| panic!("{}: no CRC", e.title));
    assert!(
        annotated_crc && crc_at + 4 == body.len(),
        "{}: the CRC is the last 4 bytes",
        e.title
    );
    assert_eq!(
        &body[crc_at..],
        FRAME_CRC.checksum(&body[..crc_at]).to_le_bytes(),
        "{}: the annotated CRC",
        e.title
    );
}

fn body_of(frame: &[u8]) -> Vec<u8> {
    let mut decoder = FrameDecoder::new();
    let mut bodies = Vec::new();
    for &b in frame {
        if let Some(r) = decoder.push(b) {
            bodies.push(r.expect("the frame decodes").to_vec());
        }
    }
    assert_eq!(bodies.len(), 1, "one frame, delimited: {frame:02x?}");
    bodies.pop().unwrap()
}

fn check_examples(chapter: &str) {
    let examples = examples(chapter);
    let messages = messages();
    let titles: Vec<&str> = examples.iter().map(|e| e.title.as_str()).collect();
    let known: Vec<&str> = messages.iter().map(|(t, _)| *t).collect();
    assert_eq!(
        titles, known,
        "the chapter's examples and this test's messages"
    );
    for (e, (_, message)) in examples.iter().zip(&messages) {
        let frame = hex_bytes(&e.frame);
        assert_eq!(frame, message.frame(), "{}: the frame: line", e.title);
        let body = body_of(&frame);
        check_body(e, &body, &message.decoded(&body));
        if let Some(cobs) = &e.cobs {
            assert_eq!(hex_bytes(cobs), frame, "{}: the COBS: line", e.title);
        }
    }
}

#[test]
fn the_chapter_s_example_frames_and_annotations_are_what_the_library_says() {
    check_examples(CHAPTER);
}

/// The check fails on a wrong byte, a stale version or CRC, and a wrong annotation: each
/// mutation of the chapter below must be caught.
#[test]
fn a_wrong_byte_or_annotation_in_the_chapter_is_caught() {
    let mutations = [
        // A frame byte.
        (
            "frame: 02 0c 05 f3 5d 6c ed 00",
            "frame: 02 0c 05 f3 5d 6c ee 00",
        ),
        // The version before the current one, with its CRC.
        (
            "body:  0c (version) | 00 (Status) | CRC f3 5d 6c ed",
            "body:  0b (version) | 00 (Status) | CRC 34 cb 2d a2",
        ),
        // A CRC alone.
        ("| CRC 6c cc bf 61", "| CRC 6c cc bf 62"),
        // A variant's name.
        ("0a (Field::Ki)", "0a (Field::Kp)"),
        ("00 (Ack)", "00 (Nack)"),
        // A field's name and a value.
        ("96 01 (samples 150)", "96 01 (count 150)"),
        ("0a (pre_trigger 10)", "0a (pre_trigger 11)"),
        ("c8 01 (zigzag 100)", "c8 01 (zigzag 101)"),
        ("(25000.0, f64 LE)", "(25000.5, f64 LE)"),
        ("(mask: setpoint, sensor)", "(mask: setpoint, left)"),
        ("01 (start_stream true)", "01 (start_stream false)"),
        // A byte moved out of its annotation.
        ("90 4e (frequency_mhz 10000)", "90 (frequency_mhz 10000) 4e"),
    ];
    for (from, to) in mutations {
        assert!(CHAPTER.contains(from), "the chapter lacks {from:?}");
        let mutated = CHAPTER.replacen(from, to, 1);
        let caught = std::panic::catch_unwind(|| check_examples(&mutated)).is_err();
        assert!(caught, "{from:?} → {to:?} was not caught");
    }
}

const RECORDING: &str = include_str!("../docs/src/guide/recording.md");

/// The number written just before `phrase` in `text` (whitespace collapsed; digits grouped by
/// spaces, "15 872"), for every occurrence of `phrase`.
fn numbers_before(text: &str, phrase: &str) -> Vec<Option<u64>> {
    let text = text.split_whitespace().collect::<Vec<_>>().join(" ");
    text.match_indices(phrase)
        .map(|(at, _)| {
            let words: Vec<&str> = text[..at].split(' ').collect();
            let digits: String = words
                .iter()
                .rev()
                .skip_while(|w| w.is_empty())
                .take_while(|w| !w.is_empty() && w.chars().all(|c| c.is_ascii_digit()))
                .collect::<Vec<_>>()
                .into_iter()
                .rev()
                .copied()
                .collect();
            digits.parse().ok()
        })
        .collect()
}

/// Where the book states a record's limit, and the constant of the image it names.
fn record_limits() -> [(&'static str, &'static str, &'static str, usize); 4] {
    use twinstack::services::recorder::{EMULATOR_RECORD_CAPACITY, RECORD_CAPACITY};
    [
        (
            "protocol",
            CHAPTER,
            "values on the board (`recorder::RECORD_CAPACITY`)",
            RECORD_CAPACITY,
        ),
        (
            "protocol",
            CHAPTER,
            "in the QEMU image (`recorder::EMULATOR_RECORD_CAPACITY`",
            EMULATOR_RECORD_CAPACITY,
        ),
        ("recording", RECORDING, "on the board, ", RECORD_CAPACITY),
        (
            "recording",
            RECORDING,
            "in the QEMU image), `--decimation",
            EMULATOR_RECORD_CAPACITY,
        ),
    ]
}

fn check_record_limits(pages: &[(&str, &str)]) -> Result<(), String> {
    for (page, _, phrase, constant) in record_limits() {
        let text = pages.iter().find(|(p, _)| *p == page).unwrap().1;
        let found = numbers_before(text, phrase);
        if found.is_empty() {
            return Err(format!("{page}: no limit before {phrase:?}"));
        }
        for n in found {
            if n != Some(constant as u64) {
                return Err(format!(
                    "{page}: {n:?} before {phrase:?}, the image's {constant}"
                ));
            }
        }
    }
    // The capture's length at the board's default rate, from the same constant.
    let secs = format!(
        "{:.2} s at 50 kHz",
        twinstack::services::recorder::RECORD_CAPACITY as f64 / 50_000.0
    );
    let chapter = pages[0].1.split_whitespace().collect::<Vec<_>>().join(" ");
    if !chapter.contains(&format!("(`recorder::RECORD_CAPACITY`): {secs}")) {
        return Err(format!("protocol: the record's length is not {secs}"));
    }
    Ok(())
}

/// The record limits the book states, one figure per image (the board's and the QEMU
/// image's), are the constants each image refuses a longer record with: a change of the
/// buffer that moves them fails here until the pages say the new figure.
#[test]
fn the_record_limits_the_book_states_are_each_image_s_constants() {
    let pages = [("protocol", CHAPTER), ("recording", RECORDING)];
    check_record_limits(&pages).unwrap();
    // A stale figure is caught, on either page and for either image.
    let board = twinstack::services::recorder::RECORD_CAPACITY;
    let stale = |n: usize| {
        let s = n.to_string();
        let (hi, lo) = s.split_at(s.len() - 3);
        format!("{hi} {lo}")
    };
    for (page, text, phrase, constant) in record_limits() {
        let text = text.split_whitespace().collect::<Vec<_>>().join(" ");
        let (right, stale) = (
            format!("{} {phrase}", stale(constant)),
            format!("{} {phrase}", stale(constant + 512)),
        );
        let wrong = text.replacen(&right, &stale, 1);
        assert_ne!(wrong, text, "{page}: the book writes {right:?}");
        let mutated: Vec<(&str, &str)> = pages
            .iter()
            .map(|&(p, t)| (p, if p == page { wrong.as_str() } else { t }))
            .collect();
        assert!(
            check_record_limits(&mutated).is_err(),
            "{page}: a stale {phrase:?} figure passes"
        );
    }
    assert!(board > twinstack::services::recorder::EMULATOR_RECORD_CAPACITY);
}

/// The settings chapter's example of the tick budget's refusal
/// (`docs/src/reference/settings.md`) is what the library says for the configuration it
/// names — a P–I of `OPERATORS` operators as the compensator (no observer), a sensor, PI
/// feedback with a notch, closed loop, at 100 kHz — and the largest P–I that fits there is the
/// one it names.
#[test]
fn the_settings_chapters_refusal_example_is_the_librarys() {
    use twinstack::board::Hardware;
    use twinstack::config::settings::{
        representative_pi, FeedbackSettings, Mode, NotchDesign, Settings,
    };
    const OPERATORS: usize = 32;
    let chapter = include_str!("../docs/src/reference/settings.md");
    let at = |n: usize| {
        let pi = representative_pi(n).unwrap();
        let defaults = Settings::default();
        Settings {
            compensator: Some(pi),
            observer: None,
            sensor: defaults.sensor,
            feedback: Some(FeedbackSettings {
                notch: Some(NotchDesign {
                    frequency_hz: 2_000.0,
                    q: 2.0,
                    depth: 0.1,
                }),
                ..FeedbackSettings::pi(0.2, 500.0, 0.1)
            }),
            mode: Mode::ClosedLoop,
            ..defaults
        }
        .build(&Hardware::driver_board(100_000.0))
    };
    let refusal = at(OPERATORS).expect_err("refused at 100 kHz");
    let said = format!("refused: {refusal}");
    let flat = |s: &str| s.split_whitespace().collect::<Vec<_>>().join(" ");
    let example = chapter
        .split("```text\n")
        .skip(1)
        .filter_map(|rest| rest.split("```").next())
        .find(|block| block.starts_with("refused:"))
        .expect("the chapter's text block of a refusal");
    assert_eq!(flat(example), flat(&said));
    let fits = (1..OPERATORS).rev().find(|&n| at(n).is_ok()).unwrap();
    let named = format!(
        "for a {OPERATORS}-operator P–I as the compensator, without an observer, with the notch at 100 kHz ({fits} operators fit)"
    );
    assert!(
        flat(chapter).contains(&named),
        "the chapter should say: {named}"
    );
}
