//! The differential drive: how one normalised drive command becomes the two stacks' voltages,
//! and the limits that hold whatever the compensator asks for.
//!
//! The hysteresis models take the left stack's voltage `u_l` as their input (DESIGN §2), over the
//! model's input range. In the differential configuration the right stack mirrors it about the
//! bias: `u_l = ū + v`, `u_r = ū − v`; in the unidirectional one the right stack sits at a fixed
//! idle voltage. Limits act on the model-normalised drive, so that clamping or slewing `u_l`
//! moves `u_r` in exact mirror and the observer sees precisely the drive that was applied.
//!
//! Formats: model-normalised drive Q2.30 (±1 over the model's input range); stack voltages in
//! 2^-15 of a DAC code (Q17.15), so that the left stack's code is `code0 + (per_drive · u) >> 30`
//! (one `SMULL`) and the right stack's its mirror about `2ū`, all in 32 bits.

use crate::board::DacCode;
use crate::fixed_point::{limit, signal_from_f64, signal_to_f64, FULL_SCALE_MAX};
use crate::scaling::Scaling;

/// How the two stacks are driven.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Configuration {
    /// Both stacks: `u_l = ū + v`, `u_r = ū − v`.
    Differential,
    /// Left stack only; the right one sits at its idle voltage.
    Unidirectional,
}

/// Where the outputs go on a fault (panic, hard fault, stop).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SafeState {
    /// Both stacks at the bias `ū` (stage at its centre, no step on a fault).
    Bias,
    /// Both stacks at 0 V (no stored energy).
    Zero,
}

/// The drive's physical settings, in volts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DriveSettings {
    /// Stacks driven.
    pub configuration: Configuration,
    /// Amplifier output at DAC full scale, volts (e.g. 150).
    pub amplifier_full_scale: f64,
    /// Bias `ū`, volts (e.g. 70).
    pub bias: f64,
    /// Right stack's voltage in the unidirectional configuration, volts.
    pub right_idle: f64,
    /// Lowest voltage either stack may see, volts.
    pub min_voltage: f64,
    /// Highest voltage either stack may see, volts.
    pub max_voltage: f64,
    /// Largest change of a stack's voltage per second, volts/s (the amplifier's and the
    /// stack's current limit).
    pub slew_rate: f64,
    /// Control rate, Hz.
    pub control_rate: f64,
    /// Full-scale DAC code (4095 or 65535).
    pub dac_full_scale: u16,
    /// What the outputs do on a fault.
    pub safe_state: SafeState,
}

/// Why drive settings were refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum DriveError {
    /// A setting is NaN or infinite.
    NotFinite,
    /// `0 ≤ min < max ≤ amplifier full scale` does not hold.
    BadVoltageRange,
    /// The bias (or right idle voltage) lies outside the voltage range.
    BiasOutsideRange,
    /// Slew rate or control rate not positive.
    BadRate,
    /// Full-scale DAC code is zero.
    BadDacFullScale,
    /// No drive command lands inside the voltage range (model input range and limits disjoint).
    EmptyDriveRange,
    /// The model's input range reaches far beyond the amplifier's output range.
    ModelRangeBeyondAmplifier,
    /// An end of the drive range lands outside `0 ..= dac_full_scale` (the voltage range
    /// reaches past the amplifier's full scale by rounding).
    CodesBeyondDac,
}

