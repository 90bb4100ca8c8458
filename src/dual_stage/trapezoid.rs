//! Trapezoidal velocity profile, generated online one coarse tick at a time.
//!
//! Units: position in **picometres** (`i64`: ±9.2e6 m, so no travel wraps and a nanometre is
//! exact), velocity in **picometres per coarse tick**, acceleration in **picometres per coarse
//! tick²** (at 1 kHz, 1 pm/tick = 1 nm/s and 1 pm/tick² = 1 µm/s²). Integers rather than
//! `f32`: a 5 mm move resolved to a nanometre needs 23 bits of position *plus* the fraction
//! the profile accumulates, more than `f32`'s 24-bit mantissa; `i64` is exact and gives the
//! host and the target the same trajectory bit for bit.
//!
//! Each tick the profile picks the fastest velocity from which it can still stop at the target
//! by braking at the acceleration limit, limited by the velocity limit and by the acceleration
//! limit from its present velocity; it never steps past the target. From rest to a fixed
//! target that gives the trapezoid (or triangle, on a short move), ending exactly on the
//! target; a target that moves is followed as closely as the limits allow.

use crate::divisor::Divisor;
use crate::fixed_point::limit_i64;

/// Velocity and acceleration limits of a profile.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MotionLimits {
    /// Largest speed, picometres per coarse tick (≥ 1).
    pub velocity: i64,
    /// Largest acceleration, picometres per coarse tick² (1 ≤ acceleration ≤ velocity).
    pub acceleration: i64,
}

/// Largest speed a profile accepts, pm per tick (1 m/s at 1 kHz); it keeps the braking
/// distance's arithmetic inside `u64`.
pub const MAX_VELOCITY_PM_PER_TICK: i64 = 1_000_000_000;

impl MotionLimits {
    /// Whether the limits are usable: `1 ≤ acceleration ≤ velocity ≤` [`MAX_VELOCITY_PM_PER_TICK`].
    pub fn is_valid(&self) -> bool {
        self.acceleration >= 1
            && self.acceleration <= self.velocity
            && self.velocity <= MAX_VELOCITY_PM_PER_TICK
    }
}

/// Motion limits with their braking arithmetic prepared ([`MotionLimits::prepare`]): what a
/// profile runs on. Preparing costs two 64-bit divisions; a profile given prepared limits
/// ([`TrapezoidalProfile::prepared`], [`TrapezoidalProfile::set_prepared`]) pays nothing on
/// the tick that takes them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PreparedLimits {
    limits: MotionLimits,
    braking: Braking,
}

impl PreparedLimits {
    /// The limits as given.
    pub fn limits(&self) -> MotionLimits {
        self.limits
    }
}

impl MotionLimits {
    /// Prepares the limits for a profile (see [`PreparedLimits`]).
    pub fn prepare(&self) -> PreparedLimits {
        PreparedLimits {
            limits: *self,
            braking: Braking::new(self),
        }
    }
}

/// The limits' braking arithmetic, prepared when the limits are set (off the tick): the
/// acceleration as a [`Divisor`], and the braking distance from full speed. The tick then asks
/// [`PreparedLimits::stopping_speed`] and [`PreparedLimits::braking_after`] with no 64-bit
/// library division.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Braking {
    /// The acceleration limit ([`Braking::limits`]), prepared for division.
    per_acceleration: Divisor,
    /// Distance braking from the speed limit covers, pm.
    from_full_speed: u64,
}

impl Braking {
    fn new(limits: &MotionLimits) -> Self {
        let (velocity, acceleration) = Self::limits(limits);
        Self {
            per_acceleration: Divisor::new(acceleration),
            from_full_speed: braking_distance(velocity, acceleration),
        }
    }

    /// The speed and acceleration limits forced into their valid range (valid limits have
    /// `1 ≤ a ≤ v ≤` [`MAX_VELOCITY_PM_PER_TICK`]), so that no division or product below can
    /// panic or overflow.
    fn limits(limits: &MotionLimits) -> (u64, u64) {
        let velocity = limits.velocity.clamp(1, MAX_VELOCITY_PM_PER_TICK) as u64;
        (velocity, (limits.acceleration.max(1) as u64).min(velocity))
    }
}

