//! # irq-bench — the whole control interrupt, every invocation, in QEMU
//!
//! An RTIC application with the firmware's control interrupt exactly as the emulator image
//! has it — SysTick at priority 3 running [`twinstack::hardware::tick::ControlTick::run`]
//! (timer, setpoint stream, controller, recorder, telemetry's tap, watchdog) — whose idle
//! task plays the host (and packs the telemetry: all six signals every tick, the tap's worst):
//! it loads settings, arms the recorder and streams setpoints through the library's
//! [`twinstack::command_handler::CommandHandler`], as requests from the UART would.
//!
//! `tests/irq_bench.rs` runs it under `qemu-system-arm -icount shift=0 -singlestep -d
//! exec,nochain,int` and counts the instructions of every SysTick invocation from its first
//! instruction to its exception return. Before each scenario the idle task calls
//! `irq_bench_marker` (so the trace can be split) and prints `SCENARIO <name>` over
//! semihosting; at the end it exits QEMU with status 0 (1 on panic).
//!
//! On the host this file compiles to a stub that says how to build the image.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(target_os = "none")]
mod image;

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "irq-bench is a QEMU test image for thumbv7em-none-eabihf: tests/irq_bench.rs builds \
         and runs it (cargo build --release --target thumbv7em-none-eabihf \
         -p twinstack-qemu-images --bin irq-bench)"
    );
    std::process::exit(2);
}
