//! Tick-cost bench: instructions per control tick in QEMU, and the firmware image's size.
//!
//! `cargo test --test tick_bench -- --nocapture` builds the `tick-bench` image (`qemu-images/`) and the board
//! and emulator firmware images and the Feather image (into `target/firmware`), runs the bench in
//! `qemu-system-arm -machine netduinoplus2 -icount shift=0` (one guest instruction per
//! virtual nanosecond, TIM2 counting at 1 GHz, so counts are exact and repeatable) and prints
//! a table. It fails if the bench does not run or report every configuration, or if the board
//! image or the Feather image exceeds its 128 KiB flash budget; the instruction target (≤ 250 for inverse P–I
//! N = 16 with observer and feedback) is printed, not asserted, because it is a property of
//! the library's tick (src/control/mod.rs), not of this harness.

mod support;

use std::time::Duration;

/// Flash budget of the board image, bytes: 140 KiB of the 896 KiB it may use (sectors 0–10),
/// just above the image (the tick-cost page's size table): room for the model family
/// (generalised P–I, creep, Bouc–Wen) and the preview (its design on the board and the
/// reading of records stored before it), tight enough to catch a path written into every
/// caller (a model's or the creep's step inlined once per model variant) or a formatting
/// machinery pulled in. Raising it is a decision, taken where an image outgrows it.
const FLASH_BUDGET: u64 = 140 * 1024;
/// Instruction budget of the N = 16 tick.
const TICK_BUDGET: f64 = 250.0;
/// The exception's entry and return, cycles (the Cortex-M4's 12 in, 10 out, with the FPU's
/// context not stacked): charged to the coarse task, an interrupt of its own, as the
/// whole-interrupt bench charges the tick (`tests/irq_bench.rs`).
const ENTRY_EXIT_CYCLES: u64 = 22;
/// A lock of the tick's resource from the instruction that masks the tick to the one that
/// unmasks it, less its body, as the board's TIM3 binding runs it: `MSR BASEPRI_MAX`, two
/// `ISB`s, `MSR BASEPRI`. (The bench's body is a call of its own, its entry and return
/// counted with it: a little more than the board's, inlined.)
const LOCK_INSTRUCTIONS: u64 = 4;

/// One `BENCH` line.
#[derive(Debug)]
struct Row {
    name: String,
    ticks: u64,
    total: u64,
    min: u64,
    max: u64,
    overhead: u64,
}

fn parse_row(line: &str) -> Result<Row, String> {
    let rest = line
        .strip_prefix("BENCH ")
        .ok_or_else(|| format!("not a BENCH line: {line:?}"))?;
    let field = |key: &str| -> Result<&str, String> {
        rest.split(' ')
            .find_map(|kv| kv.strip_prefix(key).and_then(|v| v.strip_prefix('=')))
            .ok_or_else(|| format!("field {key} missing in {line:?}"))
    };
    let num = |key: &str| -> Result<u64, String> {
        field(key)?
            .parse()
            .map_err(|e| format!("field {key} in {line:?}: {e}"))
    };
    Ok(Row {
        name: field("name")?.to_string(),
        ticks: num("ticks")?,
        total: num("total")?,
        min: num("min")?,
        max: num("max")?,
        overhead: num("overhead")?,
    })
}

/// The opt-level the firmware images are built with: the `twinstack` package's release
/// override in `Cargo.toml` (the images are that package's binaries), else the profile's.
fn firmware_opt_level() -> String {
    let manifest = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/Cargo.toml"))
        .expect("read Cargo.toml");
    let level_in = |section: &str| {
        let start = manifest.find(section)? + section.len();
        let body = &manifest[start..];
        let body = &body[..body.find("\n[").unwrap_or(body.len())];
        let line = body
            .lines()
            .find(|l| l.trim_start().starts_with("opt-level"))?;
        Some(line.split('=').nth(1)?.trim().trim_matches('"').to_string())
    };
    level_in("[profile.release.package.twinstack]")
        .or_else(|| level_in("[profile.release]"))
        .unwrap_or_else(|| "3".to_string())
}

/// One `PART` line: a piece of the tick measured alone (call overhead included).
#[derive(Debug)]
struct Part {
    name: String,
    ticks: u64,
    total: u64,
    max: u64,
}

