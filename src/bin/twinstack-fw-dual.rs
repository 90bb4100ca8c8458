//! # twinstack-fw-dual — the driver board's firmware with the dual-actuated stage
//!
//! The board image (`twinstack-fw.rs` describes the shell and its tasks) with the coarse axis
//! of a dual-actuated stage (feature `dual-stage`): a coarse task (priority 2, TIM3 at 5 kHz)
//! runs [`twinstack::dual_stage::DualStage::coarse_tick`] through
//! `twinstack::hardware::setup::CoarseStage::run`: it reads the motor and linear encoders
//! (TIM8, TIM4), runs the trajectory and emits a burst of step pulses on TIM1. It holds its
//! power-up position until a command moves it; the piezo tick is untouched.
//! `cargo build-fw-dual` writes `target/thumbv7em-none-eabihf/release/twinstack-fw-dual`; the
//! book's dual-stage guide (`docs/src/guide/dual-stage.md`) has the wiring.
//!
//! On the host this file compiles to a stub that says how to build the image.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "twinstack-fw-dual is the board firmware with the coarse axis: build it with \
         `cargo build-fw-dual`; see docs/src/guide/dual-stage.md"
    );
    std::process::exit(2);
}

// Its emulator image is `twinstack-emu-dual`, for the reason twinstack-fw.rs gives.
#[cfg(all(target_os = "none", feature = "emulator"))]
compile_error!(
    "twinstack-fw-dual is a board image; its emulator image is twinstack-emu-dual: `cargo build-emu-dual`"
);

/// This image's name, in its start-up log.
#[cfg(target_os = "none")]
const IMAGE_NAME: &str = "twinstack-fw-dual";

include!("firmware/app.rs");

#[cfg(target_os = "none")]
firmware_app!(
    tick = TIM2,
    coarse = TIM3,
    rx = USART1,
    rx_dma = DMA2_STREAM2,
    uplink_done = DMA2_STREAM7,
);
