//! Shared by the tests that run the firmware in QEMU (`tests/emulator.rs`,
//! `tests/tick_bench.rs`): check that the prerequisites are installed (`cargo xtask setup`
//! installs them), build firmware images (once per test run, serialised, into
//! `target/firmware` so they never fight the host build for its lock), read an image's flash
//! and RAM size, and run QEMU.
#![allow(dead_code)] // each test binary uses its own subset

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::{Mutex, OnceLock};

/// The firmware's target triple.
pub const TARGET: &str = "thumbv7em-none-eabihf";
/// QEMU's STM32F405 board.
pub const MACHINE: &str = "netduinoplus2";

/// The workspace root (where `Cargo.toml` and `.cargo/config.toml` are). `hal-sim`'s tests
/// include this file too (`#[path]`): from there the root is the parent directory.
pub fn workspace_root() -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    if dir.join("memory.x").is_file() {
        dir
    } else {
        dir.parent().map(Path::to_path_buf).unwrap_or(dir)
    }
}

/// Separate target directory for the firmware images.
pub fn firmware_target_dir() -> PathBuf {
    workspace_root().join("target").join("firmware")
}

fn run_quiet(cmd: &mut Command) -> Result<(), String> {
    let out = cmd
        .stdin(Stdio::null())
        .output()
        .map_err(|e| format!("cannot run {cmd:?}: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "{cmd:?} failed ({}):\n{}{}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ))
    }
}

/// What to tell the user when a tool the QEMU tests need is missing.
const SETUP_HINT: &str =
    "run `cargo xtask setup` (it installs what the tests need), then the tests again";

/// Checks that the firmware target's standard library is installed (in the sysroot of the
/// `rustc` on the PATH); panics telling the user to run `cargo xtask setup` otherwise.
pub fn ensure_target() {
    static FOUND: OnceLock<Result<(), String>> = OnceLock::new();
    let r = FOUND.get_or_init(|| {
        let out = Command::new("rustc")
            .args(["--print", "sysroot"])
            .stdin(Stdio::null())
            .output()
            .map_err(|e| format!("cannot run rustc: {e}"))?;
        let sysroot = PathBuf::from(String::from_utf8_lossy(&out.stdout).trim());
        let lib = sysroot.join("lib").join("rustlib").join(TARGET);
        if lib.is_dir() {
            Ok(())
        } else {
            Err(format!(
                "the firmware target {TARGET} is not installed (no {}): {SETUP_HINT}",
                lib.display()
            ))
        }
    });
    if let Err(e) = r {
        panic!("{e}");
    }
}

/// Checks that `qemu-system-arm` runs; panics telling the user to run `cargo xtask setup`
/// otherwise.
pub fn ensure_qemu() {
    static FOUND: OnceLock<bool> = OnceLock::new();
    let runs = *FOUND.get_or_init(|| {
        Command::new("qemu-system-arm")
            .arg("--version")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success())
    });
    assert!(
        runs,
        "qemu-system-arm is not installed (or does not run): {SETUP_HINT}"
    );
}

/// The package of the firmware itself (`twinstack-fw`).
pub const FIRMWARE: &str = "twinstack";
/// The package of the test-only images (`qemu-images/`: tick bench, safe-state probe,
/// golden replay).
pub const QEMU_IMAGES: &str = "twinstack-qemu-images";

