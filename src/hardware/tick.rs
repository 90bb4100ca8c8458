//! The control interrupt's body, shared by the firmware (`src/bin/twinstack-fw.rs`) and the
//! whole-interrupt bench image (`qemu-images`, `irq-bench`), so that the bench measures the
//! very code the board runs: acknowledge the timer, write the trigger outputs the last tick
//! computed (one `BSRR` store: they mark the drive the DAC latched at this timer event), sample
//! the trigger input, [`ControlLoop::tick`] on the board's converters (its snapshot pushed
//! for the services), feed the watchdog (unless a drill stopped it:
//! [`ControlLoop::feeds_watchdog`]), count an overrun.
//!
//! The services ([`Services`]: the recorder, telemetry's tap) are the [`ServiceSide`]
//! resource, run by a priority-2 task the tick wakes once a batch of snapshots
//! ([`ServiceSide::run`]); the command handler reaches both halves through [`BoardLocks`].

use core::mem::MaybeUninit;
use core::sync::atomic::{AtomicBool, Ordering};

use heapless::spsc::{Consumer, Producer};

use crate::command_handler::Locks;
use crate::control::Controller;
use crate::control_loop::{ControlLoop, SETPOINT_QUEUE_LEN};
use crate::services::consumer::Services;
use crate::services::recorder::{SplitStore, CAPTURE_SLOTS};
use crate::services::snapshot::{SnapshotConsumer, SnapshotProducer};
use crate::services::telemetry::{TelemetrySample, TELEMETRY_QUEUE_LEN};

use super::adc::SensorInput;
use super::control_timer::ControlTimer;
use super::dac::InternalDac;
use super::trigger_pins::TriggerPins;
use super::watchdog::Watchdog;

/// The CCM part of the recorder's buffer: 12 288 slots, 24 KiB of CCM RAM (the setpoint
/// queue takes the other 40 KiB, [`super::ccm::setpoint_queue`]).
pub const HALF_SLOTS: usize = crate::services::recorder::CCM_SLOTS;

/// The SRAM part of the recorder's buffer: 19 456 slots, 38 KiB (the rest of
/// [`CAPTURE_SLOTS`]), so that with the learning's tables, telemetry's queue and the scan
/// every image's static RAM leaves the stack its reserve (`memory.x`).
pub const SRAM_SLOTS: usize = CAPTURE_SLOTS - HALF_SLOTS;

/// The recorder's buffer: 38 KiB of SRAM, then 24 KiB of CCM RAM on the board
/// ([`super::ccm::capture_half`]); QEMU 7.2's `netduinoplus2` models no CCM, so the emulator
/// images pass an empty second part (19 456 slots in all).
pub type RecordBuffer = SplitStore<&'static mut [i16; SRAM_SLOTS], &'static mut [i16]>;

/// The tick's loop on the board: two controllers in statics, passed by pointer between the
/// tick and the command handler.
pub type BoardLoop = ControlLoop<&'static mut Controller>;

/// The services on the board, over the recorder's split buffer.
pub type BoardServices = Services<RecordBuffer>;

/// The loop's home (8 KiB, most of it the learning's tables): a static, written once by
/// [`control_loop`], so that the loop is built where it stays and never sits on the boot's
/// stack, nor is moved through `init`'s return into RTIC's resources.
static mut CONTROL: MaybeUninit<BoardLoop> = MaybeUninit::uninit();

/// Whether [`control_loop`] has handed the loop out (in `.bss`: zeroed at start-up).
static CONTROL_TAKEN: AtomicBool = AtomicBool::new(false);

/// The loop at rest ([`ControlLoop::new`]), built in its static: `Some` the first time,
/// `None` after.
pub fn control_loop(
    controller: &'static mut Controller,
    spare: &'static mut Controller,
    control_rate_hz: u32,
) -> Option<&'static mut BoardLoop> {
    if CONTROL_TAKEN.swap(true, Ordering::AcqRel) {
        return None;
    }
    // SAFETY: `CONTROL_TAKEN` lets exactly one caller through, so this is the only reference
    // to the static ever made; it is initialised before it is handed out.
    let slot = unsafe { &mut *core::ptr::addr_of_mut!(CONTROL) };
    Some(slot.write(ControlLoop::new(controller, spare, control_rate_hz)))
}

