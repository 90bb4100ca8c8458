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
use crate::services::snapshot::{Events, Snapshot, SnapshotConsumer, BATCH, SNAPSHOT_RING_LEN};
use crate::services::telemetry::{TelemetrySample, TelemetryTap};

/// The services' part of a tick while they listen ([`Services`]: a capture or a record armed
/// or running, telemetry running) and pass over the snapshots that take nothing: a snapshot
/// passed over (its dequeue, its sequence, generation and awaited-event checks) and its share
/// of the services' task's wake (its entry, return and lock, and the floating-point context
/// its task saves and restores — it runs the observer's models inline, the floating-point
/// ones among them: `config::tick_budget::FP_CONTEXT_CYCLES` — once a batch of [`BATCH`]
/// snapshots). The snapshot's push in the tick is in the tick budget's `FIXED_CYCLES`.
///
/// The services serve a batch in one of two loops ([`Services::consume_at_most`]), and the
/// charge follows the loop: where every snapshot is served in full (an observer below the
/// tick, or a capture or telemetry on every tick), [`SERVICES_EVERY_CYCLES`] a snapshot;
/// otherwise this base a snapshot and [`SERVE_CYCLES`] for each that takes a frame or a
/// sample, and a capture's with a pre-trigger window [`FIRE_CYCLES`] more. Each frame and sample adds
/// [`CAPTURE_FRAME_CYCLES`] and [`TELEMETRY_SAMPLE_CYCLES`]. These coefficients are declared here, beside the code they
/// cost, and the tick budget (`config::tick_budget`) charges them; the whole-interrupt bench
/// (`tests/irq_bench.rs`) measures the services' dearest batch in every scenario, with the
/// capture and telemetry each on every tick or every eighth (the two loops' dearest
/// batches), and fails any scenario whose share of that batch a tick exceeds this charge, and
/// any whose worst tick and share exceed the pipeline's prediction.
pub const SERVICES_BASE_CYCLES: u32 = 80;

/// A snapshot the passing loop serves in full (a frame or a sample due, an awaited event, a
/// gap, a new configuration), beyond a passed one: the loop's checks, the countdowns moved
/// at once, the full serve (see [`SERVICES_BASE_CYCLES`]). Charged for each frame and sample
/// a batch holds, and, while a capture is armed or running, for one more: the snapshot of
/// the event it waits for.
pub const SERVE_CYCLES: u32 = 190;

/// The batch in which a capture with a pre-trigger window fires (its awaited event served in
/// full), beyond the [`SERVE_CYCLES`] of that serve: the window closed and what falls beside
/// it in that batch. Measured by the whole-interrupt bench's trigger scenarios (the dearest:
/// a capture armed on the trigger input's edge with a pre-trigger window, every eighth tick,
/// beside telemetry every eighth and a spiral with the learning, the generalised P–I 17 + creep
/// 4 as the compensator only: 1 745 cycles at 5 WS for that batch, which 320 covers). A capture
/// without a window (every other scenario) stays within the charge without it.
pub const FIRE_CYCLES: u32 = 320;

/// The batch in which a reloaded configuration's observer below the tick takes over (the
/// staged observer moved into place, its bank's state with it), beyond its serve. Measured
/// by the whole-interrupt bench's reload scenario (mid-stream, another configuration and its
/// observer loaded, then the modes switched: the P–I and the Duhem configurations reload
/// each other, the rest the P–I one). The dearest batch, the Bouc–Wen + output map + creep
/// configuration's handing over to the P–I one, is 784 cycles a tick with its serves, where
/// 480 here charged 753: the observer's step tests the creep that follows it on every
/// snapshot, and where the reload falls, and how many snapshots the batch catches up on,
/// moves with the ticks' length (the floating-point models' ticks grew by the call that keeps
/// their registers out of the tick's prologue).
pub const RELOAD_CYCLES: u32 = 740;

