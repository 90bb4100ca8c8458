//! Bumpless mode switching and reloads: bypass ↔ open loop (compensated) ↔ closed loop, and
//! one configuration to another, between two ticks, without a jump in the drive.
//!
//! A switch changes what the tick computes — the feedforward becomes the setpoint or the
//! inverse model's output, a correction appears or vanishes, a reload brings other models and
//! ranges — so the first command after it would differ from the drive the stacks hold.
//! [`crate::control::Controller::set_mode`] and [`crate::control::Controller::take_over`]
//! (both O(1), under the command handler's lock) note the drive the stacks hold; the first tick
//! after hands the difference between its command and that drive to a [`BumplessTransfer`]:
//! an offset added to the command that fades out over about 2^[`TRANSFER_SHIFT`] ticks (5 ms at
//! 50 kHz), so the drive glides from where it was to the new mode's command. Entering closed
//! loop also restarts the feedback's history at the present setpoint
//! ([`crate::control::feedback::FeedbackState::enter_closed_loop`]): the integrator takes up what the
//! fading offset leaves.

/// Control mode.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Mode {
    /// No compensation: the drive follows the setpoint linearly, range onto range.
    Bypass,
    /// Inverse-model feedforward.
    OpenLoop,
    /// Feedforward (inverse model, or the setpoint itself without a compensator) plus PI(D)
    /// feedback on the sensor.
    ClosedLoop,
}

/// Why a mode switch was refused (nothing changed).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ModeError {
    /// Open loop needs a compensator (a model), and the configuration has none.
    NoCompensator,
    /// Closed loop needs the sensor feedback, and the configuration has none.
    NoSensor,
}

/// The transfer offset fades by `1/2^TRANSFER_SHIFT` of itself per tick.
pub const TRANSFER_SHIFT: u32 = 8;

/// The fading offset of a mode switch, Q2.30 normalised drive (0 when no switch is under way).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BumplessTransfer {
    remaining: i32,
}

impl BumplessTransfer {
    /// Starts a transfer of `offset` (Q2.30), replacing what was left of the last one.
    pub fn start(&mut self, offset: i32) {
        self.remaining = offset;
    }

    /// What is left to fade, Q2.30.
    pub fn remaining(&self) -> i32 {
        self.remaining
    }

    /// Adds the offset to `command` (saturating) and fades it one tick. Once it is below
    /// `2^TRANSFER_SHIFT` LSB (2.4e-7 of full scale) it ends: the transfer always finishes.
    #[inline(always)]
    pub fn apply(&mut self, command: i32) -> i32 {
        let r = self.remaining;
        if r == 0 {
            return command;
        }
        let fade = r >> TRANSFER_SHIFT;
        self.remaining = if fade == 0 || fade == -1 { 0 } else { r - fade };
        command.saturating_add(r)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed_point::signal_from_f64;

    #[test]
    fn the_offset_fades_smoothly_and_ends() {
        for offset in [signal_from_f64(0.3), signal_from_f64(-0.3), 1, -1, i32::MIN] {
            let mut t = BumplessTransfer::default();
            t.start(offset);
            let mut last = t.apply(0);
            assert_eq!(last, offset, "the first tick carries the whole offset");
            let mut ticks = 0;
            while t.remaining() != 0 {
                let now = t.apply(0);
                // Each tick moves by at most 1/256 of what is left: no bump.
                assert!((now as i64 - last as i64).abs() <= (last as i64).abs() / 256 + 256);
                last = now;
                ticks += 1;
                assert!(ticks < 10_000, "the transfer must end");
            }
            assert_eq!(t.apply(5), 5);
        }
    }
}
