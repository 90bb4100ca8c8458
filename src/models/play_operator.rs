//! The play (backlash) operator, in fixed point.
//!
//! `p_k = max(u_k − r, min(u_k + r, p_{k−1}))` (see the book, docs/src/reference/models.md): the output follows the input with
//! a dead band of half-width `r`. It is rate independent (only the order of input values
//! matters, not their timing) and wipes out inner minor loops, which is what makes
//! Prandtl–Ishlinskii models invertible in closed form.
//!
//! ## Two operators per word
//!
//! The tick runs its P–I banks two operators at a time: states and thresholds are Q1.15
//! halfwords packed in a `u32` (operator `2k` in the low half, `2k + 1` in the high half), the
//! states in offset binary (`v + 2^15`: the unsigned saturation of `UQADD16`/`UQSUB16` then
//! stops exactly at the signal range's ends, and one lane holds any threshold up to
//! `2 − 2^-15`). One pair's update is six dual-16-bit instructions ([`play2`]: `UQADD16`,
//! `UQSUB16`, and `USUB16` + `SEL` twice for the per-lane min and max), its weighted sum one
//! `SMLALD` per 16-bit half of the weights (see
//! [`crate::models::prandtl_ishlinskii::PlayOperatorBank`]).
//! On the target each primitive below is that instruction (`core::arch::asm!`; the compiler
//! does not emit them from portable code); on the host the same function is plain Rust
//! written from the instruction's definition in the Armv7-M Architecture Reference Manual
//! (A7.7: per-lane saturation to `[0, 2^16 − 1]`, `GE` flags from the exact 17-bit
//! difference, 64-bit wrapping accumulate), so host and board compute the same bits — the
//! golden vectors replay them in QEMU.

/// One play operator: its threshold and its state, both Q2.30 normalised signals.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct PlayOperator {
    /// Threshold `r` (half-width of the dead band), Q2.30, `0 ≤ r ≤ 1`.
    pub threshold: i32,
    /// Output state `p`, Q2.30.
    pub state: i32,
}

impl PlayOperator {
    /// A play operator with threshold `threshold` (Q2.30) whose state starts at `state` (Q2.30).
    pub const fn new(threshold: i32, state: i32) -> Self {
        Self { threshold, state }
    }

    /// Advances the operator by one input sample `u` (Q2.30) and returns its new output.
    #[inline(always)]
    pub fn step(&mut self, u: i32) -> i32 {
        self.state = play(u, self.threshold, self.state);
        self.state
    }
}

/// The play operator's update as a pure function on Q2.30 signals:
/// `max(u − r, min(u + r, p))`. The additions saturate, so an input at the range end cannot
/// wrap around (on the Cortex-M4 they compile to `QADD`/`QSUB`).
#[inline(always)]
pub fn play(u: i32, r: i32, p: i32) -> i32 {
    let upper = u.saturating_add(r);
    let lower = u.saturating_sub(r);
    let held = if p < upper { p } else { upper };
    if held > lower {
        held
    } else {
        lower
    }
}

/// The two signed 16-bit lanes of a packed word: (low, high).
#[inline(always)]
pub fn lanes(w: u32) -> (i32, i32) {
    (w as u16 as i16 as i32, (w >> 16) as u16 as i16 as i32)
}

/// A packed word from two signed 16-bit lanes (each truncated to 16 bits).
#[inline(always)]
pub const fn pack(low: i32, high: i32) -> u32 {
    (low as u16 as u32) | ((high as u16 as u32) << 16)
}

/// Saturates to an unsigned 16-bit lane.
#[cfg(any(test, not(target_arch = "arm")))]
#[inline(always)]
fn usat16(x: i32) -> u32 {
    x.clamp(0, u16::MAX as i32) as u32
}

/// The two unsigned 16-bit lanes of a packed word: (low, high).
#[cfg(any(test, not(target_arch = "arm")))]
#[inline(always)]
fn ulanes(w: u32) -> (i32, i32) {
    ((w & 0xffff) as i32, (w >> 16) as i32)
}

/// `UQADD16`: per-lane unsigned saturating addition.
#[inline(always)]
#[cfg_attr(target_arch = "arm", allow(unsafe_code))] // one instruction, registers only
pub fn uqadd16(a: u32, b: u32) -> u32 {
    #[cfg(target_arch = "arm")]
    {
        let d: u32;
        // SAFETY: a register-only DSP instruction; touches no memory and no flags.
        unsafe {
            core::arch::asm!("uqadd16 {d}, {a}, {b}", d = lateout(reg) d, a = in(reg) a, b = in(reg) b,
                options(pure, nomem, nostack, preserves_flags));
        }
        d
    }
    #[cfg(not(target_arch = "arm"))]
    {
        let ((al, ah), (bl, bh)) = (ulanes(a), ulanes(b));
        usat16(al + bl) | usat16(ah + bh) << 16
    }
}

