//! # twinstack-fw — the driver board's firmware (STM32F405RG, RTIC 2)
//!
//! A thin RTIC shell (`src/bin/firmware/app.rs`) over the library: the board is brought up by
//! `twinstack::hardware::setup::setup`, and every task's body is one library function, over
//! the two halves of the board, [`twinstack::control_loop`] (tick side) and
//! [`twinstack::command_handler`] (command side):
//!
//! * **Control tick** (highest priority, 3): TIM2's update event, at the rate stored in the
//!   parameter record (10–100 kHz, default 50 kHz), starts the sensor ADC conversion and raises
//!   the interrupt; the interrupt runs `ControlLoop::tick` (pending configuration swapped in,
//!   setpoint from the queue or the waveform generator, compensator, feedback, limits,
//!   differential split, both DAC channels in one store, one snapshot onto the snapshot
//!   ring), feeds the watchdog and counts overruns (a tick still running when the next is due)
//!   (`twinstack::hardware::setup::tick`).
//! * **Services** (priority 2, EXTI2 as a software interrupt, pended by the tick once every 8
//!   snapshots, `twinstack::hardware::setup::services`): the recorder's capture and telemetry's
//!   tap, served from the snapshots; they wake the command handler when the telemetry queue
//!   holds a frame's worth of samples.
//! * **USART1 receive** (priority 2): DMA into a ring, drained on idle line and half/full
//!   transfer, bytes queued for the command handler.
//! * **USART1 transmit** (priority 2, DMA2 stream 7): frames leave by DMA, double-buffered;
//!   the transfer-complete interrupt puts the waiting frame on the line and wakes the command
//!   task.
//! * **Command handler** (priority 1, EXTI0 as a software interrupt,
//!   `twinstack::hardware::setup::command`): `CommandHandler` decodes frames, answers each
//!   request with one response frame, queues setpoint batches for the tick, and reaches the
//!   tick's state through short RTIC locks, the services' through locks that do not mask the
//!   tick. A response the uplink cannot take yet waits in an
//!   outbox and no further request is read until it has gone: nothing spins on the line.
//!   Telemetry frames fill the line between responses; the services wake this task when the
//!   telemetry queue holds a frame's worth of samples, not once per tick. After each request
//!   it re-arms the safe-state codes of the newest configuration. A parameter load is
//!   validated and *prepared* here (the models relaxed at the stacks' present voltages, in the
//!   spare controller); the tick swaps it in by moving a pointer. `StoreParams` writes flash
//!   sector 11 (the tick stalls for the erase, the watchdog is stretched meanwhile).
//! * **Safety**: the board boots in the safe state and in bypass (the compiled-in settings
//!   have no model and close no loop; a stored record boots in the mode the user stored it
//!   with). A panic or hard fault masks interrupts, drives both outputs to the safe state
//!   (bias or zero) and halts; the watchdog then resets the MCU. A parameter record with a
//!   bad CRC (or none) means defaults and the `DEFAULTS` flag in the status report.
//! * **Logging**: `defmt` over RTT.
//!
//! The other images are the same shell with their own interrupt bindings and the library's
//! `setup()` for their target: `twinstack-fw-dual` (this board with the dual-actuated stage's
//! coarse axis), `twinstack-emu` and `twinstack-emu-dual` (QEMU `netduinoplus2`: HSI clock,
//! SysTick instead of TIM2, interrupt-driven receive, polled transmit), `twinstack-feather`
//! and `twinstack-feather-emu` (the Adafruit Feather). Each image is its own file with its
//! own name, and each says in its status report whether it is a board or an emulator image
//! ([`twinstack::protocol::messages::Image`]), so the host can refuse the wrong one.
//!
//! On the host this file compiles to a stub that says how to build the firmware.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "twinstack-fw is the STM32F405 firmware: build it with `cargo build-fw` \
         (board) or `cargo build-emu` (QEMU); see README.md, Firmware"
    );
    std::process::exit(2);
}

// The emulator image is `twinstack-emu`: this binary built with `emulator` would be an
// emulator image under the board image's name, the confusion the two names exist to prevent.
#[cfg(all(target_os = "none", feature = "emulator"))]
compile_error!(
    "twinstack-fw is the board image; the emulator image is twinstack-emu: `cargo build-emu` \
     (--bin twinstack-emu --features emulator)"
);

// The Feather profile has its own images (`twinstack-feather`, `twinstack-feather-emu`), so
// that this name always means the driver board's pins and clock.
#[cfg(all(target_os = "none", feature = "feather"))]
compile_error!(
    "twinstack-fw is the driver board's image; the Feather's is twinstack-feather: `cargo build-fw-feather`"
);

// The coarse axis has its own image, so that this name always means the piezo-only board.
#[cfg(all(target_os = "none", feature = "dual-stage"))]
compile_error!(
    "twinstack-fw is the piezo-only image; with the coarse axis it is twinstack-fw-dual: `cargo build-fw-dual`"
);

/// This image's name, in its start-up log.
#[cfg(target_os = "none")]
const IMAGE_NAME: &str = "twinstack-fw";

include!("firmware/app.rs");

#[cfg(target_os = "none")]
firmware_app!(
    tick = TIM2,
    coarse = TIM3,
    rx = USART1,
    rx_dma = DMA2_STREAM2,
    uplink_done = DMA2_STREAM7,
);
