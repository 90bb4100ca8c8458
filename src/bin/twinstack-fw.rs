//! # twinstack-fw — the driver board's firmware (STM32F405RG, RTIC 2)
//!
//! A thin shell over the library's two halves of the board, [`twinstack::control_loop`]
//! (tick side) and [`twinstack::command_handler`] (command side):
//!
//! * **Control tick** (highest priority, 3): TIM2's update event, at the rate stored in the
//!   parameter record (10–100 kHz, default 50 kHz), starts the sensor ADC conversion and raises
//!   the interrupt; the interrupt runs `ControlLoop::tick` (pending configuration swapped in,
//!   setpoint from the queue or the waveform generator, compensator, feedback, limits,
//!   differential split, both DAC channels in one store, recorder), feeds the watchdog and
//!   counts overruns (a tick still running when the next is due).
//! * **USART1 receive** (priority 2): DMA into a ring, drained on idle line and half/full
//!   transfer, bytes queued for the command handler.
//! * **Command handler** (priority 1, EXTI0 as a software interrupt): `CommandHandler`
//!   decodes frames, answers each request with one response frame (sent from this task with
//!   blocking writes on USART1 TX), queues setpoint batches for the tick, and reaches the
//!   tick's state through short RTIC locks. After each request it re-arms the safe-state codes
//!   of the newest configuration. A parameter load is validated and *prepared* here (the
//!   models relaxed at the stacks' present voltages, in the spare controller); the tick swaps
//!   it in by moving a pointer. `StoreParams` writes flash sector 11 (board image; the tick
//!   stalls for the erase, the watchdog is stretched meanwhile).
//! * **Coarse stage** (feature `dual-stage`; priority 2, TIM3 at 5 kHz): the dual-actuated
//!   stage's coarse tick ([`twinstack::dual_stage::DualStage::coarse_tick`]): reads the motor
//!   and linear encoders, runs the trajectory and emits a burst of step pulses on TIM1. It
//!   holds its power-up position until a command moves it; the piezo tick is untouched.
//! * **Safety**: the board boots in the safe state and in bypass (the compiled-in settings
//!   have no model and close no loop; a stored record boots in the mode the user stored it
//!   with). A panic or hard fault masks interrupts, drives both outputs to the safe state
//!   (bias or zero) and halts; the watchdog then resets the MCU. A parameter record with a
//!   bad CRC (or none) means defaults and the `DEFAULTS` flag in the status report.
//! * **Logging**: `defmt` over RTT.
//!
//! The emulator image is the same application built as `twinstack-emu`
//! (`src/bin/twinstack-emu.rs`, feature `emulator`, `cargo build-emu`): QEMU `netduinoplus2`,
//! HSI clock, SysTick instead of TIM2 for the tick, interrupt-driven USART receive instead of
//! DMA. The two images are two files with two names, and each says which it is in its status
//! report ([`twinstack::protocol::messages::Image`]), so the host can refuse the wrong one. The
//! application itself is `src/bin/firmware/app.rs`, included by both.
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

/// This image's name, in its start-up log.
#[cfg(target_os = "none")]
const IMAGE_NAME: &str = "twinstack-fw";

include!("firmware/app.rs");
