//! The services below the tick: the recorder, continuous telemetry's tap and the observer
//! with its drift check ([`crate::services::observer`]), fed from the snapshot ring
//! ([`crate::services::snapshot`]).
//!
//! On the board they are one RTIC resource of their own, run by a priority-2 task the tick
//! wakes once every [`crate::services::snapshot::BATCH`] ticks, and reached by the command
//! handler through a lock that never masks the tick: reading a capture back, arming the
//! recorder or starting telemetry holds off the consumer, not the control law. In the
//! simulator the same struct is stepped after the ticks.
//!
//! Whoever takes the services (the consumer's task, or the command handler through its lock)
//! first drains the ring ([`Services::consume`]), so that what the handler reads or arms is
//! up to date with every tick pushed before it: a capture armed now starts with the next
//! tick's frame, as it did when the recorder ran in the tick.

use heapless::spsc::Producer;

use crate::control::TickFlags;
use crate::services::observer::ObserverBelow;
use crate::services::recorder::{Recorder, SampleStore, TickSignals};
use crate::services::snapshot::{Snapshot, SnapshotConsumer, BATCH, SNAPSHOT_RING_LEN};
use crate::services::telemetry::{TelemetrySample, TelemetryTap};

/// The services' part of a tick while they listen ([`Services`]:
/// a capture or a record armed or running, telemetry running), whatever they take: the tick's
/// share of the services' task's wake (its entry, return and lock, once a batch of
/// [`BATCH`] snapshots) and of each snapshot's serving (its
/// dequeue, sequence and events checks, the capture's and the tap's countdowns). The
/// snapshot's push in the tick is in the tick budget's `FIXED_CYCLES`. These three
/// coefficients are declared here, beside the code they cost, and the tick budget
/// (`config::tick_budget`) charges them; the whole-interrupt bench (`tests/irq_bench.rs`)
/// measures the services' dearest turn in every scenario, with the capture and telemetry each
/// on every tick or every eighth (a batch's cost is affine in the frames and samples it holds,
/// so these bound every decimation), and checks the pipeline — the worst tick and the share of
/// that turn each tick carries — against the budget's prediction with these charges. The
/// charge alone is not the share alone: on the bench's configuration without an observer the
/// share exceeds it where the snapshots carry the recorder's events (a scan's, or a capture
/// armed on the trigger input: up to 247 cycles a tick against 174), which the interrupt's
/// prediction covers.
pub const SERVICES_BASE_CYCLES: u32 = 140;

/// A frame the capture (or a `Record`) stores, all seven signals: charged for each frame a
/// batch of snapshots can hold at the capture's decimation (see [`SERVICES_BASE_CYCLES`]).
pub const CAPTURE_FRAME_CYCLES: u32 = 155;

/// A sample telemetry's tap queues (all seven signals): charged for each sample a batch of
/// snapshots can hold at telemetry's decimation (see [`SERVICES_BASE_CYCLES`]).
pub const TELEMETRY_SAMPLE_CYCLES: u32 = 115;

/// What the services run, as the tick budget charges it: a capture (or a `Record`) and
/// telemetry, each by its decimation (`None`: not running), and the configuration's observer
/// where it runs below the tick. Nothing running costs nothing: the tick then pushes no
/// snapshot and never wakes the services.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ServicesLoad {
    /// The capture's (or record's) decimation, if one is armed or running.
    pub capture_decimation: Option<u16>,
    /// Telemetry's decimation, if it runs.
    pub telemetry_decimation: Option<u16>,
    /// What the configuration's observer below the tick costs a snapshot, cycles (its model,
    /// its creep, the drift check: `config::tick_budget::observer_below_cycles`); 0 where it
    /// has none there. The tick budget sets it from the configuration.
    pub observer_cycles: u32,
}

impl ServicesLoad {
    /// The dearest a capture and telemetry can be: both taking every tick (with no observer
    /// below the tick: that one is the configuration's, charged with it).
    pub const WORST: Self = Self {
        capture_decimation: Some(1),
        telemetry_decimation: Some(1),
        observer_cycles: 0,
    };

    /// This load with an observer below the tick costing `cycles` a snapshot.
    pub const fn observing(self, cycles: u32) -> Self {
        Self {
            observer_cycles: cycles,
            ..self
        }
    }

    /// Whether anything runs (the tick hands the services its snapshots).
    pub fn is_listening(&self) -> bool {
        self.capture_decimation.is_some()
            || self.telemetry_decimation.is_some()
            || self.observer_cycles > 0
    }