/// Builds binary `bin` of `package` ([`FIRMWARE`] or [`QEMU_IMAGES`]) with `features`
/// (release, for the target) into [`firmware_target_dir`] and returns the ELF's path. Each
/// (bin, features) is built at most once per test process; concurrent callers wait for it (and
/// cargo's own lock on the target directory serialises separate test processes).
pub fn build_image(package: &str, bin: &str, features: &[&str]) -> PathBuf {
    static BUILT: OnceLock<Mutex<HashMap<String, PathBuf>>> = OnceLock::new();
    ensure_target();
    let key = format!("{bin}|{}", features.join(","));
    let mut built = BUILT
        .get_or_init(|| Mutex::new(HashMap::new()))
        .lock()
        .unwrap_or_else(|e| e.into_inner());
    if let Some(p) = built.get(&key) {
        return p.clone();
    }
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".to_string());
    let mut cmd = Command::new(cargo);
    cmd.current_dir(workspace_root())
        .args(["build", "--release", "--target", TARGET])
        .args(["-p", package, "--bin", bin])
        .arg("--target-dir")
        .arg(firmware_target_dir())
        // RUSTFLAGS from the environment would replace the target's link arguments in
        // .cargo/config.toml.
        .env_remove("RUSTFLAGS")
        .env_remove("CARGO_ENCODED_RUSTFLAGS")
        .env_remove("CARGO_BUILD_TARGET");
    if !features.is_empty() {
        cmd.args(["--features", &features.join(",")]);
    }
    if let Err(e) = run_quiet(&mut cmd) {
        panic!("building firmware image {bin} ({features:?}) failed: {e}");
    }
    let path = firmware_target_dir().join(TARGET).join("release").join(bin);
    assert!(
        path.is_file(),
        "cargo built {bin} but {} is missing",
        path.display()
    );
    // Keep a copy per feature set: the next build of the same bin overwrites the file.
    let copy = firmware_target_dir().join(format!(
        "{bin}{}{}.elf",
        if features.is_empty() { "" } else { "-" },
        features.join("-")
    ));
    std::fs::copy(&path, &copy)
        .unwrap_or_else(|e| panic!("cannot copy {} to {}: {e}", path.display(), copy.display()));
    built.insert(key, copy.clone());
    copy
}

/// Flash and RAM an ELF image occupies, bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageSize {
    /// Bytes loaded into flash (code, constants, initial values of `.data`).
    pub flash: u64,
    /// Bytes of RAM reserved statically (`.data`, `.bss`, `.uninit`; not the stack).
    pub ram: u64,
}

fn u16_at(b: &[u8], o: usize) -> Result<u16, String> {
    b.get(o..o + 2)
        .map(|s| u16::from_le_bytes([s[0], s[1]]))
        .ok_or_else(|| format!("ELF truncated at byte {o}"))
}

