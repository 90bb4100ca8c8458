//! `cargo xtask figures [--check] [NAME…]`: the book's figures, written by the commands that
//! measure them.
//!
//! A figure is a block of a page between `<!-- figures:NAME -->` and `<!-- /figures -->`: the
//! command that makes it, then what it prints, turned into a table. `cargo xtask figures` runs
//! each command and rewrites the block; with `--check` it writes nothing and fails when a page
//! differs from what the code produces now. `cargo xtask test` runs the check for the figures
//! marked deterministic (they depend on nothing but the code and the committed data), so a
//! change that moves them has to update the page in the same commit.
//!
//! A figure comes from one of three sources ([`Source`]): the host tool's runs (its optimised
//! build, `cargo run --profile host-opt -p twinstack-cli`); a cargo command run as is (the
//! fixed-point accuracy table, checked; the host benchmarks and the throughput examples,
//! timings of the machine, written only when named and never checked); or a file a long
//! command writes, read rather than run (the QEMU benches, the whole interrupt's taking 20–30
//! minutes: their instruction and cycle counts are deterministic, so `--check` compares the
//! page with the bench's latest output, and fails, naming the command, when there is none).

use std::path::Path;
use std::process::Command;

/// What the host tool is called in the commands shown beside the figures.
const TOOL: &str = "twinstack";

mod identification;
mod output;
mod runs;
mod tick_cost;

use identification::*;
use output::*;
use runs::*;
use tick_cost::*;

/// One figure: where it goes, what writes it, and how its output becomes the block.
struct Figure {
    /// The marker's name (`<!-- figures:NAME -->`).
    name: &'static str,
    /// The page, relative to the workspace root.
    page: &'static str,
    /// The arguments of each run: the host tool's, or cargo's (see [`Source`]).
    runs: &'static [&'static [&'static str]],
    /// What the runs are.
    source: Source,
    /// Checked by `cargo xtask test` (deterministic).
    checked: bool,
    /// The block's body from the runs' standard output.
    render: Render,
}

/// What a figure's runs are, and how their output is had.
#[derive(Clone, Copy, PartialEq)]
enum Source {
    /// The host tool `twinstack` (its optimised build, `cargo run --profile host-opt -p
    /// twinstack-cli`), run for each of the runs.
    Tool,
    /// `cargo` with the run's arguments, run from the workspace root.
    Cargo,
    /// A file (relative to the workspace root) the one run, a cargo command, writes: read, not
    /// run (the command takes too long for the figures gate; the test gate runs it before).
    Written(&'static str),
}

impl Source {
    /// The program the runs' arguments follow, as the page shows it.
    fn program(self) -> &'static str {
        match self {
            Source::Tool => TOOL,
            Source::Cargo | Source::Written(_) => "cargo",
        }
    }
}

/// How a figure's output becomes its block.
enum Render {
    /// From the one run's output.
    One(fn(&str) -> Result<String, String>),
    /// From every run's arguments and output (a table with a row per run).
    Many(fn(&[Run]) -> Result<String, String>),
}

/// One run: its arguments and what it printed (or the file it wrote).
struct Run {
    args: &'static [&'static str],
    out: String,
}

/// A figure's run of one host test binary, as the tests' gate builds it: `cargo test --profile
/// host-opt --workspace --test NAME` and what follows (`-p` alone would select other features
/// and build every crate under it again).
macro_rules! host_test {
    ($test:literal $(, $arg:literal)*) => {
        &["test", "--profile", "host-opt", "--workspace", "--test", $test $(, $arg)*]
    };
}

/// The lab stage's triangles with the preview (`lab-stage … --triangles … --preview`), the
/// arguments before the triangles given: the models, and the rate the record, the
/// identification and the tracking are sampled at. Checked by the gate unless `unchecked`
/// follows the name (written only when named).
macro_rules! triangles_figure {
    ($name:literal, unchecked, $($arg:literal),+) => {
        triangles_figure!(@ $name, false, $($arg),+)
    };
    ($name:literal, $($arg:literal),+) => {
        triangles_figure!(@ $name, true, $($arg),+)
    };
    (@ $name:literal, $checked:literal, $($arg:literal),+) => {
        Figure {
            name: $name,
            page: "docs/src/results/lab-stage.md",
            runs: &[&[
                "lab-stage",
                $($arg,)+
                "--triangles",
                "1,5,20,50,100,200",
                "--preview",
                "--json",
            ]],
            source: Source::Tool,
            checked: $checked,
            render: Render::One(triangles_table),
        }
    };
}

