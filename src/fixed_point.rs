//! Fixed-point formats of the control tick.
//!
//! Two `i32` formats carry every signal and model coefficient:
//!
//! | name | format | 1.0 is | range | resolution | used for |
//! |------|--------|--------|-------|------------|----------|
//! | signal | Q2.30 | `1 << 30` | [-2, 2) | 9.3e-10 | normalised drive, displacement, play states, thresholds |
//! | gain | Q8.24 | `1 << 24` | [-128, 128) | 6.0e-8 | P–I weights (forward and inverse), Duhem α β γ |
//!
//! Three more `i32` formats hold the feedback's coefficients, and two `i64` formats hold the
//! accumulators inside a step:
//!
//! | format | range | used for |
//! |--------|-------|----------|
//! | Q4.28 `i32` ([`q4_28_from_f64`]) | [-8, 8) | feedback `kp` and `kd`, sensor calibration |
//! | Q1.31 `i32` ([`q1_31_from_f64`]) | [-1, 1) | per-tick coefficients below 1 (filter poles) |
//! | Q0.32 `i32` ([`q0_32_from_f64`], [`mul_high`]) | [-0.5, 0.5) | the integral gain per tick: `ki · e` is one `SMMUL` |
//! | Q10.54 `i64` ([`Q54_FRAC_BITS`]) | | gain × signal products and their sums (P–I) |
//! | Q4.60 `i64` ([`Q60_FRAC_BITS`]) | | signal × signal products and their sums (the Duhem update) |
//!
//! The differential split forms its DAC codes in a Q19.45 `i64` of its own (see
//! [`crate::control::drive`]).
//!
//! Signals are *normalised*: the physical range of a quantity (e.g. 0…150 V of drive, or the
//! stage's stroke in µm) maps to [-1, 1] (see [`crate::scaling::Scaling`]). The extra integer bit
//! of Q2.30 is headroom: a play operator's state lives in `[u − r, u + r]`, which leaves [-1, 1]
//! when `r > 0`, and intermediate sums may overshoot before the final saturation.
//!
//! The inverse P–I's weights `w'_i = −w_i / (S_i S_{i−1})` routinely exceed 10 in magnitude;
//! Q8.24 holds ±128 and still resolves 6e-8, i.e. 1/500 of a 16-bit LSB per unit signal.
//! Products of a gain and a signal are formed in `i64` (Q10.54) and summed there; parameter
//! validation bounds `Σ|w|` so that the sum provably fits (see [`MAX_GAIN_SUM`]), and only the
//! final result is brought back to Q2.30 ([`q54_to_signal_floor`]; [`q60_to_signal_floor`] for
//! Q4.60), saturating.
//!
//! **Why our own Q types rather than the `fixed` crate.** The tick needs a handful of formats,
//! widening multiply-accumulates and saturation at a few chosen points. Writing those as
//! plain `i32`/`i64` operations keeps the generated code obvious (one `SMLAL` per operator on
//! the Cortex-M4, `QADD`/`QSUB` for saturating adds), makes the rounding explicit, so host and
//! target are bit-identical by construction, and adds no dependency to the firmware.
//! Every conversion from `f64` saturates and rejects NaN.

/// Fractional bits of a Q2.30 signal.
pub const SIGNAL_FRAC_BITS: u32 = 30;
/// Fractional bits of a Q8.24 gain.
pub const GAIN_FRAC_BITS: u32 = 24;
/// Fractional bits of an accumulator of gain × signal products (Q10.54 in `i64`).
pub const Q54_FRAC_BITS: u32 = SIGNAL_FRAC_BITS + GAIN_FRAC_BITS;
/// 1.0 as a Q2.30 signal (full scale).
pub const SIGNAL_ONE: i32 = 1 << SIGNAL_FRAC_BITS;
/// 1.0 as a Q8.24 gain.
pub const GAIN_ONE: i32 = 1 << GAIN_FRAC_BITS;
/// Largest `Σ|w_i|` (plus `|offset|`) a model may have, so that a Q10.54 accumulation of
/// gains × signals (|signal| < 2) stays inside `i64`: `64 · 2 · 2^54 = 2^61 < 2^63`.
pub const MAX_GAIN_SUM: f64 = 64.0;