/// The drive, converted once into the fixed-point form the tick uses.
///
/// A stack's DAC code is an affine function of the applied drive `a` (Q2.30), evaluated as one
/// multiply-accumulate into a Q19.45 accumulator (2^-45 of a code) and one shift:
/// `code = (base + per_drive · a) >> 45`, where `base` already holds the half code that makes
/// the shift round to nearest. The left stack rises with the drive (`per_drive > 0`), the
/// right one mirrors it (`−per_drive`, differential) or stays put (`0`, unidirectional), so
/// each code is monotonic in `a`: [`DifferentialDrive::new`] evaluates both codes at both ends
/// of the drive range and refuses a drive whose codes leave `0 ..= dac_full_scale` there,
/// which proves every drive the range limit lets through lands on a valid code — the tick
/// needs no clamp of its own after the range limit (the DAC driver still clamps to its
/// hardware width).
// Fields in the order the split reads them, so neighbours load in pairs (`LDRD`).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DifferentialDrive {
    /// Lowest model-normalised drive, Q2.30.
    drive_min: i32,
    /// Highest model-normalised drive, Q2.30.
    drive_max: i32,
    /// Left stack's code at drive 0 plus half a code, Q19.45 (2^-45 of a code).
    left_base: i64,
    /// Largest change of the model-normalised drive per tick, Q2.30.
    slew_per_tick: i32,
    /// Left stack's codes per unit of model-normalised drive, Q17.15 (> 0).
    left_per_drive: i32,
    /// Right stack's code at drive 0 plus half a code, Q19.45.
    right_base: i64,
    /// Right stack's codes per unit of drive, Q17.15: `−left_per_drive` (differential: it
    /// mirrors the left one about the bias) or 0 (unidirectional: it idles).
    right_per_drive: i32,
    /// DAC full-scale code.
    dac_full_scale: u16,
    /// The safe state's code for both stacks when it is the bias.
    bias_code: DacCode,
    configuration: Configuration,
    safe_state: SafeState,
    /// Model-normalised drive that puts the left stack at the bias, Q2.30 (the rest position).
    rest_drive: i32,
}

/// Both stacks' DAC codes and what the limits did this tick.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DriveOutput {
    /// Left stack code.
    pub left: DacCode,
    /// Right stack code.
    pub right: DacCode,
    /// The model-normalised drive actually applied, Q2.30 (what the observer is fed).
    pub applied: i32,
    /// The range limit clipped the command.
    pub range_limited: bool,
    /// The slew limit clipped the command.
    pub slew_limited: bool,
}

impl DifferentialDrive {
    /// Validates `settings` and builds the drive for a model whose input range is that of
    /// `scaling` (volts of the left stack).
    pub fn new(settings: &DriveSettings, scaling: &Scaling) -> Result<Self, DriveError> {
        let s = settings;
        let all_finite = [
            s.amplifier_full_scale,
            s.bias,
            s.right_idle,
            s.min_voltage,
            s.max_voltage,
            s.slew_rate,
            s.control_rate,
        ]
        .iter()
        .all(|v| v.is_finite());
        if !all_finite {
            return Err(DriveError::NotFinite);
        }
        if !(s.min_voltage >= 0.0
            && s.min_voltage < s.max_voltage
            && s.max_voltage <= s.amplifier_full_scale)
        {
            return Err(DriveError::BadVoltageRange);
        }
        let inside = |v: f64| v >= s.min_voltage && v <= s.max_voltage;
        if !inside(s.bias)
            || (s.configuration == Configuration::Unidirectional && !inside(s.right_idle))
        {
            return Err(DriveError::BiasOutsideRange);
        }
        if s.slew_rate <= 0.0 || s.control_rate <= 0.0 {
            return Err(DriveError::BadRate);
        }
        if s.dac_full_scale == 0 {
            return Err(DriveError::BadDacFullScale);
        }
        // Left-stack voltage window: in the differential configuration the right stack
        // (2ū − u_l) must stay in range too.
        let (lo, hi) = match s.configuration {
            Configuration::Differential => (
                s.min_voltage.max(2.0 * s.bias - s.max_voltage),
                s.max_voltage.min(2.0 * s.bias - s.min_voltage),
            ),
            Configuration::Unidirectional => (s.min_voltage, s.max_voltage),
        };
        let drive_min = scaling.input_to_norm(lo).max(-1.0);
        // The top of the full-scale range is 1 − 2^-30 (`clamp_full_scale`).
        let drive_max = scaling.input_to_norm(hi).min(signal_to_f64(FULL_SCALE_MAX));
        if drive_min > drive_max {
            return Err(DriveError::EmptyDriveRange);
        }
        let fs = s.amplifier_full_scale;
        let slew = s.slew_rate / s.control_rate / scaling.input_half_span();
        // Volts → 2^-15 of a DAC code. The model's input range must lie within the
        // amplifier's (so the left stack's per-drive slope fits 32 bits and every Q19.45
        // accumulation fits 64).
        let q15 = s.dac_full_scale as f64 * 32768.0 / fs;
        let per_drive = scaling.input_half_span() * q15;
        let code0 = scaling.input_mid() * q15;
        if !(per_drive < i32::MAX as f64 && code0.abs() < i32::MAX as f64 / 2.0) {
            return Err(DriveError::ModelRangeBeyondAmplifier);
        }
        let left_per_drive = (libm::round(per_drive) as i32).max(1);
        // Q17.15 → Q19.45, plus half a code (2^44) so that the tick's floor rounds to nearest.
        let q45 = |q15: f64| libm::round(q15 * (1u64 << 30) as f64) as i64 + (1 << 44);
        let (right_base, right_per_drive) = match s.configuration {
            // u_r = 2ū − u_l: the same slope, mirrored.
            Configuration::Differential => (q45(2.0 * s.bias * q15 - code0), -left_per_drive),
            Configuration::Unidirectional => (q45(s.right_idle * q15), 0),
        };
        let bias_code = libm::round(s.bias * q15 / 32768.0)
            .max(0.0)
            .min(s.dac_full_scale as f64);
        let drive = Self {
            configuration: s.configuration,
            drive_min: signal_from_f64(drive_min),
            drive_max: signal_from_f64(drive_max),
            slew_per_tick: signal_from_f64(slew.min(2.0)).max(1),
            bias_code: DacCode(bias_code as u16),
            // max/min, not f64::clamp: its panic message would pull float formatting into flash.
            rest_drive: signal_from_f64(
                scaling.input_to_norm(s.bias).max(drive_min).min(drive_max),
            ),
            dac_full_scale: s.dac_full_scale,
            safe_state: s.safe_state,
            left_base: q45(code0),
            left_per_drive,
            right_base,
            right_per_drive,
        };
        // The codes are monotonic in the drive: in range at both ends means in range
        // everywhere in between (see the type's doc).
        let fits = |code: i64| (0..=s.dac_full_scale as i64).contains(&code);
        for applied in [drive.drive_min, drive.drive_max] {
            let (left, right) = drive.codes(applied);
            if !(fits(left) && fits(right)) {
                return Err(DriveError::CodesBeyondDac);
            }
        }
        Ok(drive)
    }

