//! The golden-vector file: one or more vector sets, each a self-checking record.
//!
//! All integers little-endian. One record:
//!
//! | field | bytes | meaning |
//! |---|---|---|
//! | magic | 4 | `TSGV` |
//! | version | 2 | [`FORMAT_VERSION`], or [`FORMAT_VERSION_WITHOUT_OUTPUT_MAP`], [`FORMAT_VERSION_WITHOUT_PREVIEW`], [`FORMAT_VERSION_WITHOUT_CHI`] or [`FORMAT_VERSION_WITHOUT_SHAPING`] (read); another version is refused |
//! | length | 4 | bytes of the whole record, magic to CRC |
//! | name length, name | 1 + n | ASCII `[a-z0-9-]`, 1…32 bytes |
//! | ticks | 4 | tick count `T` (1…[`MAX_TICKS`]) |
//! | config fingerprint | 4 | [`super::config_fingerprint`] of the host's build of the recipe |
//! | recipe length, recipe | 2 + m | [`super::Recipe`], physical units |
//! | inputs | 7 `T` | per tick: flags `u8` (bit 0 setpoint present, bit 1 ADC read fails, bit 2 DAC write fails), setpoint `i32` (Q2.30; 0 when absent), ADC code `u16` |
//! | outputs | 13 `T` | per tick: left code `u16`, right code `u16`, estimate `i32` (Q2.30), applied drive `i32` (Q2.30), tick flags `u8` |
//! | outputs CRC | 4 | CRC-32 of the outputs field (the digest the board reports) |
//! | record CRC | 4 | CRC-32 of every byte before it |
//!
//! A file is records back to back. [`VectorSets`] walks them; every length is checked before
//! it is used, so a truncated or corrupted file gives a [`FormatError`], never a panic.

use super::recipe::{Recipe, RecipeError};
use super::{TickInput, TickOutput, CRC32};

/// Record magic.
pub const MAGIC: [u8; 4] = *b"TSGV";
/// Version of the layout above and of the recipe's encoding ([`super::recipe`]): 2 since the
/// feedback carries a drift limit, 3 since the settings end with the optional creep, 4 since
/// they end with the optional input shaping, 5 since a Bouc–Wen model's coefficients end
/// with `χ`, 6 since the settings end with the optional preview, 7 since they end with the
/// optional output map.
pub const FORMAT_VERSION: u16 = 7;
/// The format before the output map, still read: its recipes' settings end with `preview`
/// ([`Recipe::decode_without_output_map`]); the same layout otherwise.
pub const FORMAT_VERSION_WITHOUT_OUTPUT_MAP: u16 = 6;
/// The format before the preview, still read: its recipes' settings end with `shaping`
/// ([`Recipe::decode_without_preview`]); the same layout otherwise.
pub const FORMAT_VERSION_WITHOUT_PREVIEW: u16 = 5;
/// The format before Bouc–Wen's `χ`, still read where neither model is Bouc–Wen (one that is
/// is refused, [`RecipeError::BoucWenWithoutChi`]); laid out as format 5 otherwise.
pub const FORMAT_VERSION_WITHOUT_CHI: u16 = 4;
/// The format before input shaping, still read: its recipes' settings end with `creep`
/// ([`Recipe::decode_without_shaping`]); the same layout otherwise.
pub const FORMAT_VERSION_WITHOUT_SHAPING: u16 = 3;
/// Bytes per tick of inputs.
pub const INPUT_BYTES: usize = 7;
/// Bytes per tick of outputs.
pub const OUTPUT_BYTES: usize = 13;
/// Longest set name, bytes.
pub const MAX_NAME: usize = 32;
/// Most ticks a set may hold.
pub const MAX_TICKS: u32 = 1 << 20;

const INPUT_SETPOINT: u8 = 1 << 0;
const INPUT_ADC_FAILS: u8 = 1 << 1;
const INPUT_DAC_FAILS: u8 = 1 << 2;

