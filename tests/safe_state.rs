//! The safe state: a panic or a hard fault must leave both DAC channels at the armed safe
//! codes, written after everything else, before the core halts.
//!
//! Runs the `safe-state-probe` image (`qemu-images/src/bin/safe-state-probe/`: the firmware's
//! own panic and hard-fault handler bodies) in QEMU with `-d unimp`: QEMU does not model the
//! DAC but logs every write to it, so the sequence of `DHR12RD` values is visible. The probe
//! arms left `0x123` / right `0x456`, writes a working pair `0x700` / `0x300`, then fails.

mod support;

use std::io::Read;
use std::process::Stdio;
use std::time::{Duration, Instant};

/// `DHR12RD` of the armed safe codes (`right << 16 | left`).
const SAFE_WORD: u32 = 0x0456_0123;
/// `DHR12RD` of the working pair written before the failure.
const WORKING_WORD: u32 = 0x0300_0700;

/// What QEMU logged while the probe ran.
struct Log {
    /// Values written to the DAC's dual 12-bit right-aligned holding register, in order.
    dual_writes: Vec<u32>,
    /// Values written to GPIOA's ODR (the probe's handler markers).
    markers: Vec<u32>,
}

fn value_of(line: &str) -> Option<u32> {
    let hex = line.split("value 0x").nth(1)?.trim_end_matches(')');
    u32::from_str_radix(hex.trim(), 16).ok()
}

/// Runs the probe; `hard_fault` puts the byte 1 at the start of the parameter sector, which
/// makes the probe fault instead of panicking. The probe halts for good, so QEMU is stopped
/// once the safe write has been logged (or after 20 s).
fn run_probe(hard_fault: bool) -> Log {
    let elf = support::build_image(support::QEMU_IMAGES, "safe-state-probe", &[]);
    let mut cmd = support::qemu_command(&elf);
    cmd.args(["-serial", "null", "-d", "unimp"]);
    let scratch = std::env::temp_dir().join(format!(
        "twinstack-safe-{}-{hard_fault}",
        std::process::id()
    ));
    std::fs::create_dir_all(&scratch).expect("scratch directory");
    if hard_fault {
        let byte = scratch.join("fault.bin");
        std::fs::write(&byte, [1u8]).expect("fault selector file");
        cmd.arg("-device")
            .arg(format!("loader,file={},addr=0x080e0000", byte.display()));
    }
    let mut child = cmd
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("qemu-system-arm starts");
    let mut stderr = child.stderr.take().expect("stderr piped");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut buf = [0u8; 4096];
        while let Ok(n) = stderr.read(&mut buf) {
            if n == 0 || tx.send(buf[..n].to_vec()).is_err() {
                break;
            }
        }
    });
    let start = Instant::now();
    let mut text = String::new();
    let marker = format!("value 0x{SAFE_WORD:08x}");
    while !text.contains(&marker) && start.elapsed() < Duration::from_secs(20) {
        if let Ok(chunk) = rx.recv_timeout(Duration::from_millis(100)) {
            text.push_str(&String::from_utf8_lossy(&chunk));
        }
    }
    // Let anything that would (wrongly) follow the safe write reach the log.
    std::thread::sleep(Duration::from_millis(300));
    while let Ok(chunk) = rx.try_recv() {
        text.push_str(&String::from_utf8_lossy(&chunk));
    }
    let _ = child.kill();
    let _ = child.wait();
    let _ = std::fs::remove_dir_all(&scratch);
    let dual_writes = text
        .lines()
        .filter(|l| l.starts_with("DAC:") && l.contains("write") && l.contains("offset 0x020"))
        .filter_map(value_of)
        .collect();
    let markers = text
        .lines()
        .filter(|l| l.starts_with("GPIOA:") && l.contains("write") && l.contains("offset 0x014"))
        .filter_map(value_of)
        .collect();
    Log {
        dual_writes,
        markers,
    }
}

fn assert_safe_last(log: &Log, path: &str) {
    assert!(
        log.dual_writes.contains(&WORKING_WORD),
        "{path}: the probe never wrote its working pair: {:x?}",
        log.dual_writes
    );
    assert_eq!(
        log.dual_writes.last(),
        Some(&SAFE_WORD),
        "{path}: the last DAC write must be the safe pair (right 0x456, left 0x123): {:x?}",
        log.dual_writes
    );
}

#[test]
fn a_panic_drives_both_outputs_to_the_safe_state_and_halts() {
    let log = run_probe(false);
    assert_eq!(log.markers, [0x0BAD], "the panic handler ran (once)");
    assert_safe_last(&log, "panic");
}

#[test]
fn a_hard_fault_drives_both_outputs_to_the_safe_state_and_halts() {
    let log = run_probe(true);
    assert_eq!(log.markers, [0xFA17], "the hard-fault handler ran (once)");
    assert_safe_last(&log, "hard fault");
}

#[test]
fn qemu_log_values_parse() {
    assert_eq!(
        value_of("DAC: unimplemented device write (size 4, offset 0x020, value 0x04560123)"),
        Some(SAFE_WORD)
    );
    assert_eq!(value_of("DAC: something else"), None);
}
