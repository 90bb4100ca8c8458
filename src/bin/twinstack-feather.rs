//! # twinstack-feather — the firmware on an Adafruit Feather STM32F405 Express
//!
//! The board's shell (`src/bin/firmware/app.rs`, documented in `twinstack-fw.rs`) with the
//! library built for the `feather` board profile (`twinstack::hardware::profile`): the same control tick,
//! command handler, converters (the chip's own DAC and ADC), watchdog and parameter sector, on
//! the Feather's 12 MHz crystal and its header pins — both stacks' drives on A0/A1, the sensor
//! on A2, the host link on USART3 at the TX/RX pins, the trigger I/O on D5, D6 and D11–D13.
//! `cargo build-fw-feather` writes `target/thumbv7em-none-eabihf/release/twinstack-feather`;
//! the book's bring-up chapter (`docs/src/hardware/bring-up.md`) has the wiring, the flashing
//! and a first calibration on a dummy load. It reports itself as a board image
//! ([`twinstack::protocol::messages::Image::Board`]).
//!
//! On the host this file compiles to a stub that says how to build the image.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "twinstack-feather is the firmware for the Adafruit Feather STM32F405 Express: build \
         it with `cargo build-fw-feather`; see docs/src/hardware/bring-up.md"
    );
    std::process::exit(2);
}

// The Feather's emulator image is `twinstack-feather-emu`, for the reason twinstack-fw.rs gives.
#[cfg(all(target_os = "none", feature = "emulator"))]
compile_error!(
    "twinstack-feather is the Feather's board image; its emulator image is \
     twinstack-feather-emu: `cargo build-emu-feather`"
);

/// This image's name, in its start-up log.
#[cfg(target_os = "none")]
const IMAGE_NAME: &str = "twinstack-feather";

include!("firmware/app.rs");

#[cfg(target_os = "none")]
firmware_app!(
    tick = TIM2,
    coarse = TIM3,
    rx = USART3,
    rx_dma = DMA1_STREAM1,
    uplink_done = DMA1_STREAM3,
);