fn u32_at(b: &[u8], o: usize) -> Result<u32, String> {
    b.get(o..o + 4)
        .map(|s| u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
        .ok_or_else(|| format!("ELF truncated at byte {o}"))
}

/// Reads the sizes from an ELF32 little-endian image's program headers: `PT_LOAD` segments
/// loaded at a flash address count their file size to flash; segments placed in RAM count
/// their memory size to RAM.
pub fn image_size(path: &Path) -> Result<ImageSize, String> {
    let b = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    if b.get(0..6) != Some(&[0x7f, b'E', b'L', b'F', 1, 1][..]) {
        return Err(format!(
            "{}: not a 32-bit little-endian ELF",
            path.display()
        ));
    }
    let phoff = u32_at(&b, 28)? as usize;
    let phentsize = u16_at(&b, 42)? as usize;
    let phnum = u16_at(&b, 44)? as usize;
    let in_flash = |a: u32| (0x0800_0000..0x0810_0000).contains(&a);
    let in_ram =
        |a: u32| (0x2000_0000..0x2002_0000).contains(&a) || (0x1000_0000..0x1001_0000).contains(&a);
    let mut size = ImageSize { flash: 0, ram: 0 };
    for i in 0..phnum {
        let h = phoff + i * phentsize;
        if u32_at(&b, h)? != 1 {
            continue; // not PT_LOAD
        }
        let vaddr = u32_at(&b, h + 8)?;
        let paddr = u32_at(&b, h + 12)?;
        let filesz = u32_at(&b, h + 16)? as u64;
        let memsz = u32_at(&b, h + 20)? as u64;
        if in_flash(paddr) {
            size.flash += filesz;
        }
        if in_ram(vaddr) {
            size.ram += memsz;
        }
    }
    Ok(size)
}

/// The common QEMU command line for an image: the STM32F405 board, no display, no monitor,
/// semihosting on (the bench prints and exits through it).
pub fn qemu_command(elf: &Path) -> Command {
    ensure_qemu();
    let mut cmd = Command::new("qemu-system-arm");
    cmd.args([
        "-machine",
        MACHINE,
        "-cpu",
        "cortex-m4",
        "-nographic",
        "-monitor",
        "none",
    ])
    .args(["-semihosting-config", "enable=on,target=native"])
    .arg("-kernel")
    .arg(elf)
    .stdin(Stdio::null());
    cmd
}

/// [`qemu_command`] for an emulated board talking to a host: with `-icount shift=0,sleep=on`,
/// one guest instruction is one nanosecond of the guest's clock and idle time passes at the
/// host's pace. The guest then takes every tick with the headroom a board has, whatever the
/// host's load: on the host's clock QEMU runs the guest slower than the chip, the tick takes
/// the whole CPU, and what runs below it (the services that record and send telemetry, the
/// command task) starves as it would on an overloaded board.
pub fn emulator_command(elf: &Path) -> Command {
    let mut cmd = qemu_command(elf);
    cmd.args(["-icount", "shift=0,sleep=on"]);
    cmd
}

/// Boots `elf` in QEMU with `extra` arguments, waits for it to exit through semihosting
/// (at most `limit`), and returns its stdout; panics, naming `what`, if it does not exit in
/// time or exits with a failure. For the images that print a report and quit (tick bench,
/// golden replay).
pub fn run_to_exit(elf: &Path, extra: &[&str], what: &str, limit: std::time::Duration) -> String {
    use std::io::Read;
    let mut child = qemu_command(elf)
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("qemu-system-arm starts");
    let start = std::time::Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().expect("wait for qemu") {
            break s;
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{what} did not exit within {limit:?}");
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    };
    let (mut out, mut err) = (String::new(), String::new());
    if let Some(mut o) = child.stdout.take() {
        o.read_to_string(&mut out).expect("read qemu's stdout");
    }
    if let Some(mut e) = child.stderr.take() {
        e.read_to_string(&mut err).expect("read qemu's stderr");
    }
    assert!(
        status.success(),
        "{what} exited with {status}:\n{out}\n{err}"
    );
    out
}

/// The value of symbol `name` in an ELF32 little-endian image's symbol table, if it is there.
pub fn elf_symbol(path: &Path, name: &str) -> Result<Option<u32>, String> {
    let b = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let shoff = u32_at(&b, 32)? as usize;
    let shentsize = u16_at(&b, 46)? as usize;
    let shnum = u16_at(&b, 48)? as usize;
    for i in 0..shnum {
        let sh = shoff + i * shentsize;
        if u32_at(&b, sh + 4)? != 2 {
            continue; // not SHT_SYMTAB
        }
        let (off, size) = (u32_at(&b, sh + 16)? as usize, u32_at(&b, sh + 20)? as usize);
        let link = u32_at(&b, sh + 24)? as usize;
        let strtab = u32_at(&b, shoff + link * shentsize + 16)? as usize;
        for s in (off..off + size).step_by(16) {
            let at = strtab + u32_at(&b, s)? as usize;
            let end = b[at..]
                .iter()
                .position(|&c| c == 0)
                .map_or(b.len(), |n| at + n);
            if &b[at..end] == name.as_bytes() {
                return Ok(Some(u32_at(&b, s + 4)?));
            }
        }
    }
    Ok(None)
}

/// The stack an image's run used, bytes, from a dump of its SRAM (`ram`, starting at
/// 0x2000_0000): cortex-m-rt's `paint-stack` fills `_stack_end .. _stack_start` with
/// `0xCCCC_CCCC` before `main`; the lowest word the run changed is its high-water mark.
/// Returns `(used, room)`: the bytes below `_stack_start` written, and the room the
/// image's static RAM leaves (`_stack_start − _stack_end`).
pub fn stack_used(elf: &Path, ram: &[u8]) -> Result<(u32, u32), String> {
    let sym =
        |n: &str| elf_symbol(elf, n)?.ok_or_else(|| format!("{}: no symbol {n}", elf.display()));
    let (top, bottom) = (sym("_stack_start")?, sym("_stack_end")?);
    let base = 0x2000_0000u32;
    let mut low = top;
    let mut a = bottom;
    while a < top {
        let o = (a - base) as usize;
        let w = ram
            .get(o..o + 4)
            .map(|s| u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
            .ok_or_else(|| format!("RAM dump too short for {a:#x}"))?;
        if w != 0xCCCC_CCCC {
            low = a;
            break;
        }
        a += 4;
    }
    Ok((top - low, top - bottom))
}

/// The functions of `elf` reachable from symbol `root` by direct branches and calls (from
/// `llvm-objdump -d`: each branch's target address, mapped to the function holding it),
/// their names as the symbol table spells them (mangled), each with the indirect branches it
/// holds (`blx rN`, `bx rN` other than a return), which the walk cannot follow: a caller that
/// vouches for what is reached checks there are none. `objdump` is the disassembler's path.
pub fn reachable_functions(objdump: &Path, elf: &Path, root: &str) -> Vec<(String, Vec<String>)> {
    let out = Command::new(objdump)
        .args(["-d", "--no-show-raw-insn", "--triple=thumbv7em-none-eabihf"])
        .arg(elf)
        .output()
        .expect("llvm-objdump runs");
    assert!(out.status.success(), "llvm-objdump failed");
    // (start address, name, branch targets, indirect branches), in address order.
    let mut funcs: Vec<(u32, String, Vec<u32>, Vec<String>)> = Vec::new();
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        if let Some(head) = line.strip_suffix(">:") {
            // An ARM mapping symbol (`$t`, `$d`: code or data follows) is not a function:
            // what follows it belongs to the function it sits in (a jump table's cases are
            // reached by falling through, not by a branch the walk sees).
            if let Some((addr, name)) = head.split_once(" <").filter(|(_, n)| !n.starts_with('$')) {
                if let Ok(a) = u32::from_str_radix(addr.trim(), 16) {
                    funcs.push((a, name.to_string(), Vec::new(), Vec::new()));
                    continue;
                }
            }
        }
        // `80007a0:      \tbl\t0x8001234 <…>`: address, colon, spaces, then tab-separated.
        let Some((_, rest)) = line.trim_start().split_once(':') else {
            continue;
        };
        let mut parts = rest.split('\t').map(str::trim).filter(|p| !p.is_empty());
        let (Some(mnemonic), Some(operands)) = (parts.next(), parts.next()) else {
            continue;
        };
        if !(mnemonic.starts_with('b') || mnemonic.starts_with("cb")) {
            continue;
        }
        let register = !operands.contains("0x") && !operands.starts_with("lr");
        if (mnemonic.starts_with("blx") || mnemonic.starts_with("bx")) && register {
            if let Some(f) = funcs.last_mut() {
                f.3.push(format!("{mnemonic} {operands}"));
            }
            continue;
        }
        let Some(hex) = operands.split("0x").nth(1) else {
            continue;
        };
        let hex: String = hex.chars().take_while(|c| c.is_ascii_hexdigit()).collect();
        if let (Ok(t), Some(f)) = (u32::from_str_radix(&hex, 16), funcs.last_mut()) {
            f.2.push(t);
        }
    }
    funcs.sort_by_key(|f| f.0);
    let holder = |t: u32| funcs.partition_point(|f| f.0 <= t).checked_sub(1);
    let mut seen = vec![false; funcs.len()];
    let mut todo: Vec<usize> = funcs.iter().position(|f| f.1 == root).into_iter().collect();
    assert!(!todo.is_empty(), "{root} is not in {}", elf.display());
    while let Some(i) = todo.pop() {
        if std::mem::replace(&mut seen[i], true) {
            continue;
        }
        todo.extend(funcs[i].2.iter().filter_map(|&t| holder(t)));
    }
    funcs
        .iter()
        .zip(seen)
        .filter(|(_, s)| *s)
        .map(|(f, _)| (f.1.clone(), f.3.clone()))
        .collect()
}

/// The functions that handler `root` of `elf` reaches by direct branches and calls, not
/// entering those whose name contains `apart`, that execute floating-point instructions
/// (`v…`), with how many each holds. The tick keeps its floating-point models' steps in
/// calls of their own (`twinstack::models::Running::step_out_of_line`), so that no other
/// configuration's tick touches the FPU and pays its context
/// (`twinstack::config::tick_budget::FP_CONTEXT_CYCLES`): walked from the tick with that
/// name apart, nothing is listed.
pub fn floating_point_functions(elf: &Path, root: &str, apart: &str) -> Vec<(String, usize)> {
    let out = Command::new(objdump())
        .args(["-d", "--no-show-raw-insn", "--triple=thumbv7em-none-eabihf"])
        .arg(elf)
        .output()
        .expect("llvm-objdump runs");
    assert!(out.status.success(), "llvm-objdump failed");
    // (start address, name, branch targets, floating-point instructions), in address order.
    let mut funcs: Vec<(u32, String, Vec<u32>, usize)> = Vec::new();
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        if let Some(head) = line.strip_suffix(">:") {
            // An ARM mapping symbol (`$t`, `$d`: code or data follows) is not a function:
            // what follows it belongs to the function it sits in (a jump table's cases are
            // reached by falling through, not by a branch the walk sees).
            if let Some((addr, name)) = head.split_once(" <").filter(|(_, n)| !n.starts_with('$')) {
                if let Ok(a) = u32::from_str_radix(addr.trim(), 16) {
                    funcs.push((a, name.to_string(), Vec::new(), 0));
                    continue;
                }
            }
        }
        let Some((_, rest)) = line.trim_start().split_once(':') else {
            continue;
        };
        let mut parts = rest.split('\t').map(str::trim).filter(|p| !p.is_empty());
        let (Some(mnemonic), operands) = (parts.next(), parts.next().unwrap_or("")) else {
            continue;
        };
        let Some(f) = funcs.last_mut() else {
            continue;
        };
        if mnemonic.starts_with('v') {
            f.3 += 1;
        } else if mnemonic.starts_with('b') || mnemonic.starts_with("cb") {
            let hex: String = operands
                .split("0x")
                .nth(1)
                .unwrap_or("")
                .chars()
                .take_while(|c| c.is_ascii_hexdigit())
                .collect();
            if let Ok(t) = u32::from_str_radix(&hex, 16) {
                f.2.push(t);
            }
        }
    }
    funcs.sort_by_key(|f| f.0);
    let holder = |t: u32| funcs.partition_point(|f| f.0 <= t).checked_sub(1);
    let mut seen = vec![false; funcs.len()];
    let mut todo: Vec<usize> = funcs.iter().position(|f| f.1 == root).into_iter().collect();
    assert!(!todo.is_empty(), "{root} is not in {}", elf.display());
    while let Some(i) = todo.pop() {
        if std::mem::replace(&mut seen[i], true) || funcs[i].1.contains(apart) {
            continue;
        }
        todo.extend(funcs[i].2.iter().filter_map(|&t| holder(t)));
    }
    funcs
        .iter()
        .zip(seen)
        .filter(|((_, name, _, fp), s)| *s && *fp > 0 && !name.contains(apart))
        .map(|(f, _)| (f.1.clone(), f.3))
        .collect()
}

