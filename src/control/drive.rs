//! The differential drive: how one normalised drive command becomes the two stacks' voltages,
//! and the limits that hold whatever the compensator asks for.
//!
//! The hysteresis models take the left stack's voltage `u_l` as their input (see the book's models chapter), over the
//! model's input range. In the differential configuration the right stack mirrors it about the
//! bias: `u_l = ū + v`, `u_r = ū − v`; in the unidirectional one the right stack sits at a fixed
//! idle voltage. Limits act on the model-normalised drive, so that clamping or slewing `u_l`
//! moves `u_r` in exact mirror and the observer sees precisely the drive that was applied.
//!
//! Formats: model-normalised drive Q2.30 (±1 over the model's input range); stack voltages in
//! board units, Q17.15 DAC codes (2^-15 of a code; see [`DifferentialDrive`]).

use crate::board::{DacCode, Hardware};
use crate::fixed_point::{limit, signal_from_f64, signal_to_f64, FULL_SCALE_MAX};
use crate::models::Rest;
use crate::refusal::{finite, within, Field, Refusal, Rule};
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

impl Configuration {
    /// Where the models' memory stands when a stage driven so rests: [`Rest::Relaxed`] for
    /// the differential pair (both stacks rose together to the bias, and in the models'
    /// coordinate their hysteresis cancels), [`Rest::Ascending`] for the unidirectional
    /// (single-ended) stack, raised from its lowest voltage.
    ///
    /// ```
    /// use twinstack::control::drive::Configuration;
    /// use twinstack::models::Rest;
    /// assert_eq!(Configuration::Differential.rest(), Rest::Relaxed);
    /// assert_eq!(Configuration::Unidirectional.rest(), Rest::Ascending);
    /// ```
    pub const fn rest(self) -> Rest {
        match self {
            Self::Differential => Rest::Relaxed,
            Self::Unidirectional => Rest::Ascending,
        }
    }
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

/// The drive's settings, in volts: what a user sets (the amplifier and the DAC are
/// [`Hardware`] facts). Built into the tick's [`DifferentialDrive`] by [`DriveSettings::build`].
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DriveSettings {
    /// Stacks driven.
    pub configuration: Configuration,
    /// Bias `ū`, volts (e.g. 70): the differential pair's centre, and the rest position.
    pub bias: f64,
    /// Lowest voltage either stack may see, volts (the right stack idles here in the
    /// unidirectional configuration).
    pub min_voltage: f64,
    /// Highest voltage either stack may see, volts.
    pub max_voltage: f64,
    /// Largest change of either stack's voltage per second, volts/s (the amplifier's and the
    /// stack's current limit).
    pub slew_rate: f64,
    /// What the outputs do on a fault, and where the board starts.
    pub safe_state: SafeState,
}

/// The drive, converted once into the fixed-point form the tick uses.
///
/// Two forms of the drive meet here. The **model-normalised drive** (Q2.30, ±1 over the
/// model's input range) is what the compensator commands and the observer is fed. The **stack
/// voltages** are kept in board units, Q17.15 DAC codes (2^-15 of a code), which no setting
/// can change: that is the form the slew limiter remembers, so a reload that changes the model's
/// ranges, the bias or the limits finds the stacks exactly where they are and moves them on
/// from there, at most one slew step per tick.
///
/// One tick ([`DifferentialDrive::split`]): the command is limited to the drive range
/// (model-normalised), converted to the left stack's voltage (one `SMLAL`), slew-limited
/// against the left stack's previous voltage; the right stack's voltage is the mirror about
/// `2ū` (differential) or the idle voltage (unidirectional), within the voltage limits and
/// slew-limited against its own previous voltage; each is rounded to its DAC code.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DifferentialDrive {
    /// Lowest model-normalised drive, Q2.30.
    drive_min: i32,
    /// Highest model-normalised drive, Q2.30.
    drive_max: i32,
    /// Left stack's voltage at drive 0 plus half an LSB, Q17.45 (2^-45 of a code).
    left_base: i64,
    /// Left stack's Q17.15 codes per unit of model-normalised drive (> 0).
    left_per_drive: i32,
    /// Largest change of a stack's voltage per tick, Q17.15 codes (≥ 1).
    slew: i32,
    /// The right stack's voltage: `right_base − (left & right_mask)`, Q17.15: the mirror
    /// about `2ū` (`right_base = 2ū`, mask all ones) or the idle voltage (mask zero).
    right_base: i32,
    right_mask: i32,
    /// Voltage limits, Q17.15 codes.
    stack_min: i32,
    stack_max: i32,
    /// Back from the left stack's voltage to the model-normalised drive:
    /// `((left − left_zero) · from_stack) >> from_stack_shift`, for `left` within
    /// `[left_min, left_max]` (the drive range's voltages, Q17.15), so it fits 32 bits.
    left_min: i32,
    left_max: i32,
    left_zero: i32,
    from_stack: i32,
    from_stack_shift: u32,
    /// DAC full-scale code.
    dac_full_scale: u16,
    configuration: Configuration,
    safe_state: SafeState,
    /// The safe state's voltages, Q17.15.
    safe: StackVoltages,
    /// Model-normalised drive that puts the left stack at the bias, Q2.30 (the rest position).
    rest_drive: i32,
}

