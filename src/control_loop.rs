//! The tick side of the board: where each tick's setpoint comes from and the control tick
//! itself — everything the timer interrupt runs, in one struct.
//!
//! One [`ControlLoop::tick`] is:
//!
//! 1. the setpoint, from the one source in force ([`SetpointSource`], switched only by the
//!    loop's command methods, so the tick dispatches once): the built-in waveform generator,
//!    or the next streamed sample from the setpoint queue through [`SetpointStream`] (rate
//!    divider with linear interpolation; on an empty queue the underrun policy holds or ramps
//!    to the rest position, and counts), or a scan, a sequence, the analog input (below) or,
//!    in the dual-stage images, the coarse axis's ramp ([`crate::dual_stage::link`]);
//! 2. [`Controller::tick`] (compensator, sensor, feedback, limits, both DACs);
//! 3. one [`Snapshot`] of what the tick did onto the snapshot ring, for the services below
//!    the tick ([`crate::services::consumer`]: the recorder, telemetry's tap). A capture armed
//!    on a stream or waveform start is triggered by an event the start (commanded in
//!    [`ControlLoop::start`] / [`ControlLoop::play`]) puts in the next snapshot.
//!
//! With a scan ([`crate::sources::scan`], protocol v6) the setpoint comes from the scan generator
//! instead (step 1), and around it the tick samples the external trigger input (set by the
//! board with [`ControlLoop::set_trigger_input`] before the tick: an armed edge starts a scan
//! waiting for it, the stream if asked, and fires a capture armed on
//! [`Trigger::External`]) and, after the controller, turns the scan's pixel / line / frame
//! events into the trigger outputs' levels ([`ControlLoop::trigger_levels`], for the board to
//! write to its pins, and in the capture's `triggers` channel). All O(1).
//!
//! With a TTL-stepped sequence armed ([`crate::sources::sequence`]) the setpoint comes from it instead
//! (step 1): each edge on the trigger input pops one position from the setpoint queue, and the
//! settled output joins the trigger levels.
//!
//! With the analog input running ([`crate::sources::analog_input`]) the setpoint comes from the board's
//! second ADC input instead (step 1: [`SensorAdc::setpoint_input`], scaled, filtered, checked
//! against its window).
//!
//! A configuration prepared by the command handler ([`Controller::prepare`], on the spare
//! controller, outside any lock) is swapped in by [`ControlLoop::post`] inside the handler's
//! short critical section, in O(1): the loop holds its controllers by pointer, so the swap
//! moves a pointer, and [`Controller::take_over`] carries the stacks' voltages over (the
//! output does not jump; nothing is half-applied). The tick itself does no reconfiguring: the
//! first tick after a swap only starts the fading transfer from the drive the stacks hold.
//! The retired controller's counters are added to the totals when the handler takes it back.
//!
//! The command handler ([`crate::command_handler`]) runs at a lower priority. The two halves
//! meet in exactly two places: the lock-free single-producer single-consumer setpoint queue
//! ([`SetpointQueue`], `heapless::spsc`), and short critical sections in which the handler
//! calls this struct's command methods ([`ControlLoop::post`], [`ControlLoop::start`], …,
//! each a few stores) through an [`rtic_core::Mutex`] — RTIC's lock on the board, a plain
//! `&mut` in the simulator. A reload's heavy work ([`Controller::prepare`]) happens in the
//! handler, on a spare controller the tick does not touch ([`ControlLoop::spare`]). Nothing on
//! the tick path allocates, panics or loops.

use heapless::spsc::{Consumer, Queue};

use core::ops::DerefMut;

use crate::board::{DualDac, SensorAdc};
use crate::config::tick_budget::Beside;
use crate::control::drive::StackVoltages;
use crate::control::mode_switch::Mode;
use crate::control::mode_switch::ModeError;
use crate::control::{ControlCounters, Controller, TickFlags, TickReport};
use crate::services::learning::{LearnHost, LearnState, LearnTick};
use crate::services::recorder::Trigger;
use crate::services::snapshot::{Events, Snapshot, SnapshotProducer, BATCH};
use crate::sources::analog_input::{AnalogInput, AnalogStatus, PreparedInput};
use crate::sources::scan::{ExternalTrigger, ScanGenerator, TriggerConfig, TriggerOutputs, INPUT};
use crate::sources::sequence::{PreparedSequence, SequenceStatus, SteppedSequence};
use crate::sources::setpoint_stream::UnderrunPolicy;
use crate::sources::setpoint_stream::{SetpointStream, Underrun};
use crate::sources::waveform::WaveformGenerator;
use crate::sources::SetpointSource;