const FIGURES: &[Figure] = &[
    Figure {
        name: "accuracy",
        page: "docs/src/results/benchmarks.md",
        runs: &[host_test!("accuracy", "--", "--nocapture")],
        source: Source::Cargo,
        checked: true,
        render: Render::One(test_markdown),
    },
    Figure {
        name: "model-bench",
        page: "docs/src/results/benchmarks.md",
        runs: &[&["bench", "--bench", "models"]],
        source: Source::Cargo,
        checked: false,
        render: Render::One(criterion_table),
    },
    Figure {
        name: "plant-speed",
        page: "docs/src/results/benchmarks.md",
        runs: &[&[
            "run",
            "--release",
            "-p",
            "hal-sim",
            "--example",
            "plant_speed",
        ]],
        source: Source::Cargo,
        checked: false,
        render: Render::One(verbatim),
    },
    Figure {
        name: "stream-throughput",
        page: "docs/src/results/throughput.md",
        runs: &[&[
            "run",
            "--profile",
            "host-opt",
            "-p",
            "twinstack-cli",
            "--example",
            "stream_throughput",
        ]],
        source: Source::Cargo,
        checked: false,
        render: Render::One(verbatim),
    },
    Figure {
        name: "stream-throughput-emulator",
        page: "docs/src/results/throughput.md",
        runs: &[
            &["build-emu"],
            &[
                "run",
                "--profile",
                "host-opt",
                "-p",
                "twinstack-cli",
                "--example",
                "stream_throughput",
                "--",
                "--emulator",
                "target/thumbv7em-none-eabihf/release/twinstack-emu",
                "--seconds",
                "10",
            ],
        ],
        source: Source::Cargo,
        checked: false,
        render: Render::Many(last_verbatim),
    },
    Figure {
        name: "telemetry-throughput",
        page: "docs/src/results/throughput.md",
        runs: &[&[
            "test",
            "--profile",
            "host-opt",
            "-p",
            "hal-sim",
            "--test",
            "telemetry",
            "--",
            "--nocapture",
            "--test-threads",
            "1",
        ]],
        source: Source::Cargo,
        checked: false,
        render: Render::One(test_markdown),
    },
    Figure {
        name: "tick-cost",
        page: "docs/src/results/tick-cost.md",
        runs: &[&["test", "--profile", "host-opt", "--test", "irq_bench"]],
        source: Source::Written("target/figures/tick-cost.json"),
        checked: true,
        render: Render::One(tick_cost),
    },
    Figure {
        name: "budget-family",
        page: "docs/src/results/tick-cost.md",
        runs: &[&["budget", "--rate", "100000"]],
        source: Source::Tool,
        checked: true,
        render: Render::One(markdown),
    },
    Figure {
        name: "tick-bench",
        page: "docs/src/results/tick-cost.md",
        runs: &[&["test", "--profile", "host-opt", "--test", "tick_bench"]],
        source: Source::Written("target/figures/tick-bench.md"),
        checked: true,
        render: Render::One(markdown),
    },
    Figure {
        name: "golden-distances",
        page: "docs/src/reference/golden-vectors.md",
        runs: &[&["golden"]],
        source: Source::Tool,
        checked: true,
        render: Render::One(golden_distances),
    },
    Figure {
        name: "demo",
        page: "docs/src/results/demo.md",
        runs: &[&["demo", "--quiet", "--out", "target/figures/demo"]],
        source: Source::Tool,
        checked: true,
        render: Render::One(markdown),
    },
    Figure {
        name: "closed-loop",
        page: "docs/src/results/closed-loop.md",
        runs: &[&["closed-loop", "--gains", "fixed", "--no-plot"]],
        source: Source::Tool,
        checked: true,
        render: Render::One(markdown),
    },
    Figure {
        name: "closed-loop-tuned",
        page: "docs/src/results/closed-loop.md",
        runs: &[&["closed-loop", "--preview", "--no-plot"]],
        source: Source::Tool,
        checked: true,
        render: Render::One(markdown),
    },
    Figure {
        name: "tune-50k",
        page: "docs/src/results/tuning.md",
        runs: &[&["tune", "--port", "sim", "--rate", "50k"]],
        source: Source::Tool,
        checked: true,
        render: Render::One(tune_summary),
    },
    Figure {
        name: "tune-100k",
        page: "docs/src/results/tuning.md",
        runs: &[&["tune", "--port", "sim", "--rate", "100k"]],
        source: Source::Tool,
        checked: true,
        render: Render::One(tune_summary),
    },
    Figure {
        name: "identify-bipolar",
        page: "docs/src/results/identification.md",
        runs: &[&[
            "identify",
            "--data",
            "data/piezo-bipolar-150v-1hz.csv",
            "--fit-until",
            "5.95",
            "--out",
            "target/figures/identify-bipolar.json",
        ]],
        source: Source::Tool,
        checked: true,
        render: Render::One(verbatim),
    },
    Figure {
        name: "identify-micromanipulator",
        page: "docs/src/results/identification.md",
        runs: &[&[
            "identify",
            "--data",
            "data/micromanipulator-unipolar-3v6-1hz.csv",
            "--fit-until",
            "16",
            "--out",
            "target/figures/identify-micromanipulator.json",
        ]],
        source: Source::Tool,
        checked: true,
        render: Render::One(verbatim),
    },
    Figure {
        name: "identify-ranking",
        page: "docs/src/results/identification.md",
        runs: RANKING_RUNS,
        source: Source::Tool,
        checked: true,
        render: Render::Many(ranking_table),
    },
    Figure {
        name: "identify-guide-bipolar",
        page: "docs/src/guide/identification.md",
        // The ranking's run on the bipolar record at 100 kHz: run once for both pages.
        runs: &[RANKING_RUNS[1]],
        source: Source::Tool,
        checked: true,
        render: Render::One(ranking_only),
    },
    Figure {
        name: "identify-models",
        page: "docs/src/results/identification.md",
        runs: IDENTIFY_RUNS,
        source: Source::Tool,
        checked: true,
        render: Render::Many(identify_table),
    },
    Figure {
        name: "calibrate-sim",
        page: "docs/src/guide/calibration.md",
        runs: &[&[
            "calibrate",
            "--port",
            "sim",
            "--out",
            "docs/src/guide/calibrate-sim.json",
        ]],
        source: Source::Tool,
        checked: false,
        render: Render::One(verbatim),
    },
    Figure {
        name: "lab-stage",
        page: "docs/src/results/lab-stage.md",
        runs: LAB_STAGE_RUNS,
        source: Source::Tool,
        checked: true,
        render: Render::Many(lab_stage_table),
    },
    Figure {
        name: "lab-stage-board-rates",
        page: "docs/src/results/lab-stage.md",
        runs: &[
            &["lab-stage", "--model", "auto,gpi", "--tick-rate", "50000"],
            &[
                "lab-stage",
                "--model",
                "gpi",
                "--creep",
                "--tick-rate",
                "50000",
            ],
            &["lab-stage", "--model", "auto,gpi", "--tick-rate", "100000"],
            &[
                "lab-stage",
                "--model",
                "gpi",
                "--creep",
                "--tick-rate",
                "100000",
            ],
        ],
        source: Source::Tool,
        checked: true,
        render: Render::Many(lab_stage_table),
    },
    Figure {
        name: "lab-stage-without",
        page: "docs/src/results/lab-stage.md",
        runs: LAB_STAGE_WITHOUT_RUNS,
        // Five more identifications of the whole stage: written, not re-run by the gate.
        source: Source::Tool,
        checked: false,
        render: Render::Many(lab_stage_table),
    },
    Figure {
        name: "lab-stage-pi-without",
        page: "docs/src/results/lab-stage.md",
        runs: LAB_STAGE_PI_WITHOUT_RUNS,
        source: Source::Tool,
        checked: false,
        render: Render::Many(lab_stage_table),
    },
    Figure {
        name: "lab-stage-duhem-without",
        page: "docs/src/results/lab-stage.md",
        runs: &[
            &[
                "lab-stage",
                "--model",
                "duhem",
                "--without",
                "creep,flexure",
            ],
            &[
                "lab-stage",
                "--model",
                "duhem",
                "--without",
                "creep,flexure,asymmetry",
            ],
        ],
        source: Source::Tool,
        checked: false,
        render: Render::Many(lab_stage_table),
    },
    triangles_figure!("lab-stage-triangles", "--model", "auto,pi,gpi"),
    // The table the test holding 1–200 Hz within 1 % at 50 kHz computes and writes: the same
    // as `twinstack lab-stage --rate 50000 --model auto --triangles 1,5,20,50,100,200 --preview
    // --json` prints (a minute and a half, not run twice).
    Figure {
        name: "lab-stage-triangles-50khz",
        page: "docs/src/results/lab-stage.md",
        runs: &[host_test!(
            "model_family",
            "--",
            "at_the_board_s_rate_one_calibration"
        )],
        source: Source::Written("target/figures/lab-stage-triangles-50khz.json"),
        checked: true,
        render: Render::One(triangles_table),
    },
    triangles_figure!(
        "lab-stage-triangles-100khz",
        "--rate",
        "100000",
        "--model",
        "auto"
    ),
    // The same calibration with its excitation swept up to the fastest triangle
    // (`--fastest-hz`): the creep fitted on fast motion too.
    triangles_figure!(
        "lab-stage-triangles-100khz-swept",
        "--rate",
        "100000",
        "--model",
        "auto",
        "--fastest-hz",
        "200"
    ),
    // At the stage's 10 kHz, where the sweep's top has 50 samples a cycle.
    triangles_figure!(
        "lab-stage-triangles-swept",
        "--model",
        "auto",
        "--fastest-hz",
        "200"
    ),
    // At the board's default rate (a minute): written, not re-run by the gate.
    triangles_figure!(
        "lab-stage-triangles-50khz-swept",
        unchecked,
        "--rate",
        "50000",
        "--model",
        "auto",
        "--fastest-hz",
        "200"
    ),
    // What the preview leaves once the stage has no creep (and the model none): the rows
    // above less the creep's share.
    triangles_figure!(
        "lab-stage-triangles-without-creep",
        "--model",
        "auto",
        "--without",
        "creep"
    ),
    // An identification at 100 kHz (two minutes): written, not re-run by the gate.
    triangles_figure!(
        "lab-stage-triangles-100khz-without-creep",
        unchecked,
        "--rate",
        "100000",
        "--model",
        "auto",
        "--without",
        "creep"
    ),
    Figure {
        name: "lab-stage-variants",
        page: "docs/src/results/lab-stage.md",
        runs: &[&["lab-stage", "--variants", "--model", "auto,pi"]],
        // 21 stages identified and tracked (minutes): `stage_variants` asserts the goals.
        source: Source::Tool,
        checked: false,
        render: Render::One(variants_table),
    },
    Figure {
        name: "lab-stage-variants-100k",
        page: "docs/src/results/lab-stage.md",
        runs: &[&[
            "lab-stage",
            "--variants",
            "--model",
            "auto,pi",
            "--tick-rate",
            "100000",
        ]],
        // As `lab-stage-variants`: minutes; written when named, not re-run by the gate.
        source: Source::Tool,
        checked: false,
        render: Render::One(variants_table),
    },
    Figure {
        name: "lab-stage-variants-swept",
        page: "docs/src/results/lab-stage.md",
        runs: &[&[
            "lab-stage",
            "--variants",
            "--model",
            "auto,pi",
            "--fastest-hz",
            "200",
        ]],
        // As `lab-stage-variants`: minutes; written when named, not re-run by the gate.
        source: Source::Tool,
        checked: false,
        render: Render::One(variants_table),
    },
    Figure {
        name: "lab-stage-bouc-wen",
        page: "docs/src/results/lab-stage.md",
        runs: &[
            &[
                "lab-stage",
                "--hysteresis",
                "bouc-wen",
                "--model",
                "auto,pi,gpi,duhem,bouc-wen",
            ],
            &[
                "lab-stage",
                "--hysteresis",
                "bouc-wen",
                "--model",
                "auto,bouc-wen",
                "--creep",
            ],
            &[
                "lab-stage",
                "--hysteresis",
                "bouc-wen",
                "--model",
                "auto",
                "--tick-rate",
                "100000",
            ],
        ],
        source: Source::Tool,
        checked: true,
        render: Render::Many(lab_stage_table),
    },
    Figure {
        name: "lab-stage-bouc-wen-variants",
        page: "docs/src/results/lab-stage.md",
        runs: &[&[
            "lab-stage",
            "--hysteresis",
            "bouc-wen",
            "--variants",
            "--model",
            "auto,pi",
        ]],
        // Eight stages identified and tracked (a minute): written when named.
        source: Source::Tool,
        checked: false,
        render: Render::One(variants_table),
    },
    Figure {
        name: "learning",
        page: "docs/src/results/learning.md",
        runs: LEARN_RUNS,
        source: Source::Tool,
        checked: true,
        render: Render::Many(learn_table),
    },
    Figure {
        name: "learning-curves",
        page: "docs/src/results/learning.md",
        runs: LEARN_CURVE_RUNS,
        source: Source::Tool,
        checked: true,
        render: Render::Many(learn_curves_table),
    },
    Figure {
        name: "learning-notch",
        page: "docs/src/results/learning.md",
        runs: LEARN_NOTCH_RUNS,
        source: Source::Tool,
        checked: true,
        render: Render::Many(learn_notch_table),
    },
    Figure {
        name: "scan-raster",
        page: "docs/src/results/scan-timing.md",
        runs: &[&[
            "scan",
            "--port",
            "sim",
            "--pattern",
            "raster:lines=32,pixels=100,turn=40",
            "--out",
            "target/figures/scan-raster.png",
        ]],
        source: Source::Tool,
        checked: true,
        render: Render::One(verbatim),
    },
    Figure {
        name: "scan-lissajous",
        page: "docs/src/results/scan-timing.md",
        runs: &[&[
            "scan",
            "--port",
            "sim",
            "--pattern",
            "lissajous:hz=20,x=3,y=2",
            "--ticks-per-pixel",
            "10",
            "--out",
            "target/figures/scan-lissajous.png",
        ]],
        source: Source::Tool,
        checked: true,
        render: Render::One(verbatim),
    },
    Figure {
        name: "scan-spiral",
        page: "docs/src/results/scan-timing.md",
        runs: &[&[
            "scan",
            "--port",
            "sim",
            "--pattern",
            "spiral:hz=200,turns=10",
            "--out",
            "target/figures/scan-spiral.png",
        ]],
        source: Source::Tool,
        checked: true,
        render: Render::One(verbatim),
    },
    Figure {
        name: "selftest-sim",
        page: "docs/src/guide/selftest.md",
        runs: &[&["selftest", "--port", "sim"]],
        // The in-process board runs on simulated time: the same lines every run.
        source: Source::Tool,
        checked: true,
        render: Render::One(verbatim),
    },
    Figure {
        name: "dual-stage",
        page: "docs/src/results/dual-stage.md",
        runs: &[&["dual-stage"]],
        source: Source::Tool,
        checked: true,
        render: Render::One(verbatim),
    },
    Figure {
        name: "coarse-board",
        page: "docs/src/results/dual-stage.md",
        runs: &[host_test!(
            "coarse_board",
            "--",
            "--nocapture",
            "--test-threads",
            "1"
        )],
        // The simulated board runs on simulated time, one test after another: the same
        // lines every run.
        source: Source::Cargo,
        checked: true,
        render: Render::One(test_verbatim),
    },
];

