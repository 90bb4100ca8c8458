//! The firmware's minimal status query on USART1, until the protocol issue defines frames.
//!
//! **Request**: the single byte `?` ([`STATUS_REQUEST`]). Every other byte is ignored (and
//! counted).
//!
//! **Reply**: one ASCII line,
//!
//! ```text
//! twinstack status ticks=<u32> overruns=<u32> underruns=<u32> rate_hz=<u32> params=<word>\n
//! ```
//!
//! `ticks` counts control ticks since boot (wrapping), `overruns` ticks that did not finish
//! before the next one was due, `underruns` ticks that found the setpoint queue empty,
//! `rate_hz` the control rate, and `params` where the settings came from
//! ([`crate::param_store::ParamSource::as_str`]: `stored`, or why the defaults run).
//!
//! The firmware only talks to this module through [`RequestDecoder::push`] and
//! [`StatusReport::write_line`], so the protocol issue can replace both without touching the
//! board code. [`StatusReport::parse_line`] is the host's side (tests, tools).

use core::fmt::Write as _;

use crate::param_store::ParamSource;

/// The request byte: ASCII `?`.
pub const STATUS_REQUEST: u8 = b'?';
/// Longest reply line, bytes (all fields at their maximum width, plus the newline).
pub const MAX_LINE: usize = 128;
/// First words of every reply line.
pub const LINE_PREFIX: &str = "twinstack status ";

/// A request the decoder recognised.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Request {
    /// Send a [`StatusReport`].
    Status,
}

/// Turns received bytes into requests, one byte at a time.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RequestDecoder {
    ignored: u32,
}

impl RequestDecoder {
    /// A decoder that has ignored nothing yet.
    pub const fn new() -> Self {
        Self { ignored: 0 }
    }

    /// Feeds one received byte; returns the request it completes, if any.
    pub fn push(&mut self, byte: u8) -> Option<Request> {
        if byte == STATUS_REQUEST {
            Some(Request::Status)
        } else {
            self.ignored = self.ignored.wrapping_add(1);
            None
        }
    }

    /// Bytes that were not part of a request.
    pub fn ignored(&self) -> u32 {
        self.ignored
    }
}

/// The counters and flags a status reply carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StatusReport {
    /// Control ticks since boot (wrapping).
    pub ticks: u32,
    /// Ticks that did not finish before the next was due.
    pub overruns: u32,
    /// Ticks that found the setpoint queue empty.
    pub underruns: u32,
    /// Control rate, Hz.
    pub tick_rate_hz: u32,
    /// Where the settings came from.
    pub params: ParamSource,
}

/// A reply line as the host received it (the `params` word kept as text).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ParsedStatus<'a> {
    /// Control ticks since boot.
    pub ticks: u32,
    /// Overrun count.
    pub overruns: u32,
    /// Underrun count.
    pub underruns: u32,
    /// Control rate, Hz.
    pub tick_rate_hz: u32,
    /// `params` word (`stored`, `erased`, `bad-crc`, …).
    pub params: &'a str,
}

/// Why a reply line could not be parsed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StatusParseError {
    /// The line does not start with [`LINE_PREFIX`].
    MissingPrefix,
    /// A `key=value` field is missing.
    MissingField(&'static str),
    /// A numeric field does not parse as `u32`.
    BadNumber(&'static str),
}

impl core::fmt::Display for StatusParseError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            StatusParseError::MissingPrefix => {
                write!(f, "status line does not start with {LINE_PREFIX:?}")
            }
            StatusParseError::MissingField(k) => write!(f, "status line has no field `{k}`"),
            StatusParseError::BadNumber(k) => write!(f, "status field `{k}` is not a u32"),
        }
    }
}

impl StatusReport {
    /// Formats the reply line (ending in `\n`) into `out`; returns its length.
    pub fn write_line(&self, out: &mut [u8; MAX_LINE]) -> usize {
        let mut line: heapless::String<MAX_LINE> = heapless::String::new();
        // The longest line is well under MAX_LINE bytes (five u32 fields of at most 10
        // digits, a word of at most 12 characters), so the write cannot run out of room.
        let _ = writeln!(
            line,
            "{LINE_PREFIX}ticks={} overruns={} underruns={} rate_hz={} params={}",
            self.ticks,
            self.overruns,
            self.underruns,
            self.tick_rate_hz,
            self.params.as_str()
        );
        let bytes = line.as_bytes();
        out[..bytes.len()].copy_from_slice(bytes);
        bytes.len()
    }

    /// Parses a reply line (with or without its newline).
    pub fn parse_line(line: &str) -> Result<ParsedStatus<'_>, StatusParseError> {
        let rest = line
            .trim_end()
            .strip_prefix(LINE_PREFIX)
            .ok_or(StatusParseError::MissingPrefix)?;
        let field = |key: &'static str| -> Result<&str, StatusParseError> {
            rest.split(' ')
                .find_map(|kv| kv.strip_prefix(key).and_then(|v| v.strip_prefix('=')))
                .ok_or(StatusParseError::MissingField(key))
        };
        let number = |key: &'static str| -> Result<u32, StatusParseError> {
            field(key)?
                .parse()
                .map_err(|_| StatusParseError::BadNumber(key))
        };
        Ok(ParsedStatus {
            ticks: number("ticks")?,
            overruns: number("overruns")?,
            underruns: number("underruns")?,
            tick_rate_hz: number("rate_hz")?,
            params: field("params")?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::param_store::{LoadFailure, StoreError};
    use proptest::prelude::*;

    #[test]
    fn only_the_request_byte_is_a_request() {
        let mut d = RequestDecoder::new();
        assert_eq!(d.push(b'x'), None);
        assert_eq!(d.push(b'?'), Some(Request::Status));
        assert_eq!(d.push(0), None);
        assert_eq!(d.ignored(), 2);
    }

    #[test]
    fn parse_rejects_lines_that_are_not_status_replies() {
        assert_eq!(
            StatusReport::parse_line("hello"),
            Err(StatusParseError::MissingPrefix)
        );
        assert_eq!(
            StatusReport::parse_line("twinstack status ticks=1 overruns=0"),
            Err(StatusParseError::MissingField("underruns"))
        );
        assert_eq!(
            StatusReport::parse_line(
                "twinstack status ticks=x overruns=0 underruns=0 rate_hz=1 params=stored"
            ),
            Err(StatusParseError::BadNumber("ticks"))
        );
    }

    fn source(i: u8) -> ParamSource {
        match i % 3 {
            0 => ParamSource::Stored,
            1 => ParamSource::Defaults(LoadFailure::Record(StoreError::BadCrc {
                stored: u32::MAX,
                computed: 0,
            })),
            _ => ParamSource::Defaults(LoadFailure::Record(StoreError::Erased)),
        }
    }

    proptest! {
        #[test]
        fn every_report_formats_to_a_line_that_parses_back(
            ticks: u32, overruns: u32, underruns: u32, tick_rate_hz: u32, p in 0u8..3
        ) {
            let report = StatusReport { ticks, overruns, underruns, tick_rate_hz, params: source(p) };
            let mut buf = [0u8; MAX_LINE];
            let n = report.write_line(&mut buf);
            prop_assert_eq!(buf[n - 1], b'\n');
            let text = core::str::from_utf8(&buf[..n]).unwrap();
            let parsed = StatusReport::parse_line(text).unwrap();
            prop_assert_eq!(parsed, ParsedStatus {
                ticks, overruns, underruns, tick_rate_hz, params: report.params.as_str()
            });
        }
    }
}
