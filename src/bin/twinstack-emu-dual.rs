//! # twinstack-emu-dual — the dual-stage image in QEMU (`netduinoplus2`, STM32F405)
//!
//! `twinstack-fw-dual` for the emulator (features `emulator`, `dual-stage`): the emulator's
//! clock, tick and link (`twinstack-emu.rs`), and the coarse task on the library's model of
//! step/dir, encoders and switches ([`twinstack::dual_stage::ideal_axis::IdealAxis`]; QEMU
//! models neither TIM1, TIM8 nor the GPIOs), pended every coarse period by the SysTick tick
//! (EXTI1). `cargo build-emu-dual` writes
//! `target/thumbv7em-none-eabihf/release/twinstack-emu-dual`; `cli/tests/emulator_link.rs`
//! boots it.
//!
//! On the host this file compiles to a stub that says how to build the image.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "twinstack-emu-dual is the dual-stage image for QEMU: build it with \
         `cargo build-emu-dual`; see docs/src/guide/dual-stage.md"
    );
    std::process::exit(2);
}

/// This image's name, in its start-up log.
#[cfg(target_os = "none")]
const IMAGE_NAME: &str = "twinstack-emu-dual";

include!("firmware/app.rs");

#[cfg(target_os = "none")]
firmware_app!(
    tick = SysTick,
    coarse = EXTI1,
    rx = USART1,
    rx_dma = DMA2_STREAM2,
);