/// Why a file was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FormatError {
    /// The file ends inside a record (byte offset where more was needed).
    Truncated {
        /// Offset into the file.
        at: usize,
    },
    /// A record does not start with `TSGV`.
    BadMagic {
        /// Offset of the record.
        at: usize,
    },
    /// A record of another format version.
    BadVersion {
        /// The version found.
        got: u16,
    },
    /// A record's stored CRC does not match its bytes.
    BadCrc {
        /// Offset of the record.
        at: usize,
    },
    /// The record's length field disagrees with its contents.
    BadLength {
        /// Offset of the record.
        at: usize,
    },
    /// The name is empty, too long, or not `[a-z0-9-]`.
    BadName {
        /// Offset of the record.
        at: usize,
    },
    /// Zero ticks, or more than [`MAX_TICKS`].
    BadTickCount {
        /// The count found.
        got: u32,
    },
    /// An input's flags have bits beyond the three defined.
    BadInputFlags {
        /// Tick index.
        tick: u32,
    },
    /// The outputs' CRC does not match them.
    BadOutputsCrc {
        /// Offset of the record.
        at: usize,
    },
}

impl TickInput {
    /// The input as stored (see the module doc).
    pub fn to_bytes(&self) -> [u8; INPUT_BYTES] {
        let mut flags = 0;
        if self.setpoint.is_some() {
            flags |= INPUT_SETPOINT;
        }
        if self.adc_fails {
            flags |= INPUT_ADC_FAILS;
        }
        if self.dac_fails {
            flags |= INPUT_DAC_FAILS;
        }
        let s = self.setpoint.unwrap_or(0).to_le_bytes();
        let a = self.adc_code.to_le_bytes();
        [flags, s[0], s[1], s[2], s[3], a[0], a[1]]
    }

    /// Decodes a stored input; `None` if the flags have undefined bits.
    pub fn from_bytes(b: &[u8; INPUT_BYTES]) -> Option<Self> {
        let flags = b[0];
        if flags & !(INPUT_SETPOINT | INPUT_ADC_FAILS | INPUT_DAC_FAILS) != 0 {
            return None;
        }
        let setpoint = i32::from_le_bytes([b[1], b[2], b[3], b[4]]);
        Some(Self {
            setpoint: (flags & INPUT_SETPOINT != 0).then_some(setpoint),
            adc_code: u16::from_le_bytes([b[5], b[6]]),
            adc_fails: flags & INPUT_ADC_FAILS != 0,
            dac_fails: flags & INPUT_DAC_FAILS != 0,
        })
    }
}

impl TickOutput {
    /// The output as stored (see the module doc); the replay's digest is over these bytes.
    pub fn to_bytes(&self) -> [u8; OUTPUT_BYTES] {
        let mut b = [0u8; OUTPUT_BYTES];
        b[0..2].copy_from_slice(&self.left.to_le_bytes());
        b[2..4].copy_from_slice(&self.right.to_le_bytes());
        b[4..8].copy_from_slice(&self.estimate.to_le_bytes());
        b[8..12].copy_from_slice(&self.drive.to_le_bytes());
        b[12] = self.flags;
        b
    }

    /// Decodes a stored output.
    pub fn from_bytes(b: &[u8; OUTPUT_BYTES]) -> Self {
        Self {
            left: u16::from_le_bytes([b[0], b[1]]),
            right: u16::from_le_bytes([b[2], b[3]]),
            estimate: i32::from_le_bytes([b[4], b[5], b[6], b[7]]),
            drive: i32::from_le_bytes([b[8], b[9], b[10], b[11]]),
            flags: b[12],
        }
    }
}

/// One parsed record, borrowing the file's bytes. Inputs have been checked at parse time.
#[derive(Clone, Copy, Debug)]
pub struct VectorSet<'a> {
    name: &'a str,
    ticks: u32,
    config_fingerprint: u32,
    /// The record's format version (the recipe's encoding).
    version: u16,
    recipe: &'a [u8],
    inputs: &'a [u8],
    outputs: &'a [u8],
    outputs_crc: u32,
    record_len: usize,
}