fn parse_part(line: &str) -> Result<Part, String> {
    let rest = line
        .strip_prefix("PART ")
        .ok_or_else(|| format!("not a PART line: {line:?}"))?;
    let field = |key: &str| -> Result<&str, String> {
        rest.split(' ')
            .find_map(|kv| kv.strip_prefix(key).and_then(|v| v.strip_prefix('=')))
            .ok_or_else(|| format!("field {key} missing in {line:?}"))
    };
    let num = |key: &str| -> Result<u64, String> {
        field(key)?
            .parse()
            .map_err(|e| format!("field {key} in {line:?}: {e}"))
    };
    Ok(Part {
        name: field("name")?.to_string(),
        ticks: num("ticks")?,
        total: num("total")?,
        max: num("max")?,
    })
}

fn run_bench() -> (Vec<Row>, Vec<Part>) {
    let elf = support::build_image(support::QEMU_IMAGES, "tick-bench", &[]);
    let out = support::run_to_exit(
        &elf,
        &["-icount", "shift=0", "-serial", "null"],
        "the bench image",
        Duration::from_secs(300),
    );
    let rows = out
        .lines()
        .filter(|l| l.starts_with("BENCH "))
        .map(|l| parse_row(l).unwrap_or_else(|e| panic!("{e}")))
        .collect();
    let parts = out
        .lines()
        .filter(|l| l.starts_with("PART "))
        .map(|l| parse_part(l).unwrap_or_else(|e| panic!("{e}")))
        .collect();
    (rows, parts)
}

/// Where the test writes what it printed, relative to the workspace root, once every
/// assertion holds (read by `cargo xtask figures tick-bench`).
const FIGURES_MD: &str = "target/figures/tick-bench.md";

/// Prints a line and keeps it in `$md`.
macro_rules! out {
    ($md:ident) => {{
        println!();
        $md.push('\n');
    }};
    ($md:ident, $($arg:tt)*) => {{
        let line = format!($($arg)*);
        println!("{line}");
        $md.push_str(&line);
        $md.push('\n');
    }};
}

