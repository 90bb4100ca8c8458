//! The outputs' safe state, entered on panic or hard fault before the core halts.
//!
//! The shell [`arm`]s it at boot with the codes for the configured
//! [`SafeState`](crate::config::param_store::SafeState) (both zero, or both at the common bias);
//! [`make_outputs_safe`] masks every interrupt (so the control tick cannot write again), writes those codes
//! through the DAC's dual register, and [`halt`]s. The watchdog, no longer fed, then resets the
//! MCU after its timeout; at reset the DAC is off until the firmware has re-initialised it.

use core::sync::atomic::{AtomicU32, Ordering};

use crate::board::DacCode;

/// Safe codes, `right << 16 | left`. Zero (both stacks discharged) until armed.
static SAFE_CODES: AtomicU32 = AtomicU32::new(0);

/// Sets the codes [`make_outputs_safe`] writes.
pub fn arm(left: DacCode, right: DacCode) {
    SAFE_CODES.store((right.0 as u32) << 16 | left.0 as u32, Ordering::Relaxed);
}

/// The codes currently armed, `(left, right)`.
pub fn armed() -> (DacCode, DacCode) {
    let w = SAFE_CODES.load(Ordering::Relaxed);
    (DacCode(w as u16), DacCode((w >> 16) as u16))
}

/// Masks every interrupt (the control tick cannot write again) and drives both outputs to the
/// armed codes. First thing in the panic and hard-fault handlers.
pub fn make_outputs_safe() {
    cortex_m::interrupt::disable();
    let (left, right) = armed();
    super::dac::force_both(left, right);
}

/// Stops here, interrupts masked; the watchdog, no longer fed, resets the MCU.
pub fn halt() -> ! {
    loop {
        cortex_m::asm::wfi();
    }
}

/// The firmware's panic handler body: outputs safe first, then the panic's source location
/// logged over defmt, then [`halt`]. (The location, not the message: formatting the message
/// would pull `core::fmt` into the image, about 3 KiB of flash for a path that should never
/// run.)
pub fn stop_on_panic(info: &core::panic::PanicInfo) -> ! {
    make_outputs_safe();
    match info.location() {
        Some(at) => defmt::error!("panic at {=str}:{=u32}", at.file(), at.line()),
        None => defmt::error!("panic"),
    }
    halt()
}

/// The firmware's hard-fault handler body: outputs safe, then [`halt`].
pub fn stop_on_fault() -> ! {
    make_outputs_safe();
    halt()
}
