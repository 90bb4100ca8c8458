//! The play (backlash) operator, in fixed point.
//!
//! `p_k = max(u_k − r, min(u_k + r, p_{k−1}))` (see the book, docs/src/reference/models.md): the output follows the input with
//! a dead band of half-width `r`. It is rate independent (only the order of input values
//! matters, not their timing) and wipes out inner minor loops, which is what makes
//! Prandtl–Ishlinskii models invertible in closed form.

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed_point::{signal_from_f64 as q, SIGNAL_ONE};

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
