//! Frames on the wire: `COBS(version ‖ postcard(message) ‖ CRC-32) 0x00`.
//!
//! | field | bytes | meaning |
//! |---|---|---|
//! | version | 1 | [`PROTOCOL_VERSION`]; a frame of another version is refused |
//! | message | n | the message, `postcard`-encoded (varint enum tag, then its fields) |
//! | crc | 4 | CRC-32 (ISO-HDLC, as zlib), little-endian, over version and message |
//!
//! The whole is COBS-stuffed and ends with one `0x00`, so a receiver that lost bytes
//! resynchronises at the next delimiter.

use crc::{Crc, CRC_32_ISO_HDLC};
use serde::{Deserialize, Serialize};

/// Version byte every frame starts with. Version 2: the status report carries
/// `frame_errors`, `next_seq`, `tick_rate_hz` and `recorded`; NACK reasons `Busy`,
/// `NothingStored` and `StoreFailed` were added. Version 4: the settings end with
/// the optional creep operator (`creep`), `Field::Creep` was appended, and `Model` gained the
/// generalised P–I (`Model::GeneralisedPi`, with its `ModelField`s appended) and then
/// Bouc–Wen (`Model::BoucWen`, with the `ModelField`s `K`, `A`, `Psi` and the rule
/// `Unbounded` appended after them); the multi-signal capture (`Capture`, `CaptureStatus`,
/// `ReadCapture`, `CaptureChunk`, `Field::RecordPreTrigger`) was added. Version 5:
/// continuous telemetry (`Request::Telemetry`, the unsolicited `Response::Telemetry` frames
/// between responses, `Field::TelemetrySignals` / `TelemetryDecimation`, the status flag
/// `TELEMETRY`); `Waveform` ends with an optional amplitude decay (`decay:
/// Option<WaveDecay>`); the dual-actuated stage's coarse axis (`CoarseHome`, `CoarseMove`,
/// `CoarseJog`, `CoarseStop`, `CoarseStatus` → `Response::Coarse`; `Field::CoarseAxis` …
/// `CoarseAcceleration`, `Rule::NotHomed`, `Rule::LimitSwitch`). Version 6: learning
/// feedforward (`Request::Learn`, `Response::Learn`, the `Field`s `LearnPeriod` …
/// `LearnLimit`), the tick budget (`Field::Workload`, `Rule::TickOverrun`), scan patterns and
/// triggers (`Request::Scan`, `Request::Trigger`, the `Field`s `ScanLines` … `TriggerPulse`).
/// Version 7: the settings end with the optional
/// input shaping (`shaping: Option<NotchDesign>`, the feedforward's notch), the `Field`s
/// `ShapingFrequency`, `ShapingQ`, `ShapingDepth` were appended, and a body may be 1 568
/// bytes (the largest settings with shaping). Version 8: appended the packed setpoint batch
/// (`Request::PackedSetpoints`), `StreamControl::Finish`, `NackReason::NotOwner` and
/// TTL-stepped sequences (`Request::Sequence`, `Response::Sequence`, the `Field`s
/// `SequenceEdge` … `SequenceSettle`), then the echo (`Request::Echo`, `Response::Echo`:
/// appended, so every other encoding stays; a board without it answers `UnknownType`), then the analog setpoint input
/// (`Request::Analog`, `Response::Analog`, the `Field`s `AnalogGain` … `AnalogRate`, the status
/// flags `ANALOG` and `ANALOG_FAULT`: appended the same way), then the watchdog drill
/// (`Request::WatchdogDrill`, `NackReason::Unsupported`, the status flag `WATCHDOG_RESET`:
/// appended the same way). Version 9 appended the drift count to the status
/// (`StatusReport::drifts`): a status of another length does not decode, so a version-8
/// board and a version-9 host refuse each other's frames whole. Version 10: Bouc–Wen's
/// coefficients end with `chi` (`BoucWenParams::chi`) and `ModelField::Chi` was appended
/// (the settings' encoding changed, so versions 9 and 10 refuse each other's frames).
/// Version 11: the settings end with the optional preview (`preview: Option<PreviewDesign>`)
/// and the `Field`s `PreviewFrequency`, `PreviewDamping` were appended (the settings'
/// encoding changed again). Version 12: the settings end with the optional static output
/// map after the model (`output_map: Option<DeadZoneParams>`), the `Field` `OutputMap` and
/// the `Rule` `NoOutputMap` were appended; a body stays at most 1 568 bytes (the largest
/// settings a board accepts, two generalised P–I models, take no map; a Bouc–Wen pair with
/// one is far smaller).
pub const PROTOCOL_VERSION: u8 = 12;
/// Largest frame body (version + message + CRC), bytes: a load of the largest settings a
/// board accepts (two generalised P–I models of 32 operators and 8 dead zones, both notches,
/// the preview) fits. Each extra byte costs RAM in every frame buffer: at 1 728, for settings
/// the board would refuse anyway (those models with an output map), the dual-stage image's
/// static RAM left the stack less than its reserve.
pub const MAX_BODY: usize = 1568;
/// Largest frame on the wire, delimiter excluded: the stuffed [`MAX_BODY`]. The sender refuses
/// a body longer than [`MAX_BODY`] ([`FrameError::TooLarge`]), the receiver a frame longer than
/// this ([`FrameError::Oversize`]).
pub const MAX_ENCODED: usize = cobs::max_encoding_length(MAX_BODY);
/// The CRC used by frames.
pub const FRAME_CRC: Crc<u32> = Crc::<u32>::new(&CRC_32_ISO_HDLC);

