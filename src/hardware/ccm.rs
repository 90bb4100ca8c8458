//! The STM32F405's 64 KiB of core-coupled memory (CCM RAM, 0x1000_0000): reachable by the core
//! only (no DMA), zero wait states, and otherwise unused by the image. It holds the setpoint
//! queue ([`setpoint_queue`]: 40 008 bytes, only the core touches it), the second part of the
//! recorder's capture buffer ([`capture_half`]: 24 KiB) and the snapshot ring from the tick to
//! the services ([`snapshot_ring`]: 776 bytes, core only); 65 360 of its 65 536 bytes, so that
//! SRAM keeps room beside the stack's reserve for the dual-stage image.
//!
//! `memory.x` places the `.ccmram` input sections there as a NOLOAD output section: the
//! start-up code neither copies nor zeroes it, so the buffer is zeroed here, once, when it is
//! taken.

use core::mem::MaybeUninit;
use core::sync::atomic::{AtomicBool, Ordering};

use super::tick::HALF_SLOTS;
use crate::control_loop::SetpointQueue;
use crate::services::snapshot::SnapshotRing;

#[link_section = ".ccmram"]
static mut CAPTURE_HALF: MaybeUninit<[i16; HALF_SLOTS]> = MaybeUninit::uninit();

#[link_section = ".ccmram"]
static mut SETPOINT_QUEUE: MaybeUninit<SetpointQueue> = MaybeUninit::uninit();

#[link_section = ".ccmram"]
static mut SNAPSHOT_RING: MaybeUninit<SnapshotRing> = MaybeUninit::uninit();

/// Whether [`capture_half`] has handed the buffer out (in `.bss`: zeroed at start-up).
static TAKEN: AtomicBool = AtomicBool::new(false);

/// Whether [`setpoint_queue`] has handed the queue out.
static QUEUE_TAKEN: AtomicBool = AtomicBool::new(false);

/// Whether [`snapshot_ring`] has handed the ring out.
static RING_TAKEN: AtomicBool = AtomicBool::new(false);

/// The snapshot ring in CCM RAM, empty: `Some` the first time, `None` after.
pub fn snapshot_ring() -> Option<&'static mut SnapshotRing> {
    // SAFETY: `SNAPSHOT_RING` is reached only here; it is initialised (an empty ring) before
    // it is handed out.
    let slot = unsafe { take_once(&RING_TAKEN, core::ptr::addr_of_mut!(SNAPSHOT_RING)) }?;
    Some(slot.write(SnapshotRing::new()))
}

/// The setpoint queue in CCM RAM, empty: `Some` the first time, `None` after.
pub fn setpoint_queue() -> Option<&'static mut SetpointQueue> {
    // SAFETY: `SETPOINT_QUEUE` is reached only here; it is initialised (an empty queue)
    // before it is handed out.
    let slot = unsafe { take_once(&QUEUE_TAKEN, core::ptr::addr_of_mut!(SETPOINT_QUEUE)) }?;
    Some(slot.write(SetpointQueue::new()))
}

/// The CCM half of the capture buffer, zeroed: `Some` the first time, `None` after.
pub fn capture_half() -> Option<&'static mut [i16; HALF_SLOTS]> {
    // SAFETY: `CAPTURE_HALF` is reached only here.
    let buffer = unsafe { take_once(&TAKEN, core::ptr::addr_of_mut!(CAPTURE_HALF)) }?;
    // SAFETY: every byte is written before it is read as `[i16; _]` (all bit patterns are
    // valid `i16`s).
    unsafe {
        core::ptr::write_bytes(buffer.as_mut_ptr(), 0, 1);
        Some(buffer.assume_init_mut())
    }
}

/// The static at `slot`, handed out once: `Some` the first time `taken` lets a caller through,
/// `None` after (the CCM statics here, and the emulator's SRAM stand-ins for them).
///
/// # Safety
/// `slot` points to a static that nothing reaches but through this call with this `taken`.
pub(super) unsafe fn take_once<T>(taken: &AtomicBool, slot: *mut T) -> Option<&'static mut T> {
    if taken.swap(true, Ordering::AcqRel) {
        return None;
    }
    // SAFETY: `taken` lets exactly one caller through, so this is the only reference to the
    // static ever made (the caller's promise).
    Some(unsafe { &mut *slot })
}