/// The block a figure's marker pair holds: the command (or commands), then the rendering.
fn block(f: &Figure, body: &str) -> String {
    let program = f.source.program();
    // Timings are the machine's: the page says so, and that the check leaves them out.
    let unchecked = if f.checked {
        String::new()
    } else {
        format!(
            " only when named (`cargo xtask figures {}`; not checked)",
            f.name
        )
    };
    match (f.source, f.runs) {
        (Source::Written(file), [one]) => format!(
            "Written by `cargo xtask figures`{unchecked} from `{file}`, which `{program} {}` \
             writes:\n\n{body}",
            one.join(" ")
        ),
        (_, [one]) => format!(
            "Written by `cargo xtask figures`{unchecked} from `{program} {}`:\n\n{body}",
            one.join(" ")
        ),
        (_, runs) => {
            let commands: Vec<String> = runs
                .iter()
                .map(|r| format!("{program} {}", r.join(" ")))
                .collect();
            format!(
                "Written by `cargo xtask figures`{unchecked} from\n\n```sh\n{}\n```\n\n{body}",
                commands.join("\n")
            )
        }
    }
}

/// Replaces the body between `f`'s markers in `page`; an error if the markers are missing.
fn replace_block(page: &str, name: &str, body: &str) -> Result<String, String> {
    let open = format!("<!-- figures:{name} -->");
    let close = "<!-- /figures -->";
    let start = page
        .find(&open)
        .ok_or_else(|| format!("no `{open}` marker"))?
        + open.len();
    let end = page[start..]
        .find(close)
        .ok_or_else(|| format!("`{open}` has no `{close}` after it"))?
        + start;
    Ok(format!("{}\n{body}{}", &page[..start], &page[end..]))
}