/// Converts a real number to Q2.30 with rounding to nearest, saturating at the range ends.
/// NaN maps to 0 (callers validate parameters before conversion; this is a last guard).
pub const fn signal_from_f64(x: f64) -> i32 {
    to_fixed(x, SIGNAL_FRAC_BITS)
}

/// Converts a Q2.30 signal to a real number.
pub fn signal_to_f64(q: i32) -> f64 {
    q as f64 / SIGNAL_ONE as f64
}

/// Converts a real number to Q8.24 with rounding to nearest, saturating at the range ends.
pub fn gain_from_f64(x: f64) -> i32 {
    to_fixed(x, GAIN_FRAC_BITS)
}

/// Converts a Q8.24 gain to a real number.
pub fn gain_to_f64(q: i32) -> f64 {
    q as f64 / GAIN_ONE as f64
}

/// Converts a real number to Q4.28 (range [-8, 8)) with rounding to nearest, saturating.
/// Used by the feedback's proportional and derivative gains and its sensor calibration.
pub fn q4_28_from_f64(x: f64) -> i32 {
    to_fixed(x, 28)
}

/// Converts a real number to Q1.31 (range [-1, 1)) with rounding to nearest, saturating.
/// Used by per-tick coefficients below 1 (integral gain, filter poles): a product with a
/// Q2.30 signal shifted right by 31 is again Q2.30 and cannot overflow.
pub fn q1_31_from_f64(x: f64) -> i32 {
    to_fixed(x, 31)
}

/// Converts a real number to Q0.32 in a signed word (range [-0.5, 0.5)) with rounding to
/// nearest, saturating. Used by per-tick gains below one half (the integral gain): the
/// product with a Q2.30 signal is then the high word of the 64-bit product, one `SMMUL`.
pub fn q0_32_from_f64(x: f64) -> i32 {
    to_fixed(x, 32)
}

/// `(a · b) >> 32`: the high word of the 64-bit product (`SMMUL` on the Cortex-M4). A Q0.32
/// gain times a Q2.30 signal is a Q2.30 signal; it cannot overflow.
#[inline(always)]
pub fn mul_high(a: i32, b: i32) -> i32 {
    ((a as i64 * b as i64) >> 32) as i32
}

const fn to_fixed(x: f64, frac_bits: u32) -> i32 {
    if x.is_nan() {
        return 0;
    }
    let scaled = x * (1u64 << frac_bits) as f64;
    let rounded = if scaled >= 0.0 {
        scaled + 0.5
    } else {
        scaled - 0.5
    };
    if rounded >= i32::MAX as f64 {
        i32::MAX
    } else if rounded <= i32::MIN as f64 {
        i32::MIN
    } else {
        rounded as i32
    }
}

/// Saturates a Q10.54 accumulator (a sum of gain × signal products) to a Q2.30 signal,
/// rounding to nearest.
#[inline(always)]
pub fn saturate_q54_to_signal(acc: i64) -> i32 {
    let shifted = (acc.saturating_add(1 << (GAIN_FRAC_BITS - 1))) >> GAIN_FRAC_BITS;
    saturate_i64(shifted)
}

/// Converts a Q10.54 accumulator to a Q2.30 signal, rounding toward −∞ (truncation of the
/// 24 dropped bits, at most 2^-30 low) and saturating exactly to the `i32` range — the tick's
/// conversion (`floor_shift_saturated` with 24 bits dropped). On the Cortex-M4 that is a
/// range check of the high word and two data instructions, where [`saturate_q54_to_signal`]
/// needs a 64-bit add and two 64-bit compares.
#[inline(always)]
pub fn q54_to_signal_floor(acc: i64) -> i32 {
    floor_shift_saturated::<GAIN_FRAC_BITS>(acc)
}

/// Fractional bits of a product of two Q2.30 signals (Q4.60 in `i64`).
pub const Q60_FRAC_BITS: u32 = 2 * SIGNAL_FRAC_BITS;

