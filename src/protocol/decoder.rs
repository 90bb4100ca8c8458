//! The receiver's side of framing: bytes in, one decoded body per delimiter out.
//!
//! Constant work per byte except at a delimiter, where the frame (at most
//! [`super::frame::MAX_ENCODED`] bytes) is un-stuffed in place by the `cobs` crate (postcard's
//! COBS), two passes over it: bounded time per byte, no allocation, no panic path. An oversize
//! frame is dropped and reported once, and the decoder picks up again at the next delimiter.
//!
//! postcard's own `CobsAccumulator` is not used: it deserializes the message straight from the
//! un-stuffed bytes, so the CRC and the version could not be checked first, and it reports
//! every failure as one `DeserError`, where a NACK names the reason ([`FrameError`]); after an
//! overflow it restarts inside the oversize frame instead of discarding up to its delimiter (a
//! long frame would be refused several times, its tail parsed as frames); and it takes two
//! delimiters in a row (how a sender resynchronises) for a frame that fails.

use super::frame::{FrameError, MAX_ENCODED};

/// Accumulates bytes until a `0x00` delimiter.
#[derive(Debug)]
pub struct FrameDecoder {
    buf: [u8; MAX_ENCODED],
    len: usize,
    overflowed: bool,
    steps: u32,
}

impl Default for FrameDecoder {
    fn default() -> Self {
        Self::new()
    }
}

impl FrameDecoder {
    /// An empty decoder.
    pub const fn new() -> Self {
        Self {
            buf: [0; MAX_ENCODED],
            len: 0,
            overflowed: false,
            steps: 0,
        }
    }

    /// Feeds one byte. At a delimiter, returns the un-stuffed body of the frame it ends (to be
    /// checked by [`super::frame::decode_body`]), or why it was refused. Empty frames (two
    /// delimiters in a row, used to resynchronise) return `None`.
    pub fn push(&mut self, byte: u8) -> Option<Result<&[u8], FrameError>> {
        self.steps = self.steps.wrapping_add(1);
        if byte != 0 {
            if let Some(slot) = self.buf.get_mut(self.len) {
                *slot = byte;
                self.len += 1;
            } else {
                self.overflowed = true;
            }
            return None;
        }
        let len = core::mem::replace(&mut self.len, 0);
        if core::mem::replace(&mut self.overflowed, false) {
            return Some(Err(FrameError::Oversize));
        }
        if len == 0 {
            return None;
        }
        let frame = self.buf.get_mut(..len)?;
        // The un-stuffing is two passes over the frame's bytes: `cobs::decode_in_place` looks
        // for a terminator (the buffer never holds one), then moves each byte once.
        self.steps = self.steps.wrapping_add(2 * len as u32);
        match cobs::decode_in_place(frame) {
            Ok(n) => frame.get(..n).map(Ok),
            Err(_) => Some(Err(FrameError::BadStuffing)),
        }
    }

    /// Work done so far (wraps): one step per byte pushed, plus two per byte of a frame
    /// un-stuffed at its delimiter. A deterministic measure of the time per byte.
    pub fn steps(&self) -> u32 {
        self.steps
    }
}