impl<'a> VectorSet<'a> {
    /// The set's name.
    pub fn name(&self) -> &'a str {
        self.name
    }
    /// Ticks in the set.
    pub fn ticks(&self) -> u32 {
        self.ticks
    }
    /// Fingerprint of the configuration the host built when it recorded the set.
    pub fn config_fingerprint(&self) -> u32 {
        self.config_fingerprint
    }
    /// CRC-32 of the stored outputs.
    pub fn outputs_crc(&self) -> u32 {
        self.outputs_crc
    }
    /// Bytes the record occupies in the file.
    pub fn record_len(&self) -> usize {
        self.record_len
    }
    /// The configuration, decoded.
    pub fn recipe(&self) -> Result<Recipe, RecipeError> {
        let recipe = match self.version {
            FORMAT_VERSION_WITHOUT_SHAPING => Recipe::decode_without_shaping(self.recipe)?,
            FORMAT_VERSION_WITHOUT_CHI | FORMAT_VERSION_WITHOUT_PREVIEW => {
                Recipe::decode_without_preview(self.recipe)?
            }
            FORMAT_VERSION_WITHOUT_OUTPUT_MAP => Recipe::decode_without_output_map(self.recipe)?,
            _ => Recipe::decode(self.recipe)?,
        };
        if self.version <= FORMAT_VERSION_WITHOUT_CHI && recipe.settings.has_bouc_wen() {
            return Err(RecipeError::BoucWenWithoutChi);
        }
        Ok(recipe)
    }
    /// The stored inputs, tick by tick.
    pub fn inputs(&self) -> impl Iterator<Item = TickInput> + 'a {
        self.inputs.chunks_exact(INPUT_BYTES).map(|c| {
            let mut b = [0u8; INPUT_BYTES];
            b.copy_from_slice(c);
            // Checked by `parse`; a bad input cannot reach here.
            TickInput::from_bytes(&b).unwrap_or_default()
        })
    }
    /// The stored outputs, tick by tick.
    pub fn outputs(&self) -> impl Iterator<Item = TickOutput> + 'a {
        self.outputs.chunks_exact(OUTPUT_BYTES).map(|c| {
            let mut b = [0u8; OUTPUT_BYTES];
            b.copy_from_slice(c);
            TickOutput::from_bytes(&b)
        })
    }
    /// The stored output of tick `k`, if there is one.
    pub fn output(&self, k: u32) -> Option<TickOutput> {
        self.outputs().nth(k as usize)
    }

    /// Parses the record at `at` in `file`.
    fn parse(file: &'a [u8], at: usize) -> Result<Self, FormatError> {
        let mut r = Reader { b: file, pos: at };
        if r.take(4)? != MAGIC {
            return Err(FormatError::BadMagic { at });
        }
        let version = r.u16()?;
        if ![
            FORMAT_VERSION,
            FORMAT_VERSION_WITHOUT_OUTPUT_MAP,
            FORMAT_VERSION_WITHOUT_PREVIEW,
            FORMAT_VERSION_WITHOUT_CHI,
            FORMAT_VERSION_WITHOUT_SHAPING,
        ]
        .contains(&version)
        {
            return Err(FormatError::BadVersion { got: version });
        }
        let len = r.u32()? as usize;
        // The whole record must be there before anything in it is trusted.
        let end = at.checked_add(len).ok_or(FormatError::BadLength { at })?;
        if len < 4 + 2 + 4 + 4 {
            return Err(FormatError::BadLength { at });
        }
        if end > file.len() {
            return Err(FormatError::Truncated { at: file.len() });
        }
        let body = &file[at..end - 4];
        let stored_crc =
            u32::from_le_bytes([file[end - 4], file[end - 3], file[end - 2], file[end - 1]]);
        if CRC32.checksum(body) != stored_crc {
            return Err(FormatError::BadCrc { at });
        }
        let mut r = Reader {
            b: &file[..end - 4],
            pos: r.pos,
        };
        let name_len = r.u8()? as usize;
        let name = core::str::from_utf8(r.take(name_len)?)
            .ok()
            .filter(|n| {
                !n.is_empty()
                    && n.len() <= MAX_NAME
                    && n.bytes()
                        .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == b'-')
            })
            .ok_or(FormatError::BadName { at })?;
        let ticks = r.u32()?;
        if ticks == 0 || ticks > MAX_TICKS {
            return Err(FormatError::BadTickCount { got: ticks });
        }
        let config_fingerprint = r.u32()?;
        let recipe_len = r.u16()? as usize;
        let recipe = r.take(recipe_len)?;
        let inputs = r.take(ticks as usize * INPUT_BYTES)?;
        let outputs = r.take(ticks as usize * OUTPUT_BYTES)?;
        let outputs_crc = r.u32()?;
        if r.pos != end - 4 {
            return Err(FormatError::BadLength { at });
        }
        if CRC32.checksum(outputs) != outputs_crc {
            return Err(FormatError::BadOutputsCrc { at });
        }
        for (k, c) in inputs.chunks_exact(INPUT_BYTES).enumerate() {
            let mut b = [0u8; INPUT_BYTES];
            b.copy_from_slice(c);
            if TickInput::from_bytes(&b).is_none() {
                return Err(FormatError::BadInputFlags { tick: k as u32 });
            }
        }
        Ok(Self {
            name,
            ticks,
            config_fingerprint,
            version,
            recipe,
            inputs,
            outputs,
            outputs_crc,
            record_len: len,
        })
    }
}

