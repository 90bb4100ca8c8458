//! # twinstack-feather-emu — the Feather image in QEMU (`netduinoplus2`, STM32F405)
//!
//! The Feather profile (`twinstack-feather.rs`) built with `emulator` as well: the emulator's
//! HSI clock, SysTick tick and interrupt-driven receive (QEMU models neither RCC, DMA, the DAC
//! nor TIM2's update interrupt), and the Feather's host link, USART3 — QEMU's third `-serial`.
//! `cargo build-emu-feather` writes
//! `target/thumbv7em-none-eabihf/release/twinstack-feather-emu`; its status report says
//! `emulator` ([`twinstack::protocol::messages::Image`]). `tests/feather.rs` boots it.
//!
//! On the host this file compiles to a stub that says how to build the image.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "twinstack-feather-emu is the Feather image for QEMU: build it with \
         `cargo build-emu-feather`; see docs/src/hardware/bring-up.md"
    );
    std::process::exit(2);
}

/// This image's name, in its start-up log.
#[cfg(target_os = "none")]
const IMAGE_NAME: &str = "twinstack-feather-emu";

include!("firmware/app.rs");

#[cfg(target_os = "none")]
firmware_app!(
    tick = SysTick,
    coarse = EXTI1,
    rx = USART3,
    rx_dma = DMA1_STREAM1,
);
