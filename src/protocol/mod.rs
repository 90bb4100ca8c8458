//! The UART protocol: COBS-delimited, CRC-checked frames carrying `postcard` messages.
//!
//! * [`cobs`] — byte stuffing, so `0x00` delimits frames;
//! * [`frame`] — the frame layout (version, message, CRC-32) and its errors;
//! * [`decoder`] — the receiver's byte-at-a-time frame decoder;
//! * [`messages`] — requests, responses and NACK reasons.

pub mod cobs;
pub mod decoder;
pub mod frame;
pub mod messages;