/// Converts a Q4.60 accumulator (a sum of signal × signal products) to a Q2.30 signal,
/// rounding toward −∞ and saturating exactly to the `i32` range: as
/// [`q54_to_signal_floor`], with 30 bits dropped instead of 24.
#[inline(always)]
pub fn q60_to_signal_floor(acc: i64) -> i32 {
    floor_shift_saturated::<{ Q60_FRAC_BITS - SIGNAL_FRAC_BITS }>(acc)
}

/// Fractional bits of the packed play-operator bank's sum (Q25.39 in `i64`): Q8.24 weights
/// times Q1.15 operator outputs (see [`crate::models::play_operator`]).
pub const Q39_FRAC_BITS: u32 = GAIN_FRAC_BITS + 15;

/// Converts a Q25.39 accumulator (the packed bank's sum) to a Q2.30 signal, rounding toward
/// −∞ and saturating exactly to the `i32` range: as [`q54_to_signal_floor`], with 9 bits
/// dropped.
#[inline(always)]
pub fn q39_to_signal_floor(acc: i64) -> i32 {
    floor_shift_saturated::<{ Q39_FRAC_BITS - SIGNAL_FRAC_BITS }>(acc)
}

/// `acc >> DROPPED` (rounding toward −∞) saturated to `i32`, for `1 ≤ DROPPED ≤ 31`, on
/// 32-bit words: the result is the high word shifted up by `32 − DROPPED` with the low
/// word's top `DROPPED` bits below it, and it fits iff the high word fits `DROPPED` signed
/// bits.
#[inline(always)]
fn floor_shift_saturated<const DROPPED: u32>(acc: i64) -> i32 {
    const { assert!(DROPPED >= 1 && DROPPED <= 31) };
    let high_max: i32 = (1 << (DROPPED - 1)) - 1;
    let high = (acc >> 32) as i32;
    let low = acc as u32;
    let fitted = high.clamp(-high_max - 1, high_max);
    // Out of range: i32::MAX for a positive accumulator, i32::MIN for a negative one. Chosen
    // by a mask, not a branch: both values are a couple of instructions, and a branch taken
    // on the common path costs the flash's wait states on every call.
    let out = -((fitted != high) as i32); // all ones where out of range
    let saturated = (high >> 31) ^ i32::MAX;
    let shifted = (high << (32 - DROPPED)) | (low >> DROPPED) as i32;
    (shifted & !out) | (saturated & out)
}

/// Saturates an `i64` to the `i32` range.
#[inline(always)]
pub fn saturate_i64(x: i64) -> i32 {
    if x > i32::MAX as i64 {
        i32::MAX
    } else if x < i32::MIN as i64 {
        i32::MIN
    } else {
        x as i32
    }
}

/// Multiplies a Q8.24 gain by a Q2.30 signal into a Q2.30 signal, rounding and saturating.
#[inline(always)]
pub fn gain_times_signal(gain: i32, signal: i32) -> i32 {
    saturate_q54_to_signal(gain as i64 * signal as i64)
}

/// Limits `x` to `[lo, hi]` without a panic path (`Ord::clamp` asserts `lo ≤ hi`; here an
/// inverted range yields `hi`, the configuration validation keeps `lo ≤ hi` anyway).
#[inline(always)]
pub fn limit(x: i32, lo: i32, hi: i32) -> i32 {
    x.max(lo).min(hi)
}

/// [`limit`] for `i64`.
#[inline(always)]
pub fn limit_i64(x: i64, lo: i64, hi: i64) -> i64 {
    x.max(lo).min(hi)
}

/// Largest full-scale signal, `1 − 2^-30` (Q2.30): the top of [`clamp_full_scale`]'s range.
pub const FULL_SCALE_MAX: i32 = SIGNAL_ONE - 1;

