//! The UART protocol: COBS-delimited, CRC-checked frames carrying `postcard` messages.
//!
//! * [`frame`] — the frame layout (version, message, CRC-32, COBS-stuffed by the `cobs` crate so
//!   that `0x00` delimits frames) and its errors;
//! * [`decoder`] — the receiver's byte-at-a-time frame decoder;
//! * [`messages`] — requests, responses and NACK reasons.
//!
//! The board's side of it, bytes in and one response frame per request, is
//! [`crate::command_handler`], above the tick side it commands.

pub mod decoder;
pub mod frame;
// Message enums are sized by their largest variant on purpose: there is no heap on the board,
// and a message lives in one stack slot while it is handled.
#[allow(clippy::large_enum_variant)]
pub mod messages;
