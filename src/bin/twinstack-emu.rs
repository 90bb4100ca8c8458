//! # twinstack-emu — the firmware's QEMU image (`netduinoplus2`, STM32F405)
//!
//! The board's application (`src/bin/firmware/app.rs`, documented in `twinstack-fw.rs`) built
//! with the `emulator` feature: HSI clock, SysTick instead of TIM2 for the tick,
//! interrupt-driven USART receive instead of DMA (QEMU models neither RCC, DMA, the DAC nor
//! TIM2's update interrupt). Nothing else changes. `cargo build-emu` writes
//! `target/thumbv7em-none-eabihf/release/twinstack-emu`, a different file from the board
//! image (`twinstack-fw`), and the image's status report says `emulator`
//! ([`twinstack::protocol::messages::Image`]).
//!
//! On the host this file compiles to a stub that says how to build the image.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "twinstack-emu is the firmware's QEMU image: build it with `cargo build-emu`; \
         see docs/src/hardware/emulator.md"
    );
    std::process::exit(2);
}

// The Feather profile has its own images (`twinstack-feather`, `twinstack-feather-emu`), so
// that this name always means the driver board's pins and clock.
#[cfg(all(target_os = "none", feature = "feather"))]
compile_error!(
    "twinstack-emu is the driver board's image; the Feather's is twinstack-feather-emu: `cargo build-emu-feather`"
);

/// This image's name, in its start-up log.
#[cfg(target_os = "none")]
const IMAGE_NAME: &str = "twinstack-emu";

include!("firmware/app.rs");