/// The records of a file, in order. Stops after the first error.
#[derive(Clone, Debug)]
pub struct VectorSets<'a> {
    file: &'a [u8],
    pos: usize,
    failed: bool,
}

impl<'a> VectorSets<'a> {
    /// Walks the records of `file`.
    pub fn new(file: &'a [u8]) -> Self {
        Self {
            file,
            pos: 0,
            failed: false,
        }
    }
}

impl<'a> Iterator for VectorSets<'a> {
    type Item = Result<VectorSet<'a>, FormatError>;
    fn next(&mut self) -> Option<Self::Item> {
        if self.failed || self.pos >= self.file.len() {
            return None;
        }
        match VectorSet::parse(self.file, self.pos) {
            Ok(set) => {
                self.pos += set.record_len;
                Some(Ok(set))
            }
            Err(e) => {
                self.failed = true;
                Some(Err(e))
            }
        }
    }
}

/// Appends one record to `out` (used by the generator on the host; no allocation here).
/// Returns `None` if a field does not fit the format (name, tick count, recipe length, or
/// inputs and outputs of different lengths).
pub fn encode_record(
    name: &str,
    config_fingerprint: u32,
    recipe: &[u8],
    inputs: &[TickInput],
    outputs: &[TickOutput],
    out: &mut impl Extend<u8>,
) -> Option<()> {
    let ticks = u32::try_from(inputs.len()).ok()?;
    let name_ok = !name.is_empty()
        && name.len() <= MAX_NAME
        && name
            .bytes()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == b'-');
    if !name_ok || inputs.len() != outputs.len() || ticks == 0 || ticks > MAX_TICKS {
        return None;
    }
    let recipe_len = u16::try_from(recipe.len()).ok()?;
    let len = 4
        + 2
        + 4
        + 1
        + name.len()
        + 4
        + 4
        + 2
        + recipe.len()
        + inputs.len() * (INPUT_BYTES + OUTPUT_BYTES)
        + 4
        + 4;
    let len = u32::try_from(len).ok()?;
    let mut record = CRC32.digest();
    let mut put = |bytes: &[u8]| {
        record.update(bytes);
        out.extend(bytes.iter().copied());
    };
    put(&MAGIC);
    put(&FORMAT_VERSION.to_le_bytes());
    put(&len.to_le_bytes());
    put(&[name.len() as u8]);
    put(name.as_bytes());
    put(&ticks.to_le_bytes());
    put(&config_fingerprint.to_le_bytes());
    put(&recipe_len.to_le_bytes());
    put(recipe);
    for i in inputs {
        put(&i.to_bytes());
    }
    let mut outputs_crc = CRC32.digest();
    for o in outputs {
        let b = o.to_bytes();
        outputs_crc.update(&b);
        put(&b);
    }
    put(&outputs_crc.finalize().to_le_bytes());
    let crc = record.finalize();
    out.extend(crc.to_le_bytes());
    Some(())
}