/// Everything the control interrupt owns: the converters, the timer and the queues by value,
/// the loop (8 KiB) by reference to its static ([`control_loop`]), so that the resource RTIC
/// moves out of `init` is a few hundred bytes, not the loop.
#[repr(C)]
pub struct ControlTick {
    /// The sensor's ADC.
    pub adc: SensorInput,
    /// Both stacks' DAC channels.
    pub dac: InternalDac,
    /// The control timer (TIM2 on the board, SysTick in the emulator).
    pub timer: ControlTimer,
    /// The independent watchdog.
    pub watchdog: Watchdog,
    /// The setpoint queue's consumer end.
    pub setpoints: Consumer<'static, i16, SETPOINT_QUEUE_LEN>,
    /// The snapshot ring's producer end (one snapshot a tick, for the services).
    pub snapshots: SnapshotProducer<'static>,
    /// The trigger I/O pins (pixel, line, frame outputs; the external trigger input).
    pub triggers: TriggerPins,
    /// The loop: setpoint sources, controller ([`control_loop`]).
    pub control: &'static mut BoardLoop,
}

/// Whom a tick wakes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Wake {
    /// The services' consumer: a batch of snapshots is in the ring.
    pub services: bool,
    /// The command task: a learning period ended ([`crate::services::learning::service`]).
    pub command: bool,
}

impl ControlTick {
    /// One tick. No allocation, no panic path, no loop. Returns whom to wake: the services'
    /// consumer once every [`crate::services::snapshot::BATCH`] ticks, the command task at a
    /// learning period's end. The caller pends them.
    #[inline(always)]
    pub fn run(&mut self) -> Wake {
        // The loop's address read once, into a register: read through `self` after each of
        // the queues' atomic operations, it would be loaded again (the tick cost 15–20
        // instructions more than with the loop held by value).
        let control = &mut *self.control;
        self.timer.acknowledge();
        // The trigger outputs the last tick computed, first: they mark the drive that tick
        // wrote, which the DAC put out at this tick's timer event. Written here, their instant
        // is the interrupt's entry, whatever this tick goes on to run — not the end of the
        // control law.
        self.triggers.write(control.trigger_levels());
        control.set_trigger_input(self.triggers.input());
        control.tick(
            &mut self.setpoints,
            &mut self.snapshots,
            &mut self.adc,
            &mut self.dac,
        );
        if control.feeds_watchdog() {
            self.watchdog.feed();
        }
        if self.timer.next_tick_already_due() {
            control.count_overrun();
        }
        let learning = control.learning();
        Wake {
            services: control.services_due(),
            command: learning.is_on() && learning.bin() == 0,
        }
    }
}

/// The services' resource: the recorder and telemetry's tap with the snapshot ring's consumer
/// end and the telemetry queue's producer end. Run by a priority-2 task the tick wakes; the
/// command handler takes it through [`BoardLocks`], a lock that never masks the tick.
pub struct ServiceSide {
    /// The recorder and telemetry's tap.
    pub services: BoardServices,
    /// The snapshot ring's consumer end.
    pub snapshots: SnapshotConsumer<'static>,
    /// The telemetry queue's producer end (the tap's samples, for the command task's packer).
    pub telemetry: Producer<'static, TelemetrySample, TELEMETRY_QUEUE_LEN>,
}

impl ServiceSide {
    /// Serves every snapshot in the ring ([`Services::consume`]); returns whether to wake the
    /// packer (a telemetry frame's worth of samples queued since its last wake).
    #[inline(always)]
    pub fn run(&mut self) -> bool {
        self.services
            .consume(&mut self.snapshots, &mut self.telemetry)
    }

    /// The services' task's turn: one batch of snapshots served
    /// ([`Services::consume_at_most`]). Returns whether to wake the packer, and whether the
    /// ring holds more (the task is to run again).
    #[inline(always)]
    pub fn run_batch(&mut self) -> (bool, bool) {
        let wake = self.services.consume_at_most(
            crate::services::snapshot::BATCH as usize,
            &mut self.snapshots,
            &mut self.telemetry,
        );
        (wake, self.snapshots.ready())
    }
}

/// The command handler's locks on the board's two halves ([`Locks`]): RTIC's lock on the tick
/// resource (`M`), handing on only the loop, and on the services' resource (`S`), which serves
/// the snapshot ring before handing on the services.
pub struct BoardLocks<M, S> {
    /// The tick's resource.
    pub tick: M,
    /// The services' resource.
    pub services: S,
}

impl<M, S> Locks for BoardLocks<M, S>
where
    M: rtic_core::Mutex<T = ControlTick>,
    S: rtic_core::Mutex<T = ServiceSide>,
{
    type Controller = &'static mut Controller;
    type Store = RecordBuffer;

    fn lock<R>(&mut self, f: impl FnOnce(&mut BoardLoop) -> R) -> R {
        self.tick.lock(|t| f(t.control))
    }

    fn lock_services<R>(&mut self, f: impl FnOnce(&mut BoardServices) -> R) -> R {
        self.services.lock(|s| {
            // The packer is the caller: it looks for due frames itself.
            let _ = s.run();
            f(&mut s.services)
        })
    }

    fn peek_services<R>(&mut self, f: impl FnOnce(&BoardServices) -> R) -> R {
        self.services.lock(|s| f(&s.services))
    }
}
