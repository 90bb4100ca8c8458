//! Puts the board's `memory.x` (the workspace root's, the one memory layout) on the linker
//! search path when building the images for the bare-metal target (cortex-m-rt's `link.x`
//! includes it). Host builds are untouched.

use std::{env, fs, path::PathBuf};

fn main() {
    println!("cargo:rerun-if-changed=../memory.x");
    println!("cargo:rerun-if-changed=build.rs");
    if env::var("CARGO_CFG_TARGET_OS").as_deref() != Ok("none") {
        return;
    }
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("cargo sets OUT_DIR for build scripts"));
    fs::copy("../memory.x", out.join("memory.x"))
        .expect("../memory.x is readable and OUT_DIR writable");
    println!("cargo:rustc-link-search={}", out.display());
}