/// A bounds-checked cursor.
struct Reader<'a> {
    b: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], FormatError> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&e| e <= self.b.len())
            .ok_or(FormatError::Truncated { at: self.b.len() })?;
        let s = &self.b[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn u8(&mut self) -> Result<u8, FormatError> {
        Ok(self.take(1)?[0])
    }
    fn u16(&mut self) -> Result<u16, FormatError> {
        let s = self.take(2)?;
        Ok(u16::from_le_bytes([s[0], s[1]]))
    }
    fn u32(&mut self) -> Result<u32, FormatError> {
        let s = self.take(4)?;
        Ok(u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Buf {
        b: [u8; 2048],
        n: usize,
    }
    impl Extend<u8> for Buf {
        fn extend<I: IntoIterator<Item = u8>>(&mut self, iter: I) {
            for x in iter {
                self.b[self.n] = x;
                self.n += 1;
            }
        }
    }

    fn sample() -> Buf {
        let inputs = [
            TickInput {
                setpoint: Some(-5),
                adc_code: 1234,
                adc_fails: false,
                dac_fails: true,
            },
            TickInput {
                setpoint: None,
                adc_code: 0,
                adc_fails: true,
                dac_fails: false,
            },
        ];
        let outputs = [
            TickOutput {
                left: 1,
                right: 65535,
                estimate: -7,
                drive: i32::MIN,
                flags: 0x11,
            },
            TickOutput::default(),
        ];
        let mut buf = Buf { b: [0; 2048], n: 0 };
        encode_record(
            "set-1",
            0xdead_beef,
            &[9, 8, 7],
            &inputs,
            &outputs,
            &mut buf,
        )
        .unwrap();
        buf
    }

    #[test]
    fn a_record_round_trips() {
        let buf = sample();
        let file = &buf.b[..buf.n];
        let sets: Result<heapless::Vec<VectorSet, 4>, _> = VectorSets::new(file).collect();
        let sets = sets.unwrap();
        assert_eq!(sets.len(), 1);
        let s = sets[0];
        assert_eq!(
            (s.name(), s.ticks(), s.config_fingerprint()),
            ("set-1", 2, 0xdead_beef)
        );
        assert_eq!(s.recipe, &[9, 8, 7]);
        let i: heapless::Vec<TickInput, 2> = s.inputs().collect();
        assert_eq!(i[0].setpoint, Some(-5));
        assert!(i[0].dac_fails && !i[0].adc_fails);
        assert_eq!(i[1].setpoint, None);
        assert!(i[1].adc_fails);
        assert_eq!(s.output(0).unwrap().drive, i32::MIN);
        assert_eq!(s.output(0).unwrap().right, 65535);
        assert_eq!(s.output(2), None);
        assert_eq!(s.record_len(), file.len());
    }

    #[test]
    fn every_truncation_and_every_flipped_byte_is_refused() {
        let buf = sample();
        let file = &buf.b[..buf.n];
        for cut in 0..file.len() {
            let r = VectorSets::new(&file[..cut]).next();
            assert!(matches!(r, None | Some(Err(_))), "cut at {cut}");
        }
        for k in 0..file.len() {
            let mut bad = [0u8; 2048];
            bad[..file.len()].copy_from_slice(file);
            bad[k] ^= 0x40;
            let r = VectorSets::new(&bad[..file.len()]).next();
            assert!(matches!(r, Some(Err(_))), "flip at {k}: {r:?}");
        }
    }

    /// A record of format 4 (before Bouc–Wen's `χ`) is read unless it holds a Bouc–Wen
    /// model, whose coefficients that format laid out without `χ`.
    #[test]
    fn a_format_4_record_is_read_unless_it_holds_a_bouc_wen_model() {
        use twinstack::board::Hardware;
        use twinstack::config::settings::{representative_bouc_wen, representative_pi, Settings};
        let record = |settings: Settings, version: u16| {
            let recipe = Recipe {
                hardware: Hardware::driver_board(50_000.0),
                settings,
            };
            let mut bytes = [0u8; 1024];
            let bytes = recipe.encode(&mut bytes).unwrap();
            // Format 6 ends before the output map's `None`, formats before the preview
            // before its `None` too.
            let cut = match version {
                FORMAT_VERSION => 0,
                FORMAT_VERSION_WITHOUT_OUTPUT_MAP => 1,
                _ => 2,
            };
            let bytes = &bytes[..bytes.len() - cut];
            let mut buf = Buf { b: [0; 2048], n: 0 };
            let (i, o) = ([TickInput::default()], [TickOutput::default()]);
            encode_record("set", 1, bytes, &i, &o, &mut buf).unwrap();
            buf.b[4..6].copy_from_slice(&version.to_le_bytes());
            let crc = CRC32.checksum(&buf.b[..buf.n - 4]);
            buf.b[buf.n - 4..buf.n].copy_from_slice(&crc.to_le_bytes());
            buf
        };
        let recipe_of = |buf: &Buf| {
            VectorSets::new(&buf.b[..buf.n])
                .next()
                .unwrap()
                .unwrap()
                .recipe()
        };
        let bouc_wen = Settings {
            compensator: Some(representative_bouc_wen()),
            ..Settings::default()
        };
        let pi = Settings {
            compensator: Some(representative_pi(8).unwrap()),
            ..Settings::default()
        };
        assert!(recipe_of(&record(bouc_wen.clone(), FORMAT_VERSION)).is_ok());
        assert_eq!(
            recipe_of(&record(bouc_wen.clone(), FORMAT_VERSION_WITHOUT_OUTPUT_MAP))
                .map(|r| r.settings),
            Ok(bouc_wen.clone())
        );
        assert!(recipe_of(&record(bouc_wen.clone(), FORMAT_VERSION_WITHOUT_PREVIEW)).is_ok());
        assert!(recipe_of(&record(pi, FORMAT_VERSION_WITHOUT_CHI)).is_ok());
        assert_eq!(
            recipe_of(&record(bouc_wen, FORMAT_VERSION_WITHOUT_CHI)),
            Err(RecipeError::BoucWenWithoutChi)
        );
    }

    #[test]
    fn wrong_version_and_undefined_input_flags_say_so() {
        let buf = sample();
        // An older (or newer) version is refused, whatever else the record holds.
        for other in [FORMAT_VERSION_WITHOUT_SHAPING - 1, FORMAT_VERSION + 1] {
            let mut bad = buf.b;
            bad[4..6].copy_from_slice(&other.to_le_bytes());
            assert!(matches!(
                VectorSets::new(&bad[..buf.n]).next(),
                Some(Err(FormatError::BadVersion { got })) if got == other
            ));
        }
        assert_eq!(TickInput::from_bytes(&[0x08, 0, 0, 0, 0, 0, 0]), None);
        assert!(encode_record(
            "Bad Name",
            0,
            &[],
            &[],
            &[],
            &mut Buf { b: [0; 2048], n: 0 }
        )
        .is_none());
    }
}
