//! The parameter record kept in a flash sector: a versioned, CRC-protected envelope around a
//! payload of settings.
//!
//! Layout (all integers little-endian):
//!
//! | offset | size | field | meaning |
//! |--------|------|-------|---------|
//! | 0 | 4 | magic | [`MAGIC`], `b"TWST"` |
//! | 4 | 2 | version | layout version of the payload ([`BoardSettings::VERSION`] for ours) |
//! | 6 | 2 | length | payload length in bytes, at most [`MAX_PAYLOAD`] |
//! | 8 | length | payload | the settings |
//! | 8 + length | 4 | crc | CRC-32 (IEEE 802.3, reflected, as in zlib) of bytes `0 .. 8 + length` |
//!
//! The firmware reads the record at boot ([`load_settings`]); anything wrong with it (erased
//! sector, wrong magic, unknown version, truncated, bad CRC, a setting out of range) gives the
//! compiled-in defaults and a [`ParamSource::Defaults`] flag that the status reply shows, never
//! a half-read configuration. Everything here is host-testable; only reading the sector's bytes
//! is board code (`hardware::param_flash`).

use core::fmt;

pub use crate::drive::SafeState;

/// First four bytes of a record.
pub const MAGIC: [u8; 4] = *b"TWST";
/// Bytes before the payload: magic, version, length.
pub const HEADER_LEN: usize = 8;
/// Bytes of the trailing CRC-32.
pub const CRC_LEN: usize = 4;
/// Largest payload a record may carry (keeps a record well inside one flash sector and lets
/// the loader read a bounded window).
pub const MAX_PAYLOAD: usize = 1024;
/// Largest encoded record.
pub const MAX_RECORD: usize = HEADER_LEN + MAX_PAYLOAD + CRC_LEN;

/// Why a record was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum StoreError {
    /// The header reads all `0xFF`: the sector is erased, nothing was ever stored.
    Erased,
    /// The first four bytes are not [`MAGIC`].
    BadMagic,
    /// The record's version is not the one this firmware reads.
    UnsupportedVersion {
        /// Version in the record.
        found: u16,
        /// Version this firmware reads.
        expected: u16,
    },
    /// The length field exceeds [`MAX_PAYLOAD`].
    PayloadTooLong {
        /// Length in the record (or of the payload to encode).
        length: usize,
    },
    /// Fewer bytes than the header and length field promise.
    Truncated {
        /// Bytes the record needs.
        needed: usize,
        /// Bytes available.
        available: usize,
    },
    /// The stored CRC does not match the record's contents.
    BadCrc {
        /// CRC stored in the record.
        stored: u32,
        /// CRC computed over the record.
        computed: u32,
    },
    /// The output buffer cannot hold the encoded record.
    BufferTooSmall {
        /// Bytes the record needs.
        needed: usize,
        /// Bytes available.
        available: usize,
    },
}

impl fmt::Display for StoreError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            StoreError::Erased => write!(f, "parameter sector is erased (no record stored)"),
            StoreError::BadMagic => {
                write!(f, "parameter record: bad magic (not a twinstack record)")
            }
            StoreError::UnsupportedVersion { found, expected } => write!(
                f,
                "parameter record: version {found}, this firmware reads version {expected}"
            ),
            StoreError::PayloadTooLong { length } => write!(
                f,
                "parameter record: payload length {length} exceeds {MAX_PAYLOAD} bytes"
            ),
            StoreError::Truncated { needed, available } => write!(
                f,
                "parameter record truncated: needs {needed} bytes, {available} available"
            ),
            StoreError::BadCrc { stored, computed } => write!(
                f,
                "parameter record: CRC mismatch (stored {stored:#010x}, computed {computed:#010x})"
            ),
            StoreError::BufferTooSmall { needed, available } => write!(
                f,
                "output buffer too small for the record: needs {needed} bytes, has {available}"
            ),
        }
    }
}

/// CRC-32 (IEEE 802.3 polynomial `0x04C11DB7`, reflected, initial value and final XOR
/// `0xFFFF_FFFF`: CRC-32/ISO-HDLC, the zlib / Ethernet CRC, the same as the protocol's frames).
pub fn crc32(bytes: &[u8]) -> u32 {
    const CRC: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);
    CRC.checksum(bytes)
}

