//! `cargo xtask` — the project's one setup step and its full set of test gates.
//!
//! * `cargo xtask setup` installs what the tests need, each only if it is missing: the
//!   `thumbv7em-none-eabihf` and `x86_64-pc-windows-gnu` standard libraries (rustup), `qemu-system-arm` (apt-get, as root on
//!   Debian/Ubuntu; elsewhere it prints the command and fails), `mdbook` (cargo install) and a
//!   Python virtual environment for the Python package's tests (`python3 -m venv` into
//!   `TARGET/py-venv`; `python3-venv` with apt-get where Debian lacks it), and Chromium with
//!   its WebDriver for the live view's browser test (apt-get, as root on Debian/Ubuntu).
//!   Running it again changes nothing.
//! * `cargo xtask test` runs `setup`, then every gate CI holds the project to, in order,
//!   stopping at the first that fails: the module graph (no cycles, `cargo xtask graph`), host
//!   tests (optimised, with overflow checks, and doc tests), the book's deterministic figures (`cargo xtask figures --check`),
//!   rustfmt, clippy on the host,
//!   clippy and builds of each firmware image on the target, `cargo check` of the host tool
//!   for Windows, the Python package (`pip install ./python` into the virtual environment —
//!   maturin, numpy, pytest, matplotlib, mypy, bluesky and selenium from PyPI — its own rustfmt
//!   and clippy, then
//!   pytest), rustdoc with warnings denied, and
//!   the docs book when there is one (`docs/book.toml`).
//!
//! `.ci/run` is `cargo xtask test`; the alias is in `.cargo/config.toml`. The installs and the
//! book's link check are in `setup.rs`, the gates here.

mod figures;
mod graph;
mod layers;
mod setup;

use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode, Stdio};
use std::time::Instant;

use setup::{check_links, ensure_python_venv, setup, target_dir, venv_python};

/// The firmware's target triple.
const TARGET: &str = "thumbv7em-none-eabihf";
/// A Windows target the host crates (the `twinstack` tool and the libraries under it) must keep compiling for: `cargo check` only
/// (no linker or C toolchain needed; serialport's Windows backend is plain Rust on
/// `windows-sys`).
const WINDOWS_TARGET: &str = "x86_64-pc-windows-gnu";
/// The mdbook `setup` installs when none is on the PATH (builds with Rust 1.85 and later).
const MDBOOK_VERSION: &str = "0.4.52";

/// Clippy on the target, one run per firmware image and feature set (package, `--bin`,
/// `--features` arguments), each with warnings denied.
const TARGET_CLIPPY: &[(&str, &[&str])] = &[
    ("twinstack-fw (board)", &["--bin", "twinstack-fw"]),
    (
        "twinstack-emu (emulator)",
        &["--bin", "twinstack-emu", "--features", "emulator"],
    ),
    (
        "twinstack-fw-dual (board, dual-stage)",
        &["--bin", "twinstack-fw-dual", "--features", "dual-stage"],
    ),
    (
        "twinstack-emu-dual (emulator, dual-stage)",
        &[
            "--bin",
            "twinstack-emu-dual",
            "--features",
            "emulator,dual-stage",
        ],
    ),
    (
        "twinstack-feather (Adafruit Feather STM32F405 Express)",
        &["--bin", "twinstack-feather", "--features", "feather"],
    ),
    (
        "twinstack-feather-emu (the Feather image for QEMU)",
        &[
            "--bin",
            "twinstack-feather-emu",
            "--features",
            "emulator,feather",
        ],
    ),
    (
        "QEMU test images (tick-bench, irq-bench, safe-state-probe, golden-replay)",
        &["-p", "twinstack-qemu-images", "--bins"],
    ),
];

/// What the Python gate installs into the virtual environment besides the package (maturin
/// comes with `pip install ./python`, as its build backend): the tests' runner, the example's
/// plotting, mypy, whose stubtest checks the shipped stubs against the module, bluesky, whose
/// RunEngine runs the package's devices, and selenium, which drives Chromium for `view`'s test.
const PYTHON_TEST_PACKAGES: &[&str] = &[
    "numpy",
    "pytest",
    "matplotlib",
    "mypy",
    "bluesky",
    "selenium",
];

/// rustdoc's flags for the documentation gate: every warning (broken or redundant links
/// included) fails it.
const RUSTDOCFLAGS: &str = "-D warnings";

const USAGE: &str = "usage: cargo xtask <command>