    /// Both stacks' DAC codes for an applied drive (Q2.30), before they are narrowed to 16
    /// bits: one `SMLAL` and one shift each. Within `[drive_min, drive_max]` they lie in
    /// `0 ..= dac_full_scale` (checked by [`Self::new`] at the ends, monotonic in between).
    #[inline(always)]
    fn codes(&self, applied: i32) -> (i64, i64) {
        let left = self.left_base + self.left_per_drive as i64 * applied as i64;
        let right = self.right_base + self.right_per_drive as i64 * applied as i64;
        (left >> 45, right >> 45)
    }

    /// Applies range and slew limits to the command `drive` (model-normalised, Q2.30), given
    /// the drive applied on the previous tick, and splits it into both stacks' DAC codes.
    #[inline(always)]
    pub fn split(&self, drive: i32, previous: i32) -> DriveOutput {
        let ranged = limit(drive, self.drive_min, self.drive_max);
        let step_min = previous.saturating_sub(self.slew_per_tick);
        let step_max = previous.saturating_add(self.slew_per_tick);
        let applied = limit(ranged, step_min, step_max);
        let (left, right) = self.codes(applied);
        DriveOutput {
            // In `0 ..= dac_full_scale` (see `codes`): the narrowing is exact, one `UBFX`.
            left: DacCode((left as u32 & 0xFFFF) as u16),
            right: DacCode((right as u32 & 0xFFFF) as u16),
            applied,
            range_limited: ranged != drive,
            slew_limited: applied != ranged,
        }
    }

    /// The codes of the safe state (both stacks at the bias, or both at zero).
    pub fn safe_codes(&self) -> (DacCode, DacCode) {
        match self.safe_state {
            SafeState::Bias => (self.bias_code, self.bias_code),
            SafeState::Zero => (DacCode(0), DacCode(0)),
        }
    }

    /// The model-normalised drive that puts the left stack at the bias (the rest position).
    pub fn rest_drive(&self) -> i32 {
        self.rest_drive
    }

