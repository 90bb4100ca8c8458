//! # tick-bench — instructions per control tick, counted in QEMU
//!
//! Run under `qemu-system-arm -machine netduinoplus2 -icount shift=0 …` (see
//! `tests/tick_bench.rs`, which builds, runs and tabulates it). With `-icount shift=0` one
//! guest instruction takes one virtual nanosecond and TIM2 (prescaler 0) counts at 1 GHz, so
//! the difference of TIM2's counter across a call is its exact instruction count, the same on
//! every run.
//!
//! For each compensator (none, inverse P–I N = 8/16/32, inverse Duhem), with the Duhem
//! observer and sensor feedback on (plus breakdown rows: `bypass` = split, limits and DAC
//! write only; `none-observer-only` = that plus the Duhem observer; `none-sensor-drift` = that
//! plus the sensor read and drift check, open loop; `none-pid-notch` = closed loop with the
//! derivative and the resonance notch), it runs `Observed::tick` — `Controller::tick` and the
//! observer's step on its report, which the board runs below the tick — on the firmware's own DAC and
//! ADC drivers (the DAC write is the real `DHR12RD` store) for a triangle setpoint (±0.95) that
//! reverses every 100 ticks, and prints one line per configuration over semihosting:
//!
//! ```text
//! BENCH name=<name> ticks=<n> total=<instructions> min=<n> max=<n> overhead=<n>
//! ```
//!
//! `total`, `min`, `max` are net of `overhead`, the count of two back-to-back timer reads: a
//! count is the tick's own instructions plus its call (`BL` and a few argument moves, which
//! the firmware, inlining the tick, does not pay), so it errs high by those few, never low.
//! (Checked against QEMU's instruction trace, `-singlestep -d exec`, which counts the tick's
//! body alone: see the README.) Then it exits QEMU with status 0 (1 on panic).
//!
//! These are instructions, not cycles: QEMU models neither flash wait states nor the
//! multi-cycle instructions; confirm on the board with DWT's cycle counter.
//!
//! On the host this file compiles to a stub that says how to build the image.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(target_os = "none")]
mod image;

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "tick-bench is a QEMU test image for thumbv7em-none-eabihf: the tests build and run it \
         (cargo build --release --target thumbv7em-none-eabihf -p twinstack-qemu-images --bin tick-bench)"
    );
    std::process::exit(2);
}