commands:
  setup   install what the tests need (thumbv7em and x86_64-pc-windows-gnu targets,
          qemu-system-arm, mdbook, a Python virtual environment), each only if missing
  test    setup, then every gate in order: tests (optimised, with overflow checks), fmt,
          clippy (host and target), firmware builds, the host tool checked for Windows, the Python
          package (pip install ./python, pytest), rustdoc, the docs book and its links; stops at
          the first failure
  python  the Python package's gates alone (virtual environment, pip install ./python,
          rustfmt and clippy of python/, pytest)
  links   check that every relative link in README.md and docs/src names a file that exists
  figures [--check] [NAME…] rewrite the book's generated figures from the commands' output
          (`--check`: the deterministic ones, compared and not written)
  graph   [--quiet] print each crate's module graph (the layers, see xtask/src/graph.rs) and fail on any
          cycle";

fn main() -> ExitCode {
    let command = std::env::args().nth(1);
    let result = match command.as_deref() {
        Some("setup") => setup(),
        Some("test") => setup().and_then(|()| test()),
        Some("python") => ensure_python_venv().and_then(|()| run_gates(python_gates())),
        Some("links") => check_links(),
        Some("figures") => figures::run(&root(), &std::env::args().skip(2).collect::<Vec<_>>()),
        Some("graph") => graph::run(&root(), std::env::args().any(|a| a == "--quiet"))
            .and_then(|()| layers::check(&root())),
        Some("help" | "-h" | "--help") => {
            println!("{USAGE}");
            Ok(())
        }
        Some(other) => Err(format!("unknown command `{other}`\n\n{USAGE}")),
        None => Err(USAGE.to_string()),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("\nxtask: {e}");
            ExitCode::FAILURE
        }
    }
}

/// The workspace root (this crate sits in `xtask/` below it).
fn root() -> PathBuf {
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR"));
    manifest.parent().unwrap_or(manifest).to_path_buf()
}

/// The cargo that runs us (`$CARGO`), or the one on the PATH.
fn cargo(args: &[&str]) -> Command {
    let mut cmd = Command::new(std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into()));
    cmd.args(args).current_dir(root());
    cmd
}

/// `cargo test --profile host-opt --workspace` followed by `args`: every host test gate runs
/// with the workspace's features, so no gate builds a crate again for another feature set.
fn host_tests(args: &[&str]) -> Command {
    let mut all = vec!["test", "--profile", HOST_PROFILE, "--workspace"];
    all.extend_from_slice(args);
    cargo(&all)
}

/// A cargo command for the firmware target: RUSTFLAGS from the environment would replace the
/// target's link arguments in `.cargo/config.toml`, so they are removed.
fn target_cargo(args: &[&str]) -> Command {
    let mut cmd = cargo(args);
    cmd.env_remove("RUSTFLAGS")
        .env_remove("CARGO_ENCODED_RUSTFLAGS")
        .env_remove("CARGO_BUILD_TARGET");
    cmd
}

/// Runs `cmd` with its output shown; `Err` names the command and its exit status.
fn run(cmd: &mut Command) -> Result<(), String> {
    let status = cmd
        .stdin(Stdio::null())
        .status()
        .map_err(|e| format!("cannot start {cmd:?}: {e}"))?;
    if status.success() {
        Ok(())
    } else {
        Err(format!("{cmd:?} failed ({status})"))
    }
}

/// One gate: what it checks, the command that checks it, and whether it runs beside the gates
/// after it or once those beside have finished.
struct Gate {
    what: String,
    cmd: Command,
    beside: bool,
    last: bool,
}

fn gate(what: impl Into<String>, cmd: Command) -> Gate {
    Gate {
        what: what.into(),
        cmd,
        beside: false,
        last: false,
    }
}

/// A gate that runs after every other, once the gates beside have finished: for one that reads
/// what a gate beside writes (the tick-cost page's figures, from the whole-interrupt bench).
fn gate_last(what: impl Into<String>, cmd: Command) -> Gate {
    Gate {
        last: true,
        ..gate(what, cmd)
    }
}

/// A gate that runs beside the gates after it (its output in a log file, its result collected
/// at the end): for a long single-threaded one (QEMU) whose core the others' builds and
/// scripts would otherwise leave idle. Its result depends on nothing they do.
fn gate_beside(what: impl Into<String>, cmd: Command) -> Gate {
    Gate {
        beside: true,
        ..gate(what, cmd)
    }
}

/// The profile every host gate builds with: optimised, with debug assertions and overflow
/// checks (`[profile.host-opt]` in the workspace manifest).
const HOST_PROFILE: &str = "host-opt";