/// A figure's output for one of its runs: the host tool's or cargo's standard output, or the
/// file the run writes.
fn output(root: &Path, source: Source, args: &[&str]) -> Result<String, String> {
    match source {
        Source::Tool => run_tool(root, args),
        Source::Cargo => run_cargo(root, args),
        Source::Written(file) => {
            let path = root.join(file);
            std::fs::read_to_string(&path).map_err(|e| {
                format!(
                    "{} cannot be read ({e}): it is written by `cargo {}`; run that first",
                    path.display(),
                    args.join(" ")
                )
            })
        }
    }
}

/// Runs `cargo` with `args` from the workspace root, returning its standard output.
fn run_cargo(root: &Path, args: &[&str]) -> Result<String, String> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args(args)
        .current_dir(root)
        .output()
        .map_err(|e| format!("cannot run cargo: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "`cargo {}` failed ({}):\n{}",
            args.join(" "),
            out.status,
            String::from_utf8_lossy(&out.stderr)
        ));
    }
    String::from_utf8(out.stdout).map_err(|e| format!("`cargo {}`: {e}", args.join(" ")))
}

/// Runs the host tool with `args` (the optimised `host-opt` build the simulation gates use),
/// returning its standard output.
fn run_tool(root: &Path, args: &[&str]) -> Result<String, String> {
    // Where the runs write their files: on a fresh clone nothing has made it yet.
    std::fs::create_dir_all(root.join("target/figures"))
        .map_err(|e| format!("cannot make target/figures: {e}"))?;
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args(["run", "--quiet"])
        .args(super::TWINSTACK_BIN)
        .arg("--")
        .args(args)
        .current_dir(root)
        .output()
        .map_err(|e| format!("cannot run cargo: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "`{TOOL} {}` failed ({}):\n{}",
            args.join(" "),
            out.status,
            String::from_utf8_lossy(&out.stderr)
        ));
    }
    String::from_utf8(out.stdout).map_err(|e| format!("`{TOOL} {}`: {e}", args.join(" ")))
}

