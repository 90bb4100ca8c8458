//! Golden vectors: recorded runs of the control tick that the board must reproduce bit for bit.
//!
//! A *vector set* is one configuration of the tick (compensator, observer, feedback, drive —
//! the [`Recipe`], in physical units, built by the same library code on the host and on the
//! board) and a few thousand ticks of inputs ([`TickInput`]: the setpoint or an underrun, the
//! sensor ADC code or a failed read, a failed DAC write) with the outputs the host's tick
//! produced from them ([`TickOutput`]: both DAC codes, the observer's estimate, the applied
//! drive, the flags). `twinstack golden --write` generates them; the replay image
//! (`src/bin/golden-replay.rs`) runs [`replay`] on the Cortex-M4 in QEMU, and the host test
//! runs the same [`replay`] on x86: both must give the stored outputs exactly.
//!
//! The byte layout is in [`format`]; the configuration's encoding and build in [`recipe`].
//! Nothing here allocates; a malformed file is refused with a [`FormatError`], never a panic.
//! It is its own `no_std` crate, apart from the firmware library: only the tests use it (the
//! host generator in `twinstack-identify`, the replay image in `qemu-images`).
#![no_std]
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod format;
pub mod recipe;

pub use format::{FormatError, VectorSet, VectorSets};
pub use recipe::{Recipe, RecipeError, MAX_RECIPE};

use crc::{Crc, Digest, CRC_32_ISO_HDLC};
use twinstack::board::{AdcCode, DacCode, DualDac, SensorAdc};
use twinstack::control::ControlConfig;
use twinstack::services::observer::Observed;

/// The CRC every digest of this module uses: CRC-32/ISO-HDLC (as zlib).
pub const CRC32: Crc<u32> = Crc::<u32>::new(&CRC_32_ISO_HDLC);

/// What the board's surroundings give one tick.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TickInput {
    /// The setpoint, Q2.30 normalised displacement (any `i32`: the tick clamps it), or `None`
    /// for an underrun (the tick holds the last setpoint).
    pub setpoint: Option<i32>,
    /// The sensor ADC's code (right-aligned; read only when feedback is on).
    pub adc_code: u16,
    /// The ADC read fails this tick.
    pub adc_fails: bool,
    /// The DAC write fails this tick (the tick reports it; the codes are still the tick's).
    pub dac_fails: bool,
}

/// What one tick put out.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TickOutput {
    /// Left stack's DAC code.
    pub left: u16,
    /// Right stack's DAC code.
    pub right: u16,
    /// Observer's estimate, Q2.30 normalised displacement.
    pub estimate: i32,
    /// Applied drive, Q2.30 model-normalised.
    pub drive: i32,
    /// [`twinstack::control::TickFlags`] bits.
    pub flags: u8,
}

/// The ADC as the replay presents it: the recorded code, or a failed read.
#[derive(Clone, Copy, Debug)]
pub struct ReplayAdc(pub Option<AdcCode>);

impl SensorAdc for ReplayAdc {
    type Error = ();
    fn full_scale(&self) -> AdcCode {
        AdcCode(u16::MAX as u32)
    }
    fn read(&mut self) -> Result<AdcCode, ()> {
        self.0.ok_or(())
    }
}

/// The DAC as the replay presents it: remembers the pair written, fails when told to.
#[derive(Clone, Copy, Debug, Default)]
pub struct ReplayDac {
    /// The last pair written.
    pub written: (DacCode, DacCode),
    /// Whether the next write fails.
    pub fails: bool,
}

impl DualDac for ReplayDac {
    type Error = ();
    fn full_scale(&self) -> DacCode {
        DacCode(u16::MAX)
    }
    fn write_both(&mut self, left: DacCode, right: DacCode) -> Result<(), ()> {
        self.written = (left, right);
        if self.fails {
            Err(())
        } else {
            Ok(())
        }
    }
}

/// One tick of `controller` on `input`: [`Observed::tick`] (the tick, and the observer below
/// it where the configuration has a sensor, as the board's services run it) with the
/// replay's ADC and DAC.
#[inline]
pub fn run_tick(controller: &mut Observed, input: &TickInput) -> TickOutput {
    let mut adc = ReplayAdc(if input.adc_fails {
        None
    } else {
        Some(AdcCode(input.adc_code as u32))
    });
    let mut dac = ReplayDac {
        written: (DacCode(0), DacCode(0)),
        fails: input.dac_fails,
    };
    let r = controller.tick(input.setpoint, &mut adc, &mut dac);
    TickOutput {
        left: r.left.0,
        right: r.right.0,
        estimate: r.estimate,
        drive: r.drive,
        flags: r.flags.0,
    }
}

/// A CRC-32 of a configuration's fixed-point form: of its `Debug` text, which names every
/// field of every model, so two configurations with the same fingerprint run the same tick.
/// The host and the board compute it from their own build of the [`Recipe`].
pub fn config_fingerprint(config: &ControlConfig) -> u32 {
    struct CrcWriter<'a>(Digest<'a, u32>);
    impl core::fmt::Write for CrcWriter<'_> {
        fn write_str(&mut self, s: &str) -> core::fmt::Result {
            self.0.update(s.as_bytes());
            Ok(())
        }
    }
    let mut w = CrcWriter(CRC32.digest());
    // Writing into a digest cannot fail.
    let _ = core::fmt::write(&mut w, format_args!("{config:?}"));
    w.0.finalize()
}

/// The first tick whose output differs from the stored one.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Mismatch {
    /// Tick index (0-based).
    pub tick: u32,
    /// Stored output.
    pub expected: TickOutput,
    /// Output of this run.
    pub actual: TickOutput,
}

/// What a replay found.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ReplayResult {
    /// Fingerprint of the configuration this run built.
    pub config_fingerprint: u32,
    /// CRC-32 of this run's outputs, serialised as in the file.
    pub outputs_crc: u32,
    /// Ticks run.
    pub ticks: u32,
    /// The first differing tick, if any.
    pub first_mismatch: Option<Mismatch>,
}

impl ReplayResult {
    /// Whether the run reproduced the set exactly (configuration and every output).
    pub fn matches(&self, set: &VectorSet<'_>) -> bool {
        self.first_mismatch.is_none()
            && self.config_fingerprint == set.config_fingerprint()
            && self.outputs_crc == set.outputs_crc()
    }
}

/// Builds the set's configuration, runs every stored input through [`Observed::tick`] from
/// a fresh controller, and compares each output with the stored one.
pub fn replay(set: &VectorSet<'_>) -> Result<ReplayResult, RecipeError> {
    let config = set.recipe()?.build()?;
    let mut controller = Observed::new(config);
    let mut digest = CRC32.digest();
    let mut first_mismatch = None;
    let mut ticks = 0u32;
    for (k, (input, expected)) in set.inputs().zip(set.outputs()).enumerate() {
        let actual = run_tick(&mut controller, &input);
        digest.update(&actual.to_bytes());
        if actual != expected && first_mismatch.is_none() {
            first_mismatch = Some(Mismatch {
                tick: k as u32,
                expected,
                actual,
            });
        }
        ticks += 1;
    }
    Ok(ReplayResult {
        config_fingerprint: config_fingerprint(&config),
        outputs_crc: digest.finalize(),
        ticks,
        first_mismatch,
    })
}