/// Both stacks' voltages in board units, Q17.15 DAC codes: what the slew limiter remembers
/// from tick to tick (and across reloads).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StackVoltages {
    /// Left stack, Q17.15 codes.
    pub left: i32,
    /// Right stack, Q17.15 codes.
    pub right: i32,
}

impl StackVoltages {
    /// The DAC codes (rounded to nearest).
    #[inline(always)]
    pub fn codes(self) -> (DacCode, DacCode) {
        let round = |v: i32| DacCode((((v as u32).wrapping_add(1 << 14)) >> 15) as u16);
        (round(self.left), round(self.right))
    }
}

/// Both stacks' DAC codes and what the limits did this tick.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DriveOutput {
    /// Left stack code.
    pub left: DacCode,
    /// Right stack code.
    pub right: DacCode,
    /// Both stacks' voltages (the slew limiter's memory for the next tick).
    pub stacks: StackVoltages,
    /// The model-normalised drive actually applied, Q2.30 (what the observer is fed).
    pub applied: i32,
    /// The range limit clipped the command.
    pub range_limited: bool,
    /// The slew limit clipped either stack.
    pub slew_limited: bool,
}

impl DriveSettings {
    /// The left stack's voltage window `(lowest, highest)`, volts: the voltage limits, and in
    /// the differential configuration also where the right stack (`2ū − u_l`) stays within
    /// them. The model's input range beyond it cannot be driven (the limit clips it).
    ///
    /// ```
    /// use twinstack::control::drive::DriveSettings;
    /// let d = DriveSettings { bias: 50.0, ..DriveSettings::DEFAULT }; // 0…140 V, differential
    /// assert_eq!(d.left_window(), (0.0, 100.0));
    /// ```
    pub fn left_window(&self) -> (f64, f64) {
        match self.configuration {
            Configuration::Differential => (
                self.min_voltage.max(2.0 * self.bias - self.max_voltage),
                self.max_voltage.min(2.0 * self.bias - self.min_voltage),
            ),
            Configuration::Unidirectional => (self.min_voltage, self.max_voltage),
        }
    }

    /// The board's default drive: differential, bias 70 V, each stack within 0…140 V,
    /// 2 V/µs, safe state at the bias.
    pub const DEFAULT: DriveSettings = DriveSettings {
        configuration: Configuration::Differential,
        bias: 70.0,
        min_voltage: 0.0,
        max_voltage: 140.0,
        slew_rate: 2.0e6,
        safe_state: SafeState::Bias,
    };