/// Cargo's arguments that select the host tool `twinstack` in [`HOST_PROFILE`]: the build the
/// Python tests start and the book's figures run.
const TWINSTACK_BIN: [&str; 6] = [
    "--profile",
    HOST_PROFILE,
    "-p",
    "twinstack-cli",
    "--bin",
    "twinstack",
];

/// The bench test that traces every tick in QEMU (`tests/irq_bench.rs`): run in the
/// optimised gate only.
const IRQ_BENCH_SCENARIOS: &str = "the_whole_interrupt_in_every_scenario";

fn gates() -> Vec<Gate> {
    // `cargo test` runs the library crates' doc tests too: no separate `--doc` run.
    let mut gates = vec![
        gate(
            "module graph and crate layers: no cycles, no dependency on a layer above (cargo xtask graph)",
            cargo(&["run", "--quiet", "-p", "xtask", "--", "graph", "--quiet"]),
        ),
        // Every host test runs optimised with debug assertions and overflow checks (the
        // `host-opt` profile): identification, calibration and the studies are numeric work
        // that takes several times longer unoptimised. The whole-interrupt bench parses QEMU's
        // instruction trace of every tick (hundreds of millions of lines) and gets its own gate,
        // started beside the rest as soon as the tests are built: the host tests run one binary
        // after another, and a binary's last long test leaves a core to the bench.
        gate(
            "host tests, built (cargo test --profile host-opt --workspace --no-run)",
            host_tests(&["--no-run"]),
        ),
        // `--workspace`, as the host tests' gate: the same features, so the bench's test
        // builds nothing again (the package alone selects other features of the crates under it).
        gate_beside(
            "the whole interrupt in QEMU (cargo test --profile host-opt --workspace --test irq_bench)",
            host_tests(&["--test", "irq_bench"]),
        ),
        gate(
            "host tests and doc tests (cargo test --profile host-opt --workspace)",
            host_tests(&["--", "--skip", IRQ_BENCH_SCENARIOS]),
        ),
        gate(
            "the lab stage's variants (cargo test --profile host-opt --workspace --test stage_variants -- --ignored)",
            // `--workspace`, as the host tests' gate: the same features, so nothing is built
            // again (`-p twinstack-cli` alone leaves out the library's test doubles, which the
            // workspace's tests turn on, and rebuilt the tool and every crate under it).
            host_tests(&["--test", "stage_variants", "--", "--ignored"]),
        ),
        // After the bench beside, whose output the tick-cost page's figures are checked against.
        gate_last(
            "the book's deterministic figures match the code (cargo xtask figures --check)",
            cargo(&["run", "--quiet", "-p", "xtask", "--", "figures", "--check"]),
        ),
        gate("rustfmt", cargo(&["fmt", "--all", "--", "--check"])),
        gate(
            "clippy, host",
            cargo(&[
                "clippy",
                "--workspace",
                "--all-targets",
                "--",
                "-D",
                "warnings",
            ]),
        ),
    ];
    for (image, select) in TARGET_CLIPPY {
        let mut args = vec!["clippy", "--target", TARGET];
        args.extend_from_slice(select);
        args.extend_from_slice(&["--", "-D", "warnings"]);
        gates.push(gate(
            format!("clippy, {TARGET}: {image}"),
            target_cargo(&args),
        ));
    }
    gates.push(gate(
        "board image with the dual-stage coarse axis (cargo build-fw-dual)",
        target_cargo(&["build-fw-dual"]),
    ));
    gates.push(gate(
        "board image (cargo build-fw)",
        target_cargo(&["build-fw"]),
    ));
    gates.push(gate(
        "Feather image (cargo build-fw-feather)",
        target_cargo(&["build-fw-feather"]),
    ));
    // The host tool on Windows: the Unix-socket transport is `cfg(unix)`; everything else
    // (serial ports, TCP to an emulator, the simulated board) must compile there.
    gates.push(gate(
        format!(
            "the host tool for Windows (cargo check -p twinstack-cli --target {WINDOWS_TARGET})"
        ),
        target_cargo(&["check", "-p", "twinstack-cli", "--target", WINDOWS_TARGET]),
    ));
    gates.extend(python_gates());
    let mut doc = cargo(&["doc", "--workspace", "--no-deps"]);
    doc.env("RUSTDOCFLAGS", RUSTDOCFLAGS);
    gates.push(gate("rustdoc, warnings denied", doc));
    if root().join("docs/book.toml").is_file() {
        let mut book = Command::new("mdbook");
        book.args(["build", "docs"]).current_dir(root());
        gates.push(gate("docs book (mdbook build docs)", book));
        gates.push(gate(
            "links in README.md and the book (cargo xtask links)",
            cargo(&["run", "--quiet", "-p", "xtask", "--", "links"]),
        ));
    }
    gates
}

