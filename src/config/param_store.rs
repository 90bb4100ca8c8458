//! The parameter record kept in a flash sector: a versioned, CRC-protected envelope around a
//! payload of settings.
//!
//! Layout (all integers little-endian):
//!
//! | offset | size | field | meaning |
//! |--------|------|-------|---------|
//! | 0 | 4 | magic | [`MAGIC`], `b"TWST"` |
//! | 4 | 2 | version | layout version of the payload ([`RECORD_VERSION`] for ours) |
//! | 6 | 2 | length | payload length in bytes, at most [`MAX_PAYLOAD`] |
//! | 8 | length | payload | the [`StoredRecord`], `postcard`-encoded |
//! | 8 + length | 4 | crc | CRC-32 (IEEE 802.3, reflected, as in zlib) of bytes `0 .. 8 + length` |
//!
//! The firmware reads the record at boot ([`load_record`]); anything wrong with it (erased
//! sector, wrong magic, unknown version, truncated, bad CRC, undecodable or refused settings)
//! gives the compiled-in defaults — bypass, no model — and a [`ParamSource::Defaults`] flag
//! that the status reply shows, never a half-read configuration. Everything here is host-testable; only reading the sector's bytes
//! is board code (`hardware::param_flash`).

use core::fmt;

use crate::board::Hardware;
use crate::config::settings::Settings;
use crate::control::ControlConfig;
use crate::refusal::Refusal;

/// First four bytes of a record.
pub const MAGIC: [u8; 4] = *b"TWST";
/// Bytes before the payload: magic, version, length.
pub const HEADER_LEN: usize = 8;
/// Bytes of the trailing CRC-32.
pub const CRC_LEN: usize = 4;
/// Largest payload a record may carry (keeps a record well inside one flash sector and lets
/// the loader read a bounded window).
pub const MAX_PAYLOAD: usize = 2048;
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

/// Payload layout version of the record (version 9: the control rate, the one [`Settings`]
/// type, and the analog setpoint input's settings ([`StoredRecord::analog`]). Version 9's
/// settings end with the optional output map ([`Settings::output_map`]); version 8 lacked it
/// and is still read, as settings without an output map. Version 8's
/// settings end with the optional preview ([`Settings::preview`]); version 7 lacked it and
/// is still read, as settings without a preview, and so are versions 5 and 6. Version 7's
/// Bouc–Wen model ends with `χ` ([`crate::BoucWenParams::chi`]); versions 4 to 6 are laid out
/// alike but for that, and are still read where neither model is Bouc–Wen (one that is is
/// refused, [`SettingsError::BoucWenWithoutChi`]: its coefficients would be read shifted).
/// Version 6 is version 7 without `χ`; version 5
/// lacked the last and is still read, as no analog input. Version 5's settings end with the
/// optional input shaping (`shaping`); version 4 lacked
/// it and is still read, as settings without shaping ([`StoredRecord::decode`]); in version 4
/// `Model` had gained the generalised P–I and Bouc–Wen (appended in that order) and the
/// settings the optional creep operator; version 3 lacked all three, and versions 1 and 2 had
/// a separate board payload and a wire parameter set: none of them is read, such a
/// board boots on the defaults and says so).
pub const RECORD_VERSION: u16 = 9;

/// The last record version without the output map, still read.
pub const RECORD_VERSION_WITHOUT_OUTPUT_MAP: u16 = 8;

/// Version 8's payload: the rate, the settings without the output map, the analog input
/// (read only).
#[derive(serde::Deserialize)]
struct RecordV8 {
    control_rate_hz: u32,
    settings: crate::config::settings::SettingsWithoutOutputMap,
    analog: Option<crate::sources::analog_input::AnalogInputConfig>,
}

/// A version-8 payload as a record without an output map.
#[inline(never)]
fn decode_v8(payload: &[u8]) -> Option<StoredRecord> {
    match postcard::take_from_bytes::<RecordV8>(payload) {
        Ok((r, [])) => Some(StoredRecord {
            control_rate_hz: r.control_rate_hz,
            settings: r.settings.into(),
            analog: r.analog,
        }),
        _ => None,
    }
}

/// The last record version without the preview, still read.
pub const RECORD_VERSION_WITHOUT_PREVIEW: u16 = 7;