/// Slots of the setpoint queue (`heapless` keeps one free: [`SETPOINT_CAPACITY`] setpoints
/// fit). 20 000 slots, 40 008 bytes with the indices: 200 ms at 100 kHz (400 ms at 50 kHz),
/// divider 1 — several round trips of a USB–serial adapter (whose latency timer holds bytes
/// up to 16 ms each way) plus the host's scheduling. On the board it lives in CCM RAM
/// (`hardware::ccm::setpoint_queue`), taken from the recorder's CCM part. The
/// emulator image (QEMU models no CCM) keeps 1 536 slots in SRAM: 15 ms at 100 kHz.
pub const SETPOINT_QUEUE_LEN: usize = if cfg!(feature = "emulator") {
    EMULATOR_SETPOINT_QUEUE_LEN
} else {
    20_000
};
/// Slots of the setpoint queue in the QEMU image: 1 536 in SRAM (QEMU's `netduinoplus2`
/// models no CCM RAM), 1 535 setpoints, 15 ms at 100 kHz. The dual-stage QEMU image has the
/// least static RAM to spare of all images (`memory.x`'s stack reserve): its queue is what
/// gives, not the board's.
pub const EMULATOR_SETPOINT_QUEUE_LEN: usize = 1536;
/// Setpoints the queue holds: the credits of an empty queue.
pub const SETPOINT_CAPACITY: usize = SETPOINT_QUEUE_LEN - 1;
/// The setpoint queue between the handler (producer) and the tick (consumer): Q1.15 wire
/// samples.
pub type SetpointQueue = Queue<i16, SETPOINT_QUEUE_LEN>;

/// Under the ramp-to-bias underrun policy, a ramp over the full stroke (2.0 in normalised
/// displacement) takes this many ticks (20 ms at 50 kHz); the drive's slew limit still holds.
pub const RAMP_TICKS_FULL_STROKE: i32 = 1000;

/// Counters and state the status report carries, read in one short critical section.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Telemetry {
    /// Ticks run.
    pub ticks: u32,
    /// Ticks the running stream found the queue empty (held or ramped).
    pub underruns: u32,
    /// Ticks that did not finish before the next was due (counted by the board's timer).
    pub overruns: u32,
    /// Ticks a range or slew limit clipped the drive.
    pub limit_hits: u32,
    /// Whether the stream consumes the queue.
    pub streaming: bool,
    /// Whether the waveform generator runs.
    pub waveform: bool,
    /// Whether a scan runs (its approach or its pattern; not once its last frame is done).
    pub scanning: bool,
    /// Whether the external trigger input is armed.
    pub trigger_armed: bool,
    /// Whether a TTL-stepped sequence is armed.
    pub sequence: bool,
    /// Whether the analog input is the setpoint source.
    pub analog: bool,
    /// Whether the analog input is lost or over-range (while it runs).
    pub analog_fault: bool,
    /// Whether the coarse axis owns the piezo's setpoint ([`ControlLoop::coarse_owns_setpoint`]).
    pub coarse: bool,
}

/// Everything the control interrupt owns. `C` is a handle on a
/// [`Controller`] (`&'static mut Controller` on the board, `Box<Controller>` on the host): the
/// loop runs one, and passes a second back and forth with the command handler.
///
/// `repr(C)` with the learning's 16 KiB of tables **last** but for the coarse link (which only
/// the coarse ramp's ticks read): left to itself the compiler may place them first, and every
/// other field's offset then exceeds the 4 095 bytes a Thumb-2 load reaches in one instruction
/// (the whole-interrupt bench saw +27 instructions a tick).
#[derive(Debug)]
#[repr(C)]
pub struct ControlLoop<C> {
    controller: C,
    /// Where the setpoint comes from: one source at a time, switched only by the loop's
    /// command methods.
    source: SetpointSource,
    /// The controller a swap retired (or the one the handler has not taken yet): the spare.
    spare: Option<C>,
    /// Counts of the controllers retired and taken back (the totals less the running one's and
    /// the spare's).
    counted: ControlCounters,
    /// Configurations swapped in since start-up.
    swaps: u32,
    stream: SetpointStream,
    underrun: UnderrunPolicy,
    waveform: bool,
    overruns: u32,
    limit_hits: u32,
    control_rate_hz: u32,
    /// The recorder's trigger events since the last snapshot (a start commanded between two
    /// ticks, the external edge seen in this one): they travel with the next snapshot.
    events: Events,
    /// The next snapshot's sequence number: snapshots pushed (or refused) since start-up,
    /// wrapping.
    seq: u32,
    /// The services listen: a capture or a record is armed or running, or telemetry runs
    /// ([`ControlLoop::listen`]). Only then does the tick push its snapshot and wake them.
    listening: bool,
    /// The scan (protocol v6), running or waiting for the external trigger.
    scan: Option<ScanGenerator>,
    /// The scan waits for the external trigger.
    scan_pending: bool,
    /// The pixel, line and frame outputs' pulse stretcher.
    outputs: TriggerOutputs,
    /// The external trigger input's edge detector.
    external: ExternalTrigger,
    /// The trigger input's level, as the board last sampled it.
    input: bool,
    /// The external trigger also starts the stream.
    stream_on_trigger: bool,
    /// The trigger outputs' levels the last tick left (bit 0 pixel, 1 line, 2 frame).
    levels: u8,
    /// The TTL-stepped sequence ([`crate::sources::sequence`]): while armed, the setpoint source.
    sequence: SteppedSequence,
    /// The analog setpoint input ([`crate::sources::analog_input`]): while running, the setpoint source.
    analog: AnalogInput,
    /// A watchdog drill is on: the tick no longer feeds the watchdog, which resets the board
    /// ([`ControlLoop::drill_watchdog`]).
    drilling: bool,
    /// The learning's tick half: the correction table it plays, the errors it stores
    /// ([`crate::services::learning`]). After every field the tick reads on every tick: see
    /// the type's doc, and the assertion after it.
    learning: LearnTick,
    /// The coarse axis's mailbox: once the coarse task (in the dual-stage images) has posted a
    /// ramp, the piezo's setpoint comes from it ([`SetpointSource::Coarse`]). Never attached
    /// in the other images. Behind the learning's tables: only that source's ticks read it
    /// (an address computed first), and every other field keeps its one-instruction offset.
    coarse: crate::dual_stage::CoarseLink,
}