/// A snapshot where every snapshot is served in full, with its share of the wake (see
/// [`SERVICES_BASE_CYCLES`]); the observer's own cost is the configuration's.
pub const SERVICES_EVERY_CYCLES: u32 = 180;

/// A frame the capture (or a `Record`) stores, all seven signals: its signals computed and
/// stored (see [`SERVICES_BASE_CYCLES`]).
pub const CAPTURE_FRAME_CYCLES: u32 = 150;

/// A sample telemetry's tap queues (all seven signals): its signals computed and queued (see
/// [`SERVICES_BASE_CYCLES`]).
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
    /// The capture keeps a pre-trigger window (charged [`FIRE_CYCLES`] for the batch it
    /// fires in).
    pub capture_pre_trigger: bool,
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
        capture_pre_trigger: true,
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

    /// Whether the services serve every snapshot in full under this load: an observer below
    /// the tick, or a capture or telemetry taking every tick (as
    /// [`Services::consume_at_most`] decides).
    pub fn serves_every_snapshot(&self) -> bool {
        every_snapshot_served(
            self.observer_cycles > 0,
            self.capture_decimation,
            self.telemetry_decimation,
        )
    }

    /// Their cost per tick, cycles (rounded up), over the dearest batch of [`BATCH`]
    /// snapshots: where every snapshot is served in full, [`SERVICES_EVERY_CYCLES`] and the
    /// observer below the tick on each; otherwise [`SERVICES_BASE_CYCLES`] on each and
    /// [`SERVE_CYCLES`] on each frame and sample the batch holds at their decimations (and on
    /// an armed capture's event); and the frames' and samples' own costs, shared by the
    /// batch's ticks.
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
        let (frames, samples) = (
            per_batch(self.capture_decimation),
            per_batch(self.telemetry_decimation),
        );
        // A capture's batch may also hold the event it waits for: one more in full, and
        // with a pre-trigger window taking every d-th tick (d > 1), what firing adds (a
        // window of every tick is filled in full all along: measured within its serves).
        let event = u32::from(self.capture_decimation.is_some());
        let fire = if self.capture_pre_trigger && frames < BATCH {
            FIRE_CYCLES * event
        } else {
            0
        };
        let serving = if self.serves_every_snapshot() {
            // With an observer, the batch a new configuration's observer takes over in.
            let reload = if self.observer_cycles > 0 {
                RELOAD_CYCLES
            } else {
                0
            };
            (SERVICES_EVERY_CYCLES + self.observer_cycles) * BATCH + reload
        } else {
            SERVICES_BASE_CYCLES * BATCH + SERVE_CYCLES * (frames + samples + event).min(BATCH)
        } + fire;
        (serving + CAPTURE_FRAME_CYCLES * frames + TELEMETRY_SAMPLE_CYCLES * samples)
            .div_ceil(BATCH)
    }
}

/// The rule by which the services serve every snapshot in full rather than pass quiet ones
/// over: an observer below the tick, or a capture or telemetry (by their decimations, `None`
/// when not running) taking every tick. [`Services::consume_at_most`] runs by it and
/// [`ServicesLoad::cycles`] charges by it.
#[inline(always)]
const fn every_snapshot_served(
    observer: bool,
    capture_decimation: Option<u16>,
    telemetry_decimation: Option<u16>,
) -> bool {
    observer
        || matches!(capture_decimation, Some(0 | 1))
        || matches!(telemetry_decimation, Some(0 | 1))
}