/// The panic paths handler `root` of `elf` links: the functions it reaches
/// ([`reachable_functions`]) that panic. Every panic — an assertion, a bound check, an
/// `unwrap`, `clamp`'s check of its bounds — ends in `core::panicking::panic_fmt` (or
/// `panic_nounwind_fmt`) and the panic handler, so a reached helper (`*_fail`, `expect_failed`)
/// brings one of those into the set as well; the names are matched in both manglings.
///
/// The walk follows direct branches only: when nothing reached panics, it also asserts that
/// nothing reached branches through a register, so that no call can hide from it.
pub fn panic_paths(elf: &Path, root: &str) -> Vec<String> {
    let reached = reachable_functions(&objdump(), elf, root);
    assert!(reached.len() > 1, "{root} calls out: {reached:?}");
    let panics: Vec<String> = reached
        .iter()
        .map(|(f, _)| f.clone())
        .filter(|f| {
            f.contains("panic")
                || f.contains("rust_begin_unwind")
                || f.contains("unwrap_failed")
                || f.contains("expect_failed")
                || f.ends_with("_fail")
                || f.contains("_fail17h")
        })
        .collect();
    if panics.is_empty() {
        let blind: Vec<_> = reached.iter().filter(|(_, i)| !i.is_empty()).collect();
        assert!(
            blind.is_empty(),
            "{root} reaches indirect branches the walk cannot follow: {blind:?}"
        );
    }
    panics
}

