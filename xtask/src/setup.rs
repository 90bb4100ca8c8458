//! Setting up a fresh machine for `cargo xtask test`: the target, QEMU, objdump, mdBook,
//! Chromium and its driver, the Python virtual environment with its pinned packages; and the
//! book's link check. Each `ensure_*` installs what is missing (through apt where it needs the
//! system's packages) and says what it found.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use crate::{cargo, root, run, MDBOOK_VERSION, TARGET, WINDOWS_TARGET};

/// The first line of `program --version`, or `None` when it does not run.
fn version(program: &str) -> Option<String> {
    let out = Command::new(program)
        .arg("--version")
        .stdin(Stdio::null())
        .stderr(Stdio::null())
        .output()
        .ok()?;
    out.status.success().then(|| {
        String::from_utf8_lossy(&out.stdout)
            .lines()
            .next()
            .unwrap_or("")
            .trim()
            .to_string()
    })
}

pub(crate) fn setup() -> Result<(), String> {
    println!("== setup");
    ensure_target(TARGET)?;
    ensure_target(WINDOWS_TARGET)?;
    ensure_qemu()?;
    ensure_mdbook()?;
    ensure_objdump()?;
    ensure_python_venv()?;
    ensure_chromium()?;
    Ok(())
}

/// Chromium and its WebDriver (`view`'s browser test), with apt-get as root on Debian/Ubuntu
/// when either is missing; elsewhere the test skips and this says how to install them.
fn ensure_chromium() -> Result<(), String> {
    let found = |names: &[&str]| names.iter().find_map(|n| version(n));
    let browser = found(&["chromium", "chromium-browser"]);
    let driver = found(&["chromedriver"]);
    if let (Some(b), Some(d)) = (&browser, &driver) {
        println!("   chromium: already installed ({b}; {d})");
        return Ok(());
    }
    if !(Path::new("/etc/debian_version").is_file() && is_root()) {
        println!(
            "   chromium: missing; `view`'s browser test skips until Chromium and chromedriver \
             are on the PATH (Debian/Ubuntu: sudo apt-get install chromium chromium-driver)"
        );
        return Ok(());
    }
    apt_install(&["chromium", "chromium-driver"])?;
    let v = found(&["chromium"]).ok_or("apt-get installed chromium, but it does not run")?;
    println!("   chromium: installed with apt-get ({v})");
    Ok(())
}

/// The build directory: `$CARGO_TARGET_DIR`, else `target/` at the root.
pub(crate) fn target_dir() -> PathBuf {
    match std::env::var_os("CARGO_TARGET_DIR") {
        Some(dir) if Path::new(&dir).is_absolute() => PathBuf::from(dir),
        Some(dir) => root().join(dir),
        None => root().join("target"),
    }
}

/// The virtual environment the Python package is tested in.
fn python_venv() -> PathBuf {
    target_dir().join("py-venv")
}

/// The virtual environment's interpreter.
pub(crate) fn venv_python() -> PathBuf {
    if cfg!(windows) {
        python_venv().join("Scripts").join("python.exe")
    } else {
        python_venv().join("bin").join("python")
    }
}

/// A Python 3.8 or later on the PATH (`python3`, else `python`).
fn system_python() -> Option<String> {
    ["python3", "python"].into_iter().find_map(|p| {
        let out = Command::new(p)
            .args(["-c", "import sys; print(sys.version_info >= (3, 8))"])
            .stdin(Stdio::null())
            .stderr(Stdio::null())
            .output()
            .ok()?;
        (out.status.success() && String::from_utf8_lossy(&out.stdout).trim() == "True")
            .then(|| p.to_string())
    })
}

/// `python3 -m venv TARGET/py-venv`, unless it exists and runs. Where the venv module is
/// missing (Debian splits it into `python3-venv`), installs it with apt-get as root on
/// Debian/Ubuntu; otherwise prints what to install and fails.
pub(crate) fn ensure_python_venv() -> Result<(), String> {
    let venv = python_venv();
    if let Some(v) = version(&venv_python().to_string_lossy()) {
        println!(
            "   Python virtual environment: already there ({v}, {})",
            venv.display()
        );
        return Ok(());
    }
    let debian = Path::new("/etc/debian_version").is_file();
    let create = |python: &str| {
        Command::new(python)
            .args(["-m", "venv", "--clear"])
            .arg(&venv)
            .stdin(Stdio::null())
            .status()
            .is_ok_and(|s| s.success())
    };
    let python = match system_python() {
        Some(p) => p,
        None if debian && is_root() => {
            apt_install(&["python3", "python3-venv"])?;
            system_python().ok_or("apt-get installed python3, but it does not run")?
        }
        None => {
            return Err(
                "Python 3.8 or later is missing: install it (python3 on the PATH) and run \
                 `cargo xtask setup` again"
                    .into(),
            )
        }
    };
    if !create(&python) {
        if !(debian && is_root()) {
            return Err(format!(
                "`{python} -m venv {}` failed: install Python's venv module (Debian/Ubuntu: \
                 `sudo apt-get install python3-venv`) and run `cargo xtask setup` again",
                venv.display()
            ));
        }
        apt_install(&["python3-venv"])?;
        if !create(&python) {
            return Err(format!("`{python} -m venv {}` failed", venv.display()));
        }
    }
    let v = version(&venv_python().to_string_lossy())
        .ok_or("the virtual environment was made, but its python does not run")?;
    println!(
        "   Python virtual environment: created ({v}, {})",
        venv.display()
    );
    Ok(())
}

