//! [`Divisor`]: division by a divisor fixed at configuration, as a multiplication.
//!
//! A Cortex-M4 divides 32-bit integers in hardware (`UDIV`, 2–12 cycles), but a 64-bit
//! quotient is a library call (`__aeabi_ldivmod`, `__aeabi_uldivmod`): 100–300 instructions,
//! with a branch for each bit group. The coarse axis works in picometres, in `i64`, and divides
//! by settings — the microstep, the piezo's half-span, the hand-over's length, the
//! acceleration — on every coarse tick. Those divisors change only when the settings do, so
//! the division is prepared there: [`Divisor::new`] takes the reciprocal once (off the tick),
//! and each quotient is then one 64 × 64 → 128-bit high product, an add, and two shifts — a few
//! dozen instructions, no branch, no call.
//!
//! The quotient is **exact** — the same as `/` for every dividend — not an approximation:
//! with `l = ⌈log₂ d⌉` and the magic number `m = ⌊2⁶⁴·(2ˡ − d)/d⌋ + 1`, `t = ⌊m·n / 2⁶⁴⌋`
//! and `⌊n/d⌋ = (t + ((n − t) >> 1)) >> (l − 1)` for every `n < 2⁶⁴` (Granlund and
//! Montgomery, "Division by invariant integers using multiplication", PLDI 1994, figure 4.1;
//! `l = 0`, `d = 1`, takes no shift). The tests check it against `/` at the edges of every
//! power of two and on random pairs.
//!
//! ```
//! use twinstack::divisor::Divisor;
//! let step = Divisor::new(312_500);
//! assert_eq!(step.div(1_000_000_000), 1_000_000_000 / 312_500);
//! // Signed: rounding down (`div_euclid`, a positive divisor) or toward zero (`/`).
//! assert_eq!(step.floor(-1), -1);
//! assert_eq!(step.trunc(-1), 0);
//! // A divisor of 0 divides everything to 0 (a setting's fallback, never a panic).
//! assert_eq!(Divisor::new(0).div(7), 0);
//! ```

/// An unsigned 64-bit divisor prepared for division by multiplication (see the module doc).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Divisor {
    /// `m = ⌊2⁶⁴·(2ˡ − d)/d⌋ + 1` (the low 64 bits: `m < 2⁶⁴` for `d ≥ 1`).
    magic: u64,
    /// `min(l, 1)`.
    first_shift: u8,
    /// `max(l − 1, 0)`.
    second_shift: u8,
    /// A divisor of 0: every quotient is 0.
    zero: bool,
}

impl Divisor {
    /// Divides by 1.
    pub const ONE: Divisor = Divisor {
        magic: 1,
        first_shift: 0,
        second_shift: 0,
        zero: false,
    };

    /// Prepares division by `d`: for `d ≤ 2³²`, two 64-bit divisions (a few hundred
    /// instructions: what the coarse task pays once when a command brings new limits); beyond,
    /// one 128-bit division (configuration only). A divisor of 0 gives quotients of 0, the
    /// fallback of `checked_div(..).unwrap_or(0)`.
    pub fn new(d: u64) -> Divisor {
        if d == 0 {
            return Divisor {
                zero: true,
                ..Divisor::ONE
            };
        }
        // l = ⌈log₂ d⌉ (0 for d = 1, 64 for d > 2⁶³).
        let l = 64 - (d - 1).leading_zeros();
        // ⌊2⁶⁴·x/d⌋ with x = 2ˡ − d < d.
        let magic = if d <= 1 << 32 {
            // Two steps of long division by 32-bit digits (two 64-bit library divisions,
            // which the coarse task can afford once a command): x < d ≤ 2³² keeps every
            // partial dividend in 64 bits and each quotient digit in 32.
            let x = (1u64 << l) - d;
            let high = (x << 32).checked_div(d).unwrap_or(0);
            let rest = (x << 32).checked_rem(d).unwrap_or(0);
            let low = (rest << 32).checked_div(d).unwrap_or(0);
            (high << 32) | low
        } else {
            // Wider divisors (no setting is one): the 128-bit division.
            (((1u128 << l) - d as u128) << 64)
                .checked_div(d as u128)
                .unwrap_or(0) as u64
        };
        Divisor {
            magic: magic.wrapping_add(1),
            first_shift: l.min(1) as u8,
            second_shift: l.saturating_sub(1) as u8,
            zero: false,
        }
    }

    /// `⌊n / d⌋`, exact for every `n`.
    #[inline(always)]
    pub fn div(&self, n: u64) -> u64 {
        let t = mul_high(self.magic, n);
        let q = (((n - t) >> self.first_shift) + t) >> self.second_shift;
        if self.zero {
            0
        } else {
            q
        }
    }