/// The longest critical section outside the tick that masks it (a lock on the tick's
/// resource, or interrupts off), instructions: how late a tick can start. The whole-interrupt
/// bench asserts it for every lock it runs (`tests/irq_bench.rs`), the tick bench for the
/// dual-stage coarse task's two exchanges with the loop (`tests/tick_bench.rs`).
pub const HELD_OFF_INSTRUCTIONS: u64 = 145;

/// The 64-bit library divisions (`compiler_builtins`' `__aeabi_uldivmod`, `__aeabi_ldivmod`
/// and what they call) that handler `root` of `elf` reaches by direct branches and calls. The
/// Cortex-M4 divides 32 bits in hardware (`UDIV`, `SDIV`, at most 12 cycles); a 64-bit
/// quotient is a library call of up to a few hundred instructions whose time depends on its
/// operands. A handler's divisions by settings are prepared off it (`twinstack::divisor`), so
/// that none is reached: a division the bench's paths happen to take with small operands,
/// cheaply, would still cost its worst on the board.
pub fn library_divisions(elf: &Path, root: &str) -> Vec<String> {
    reachable_functions(&objdump(), elf, root)
        .into_iter()
        .map(|(f, _)| f)
        .filter(|f| {
            [
                "divmoddi4",
                "divdi3",
                "moddi3",
                "ldivmod",
                "uldivmod",
                "64_div_rem",
            ]
            .iter()
            .any(|d| f.contains(d))
        })
        .collect()
}