    /// Their cost per tick, cycles (rounded up): [`SERVICES_BASE_CYCLES`], the observer below
    /// the tick on every snapshot, and the frames and samples the dearest batch of [`BATCH`]
    /// snapshots holds at their decimations shared by its ticks.
    ///
    /// ```
    /// use twinstack::services::consumer::{ServicesLoad, SERVICES_BASE_CYCLES};
    /// assert_eq!(ServicesLoad::default().cycles(), 0);
    /// let decimated = ServicesLoad { capture_decimation: Some(10), ..ServicesLoad::default() };
    /// assert!(decimated.cycles() > SERVICES_BASE_CYCLES);
    /// assert!(decimated.cycles() < ServicesLoad::WORST.cycles());
    /// ```
    pub fn cycles(&self) -> u32 {
        if !self.is_listening() {
            return 0;
        }
        // The most frames (samples) a batch holds at decimation `d`: one every `d` ticks.
        let per_batch = |d: Option<u16>| d.map_or(0, |d| BATCH.div_ceil(u32::from(d.max(1))));
        ((SERVICES_BASE_CYCLES + self.observer_cycles) * BATCH
            + CAPTURE_FRAME_CYCLES * per_batch(self.capture_decimation)
            + TELEMETRY_SAMPLE_CYCLES * per_batch(self.telemetry_decimation))
        .div_ceil(BATCH)
    }
}

/// The recorder, telemetry's tap and the observer below the tick, consuming the tick's
/// snapshots. `B` is the recorder's buffer.
#[derive(Debug)]
pub struct Services<B> {
    recorder: Recorder<B>,
    telemetry: TelemetryTap,
    /// The configuration's observer, where it runs below the tick.
    observer: Option<ObserverBelow>,
    /// The observer of a configuration posted to the tick but not yet seen running
    /// (`Some(None)`: the next configuration has none here).
    staged: Option<Option<ObserverBelow>>,
    /// The generation of the last snapshot served ([`Snapshot::generation`]).
    generation: u8,
    /// Ticks the drift check flagged, since power-up, wrapping.
    drifts: u32,
    /// The sequence number the next snapshot should carry.
    expected: u32,
    /// Snapshots the ring refused (gaps in the sequence), since power-up, wrapping.
    lost: u32,
}

impl<B: SampleStore> Services<B> {
    /// Idle services over `record_buffer`: no capture armed, telemetry stopped.
    ///
    /// ```
    /// use twinstack::services::consumer::Services;
    /// let services = Services::new(vec![0i16; 1024]);
    /// assert_eq!(services.recorder().capacity(), 1024);
    /// assert!(!services.recorder().is_capturing());
    /// ```
    pub fn new(record_buffer: B) -> Self {
        Self {
            recorder: Recorder::new(record_buffer),
            telemetry: TelemetryTap::new(),
            observer: None,
            staged: None,
            generation: 0,
            drifts: 0,
            expected: 0,
            lost: 0,
        }
    }

    /// Serves every snapshot the ring holds, oldest first (at most the ring's length: the
    /// loop is bounded), putting telemetry's samples on `telemetry`. Returns whether to wake
    /// the packer (a frame's worth of samples taken since its last wake).
    pub fn consume<const T: usize>(
        &mut self,
        ring: &mut SnapshotConsumer<'_>,
        telemetry: &mut Producer<'_, TelemetrySample, T>,
    ) -> bool {
        self.consume_at_most(SNAPSHOT_RING_LEN, ring, telemetry)
    }

    /// Serves at most `count` snapshots, oldest first, as [`Services::consume`] does: the
    /// services' task serves a batch ([`crate::services::snapshot::BATCH`]) a wake, so that
    /// one wake never costs more than a batch, and wakes itself again while the ring holds
    /// more (a task held off for a few ticks catches up in batches).
    pub fn consume_at_most<const T: usize>(
        &mut self,
        count: usize,
        ring: &mut SnapshotConsumer<'_>,
        telemetry: &mut Producer<'_, TelemetrySample, T>,
    ) -> bool {
        let mut wake = false;
        for _ in 0..count.min(SNAPSHOT_RING_LEN) {
            // Served where it lies in the ring, then released: no copy of it out.
            let Some(snapshot) = ring.peek() else {
                break;
            };
            wake |= self.serve(snapshot, telemetry);
            let _ = ring.dequeue();
        }
        wake
    }