/// Why a frame was refused. Each is answered with a NACK carrying this reason.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum FrameError {
    /// More bytes than [`MAX_ENCODED`] before a delimiter: discarded up to the next one.
    Oversize,
    /// Shorter than a version byte and a CRC.
    Truncated,
    /// The COBS stuffing is broken.
    BadStuffing,
    /// The CRC does not match.
    BadCrc,
    /// The version byte is not [`PROTOCOL_VERSION`].
    BadVersion {
        /// Version the frame carried.
        got: u8,
    },
    /// The message tag names no known message.
    UnknownType,
    /// The message's fields do not decode (too short, bad varint, trailing bytes).
    Malformed,
    /// The message does not fit a frame (sender side).
    TooLarge,
}

/// Encodes `message` as a complete frame, delimiter included, into `out`; returns its length.
pub fn encode<T: Serialize>(message: &T, out: &mut [u8]) -> Result<usize, FrameError> {
    let mut body = [0u8; MAX_BODY];
    let used = postcard::to_slice(message, &mut body[1..MAX_BODY - 4])
        .map_err(|_| FrameError::TooLarge)?
        .len();
    seal(&mut body, used, out)
}

/// Frames message bytes as they are (a tag, then its fields, postcard-encoded: nothing checks
/// that they decode) into `out`, delimiter included; returns its length. What a test that
/// mutates a message's fields sends, so that the frame passes the CRC and reaches the decoder.
///
/// ```
/// use twinstack::protocol::frame::{encode_message_bytes, MAX_ENCODED};
/// let mut out = [0u8; MAX_ENCODED + 1];
/// let n = encode_message_bytes(&[0], &mut out).unwrap(); // tag 0: Status
/// assert_eq!(out[n - 1], 0);
/// ```
pub fn encode_message_bytes(message: &[u8], out: &mut [u8]) -> Result<usize, FrameError> {
    let mut body = [0u8; MAX_BODY];
    let room = body.get_mut(1..MAX_BODY - 4).ok_or(FrameError::TooLarge)?;
    room.get_mut(..message.len())
        .ok_or(FrameError::TooLarge)?
        .copy_from_slice(message);
    seal(&mut body, message.len(), out)
}

/// Frames a body as it is (a version byte, then message bytes: nothing is checked), CRC and
/// delimiter appended, into `out`; returns its length. For tests of the receiver's refusals
/// (another version, an unknown tag), which need frames the encoder would not write.
pub fn encode_body_bytes(body: &[u8], out: &mut [u8]) -> Result<usize, FrameError> {
    let crc = FRAME_CRC.checksum(body).to_le_bytes();
    let mut whole = [0u8; MAX_BODY];
    let end = body.len() + 4;
    let whole = whole.get_mut(..end).ok_or(FrameError::TooLarge)?;
    whole[..body.len()].copy_from_slice(body);
    whole[body.len()..].copy_from_slice(&crc);
    stuff(whole, out)
}

/// Puts the version before the `used` message bytes at `body[1..]`, the CRC after them, and
/// stuffs the whole into `out` with its delimiter; returns the frame's length.
fn seal(body: &mut [u8; MAX_BODY], used: usize, out: &mut [u8]) -> Result<usize, FrameError> {
    body[0] = PROTOCOL_VERSION;
    let end = 1 + used;
    let crc = FRAME_CRC.checksum(&body[..end]);
    body[end..end + 4].copy_from_slice(&crc.to_le_bytes());
    stuff(&body[..end + 4], out)
}

/// COBS-stuffs `body` into `out` (the `cobs` crate's encoder: postcard's COBS) and appends the
/// delimiter; returns the frame's length.
///
/// Not postcard's `Cobs` and CRC serializer flavors (one pass, no body buffer): they are
/// inlined into every field's serialization of every message type, which made the board image
/// 2.4 KiB larger than one stuffing pass over a finished body.
fn stuff(body: &[u8], out: &mut [u8]) -> Result<usize, FrameError> {
    let n = cobs::try_encode(body, out).map_err(|_| FrameError::TooLarge)?;
    *out.get_mut(n).ok_or(FrameError::TooLarge)? = 0;
    Ok(n + 1)
}

/// A message enum carried in frames: its tag is a varint below [`Message::VARIANTS`].
pub trait Message {
    /// Number of variants; a tag at or above it is an unknown message type.
    const VARIANTS: u32;
}

/// Checks a decoded (un-stuffed) body's length, CRC and version, and returns its message
/// bytes (the tag, then the fields), undecoded.
pub fn message_bytes(body: &[u8]) -> Result<&[u8], FrameError> {
    if body.len() < 5 {
        return Err(FrameError::Truncated);
    }
    let (payload, crc_bytes) = body.split_at(body.len() - 4);
    let crc = u32::from_le_bytes([crc_bytes[0], crc_bytes[1], crc_bytes[2], crc_bytes[3]]);
    if FRAME_CRC.checksum(payload) != crc {
        return Err(FrameError::BadCrc);
    }
    if payload[0] != PROTOCOL_VERSION {
        return Err(FrameError::BadVersion { got: payload[0] });
    }
    Ok(payload.get(1..).unwrap_or(&[]))
}

/// Checks a decoded (un-stuffed) body and decodes its message.
pub fn decode_body<'a, T: Deserialize<'a> + Message>(body: &'a [u8]) -> Result<T, FrameError> {
    let message = message_bytes(body)?;
    // The tag is the message's first varint: one byte below 0x80, more bytes above.
    match message.first() {
        None => return Err(FrameError::Truncated),
        Some(&tag) if tag >= 0x80 || u32::from(tag) >= T::VARIANTS => {
            return Err(FrameError::UnknownType)
        }
        Some(_) => {}
    }
    match postcard::take_from_bytes::<T>(message) {
        Ok((message, [])) => Ok(message),
        _ => Err(FrameError::Malformed),
    }
}