/// `llvm-objdump`: on the path, or rustup's llvm-tools in the toolchain's sysroot.
pub fn objdump() -> PathBuf {
    llvm_tool("llvm-objdump", &[]).unwrap_or_else(|| {
        panic!("llvm-objdump is missing: run `cargo xtask setup` (it adds rustup's llvm-tools)")
    })
}

/// The interposer that gives QEMU's trace file a large buffer (`tests/support/trace_buffer.c`,
/// loaded with `LD_PRELOAD` for the file named by `TWINSTACK_TRACE_FILE`): QEMU line-buffers
/// its log and flushes it after every line, one `write(2)` per traced instruction. Built once
/// per test process with the system's C compiler (`cc`, the linker every Rust toolchain on
/// Linux links with) into [`firmware_target_dir`]. `None` off Linux (it needs glibc's
/// `dlsym(RTLD_NEXT, …)`), where the trace is the same, written a line at a time; on Linux a
/// compiler that fails is a failed test, not a silently slower bench.
pub fn trace_buffer() -> Option<PathBuf> {
    static BUILT: OnceLock<Option<PathBuf>> = OnceLock::new();
    BUILT
        .get_or_init(|| {
            if !cfg!(target_os = "linux") {
                return None;
            }
            let source = workspace_root().join("tests/support/trace_buffer.c");
            Some(compile_c(&source, "trace-buffer.so", &["-shared", "-fPIC"]))
        })
        .clone()
}

/// Compiles the C file `source` with `cc -O2 flags… -o firmware_target_dir()/out … -ldl`;
/// panics naming the file and the compiler's output if it fails.
pub fn compile_c(source: &Path, out: &str, flags: &[&str]) -> PathBuf {
    let dir = firmware_target_dir();
    std::fs::create_dir_all(&dir)
        .unwrap_or_else(|e| panic!("cannot create {}: {e}", dir.display()));
    let out = dir.join(out);
    let mut cmd = Command::new("cc");
    cmd.arg("-O2")
        .args(flags)
        .arg("-o")
        .arg(&out)
        .arg(source)
        .arg("-ldl");
    if let Err(e) = run_quiet(&mut cmd) {
        panic!(
            "cc could not build {} (the C compiler Rust links with on Linux): {e}",
            source.display()
        );
    }
    out
}

/// `llvm-objcopy`: on the path, rustup's llvm-tools, or the `rust-objcopy` every toolchain
/// ships in its sysroot (LLVM's objcopy under rustc's name).
pub fn objcopy() -> PathBuf {
    llvm_tool("llvm-objcopy", &["rust-objcopy"]).unwrap_or_else(|| {
        panic!("llvm-objcopy is missing: run `cargo xtask setup` (it adds rustup's llvm-tools)")
    })
}

