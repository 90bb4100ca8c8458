//! The UART protocol: COBS-delimited, CRC-checked frames carrying `postcard` messages.
//!
//! * [`frame`] — the frame layout (version, message, CRC-32, COBS-stuffed by the `cobs` crate so
//!   that `0x00` delimits frames) and its errors;
//! * [`decoder`] — the receiver's byte-at-a-time frame decoder;
//! * [`messages`] — requests, responses and NACK reasons.
//!
//! The board's side of it, bytes in and one response frame per request, is
//! [`crate::command_handler`], above the tick side it commands.

/// The host link's line rate: USART1 at 3 Mbaud, 8N1 (300 000 bytes/s each way). The board
/// sets its UART to it (`hardware::usart::BAUD` on the target) and the host opens
/// its ports and models the simulated board's line at it.
pub const LINK_BAUD: u32 = 3_000_000;

pub mod decoder;
pub mod frame;
// Message enums are sized by their largest variant on purpose: there is no heap on the board,
// and a message lives in one stack slot while it is handled.
#[allow(clippy::large_enum_variant)]
pub mod messages;