/// The Python package (`python/`, its own cargo workspace): its Rust formatted and clippy-clean,
/// installed with pip into the virtual environment `setup` made (maturin builds it from PyPI's
/// wheel; the build goes to `TARGET/python`), then its pytest suite against the in-process board
/// and a `twinstack virtual-board` process (the optimised `twinstack` the host tests built).
fn python_gates() -> Vec<Gate> {
    let manifest = root().join("python").join("Cargo.toml");
    let manifest = manifest.to_string_lossy().into_owned();
    let build = target_dir().join("python");
    let python = venv_python();
    let pip = |args: &[&str]| {
        let mut cmd = Command::new(&python);
        cmd.args([
            "-m",
            "pip",
            "install",
            "--disable-pip-version-check",
            "--quiet",
        ])
        .args(args)
        .current_dir(root())
        .env("CARGO_TARGET_DIR", &build);
        cmd
    };
    let mut fmt = cargo(&["fmt", "--manifest-path", &manifest, "--", "--check"]);
    fmt.env("CARGO_TARGET_DIR", &build);
    let mut clippy = cargo(&[
        "clippy",
        "--manifest-path",
        &manifest,
        "--",
        "-D",
        "warnings",
    ]);
    clippy.env("CARGO_TARGET_DIR", &build);
    let mut pytest = Command::new(&python);
    pytest
        .args(["-m", "pytest", "-q", "python/tests"])
        .current_dir(root())
        .env(
            "TWINSTACK_HAL_SIM",
            target_dir()
                .join(HOST_PROFILE)
                .join(format!("twinstack{}", std::env::consts::EXE_SUFFIX)),
        );
    vec![
        gate(
            format!(
                "Python: test packages in the virtual environment ({})",
                PYTHON_TEST_PACKAGES.join(", ")
            ),
            pip(PYTHON_TEST_PACKAGES),
        ),
        gate("Python: rustfmt of python/", fmt),
        gate("Python: clippy of python/", clippy),
        gate(
            "Python: the package (pip install ./python)",
            pip(&["--force-reinstall", "--no-deps", "./python"]),
        ),
        gate(
            "Python: the twinstack binary the tests start (cargo build --profile host-opt -p twinstack-cli)",
            cargo(&[&["build"][..], &TWINSTACK_BIN].concat()),
        ),
        gate("Python: pytest python/tests", pytest),
    ]
}

fn test() -> Result<(), String> {
    run_gates(gates())
}

