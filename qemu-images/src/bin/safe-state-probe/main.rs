//! # safe-state-probe — drives the firmware's panic and hard-fault paths in QEMU
//!
//! A test image for `tests/safe_state.rs`. It sets the DAC up the way the firmware does,
//! arms the safe codes (left `0x123`, right `0x456`), writes a working pair (`0x700`,
//! `0x300`) as a tick would, and then fails: with a panic, or — when the first byte of the
//! parameter sector is `1` (QEMU `-device loader,file=<one byte 0x01>,addr=0x080e0000`) — with a
//! hard fault (an undefined instruction, escalated because UsageFault is not enabled). Its
//! panic and hard-fault handlers are the firmware's own
//! (`safe_state::stop_on_panic`, `safe_state::stop_on_fault`).
//!
//! QEMU ignores DAC writes but logs them with `-d unimp`, so the test reads the sequence of
//! `DHR12RD` values (`right << 16 | left`) and expects the safe pair last; each handler first
//! writes a marker to GPIOA's ODR (also logged) so the test knows which path ran.
//!
//! On the host this file compiles to a stub that says how to build the image.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(target_os = "none")]
mod image;

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "safe-state-probe is a QEMU test image for thumbv7em-none-eabihf: the tests build and run it \
         (cargo build --release --target thumbv7em-none-eabihf -p twinstack-qemu-images --bin safe-state-probe)"
    );
    std::process::exit(2);
}