    /// Validates the settings on `hardware` for a model whose input range is `scaling`'s
    /// (volts of the left stack) and builds the tick's drive.
    ///
    /// ```
    /// use twinstack::board::Hardware;
    /// use twinstack::control::drive::DriveSettings;
    /// use twinstack::Scaling;
    /// let ranges = Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap();
    /// let drive = DriveSettings::DEFAULT.build(&Hardware::driver_board(50e3), &ranges).unwrap();
    /// assert_eq!(drive.rest_drive(), 0); // the bias is mid-range
    /// ```
    pub fn build(&self, hw: &Hardware, scaling: &Scaling) -> Result<DifferentialDrive, Refusal> {
        let s = self;
        let fs = hw.amplifier_full_scale;
        finite(Field::Bias, s.bias)?;
        finite(Field::VoltageLimits, s.min_voltage)?;
        finite(Field::VoltageLimits, s.max_voltage)?;
        finite(Field::SlewRate, s.slew_rate)?;
        if !(fs.is_finite() && fs > 0.0 && hw.dac_full_scale > 0) {
            return Err(Refusal::new(Field::VoltageLimits, Rule::NoHardware));
        }
        if !(hw.control_rate_hz.is_finite() && hw.control_rate_hz > 0.0) {
            return Err(Refusal::new(Field::SlewRate, Rule::NoHardware));
        }
        within(Field::VoltageLimits, s.min_voltage, 0.0, fs)?;
        within(Field::VoltageLimits, s.max_voltage, 0.0, fs)?;
        if s.max_voltage <= s.min_voltage {
            return Err(Refusal::new(Field::VoltageLimits, Rule::Empty));
        }
        within(Field::Bias, s.bias, s.min_voltage, s.max_voltage)?;
        if s.slew_rate <= 0.0 {
            return Err(Refusal::new(Field::SlewRate, Rule::Above(0.0)));
        }
        let (lo, hi) = s.left_window();
        let drive_min = scaling.input_to_norm(lo).max(-1.0);
        // The top of the full-scale range is 1 − 2^-30 (`clamp_full_scale`).
        let drive_max = scaling.input_to_norm(hi).min(signal_to_f64(FULL_SCALE_MAX));
        if drive_min.is_nan() || drive_max.is_nan() || drive_min > drive_max {
            return Err(Refusal::new(Field::InputRange, Rule::Unreachable));
        }
        // Volts → 2^-15 of a DAC code.
        let q15 = hw.dac_full_scale as f64 * 32768.0 / fs;
        let per_drive = scaling.input_half_span() * q15;
        let code0 = scaling.input_mid() * q15;
        if !(per_drive < i32::MAX as f64 && code0.abs() < i32::MAX as f64 / 2.0) {
            return Err(Refusal::new(Field::InputRange, Rule::AtMost(2.0 * fs)));
        }
        let left_per_drive = (libm::round(per_drive) as i32).max(1);
        let q15_of = |volts: f64| libm::round(volts * q15) as i32;
        // Back-conversion: the largest shift whose factor 2^(30+shift)/per fits 31 bits.
        let mut shift = 0u32;
        while shift < 32 && (1u64 << (31 + shift)) as f64 / (left_per_drive as f64) < 2.0e9 {
            shift += 1;
        }
        let from_stack = libm::round((1u64 << (30 + shift)) as f64 / left_per_drive as f64) as i32;
        let (right_base, right_mask) = match s.configuration {
            Configuration::Differential => (q15_of(2.0 * s.bias), -1),
            Configuration::Unidirectional => (q15_of(s.min_voltage), 0),
        };
        let bias = q15_of(s.bias);
        let safe = match s.safe_state {
            SafeState::Bias => StackVoltages {
                left: bias,
                right: bias,
            },
            SafeState::Zero => StackVoltages::default(),
        };
        let drive = DifferentialDrive {
            drive_min: signal_from_f64(drive_min),
            drive_max: signal_from_f64(drive_max),
            // Q17.15 → Q17.45, plus half an LSB of Q17.15 so the shift rounds to nearest.
            left_base: ((libm::round(code0) as i64) << 30) + (1 << 29),
            left_per_drive,
            slew: (libm::round(s.slew_rate / hw.control_rate_hz * q15).min(i32::MAX as f64) as i32)
                .max(1),
            right_base,
            right_mask,
            stack_min: q15_of(s.min_voltage),
            stack_max: q15_of(s.max_voltage),
            left_min: 0,
            left_max: 0,
            left_zero: libm::round(code0) as i32,
            from_stack,
            from_stack_shift: shift,
            dac_full_scale: hw.dac_full_scale,
            configuration: s.configuration,
            safe_state: s.safe_state,
            safe,
            // max/min, not f64::clamp: its panic message would pull float formatting into flash.
            rest_drive: signal_from_f64(
                scaling.input_to_norm(s.bias).max(drive_min).min(drive_max),
            ),
        };
        let mut drive = drive;
        drive.left_min = drive.left_of(drive.drive_min);
        drive.left_max = drive.left_of(drive.drive_max);
        // Every voltage the limits allow must have a code: the stack limits lie within the
        // amplifier's range, so this holds unless rounding pushes an end past full scale.
        let top = (hw.dac_full_scale as i64) << 15;
        if drive.stack_max as i64 + (1 << 14) > top + (1 << 15) - 1 || drive.stack_min < 0 {
            return Err(Refusal::new(Field::VoltageLimits, Rule::Unreachable));
        }
        Ok(drive)
    }
}

