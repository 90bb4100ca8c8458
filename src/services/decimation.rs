//! One tick in every `n`: the countdown by which the recorder takes its frames and
//! telemetry's tap its samples, and by which the services pass the ticks between them over
//! at once ([`crate::services::consumer`]).

/// A countdown over the ticks: due on the first tick after [`Decimation::restart`], then on
/// one tick in every [`Decimation::ticks`]. O(1) in every operation, no panic path. The
/// default is every tick.
///
/// ```
/// use twinstack::services::decimation::Decimation;
/// let mut every_third = Decimation::every(3);
/// let due: Vec<bool> = (0..7).map(|_| every_third.due()).collect();
/// assert_eq!(due, [true, false, false, true, false, false, true]);
/// ```
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Decimation {
    /// `ticks − 1`: the countdown after a due tick.
    reload: u16,
    /// Ticks until the next due one (0: this one).
    countdown: u16,
}

impl Decimation {
    /// Due on the next tick, then every `ticks` ticks (0 counts as 1: every tick).
    pub const fn every(ticks: u16) -> Self {
        Self {
            reload: ticks.saturating_sub(1),
            countdown: 0,
        }
    }

    /// One due tick in every this many.
    pub const fn ticks(&self) -> u16 {
        // reload ≤ u16::MAX − 1: `every` takes one off a u16.
        self.reload + 1
    }

    /// The next tick is due (the countdown starts again from it).
    #[inline(always)]
    pub fn restart(&mut self) {
        self.countdown = 0;
    }

    /// One tick: whether it is due (the countdown at zero, which it reloads).
    #[inline(always)]
    pub fn due(&mut self) -> bool {
        if self.countdown > 0 {
            self.countdown -= 1;
            return false;
        }
        self.countdown = self.reload;
        true
    }

    /// Ticks before the next due one, each of which [`Decimation::due`] would only count down.
    #[inline(always)]
    pub fn quiet_ticks(&self) -> u32 {
        u32::from(self.countdown)
    }

    /// Counts `ticks` ticks down at once, as that many [`Decimation::due`] calls returning
    /// `false` would: `ticks` is at most [`Decimation::quiet_ticks`] (more stops at the due
    /// tick, which `due` then takes).
    #[inline(always)]
    pub fn pass(&mut self, ticks: u32) {
        self.countdown = u32::from(self.countdown).saturating_sub(ticks) as u16;
    }

    /// Counts `ticks` ticks at once, due ones included, as that many [`Decimation::due`]
    /// calls would; returns how many of them were due. Off the tick (one division).
    #[cold]
    pub fn skip(&mut self, ticks: u32) -> u32 {
        let countdown = u32::from(self.countdown);
        if ticks <= countdown {
            self.countdown = (countdown - ticks) as u16;
            return 0;
        }
        // The first due tick is the countdown's end; then one every period.
        let period = u32::from(self.reload) + 1;
        let after = ticks - countdown - 1;
        self.countdown = (u32::from(self.reload) - after % period) as u16;
        1 + after / period
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Passing the quiet ticks and skipping any number at once count as the same calls
        /// to `due` one by one would.
        #[test]
        fn passing_and_skipping_are_due_one_by_one(
            every in 0u16..20,
            warm in 0u32..40,
            ticks in 0u32..200,
        ) {
            let mut one_by_one = Decimation::every(every);
            for _ in 0..warm {
                one_by_one.due();
            }
            let (mut passed, mut skipped) = (one_by_one, one_by_one);
            let quiet = passed.quiet_ticks();
            let due = (0..ticks).filter(|_| one_by_one.due()).count() as u32;
            prop_assert_eq!(skipped.skip(ticks), due);
            prop_assert_eq!(skipped, one_by_one);
            if ticks <= quiet {
                prop_assert_eq!(due, 0);
                passed.pass(ticks);
                prop_assert_eq!(passed, one_by_one);
            }
        }
    }

    #[test]
    fn every_tick_and_the_longest() {
        let mut each = Decimation::every(0);
        assert_eq!(each.ticks(), 1);
        assert!((0..5).all(|_| each.due()));
        let mut longest = Decimation::every(u16::MAX);
        assert_eq!(longest.ticks(), u16::MAX);
        assert!(longest.due());
        assert_eq!(longest.quiet_ticks(), u32::from(u16::MAX) - 1);
        longest.restart();
        assert!(longest.due());
    }
}