    /// `⌊n / d⌋` rounded down (`n.div_euclid(d)` for the positive divisor `d`).
    #[inline(always)]
    pub fn floor(&self, n: i64) -> i64 {
        // For n < 0, ⌊n/d⌋ = −⌊(−n − 1)/d⌋ − 1 = !⌊!n/d⌋.
        let sign = n >> 63;
        let q = (self.div((n ^ sign) as u64) as i64) ^ sign;
        if self.zero {
            0
        } else {
            q
        }
    }

    /// `n / d` rounded toward zero (Rust's `/` for the positive divisor `d`; `i64::MIN / 1`
    /// is `i64::MIN`).
    #[inline(always)]
    pub fn trunc(&self, n: i64) -> i64 {
        let q = self.div(n.unsigned_abs()) as i64;
        if n < 0 {
            q.wrapping_neg()
        } else {
            q
        }
    }
}

/// `⌊a·b / 2⁶⁴⌋`: four 32 × 32 → 64-bit products (`UMULL`), no library call.
#[inline(always)]
fn mul_high(a: u64, b: u64) -> u64 {
    let (a0, a1) = (a & 0xffff_ffff, a >> 32);
    let (b0, b1) = (b & 0xffff_ffff, b >> 32);
    let low = a0 * b0;
    let cross_a = a1 * b0;
    let cross_b = a0 * b1;
    let middle = (low >> 32) + (cross_a & 0xffff_ffff) + (cross_b & 0xffff_ffff);
    a1 * b1 + (cross_a >> 32) + (cross_b >> 32) + (middle >> 32)
}

#[cfg(test)]
pub(crate) mod tests {
    extern crate std;
    use super::*;

    /// xorshift64 from `seed`: deterministic pseudo-random words for the tests' sweeps.
    pub(crate) fn xorshift(mut x: u64) -> impl FnMut() -> u64 {
        move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        }
    }

    fn check(d: u64, n: u64) {
        let q = Divisor::new(d).div(n);
        let want = n.checked_div(d).unwrap_or(0);
        assert_eq!(q, want, "{n} / {d}");
    }

    fn check_signed(d: i64, n: i64) {
        let p = Divisor::new(d as u64);
        assert_eq!(p.floor(n), n.div_euclid(d), "{n} div_euclid {d}");
        assert_eq!(p.trunc(n), n.wrapping_div(d), "{n} / {d}");
    }

    /// Values at and beside every power of two, and the extremes.
    fn edges() -> std::vec::Vec<u64> {
        let mut v = std::vec![0, 1, 2, 3, u64::MAX, u64::MAX - 1];
        for k in 1..64 {
            let p = 1u64 << k;
            v.extend([p - 1, p, p + 1]);
        }
        v
    }

    #[test]
    fn the_quotient_is_exact_at_every_power_of_two_s_edges() {
        for &d in &edges() {
            for &n in &edges() {
                check(d, n);
            }
        }
    }

    #[test]
    fn the_quotient_is_exact_on_random_pairs_of_every_size() {
        // Every bit length of both.
        let mut next = xorshift(0x9e37_79b9_7f4a_7c15);
        for _ in 0..200_000 {
            let (a, b) = (next(), next());
            let (n, d) = (a >> (b % 64), b >> (a % 64));
            check(d, n);
            check(d.max(1), n / d.max(1) * d.max(1)); // exact multiples
            check(d.max(1), (n / d.max(1) * d.max(1)).wrapping_sub(1)); // one below
        }
    }

    #[test]
    fn signed_quotients_round_down_or_toward_zero_as_rust_s() {
        let mut next = xorshift(0x2545_f491_4f6c_dd1d);
        for d in [1i64, 2, 3, 7, 312_500, 5_000, 1 << 40, i64::MAX] {
            for n in [
                0,
                1,
                -1,
                d,
                -d,
                d - 1,
                1 - d,
                -d - 1,
                i64::MAX,
                i64::MIN,
                i64::MIN + 1,
            ] {
                check_signed(d, n);
            }
        }
        for _ in 0..100_000 {
            let (a, b) = (next(), next());
            let n = (a as i64) >> (b % 64);
            let d = ((b >> (a % 63)) as i64).max(1);
            check_signed(d, n);
        }
    }

    #[test]
    fn a_divisor_of_zero_gives_zero() {
        for n in [0, 1, u64::MAX] {
            assert_eq!(Divisor::new(0).div(n), 0);
        }
        assert_eq!(Divisor::new(0).floor(-5), 0);
        assert_eq!(Divisor::new(0).trunc(-5), 0);
    }
}