impl DifferentialDrive {
    /// The left stack's voltage for a model-normalised drive within the drive range, Q17.15.
    #[inline(always)]
    fn left_of(&self, drive: i32) -> i32 {
        // Only ever called with a drive within the drive range, whose voltages lie within
        // the amplifier's (checked by `DriveSettings::build`): the value fits 32 bits.
        ((self.left_base + self.left_per_drive as i64 * drive as i64) >> 30) as i32
    }

    /// The model-normalised drive of a left-stack voltage (Q17.15), within the drive range to
    /// rounding (a few LSB): the voltage is first limited to the drive range's voltages, so the
    /// product and the result fit 32 bits (one `SMULL` and a shift; no 64-bit compares). Where
    /// it is used — the observer's input on a slew-limited tick, a transfer's starting point —
    /// the models clamp their inputs to full scale, which lies beyond the drive range.
    #[inline(always)]
    pub fn drive_of(&self, left: i32) -> i32 {
        let left = limit(left, self.left_min, self.left_max);
        (((left.wrapping_sub(self.left_zero)) as i64 * self.from_stack as i64)
            >> self.from_stack_shift) as i32
    }

    /// Both stacks' voltages for a drive at rest in `drive` (no slew limit): where the stacks
    /// settle for it.
    pub fn stacks_at(&self, drive: i32) -> StackVoltages {
        let left = self.left_of(limit(drive, self.drive_min, self.drive_max));
        StackVoltages {
            left,
            right: limit(
                self.right_base.wrapping_sub(left & self.right_mask),
                self.stack_min,
                self.stack_max,
            ),
        }
    }

    /// Applies the range limit to the command `drive` (model-normalised, Q2.30) and the slew
    /// limit against the stacks' voltages on the previous tick (`previous`, board units), and
    /// gives both stacks' DAC codes. `slew` is the slew step in force (Q17.15 codes per tick:
    /// [`Self::slew`], or a stricter one while a reload settles).
    #[inline(always)]
    pub fn split(&self, drive: i32, previous: StackVoltages, slew: i32) -> DriveOutput {
        let ranged = limit(drive, self.drive_min, self.drive_max);
        let left_target = self.left_of(ranged);
        let left = limit(
            left_target,
            previous.left.saturating_sub(slew),
            previous.left.saturating_add(slew),
        );
        let right_target = limit(
            self.right_base.wrapping_sub(left & self.right_mask),
            self.stack_min,
            self.stack_max,
        );
        let right = limit(
            right_target,
            previous.right.saturating_sub(slew),
            previous.right.saturating_add(slew),
        );
        let stacks = StackVoltages { left, right };
        let (l, r) = stacks.codes();
        let left_limited = left != left_target;
        DriveOutput {
            left: l,
            right: r,
            stacks,
            // Unlimited, the observer gets the command itself, bit for bit; slewed, the drive
            // of the voltage the left stack actually has.
            applied: if left_limited {
                limit(self.drive_of(left), self.drive_min, self.drive_max)
            } else {
                ranged
            },
            range_limited: ranged != drive,
            slew_limited: left_limited | (right != right_target),
        }
    }

    /// The slew step the settings allow, Q17.15 codes per tick.
    pub fn slew(&self) -> i32 {
        self.slew
    }

    /// The stacks' voltages in the safe state (board units).
    pub fn safe_stacks(&self) -> StackVoltages {
        self.safe
    }

    /// The codes of the safe state (both stacks at the bias, or both at zero).
    pub fn safe_codes(&self) -> (DacCode, DacCode) {
        self.safe.codes()
    }