/// `cargo xtask figures [--check] [NAME…]`: the deterministic figures (or those named, timings
/// included), or with `--check` the deterministic ones, compared and not written. Timings are
/// written only when named: they take minutes and differ from run to run.
pub fn run(root: &Path, args: &[String]) -> Result<(), String> {
    let check = args.iter().any(|a| a == "--check");
    let names: Vec<&str> = args
        .iter()
        .filter(|a| !a.starts_with("--"))
        .map(String::as_str)
        .collect();
    for n in &names {
        if !FIGURES.iter().any(|f| f.name == *n) {
            let known: Vec<&str> = FIGURES.iter().map(|f| f.name).collect();
            return Err(format!("no figure `{n}` (known: {})", known.join(", ")));
        }
    }
    // Run: what is named, or with no names every checked figure; `--check` only checked ones.
    let wanted = |f: &Figure| {
        (names.contains(&f.name) || (names.is_empty() && f.checked)) && (f.checked || !check)
    };
    let figures: Vec<&Figure> = FIGURES.iter().filter(|f| wanted(f)).collect();
    if names.is_empty() && !check {
        for f in FIGURES.iter().filter(|f| !f.checked) {
            println!(
                "{}: {} left as it is (timings: `cargo xtask figures {}` writes it)",
                f.page, f.name, f.name
            );
        }
    }
    // Every run of every wanted figure, on as many cores as the machine has: the runs are
    // independent (each writes its own files), the deterministic ones are single-threaded
    // simulations, and the timings are written only when named, one figure at a time.
    let jobs: Vec<(&Figure, &'static [&'static str])> = figures
        .iter()
        .flat_map(|&f| f.runs.iter().map(move |&args| (f, args)))
        .collect();
    let workers = if figures.iter().all(|f| f.checked) {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        1
    };
    // A run two figures share (the same source and arguments) is run once: the runs are
    // deterministic, and the figures' gate is the test command's longest after the bench.
    let (unique, slot) = shared_runs(&jobs);
    let results = run_all(&unique, workers, |&(f, args)| {
        let started = std::time::Instant::now();
        let out = output(root, f.source, args);
        // How long each run took: what the figures' share of the test command's time is made of.
        eprintln!(
            "{}: `{} {}` took {:.0} s",
            f.name,
            f.source.program(),
            args.join(" "),
            started.elapsed().as_secs_f64()
        );
        out
    });
    let mut outputs = jobs
        .iter()
        .zip(&slot)
        .map(|(&(f, _), &i)| results[i].clone().map_err(|e| format!("{}: {e}", f.name)))
        .collect::<Vec<_>>()
        .into_iter();
    let mut stale = Vec::new();
    for f in figures {
        let path = root.join(f.page);
        let page = std::fs::read_to_string(&path)
            .map_err(|e| format!("{}: cannot read: {e}", path.display()))?;
        let mut runs = Vec::new();
        for args in f.runs {
            let out = outputs
                .next()
                .ok_or_else(|| format!("{}: a run's output is missing", f.name))??;
            runs.push(Run { args, out });
        }
        let body = match (&f.render, &runs[..]) {
            (Render::One(render), [run]) => render(&run.out),
            (Render::One(_), _) => Err("a figure rendered from one run has one run".into()),
            (Render::Many(render), runs) => render(runs),
        }
        .map_err(|e| format!("{}: {e}", f.name))?;
        let new = replace_block(&page, f.name, &block(f, &body))
            .map_err(|e| format!("{}: {e}", f.page))?;
        if new == page {
            println!("{}: {} is current", f.page, f.name);
        } else if check {
            stale.push(format!("{} ({})", f.page, f.name));
        } else {
            std::fs::write(&path, new)
                .map_err(|e| format!("{}: cannot write: {e}", path.display()))?;
            println!("{}: wrote {}", f.page, f.name);
        }
    }
    if stale.is_empty() {
        Ok(())
    } else {
        Err(format!(
            "figures differ from what the code produces now: {}; run `cargo xtask figures` and \
             commit the pages",
            stale.join(", ")
        ))
    }
}