/// Writes a record holding `payload` (layout version `version`) into `out`; returns the number
/// of bytes written. Nothing is written if the payload is too long or `out` too small.
pub fn encode(version: u16, payload: &[u8], out: &mut [u8]) -> Result<usize, StoreError> {
    if payload.len() > MAX_PAYLOAD {
        return Err(StoreError::PayloadTooLong {
            length: payload.len(),
        });
    }
    let total = HEADER_LEN + payload.len() + CRC_LEN;
    if out.len() < total {
        return Err(StoreError::BufferTooSmall {
            needed: total,
            available: out.len(),
        });
    }
    let body_end = HEADER_LEN + payload.len();
    out[0..4].copy_from_slice(&MAGIC);
    out[4..6].copy_from_slice(&version.to_le_bytes());
    // payload.len() <= MAX_PAYLOAD < 2^16.
    out[6..8].copy_from_slice(&(payload.len() as u16).to_le_bytes());
    out[HEADER_LEN..body_end].copy_from_slice(payload);
    let crc = crc32(&out[..body_end]);
    out[body_end..total].copy_from_slice(&crc.to_le_bytes());
    Ok(total)
}

/// Checks a record (which may be followed by anything, e.g. the rest of the sector) and
/// returns its payload. `expected_version` is the only version accepted.
pub fn decode(record: &[u8], expected_version: u16) -> Result<&[u8], StoreError> {
    if record.len() < HEADER_LEN {
        if !record.is_empty() && record.iter().all(|&b| b == 0xFF) {
            return Err(StoreError::Erased);
        }
        return Err(StoreError::Truncated {
            needed: HEADER_LEN,
            available: record.len(),
        });
    }
    let header = &record[..HEADER_LEN];
    if header.iter().all(|&b| b == 0xFF) {
        return Err(StoreError::Erased);
    }
    if header[0..4] != MAGIC {
        return Err(StoreError::BadMagic);
    }
    let version = u16::from_le_bytes([header[4], header[5]]);
    if version != expected_version {
        return Err(StoreError::UnsupportedVersion {
            found: version,
            expected: expected_version,
        });
    }
    let length = u16::from_le_bytes([header[6], header[7]]) as usize;
    if length > MAX_PAYLOAD {
        return Err(StoreError::PayloadTooLong { length });
    }
    let body_end = HEADER_LEN + length;
    let total = body_end + CRC_LEN;
    if record.len() < total {
        return Err(StoreError::Truncated {
            needed: total,
            available: record.len(),
        });
    }
    let stored = u32::from_le_bytes([
        record[body_end],
        record[body_end + 1],
        record[body_end + 2],
        record[body_end + 3],
    ]);
    let computed = crc32(&record[..body_end]);
    if stored != computed {
        return Err(StoreError::BadCrc { stored, computed });
    }
    Ok(&record[HEADER_LEN..body_end])
}

/// The board settings the parameter record holds (payload layout [`BoardSettings::VERSION`]).
///
/// Payload: `tick_rate_hz: u32 LE`, `safe_state: u8` (0 = zero, 1 = bias).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct BoardSettings {
    /// Control interrupt rate, Hz, within [`BoardSettings::MIN_TICK_RATE_HZ`] ..=
    /// [`BoardSettings::MAX_TICK_RATE_HZ`].
    pub tick_rate_hz: u32,
    /// Output state on panic or hard fault.
    pub safe_state: SafeState,
}

/// Why a settings payload was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SettingsError {
    /// The payload is not [`BoardSettings::PAYLOAD_LEN`] bytes long.
    WrongLength {
        /// Bytes in the payload.
        length: usize,
    },
    /// `tick_rate_hz` is outside 10–100 kHz.
    TickRateOutOfRange {
        /// The stored rate, Hz.
        tick_rate_hz: u32,
    },
    /// `safe_state` is neither 0 (zero) nor 1 (bias).
    UnknownSafeState {
        /// The stored byte.
        code: u8,
    },
}

impl fmt::Display for SettingsError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            SettingsError::WrongLength { length } => write!(
                f,
                "settings payload is {length} bytes, expected {}",
                BoardSettings::PAYLOAD_LEN
            ),
            SettingsError::TickRateOutOfRange { tick_rate_hz } => write!(
                f,
                "tick_rate_hz = {tick_rate_hz} is outside {}..={}",
                BoardSettings::MIN_TICK_RATE_HZ,
                BoardSettings::MAX_TICK_RATE_HZ
            ),
            SettingsError::UnknownSafeState { code } => {
                write!(f, "safe_state = {code}: expected 0 (zero) or 1 (bias)")
            }
        }
    }
}

