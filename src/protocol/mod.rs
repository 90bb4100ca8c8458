//! The UART protocol: COBS-delimited, CRC-checked frames carrying `postcard` messages.
//!
//! * [`frame`] — the frame layout (version, message, CRC-32, COBS-stuffed by the `cobs` crate so
//!   that `0x00` delimits frames) and its errors;
//! * [`decoder`] — the receiver's byte-at-a-time frame decoder;
//! * [`messages`] — requests, responses and NACK reasons;
//! * [`handler`] — the board's command handler (bytes in, one response frame per request).

pub mod decoder;
pub mod frame;
pub mod handler;
// Message enums are sized by their largest variant on purpose: there is no heap on the board,
// and a message lives in one stack slot while it is handled.
#[allow(clippy::large_enum_variant)]
pub mod messages;
