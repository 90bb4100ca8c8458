//! # twinstack-emu — the firmware's QEMU image (`netduinoplus2`, STM32F405)
//!
//! The board's shell (`src/bin/firmware/app.rs`, documented in `twinstack-fw.rs`) with the
//! library built for the emulator (feature `emulator`, `twinstack::hardware::setup`): HSI
//! clock, SysTick instead of TIM2 for the tick, interrupt-driven USART receive and polled
//! transmit instead of DMA, the parameter record read-only (QEMU models neither RCC, DMA, the
//! DAC, the flash interface nor TIM2's update interrupt). `cargo build-emu` writes
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

// The coarse axis has its own emulator image.
#[cfg(all(target_os = "none", feature = "dual-stage"))]
compile_error!(
    "twinstack-emu is the piezo-only emulator image; with the coarse axis it is \
     twinstack-emu-dual: `cargo build-emu-dual`"
);

/// This image's name, in its start-up log.
#[cfg(target_os = "none")]
const IMAGE_NAME: &str = "twinstack-emu";

include!("firmware/app.rs");

#[cfg(target_os = "none")]
firmware_app!(
    tick = SysTick,
    coarse = EXTI1,
    rx = USART1,
    rx_dma = DMA2_STREAM2,
);