/// Marks the branch that serves a snapshot in full as the less likely one: the loop is laid
/// out with passing a quiet snapshot as its straight run of instructions, and the full serve
/// (inlined still) out of it.
#[cold]
#[inline(always)]
fn full_serve() {}

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
    ///
    /// A snapshot that takes no frame and no sample, where no observer runs below the tick,
    /// is passed over in one pass: dequeued, its sequence, generation
    /// and awaited event checked, and nothing else; the capture's and the tap's countdowns
    /// then move by the snapshots passed at once. Any other snapshot (a frame or a sample
    /// due, an observer, a gap, a new configuration, the event an armed capture waits for)
    /// is served in full, as every snapshot is where nothing can be passed over.
    pub fn consume_at_most<const T: usize>(
        &mut self,
        count: usize,
        ring: &mut SnapshotConsumer<'_>,
        telemetry: &mut Producer<'_, TelemetrySample, T>,
    ) -> bool {
        let mut left = count.min(SNAPSHOT_RING_LEN);
        let mut wake = false;
        if !self.serves_every_snapshot() {
            wake = self.pass_quiet(&mut left, ring, telemetry);
        }
        // Every snapshot in full (an observer, or a capture or telemetry taking every tick),
        // with none of passing's checks around it.
        for _ in 0..left {
            let Some(snapshot) = ring.peek() else {
                break;
            };
            wake |= self.serve(snapshot, telemetry);
            let _ = ring.dequeue();
        }
        wake
    }

    /// The passing loop of [`Services::consume_at_most`]: serves snapshots, passing quiet ones
    /// over, until `left` is used up, the ring is empty, or a full serve made every snapshot
    /// one to serve in full (a new configuration's observer, a capture taking every tick);
    /// `left` is what remains. Whether to wake the packer.
    #[inline(always)]
    fn pass_quiet<const T: usize>(
        &mut self,
        left: &mut usize,
        ring: &mut SnapshotConsumer<'_>,
        telemetry: &mut Producer<'_, TelemetrySample, T>,
    ) -> bool {
        let mut wake = false;
        let mut quiet = self.quiet();
        // The event an armed capture waits for: only arming sets it, never while the services
        // consume; the full serve that fires it clears it (so an armed capture's events cost
        // one full serve, the one that fires it).
        let mut awaited = self.awaited();
        // What a quiet snapshot is checked against, in registers: only a full serve changes
        // them.
        let (mut expected, mut generation) = (self.expected, self.generation);
        let mut passed = 0;
        while *left > 0 {
            // Checked and served where it lies in the ring, then released: no copy of it out
            // (a dequeue by value would copy all of it before releasing its slot).
            let Some(snapshot) = ring.peek() else {
                break;
            };
            *left -= 1;
            if quiet > passed
                && snapshot.seq == expected.wrapping_add(passed)
                && snapshot.generation == generation
                && snapshot.events.0 & awaited == 0
            {
                passed += 1;
                let _ = ring.dequeue();
                continue;
            }
            full_serve();
            self.pass(passed);
            passed = 0;
            wake |= self.serve(snapshot, telemetry);
            let _ = ring.dequeue();
            if self.serves_every_snapshot() {
                return wake;
            }
            (quiet, awaited) = (self.quiet(), self.awaited());
            (expected, generation) = (self.expected, self.generation);
        }
        self.pass(passed);
        wake
    }

    /// Whether every snapshot is served in full whatever happens before the batch ends: an
    /// observer runs below the tick, or a capture or telemetry takes every tick. (A reload
    /// or a capture's end within the batch only makes a full serve unneeded, never wrong.)
    #[inline(always)]
    fn serves_every_snapshot(&self) -> bool {
        every_snapshot_served(
            self.observer.is_some(),
            self.recorder.running_decimation(),
            self.telemetry.running_decimation(),
        )
    }

    /// How many snapshots from the next on need nothing but their countdowns: those before
    /// the next frame or sample (`u32::MAX` when neither a capture nor telemetry runs). Only
    /// the passing loop asks, which never runs beside an observer below the tick.
    #[inline(always)]
    fn quiet(&self) -> u32 {
        self.recorder
            .quiet_ticks()
            .min(self.telemetry.quiet_ticks())
    }

    /// The [`Events`] bit of the event an armed capture waits for (0: none waits).
    #[inline(always)]
    fn awaited(&self) -> u8 {
        self.recorder.awaited_trigger().map_or(0, Events::bit)
    }

    /// `ticks` snapshots passed over ([`Services::quiet`]): the sequence, the capture's and
    /// the tap's countdowns move by them at once.
    #[inline(always)]
    fn pass(&mut self, ticks: u32) {
        if ticks > 0 {
            self.expected = self.expected.wrapping_add(ticks);
            self.recorder.pass(ticks);
            self.telemetry.pass(ticks);
        }
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
        // Of the events, only the one an armed capture waits for does anything (the first
        // fires it; after that it waits for none): one test, not one per event.
        if s.events.0 != 0 {
            if let Some(awaited) = self.recorder.awaited_trigger() {
                if s.events.0 & Events::bit(awaited) != 0 {
                    self.recorder.trigger(awaited);
                }
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
            capture_pre_trigger: self.recorder.keeps_pre_trigger(),
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
    use crate::services::recorder::{CaptureInfo, CaptureState, Channel, Trigger};
    extern crate std;
    use crate::services::snapshot::{Events, SnapshotRing};
    use heapless::spsc::Queue;
    use std::vec::Vec;

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

    /// What a script of snapshots and commands leaves in the services: the capture's state
    /// and frames, a `Record`'s values, telemetry's samples and counts.
    type Outcome = (
        CaptureInfo,
        Vec<i16>,
        u32,
        Vec<TelemetrySample>,
        (u32, u32, u32),
    );

    fn outcome(s: &Services<[i16; 96]>, samples: Vec<TelemetrySample>) -> Outcome {
        let info = s.recorder().capture_info();
        let mut frames = Vec::new();
        let mut out = heapless::Vec::new();
        let mut at = 0;
        while s
            .recorder()
            .read_capture_piece(at, 8, &mut out)
            .unwrap_or(0)
            > 0
        {
            frames.extend_from_slice(&out);
            at += out.len() as u32;
        }
        (
            info,
            frames,
            s.recorder().recorded(),
            samples,
            (s.lost(), s.telemetry().overflows(), s.drifts()),
        )
    }

    /// A command between two batches, applied to both services alike.
    #[derive(Clone, Debug)]
    enum Command {
        Capture(u8, u32, u32, u8, u16),
        Record(u8, u32, u16),
        Telemetry(u8, u16),
        StopTelemetry,
        /// An observer below the tick (with a 2 % drift check) for the next configuration,
        /// or none.
        Stage(bool),
    }

    /// A P–I 4 observer with its drift check at 2 %.
    fn observer() -> ObserverBelow {
        use crate::config::settings::{representative_pi, Settings};
        let mut settings = Settings {
            observer: Some(representative_pi(4).unwrap()),
            ..Settings::default()
        };
        if let Some(sensor) = &mut settings.sensor {
            sensor.drift_limit = Some(0.02);
        }
        let config = settings
            .build(&crate::board::Hardware::driver_board(50_000.0))
            .unwrap();
        ObserverBelow::prepare(&config, config.drive.safe_stacks()).unwrap()
    }

    fn apply(s: &mut Services<[i16; 96]>, command: &Command) {
        const TRIGGERS: [Trigger; 5] = [
            Trigger::Now,
            Trigger::StreamStart,
            Trigger::WaveformStart,
            Trigger::ScanStart,
            Trigger::External,
        ];
        match *command {
            Command::Capture(mask, samples, pre, trigger, decimation) => {
                let _ = s.recorder_mut().arm_capture(
                    mask,
                    samples,
                    pre,
                    TRIGGERS[usize::from(trigger) % 5],
                    decimation,
                );
            }
            Command::Record(signal, count, decimation) => {
                let signal = [
                    crate::protocol::messages::Signal::Setpoint,
                    crate::protocol::messages::Signal::Drive,
                    crate::protocol::messages::Signal::Sensor,
                    crate::protocol::messages::Signal::Estimate,
                ][usize::from(signal) % 4];
                let _ = s.recorder_mut().arm(signal, count, decimation);
            }
            Command::Telemetry(mask, decimation) => {
                let _ = s.start_telemetry(mask, decimation, 3);
            }
            Command::StopTelemetry => {
                let _ = s.stop_telemetry();
            }
            Command::Stage(with) => s.stage_observer(with.then(observer)),
        }
    }

    fn command() -> impl proptest::strategy::Strategy<Value = Command> {
        use proptest::prelude::*;
        prop_oneof![
            (1u8..128, 1u32..20, 0u32..6, 0u8..5, 1u16..12)
                .prop_map(|(m, n, p, t, d)| Command::Capture(m, n, p, t, d)),
            (0u8..4, 1u32..30, 1u16..12).prop_map(|(s, n, d)| Command::Record(s, n, d)),
            (1u8..128, 1u16..12).prop_map(|(m, d)| Command::Telemetry(m, d)),
            Just(Command::StopTelemetry),
            proptest::bool::ANY.prop_map(Command::Stage),
        ]
    }

    proptest::proptest! {
        /// Passing over quiet snapshots in one pass leaves the services exactly as serving
        /// each snapshot in full does: the same frames, `Record` values, telemetry samples
        /// and indices, and counts, whatever the decimations, the events (awaited or not),
        /// the gaps in the sequence, the configurations' generations and the commands between
        /// batches, with or without an observer below the tick.
        #[test]
        fn passing_quiet_snapshots_is_serving_each(
            script in proptest::collection::vec(
                (
                    proptest::option::weighted(0.3, command()),
                    proptest::collection::vec((0u32..40, 0u8..16, 0u8..20), 1..20),
                ),
                1..12,
            ),
            batch in 1usize..12,
        ) {
            let mut batched = Services::new([0i16; 96]);
            let mut each = Services::new([0i16; 96]);
            let mut ring_b = SnapshotRing::new();
            let mut ring_e = SnapshotRing::new();
            let (mut push_b, mut pop_b) = ring_b.split();
            let (mut push_e, mut pop_e) = ring_e.split();
            let mut out_b: Queue<TelemetrySample, 512> = Queue::new();
            let mut out_e: Queue<TelemetrySample, 512> = Queue::new();
            let (mut tx_b, mut rx_b) = out_b.split();
            let (mut tx_e, mut rx_e) = out_e.split();
            let (mut samples_b, mut samples_e) = (Vec::new(), Vec::new());
            let (mut wakes_b, mut wakes_e) = (0, 0);
            let (mut seq, mut generation) = (0u32, 0u8);
            for (command, ticks) in &script {
                if let Some(c) = command {
                    apply(&mut batched, c);
                    apply(&mut each, c);
                }
                for &(value, events, roll) in ticks.iter().take(SNAPSHOT_RING_LEN - 1) {
                    // Rare gaps and new configurations; events on a fifth of the ticks.
                    seq = seq.wrapping_add(if roll == 0 { 3 } else { 1 });
                    if roll == 1 {
                        generation = generation.wrapping_add(1);
                    }
                    let events = Events(if roll % 5 == 2 { events } else { 0 });
                    let mut shot = snapshot(seq, events);
                    shot.measured = (value as i32 - 20) << 24;
                    shot.generation = generation;
                    push_b.enqueue(shot).unwrap();
                    push_e.enqueue(shot).unwrap();
                }
                while pop_b.ready() {
                    wakes_b += u32::from(batched.consume_at_most(batch, &mut pop_b, &mut tx_b));
                }
                while let Some(shot) = pop_e.dequeue() {
                    wakes_e += u32::from(each.serve(&shot, &mut tx_e));
                }
                samples_b.extend(core::iter::from_fn(|| rx_b.dequeue()));
                samples_e.extend(core::iter::from_fn(|| rx_e.dequeue()));
            }
            proptest::prop_assert_eq!(wakes_b > 0, wakes_e > 0);
            proptest::prop_assert_eq!(outcome(&batched, samples_b), outcome(&each, samples_e));
        }
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