impl PreparedLimits {
    /// The fastest speed from which braking at `acceleration` per tick stops within `distance`:
    /// braking from `v` covers `v + (v − a) + … ≈ v²/(2a) + v/2`, so
    /// `v ≈ (√(a² + 8a·d) − a) / 2` (then settled on the exact sum), capped at the velocity limit.
    fn stopping_speed(&self, distance: u64) -> i64 {
        let (v, a) = Braking::limits(&self.limits);
        let braking = &self.braking;
        // Beyond the braking distance from full speed the answer is the limit (and the square
        // root's argument would no longer be bounded).
        if distance >= braking.from_full_speed {
            return v as i64;
        }
        // Exactly: with `u = n·a + r` (0 ≤ r < a) braking covers `(n + 1)(n·a/2 + r)`. The
        // largest whole `n` with `(n + 1)·n·a/2 ≤ d` is the square root's: `(n + 1)·n/2 ≤
        // ⌊d/a⌋ ⇔ 2n + 1 ≤ ⌊√(8⌊d/a⌋ + 1)⌋`, the quotient exact ([`Divisor`]) and the root
        // exact ([`isqrt`]) (`8⌊d/a⌋ < 4·10¹⁸` below the braking distance from full speed:
        // no overflow). Then
        // the largest `r` that still fits, `r = (2d − (n + 1)·n·a) / (2(n + 1))`: `d` short of
        // the braking distance from full speed gives `n ≤ v/a`, so the remainder (less than
        // `2(n + 1)·a ≤ 2(v + a) ≤ 4·10⁹`) and the divisor fit 32 bits: one hardware `UDIV`,
        // never a 64-bit library division (saturated, were they ever larger).
        let n = (isqrt(1 + 8 * braking.per_acceleration.div(distance)) - 1) / 2;
        let remainder = (2 * distance).saturating_sub((n + 1) * n * a);
        let remainder = u32::try_from(remainder).unwrap_or(u32::MAX);
        let per = u32::try_from(2 * (n + 1)).unwrap_or(u32::MAX);
        let r = u64::from(remainder.checked_div(per).unwrap_or(0)).min(a - 1);
        let u = n * a + r;
        (u as i64).min(v as i64)
    }

    /// The distance braking from speed `u` (pm per tick) covers after the tick at `u`:
    /// `(u − a) + (u − 2a) + …` while the terms are positive, `a` the acceleration limit. The
    /// number of terms from the prepared divisor: no 64-bit library division.
    fn braking_after(&self, u: u64) -> u64 {
        let (_, a) = Braking::limits(&self.limits);
        if u <= a {
            // A speed within one tick's braking stops at the next tick.
            return 0;
        }
        braking_sum(u, self.braking.per_acceleration.div(u), a) - u
    }
}

/// Distance covered by `u + (u − a) + (u − 2a) + …` while the terms are positive.
fn braking_distance(u: u64, a: u64) -> u64 {
    braking_sum(u, u.checked_div(a).unwrap_or(0), a)
}

/// `⌊√x⌋`, exact, without a 64-bit division (`u64::isqrt` divides in 64 bits: a library call
/// on the Cortex-M4): `u32::isqrt` (hardware `UDIV`s) of `x`'s top bits at an even shift
/// `2k`, which is the root's top bits (`⌊√⌊x/4^k⌋⌋ = ⌊√x/2^k⌋`), then the root's `k` low
/// bits one by one, each kept if its square stays within `x`: no step below 2^32, at most 16.
fn isqrt(x: u64) -> u64 {
    let k = (64 - x.leading_zeros()).saturating_sub(32).div_ceil(2);
    let mut root = u64::from(((x >> (2 * k)) as u32).isqrt()) << k;
    for bit in (0..k).rev() {
        // Below 2^32: the square fits.
        let tried = root | (1 << bit);
        if tried * tried <= x {
            root = tried;
        }
    }
    root
}

/// `u + (u − a) + … + (u − n·a)`: the braking distance from `u` with `n = ⌊u/a⌋`.
fn braking_sum(u: u64, n: u64, a: u64) -> u64 {
    (n + 1) * u - a * n * (n + 1) / 2
}

/// The profile's state: where it is and how fast it goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TrapezoidalProfile {
    limits: PreparedLimits,
    /// Position, pm.
    position: i64,
    /// Velocity of the last tick, pm per tick.
    velocity: i64,
    /// Target of the last tick, pm.
    last_target: i64,
}