#[test]
fn tick_cost_table_and_image_size() {
    // What the test prints, kept for the tick-cost page (`cargo xtask figures tick-bench`).
    let mut md = String::new();
    let (rows, parts) = run_bench();
    let expected = [
        "bypass",
        "none-observer-only",
        "none",
        "inverse-pi-8",
        "inverse-pi-16",
        "inverse-pi-32",
        "inverse-duhem",
        "none-sensor-drift",
        "none-pid-notch",
        "inverse-gpi-16",
        "inverse-pi-16-creep-4",
        "inverse-bouc-wen",
        "inverse-bouc-wen-bouc-wen",
    ];
    let names: Vec<&str> = rows.iter().map(|r| r.name.as_str()).collect();
    assert_eq!(names, expected, "the bench must report every configuration");
    for r in &rows {
        assert!(
            r.ticks > 0 && r.min > 0 && r.min <= r.max,
            "implausible row {r:?}"
        );
    }

    out!(md);
    out!(
        md,
        "Instructions per control tick (QEMU netduinoplus2, -icount shift=0, opt-level {}, \
         `Controller::tick` on the firmware's DAC/ADC drivers, 1000 ticks of a ±0.95 triangle):",
        firmware_opt_level()
    );
    out!(md);
    out!(
        md,
        "| compensator | observer | feedback | mean | min | max |"
    );
    out!(md, "|---|---|---|---:|---:|---:|");
    for r in &rows {
        let (comp, obs, fb) = match r.name.as_str() {
            "bypass" => ("none", "off", "off"),
            "none-observer-only" => ("none", "Duhem", "off"),
            "none" => ("none", "Duhem", "PI"),
            "inverse-pi-8" => ("inverse P–I, N = 8", "Duhem", "PI"),
            "inverse-pi-16" => ("inverse P–I, N = 16", "Duhem", "PI"),
            "inverse-pi-32" => ("inverse P–I, N = 32", "Duhem", "PI"),
            "none-sensor-drift" => ("none", "Duhem", "sensor + drift check (bypass)"),
            "none-pid-notch" => ("none", "Duhem", "PID + notch"),
            "inverse-duhem" => ("inverse Duhem", "Duhem", "PI"),
            "inverse-gpi-16" => (
                "inverse generalised P–I, N = 16, 6 dead zones",
                "Duhem",
                "PI",
            ),
            "inverse-pi-16-creep-4" => (
                "inverse P–I, N = 16, + inverse creep (4 modes)",
                "Duhem + creep",
                "PI",
            ),
            "inverse-bouc-wen" => ("inverse Bouc–Wen", "Duhem", "PI"),
            "inverse-bouc-wen-bouc-wen" => ("inverse Bouc–Wen", "Bouc–Wen", "PI"),
            other => panic!("unknown bench row {other}"),
        };
        out!(
            md,
            "| {comp} | {obs} | {fb} | {:.1} | {} | {} |",
            r.total as f64 / r.ticks as f64,
            r.min,
            r.max
        );
    }
    out!(
        md,
        "\n(net of the {}-instruction timer bracket; each count still includes the call, `BL` and \
         argument moves, which the firmware's inlined tick does not pay)",
        rows[0].overhead
    );
    let n16 = &rows[4];
    let n16_mean = n16.total as f64 / n16.ticks as f64;
    out!(
        md,
        "target: inverse P–I N = 16 + observer + feedback ≤ {TICK_BUDGET} instructions per tick: \
         {} (mean {n16_mean:.1}; max {}, on the ticks where the P–I memory changes)",
        if n16_mean <= TICK_BUDGET {
            "met"
        } else {
            "NOT met"
        },
        n16.max
    );

    let part_names: Vec<&str> = parts.iter().map(|p| p.name.as_str()).collect();
    assert_eq!(
        part_names,
        [
            "drive-split",
            "duhem-observer-step",
            "inverse-pi-16-step",
            "inverse-pi-16-full-steps",
            "dac-write",
            "gpi-16-6-observer-step",
            "inverse-gpi-16-6-step",
            "coarse-tick"
        ],
        "the bench must report every part"
    );
    out!(
        md,
        "\nParts of the tick measured alone (each includes its own call, ≈ 14 instructions):"
    );
    out!(md, "\n| part | mean | max |");
    out!(md, "|---|---:|---:|");
    for p in parts.iter().filter(|p| p.name != "coarse-tick") {
        out!(
            md,
            "| {} | {:.1} | {} |",
            p.name,
            p.total as f64 / p.ticks as f64,
            p.max
        );
    }
    // Not a part of the tick: the dual-stage images' coarse task, below it. Counted in
    // instructions by the image's timer, and traced instruction by instruction for its cycles
    // (the whole-interrupt bench's cost model, `support::base_cycles`).
    if let Some(p) = parts.iter().find(|p| p.name == "coarse-tick") {
        use twinstack::config::tick_budget::COARSE_TASK_CYCLES;
        let elf = support::build_image(support::QEMU_IMAGES, "tick-bench", &[]);
        let calls =
            support::traced_calls(&elf, "tick_bench::image::coarse_part", &["-serial", "null"]);
        assert_eq!(
            calls.len() as u64,
            p.ticks,
            "the trace sees every coarse tick the image timed"
        );
        let worst = calls
            .iter()
            .copied()
            .max_by_key(|c| c.cycles_ws5)
            .unwrap_or_default();
        let most = calls.iter().map(|c| c.instructions).max().unwrap_or(0);
        let mean_ws5 =
            calls.iter().map(|c| c.cycles_ws5).sum::<u64>() as f64 / calls.len().max(1) as f64;
        // The timer's bracket adds its reads to the image's count: the trace's is a little less.
        assert!(
            most <= p.max && most + 40 >= p.max,
            "the trace's worst coarse tick, {most} instructions, against the timer's {}",
            p.max
        );
        // The task is an interrupt of its own: the exception's entry and return beside it.
        let charged = worst.cycles_ws5 + ENTRY_EXIT_CYCLES;
        out!(
            md,
            "\nThe dual-stage images' coarse task, one coarse period as the firmware's task \
             runs it (`CoarseSupervisor::period`: the handler's command and the piezo's \
             position taken from the control loop, the supervisor's tick, its fine setpoints \
             and status posted to the loop; part `coarse-tick`; not the two locks' `BASEPRI` \
             writes nor the timer's acknowledgement) on the library's model of the axis, its \
             encoders and switches latched before the period as the board's timers and GPIOs \
             hold them: homing, then \
             10 mm and back at the paper stage's limits, then a stop at full speed in a 20 mm \
             move and a stopped jog ({} ticks): {:.1} \
             instructions on average, {} at worst. Traced instruction by instruction and costed \
             as the whole-interrupt bench costs the tick: {} cycles at 0 WS and {} at 5 WS at \
             worst ({} instructions; {:.0} cycles at 5 WS on average); with the exception's \
             entry and return ({ENTRY_EXIT_CYCLES}), {charged}, within the \
             `COARSE_TASK_CYCLES` = {COARSE_TASK_CYCLES} the tick budget charges a coarse period.",
            p.ticks,
            p.total as f64 / p.ticks as f64,
            p.max,
            worst.cycles,
            worst.cycles_ws5,
            worst.instructions,
            mean_ws5,
        );
        // Room for the paths the bench does not run, and no more (the charge's doc).
        assert!(
            f64::from(COARSE_TASK_CYCLES) <= 1.5 * charged as f64,
            "COARSE_TASK_CYCLES ({COARSE_TASK_CYCLES}) is looser than 1.5 × the dearest traced \
             coarse tick ({charged}): lower it"
        );
        assert!(
            u64::from(COARSE_TASK_CYCLES) >= charged,
            "the coarse task's worst tick takes {charged} cycles at 5 WS with its entry and \
             return: more than COARSE_TASK_CYCLES ({COARSE_TASK_CYCLES})"
        );
        // Its two exchanges with the loop run under the tick's lock on the board: each holds
        // the tick off, from the `BASEPRI` write that masks it (then an `ISB`) to the one that
        // unmasks it.
        let mut held = Vec::new();
        for (what, function) in [
            ("taking the command", "tick_bench::image::coarse_take"),
            ("posting the period", "tick_bench::image::coarse_post"),
        ] {
            let calls = support::traced_calls(&elf, function, &["-serial", "null"]);
            assert_eq!(calls.len() as u64, p.ticks, "every period {what}");
            let most = calls.iter().map(|c| c.instructions).max().unwrap_or(0);
            let locked = most + LOCK_INSTRUCTIONS;
            assert!(
                locked <= support::HELD_OFF_INSTRUCTIONS,
                "the coarse task holds the tick off for {locked} instructions {what} \
                 (asserted ≤ {})",
                support::HELD_OFF_INSTRUCTIONS
            );
            held.push(format!("{locked} ({what})"));
        }
        out!(
            md,
            "\nIts two locks of the tick hold the tick off for at most {} instructions (the \
             exchange traced, with the lock's own {LOCK_INSTRUCTIONS}), within the {} asserted \
             for every critical section outside the tick.",
            held.join(" and "),
            support::HELD_OFF_INSTRUCTIONS
        );
    }

    out!(
        md,
        "\nEach image's size (flash: loadable segments at flash addresses; static RAM: `.data` + \
         `.bss` + `.uninit`, CCM included):"
    );
    out!(md, "\n| image | flash (bytes) | static RAM (bytes) |");
    out!(md, "|---|---:|---:|");
    let board = support::build_image(support::FIRMWARE, "twinstack-fw", &[]);
    let emu = support::build_image(support::FIRMWARE, "twinstack-emu", &["emulator"]);
    let feather = support::build_image(support::FIRMWARE, "twinstack-feather", &["feather"]);
    let bench = support::build_image(support::QEMU_IMAGES, "tick-bench", &[]);
    for (label, path, budget) in [
        ("twinstack-fw (board)", &board, Some(FLASH_BUDGET)),
        ("twinstack-emu", &emu, None),
        ("twinstack-feather (Feather)", &feather, Some(FLASH_BUDGET)),
        ("tick-bench", &bench, None),
    ] {
        let s = support::image_size(path).unwrap_or_else(|e| panic!("{e}"));
        out!(md, "| {label} | {} | {} |", s.flash, s.ram);
        // Both board images: the same chip, the same budget.
        if let Some(budget) = budget {
            assert!(
                s.flash <= budget,
                "{label} is {} bytes of flash, over the {budget}-byte budget",
                s.flash
            );
        }
    }
    let path = support::workspace_root().join(FIGURES_MD);
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).expect("create target/figures");
    }
    std::fs::write(&path, md).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
}

#[test]
fn bench_lines_parse_and_malformed_ones_are_refused() {
    let r = parse_row("BENCH name=x ticks=10 total=2000 min=190 max=210 overhead=12").unwrap();
    assert_eq!(
        (r.ticks, r.total, r.min, r.max, r.overhead),
        (10, 2000, 190, 210, 12)
    );
    assert!(parse_row("BENCH name=x ticks=ten").is_err());
    assert!(parse_row("hello").is_err());
    let p = parse_part("PART name=dac-write ticks=10 total=210 max=21").unwrap();
    assert_eq!(
        (p.name.as_str(), p.ticks, p.total, p.max),
        ("dac-write", 10, 210, 21)
    );
    assert!(parse_part("PART name=x ticks=1").is_err());
}