/// Versions 6 and 7's payload: the rate, the settings without the preview, the analog input
/// (read only).
#[derive(serde::Deserialize)]
struct RecordV7 {
    control_rate_hz: u32,
    settings: crate::config::settings::SettingsWithoutPreview,
    analog: Option<crate::sources::analog_input::AnalogInputConfig>,
}

/// A version-6 or -7 payload as a record without a preview.
#[inline(never)]
fn decode_v7(payload: &[u8]) -> Option<StoredRecord> {
    match postcard::take_from_bytes::<RecordV7>(payload) {
        Ok((r, [])) => Some(StoredRecord {
            control_rate_hz: r.control_rate_hz,
            settings: r.settings.into(),
            analog: r.analog,
        }),
        _ => None,
    }
}

/// The last record version whose Bouc–Wen model has no `χ`, still read without one.
pub const RECORD_VERSION_WITHOUT_CHI: u16 = 6;

/// The last record version without the analog input's settings, still read.
pub const RECORD_VERSION_WITHOUT_ANALOG: u16 = 5;

/// Version 5's payload: the rate and the settings, no analog input (read only).
#[derive(serde::Deserialize)]
struct RecordV5 {
    control_rate_hz: u32,
    settings: crate::config::settings::SettingsWithoutPreview,
}

/// A version-5 payload as a record without an analog input.
#[inline(never)]
fn decode_v5(payload: &[u8]) -> Option<StoredRecord> {
    match postcard::take_from_bytes::<RecordV5>(payload) {
        Ok((r, [])) => Some(StoredRecord {
            control_rate_hz: r.control_rate_hz,
            settings: r.settings.into(),
            analog: None,
        }),
        _ => None,
    }
}

/// The last record version without input shaping, still read.
pub const RECORD_VERSION_WITHOUT_SHAPING: u16 = 4;

/// Version 4's payload: the settings without `shaping` (read only).
#[derive(serde::Deserialize)]
struct RecordV4 {
    control_rate_hz: u32,
    settings: crate::config::settings::SettingsWithoutShaping,
}

/// A version-4 payload as a record without shaping (out of line: its frame is only on the
/// stack for such a record).
#[inline(never)]
fn decode_v4(payload: &[u8]) -> Option<StoredRecord> {
    match postcard::take_from_bytes::<RecordV4>(payload) {
        Ok((r, [])) => Some(StoredRecord {
            control_rate_hz: r.control_rate_hz,
            settings: r.settings.into(),
            analog: None,
        }),
        _ => None,
    }
}

/// What the parameter record holds: the control rate (fixed at boot) and the settings.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StoredRecord {
    /// Control (tick) rate, Hz, within [`Hardware::MIN_CONTROL_RATE_HZ`] ..=
    /// [`Hardware::MAX_CONTROL_RATE_HZ`].
    pub control_rate_hz: u32,
    /// The settings, in the mode the user stored them to boot in.
    pub settings: Settings,
    /// The analog setpoint input's settings last started ([`crate::sources::analog_input`]), or none;
    /// with `start_at_boot` the board starts it at power-up, with no host.
    pub analog: Option<crate::sources::analog_input::AnalogInputConfig>,
}

/// Why a sound record's contents were refused.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SettingsError {
    /// The payload is not a `postcard`-encoded [`StoredRecord`].
    Undecodable,
    /// The control rate is outside what the board runs.
    ControlRateOutOfRange {
        /// The stored rate, Hz.
        control_rate_hz: u32,
    },
    /// The settings were refused on this board.
    Refused(Refusal),
    /// A record of an older layout (`version`) holds a Bouc–Wen model, whose coefficients
    /// that layout did not end with `χ`: load its parameter file again.
    BoucWenWithoutChi {
        /// The record's layout version.
        version: u16,
    },
}

impl fmt::Display for SettingsError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            SettingsError::Undecodable => write!(f, "record payload is not a settings record"),
            SettingsError::ControlRateOutOfRange { control_rate_hz } => write!(
                f,
                "control rate {control_rate_hz} Hz is outside {}..={}",
                Hardware::MIN_CONTROL_RATE_HZ,
                Hardware::MAX_CONTROL_RATE_HZ
            ),
            SettingsError::Refused(r) => write!(f, "stored settings refused: {r}"),
            SettingsError::BoucWenWithoutChi { version } => write!(
                f,
                "record version {version} holds a Bouc-Wen model stored before its chi term: load its parameter file again"
            ),
        }
    }
}