/// The runs of `jobs` with a source and arguments of their own, and for each job the index of
/// its run among them (two figures that show one run's output share it).
fn shared_runs<'a>(
    jobs: &[(&'a Figure, &'static [&'static str])],
) -> (Vec<(&'a Figure, &'static [&'static str])>, Vec<usize>) {
    let mut unique: Vec<(&Figure, &[&str])> = Vec::new();
    let slot = jobs
        .iter()
        .map(|&(f, args)| {
            let same = |&(g, a): &(&Figure, &[&str])| g.source == f.source && a == args;
            unique.iter().position(same).unwrap_or_else(|| {
                unique.push((f, args));
                unique.len() - 1
            })
        })
        .collect();
    (unique, slot)
}

/// `run` on each of `jobs` on `workers` threads, its results in the jobs' order (a job's
/// panic is the caller's).
fn run_all<J: Sync, R: Send>(jobs: &[J], workers: usize, run: impl Fn(&J) -> R + Sync) -> Vec<R> {
    let next = std::sync::atomic::AtomicUsize::new(0);
    let mut done: Vec<(usize, R)> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..workers.clamp(1, jobs.len().max(1)))
            .map(|_| {
                scope.spawn(|| {
                    let mut done = Vec::new();
                    loop {
                        let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        let Some(job) = jobs.get(i) else { break done };
                        done.push((i, run(job)));
                    }
                })
            })
            .collect();
        handles
            .into_iter()
            .flat_map(|h| h.join().unwrap_or_else(|p| std::panic::resume_unwind(p)))
            .collect()
    });
    done.sort_by_key(|&(i, _)| i);
    done.into_iter().map(|(_, r)| r).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_run_two_figures_show_is_run_once_and_a_run_differing_in_anything_is_not_shared() {
        let figure = |name: &str| FIGURES.iter().find(|f| f.name == name).unwrap();
        let (ranking, guide) = (figure("identify-ranking"), figure("identify-guide-bipolar"));
        let tool = figure("budget-family");
        let cargo = figure("accuracy");
        let jobs = [
            (ranking, RANKING_RUNS[0]),
            (ranking, RANKING_RUNS[1]),
            (guide, guide.runs[0]),
            (tool, &["golden"][..]),
            (cargo, &["golden"][..]),
        ];
        let (unique, slot) = shared_runs(&jobs);
        assert_eq!(
            slot,
            [0, 1, 1, 2, 3],
            "the guide's run is the ranking's second"
        );
        assert_eq!(
            unique.len(),
            4,
            "the same arguments to cargo are not the tool's run"
        );
    }

    #[test]
    fn a_figure_read_from_a_file_that_is_not_there_names_the_command_that_writes_it() {
        let e = output(
            Path::new("/nonexistent-root"),
            Source::Written("target/figures/tick-cost.json"),
            &["test", "--profile", "host-opt", "--test", "irq_bench"],
        )
        .unwrap_err();
        assert!(
            e.contains("cargo test --profile host-opt --test irq_bench")
                && e.contains("run that first"),
            "{e}"
        );
    }

    #[test]
    fn runs_on_several_threads_come_back_in_the_jobs_order() {
        let jobs: Vec<u64> = (0..40).collect();
        let out = run_all(&jobs, 3, |&j| {
            // Later jobs finish first.
            std::thread::sleep(std::time::Duration::from_millis(40 - j));
            j * 10
        });
        assert_eq!(out, (0..40).map(|j| j * 10).collect::<Vec<_>>());
        assert_eq!(run_all(&[] as &[u64], 2, |&j| j), Vec::<u64>::new());
    }

    #[test]
    fn a_block_is_replaced_between_its_markers_only() {
        let page = "a\n<!-- figures:x -->\nold\n<!-- /figures -->\nb\n<!-- figures:y -->\nkeep\n<!-- /figures -->\n";
        let new = replace_block(page, "x", "new\n").unwrap();
        assert_eq!(
            new,
            "a\n<!-- figures:x -->\nnew\n<!-- /figures -->\nb\n<!-- figures:y -->\nkeep\n<!-- /figures -->\n"
        );
        assert_eq!(replace_block(&new, "x", "new\n").unwrap(), new);
        assert!(replace_block(page, "z", "").is_err());
    }
}