/// The LLVM tool `name` on the path, else `name` or one of `others` in the toolchain's
/// sysroot (`lib/rustlib/<host>/bin`).
fn llvm_tool(name: &str, others: &[&str]) -> Option<PathBuf> {
    if Command::new(name).arg("--version").output().is_ok() {
        return Some(PathBuf::from(name));
    }
    let sysroot = Command::new("rustc")
        .args(["--print", "sysroot"])
        .output()
        .expect("rustc runs");
    let sysroot = String::from_utf8_lossy(&sysroot.stdout).trim().to_string();
    let host = Command::new("rustc")
        .arg("-vV")
        .output()
        .expect("rustc runs");
    let host = String::from_utf8_lossy(&host.stdout)
        .lines()
        .find_map(|l| l.strip_prefix("host: ").map(str::to_string))
        .expect("rustc -vV names the host");
    let bin = Path::new(&sysroot)
        .join("lib/rustlib")
        .join(host)
        .join("bin");
    std::iter::once(name)
        .chain(others.iter().copied())
        .map(|tool| bin.join(tool))
        .find(|p| p.is_file())
}
/// Cycles of the instruction `mnemonic operands` when it does not branch, on the Cortex-M4 at 0
/// wait states (the TRM's instruction set summary): loads and stores 2 (no pipelining of
/// neighbouring loads assumed), LDM/STM/PUSH/POP 1 + registers, SDIV/UDIV 12 (worst), VDIV/VSQRT
/// 14, VLDR/VSTR 2, VMLA/VMLS 3, everything else 1. A taken branch adds a pipeline refill of 3
/// (the TRM's worst), and at 5 wait states the flash's 5 more ([`traced_calls`]).
pub fn base_cycles(mnemonic: &str, operands: &str) -> u64 {
    let m = mnemonic.trim_end_matches(".w").trim_end_matches(".n");
    let regs = operands.matches(',').count() as u64 + 1;
    match m {
        _ if m.starts_with("push") || m.starts_with("pop") => 1 + regs,
        _ if m.starts_with("ldm") || m.starts_with("stm") => 1 + regs.saturating_sub(1),
        _ if m.starts_with("vpush") || m.starts_with("vpop") => 1 + regs,
        _ if m.starts_with("vldm") || m.starts_with("vstm") => 1 + regs.saturating_sub(1),
        "ldrd" | "strd" => 3,
        _ if m.starts_with("ldr") || m.starts_with("str") => 2,
        _ if m.starts_with("sdiv") || m.starts_with("udiv") => 12,
        _ if m.starts_with("vdiv") || m.starts_with("vsqrt") => 14,
        _ if m.starts_with("vldr") || m.starts_with("vstr") => 2,
        _ if m.starts_with("vmla") || m.starts_with("vmls") => 3,
        _ => 1,
    }
}

/// Whether `mnemonic operands` can change the flow (so `taken` is meaningful for it).
pub fn can_branch(m: &str, operands: &str) -> bool {
    m.starts_with('b') && !m.starts_with("bic") && !m.starts_with("bfc") && !m.starts_with("bfi")
        || m.starts_with("cbz")
        || m.starts_with("cbnz")
        || m.starts_with("tbb")
        || m.starts_with("tbh")
        || (m.starts_with("pop") || m.starts_with("ldm") || m.starts_with("ldr"))
            && operands.contains("pc")
        || m.starts_with("mov") && operands.starts_with("pc")
}

/// [`qemu_command`] for `elf` with its trace going to a new FIFO in [`firmware_target_dir`]
/// named after `name` (returned beside the command: the caller adds `-d … -D` with it, opens
/// it after spawning QEMU and removes it afterwards). QEMU writes its log a line at a time,
/// flushed: one system call per traced instruction, most of its time; the interposer
/// ([`trace_buffer`]) buffers the trace's file, without which the trace is the same, several
/// times slower.
pub fn traced_qemu(elf: &Path, name: &str) -> (Command, PathBuf) {
    let fifo = firmware_target_dir().join(format!("{name}.trace.fifo"));
    let _ = std::fs::remove_file(&fifo);
    let made = Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .expect("mkfifo runs");
    assert!(made.success(), "mkfifo {}", fifo.display());
    let mut qemu = qemu_command(elf);
    if let Some(buffer) = trace_buffer() {
        qemu.env("LD_PRELOAD", buffer)
            .env("TWINSTACK_TRACE_FILE", &fifo);
    }
    (qemu, fifo)
}

/// One invocation of a traced function: instructions and cycles (0 and 5 wait states) from its
/// first instruction to the return to its caller.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CallCost {
    /// Instructions executed.
    pub instructions: u64,
    /// Cycles at 0 wait states ([`base_cycles`], a taken branch 3 more).
    pub cycles: u64,
    /// Cycles at 5 wait states: every taken branch waits the flash's 5 more.
    pub cycles_ws5: u64,
}