impl TrapezoidalProfile {
    /// At rest at `position` (pm). `limits` must be valid ([`MotionLimits::is_valid`]; the
    /// settings check them).
    pub fn new(position: i64, limits: MotionLimits) -> Self {
        Self::prepared(position, limits.prepare())
    }

    /// At rest at `position` (pm), on limits already prepared.
    pub fn prepared(position: i64, limits: PreparedLimits) -> Self {
        Self {
            limits,
            position,
            velocity: 0,
            last_target: position,
        }
    }

    /// Advances one tick toward a fixed `target` (pm); returns the new position.
    pub fn step(&mut self, target: i64) -> i64 {
        self.last_target = target;
        self.advance(target, 0)
    }

    /// Advances one tick toward a `target` (pm) that moves: its velocity (the change since the
    /// last call, limited to the velocity limit) is fed forward and the profile closes the gap
    /// relative to it, so a target moving at constant speed is followed without lag.
    pub fn follow(&mut self, target: i64) -> i64 {
        let v = self.limits.limits.velocity;
        let target_velocity = limit_i64(target.saturating_sub(self.last_target), -v, v);
        self.last_target = target;
        self.advance(target, target_velocity)
    }

    fn advance(&mut self, target: i64, target_velocity: i64) -> i64 {
        // In the frame moving with the target (`v = target_velocity + w`), the gap left after
        // this tick, if we only kept pace, is `d = target − position − target_velocity`, and it
        // evolves as `d ← d − w`: a profile toward a fixed target at distance `d`.
        let distance = target
            .saturating_sub(self.position)
            .saturating_sub(target_velocity);
        let a = self.limits.limits.acceleration;
        let speed = self
            .limits
            .stopping_speed(distance.unsigned_abs())
            .min(distance.saturating_abs());
        let closing = if distance >= 0 { speed } else { -speed };
        let v = self.limits.limits.velocity;
        let wanted = limit_i64(target_velocity.saturating_add(closing), -v, v);
        self.velocity = limit_i64(wanted, self.velocity - a, self.velocity + a);
        self.position = self.position.saturating_add(self.velocity);
        self.position
    }

    /// Position, pm.
    pub fn position(&self) -> i64 {
        self.position
    }

    /// Velocity of the last tick, pm per tick.
    pub fn velocity(&self) -> i64 {
        self.velocity
    }

    /// The limits.
    pub fn limits(&self) -> MotionLimits {
        self.limits.limits
    }

    /// Changes the limits (a new move's speed and acceleration); the present velocity is kept
    /// and brought within the new limits at the new acceleration, tick by tick.
    pub fn set_limits(&mut self, limits: MotionLimits) {
        self.set_prepared(limits.prepare());
    }

    /// [`TrapezoidalProfile::set_limits`] with limits already prepared.
    pub fn set_prepared(&mut self, limits: PreparedLimits) {
        self.limits = limits;
    }

    /// Where the profile comes to rest if it brakes now at its acceleration limit, pm (the
    /// target of a controlled stop).
    pub fn stopping_point(&self) -> i64 {
        let d = self.limits.braking_after(self.velocity.unsigned_abs());
        let d = d.min(i64::MAX as u64) as i64;
        if self.velocity >= 0 {
            self.position.saturating_add(d)
        } else {
            self.position.saturating_sub(d)
        }
    }