// The learning's tables come after every field the tick reads on every tick, each within a
// one-instruction load's reach (a field placed after them would cost every tick an extra
// instruction for each of its accesses); only the coarse link, which no other source's tick
// reads, follows them.
const _: () = {
    type Board = ControlLoop<&'static mut Controller>;
    let end = core::mem::offset_of!(Board, learning) + core::mem::size_of::<LearnTick>();
    assert!(core::mem::offset_of!(Board, coarse) >= end);
    assert!(
        end + core::mem::size_of::<crate::dual_stage::CoarseLink>() + 8
            > core::mem::size_of::<Board>()
    );
    assert!(core::mem::offset_of!(Board, learning) < 1024);
};

impl<C> ControlLoop<C>
where
    C: DerefMut<Target = Controller>,
{
    /// The loop at rest on `controller`, with `spare` for the handler's reloads: stream
    /// stopped (holding the setpoint), divider 1, underrun policy hold.
    pub fn new(controller: C, spare: C, control_rate_hz: u32) -> Self {
        let stream = SetpointStream::new(controller.setpoint());
        Self {
            controller,
            source: SetpointSource::Stream,
            spare: Some(spare),
            counted: ControlCounters::default(),
            swaps: 0,
            stream,
            underrun: UnderrunPolicy::Hold,
            waveform: false,
            overruns: 0,
            limit_hits: 0,
            control_rate_hz,
            events: Events::NONE,
            seq: 0,
            listening: false,
            learning: LearnTick::new(),
            coarse: crate::dual_stage::CoarseLink::new(),
            scan: None,
            scan_pending: false,
            outputs: TriggerOutputs::new(1),
            external: ExternalTrigger::new(),
            input: false,
            stream_on_trigger: false,
            levels: 0,
            sequence: SteppedSequence::new(),
            analog: AnalogInput::new(),
            drilling: false,
        }
    }

    /// One tick (see the module doc) with the DAC and the ADC as two handles.
    #[inline]
    pub fn tick<const N: usize, A: SensorAdc, D: DualDac>(
        &mut self,
        queue: &mut Consumer<'_, i16, N>,
        snapshots: &mut SnapshotProducer<'_>,
        adc: &mut A,
        dac: &mut D,
    ) -> TickReport {
        if self.external.poll(self.input) {
            crate::rare();
            self.fire_external();
        }
        // One source at a time, one dispatch: the stream (the common tick) goes straight to
        // the queue below.
        let (scanned, events) = match self.source {
            SetpointSource::Stream => (None, 0),
            SetpointSource::Scan => {
                // The other sources are charged apart (`tick_budget::source_cycles`): out of
                // line, so that the stream's tick takes no branch here.
                crate::rare();
                self.scan_tick()
            }
            SetpointSource::Sequence => {
                crate::rare();
                (Some(self.sequence_tick(queue)), 0)
            }
            SetpointSource::Analog => {
                crate::rare();
                (Some(self.analog_tick(adc)), 0)
            }
            SetpointSource::Coarse => {
                crate::rare();
                (Some(self.coarse.next_setpoint()), 0)
            }
        };
        let setpoint = match scanned {
            Some(x) => Some(x),
            None => self.stream.next(queue),
        };
        // Learning off (the common case) costs one compare here and one below; the
        // controller's correction was zeroed when it was turned off (and a prepared controller
        // starts at zero).
        let learning = self.learning.is_on();
        if learning {
            // The learning's ticks are charged apart (`tick_budget::LEARNING_CYCLES`): out of
            // line, so that the tick without it takes no branch here, nor below.
            crate::rare();
            self.controller.set_learned(self.learning.correction());
        }
        let mut report = self.controller.tick(setpoint, adc, dac);
        self.levels = self.outputs.tick(events);
        report.triggers = self.levels | if self.input { INPUT } else { 0 };
        if learning {
            crate::rare();
            // The error the learning stores: only a reading of a sensor the configuration has.
            let measured = (self.controller.sensor_config().is_some()
                && !report.flags.contains(TickFlags::ADC_ERROR))
            .then_some(report.measured);
            self.learning.observe(self.controller.target(), measured);
        }
        if report.flags.0 & (TickFlags::RANGE_LIMIT | TickFlags::SLEW_LIMIT) != 0 {
            self.limit_hits = self.limit_hits.wrapping_add(1);
        }
        // While the services listen, one snapshot for them (the recorder, telemetry's tap):
        // a fixed-size copy. A full ring refuses it; the sequence number's gap tells the
        // consumer ([`crate::services::consumer::Services::consume`]).
        if self.listening {
            // What the tick aimed the stage at (with the preview, four ticks late).
            let setpoint = self.controller.target();
            let _ = snapshots.enqueue(Snapshot::of(
                self.seq,
                setpoint,
                &report,
                self.events,
                self.swaps as u8,
            ));
            self.seq = self.seq.wrapping_add(1);
        }
        self.events = Events::NONE;
        report
    }

    /// Whether the services' consumer is due: while they listen, one wake every [`BATCH`]
    /// snapshots (the tick's caller pends it).
    #[inline(always)]
    pub fn services_due(&self) -> bool {
        self.listening && self.seq % BATCH == 0
    }

    /// Whether the tick hands its snapshots to the services (see [`ControlLoop::listen`]).
    pub fn is_listening(&self) -> bool {
        self.listening
    }

    /// Starts (`true`) or stops handing the services a snapshot a tick. The command handler
    /// turns it on before it arms a capture or a record or starts telemetry (so that the
    /// tick that arms it is served), and off once the services are idle again: while nothing
    /// listens, the tick pushes nothing and the services' task is never woken, and the tick
    /// budget charges them ([`crate::config::tick_budget::ServicesLoad`]) only while they
    /// listen. Snapshots are numbered by push, so the pause leaves no gap.
    pub fn listen(&mut self, on: bool) {
        self.listening = on;
    }

    /// The scan's setpoint and events this tick (the source is the scan, running: not waiting
    /// for its trigger).
    #[inline(always)]
    fn scan_tick(&mut self) -> (Option<i32>, u8) {
        match self.scan.as_mut() {
            Some(g) => {
                let s = g.next_sample();
                (Some(s.x), s.events)
            }
            None => (None, 0),
        }
    }

    /// The sequence's setpoint this tick (armed): an edge on the input pops the next
    /// position ([`SteppedSequence::next`]).
    #[inline(always)]
    fn sequence_tick<const N: usize>(&mut self, queue: &mut Consumer<'_, i16, N>) -> i32 {
        let position = self.controller.position();
        self.sequence.next(self.input, position, queue)
    }

    /// The analog input's setpoint this tick (running): the input's conversion, scaled,
    /// filtered and checked ([`AnalogInput::next`]).
    #[inline(always)]
    fn analog_tick<A: SensorAdc>(&mut self, adc: &mut A) -> i32 {
        let rest = self.controller.rest_setpoint();
        self.analog.next(adc.setpoint_input(), rest)
    }

    /// Makes the analog input the setpoint source with `prepared` (checked and prepared by
    /// the caller, [`crate::sources::analog_input::AnalogInputConfig::prepare`]): the stream, the
    /// waveform, a scan or a sequence stops, and the setpoint walks from where it is to the
    /// input's value at the configured rate.
    pub fn start_analog(&mut self, prepared: PreparedInput) {
        self.stop();
        let from = self.controller.setpoint();
        self.analog.start(prepared, from);
        self.source = SetpointSource::Analog;
    }

    /// Starts a watchdog drill: from the next tick on the tick stops feeding the watchdog,
    /// which resets the board within [`crate::board::WATCHDOG_TIMEOUT_MS`] while the control
    /// law keeps running until then (the outputs hold where they are). Irreversible short of
    /// the reset: what a real hang would do, on purpose, to prove the watchdog is armed.
    pub fn drill_watchdog(&mut self) {
        self.drilling = true;
    }

    /// Whether the tick feeds the watchdog (it does unless a drill is on).
    #[inline(always)]
    pub fn feeds_watchdog(&self) -> bool {
        !self.drilling
    }

    /// The analog input's state and counts.
    pub fn analog_status(&self) -> AnalogStatus {
        self.analog.status()
    }

    /// Stops the analog input: the stream (stopped) holds where it left the setpoint.
    fn end_analog(&mut self) {
        if self.analog.is_running() {
            self.analog.stop();
            self.source = SetpointSource::Stream;
            self.stream.hold_at_if_stopped(self.controller.setpoint());
        }
    }

    /// Arms a TTL-stepped sequence ([`crate::sources::sequence`]; `config` checked and
    /// prepared by the caller, [`crate::sources::sequence::SequenceConfig::prepare`]) over the
    /// positions queued: the stream, the waveform or a scan stops, and the stage holds until
    /// the first edge.
    pub fn arm_sequence(&mut self, config: &PreparedSequence) {
        self.stop();
        let from = self.controller.setpoint();
        self.sequence.arm(config, from, self.input);
        self.source = SetpointSource::Sequence;
    }

    /// The sequence's state and counts.
    pub fn sequence_status(&self) -> SequenceStatus {
        self.sequence.status()
    }

    /// The external trigger's armed edge came (on the tick): starts the scan waiting for it
    /// (from the setpoint in force: no step), the stream if asked (neither while a watchdog
    /// drill is on: its reset would cut them off), and fires a capture armed on it. O(1).
    #[inline(never)] // rare: kept out of the tick's common path
    fn fire_external(&mut self) {
        if self.drilling {
            // The watchdog resets the board within its timeout: no source starts to be cut
            // off mid-motion (a capture still fires).
        } else if self.scan_pending {
            self.scan_pending = false;
            let from = self.controller.setpoint();
            if let Some(g) = self.scan.as_mut() {
                g.start(from);
                self.source = SetpointSource::Scan;
            }
            self.learning.restart();
            self.events.add(Trigger::ScanStart);
        } else if self.stream_on_trigger {
            self.start();
        }
        self.events.add(Trigger::External);
    }

    /// The board's trigger input level, sampled before each tick (the tick looks for the
    /// armed edge in it).
    #[inline(always)]
    pub fn set_trigger_input(&mut self, level: bool) {
        self.input = level;
    }

    /// The trigger outputs' levels after the last tick (bit 0 pixel, 1 line, 2 frame: see
    /// [`crate::sources::scan`]), for the board to write to its pins.
    #[inline(always)]
    pub fn trigger_levels(&self) -> u8 {
        self.levels | self.sequence.level()
    }

    /// Applies trigger I/O settings: the pulse width, and arms (or disarms) the input.
    pub fn set_trigger(&mut self, config: TriggerConfig) {
        self.outputs.set_width(config.pulse_ticks);
        self.external.arm(config.input, self.input);
        self.stream_on_trigger = config.start_stream;
    }

    /// The trigger outputs' pulse width, ticks (what a scan's pixel clock must exceed).
    pub fn trigger_pulse_ticks(&self) -> u16 {
        self.outputs.width()
    }

    /// Times the external trigger fired since power-up.
    pub fn trigger_fired(&self) -> u32 {
        self.external.fired()
    }

    /// Whether a source waits for the trigger input's armed edge to start it: a scan armed
    /// on it, or the stream (what a lab's camera, started after the arming, would trigger).
    pub fn waits_for_trigger(&self) -> bool {
        self.external.is_armed() && (self.scan_pending || self.stream_on_trigger)
    }

    /// Runs `scan` (validated, [`ScanGenerator::new`]) instead of the stream or the
    /// waveform: now, from the setpoint in force (its approach walks from there), or, with
    /// `on_trigger`, when the armed external trigger fires (the setpoint holds meanwhile).
    pub fn scan(&mut self, mut scan: ScanGenerator, on_trigger: bool) {
        self.end_sequence();
        self.end_analog();
        self.waveform = false;
        self.stream.stop();
        self.stream.hold_at_if_stopped(self.controller.setpoint());
        if !on_trigger {
            scan.start(self.controller.setpoint());
            self.learning.restart();
            self.events.add(Trigger::ScanStart);
        }
        self.scan = Some(scan);
        self.scan_pending = on_trigger;
        // Waiting for its trigger, the scan is not the source yet: the stopped stream holds.
        self.source = if on_trigger {
            SetpointSource::Stream
        } else {
            SetpointSource::Scan
        };
    }

    /// Ends a scan (running, done or waiting): the stream holds where the scan left the
    /// setpoint.
    fn end_scan(&mut self) {
        self.scan_pending = false;
        if self.source == SetpointSource::Scan {
            self.source = SetpointSource::Stream;
        }
        if self.scan.take().is_some() {
            self.stream.hold_at_if_stopped(self.controller.setpoint());
        }
    }

    /// What runs beside the controller and costs the tick, as the tick budget charges it
    /// ([`Beside`]): the learning (playing or learning), a scan (running, or waiting for its
    /// trigger: the edge starts it), the analog input, an armed sequence, the armed trigger
    /// input (the services' load is the command handler's to add: they are not the loop's).
    pub fn beside(&self) -> Beside {
        Beside {
            learning: self.learning.state() != LearnState::Off,
            // A scan waiting for its trigger is charged as running: the edge starts it.
            source: if self.scan_pending {
                SetpointSource::Scan
            } else {
                self.source
            },
            coarse_task: self.coarse.task_share(),
            trigger: self.external.is_armed(),
            // The services are not the loop's: the command handler adds what they run.
            services: Default::default(),
        }
    }

    /// Whether a scan runs (its approach or its pattern, not yet done).
    pub fn is_scanning(&self) -> bool {
        !self.scan_pending && self.scan.as_ref().is_some_and(|g| !g.is_done())
    }

    /// The scan (running, done or waiting), for the host's simulated board to inspect.
    pub fn scan_generator(&self) -> Option<&ScanGenerator> {
        self.scan.as_ref()
    }

    /// The coarse axis's mailbox, for the handler's short lock (attached only in the
    /// dual-stage images).
    pub fn coarse(&mut self) -> &mut crate::dual_stage::CoarseLink {
        &mut self.coarse
    }

    /// Attaches the coarse task (the dual-stage images, at boot; `task` prepared off the
    /// lock at this loop's control rate, [`crate::dual_stage::PreparedCoarse::new`]): its
    /// limits, its status, and its share of each tick, which the tick budget charges from
    /// then on. Whether the configuration in force leaves the task its share is the caller's
    /// check ([`crate::config::tick_budget::check_with`], as `hardware::setup` does at boot);
    /// the command handler checks every load and start against it from then on.
    pub fn attach_coarse(&mut self, task: &crate::dual_stage::PreparedCoarse) {
        self.coarse.attach(task);
    }

    /// The coarse task's first exchange (once per coarse period, under the tick's lock): the
    /// handler's pending command, taken, and where the piezo is as the tick knows it
    /// ([`Controller::position`]: the sensor's last reading; `None` without a sensor).
    pub fn take_coarse(&mut self) -> crate::dual_stage::CoarseTake {
        let released = self.coarse.is_piezo_released();
        let (command, engages) = self.coarse.take();
        let measured = if self.controller.sensor_config().is_some() {
            Some(self.controller.position())
        } else if released {
            // Handed back, the piezo moves on its own sources: without a sensor, its setpoint
            // is the best reading of it the carriage estimate can subtract.
            Some(self.controller.setpoint())
        } else {
            None
        };
        crate::dual_stage::CoarseTake {
            command,
            measured,
            resume_fine: engages.then(|| self.controller.setpoint()),
        }
    }

    /// The coarse task's post (once per coarse period, under the tick's lock): the period's
    /// fine setpoints (ramping from the setpoint the tick uses now) and the status. The first
    /// post makes the coarse axis the setpoint source ([`SetpointSource::Coarse`]): whatever ran
    /// before stops, and the handler refuses the other sources from then on
    /// ([`ControlLoop::coarse_owns_setpoint`]). A post without an attached task
    /// ([`ControlLoop::attach_coarse`]) is ignored: no task is charged, none drives the
    /// setpoint. See [`crate::dual_stage::link`].
    pub fn post_coarse(
        &mut self,
        fine: &crate::dual_stage::FineSetpoints,
        status: crate::dual_stage::CoarseStatus,
    ) {
        if !self.coarse.is_attached() {
            return;
        }
        let current = self.controller.setpoint();
        // Handed back ([`ControlLoop::release_piezo`]): the status only.
        if self.coarse.post(current, fine, status) && self.source != SetpointSource::Coarse {
            self.stop();
            // An input edge armed to start the stream would start nothing now.
            self.stream_on_trigger = false;
            self.source = SetpointSource::Coarse;
        }
    }

    /// Hands the piezo's setpoint back from the coarse axis to the loop's own sources, the
    /// coarse task running on (attached and charged: it still reads the encoders and the
    /// switches and holds the carriage): the stream, stopped, holds where the ramp left the
    /// setpoint, and the stream, the waveform, scans, sequences and the analog input may
    /// start again. The coarse task's next motion command engages the piezo again
    /// ([`crate::dual_stage::CoarseLink::take`]). The handler asks it only of an axis at rest.
    pub fn release_piezo(&mut self) {
        self.coarse.release_piezo();
        self.end_coarse_ramp();
    }

    /// Where the coarse ramp is the setpoint source, hands the setpoint to the stream,
    /// stopped, holding where the ramp left it.
    fn end_coarse_ramp(&mut self) {
        if self.source == SetpointSource::Coarse {
            self.source = SetpointSource::Stream;
            self.stream.stop();
            self.stream.hold_at_if_stopped(self.controller.setpoint());
        }
    }

    /// Whether one of the piezo's own sources runs or waits to start (the stream or the
    /// waveform, a scan running or waiting for its edge, an armed sequence, the analog input,
    /// the stream armed to start on the input's edge): what engaging the coarse axis again
    /// would cut off.
    pub fn piezo_source_busy(&self) -> bool {
        self.is_running()
            || self.scan_pending
            || (self.stream_on_trigger && self.external.is_armed())
    }

    /// Detaches the coarse task and hands the piezo's setpoint back: the stream, stopped,
    /// holds where the ramp left it, the other sources may start again, and the task is no
    /// longer charged; its posts are ignored until it is attached again.
    pub fn release_coarse(&mut self) {
        self.coarse.release();
        self.end_coarse_ramp();
    }

    /// Whether the coarse axis owns the piezo's setpoint (its task has posted a ramp, and the
    /// piezo is not handed back; or a motion command that engages it again waits for the
    /// task): the stream, the waveform, a scan, a sequence and the analog input are refused.
    pub fn coarse_owns_setpoint(&self) -> bool {
        self.source == SetpointSource::Coarse || self.coarse.is_engaging()
    }

    /// The spare controller, for the handler to prepare a reload in (outside any lock): the
    /// one the last swap retired. `None` only while the handler already holds it.
    pub fn spare(&mut self) -> Option<C> {
        let mut spare = self.spare.take()?;
        self.counted = self.counted.plus(spare.take_counters());
        Some(spare)
    }

    /// Configurations swapped in since start-up (loads and recalls that took effect).
    pub fn swaps(&self) -> u32 {
        self.swaps
    }

    /// The counters since start-up: the running controller's, the spare's, and those of the
    /// controllers before them.
    pub fn counters(&self) -> ControlCounters {
        let spare = self
            .spare
            .as_ref()
            .map(|s| s.counters())
            .unwrap_or_default();
        self.counted.plus(self.controller.counters()).plus(spare)
    }

    /// Swaps a prepared controller in, between two ticks (the caller holds the lock that
    /// keeps the tick out): O(1), a pointer and a few words ([`Controller::take_over`]). The
    /// controller it replaces becomes the spare.
    pub fn post(&mut self, mut prepared: C) {
        prepared.take_over(&self.controller);
        let old = core::mem::replace(&mut self.controller, prepared);
        self.spare = Some(old);
        self.swaps = self.swaps.wrapping_add(1);
        // The rest position moves with the configuration (prepared with it), and a stopped
        // stream holds where the new configuration puts the stage.
        self.stream.move_rest(self.controller.rest_setpoint());
        self.stream.hold_at_if_stopped(self.controller.setpoint());
    }

    /// Gives a spare back unused (a reload refused after [`ControlLoop::spare`]).
    pub fn give_back(&mut self, spare: C) {
        self.spare = Some(spare);
    }

    /// Switches the mode between two ticks (O(1), see [`Controller::set_mode`]).
    pub fn set_mode(&mut self, mode: Mode) -> Result<(), ModeError> {
        self.controller.set_mode(mode)
    }

    /// Counts a tick that overran (the board's timer sees the next one already due).
    pub fn count_overrun(&mut self) {
        self.overruns = self.overruns.wrapping_add(1);
    }

    /// Starts consuming the setpoint queue (stopping the waveform generator).
    pub fn start(&mut self) {
        self.waveform = false;
        self.end_scan();
        self.end_sequence();
        self.end_analog();
        self.stream.start();
        self.learning.restart();
        self.events.add(Trigger::StreamStart);
    }

    /// Stops the stream or the waveform: the setpoint holds; queued setpoints stay queued.
    pub fn stop(&mut self) {
        self.waveform = false;
        self.stream.stop();
        self.end_scan();
        self.end_sequence();
        self.end_analog();
    }

    /// Disarms a sequence: the stream (stopped) holds where the sequence left the setpoint.
    fn end_sequence(&mut self) {
        if self.sequence.is_armed() {
            self.sequence.disarm();
            self.source = SetpointSource::Stream;
            self.stream.hold_at_if_stopped(self.controller.setpoint());
        }
    }

    /// Plays what is queued, then stops the stream (no underruns counted after its end).
    pub fn finish(&mut self) {
        self.stream.finish();
    }

    /// Ticks per streamed setpoint (interpolated in between); 0 is refused (`false`).
    pub fn set_divider(&mut self, divider: u16) -> bool {
        self.stream.set_divider(divider)
    }

    /// The underrun policy; ramp-to-bias ramps to the rest position of the configuration in
    /// force at [`RAMP_TICKS_FULL_STROKE`].
    pub fn set_underrun(&mut self, policy: UnderrunPolicy) {
        self.underrun = policy;
        let underrun = match policy {
            UnderrunPolicy::Hold => Underrun::Hold,
            UnderrunPolicy::RampToBias => Underrun::RampToRest {
                rest: self.controller.rest_setpoint(),
                step: ((2i64 << 30) / RAMP_TICKS_FULL_STROKE as i64) as i32,
            },
        };
        // The step is a positive constant, so the stream accepts it.
        let _ = self.stream.set_underrun(underrun);
    }

    /// Plays `waveform` instead of the queue, from the next tick.
    pub fn play(&mut self, waveform: WaveformGenerator) {
        self.end_scan();
        self.end_sequence();
        self.end_analog();
        self.waveform = true;
        self.stream.play(waveform);
        self.learning.restart();
        self.events.add(Trigger::WaveformStart);
    }

    /// Counters and state for the status report.
    pub fn telemetry(&self) -> Telemetry {
        let c = self.counters();
        Telemetry {
            ticks: c.ticks,
            underruns: c.underruns.wrapping_add(self.stream.ramp_underruns()),
            overruns: self.overruns,
            limit_hits: self.limit_hits,
            streaming: self.stream.is_running() && !self.waveform,
            waveform: self.waveform,
            scanning: self.is_scanning(),
            trigger_armed: self.external.is_armed(),
            sequence: self.sequence.is_armed(),
            analog: self.analog.is_running(),
            analog_fault: {
                let a = self.analog.status();
                a.running && (a.lost || a.over_range)
            },
            coarse: self.coarse_owns_setpoint(),
        }
    }

    /// Whether the stream, the waveform generator, a scan, a sequence or the analog input is
    /// running.
    pub fn is_running(&self) -> bool {
        self.stream.is_running()
            || self.is_scanning()
            || self.sequence.is_armed()
            || self.analog.is_running()
    }

    /// Whether a source other than the analog input runs (the stream, the waveform, a scan or
    /// a sequence): what an analog start is refused for.
    pub fn other_source_running(&self) -> bool {
        self.stream.is_running() || self.is_scanning() || self.sequence.is_armed()
    }

    /// The controller (configuration in force, counters).
    pub fn controller(&self) -> &Controller {
        &self.controller
    }

    /// DAC codes of the safe state of the configuration in force, for the fault handlers to
    /// arm.
    pub fn safe_codes(&self) -> (crate::board::DacCode, crate::board::DacCode) {
        self.controller.safe_codes()
    }

    /// Where the stacks are now (board units): what a reload is prepared at.
    pub fn stacks(&self) -> StackVoltages {
        self.controller.stacks()
    }

    /// Control rate, Hz.
    pub fn control_rate_hz(&self) -> u32 {
        self.control_rate_hz
    }

    /// The learning's tick half (state, period, tables, errors).
    pub fn learning(&self) -> &LearnTick {
        &self.learning
    }

    /// The learning's tick half, to configure it or move a table in or errors out (O(1) or one
    /// [`crate::services::learning::CHUNK`] per call: see [`crate::services::learning::service`]).
    pub fn learning_mut(&mut self) -> &mut LearnTick {
        &mut self.learning
    }

    /// Sets the learning's state (off, learning, frozen) between two ticks, in O(1).
    pub fn set_learning(&mut self, state: LearnState) {
        let target = self.controller.target();
        self.learning.set_state(state, target);
        if state == LearnState::Off {
            self.controller.set_learned(0);
        }
    }
}

/// The coarse task's exchanges, called on the loop directly where nothing else runs it
/// concurrently (the simulator, the bench); the board locks the tick around each.
impl<C> crate::dual_stage::LoopExchange for ControlLoop<C>
where
    C: DerefMut<Target = Controller>,
{
    fn take(&mut self) -> crate::dual_stage::CoarseTake {
        self.take_coarse()
    }

    fn post(
        &mut self,
        fine: &crate::dual_stage::FineSetpoints,
        status: crate::dual_stage::CoarseStatus,
    ) {
        self.post_coarse(fine, status);
    }
}

impl<C> LearnHost for ControlLoop<C>
where
    C: DerefMut<Target = Controller>,
{
    fn learning(&self) -> &LearnTick {
        ControlLoop::learning(self)
    }
    fn learning_mut(&mut self) -> &mut LearnTick {
        ControlLoop::learning_mut(self)
    }
    fn set_learning(&mut self, state: LearnState) {
        ControlLoop::set_learning(self, state)
    }
}