impl Default for StoredRecord {
    /// The compiled-in defaults: 50 kHz, [`Settings::default`] (bypass, no model).
    fn default() -> Self {
        Self {
            control_rate_hz: Hardware::DEFAULT_CONTROL_RATE_HZ,
            settings: Settings::default(),
            analog: None,
        }
    }
}

impl StoredRecord {
    /// Encodes the record (envelope included) into `out`; returns its length.
    pub fn encode(&self, out: &mut [u8; MAX_RECORD]) -> Result<usize, StoreError> {
        let mut payload = [0u8; MAX_PAYLOAD];
        let used = postcard::to_slice(self, &mut payload)
            .map_err(|_| StoreError::PayloadTooLong {
                length: MAX_PAYLOAD + 1,
            })?
            .len();
        encode(RECORD_VERSION, &payload[..used], out)
    }

    /// Decodes and checks a record: the envelope, the payload, the control rate, and the
    /// settings and the analog input's on `hardware` at the stored rate (`hardware`'s own rate
    /// is ignored). A version-8 record is read as settings without an output map, a version-6
    /// or -7 record as settings without a preview either, a version-5
    /// record as no analog input either, a version-4 record (before input shaping) as settings
    /// without shaping.
    pub fn decode(record: &[u8], hardware: &Hardware) -> Result<Self, LoadFailure> {
        // The record's layout: ours, or an older one still read.
        let version = match decode(record, RECORD_VERSION) {
            Ok(_) => RECORD_VERSION,
            Err(StoreError::UnsupportedVersion { found, .. })
                if (RECORD_VERSION_WITHOUT_SHAPING..RECORD_VERSION).contains(&found) =>
            {
                found
            }
            Err(e) => return Err(LoadFailure::Record(e)),
        };
        let payload = decode(record, version).map_err(LoadFailure::Record)?;
        let stored = match version {
            RECORD_VERSION_WITHOUT_SHAPING => decode_v4(payload),
            RECORD_VERSION_WITHOUT_ANALOG => decode_v5(payload),
            // Versions 6 and 7: laid out alike but for Bouc–Wen's χ (refused below).
            RECORD_VERSION_WITHOUT_CHI | RECORD_VERSION_WITHOUT_PREVIEW => decode_v7(payload),
            RECORD_VERSION_WITHOUT_OUTPUT_MAP => decode_v8(payload),
            _ => match postcard::take_from_bytes::<StoredRecord>(payload) {
                Ok((r, [])) => Some(r),
                _ => None,
            },
        };
        let Some(stored) = stored else {
            return Err(LoadFailure::Settings(SettingsError::Undecodable));
        };
        if version <= RECORD_VERSION_WITHOUT_CHI && stored.settings.has_bouc_wen() {
            return Err(LoadFailure::Settings(SettingsError::BoucWenWithoutChi {
                version,
            }));
        }
        let rate = stored.control_rate_hz;
        if !(Hardware::MIN_CONTROL_RATE_HZ..=Hardware::MAX_CONTROL_RATE_HZ).contains(&rate) {
            return Err(LoadFailure::Settings(
                SettingsError::ControlRateOutOfRange {
                    control_rate_hz: rate,
                },
            ));
        }
        let hw = Hardware {
            control_rate_hz: rate as f64,
            ..*hardware
        };
        stored
            .settings
            .build(&hw)
            .map_err(|r| LoadFailure::Settings(SettingsError::Refused(r)))?;
        if let Some(a) = &stored.analog {
            a.check(rate as f64)
                .map_err(|r| LoadFailure::Settings(SettingsError::Refused(r)))?;
        }
        Ok(stored)
    }
}

/// Where the running settings came from (shown in the status reply).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ParamSource {
    /// A valid record was loaded from flash.
    Stored,
    /// The record was missing or invalid; the compiled-in defaults run.
    Defaults(LoadFailure),
}