/// `apt-get update && apt-get install -y PACKAGES` (as root on Debian/Ubuntu).
fn apt_install(packages: &[&str]) -> Result<(), String> {
    let mut install = vec!["install", "-y"];
    install.extend_from_slice(packages);
    for args in [&["update"][..], &install] {
        run(Command::new("apt-get")
            .args(args)
            .env("DEBIAN_FRONTEND", "noninteractive"))?;
    }
    Ok(())
}

/// `llvm-objdump` for the whole-interrupt bench's cycle estimate (`tests/irq_bench.rs`): the
/// system's if there is one, else rustup's `llvm-tools` component.
fn ensure_objdump() -> Result<(), String> {
    if let Some(v) = version("llvm-objdump") {
        println!(
            "   llvm-objdump: already installed ({})",
            v.lines().next().unwrap_or("")
        );
        return Ok(());
    }
    run(Command::new("rustup")
        .args(["component", "add", "llvm-tools"])
        .current_dir(root()))?;
    println!("   llvm-objdump: installed (rustup component add llvm-tools)");
    Ok(())
}

/// Every relative link in `README.md` and `docs/src/**/*.md` names a file that exists
/// (anchors and web links are not followed).
pub(crate) fn check_links() -> Result<(), String> {
    let root = root();
    let mut files = vec![root.join("README.md")];
    let mut dirs = vec![root.join("docs/src")];
    while let Some(dir) = dirs.pop() {
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                dirs.push(p);
            } else if p.extension().is_some_and(|x| x == "md") {
                files.push(p);
            }
        }
    }
    let mut broken = Vec::new();
    let mut checked = 0;
    for file in &files {
        let text = std::fs::read_to_string(file).map_err(|e| format!("{}: {e}", file.display()))?;
        for (n, line) in text.lines().enumerate() {
            let mut rest = line;
            while let Some(i) = rest.find("](") {
                rest = &rest[i + 2..];
                let Some(end) = rest.find(')') else { break };
                let target = &rest[..end];
                rest = &rest[end..];
                let target = target.split_whitespace().next().unwrap_or("");
                if target.is_empty()
                    || target.starts_with('#')
                    || target.contains("://")
                    || target.starts_with("mailto:")
                {
                    continue;
                }
                let path = target.split('#').next().unwrap_or(target);
                checked += 1;
                let base = file.parent().unwrap_or(&root);
                if !base.join(path).exists() {
                    broken.push(format!("{}:{}: {target}", file.display(), n + 1));
                }
            }
        }
    }
    if broken.is_empty() {
        println!(
            "   {checked} relative links in {} files: all resolve",
            files.len()
        );
        Ok(())
    } else {
        Err(format!("broken links:\n{}", broken.join("\n")))
    }
}

/// `rustup target add TARGET`, unless it is installed.
fn ensure_target(target: &str) -> Result<(), String> {
    let installed = Command::new("rustup")
        .args(["target", "list", "--installed"])
        .current_dir(root())
        .stdin(Stdio::null())
        .output()
        .map_err(|e| {
            format!(
                "cannot run rustup ({e}): install the {target} standard library for your \
                 toolchain (https://rustup.rs, then `rustup target add {target}`)"
            )
        })?;
    if String::from_utf8_lossy(&installed.stdout)
        .lines()
        .any(|l| l.trim() == target)
    {
        println!("   {target}: already installed");
        return Ok(());
    }
    run(Command::new("rustup")
        .args(["target", "add", target])
        .current_dir(root()))?;
    println!("   {target}: installed (rustup target add {target})");
    Ok(())
}

fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .stdin(Stdio::null())
        .output()
        .map(|o| o.status.success() && String::from_utf8_lossy(&o.stdout).trim() == "0")
        .unwrap_or(false)
}

/// `apt-get update && apt-get install -y qemu-system-arm` when it is missing and we are root
/// on Debian or Ubuntu; otherwise the command to run, and failure.
fn ensure_qemu() -> Result<(), String> {
    if let Some(v) = version("qemu-system-arm") {
        println!("   qemu-system-arm: already installed ({v})");
        return Ok(());
    }
    let debian = Path::new("/etc/debian_version").is_file();
    if !(debian && is_root()) {
        let how = if debian {
            "sudo apt-get update && sudo apt-get install -y qemu-system-arm".to_string()
        } else {
            "install QEMU's Arm system emulator with your package manager so that \
             `qemu-system-arm` is on the PATH (e.g. `brew install qemu`, \
             `sudo dnf install qemu-system-arm`)"
                .to_string()
        };
        return Err(format!(
            "qemu-system-arm is missing, and xtask installs it itself only as root on \
             Debian/Ubuntu. Install it:\n    {how}\nthen run `cargo xtask setup` again."
        ));
    }
    for args in [&["update"][..], &["install", "-y", "qemu-system-arm"]] {
        run(Command::new("apt-get")
            .args(args)
            .env("DEBIAN_FRONTEND", "noninteractive"))?;
    }
    let v = version("qemu-system-arm")
        .ok_or("apt-get installed qemu-system-arm, but `qemu-system-arm --version` fails")?;
    println!("   qemu-system-arm: installed with apt-get ({v})");
    Ok(())
}

/// `cargo install mdbook --locked --version MDBOOK_VERSION`, unless an mdbook runs.
fn ensure_mdbook() -> Result<(), String> {
    if let Some(v) = version("mdbook") {
        println!("   mdbook: already installed ({v})");
        return Ok(());
    }
    run(&mut cargo(&[
        "install",
        "mdbook",
        "--locked",
        "--version",
        MDBOOK_VERSION,
    ]))?;
    let v = version("mdbook").ok_or(
        "cargo installed mdbook, but `mdbook --version` fails: is cargo's bin directory \
         (~/.cargo/bin) on the PATH?",
    )?;
    println!("   mdbook: installed with cargo install ({v})");
    Ok(())
}
