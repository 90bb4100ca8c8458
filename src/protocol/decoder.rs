//! The receiver's side of framing: bytes in, one decoded body per delimiter out.
//!
//! Constant work per byte except at a delimiter, where the frame (at most
//! [`super::frame::MAX_ENCODED`] bytes) is un-stuffed in place: bounded time per
//! byte, no allocation, no panic path. An oversize frame is dropped and reported once, and the
//! decoder picks up again at the next delimiter.

use super::cobs;
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
            if self.len < self.buf.len() {
                self.buf[self.len] = byte;
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
        match cobs::decode_in_place_counting(frame, &mut self.steps) {
            Ok(n) => frame.get(..n).map(Ok),
            Err(_) => Some(Err(FrameError::BadStuffing)),
        }
    }

    /// Work done so far, in loop iterations (one per byte pushed, plus one per byte
    /// un-stuffed at a delimiter; wraps): a deterministic measure of the time per byte.
    pub fn steps(&self) -> u32 {
        self.steps
    }
}