impl BoardSettings {
    /// Payload layout version written into the record.
    pub const VERSION: u16 = 1;
    /// Encoded payload length.
    pub const PAYLOAD_LEN: usize = 5;
    /// Slowest control rate, Hz.
    pub const MIN_TICK_RATE_HZ: u32 = 10_000;
    /// Fastest control rate, Hz.
    pub const MAX_TICK_RATE_HZ: u32 = 100_000;
    /// The compiled-in defaults: 50 kHz, safe state = bias.
    pub const DEFAULT: BoardSettings = BoardSettings {
        tick_rate_hz: 50_000,
        safe_state: SafeState::Bias,
    };

    /// Checks the settings are within range.
    pub fn validate(&self) -> Result<(), SettingsError> {
        if !(Self::MIN_TICK_RATE_HZ..=Self::MAX_TICK_RATE_HZ).contains(&self.tick_rate_hz) {
            return Err(SettingsError::TickRateOutOfRange {
                tick_rate_hz: self.tick_rate_hz,
            });
        }
        Ok(())
    }

    /// The payload bytes.
    pub fn to_payload(&self) -> [u8; Self::PAYLOAD_LEN] {
        let r = self.tick_rate_hz.to_le_bytes();
        let s = match self.safe_state {
            SafeState::Zero => 0,
            SafeState::Bias => 1,
        };
        [r[0], r[1], r[2], r[3], s]
    }

    /// Parses and validates a payload.
    pub fn from_payload(payload: &[u8]) -> Result<Self, SettingsError> {
        let &[r0, r1, r2, r3, s] = payload else {
            return Err(SettingsError::WrongLength {
                length: payload.len(),
            });
        };
        let safe_state = match s {
            0 => SafeState::Zero,
            1 => SafeState::Bias,
            code => return Err(SettingsError::UnknownSafeState { code }),
        };
        let settings = Self {
            tick_rate_hz: u32::from_le_bytes([r0, r1, r2, r3]),
            safe_state,
        };
        settings.validate()?;
        Ok(settings)
    }
}

/// Where the running settings came from (shown in the status reply).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ParamSource {
    /// A valid record was loaded from flash.
    Stored,
    /// The record was missing or invalid; the compiled-in defaults run.
    Defaults(LoadFailure),
}

/// Why the stored record was not used.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum LoadFailure {
    /// The envelope was refused (erased, magic, version, length, CRC).
    Record(StoreError),
    /// The envelope was sound but a setting was out of range.
    Settings(SettingsError),
}

impl ParamSource {
    /// Short, stable word for the status reply: `stored`, `erased`, `bad-magic`, `bad-version`,
    /// `bad-length`, `truncated`, `bad-crc`, `bad-settings`.
    pub fn as_str(&self) -> &'static str {
        match self {
            ParamSource::Stored => "stored",
            ParamSource::Defaults(LoadFailure::Record(e)) => match e {
                StoreError::Erased => "erased",
                StoreError::BadMagic => "bad-magic",
                StoreError::UnsupportedVersion { .. } => "bad-version",
                StoreError::PayloadTooLong { .. } | StoreError::BufferTooSmall { .. } => {
                    "bad-length"
                }
                StoreError::Truncated { .. } => "truncated",
                StoreError::BadCrc { .. } => "bad-crc",
            },
            ParamSource::Defaults(LoadFailure::Settings(_)) => "bad-settings",
        }
    }
}

/// Payload layout version of a record that also holds a parameter set (written by the
/// protocol's `StoreParams`): the 5 bytes of [`BoardSettings`], then the parameter set,
/// `postcard`-encoded (`protocol::messages::ParamSet`).
pub const PARAMS_VERSION: u16 = 2;

/// The record's payload, of either layout: ([`BoardSettings`] bytes, parameter-set bytes —
/// empty for a version-1 record).
pub fn decode_payload(record: &[u8]) -> Result<(&[u8], &[u8]), StoreError> {
    match decode(record, BoardSettings::VERSION) {
        Ok(payload) => Ok((payload, &[])),
        Err(StoreError::UnsupportedVersion { found, .. }) if found == PARAMS_VERSION => {
            let payload = decode(record, PARAMS_VERSION)?;
            Ok(payload.split_at(payload.len().min(BoardSettings::PAYLOAD_LEN)))
        }
        Err(e) => Err(e),
    }
}

/// Where the parameter record lives: a flash sector on the board, RAM in the simulator.
pub trait RecordStorage {
    /// The stored bytes (the record, possibly followed by anything; all `0xFF` when erased).
    fn read(&self) -> &[u8];
    /// Replaces the record with `record` (erase, program, read back).
    fn write(&mut self, record: &[u8]) -> Result<(), StorageError>;
}