/// Clamps a Q2.30 signal to the normalised full-scale range `[-1, 1 − 2^-30]`.
///
/// The range is that of a 31-bit two's-complement number, as in Q1.31 (where +1 is one LSB
/// out of reach too), so the Cortex-M4 does it in one `SSAT #31` instead of two compares and
/// two conditional moves; the top is short of +1 by 2^-30 (1.6e-5 of a 16-bit LSB).
#[inline(always)]
pub fn clamp_full_scale(signal: i32) -> i32 {
    signal.clamp(-SIGNAL_ONE, FULL_SCALE_MAX)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn floor_conversion_is_the_shift_saturated() {
        let cases = [
            0i64,
            1,
            -1,
            (1 << 24) - 1,
            -(1 << 24),
            (SIGNAL_ONE as i64) << 24,
            ((SIGNAL_ONE as i64) << 24) + 12345,
            -((SIGNAL_ONE as i64) << 25),
            ((i32::MAX as i64) << 24) + ((1 << 24) - 1),
            (i32::MAX as i64 + 1) << 24,
            (i32::MIN as i64) << 24,
            ((i32::MIN as i64) << 24) - 1,
            i64::MAX,
            i64::MIN,
        ];
        for acc in cases {
            let expected = saturate_i64(acc >> GAIN_FRAC_BITS);
            assert_eq!(q54_to_signal_floor(acc), expected, "acc = {acc:#x}");
        }
    }

    proptest::proptest! {
        #[test]
        fn floor_conversion_matches_the_i64_shift(acc in proptest::num::i64::ANY, shift in 0u32..40) {
            let acc = acc >> shift; // spread over magnitudes, in and out of range
            proptest::prop_assert_eq!(q54_to_signal_floor(acc), saturate_i64(acc >> GAIN_FRAC_BITS));
        }

        #[test]
        fn q60_floor_conversion_matches_the_i64_shift(acc in proptest::num::i64::ANY, shift in 0u32..40) {
            let acc = acc >> shift;
            proptest::prop_assert_eq!(q60_to_signal_floor(acc), saturate_i64(acc >> SIGNAL_FRAC_BITS));
        }

        #[test]
        fn q39_floor_conversion_matches_the_i64_shift(acc in proptest::num::i64::ANY, shift in 0u32..40) {
            let acc = acc >> shift;
            proptest::prop_assert_eq!(q39_to_signal_floor(acc), saturate_i64(acc >> 9));
        }
    }

    #[test]
    fn q60_floor_conversion_is_the_shift_saturated_at_the_edges() {
        let edge = (i32::MAX as i64) << 30;
        for acc in [
            0,
            -1,
            1 << 30,
            (1 << 30) - 1,
            edge,
            edge + (1 << 30) - 1,
            edge + (1 << 30),
            (i32::MIN as i64) << 30,
            ((i32::MIN as i64) << 30) - 1,
            i64::MAX,
            i64::MIN,
        ] {
            assert_eq!(
                q60_to_signal_floor(acc),
                saturate_i64(acc >> 30),
                "acc = {acc:#x}"
            );
        }
    }

    #[test]
    fn conversions_round_trip_within_half_an_lsb() {
        for &x in &[0.0, 1.0, -1.0, 0.123_456_789, -1.999_999, 1.5] {
            let back = signal_to_f64(signal_from_f64(x));
            assert!((back - x).abs() <= 0.5 / SIGNAL_ONE as f64, "{x} -> {back}");
            let back = gain_to_f64(gain_from_f64(x * 50.0));
            assert!((back - x * 50.0).abs() <= 0.5 / GAIN_ONE as f64);
        }
    }

    #[test]
    fn conversions_saturate_instead_of_wrapping() {
        assert_eq!(signal_from_f64(5.0), i32::MAX);
        assert_eq!(signal_from_f64(-5.0), i32::MIN);
        assert_eq!(gain_from_f64(1e9), i32::MAX);
        assert_eq!(signal_from_f64(f64::NAN), 0);
        assert_eq!(saturate_q54_to_signal(i64::MAX), i32::MAX);
        assert_eq!(saturate_q54_to_signal(i64::MIN), i32::MIN);
    }

    #[test]
    fn gain_times_signal_matches_real_product() {
        let g = gain_from_f64(-12.5);
        let s = signal_from_f64(0.1);
        let p = signal_to_f64(gain_times_signal(g, s));
        assert!((p - (-1.25)).abs() < 1e-8);
        // 100 × 1.5 saturates at the top of Q2.30 rather than wrapping negative.
        assert_eq!(
            gain_times_signal(gain_from_f64(100.0), signal_from_f64(1.5)),
            i32::MAX
        );
    }
}
