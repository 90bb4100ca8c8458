//! The snapshot ring: what each tick hands the services below it.
//!
//! The control interrupt runs the control law and ends with one fixed-size push: a
//! [`Snapshot`] of what the tick did (the setpoint in force, the tick's [`TickReport`], the
//! recorder's trigger events since the last tick) onto a `heapless::spsc` ring
//! ([`SnapshotRing`]). The services ([`crate::services::consumer::Services`]: the recorder and
//! continuous telemetry's tap) consume the ring at a lower priority, in batches, on their own
//! time — never inside the tick, and never under a lock the tick takes.
//!
//! Nothing the tick pushes is lost silently: each snapshot carries the tick's sequence number,
//! and a push the full ring refuses is counted by the tick; the consumer sees the gap in the
//! sequence and says so (telemetry's sample indices skip the samples lost, a capture that lost
//! a frame ends without completing, see [`crate::services::consumer::Services::consume`]).

use heapless::spsc::{Consumer, Producer, Queue};

use crate::board::DacCode;
use crate::control::{TickFlags, TickReport};
use crate::services::recorder::Trigger;

/// Slots of the snapshot ring (`heapless` keeps one free: 31 snapshots). The tick wakes the
/// consumer every [`BATCH`] snapshots, so it has 23 more ticks (230 µs at 100 kHz) to start
/// before one is lost; nothing at its priority or above runs that long.
pub const SNAPSHOT_RING_LEN: usize = 32;

/// Snapshots per wake of the consumer: the tick pends it once every `BATCH` ticks, so the
/// exception's entry and return are paid once a batch, not once a tick.
pub const BATCH: u32 = 8;

/// The ring between the tick (producer) and the services (consumer).
pub type SnapshotRing = Queue<Snapshot, SNAPSHOT_RING_LEN>;

/// The tick's end of the ring.
pub type SnapshotProducer<'a> = Producer<'a, Snapshot, SNAPSHOT_RING_LEN>;

/// The services' end of the ring.
pub type SnapshotConsumer<'a> = Consumer<'a, Snapshot, SNAPSHOT_RING_LEN>;

/// What one tick did, as the services need it: fixed size (24 bytes: the tick's
/// [`TickReport`] laid out flat beside the sequence number, the setpoint, the events and the
/// generation, so that no padding is copied; the estimate is not in it, the services compute
/// it), written once by the tick.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Snapshot {
    /// The tick's sequence number (wrapping): one more than the snapshot before it, unless
    /// the ring refused some in between.
    pub seq: u32,
    /// The setpoint in force, Q2.30 normalised displacement.
    pub setpoint: i32,
    /// The measured displacement, Q2.30 ([`TickReport::measured`]).
    pub measured: i32,
    /// The model-normalised drive applied, Q2.30 ([`TickReport::drive`]).
    pub drive: i32,
    /// The left stack's DAC code.
    pub left: DacCode,
    /// The right stack's DAC code.
    pub right: DacCode,
    /// What happened ([`TickReport::flags`]).
    pub flags: TickFlags,
    /// The trigger levels ([`TickReport::triggers`]).
    pub triggers: u8,
    /// The recorder's trigger events commanded or seen since the snapshot before it
    /// ([`Events`]), in force from this tick's frame on.
    pub events: Events,
    /// The configurations swapped in before this tick, wrapping at 256 (the control loop's
    /// swap count): a change from the snapshot before says a new configuration ran its first
    /// tick here, where the services put its observer in force
    /// ([`crate::services::observer`]). It fills the byte the layout would pad.
    pub generation: u8,
}

impl Snapshot {
    /// The snapshot of a tick: its sequence number, the setpoint in force, its report, the
    /// events since the last one and the configuration's generation.
    #[inline(always)]
    pub fn of(
        seq: u32,
        setpoint: i32,
        report: &TickReport,
        events: Events,
        generation: u8,
    ) -> Self {
        Self {
            seq,
            setpoint,
            measured: report.measured,
            drive: report.drive,
            left: report.left,
            right: report.right,
            flags: report.flags,
            triggers: report.triggers,
            events,
            generation,
        }
    }

    /// The tick's report, as the tick returned it.
    #[inline(always)]
    pub fn report(&self) -> TickReport {
        TickReport {
            left: self.left,
            right: self.right,
            // The observer runs below the tick, on this snapshot
            // ([`crate::services::observer`]).
            estimate: 0,
            measured: self.measured,
            drive: self.drive,
            flags: self.flags,
            triggers: self.triggers,
        }
    }
}

/// The recorder's trigger events a snapshot carries: one bit per [`Trigger`] that can fire
/// a capture (`Trigger::Now` fires at the arming, so it has none).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Events(pub u8);

impl Events {
    /// No event.
    pub const NONE: Self = Self(0);

    /// The bit of `trigger` (0 for [`Trigger::Now`]).
    #[inline(always)]
    pub const fn bit(trigger: Trigger) -> u8 {
        match trigger {
            Trigger::Now => 0,
            Trigger::StreamStart => 1 << 0,
            Trigger::WaveformStart => 1 << 1,
            Trigger::ScanStart => 1 << 2,
            Trigger::External => 1 << 3,
        }
    }

    /// Adds `trigger`.
    #[inline(always)]
    pub fn add(&mut self, trigger: Trigger) {
        self.0 |= Self::bit(trigger);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn events_keep_every_trigger_apart() {
        let all = [
            Trigger::StreamStart,
            Trigger::WaveformStart,
            Trigger::ScanStart,
            Trigger::External,
        ];
        let mut e = Events::NONE;
        e.add(Trigger::External);
        e.add(Trigger::ScanStart);
        e.add(Trigger::Now);
        // Each trigger a bit of its own; `Now` (fired at the arming) none.
        for t in all {
            let expected = matches!(t, Trigger::External | Trigger::ScanStart);
            assert_eq!(e.0 & Events::bit(t) != 0, expected, "{t:?}");
            assert_eq!(Events::bit(t).count_ones(), 1, "{t:?}");
        }
        assert_eq!(Events::bit(Trigger::Now), 0);
        let bits = all.iter().fold(0u8, |acc, &t| acc | Events::bit(t));
        assert_eq!(bits.count_ones(), 4);
    }

    #[test]
    fn a_snapshot_is_small_and_keeps_the_report() {
        assert_eq!(core::mem::size_of::<Snapshot>(), 24);
        let report = TickReport {
            left: DacCode(1),
            right: DacCode(2),
            estimate: 0,
            measured: 4,
            drive: 5,
            flags: TickFlags(6),
            triggers: 7,
        };
        let s = Snapshot::of(8, 9, &report, Events(1), 10);
        assert_eq!(s.report(), report);
        assert_eq!(
            (s.seq, s.setpoint, s.events, s.generation),
            (8, 9, Events(1), 10)
        );
    }
}
