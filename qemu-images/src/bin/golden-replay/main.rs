//! # golden-replay — the golden vectors replayed on the Cortex-M4, in QEMU
//!
//! Run under `qemu-system-arm -machine netduinoplus2 …` with semihosting (see
//! `tests/golden.rs`, which builds and runs it). The image embeds `tests/golden/vectors.bin`
//! and, for every vector set in it, runs `twinstack_golden::replay`: it builds the set's
//! configuration from its recipe with the library's constructors, runs each stored input
//! through `Observed::tick` (the code the firmware's interrupt runs, then the observer its
//! services run where the configuration has a sensor) and compares each output with the
//! stored one. Per set it prints over semihosting
//!
//! ```text
//! GOLDEN set=<name> ticks=<n> config=<crc> expected_config=<crc> outputs=<crc> expected=<crc> first_diff=<tick|none>
//! GOLDEN-DIFF set=<name> tick=<k> expected=<output> actual=<output>     (only on a mismatch)
//! ```
//!
//! (`config`: the fingerprint of the configuration this build made; `outputs`: CRC-32 of this
//! run's outputs), then `GOLDEN-END sets=<n>` and exits QEMU with status 0; a file it cannot
//! parse or a recipe it cannot build prints `GOLDEN-ERROR …` and exits with status 1.
//!
//! On the host this file compiles to a stub that says how to build the image.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(target_os = "none")]
mod image;

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "golden-replay is a QEMU test image for thumbv7em-none-eabihf: the tests build and run it \
         (cargo build --release --target thumbv7em-none-eabihf -p twinstack-qemu-images --bin golden-replay)"
    );
    std::process::exit(2);
}