    /// Lowest and highest model-normalised drive the limits allow, Q2.30.
    pub fn drive_range(&self) -> (i32, i32) {
        (self.drive_min, self.drive_max)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed_point::signal_to_f64;

    fn settings(
        configuration: Configuration,
        fs: f64,
        min: f64,
        max: f64,
        bias: f64,
    ) -> DriveSettings {
        DriveSettings {
            configuration,
            amplifier_full_scale: fs,
            bias,
            right_idle: min,
            min_voltage: min,
            max_voltage: max,
            slew_rate: 1.0e6,
            control_rate: 50_000.0,
            dac_full_scale: 65535,
            safe_state: SafeState::Bias,
        }
    }

    /// The exact code of a stack voltage, before rounding.
    fn exact_code(volts: f64, s: &DriveSettings) -> f64 {
        volts / s.amplifier_full_scale * s.dac_full_scale as f64
    }

    #[test]
    fn codes_round_the_exact_voltage_to_nearest_and_mirror_about_the_bias() {
        let s = settings(Configuration::Differential, 150.0, 0.0, 140.0, 70.0);
        let scaling = Scaling::new(0.0, 140.0, 0.0, 10.0).unwrap();
        let d = DifferentialDrive::new(&s, &scaling).unwrap();
        let (lo, hi) = d.drive_range();
        for k in 0..=1000 {
            let applied = lo + ((hi as i64 - lo as i64) * k / 1000) as i32;
            let out = d.split(applied, applied);
            let ul = scaling.norm_to_input(signal_to_f64(applied));
            let (l, r) = (exact_code(ul, &s), exact_code(140.0 - ul, &s));
            assert!(
                (out.left.0 as f64 - l).abs() <= 0.5 + 1e-6,
                "{applied}: {} vs {l}",
                out.left.0
            );
            assert!(
                (out.right.0 as f64 - r).abs() <= 0.5 + 1e-6,
                "{applied}: {} vs {r}",
                out.right.0
            );
        }
    }

    proptest::proptest! {
        /// Every drive the constructor accepts maps its whole range onto valid codes: the
        /// tick's split has no clamp of its own, so this is what keeps a code from wrapping.
        #[test]
        fn accepted_drives_keep_every_code_within_the_dac(
            fs in 10.0f64..200.0,
            lo_frac in 0.0f64..0.5,
            hi_frac in 0.5f64..=1.0,
            bias_frac in 0.0f64..=1.0,
            in_lo_frac in 0.0f64..0.5,
            in_hi_frac in 0.5f64..=1.0,
            twelve_bit in proptest::bool::ANY,
            differential in proptest::bool::ANY,
            picks in proptest::array::uniform32(0.0f64..=1.0),
        ) {
            let (min, max) = (fs * lo_frac, fs * hi_frac);
            let mut s = settings(
                if differential { Configuration::Differential } else { Configuration::Unidirectional },
                fs, min, max, min + (max - min) * bias_frac,
            );
            s.right_idle = s.bias;
            s.dac_full_scale = if twelve_bit { 4095 } else { 65535 };
            let scaling = Scaling::new(fs * in_lo_frac, fs * in_hi_frac, 0.0, 10.0).unwrap();
            let Ok(d) = DifferentialDrive::new(&s, &scaling) else {
                return Ok(()); // refused: nothing to hold
            };
            let (lo, hi) = d.drive_range();
            let picked = picks.map(|p| lo + ((hi as f64 - lo as f64) * p) as i32);
            let ends = [lo, hi, i32::MIN, i32::MAX, 0];
            for command in picked.into_iter().chain(ends) {
                // From any previous drive in range; the slew limit keeps it in range too.
                let out = d.split(command, lo.max(hi.min(command)));
                proptest::prop_assert!(out.applied >= lo && out.applied <= hi);
                proptest::prop_assert!(out.left.0 <= s.dac_full_scale);
                proptest::prop_assert!(out.right.0 <= s.dac_full_scale);
                let ul = scaling.norm_to_input(signal_to_f64(out.applied));
                proptest::prop_assert!(
                    (out.left.0 as f64 - exact_code(ul, &s)).abs() <= 0.5 + 1e-6,
                    "left {} for {} V", out.left.0, ul
                );
            }
        }
    }
}