/// Runs `elf` in QEMU (`extra` arguments beside `-icount shift=0 -singlestep -d exec,nochain`)
/// and costs every invocation of the function whose symbol starts with `function` (demangled,
/// e.g. `tick_bench::image::coarse_part`, which must be `#[inline(never)]` and called with
/// `bl`), each instruction by [`base_cycles`] and [`can_branch`] on the image's disassembly:
/// from its entry to the instruction after a `bl` to it. Panics, naming what, if the image
/// has no such function or QEMU fails.
pub fn traced_calls(elf: &Path, function: &str, extra: &[&str]) -> Vec<CallCost> {
    use std::io::BufRead;
    // The image's instructions: size, whether they can branch, their cycles.
    let out = Command::new(objdump())
        .args([
            "-d",
            "--demangle",
            "--no-show-raw-insn",
            "--triple=thumbv7em-none-eabihf",
        ])
        .arg(elf)
        .output()
        .expect("llvm-objdump runs");
    assert!(
        out.status.success(),
        "llvm-objdump failed on {}",
        elf.display()
    );
    let mut rows: Vec<(u32, bool, u64)> = Vec::new();
    let mut entry = None;
    let mut returns = std::collections::HashSet::new();
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        if let Some(label) = line.strip_suffix(">:") {
            if let Some((addr, symbol)) = label.split_once(" <") {
                if symbol.starts_with(function) {
                    entry = u32::from_str_radix(addr.trim(), 16).ok();
                }
            }
            continue;
        }
        let Some((addr, rest)) = line.trim_start().split_once(':') else {
            continue;
        };
        let Ok(addr) = u32::from_str_radix(addr, 16) else {
            continue;
        };
        let mut fields = rest.split_whitespace();
        let Some(mnemonic) = fields.next() else {
            continue;
        };
        let operands = rest
            .trim_start()
            .strip_prefix(mnemonic)
            .unwrap_or("")
            .split('@')
            .next()
            .unwrap_or("")
            .trim();
        if mnemonic == "bl" && operands.contains(&format!("<{function}")) {
            returns.insert(addr + 4);
        }
        rows.push((
            addr,
            can_branch(mnemonic, operands),
            base_cycles(mnemonic, operands),
        ));
    }
    let entry = entry.unwrap_or_else(|| panic!("{} has no function {function}", elf.display()));
    assert!(!returns.is_empty(), "nothing calls {function} with `bl`");
    // Each instruction's size: the distance to the next (2 or 4 bytes in Thumb-2).
    let mut code: HashMap<u32, (u32, bool, u64)> = HashMap::new();
    for (k, &(addr, branch, base)) in rows.iter().enumerate() {
        let size = rows
            .get(k + 1)
            .map(|n| n.0.wrapping_sub(addr))
            .filter(|&d| d == 2 || d == 4)
            .unwrap_or(4);
        code.insert(addr, (size, branch, base));
    }
    // The trace, through a FIFO (with the interposer that buffers it, where there is one).
    let name = elf.file_name().and_then(|n| n.to_str()).unwrap_or("image");
    let (mut qemu, fifo) = traced_qemu(elf, &format!("traced-calls-{name}"));
    let child = qemu
        .args(extra)
        .args([
            "-icount",
            "shift=0",
            "-singlestep",
            "-d",
            "exec,nochain",
            "-D",
        ])
        .arg(&fifo)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("qemu-system-arm starts");
    let trace = std::fs::File::open(&fifo).expect("open the trace FIFO");
    let mut calls = Vec::new();
    let mut current: Option<(CallCost, u32)> = None;
    for line in std::io::BufReader::with_capacity(1 << 20, trace).split(b'\n') {
        let Ok(line) = line else { break };
        // `Trace 0: 0x… [00800408/08000188/…] symbol`: the second field is the PC.
        let Some(pc) = line
            .iter()
            .position(|&b| b == b'[')
            .and_then(|i| line.get(i + 10..i + 18))
            .and_then(|h| std::str::from_utf8(h).ok())
            .and_then(|h| u32::from_str_radix(h, 16).ok())
        else {
            continue;
        };
        match current.as_mut() {
            None => {
                if pc == entry {
                    current = Some((CallCost::default(), pc));
                }
            }
            Some((cost, previous)) => {
                // The previous instruction, settled now that its successor is known.
                if let Some(&(size, branch, base)) = code.get(&*previous) {
                    let taken = branch && pc != previous.wrapping_add(size);
                    let c = base + if taken { 3 } else { 0 };
                    cost.instructions += 1;
                    cost.cycles += c;
                    cost.cycles_ws5 += c + if taken { 5 } else { 0 };
                }
                *previous = pc;
                if returns.contains(&pc) {
                    calls.push(*cost);
                    current = None;
                }
            }
        }
    }
    let out = child.wait_with_output().expect("qemu exits");
    let _ = std::fs::remove_file(&fifo);
    assert!(
        out.status.success(),
        "{} failed under the trace ({}): {}",
        elf.display(),
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    calls
}