    /// Stops the profile where it is (velocity 0), e.g. when a new move is planned from rest.
    pub fn reset_to(&mut self, position: i64) {
        self.position = position;
        self.velocity = 0;
        self.last_target = position;
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec;
    use std::vec::Vec;

    fn run(limits: MotionLimits, from: i64, to: i64) -> Vec<(i64, i64)> {
        let mut p = TrapezoidalProfile::new(from, limits);
        let mut out = vec![];
        for _ in 0..1_000_000 {
            p.step(to);
            out.push((p.position(), p.velocity()));
            if p.position() == to && p.velocity() == 0 {
                break;
            }
        }
        out
    }

    /// The largest speed `u ≤ v` whose braking (`u + (u − a) + …`) stays within `d`, by
    /// bisection on the sum itself.
    fn stopping_speed_by_search(v: u64, a: u64, d: u64) -> u64 {
        let (mut lo, mut hi) = (0u64, v);
        while lo < hi {
            let mid = lo + (hi - lo).div_ceil(2);
            if braking_distance(mid, a) <= d {
                lo = mid;
            } else {
                hi = mid - 1;
            }
        }
        lo
    }

    #[test]
    fn the_stopping_speed_is_the_largest_that_brakes_within_the_distance() {
        let mut next = crate::divisor::tests::xorshift(0x51a7_e5c0_ffee_1234);
        let mut cases = std::vec![
            (MAX_VELOCITY_PM_PER_TICK as u64, 1),
            (
                MAX_VELOCITY_PM_PER_TICK as u64,
                MAX_VELOCITY_PM_PER_TICK as u64
            ),
            (MAX_VELOCITY_PM_PER_TICK as u64, 3),
            (1, 1),
            (2_000_000, 4_000),
        ];
        for _ in 0..2_000 {
            let v = next() % MAX_VELOCITY_PM_PER_TICK as u64 + 1;
            let a = next() % v + 1;
            cases.push((v, a));
            // Small accelerations: many braking steps.
            cases.push((v, a % 1_000 + 1));
        }
        for (v, a) in cases {
            let limits = MotionLimits {
                velocity: v as i64,
                acceleration: a as i64,
            };
            let prepared = limits.prepare();
            let full = braking_distance(v, a);
            let stopping_speed = |d| prepared.stopping_speed(d);
            let mut distances = std::vec![0, 1, a - 1, a, a + 1, full - 1, full, full + 1];
            for _ in 0..20 {
                distances.push(next() % full);
            }
            for d in distances {
                assert_eq!(
                    stopping_speed(d) as u64,
                    stopping_speed_by_search(v, a, d),
                    "v {v}, a {a}, d {d}"
                );
            }
        }
    }

    /// The root without a 64-bit division is `u64::isqrt`'s: at every power of two and on
    /// both sides of squares up to `u64::MAX`, and at random.
    #[test]
    fn the_integer_square_root_is_exact() {
        let mut next = crate::divisor::tests::xorshift(0x5eed_0f20_0700_1234);
        let mut xs = std::vec![0u64, 1, 2, 3, 4, u64::MAX, u64::MAX - 1];
        for b in 0..64 {
            let p = 1u64 << b;
            xs.extend([p - 1, p, p + 1]);
        }
        for r in [
            1u64,
            2,
            3,
            65_535,
            65_536,
            65_537,
            1 << 20,
            3_037_000_499,
            u32::MAX as u64,
        ] {
            let sq = r * r;
            xs.extend([sq - 1, sq, sq + 1]);
        }
        for _ in 0..100_000 {
            let x = next();
            xs.extend([x, x >> (x % 64)]);
        }
        for x in xs {
            assert_eq!(isqrt(x), x.isqrt(), "{x}");
        }
    }

    /// The distance a stop covers after the tick at speed `u`, from the prepared divisor, is
    /// the braking sum `(u − a) + (u − 2a) + …` summed term by term: at the speeds that end
    /// the sum's terms, on both sides of each multiple of `a`, and at random speeds up to
    /// beyond the limit (a move whose limits were lowered while it ran).
    #[test]
    fn a_stop_s_braking_distance_is_the_sum_of_its_braking_ticks() {
        let mut next = crate::divisor::tests::xorshift(0x0b5e_55ed_57a1_1e55);
        let term_by_term = |u: u64, a: u64| {
            let (mut sum, mut speed) = (0u64, u);
            while speed > a {
                speed -= a;
                sum += speed;
            }
            sum
        };
        let mut cases = std::vec![(1u64, 1u64), (1_000, 1), (2_000_000, 4_000), (7, 7)];
        for _ in 0..300 {
            let v = next() % 200_000 + 1;
            cases.push((v, next() % v + 1));
        }
        for (v, a) in cases {
            let limits = MotionLimits {
                velocity: v as i64,
                acceleration: a as i64,
            }
            .prepare();
            let mut speeds = std::vec![0, 1, a - 1, a, a + 1, 2 * a, 2 * a + 1, v - 1, v, 2 * v];
            for _ in 0..10 {
                speeds.push(next() % (2 * v));
            }
            for u in speeds {
                assert_eq!(
                    limits.braking_after(u),
                    term_by_term(u, a),
                    "v {v}, a {a}, u {u}"
                );
            }
        }
        // At the speed limit the product form is exact where summing is too slow to check.
        let limits = MotionLimits {
            velocity: MAX_VELOCITY_PM_PER_TICK,
            acceleration: 3,
        };
        let u = MAX_VELOCITY_PM_PER_TICK as u64;
        let n = u / 3;
        assert_eq!(
            limits.prepare().braking_after(u),
            n * u - 3 * n * (n + 1) / 2
        );
    }

    #[test]
    fn move_from_rest_is_a_trapezoid_that_ends_exactly_on_target() {
        let limits = MotionLimits {
            velocity: 10_000_000,
            acceleration: 200_000,
        };
        for (from, to) in [(0, 5_000_000_000), (3, -123_456_789), (0, 7), (0, 150_000)] {
            let path = run(limits, from, to);
            let (mut prev_v, mut prev_x) = (0i64, from);
            let mut peak = 0i64;
            for &(x, v) in &path {
                assert!(v.abs() <= limits.velocity);
                assert!((v - prev_v).abs() <= limits.acceleration);
                // Monotone, never past the target.
                assert!((x - prev_x) * (to - from).signum() >= 0);
                assert!((x - from).abs() <= (to - from).abs());
                prev_v = v;
                prev_x = x;
                peak = peak.max(v.abs());
            }
            assert_eq!(*path.last().unwrap(), (to, 0));
            if (to - from).abs() > 1_000_000_000 {
                assert_eq!(peak, limits.velocity, "a long move cruises at the limit");
            }
        }
    }

    #[test]
    fn long_move_takes_the_time_optimal_duration_within_a_few_ticks() {
        let limits = MotionLimits {
            velocity: 10_000_000,
            acceleration: 100_000,
        };
        let d = 5_000_000_000i64;
        let ideal = d as f64 / limits.velocity as f64 + limits.velocity as f64 / 100_000.0;
        let ticks = run(limits, 0, d).len() as f64;
        assert!((ticks - ideal).abs() < 3.0, "{ticks} ticks vs {ideal}");
    }

    #[test]
    fn a_target_moving_at_constant_speed_is_followed_without_lag() {
        let limits = MotionLimits {
            velocity: 15_000,
            acceleration: 400,
        };
        let mut p = TrapezoidalProfile::new(0, limits);
        let mut prev = 0;
        for k in 1..=2000i64 {
            p.follow(10_000 * k);
            assert!((p.velocity() - prev).abs() <= 400 && p.velocity().abs() <= 15_000);
            prev = p.velocity();
        }
        assert_eq!(p.position(), 10_000 * 2000);
    }

    #[test]
    fn braking_toward_the_stopping_point_never_reverses() {
        let limits = MotionLimits {
            velocity: 10_000,
            acceleration: 300,
        };
        let mut p = TrapezoidalProfile::new(0, limits);
        for _ in 0..100 {
            p.step(1_000_000_000);
        }
        assert_eq!(p.velocity(), 10_000);
        let stop = p.stopping_point();
        assert!(stop > p.position());
        let mut prev = p.velocity();
        let mut ticks = 0;
        while p.velocity() != 0 {
            p.step(stop);
            assert!(p.velocity() >= 0 && prev - p.velocity() <= 300, "{p:?}");
            prev = p.velocity();
            ticks += 1;
        }
        assert_eq!(p.position(), stop);
        // About v / a ticks: braking at the limit, not crawling.
        assert!(ticks <= 10_000 / 300 + 3, "{ticks}");
    }

    #[test]
    fn a_target_reversed_mid_move_is_reached_within_the_limits() {
        let limits = MotionLimits {
            velocity: 1000,
            acceleration: 10,
        };
        let mut p = TrapezoidalProfile::new(0, limits);
        for _ in 0..200 {
            p.step(1_000_000);
        }
        let mut prev = p.velocity();
        for _ in 0..10_000 {
            p.step(-500);
            assert!((p.velocity() - prev).abs() <= 10 && p.velocity().abs() <= 1000);
            prev = p.velocity();
        }
        assert_eq!((p.position(), p.velocity()), (-500, 0));
    }
}