/// Runs `gates` in order, stopping at the first that fails, with each one's time; a gate marked
/// beside runs in the background from its turn on, and its result is collected after the rest;
/// a gate marked last runs after that, in order.
fn run_gates(mut gates: Vec<Gate>) -> Result<(), String> {
    let total = gates.len();
    let start = Instant::now();
    let mut beside: Vec<Beside> = Vec::new();
    for (i, g) in gates.iter_mut().enumerate() {
        if g.last {
            continue;
        }
        if g.beside {
            let b = Beside::spawn(i + 1, &g.what, &mut g.cmd)?;
            println!(
                "\n== [{}/{total}] {} (beside the gates after it; its output: {})",
                i + 1,
                g.what,
                b.log.display()
            );
            beside.push(b);
            continue;
        }
        println!("\n== [{}/{total}] {}", i + 1, g.what);
        let t = Instant::now();
        run(&mut g.cmd).map_err(|e| {
            for b in &mut beside {
                b.stop();
            }
            format!(
                "gate {}/{total} failed: {}\n{e}\nThe gates after it did not run; fix it and run \
                 `cargo xtask test` again.",
                i + 1,
                g.what
            )
        })?;
        println!("   ok ({:.0} s)", t.elapsed().as_secs_f64());
    }
    for mut b in beside {
        println!("\n== [{}/{total}] {}: waiting for it", b.index, b.what);
        b.finish().map_err(|e| {
            format!(
                "gate {}/{total} failed: {}\n{e}\nFix it and run `cargo xtask test` again.",
                b.index, b.what
            )
        })?;
        println!("   ok ({:.0} s)", b.started.elapsed().as_secs_f64());
    }
    for (i, g) in gates.iter_mut().enumerate().filter(|(_, g)| g.last) {
        println!("\n== [{}/{total}] {}", i + 1, g.what);
        let t = Instant::now();
        run(&mut g.cmd).map_err(|e| format!("gate {}/{total} failed: {}\n{e}", i + 1, g.what))?;
        println!("   ok ({:.0} s)", t.elapsed().as_secs_f64());
    }
    println!(
        "\nAll {total} gates passed ({:.0} s).",
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

/// A gate running in the background, its output going to a log file.
struct Beside {
    index: usize,
    what: String,
    child: std::process::Child,
    log: PathBuf,
    started: Instant,
}

impl Beside {
    fn spawn(index: usize, what: &str, cmd: &mut Command) -> Result<Self, String> {
        let dir = target_dir().join("xtask");
        std::fs::create_dir_all(&dir)
            .map_err(|e| format!("cannot create {}: {e}", dir.display()))?;
        let log = dir.join(format!("gate-{index}.log"));
        let file = std::fs::File::create(&log)
            .map_err(|e| format!("cannot create {}: {e}", log.display()))?;
        let err = file
            .try_clone()
            .map_err(|e| format!("{}: {e}", log.display()))?;
        let child = cmd
            .stdin(Stdio::null())
            .stdout(file)
            .stderr(err)
            .spawn()
            .map_err(|e| format!("cannot start {cmd:?}: {e}"))?;
        Ok(Self {
            index,
            what: what.to_string(),
            child,
            log,
            started: Instant::now(),
        })
    }

    /// Waits for it; on failure the error carries the end of its log.
    fn finish(&mut self) -> Result<(), String> {
        let status = self
            .child
            .wait()
            .map_err(|e| format!("cannot wait for the gate: {e}"))?;
        if status.success() {
            return Ok(());
        }
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        let lines: Vec<&str> = text.lines().collect();
        let tail = lines[lines.len().saturating_sub(80)..].join("\n");
        Err(format!(
            "it failed ({status}); the end of {}:\n{tail}",
            self.log.display()
        ))
    }

    /// Stops it (another gate failed first).
    fn stop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_host_test_gate_runs_the_command_its_name_shows() {
        let mut seen = 0;
        for g in gates() {
            let Some(shown) = g.what.split_once("(cargo test ").map(|(_, c)| c) else {
                continue;
            };
            let shown: Vec<&str> = shown.trim_end_matches(')').split(' ').collect();
            let args: Vec<String> = g
                .cmd
                .get_args()
                .map(|a| a.to_string_lossy().into_owned())
                .collect();
            assert_eq!(args[0], "test", "{}", g.what);
            assert!(
                args[1..].starts_with(&shown.iter().map(|s| s.to_string()).collect::<Vec<_>>()),
                "{}: runs {args:?}",
                g.what
            );
            seen += 1;
        }
        assert!(
            seen >= 4,
            "the host tests' build and run, the bench and the variants"
        );
    }

    fn shell(script: &str) -> Command {
        let mut cmd = Command::new("sh");
        cmd.args(["-c", script]);
        cmd
    }

    #[test]
    fn a_gate_beside_the_others_is_waited_for_and_its_failure_reported_with_its_log() {
        let gates = vec![
            gate_beside(
                "beside, failing",
                shell("sleep 0.2; echo the-bench-said-this; exit 3"),
            ),
            gate("after it", shell("true")),
        ];
        let e = run_gates(gates).unwrap_err();
        assert!(e.contains("beside, failing"), "{e}");
        assert!(e.contains("the-bench-said-this"), "{e}");
        let gates = vec![
            gate_beside("beside, passing", shell("sleep 0.2")),
            gate("after it", shell("true")),
        ];
        assert!(run_gates(gates).is_ok());
    }

    #[test]
    fn a_last_gate_runs_after_the_gate_beside_has_finished() {
        let dir = std::env::temp_dir().join(format!("xtask-last-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("written");
        let gates = vec![
            gate_beside(
                "beside, writes",
                shell(&format!("sleep 0.5; echo x > {}", file.display())),
            ),
            gate_last("reads", shell(&format!("test -f {}", file.display()))),
            gate("runs first", shell("true")),
        ];
        let ran = run_gates(gates);
        let _ = std::fs::remove_dir_all(&dir);
        assert!(ran.is_ok(), "{ran:?}");
    }

    #[test]
    fn a_failing_gate_stops_the_run_and_the_one_beside_it() {
        let gates = vec![
            gate_beside("beside", shell("sleep 30")),
            gate("fails", shell("exit 1")),
            gate("never runs", shell("exit 1")),
        ];
        let t = Instant::now();
        let e = run_gates(gates).unwrap_err();
        assert!(e.contains("gate 2/3 failed: fails"), "{e}");
        assert!(
            t.elapsed().as_secs() < 25,
            "the gate beside was stopped, not waited for"
        );
    }
}