    /// One tick's snapshot: the observer below the tick on its drive and measurement, then
    /// what the recorder did in the tick, in the same order — its trigger events, then its
    /// capture — and telemetry's tap.
    #[inline(always)]
    fn serve<const T: usize>(
        &mut self,
        s: &Snapshot,
        telemetry: &mut Producer<'_, TelemetrySample, T>,
    ) -> bool {
        let missing = s.seq.wrapping_sub(self.expected);
        self.expected = s.seq.wrapping_add(1);
        if missing != 0 {
            self.lose(missing);
        }
        if s.generation != self.generation {
            self.reload(s.generation);
        }
        let mut report = s.report();
        if let Some(o) = &mut self.observer {
            o.observe(&mut report);
            if report.flags.contains(TickFlags::DRIFT) {
                self.drifts = self.drifts.wrapping_add(1);
            }
        }
        if s.events.0 != 0 {
            for event in s.events.iter() {
                self.recorder.trigger(event);
            }
        }
        // The countdowns first: the signals are computed only on a tick that takes them.
        let frame = self.recorder.due();
        let sample = self.telemetry.due();
        if !(frame || sample) {
            return false;
        }
        let signals = TickSignals::of(s.setpoint, s.measured, &report);
        if frame {
            self.recorder
                .store(&signals, s.setpoint, s.measured, &report);
        }
        sample && self.telemetry.queue(telemetry, &signals)
    }

    /// A new configuration ran its first tick at this snapshot: its observer (staged by
    /// [`Services::stage_observer`] before the controller was posted) takes over.
    #[cold]
    fn reload(&mut self, generation: u8) {
        self.generation = generation;
        if let Some(observer) = self.staged.take() {
            self.observer = observer;
        }
    }

    /// `ticks` snapshots never reached the ring: a capture in progress ends without
    /// completing, telemetry's indices skip the samples lost. The observer below the tick
    /// goes on from the next drive it is given: for a rate-independent model that is as if
    /// the drive had moved straight between the two, so the estimate stays within the
    /// hysteresis of what the lost ticks swept (each loss is counted in the overruns).
    #[cold]
    fn lose(&mut self, ticks: u32) {
        self.lost = self.lost.wrapping_add(ticks);
        self.recorder.lose_frames();
        self.telemetry.lose_ticks(ticks);
    }

    /// Whether the services need the tick's snapshots: a capture or a record armed or
    /// running, telemetry running, or an observer below the tick in force or staged.
    pub fn is_active(&self) -> bool {
        self.recorder.is_capturing()
            || self.telemetry.is_running()
            || self.observer.is_some()
            || self.staged.is_some()
    }

    /// Stages the observer below the tick of a configuration about to be posted to the tick
    /// ([`ObserverBelow::from_relaxed`], `None` where it has none there): it takes over at the
    /// first snapshot the new configuration's tick pushes. Call it before the post, with the
    /// tick handing the services its snapshots if either observer is there; a newer staging
    /// replaces one no tick has run yet, as the newer of two posts between two ticks
    /// replaces the older.
    pub fn stage_observer(&mut self, observer: Option<ObserverBelow>) {
        self.staged = if observer.is_none() && self.observer.is_none() {
            None
        } else {
            Some(observer)
        };
    }

    /// Puts `observer` in force at once, for the configuration the tick runs from power-up
    /// (generation 0: no swap yet).
    pub fn start_observer(&mut self, observer: Option<ObserverBelow>) {
        self.observer = observer;
        self.staged = None;
    }

    /// The observer below the tick in force, if any: its last estimate and drift.
    pub fn observer(&self) -> Option<&ObserverBelow> {
        self.observer.as_ref()
    }

    /// Ticks the drift check below the tick flagged since power-up (wrapping): a load does
    /// not reset it, and ticks whose snapshots were lost are not checked. The status reports
    /// it (`StatusReport::drifts`).
    pub fn drifts(&self) -> u32 {
        self.drifts
    }

    /// What they run, as the tick budget charges it: the capture's (or record's) and
    /// telemetry's decimations (the observer below the tick is the configuration's: the tick
    /// budget charges it from the configuration).
    pub fn load(&self) -> ServicesLoad {
        ServicesLoad {
            capture_decimation: self.recorder.running_decimation(),
            telemetry_decimation: self.telemetry.running_decimation(),
            observer_cycles: 0,
        }
    }

    /// Snapshots lost since power-up (the ring was full when the tick pushed them): each one
    /// a tick whose services did not keep up, counted with the board's overruns.
    pub fn lost(&self) -> u32 {
        self.lost
    }

    /// The recorder: its settings, progress and reads.
    pub fn recorder(&self) -> &Recorder<B> {
        &self.recorder
    }

    /// The recorder, to arm it.
    pub fn recorder_mut(&mut self) -> &mut Recorder<B> {
        &mut self.recorder
    }