    /// The model-normalised drive that puts the left stack at the bias (the rest position).
    pub fn rest_drive(&self) -> i32 {
        self.rest_drive
    }

    /// Where the models' memory stands when the drive rests ([`Configuration::rest`]): on
    /// the loop for the single-ended stack, relaxed for the pair.
    pub fn rest(&self) -> Rest {
        self.configuration.rest()
    }

    /// Lowest and highest model-normalised drive the limits allow, Q2.30.
    pub fn drive_range(&self) -> (i32, i32) {
        (self.drive_min, self.drive_max)
    }

    /// Lowest and highest stack voltage the limits allow, Q17.15 codes.
    pub fn stack_range(&self) -> (i32, i32) {
        (self.stack_min, self.stack_max)
    }

    /// DAC full-scale code.
    pub fn dac_full_scale(&self) -> u16 {
        self.dac_full_scale
    }

    /// Stacks driven.
    pub fn configuration(&self) -> Configuration {
        self.configuration
    }

    /// The safe state.
    pub fn safe_state(&self) -> SafeState {
        self.safe_state
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed_point::signal_to_f64;

    fn settings(configuration: Configuration, min: f64, max: f64, bias: f64) -> DriveSettings {
        DriveSettings {
            configuration,
            bias,
            min_voltage: min,
            max_voltage: max,
            slew_rate: 1.0e9,
            safe_state: SafeState::Bias,
        }
    }

    fn hw(fs: f64, dac: u16) -> Hardware {
        Hardware {
            amplifier_full_scale: fs,
            dac_full_scale: dac,
            sensor_adc_bits: None,
            control_rate_hz: 50_000.0,
        }
    }

    /// The exact code of a stack voltage, before rounding.
    fn exact_code(volts: f64, hw: &Hardware) -> f64 {
        volts / hw.amplifier_full_scale * hw.dac_full_scale as f64
    }

    #[test]
    fn codes_round_the_exact_voltage_to_nearest_and_mirror_about_the_bias() {
        let s = settings(Configuration::Differential, 0.0, 140.0, 70.0);
        let h = hw(150.0, 65535);
        let scaling = Scaling::new(0.0, 140.0, 0.0, 10.0).unwrap();
        let d = s.build(&h, &scaling).unwrap();
        let (lo, hi) = d.drive_range();
        for k in 0..=1000 {
            let applied = lo + ((hi as i64 - lo as i64) * k / 1000) as i32;
            let out = d.split(applied, d.stacks_at(applied), d.slew());
            assert_eq!(out.applied, applied, "unlimited: the command itself");
            let ul = scaling.norm_to_input(signal_to_f64(applied));
            let (l, r) = (exact_code(ul, &h), exact_code(140.0 - ul, &h));
            assert!(
                (out.left.0 as f64 - l).abs() <= 0.5 + 1e-3,
                "{applied}: {} vs {l}",
                out.left.0
            );
            assert!(
                (out.right.0 as f64 - r).abs() <= 0.5 + 1e-3,
                "{applied}: {} vs {r}",
                out.right.0
            );
        }
    }

    #[test]
    fn refusals_name_the_field() {
        let h = hw(150.0, 4095);
        let scaling = Scaling::new(0.0, 140.0, 0.0, 10.0).unwrap();
        let mut s = settings(Configuration::Differential, 0.0, 140.0, 70.0);
        s.bias = f64::NAN;
        assert_eq!(
            s.build(&h, &scaling).unwrap_err(),
            Refusal::new(Field::Bias, Rule::NotFinite)
        );
        s.bias = 145.0;
        assert_eq!(
            s.build(&h, &scaling).unwrap_err(),
            Refusal::new(Field::Bias, Rule::AtMost(140.0))
        );
        s.bias = 70.0;
        s.max_voltage = 160.0;
        assert_eq!(
            s.build(&h, &scaling).unwrap_err(),
            Refusal::new(Field::VoltageLimits, Rule::AtMost(150.0))
        );
        s.max_voltage = 140.0;
        s.slew_rate = f64::INFINITY;
        assert_eq!(s.build(&h, &scaling).unwrap_err().field, Field::SlewRate);
    }

    #[test]
    fn the_slew_limit_holds_on_both_stacks_and_the_applied_drive_follows_the_left_one() {
        let h = hw(150.0, 4095);
        let scaling = Scaling::new(0.0, 140.0, 0.0, 10.0).unwrap();
        let mut s = settings(Configuration::Differential, 0.0, 140.0, 70.0);
        s.slew_rate = 50_000.0; // 1 V per tick
        let d = s.build(&h, &scaling).unwrap();
        let mut prev = d.stacks_at(d.rest_drive());
        let out = d.split(i32::MAX, prev, d.slew());
        assert!(out.slew_limited && out.range_limited);
        let volts = |v: i32| v as f64 / 32768.0 / 4095.0 * 150.0;
        assert!((volts(out.stacks.left) - 71.0).abs() < 1e-3);
        assert!((volts(out.stacks.right) - 69.0).abs() < 1e-3);
        assert!((scaling.norm_to_input(signal_to_f64(out.applied)) - 71.0).abs() < 1e-3);
        // A right stack far from its mirror (a bias change) slews there too.
        prev.right = 0;
        let out = d.split(d.rest_drive(), prev, d.slew());
        assert!((volts(out.stacks.right) - 1.0).abs() < 1e-3 && out.slew_limited);
    }

    #[test]
    fn the_drive_of_a_voltage_inverts_the_voltage_of_a_drive_and_stays_in_range() {
        let h = hw(150.0, 4095);
        for (lo, hi) in [(0.0, 140.0), (-156.0, 156.0), (0.0, 3.6), (100.0, 110.0)] {
            let scaling = Scaling::new(lo, hi, 0.0, 10.0).unwrap();
            let mut s = settings(Configuration::Unidirectional, 0.0, 140.0, 0.0);
            s.min_voltage = lo.max(0.0);
            s.max_voltage = hi.min(140.0);
            s.bias = s.min_voltage;
            let d = s.build(&h, &scaling).unwrap();
            let (dmin, dmax) = d.drive_range();
            for k in 0..=100i64 {
                let drive = (dmin as i64 + (dmax as i64 - dmin as i64) * k / 100) as i32;
                let back = d.drive_of(d.stacks_at(drive).left);
                // One Q17.15 step of voltage is this many drive LSBs (plus rounding).
                let tolerance = (d.from_stack as i64 >> d.from_stack_shift).max(0) + 2;
                assert!(
                    ((back - drive) as i64).abs() <= tolerance,
                    "{lo}…{hi}: {drive} → {back}"
                );
            }
            for far in [i32::MIN, -1, 0, i32::MAX] {
                let back = d.drive_of(far);
                assert!(
                    back >= dmin - 4 && back <= dmax.saturating_add(4),
                    "{far} → {back}"
                );
            }
        }
    }

    proptest::proptest! {
        /// Every drive the builder accepts keeps every code within the DAC, from any previous
        /// voltages within the limits, and rounds the exact voltage to nearest.
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
            let s = settings(
                if differential { Configuration::Differential } else { Configuration::Unidirectional },
                min, max, min + (max - min) * bias_frac,
            );
            let h = hw(fs, if twelve_bit { 4095 } else { 65535 });
            let scaling = Scaling::new(fs * in_lo_frac, fs * in_hi_frac, 0.0, 10.0).unwrap();
            let Ok(d) = s.build(&h, &scaling) else {
                return Ok(()); // refused: nothing to hold
            };
            let (lo, hi) = d.drive_range();
            let picked = picks.map(|p| lo + ((hi as f64 - lo as f64) * p) as i32);
            let ends = [lo, hi, i32::MIN, i32::MAX, 0];
            for command in picked.into_iter().chain(ends) {
                let from = d.stacks_at(lo.max(hi.min(command)));
                let out = d.split(command, from, d.slew());
                proptest::prop_assert!(out.applied >= lo && out.applied <= hi);
                proptest::prop_assert!(out.left.0 <= h.dac_full_scale);
                proptest::prop_assert!(out.right.0 <= h.dac_full_scale);
                let ul = scaling.norm_to_input(signal_to_f64(out.applied));
                proptest::prop_assert!(
                    (out.left.0 as f64 - exact_code(ul, &h)).abs() <= 0.5 + 1e-3,
                    "left {} for {} V", out.left.0, ul
                );
            }
        }
    }
}