/// Why a record could not be written.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum StorageError {
    /// This board has no writable parameter storage.
    Unavailable,
    /// The erase or the programming failed, or the read-back differs.
    WriteFailed,
}

/// Parameter storage in RAM (the simulated board; tests): starts erased.
#[derive(Clone, Debug)]
pub struct RamStorage {
    bytes: [u8; MAX_RECORD],
}

impl Default for RamStorage {
    fn default() -> Self {
        Self {
            bytes: [0xFF; MAX_RECORD],
        }
    }
}

impl RecordStorage for RamStorage {
    fn read(&self) -> &[u8] {
        &self.bytes
    }

    fn write(&mut self, record: &[u8]) -> Result<(), StorageError> {
        let slot = self
            .bytes
            .get_mut(..record.len())
            .ok_or(StorageError::WriteFailed)?;
        slot.copy_from_slice(record);
        if let Some(rest) = self.bytes.get_mut(record.len()..) {
            rest.fill(0xFF);
        }
        Ok(())
    }
}

/// No writable storage: reads as erased (or as the given read-only bytes), refuses writes.
#[derive(Clone, Copy, Debug)]
pub struct ReadOnlyStorage<'a>(pub &'a [u8]);

impl RecordStorage for ReadOnlyStorage<'_> {
    fn read(&self) -> &[u8] {
        self.0
    }

    fn write(&mut self, _record: &[u8]) -> Result<(), StorageError> {
        Err(StorageError::Unavailable)
    }
}