    /// Telemetry's tap: whether it runs, its counts.
    pub fn telemetry(&self) -> &TelemetryTap {
        &self.telemetry
    }

    /// Starts telemetry of `mask` every `decimation` ticks (see [`TelemetryTap::start`]);
    /// the index of its first sample, or `None` for a bad mask or decimation. The tap wakes
    /// the packer at `wake` queued samples (a frame's worth,
    /// [`crate::services::telemetry::frame_target`]).
    pub fn start_telemetry(&mut self, mask: u8, decimation: u16, wake: u16) -> Option<u32> {
        self.telemetry.wake_at(wake);
        self.telemetry.start(mask, decimation)
    }

    /// Stops telemetry; the index its next sample would have carried.
    pub fn stop_telemetry(&mut self) -> u32 {
        self.telemetry.stop()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::board::DacCode;
    use crate::control::{TickFlags, TickReport};
    use crate::services::recorder::{CaptureState, Channel, Trigger};
    use crate::services::snapshot::{Events, SnapshotRing};
    use heapless::spsc::Queue;

    fn snapshot(seq: u32, events: Events) -> Snapshot {
        let report = TickReport {
            left: DacCode(seq as u16),
            right: DacCode(0),
            estimate: 0,
            measured: 0,
            drive: 0,
            flags: TickFlags(0),
            triggers: 0,
        };
        Snapshot::of(seq, (seq as i32) << 16, &report, events, 0)
    }

    /// A capture armed on the stream's start begins with the snapshot carrying that event,
    /// as it began with the tick after the start when it ran in the tick.
    #[test]
    fn a_trigger_event_starts_the_capture_at_its_own_snapshot() {
        let mut ring = SnapshotRing::new();
        let mut samples: Queue<TelemetrySample, 4> = Queue::new();
        let (mut tx, _rx) = samples.split();
        let (mut push, mut pop) = ring.split();
        let mut s = Services::new([0i16; 64]);
        s.recorder_mut()
            .arm_capture(Channel::Left.bit(), 4, 0, Trigger::StreamStart, 1)
            .unwrap();
        for seq in 0..3 {
            push.enqueue(snapshot(seq, Events::NONE)).unwrap();
        }
        let mut start = Events::NONE;
        start.add(Trigger::StreamStart);
        push.enqueue(snapshot(3, start)).unwrap();
        for seq in 4..10 {
            push.enqueue(snapshot(seq, Events::NONE)).unwrap();
        }
        s.consume(&mut pop, &mut tx);
        assert_eq!(s.recorder().capture_info().state, CaptureState::Done);
        let mut out = heapless::Vec::new();
        s.recorder().read_capture_piece(0, 4, &mut out).unwrap();
        assert_eq!(&out[..], &[3, 4, 5, 6]);
        assert_eq!(s.lost(), 0);
    }

    /// A gap in the sequence ends a capture in progress (its state no longer reads as one
    /// that completes) and skips telemetry's indices by the samples lost.
    #[test]
    fn a_lost_snapshot_ends_the_capture_and_skips_telemetry() {
        let mut ring = SnapshotRing::new();
        let mut samples: Queue<TelemetrySample, 16> = Queue::new();
        let (mut tx, mut rx) = samples.split();
        let (mut push, mut pop) = ring.split();
        let mut s = Services::new([0i16; 64]);
        s.recorder_mut()
            .arm_capture(Channel::Left.bit(), 8, 0, Trigger::Now, 1)
            .unwrap();
        assert_eq!(s.start_telemetry(Channel::Left.bit(), 2, 100), Some(0));
        push.enqueue(snapshot(0, Events::NONE)).unwrap();
        push.enqueue(snapshot(1, Events::NONE)).unwrap();
        // Ticks 2–6 lost: telemetry's samples of ticks 2, 4 and 6.
        push.enqueue(snapshot(7, Events::NONE)).unwrap();
        push.enqueue(snapshot(8, Events::NONE)).unwrap();
        s.consume(&mut pop, &mut tx);
        assert_eq!(s.lost(), 5);
        assert_eq!(s.recorder().capture_info().state, CaptureState::Idle);
        assert!(!s.recorder().is_capturing());
        let indices: heapless::Vec<u32, 8> = core::iter::from_fn(|| rx.dequeue())
            .map(|t| t.index)
            .collect();
        // Tick 0 sampled (index 0), ticks 2, 4, 6 lost (1–3), tick 8 sampled (index 4).
        assert_eq!(&indices[..], &[0, 4]);
        assert_eq!(s.telemetry().overflows(), 3);
    }
}