/// Why the stored record was not used.
#[derive(Clone, Copy, Debug, PartialEq)]
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

/// Reads the record from the bytes of the parameter sector: the stored record when it is
/// sound and its settings are accepted on `hardware`, otherwise [`StoredRecord::default`]
/// (bypass, no model, 50 kHz) and the reason.
pub fn load_record(sector: &[u8], hardware: &Hardware) -> (StoredRecord, ParamSource) {
    match StoredRecord::decode(sector, hardware) {
        Ok(r) => (r, ParamSource::Stored),
        Err(e) => (StoredRecord::default(), ParamSource::Defaults(e)),
    }
}

/// The settings the board starts on, given what [`load_record`] found and the hardware at the
/// rate the control timer actually runs: the stored settings if they build there, else
/// [`Settings::default`] (bypass, no model). Returns the settings, their build, and whether
/// they are the defaults; `Err` only if even the defaults are refused on `hardware`.
pub fn boot(
    record: StoredRecord,
    source: ParamSource,
    hardware: &Hardware,
) -> Result<(Settings, ControlConfig, bool), Refusal> {
    if source == ParamSource::Stored {
        if let Ok(config) = record.settings.build(hardware) {
            return Ok((record.settings, config, false));
        }
    }
    let settings = Settings::default();
    let config = settings.build(hardware)?;
    Ok((settings, config, true))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const HW: Hardware = Hardware::driver_board(50_000.0);

    fn record_of(record: &StoredRecord) -> ([u8; MAX_RECORD], usize) {
        let mut buf = [0u8; MAX_RECORD];
        let n = record.encode(&mut buf).unwrap();
        (buf, n)
    }

    fn stored(rate: u32) -> StoredRecord {
        let mut settings = Settings::default();
        settings.drive.safe_state = crate::control::drive::SafeState::Zero;
        StoredRecord {
            control_rate_hz: rate,
            settings,
            analog: None,
        }
    }

    #[test]
    fn crc32_matches_the_standard_check_value() {
        // The catalogue check value of CRC-32/ISO-HDLC (zlib) for "123456789".
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc32(b""), 0);
    }

    #[test]
    fn a_stored_record_loads_its_settings() {
        let s = stored(100_000);
        let (buf, n) = record_of(&s);
        assert_eq!(
            load_record(&buf[..n], &HW),
            (s.clone(), ParamSource::Stored)
        );
        // Trailing sector bytes after the record are ignored.
        assert_eq!(load_record(&buf, &HW), (s, ParamSource::Stored));
    }

    #[test]
    fn bad_crc_gives_defaults_and_says_so() {
        let (mut buf, n) = record_of(&stored(20_000));
        buf[HEADER_LEN] ^= 0x01;
        let (record, source) = load_record(&buf[..n], &HW);
        assert_eq!(record, StoredRecord::default());
        assert!(matches!(
            source,
            ParamSource::Defaults(LoadFailure::Record(StoreError::BadCrc { .. }))
        ));
        assert_eq!(source.as_str(), "bad-crc");
    }

    /// A record stored before input shaping (version 4: the settings without `shaping`)
    /// still loads, as settings without shaping; a record with shaping round-trips.
    #[test]
    fn a_version_4_record_loads_without_shaping() {
        let mut s = stored(50_000);
        s.settings.compensator = Some(crate::config::settings::representative_pi(8).unwrap());
        s.settings.mode = crate::config::settings::Mode::OpenLoop;
        // Version 4's payload is version 9's without the last four bytes (`shaping: None`,
        // `preview: None`, `output_map: None`, `analog: None`).
        let mut payload = [0u8; MAX_PAYLOAD];
        let used = postcard::to_slice(&s, &mut payload).unwrap().len();
        assert_eq!(payload[used - 4..used], [0, 0, 0, 0], "the trailing Nones");
        let mut buf = [0u8; MAX_RECORD];
        let n = encode(
            RECORD_VERSION_WITHOUT_SHAPING,
            &payload[..used - 4],
            &mut buf,
        )
        .unwrap();
        assert_eq!(
            load_record(&buf[..n], &HW),
            (s.clone(), ParamSource::Stored)
        );
        // Version 5 with the byte left off is malformed, not silently shaped.
        let n = encode(
            RECORD_VERSION_WITHOUT_ANALOG,
            &payload[..used - 4],
            &mut buf,
        )
        .unwrap();
        assert_eq!(load_record(&buf[..n], &HW).1.as_str(), "bad-settings");
        s.settings.shaping = Some(crate::control::notch::NotchDesign {
            frequency_hz: 21_807.0,
            q: 0.5,
            depth: 0.0173,
        });
        let (buf, n) = record_of(&s);
        assert_eq!(load_record(&buf[..n], &HW), (s, ParamSource::Stored));
    }

    /// A record stored before the analog input (version 5) still loads, as no analog input;
    /// a record with one round-trips, and one with hostile analog settings is refused.
    #[test]
    fn a_version_5_record_loads_without_an_analog_input() {
        use crate::sources::analog_input::{AnalogInputConfig, OnFault};
        let mut s = stored(50_000);
        // Version 5's payload is version 9's without the last three bytes (`preview: None`,
        // `output_map: None`, `analog: None`).
        let mut payload = [0u8; MAX_PAYLOAD];
        let used = postcard::to_slice(&s, &mut payload).unwrap().len();
        assert_eq!(payload[used - 3..used], [0, 0, 0], "the trailing Nones");
        let mut buf = [0u8; MAX_RECORD];
        let n = encode(
            RECORD_VERSION_WITHOUT_ANALOG,
            &payload[..used - 3],
            &mut buf,
        )
        .unwrap();
        assert_eq!(
            load_record(&buf[..n], &HW),
            (s.clone(), ParamSource::Stored)
        );
        // The present version without the bytes is malformed.
        let n = encode(RECORD_VERSION, &payload[..used - 3], &mut buf).unwrap();
        assert_eq!(load_record(&buf[..n], &HW).1.as_str(), "bad-settings");
        let analog = AnalogInputConfig {
            gain: 2.0,
            offset: -1.0,
            corner_hz: Some(1000.0),
            lost_below: 0.02,
            over_above: 0.98,
            on_fault: OnFault::RampToRest,
            rate: 5.0,
            start_at_boot: true,
        };
        s.analog = Some(analog);
        let (buf, n) = record_of(&s);
        assert_eq!(
            load_record(&buf[..n], &HW),
            (s.clone(), ParamSource::Stored)
        );
        s.analog = Some(AnalogInputConfig {
            rate: -1.0,
            ..analog
        });
        let (buf, n) = record_of(&s);
        let (record, source) = load_record(&buf[..n], &HW);
        assert_eq!(record, StoredRecord::default());
        assert_eq!(source.as_str(), "bad-settings");
    }

    /// A record stored before the preview (version 7) still loads, as settings without one; a
    /// record with a preview round-trips, and one whose preview the rate cannot run is refused.
    #[test]
    fn a_version_7_record_loads_without_a_preview() {
        let mut s = stored(50_000);
        s.settings.compensator = Some(crate::config::settings::representative_pi(8).unwrap());
        s.settings.mode = crate::config::settings::Mode::OpenLoop;
        s.settings.shaping = Some(crate::control::notch::NotchDesign {
            frequency_hz: 21_807.0,
            q: 0.5,
            depth: 0.0173,
        });
        let mut payload = [0u8; MAX_PAYLOAD];
        let used = postcard::to_slice(&s, &mut payload).unwrap().len();
        assert_eq!(payload[used - 3..used], [0, 0, 0], "the trailing Nones");
        let mut buf = [0u8; MAX_RECORD];
        let n = encode(
            RECORD_VERSION_WITHOUT_PREVIEW,
            &payload[..used - 2],
            &mut buf,
        )
        .unwrap();
        assert_eq!(
            load_record(&buf[..n], &HW),
            (s.clone(), ParamSource::Stored)
        );
        // Version 7's payload is version 9's without `preview: None` and `output_map: None`
        // (zeros before the last, `analog: None`). The present version without the bytes is
        // malformed, not read without a preview.
        let n = encode(RECORD_VERSION, &payload[..used - 2], &mut buf).unwrap();
        assert_eq!(load_record(&buf[..n], &HW).1.as_str(), "bad-settings");
        s.settings.preview = Some(crate::control::preview::PreviewDesign {
            frequency_hz: 3_500.0,
            damping: 0.03,
        });
        let (buf, n) = record_of(&s);
        assert_eq!(
            load_record(&buf[..n], &HW),
            (s.clone(), ParamSource::Stored)
        );
        // At or above half the stored rate the preview is refused, and the board boots on
        // the defaults.
        s.settings.preview = Some(crate::control::preview::PreviewDesign {
            frequency_hz: 25_000.0,
            damping: 0.03,
        });
        let (buf, n) = record_of(&s);
        let (record, source) = load_record(&buf[..n], &HW);
        assert_eq!(record, StoredRecord::default());
        assert_eq!(source.as_str(), "bad-settings");
    }

    /// A record stored before the output map (version 8) still loads, as settings without
    /// one, and so does its Bouc–Wen model (laid out as today's, `χ` included); a record with
    /// an output map round-trips, and one whose map is not invertible is refused.
    #[test]
    fn a_version_8_record_loads_without_an_output_map() {
        use crate::config::settings::{representative_bouc_wen, DeadZoneParams, Mode};
        let mut s = stored(50_000);
        s.settings.compensator = Some(representative_bouc_wen());
        s.settings.observer = Some(representative_bouc_wen());
        s.settings.mode = Mode::OpenLoop;
        let mut payload = [0u8; MAX_PAYLOAD];
        let used = postcard::to_slice(&s, &mut payload).unwrap().len();
        assert_eq!(payload[used - 2..used], [0, 0], "the trailing Nones");
        // Version 8's payload is version 9's without `output_map: None` (zero, before
        // `analog: None`).
        let mut buf = [0u8; MAX_RECORD];
        let n = encode(
            RECORD_VERSION_WITHOUT_OUTPUT_MAP,
            &payload[..used - 1],
            &mut buf,
        )
        .unwrap();
        assert_eq!(
            load_record(&buf[..n], &HW),
            (s.clone(), ParamSource::Stored)
        );
        // The present version without the byte is malformed, not read without a map.
        let n = encode(RECORD_VERSION, &payload[..used - 1], &mut buf).unwrap();
        assert_eq!(load_record(&buf[..n], &HW).1.as_str(), "bad-settings");
        s.settings.output_map =
            Some(DeadZoneParams::new(35.0, 1.0, &[-20.0, 20.0], &[0.05, -0.05]).unwrap());
        let (buf, n) = record_of(&s);
        assert_eq!(
            load_record(&buf[..n], &HW),
            (s.clone(), ParamSource::Stored)
        );
        // A map whose slope falls to zero has no inverse: the board boots on the defaults.
        s.settings.output_map = Some(DeadZoneParams::new(35.0, 1.0, &[20.0], &[-1.0]).unwrap());
        let (buf, n) = record_of(&s);
        let (record, source) = load_record(&buf[..n], &HW);
        assert_eq!(record, StoredRecord::default());
        assert_eq!(source.as_str(), "bad-settings");
    }

    /// A version-6 record (Bouc–Wen without `χ`) still loads where neither model is
    /// Bouc–Wen; one holding a Bouc–Wen model is refused by name, not read shifted.
    #[test]
    fn a_version_6_record_loads_unless_it_holds_a_bouc_wen_model() {
        use crate::config::settings::{representative_bouc_wen, representative_pi, Mode, Model};
        let mut s = stored(50_000);
        s.settings.compensator = Some(representative_pi(8).unwrap());
        s.settings.mode = Mode::OpenLoop;
        let mut payload = [0u8; MAX_PAYLOAD];
        let used = postcard::to_slice(&s, &mut payload).unwrap().len();
        let mut buf = [0u8; MAX_RECORD];
        // Version 6's payload is version 9's without `preview: None` and `output_map: None`
        // (the bytes before the last, all 0 here).
        let n = encode(RECORD_VERSION_WITHOUT_CHI, &payload[..used - 2], &mut buf).unwrap();
        assert_eq!(
            load_record(&buf[..n], &HW),
            (s.clone(), ParamSource::Stored)
        );
        // Version 6's Bouc–Wen: six coefficients where version 7 has seven (`χ` last, a
        // postcard `f64` is its 8 bytes): the same payload without `χ`'s bytes after `ψ`'s.
        s.settings.compensator = Some(representative_bouc_wen());
        let Some(Model::BoucWen(p)) = s.settings.compensator else {
            unreachable!()
        };
        let used = postcard::to_slice(&s, &mut payload).unwrap().len();
        let mut coefficients = [0u8; 16];
        coefficients[..8].copy_from_slice(&p.psi.to_le_bytes());
        coefficients[8..].copy_from_slice(&p.chi.to_le_bytes());
        let at = payload[..used]
            .windows(16)
            .position(|w| w == coefficients)
            .unwrap()
            + 8;
        let chi = 8;
        let mut old = [0u8; MAX_PAYLOAD];
        old[..at].copy_from_slice(&payload[..at]);
        old[at..used - chi].copy_from_slice(&payload[at + chi..used]);
        let n = encode(RECORD_VERSION_WITHOUT_CHI, &old[..used - chi - 2], &mut buf).unwrap();
        let (record, source) = load_record(&buf[..n], &HW);
        assert_eq!(record, StoredRecord::default());
        assert_eq!(source.as_str(), "bad-settings");
        // Where the shifted bytes happen to decode, the Bouc–Wen model in an old layout is
        // refused by name: the present layout's bytes labelled version 6.
        // Version 6's payload is version 9's without `preview: None` and `output_map: None`
        // (the bytes before the last, all 0 here).
        let n = encode(RECORD_VERSION_WITHOUT_CHI, &payload[..used - 2], &mut buf).unwrap();
        let (record, source) = load_record(&buf[..n], &HW);
        assert_eq!(record, StoredRecord::default());
        assert_eq!(
            source,
            ParamSource::Defaults(LoadFailure::Settings(SettingsError::BoucWenWithoutChi {
                version: RECORD_VERSION_WITHOUT_CHI
            }))
        );
        // The same model in the present layout loads.
        let (buf, n) = record_of(&s);
        assert_eq!(load_record(&buf[..n], &HW), (s, ParamSource::Stored));
    }

    #[test]
    fn bad_version_is_refused_before_the_payload_is_read() {
        let mut buf = [0u8; MAX_RECORD];
        let n = encode(RECORD_VERSION + 1, &[1, 2, 3], &mut buf).unwrap();
        assert_eq!(
            decode(&buf[..n], RECORD_VERSION),
            Err(StoreError::UnsupportedVersion {
                found: RECORD_VERSION + 1,
                expected: RECORD_VERSION
            })
        );
        assert_eq!(load_record(&buf[..n], &HW).1.as_str(), "bad-version");
    }

    #[test]
    fn truncation_at_every_length_is_refused() {
        let (buf, n) = record_of(&StoredRecord::default());
        for cut in 0..n {
            let r = decode(&buf[..cut], RECORD_VERSION);
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
        assert_eq!(load_record(&[0xFF; 64], &HW).1.as_str(), "erased");
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
        let (buf, n) = record_of(&stored(5_000));
        assert_eq!(
            load_record(&buf[..n], &HW),
            (
                StoredRecord::default(),
                ParamSource::Defaults(LoadFailure::Settings(
                    SettingsError::ControlRateOutOfRange {
                        control_rate_hz: 5_000
                    }
                ))
            )
        );
        let mut bad = stored(50_000);
        bad.settings.drive.bias = f64::NAN;
        let (buf, n) = record_of(&bad);
        let (record, source) = load_record(&buf[..n], &HW);
        assert_eq!(record, StoredRecord::default());
        assert_eq!(source.as_str(), "bad-settings");
        let mut buf = [0u8; MAX_RECORD];
        let n = encode(RECORD_VERSION, &[1, 2, 3], &mut buf).unwrap();
        assert_eq!(
            load_record(&buf[..n], &HW).1,
            ParamSource::Defaults(LoadFailure::Settings(SettingsError::Undecodable))
        );
    }

    #[test]
    fn the_defaults_boot_in_bypass() {
        assert_eq!(
            StoredRecord::default().settings.mode,
            crate::config::settings::Mode::Bypass
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
            let _ = load_record(&bytes, &HW);
        }
    }
}