/// Reads the settings from a record (the bytes of the parameter sector): the stored settings
/// when the record is sound, otherwise [`BoardSettings::DEFAULT`] and the reason. Records of
/// both layouts ([`BoardSettings::VERSION`], [`PARAMS_VERSION`]) are read.
pub fn load_settings(sector: &[u8]) -> (BoardSettings, ParamSource) {
    match decode_payload(sector).map(|(settings, _)| settings) {
        Err(e) => (
            BoardSettings::DEFAULT,
            ParamSource::Defaults(LoadFailure::Record(e)),
        ),
        Ok(payload) => match BoardSettings::from_payload(payload) {
            Ok(s) => (s, ParamSource::Stored),
            Err(e) => (
                BoardSettings::DEFAULT,
                ParamSource::Defaults(LoadFailure::Settings(e)),
            ),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn record_of(settings: &BoardSettings) -> ([u8; MAX_RECORD], usize) {
        let mut buf = [0u8; MAX_RECORD];
        let n = encode(BoardSettings::VERSION, &settings.to_payload(), &mut buf).unwrap();
        (buf, n)
    }

    #[test]
    fn crc32_matches_the_standard_check_value() {
        // The catalogue check value of CRC-32/ISO-HDLC (zlib) for "123456789".
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc32(b""), 0);
    }

    #[test]
    fn a_stored_record_loads_its_settings() {
        let s = BoardSettings {
            tick_rate_hz: 100_000,
            safe_state: SafeState::Zero,
        };
        let (buf, n) = record_of(&s);
        assert_eq!(load_settings(&buf[..n]), (s, ParamSource::Stored));
        // Trailing sector bytes after the record are ignored.
        assert_eq!(load_settings(&buf), (s, ParamSource::Stored));
    }

    #[test]
    fn bad_crc_gives_defaults_and_says_so() {
        let (mut buf, n) = record_of(&BoardSettings {
            tick_rate_hz: 20_000,
            safe_state: SafeState::Zero,
        });
        buf[HEADER_LEN] ^= 0x01;
        let (settings, source) = load_settings(&buf[..n]);
        assert_eq!(settings, BoardSettings::DEFAULT);
        assert!(matches!(
            source,
            ParamSource::Defaults(LoadFailure::Record(StoreError::BadCrc { .. }))
        ));
        assert_eq!(source.as_str(), "bad-crc");
    }

    #[test]
    fn bad_version_is_refused_before_the_payload_is_read() {
        let mut buf = [0u8; MAX_RECORD];
        let n = encode(7, &BoardSettings::DEFAULT.to_payload(), &mut buf).unwrap();
        assert_eq!(
            decode(&buf[..n], BoardSettings::VERSION),
            Err(StoreError::UnsupportedVersion {
                found: 7,
                expected: 1
            })
        );
        assert_eq!(load_settings(&buf[..n]).1.as_str(), "bad-version");
    }

    #[test]
    fn truncation_at_every_length_is_refused() {
        let (buf, n) = record_of(&BoardSettings::DEFAULT);
        for cut in 0..n {
            let r = decode(&buf[..cut], BoardSettings::VERSION);
            assert!(
                matches!(r, Err(StoreError::Truncated { available, .. }) if available == cut),
                "cut at {cut}: {r:?}"
            );
        }
    }

    #[test]
    fn erased_flash_and_foreign_bytes_are_told_apart() {
        assert_eq!(decode(&[0xFF; 64], 1), Err(StoreError::Erased));
        assert_eq!(decode(&[0x00; 64], 1), Err(StoreError::BadMagic));
        assert_eq!(load_settings(&[0xFF; 64]).1.as_str(), "erased");
    }

    #[test]
    fn oversized_length_field_is_refused_without_reading_past_the_buffer() {
        let mut buf = [0u8; 16];
        buf[..4].copy_from_slice(&MAGIC);
        buf[4..6].copy_from_slice(&1u16.to_le_bytes());
        buf[6..8].copy_from_slice(&u16::MAX.to_le_bytes());
        assert_eq!(
            decode(&buf, 1),
            Err(StoreError::PayloadTooLong {
                length: u16::MAX as usize
            })
        );
    }

    #[test]
    fn encode_writes_nothing_when_the_buffer_is_too_small() {
        let mut buf = [0xAAu8; 12];
        assert_eq!(
            encode(1, &[1, 2, 3], &mut buf),
            Err(StoreError::BufferTooSmall {
                needed: 15,
                available: 12
            })
        );
        assert!(buf.iter().all(|&b| b == 0xAA));
        let mut big = [0u8; MAX_RECORD + 8];
        assert_eq!(
            encode(1, &[0; MAX_PAYLOAD + 1], &mut big),
            Err(StoreError::PayloadTooLong {
                length: MAX_PAYLOAD + 1
            })
        );
    }

    #[test]
    fn out_of_range_settings_in_a_sound_record_give_defaults() {
        let mut payload = BoardSettings::DEFAULT.to_payload();
        payload[..4].copy_from_slice(&5_000u32.to_le_bytes());
        let mut buf = [0u8; MAX_RECORD];
        let n = encode(BoardSettings::VERSION, &payload, &mut buf).unwrap();
        assert_eq!(
            load_settings(&buf[..n]),
            (
                BoardSettings::DEFAULT,
                ParamSource::Defaults(LoadFailure::Settings(SettingsError::TickRateOutOfRange {
                    tick_rate_hz: 5_000
                }))
            )
        );
        assert_eq!(
            BoardSettings::from_payload(&[0x50, 0xC3, 0, 0, 9]),
            Err(SettingsError::UnknownSafeState { code: 9 })
        );
        assert_eq!(
            BoardSettings::from_payload(&[1, 2, 3]),
            Err(SettingsError::WrongLength { length: 3 })
        );
    }

    proptest! {
        #[test]
        fn any_payload_round_trips(version: u16, payload in proptest::collection::vec(any::<u8>(), 0..=MAX_PAYLOAD)) {
            let mut buf = [0u8; MAX_RECORD];
            let n = encode(version, &payload, &mut buf).unwrap();
            prop_assert_eq!(n, HEADER_LEN + payload.len() + CRC_LEN);
            prop_assert_eq!(decode(&buf[..n], version).unwrap(), &payload[..]);
        }

        #[test]
        fn any_single_bit_flip_is_detected(payload in proptest::collection::vec(any::<u8>(), 0..64), bit in any::<prop::sample::Index>()) {
            let mut buf = [0u8; MAX_RECORD];
            let n = encode(3, &payload, &mut buf).unwrap();
            let bit = bit.index(n * 8);
            buf[bit / 8] ^= 1 << (bit % 8);
            prop_assert!(decode(&buf[..n], 3).is_err());
        }

        #[test]
        fn decode_never_panics_on_arbitrary_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..2048), version: u16) {
            let _ = decode(&bytes, version);
            let _ = load_settings(&bytes);
        }

        #[test]
        fn valid_settings_round_trip(rate in BoardSettings::MIN_TICK_RATE_HZ..=BoardSettings::MAX_TICK_RATE_HZ, bias: bool) {
            let s = BoardSettings { tick_rate_hz: rate, safe_state: if bias { SafeState::Bias } else { SafeState::Zero } };
            prop_assert_eq!(BoardSettings::from_payload(&s.to_payload()), Ok(s));
        }
    }
}