/// `UQSUB16`: per-lane unsigned saturating subtraction `a − b`.
#[inline(always)]
#[cfg_attr(target_arch = "arm", allow(unsafe_code))] // one instruction, registers only
pub fn uqsub16(a: u32, b: u32) -> u32 {
    #[cfg(target_arch = "arm")]
    {
        let d: u32;
        // SAFETY: as `uqadd16`.
        unsafe {
            core::arch::asm!("uqsub16 {d}, {a}, {b}", d = lateout(reg) d, a = in(reg) a, b = in(reg) b,
                options(pure, nomem, nostack, preserves_flags));
        }
        d
    }
    #[cfg(not(target_arch = "arm"))]
    {
        let ((al, ah), (bl, bh)) = (ulanes(a), ulanes(b));
        usat16(al - bl) | usat16(ah - bh) << 16
    }
}

/// Per-lane unsigned minimum: `USUB16` (sets `GE` per lane where `a ≥ b`, unsigned) then
/// `SEL` (`b` where `GE`, else `a`).
#[inline(always)]
#[cfg_attr(target_arch = "arm", allow(unsafe_code))] // two instructions, registers only
pub fn umin16(a: u32, b: u32) -> u32 {
    #[cfg(target_arch = "arm")]
    {
        let d: u32;
        // SAFETY: register-only; `USUB16` writes the APSR's GE bits, which `SEL` reads in the
        // same block (the flags are declared clobbered).
        unsafe {
            core::arch::asm!("usub16 {d}, {a}, {b}", "sel {d}, {b}, {a}", d = out(reg) d, a = in(reg) a, b = in(reg) b,
                options(pure, nomem, nostack));
        }
        d
    }
    #[cfg(not(target_arch = "arm"))]
    {
        let ((al, ah), (bl, bh)) = (ulanes(a), ulanes(b));
        (al.min(bl) as u32) | (ah.min(bh) as u32) << 16
    }
}

/// Per-lane unsigned maximum: `USUB16` then `SEL` (`a` where `a ≥ b`, else `b`).
#[inline(always)]
#[cfg_attr(target_arch = "arm", allow(unsafe_code))] // two instructions, registers only
pub fn umax16(a: u32, b: u32) -> u32 {
    #[cfg(target_arch = "arm")]
    {
        let d: u32;
        // SAFETY: as `umin16`.
        unsafe {
            core::arch::asm!("usub16 {d}, {a}, {b}", "sel {d}, {a}, {b}", d = out(reg) d, a = in(reg) a, b = in(reg) b,
                options(pure, nomem, nostack));
        }
        d
    }
    #[cfg(not(target_arch = "arm"))]
    {
        let ((al, ah), (bl, bh)) = (ulanes(a), ulanes(b));
        (al.max(bl) as u32) | (ah.max(bh) as u32) << 16
    }
}

/// `SMLALD`: `acc + a.low · b.low + a.high · b.high` (signed 16 × 16 products, 64-bit
/// accumulate, wrapping).
#[inline(always)]
#[cfg_attr(target_arch = "arm", allow(unsafe_code))] // one instruction, registers only
pub fn smlald(acc: i64, a: u32, b: u32) -> i64 {
    #[cfg(target_arch = "arm")]
    {
        let (mut lo, mut hi) = (acc as u32, (acc >> 32) as u32);
        // SAFETY: register-only; SMLALD changes no flags.
        unsafe {
            core::arch::asm!("smlald {lo}, {hi}, {a}, {b}", lo = inout(reg) lo, hi = inout(reg) hi,
                a = in(reg) a, b = in(reg) b, options(pure, nomem, nostack, preserves_flags));
        }
        ((hi as u64) << 32 | lo as u64) as i64
    }
    #[cfg(not(target_arch = "arm"))]
    {
        let ((al, ah), (bl, bh)) = (lanes(a), lanes(b));
        acc.wrapping_add(al as i64 * bl as i64 + ah as i64 * bh as i64)
    }
}

/// The sign bit of both lanes: `v ^ OFFSET_BINARY` turns signed Q1.15 lanes into offset
/// binary (`v + 2^15`, unsigned) and back.
pub const OFFSET_BINARY: u32 = 0x8000_8000;

/// Two play operators at once, on offset-binary Q1.15 lanes (`v + 2^15`, so `[−1, 1)` is
/// `[0, 2^16)`): `max(x − r, min(x + r, p))` per lane, with `x ± r` saturated to the lane by
/// `UQADD16`/`UQSUB16` — a lane saturates exactly at the signal range's ends, so every
/// threshold up to `2 − 2^-15` (`0xffff`) is one lane — and the min and max by `USUB16` +
/// `SEL`. `xx` holds the input in both lanes, `band` the thresholds, `p` the states.
#[inline(always)]
pub fn play2(xx: u32, band: u32, p: u32) -> u32 {
    umax16(umin16(p, uqadd16(xx, band)), uqsub16(xx, band))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed_point::{signal_from_f64 as q, SIGNAL_ONE};
    extern crate std;

    /// The packed primitives are the instructions' definitions: checked lane by lane
    /// against `i32` arithmetic, at the lanes' ends and on random words.
    #[test]
    fn packed_primitives_follow_the_instruction_definitions() {
        let edges = [
            i16::MIN as i32,
            -32767,
            -1,
            0,
            1,
            32766,
            i16::MAX as i32,
            1234,
            -20000,
        ];
        let mut words = std::vec::Vec::new();
        for &a in &edges {
            for &b in &edges {
                words.push(pack(a, b));
            }
        }
        let mut seed = 0x1234_5678u32;
        for _ in 0..2000 {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            words.push(seed);
        }
        for (k, &a) in words.iter().enumerate() {
            let b = words[(k * 7 + 3) % words.len()];
            let ((al, ah), (bl, bh)) = (ulanes(a), ulanes(b));
            let u = |l: u32, h: u32| l | h << 16;
            assert_eq!(uqadd16(a, b), u(usat16(al + bl), usat16(ah + bh)));
            assert_eq!(uqsub16(a, b), u(usat16(al - bl), usat16(ah - bh)));
            assert_eq!(umin16(a, b), u(al.min(bl) as u32, ah.min(bh) as u32));
            assert_eq!(umax16(a, b), u(al.max(bl) as u32, ah.max(bh) as u32));
            let ((sl, sh), (tl, th)) = (lanes(a), lanes(b));
            let acc = (k as i64 - 1000) << 40;
            assert_eq!(smlald(acc, a, b), acc + (sl * tl) as i64 + (sh * th) as i64);
        }
    }

    /// The pair update is the play operator on each lane (signed values, saturated to the
    /// lane), for every threshold a lane holds.
    #[test]
    fn two_operators_per_word_are_two_play_operators() {
        let mut seed = 99u32;
        let mut next = || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (seed >> 16) as i32 - 32768
        };
        let sat = |v: i32| v.clamp(i16::MIN as i32, i16::MAX as i32);
        for _ in 0..20_000 {
            let (x, p0, p1) = (next(), next(), next());
            let (r0, r1) = (next() + 32768, (next() + 32768) / 2);
            let got = play2(
                pack(x, x) ^ OFFSET_BINARY,
                r0 as u32 | (r1 as u32) << 16,
                pack(p0, p1) ^ OFFSET_BINARY,
            );
            let one = |r: i32, p: i32| sat(x - r).max(sat(x + r).min(p));
            assert_eq!(
                lanes(got ^ OFFSET_BINARY),
                (one(r0, p0), one(r1, p1)),
                "x {x} r {r0} {r1} p {p0} {p1}"
            );
        }
    }

    #[test]
    fn output_holds_inside_the_dead_band_and_follows_outside() {
        let mut op = PlayOperator::new(q(0.25), 0);
        assert_eq!(op.step(q(0.2)), 0, "inside the band the output holds");
        assert_eq!(op.step(q(0.75)), q(0.5), "pushed up by the upper edge");
        assert_eq!(op.step(q(0.6)), q(0.5), "reversal: held again");
        assert_eq!(op.step(q(0.0)), q(0.25), "dragged down by the lower edge");
    }

    #[test]
    fn zero_threshold_is_the_identity() {
        let mut op = PlayOperator::new(0, 123);
        for u in [-SIGNAL_ONE, -7, 0, 99, SIGNAL_ONE] {
            assert_eq!(op.step(u), u);
        }
    }

    #[test]
    fn extreme_inputs_saturate_rather_than_wrap() {
        assert_eq!(play(i32::MAX, SIGNAL_ONE, i32::MAX), i32::MAX);
        assert_eq!(play(i32::MIN, SIGNAL_ONE, i32::MIN), i32::MIN);
        assert_eq!(play(i32::MAX, SIGNAL_ONE, 0), i32::MAX - SIGNAL_ONE);
    }
}
