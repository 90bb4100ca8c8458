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
#[derive(Clone, Copy)]
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

/// `auto`'s ranking on each shipped record at the board's two control rates: every candidate's
/// forward, inverse and tracking figures on the validation part, and where it stands.
const RANKING_RUNS: &[&[&str]] = &[
    &[
        "identify",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--tick-rate",
        "50000",
        "--out",
        "target/figures/identify-ranking.json",
    ],
    &[
        "identify",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--tick-rate",
        "100000",
        "--out",
        "target/figures/identify-ranking.json",
    ],
    &[
        "identify",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--tick-rate",
        "50000",
        "--out",
        "target/figures/identify-ranking.json",
    ],
    &[
        "identify",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--tick-rate",
        "100000",
        "--out",
        "target/figures/identify-ranking.json",
    ],
];

/// The identification page's per-model runs: every model, without and with creep, on each
/// shipped record (fitted on its first cycles, scored on the rest).
const IDENTIFY_RUNS: &[&[&str]] = &[
    &[
        "identify",
        "--model",
        "pi",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "pi",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "pi",
        "--creep",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "pi",
        "--creep",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "gpi",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "gpi",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "gpi",
        "--creep",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "gpi",
        "--creep",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "duhem",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "duhem",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "duhem",
        "--creep",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "duhem",
        "--creep",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "bouc-wen",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "bouc-wen",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "bouc-wen",
        "--creep",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "bouc-wen",
        "--creep",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--out",
        "target/figures/identify-model.json",
    ],
];

/// The lab-stage page's runs: `identify`'s default with the textbook and generalised P–I, the
/// models that do not fit the stage, and both P–Is with creep.
const LAB_STAGE_RUNS: &[&[&str]] = &[
    &["lab-stage"],
    &["lab-stage", "--model", "duhem,bouc-wen"],
    &["lab-stage", "--model", "pi,gpi", "--creep"],
];

/// The lab stage with its non-idealities taken out, one run each and all four at once: what is
/// left of the generalised P–I + creep's error.
const LAB_STAGE_WITHOUT_RUNS: &[&[&str]] = &[
    &[
        "lab-stage",
        "--model",
        "gpi",
        "--creep",
        "--without",
        "creep",
    ],
    &[
        "lab-stage",
        "--model",
        "gpi",
        "--creep",
        "--without",
        "flexure",
    ],
    &[
        "lab-stage",
        "--model",
        "gpi",
        "--creep",
        "--without",
        "asymmetry",
    ],
    &[
        "lab-stage",
        "--model",
        "gpi",
        "--creep",
        "--without",
        "noise",
    ],
    &[
        "lab-stage",
        "--model",
        "gpi",
        "--creep",
        "--without",
        "creep,flexure,asymmetry,noise",
    ],
];

/// The lab stage with its non-idealities taken out one by one, cumulatively: what each costs the
/// textbook P–I.
const LAB_STAGE_PI_WITHOUT_RUNS: &[&[&str]] = &[
    &["lab-stage", "--model", "pi", "--without", "noise"],
    &["lab-stage", "--model", "pi", "--without", "creep"],
    &["lab-stage", "--model", "pi", "--without", "creep,flexure"],
    &[
        "lab-stage",
        "--model",
        "pi",
        "--without",
        "creep,flexure,asymmetry",
    ],
];

/// The learning page's runs: each waveform without input shaping (the learning's corner at
/// 18 kHz) and with it (the notch on the simulated stage's resonance as `tune` fits it).
const LEARN_RUNS: &[&[&str]] = &[
    &[
        "learn",
        "--waveform",
        "sine:750",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "sine:750",
        "--shape-hz",
        "21807",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "triangle:200",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "triangle:200",
        "--shape-hz",
        "21807",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "sine:500",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "sine:500",
        "--shape-hz",
        "21807",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "sine:1000",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "sine:1000",
        "--shape-hz",
        "21807",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "triangle:100",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "triangle:100",
        "--shape-hz",
        "21807",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "triangle:250",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "triangle:250",
        "--shape-hz",
        "21807",
        "--out",
        "target/figures/learning",
    ],
];

const FIGURES: &[Figure] = &[
    Figure {
        name: "accuracy",
        page: "docs/src/results/benchmarks.md",
        runs: &[&[
            "test",
            "--profile",
            "host-opt",
            "-p",
            "twinstack-identify",
            "--test",
            "accuracy",
            "--",
            "--nocapture",
        ]],
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
            "hal-sim",
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
                "hal-sim",
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
        runs: &[&["closed-loop", "--no-plot"]],
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
        runs: &[&[
            "identify",
            "--data",
            "data/piezo-bipolar-150v-1hz.csv",
            "--fit-until",
            "5.95",
            "--tick-rate",
            "100000",
            "--out",
            "target/figures/identify-guide.json",
        ]],
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
        name: "lab-stage",
        page: "docs/src/results/lab-stage.md",
        runs: LAB_STAGE_RUNS,
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
        name: "learning",
        page: "docs/src/results/learning.md",
        runs: LEARN_RUNS,
        source: Source::Tool,
        checked: true,
        render: Render::Many(learn_table),
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
];

/// The lines of a command's output, trailing spaces trimmed, less those naming the files it
/// wrote (`wrote PATH`: where they go depends on the machine, not on the code).
fn printed_lines(out: &str) -> impl Iterator<Item = &str> {
    out.lines()
        .map(str::trim_end)
        .filter(|l| !l.starts_with("wrote "))
}

/// What a `cargo test -- --nocapture` run printed, less the test harness's own lines (`running
/// N tests`, `test NAME ... ok`, `test result: …`).
fn test_printed(out: &str) -> String {
    let mut kept = Vec::new();
    for line in out.lines() {
        let line = line.trim_end();
        if line.starts_with("running ") || line.starts_with("test result:") {
            continue;
        }
        // The harness writes `test NAME ... ` before the test's output and its verdict after it.
        let line = match line
            .strip_prefix("test ")
            .and_then(|l| l.split_once(" ... "))
        {
            Some((_, rest)) => rest,
            None => line,
        };
        let line = ["ok", "ignored", "FAILED"]
            .iter()
            .find_map(|v| line.strip_suffix(v))
            .unwrap_or(line)
            .trim_end();
        if !line.is_empty() {
            kept.push(line);
        }
    }
    kept.join("\n") + "\n"
}

/// A test's printed Markdown (see [`test_printed`] and [`markdown`]).
fn test_markdown(out: &str) -> Result<String, String> {
    markdown(&test_printed(out))
}

/// criterion's results (`cargo bench`) as a table: each benchmark's estimate of one iteration
/// (the middle of its `time: [low estimate high]`).
fn criterion_table(out: &str) -> Result<String, String> {
    let mut table = String::from("| benchmark | time per iteration |\n|---|---:|\n");
    let mut name = "";
    let mut rows = 0;
    for line in out.lines().map(str::trim) {
        let (before, times) = match line.split_once("time:") {
            Some(split) => split,
            None => {
                if !line.is_empty() && !line.contains(':') && !line.starts_with(['F', 'c']) {
                    name = line;
                }
                continue;
            }
        };
        let before = before.trim();
        if !before.is_empty() {
            name = before;
        }
        let words: Vec<&str> = times
            .trim()
            .trim_start_matches('[')
            .trim_end_matches(']')
            .split_whitespace()
            .collect();
        let [_, _, mid, unit, _, _] = words[..] else {
            return Err(format!("`{line}`: not criterion's `time: [a u b u c u]`"));
        };
        table.push_str(&format!("| `{name}` | {mid} {unit} |\n"));
        rows += 1;
    }
    if rows == 0 {
        return Err("no criterion results in the output".into());
    }
    Ok(table)
}

/// Output that is already Markdown (titles and tables, as `demo` and `closed-loop` print
/// them): each title line its own paragraph, each table as printed, the lines naming the files
/// the command wrote left out.
fn markdown(out: &str) -> Result<String, String> {
    let mut body = String::new();
    let mut tables = 0;
    // Whether the last line written was a table row (`None` before the first line).
    let mut last_row = None;
    for line in printed_lines(out).filter(|l| !l.is_empty()) {
        let row = line.starts_with('|');
        if last_row.is_some() && !(row && last_row == Some(true)) {
            body.push('\n');
        }
        tables += usize::from(line.starts_with("|---"));
        body.push_str(line);
        body.push('\n');
        last_row = Some(row);
    }
    if tables == 0 {
        return Err("no Markdown table in the output".into());
    }
    Ok(body)
}

/// `tune`'s summary: its output less the measured response's lines (`FREQ Hz  GAIN dB  PHASE°`,
/// which the PNG draws), as Markdown.
fn tune_summary(out: &str) -> Result<String, String> {
    let is_response = |l: &str| {
        let cols: Vec<&str> = l.split_whitespace().collect();
        matches!(cols[..], [f, "Hz", _, "dB", _] if f.parse::<f64>().is_ok())
    };
    let kept: String = out
        .lines()
        .filter(|l| !is_response(l))
        .map(|l| format!("{l}\n"))
        .collect();
    if !kept.contains("fit: ") || !kept.contains("tuned: ") {
        return Err("no `fit:` and `tuned:` lines in the output".into());
    }
    markdown(&kept)
}

/// Output shown as printed, in a text block, less the lines naming the files it wrote.
fn verbatim(out: &str) -> Result<String, String> {
    let kept: Vec<&str> = printed_lines(out).collect();
    let text = kept.join("\n");
    let text = text.trim_matches('\n');
    if text.is_empty() {
        return Err("no output".into());
    }
    Ok(format!("```text\n{text}\n```\n"))
}

/// The last run's output as a text block (the runs before it build what it runs).
fn last_verbatim(runs: &[Run]) -> Result<String, String> {
    verbatim(&runs.last().ok_or("no runs")?.out)
}

/// `twinstack golden`'s per-set lines as the page's table: distances to the `f64` reference
/// tick, the worst DAC-code error, ambiguous flag decisions and the flag counts.
fn golden_distances(out: &str) -> Result<String, String> {
    let mut table = String::from(
        "| set | drive LSB16 | estimate LSB16 | code | ambiguous | underrun/range/slew/adc/dac/drift |\n\
         |---|---:|---:|---:|---:|---|\n",
    );
    let mut sets = 0;
    let mut total = None;
    for line in out.lines() {
        let cols: Vec<&str> = line.split_whitespace().collect();
        if let ["total", bytes, "bytes", "in", n, "sets"] = cols[..] {
            total = Some((bytes.to_string(), n.to_string()));
            continue;
        }
        // set, ticks, bytes, CRC, drive, estimate, code, ambiguous, counts
        let [set, ticks, _bytes, _crc, drive, estimate, code, ambiguous, counts] = cols[..] else {
            continue;
        };
        if ticks.parse::<u32>().is_err() {
            continue; // the header
        }
        table.push_str(&format!(
            "| `{set}` | {drive} | {estimate} | {code} | {ambiguous} | {counts} |\n"
        ));
        sets += 1;
    }
    let Some((bytes, n)) = total else {
        return Err("no `total … bytes in … sets` line".into());
    };
    if n.parse::<usize>() != Ok(sets) {
        return Err(format!("{sets} set lines, but the total says {n}"));
    }
    table.push_str(&format!(
        "\n{sets} sets, {bytes} bytes in `tests/golden/vectors.bin`.\n"
    ));
    Ok(table)
}

/// `identify`'s held-out errors of each run: a row per model (its name as `identify` prints it,
/// less the creep's mode count, which differs from record to record), forward and inverse
/// columns per record, `max / RMS %`.
fn identify_table(runs: &[Run]) -> Result<String, String> {
    let mut records: Vec<(&str, &str)> = Vec::new();
    let mut rows: Vec<(String, Vec<Option<String>>)> = Vec::new();
    let mut cells = Vec::new();
    for run in runs {
        let arg = |flag: &str| {
            run.args
                .iter()
                .position(|a| *a == flag)
                .and_then(|i| run.args.get(i + 1))
                .copied()
        };
        let what = |e: &str| format!("`{TOOL} {}`: {e}", run.args.join(" "));
        let data = arg("--data").ok_or_else(|| what("no --data"))?;
        let until = arg("--fit-until").ok_or_else(|| what("no --fit-until"))?;
        let model = run
            .out
            .lines()
            .find_map(|l| l.strip_prefix("identified "))
            .and_then(|l| l.split(" from ").next())
            .ok_or_else(|| what("no `identified … from` line"))?;
        // "+ creep (2 modes)" → "+ creep".
        let model = match model.split_once(" + creep") {
            Some((m, _)) => format!("{m} + creep"),
            None => model.to_string(),
        };
        let errors = |prefix: &str| -> Result<String, String> {
            let line = run
                .out
                .lines()
                .map(str::trim)
                .find(|l| l.starts_with(prefix))
                .ok_or_else(|| what(&format!("no `{prefix}` line")))?;
            let cols: Vec<&str> = line.split_whitespace().collect();
            let at = |word: &str| {
                cols.iter()
                    .position(|c| *c == word)
                    .and_then(|i| cols.get(i + 1))
            };
            match (at("max"), at("RMS")) {
                (Some(max), Some(rms)) => Ok(format!("{max} / {rms} %")),
                _ => Err(what(&format!("`{prefix}` has no max and RMS"))),
            }
        };
        let forward = errors("held-out (predict vs measured x):")?;
        let inverse = errors("inverse held-out (compensate u vs measured u):")?;
        let column = match records.iter().position(|(d, _)| *d == data) {
            Some(i) => i,
            None => {
                records.push((data, until));
                records.len() - 1
            }
        };
        cells.push((model, column, forward, inverse));
    }
    for (model, column, forward, inverse) in cells {
        let row = match rows.iter().position(|(m, _)| *m == model) {
            Some(i) => i,
            None => {
                rows.push((model, vec![None; records.len()]));
                rows.len() - 1
            }
        };
        if rows[row].1[column].is_some() {
            return Err(format!("{} twice on one record", rows[row].0));
        }
        rows[row].1[column] = Some(format!("{forward} | {inverse}"));
    }
    let mut table = String::from("| model |");
    for (data, until) in &records {
        let name = data
            .rsplit('/')
            .next()
            .unwrap_or(data)
            .trim_end_matches(".csv");
        table.push_str(&format!(
            " `{name}` (`--fit-until {until}`): held-out max / RMS | inverse |"
        ));
    }
    table.push_str("\n|---|");
    table.push_str(&"---:|---:|".repeat(records.len()));
    table.push('\n');
    for (model, cols) in rows {
        table.push_str(&format!("| {model} |"));
        for c in cols {
            table.push_str(&format!(" {} |", c.unwrap_or_else(|| "— | —".into())));
        }
        table.push('\n');
    }
    Ok(table)
}

/// What `identify` prints of `auto`'s choice: the ranking, its legend and the pick, then the
/// model kept and its held-out figures (its notes and the fixed-point check left out).
fn ranking_only(out: &str) -> Result<String, String> {
    let kept: Vec<&str> = printed_lines(out)
        .filter(|l| {
            let l = l.trim_start();
            !(l.starts_with("note:")
                || l.starts_with("fitted t")
                || l.starts_with("sensor lag")
                || l.starts_with("fixed point")
                || l.starts_with("inverse held-out, f64"))
        })
        .collect();
    if !kept.iter().any(|l| l.starts_with("picked: ")) {
        return Err("no `picked:` line".into());
    }
    verbatim(&kept.join("\n"))
}

/// One `identify` ranking line (`  1.  LABEL forward  0.85 % (RMS 0.21 %)  inverse  1.22 %
/// tracking  0.74 %[  set aside: …]`) as its place, label, three figures and standing.
fn ranking_row(line: &str) -> Option<(String, String, [String; 3], String)> {
    let line = line.trim_start();
    let (place, rest) = line.split_once(' ')?;
    if !place.ends_with('.') {
        return None;
    }
    let rest = rest.trim_start();
    let Some((label, figures)) = rest.split_once(" forward ") else {
        // Not fitted: no figures, only why.
        let (label, why) = rest.split_once("  ")?;
        let dash = || "—".to_string();
        return Some((
            place.into(),
            label.trim().into(),
            [dash(), dash(), dash()],
            why.trim().into(),
        ));
    };
    let after = |key: &str| -> Option<String> {
        let i = figures.find(key)? + key.len();
        let v = figures[i..].split_whitespace().next()?;
        Some(if v == "-" {
            "—".into()
        } else {
            format!("{v} %")
        })
    };
    let forward = figures.split_whitespace().next()?;
    let forward = if forward == "-" {
        "—".into()
    } else {
        format!("{forward} %")
    };
    let (inverse, tracking) = (after("inverse ")?, after("tracking ")?);
    // What follows the tracking figure: the standing, if any.
    let tracked = figures[figures.find("tracking ")? + "tracking ".len()..].trim_start();
    let value = tracked.split_whitespace().next()?;
    let tail = tracked[value.len()..].trim_start();
    let tail = tail.strip_prefix('%').unwrap_or(tail).trim();
    let ratio = |t: &str| {
        t.split(" is ")
            .nth(1)
            .and_then(|r| r.split(" × ").next())
            .map(str::to_string)
    };
    let standing = if let Some(t) = tail.strip_prefix("set aside: ") {
        format!(
            "set aside: inverse {} × its fit, far from the best",
            ratio(t)?
        )
    } else if let Some(t) = tail.strip_prefix("(inverse ") {
        let r = t.split(" × ").next()?;
        format!("inverse {r} × its fit: at the noise floor")
    } else if let Some(t) = tail.strip_prefix("not admitted: ") {
        match t
            .split("needs ")
            .nth(1)
            .and_then(|n| n.split(" cycles").next())
        {
            Some(cycles) => format!("not admitted: {cycles} cycles per tick"),
            None => format!("not admitted: {t}"),
        }
    } else if tail.is_empty() {
        "inverse holds".into()
    } else {
        return None;
    };
    Some((
        place.into(),
        label.trim().into(),
        [forward, inverse, tracking],
        standing,
    ))
}

/// `auto`'s ranking from every run as one Markdown table: per record and tick rate, each
/// candidate's validation max errors (forward, inverse, tracking) and where it stands, the
/// pick marked with its held-out figures.
fn ranking_table(runs: &[Run]) -> Result<String, String> {
    let mut table = String::from(
        "| record, tick rate | candidate | forward | inverse | tracking | standing |\n\
         |---|---|---:|---:|---:|---|\n",
    );
    for run in runs {
        let what = |e: &str| format!("`{TOOL} {}`: {e}", run.args.join(" "));
        let arg = |flag: &str| {
            run.args
                .iter()
                .position(|a| *a == flag)
                .and_then(|i| run.args.get(i + 1))
                .copied()
        };
        let data = arg("--data").ok_or_else(|| what("no --data"))?;
        let name = data
            .rsplit('/')
            .next()
            .unwrap_or(data)
            .trim_end_matches(".csv");
        let rate = arg("--tick-rate").map_or("any".to_string(), |r| {
            r.parse::<f64>()
                .map_or(r.to_string(), |hz| format!("{:.0} kHz", hz / 1e3))
        });
        let held = |prefix: &str| -> Result<String, String> {
            run.out
                .lines()
                .map(str::trim)
                .find_map(|l| l.strip_prefix(prefix))
                .and_then(|l| l.split_whitespace().nth(1))
                .map(|v| format!("{v} %"))
                .ok_or_else(|| what(&format!("no `{prefix}` line")))
        };
        let (held_forward, held_inverse) = (
            held("held-out (predict vs measured x):")?,
            held("inverse held-out (compensate u vs measured u):")?,
        );
        let mut rows = 0;
        let mut in_ranking = false;
        for line in run.out.lines() {
            if line.starts_with("ranking ") {
                in_ranking = true;
                continue;
            }
            if !line.starts_with("  ") {
                in_ranking = false;
            }
            if !in_ranking || line.trim_start().starts_with('(') {
                continue;
            }
            let (place, label, [f, i, t], standing) =
                ranking_row(line).ok_or_else(|| what(&format!("unread ranking line `{line}`")))?;
            let standing = if rows == 0 {
                format!("**picked** (held out: forward {held_forward}, inverse {held_inverse})")
            } else if place == "-." {
                standing
            } else {
                format!("{place} {standing}")
            };
            let record = if rows == 0 {
                format!("`{name}`, {rate}")
            } else {
                String::new()
            };
            table.push_str(&format!(
                "| {record} | {label} | {f} | {i} | {t} | {standing} |\n"
            ));
            rows += 1;
        }
        if rows == 0 {
            return Err(what("no ranking"));
        }
    }
    Ok(table)
}

/// `lab-stage`'s rows from every run as one Markdown table, a method that several runs print
/// (`none`) once: held-out, the three trajectories and the worst max (`max / RMS %`), or the
/// reason a model was refused.
fn lab_stage_table(runs: &[Run]) -> Result<String, String> {
    let mut table = String::from(
        "| method | held-out (last cycle) | triangle | minor loops | multisine | worst max |\n\
         |---|---:|---:|---:|---:|---:|\n",
    );
    let mut seen: Vec<String> = Vec::new();
    for run in runs {
        let what = |e: &str| format!("`{TOOL} {}`: {e}", run.args.join(" "));
        // A stage with some of its non-idealities taken out: its rows say so.
        let without = run
            .args
            .iter()
            .position(|a| *a == "--without")
            .and_then(|i| run.args.get(i + 1))
            .map(|w| format!(", without {}", w.replace(',', ", ")))
            .unwrap_or_default();
        let mut lines = run.out.lines().skip_while(|l| !l.starts_with("method "));
        if lines.next().is_none() {
            return Err(what("no `method` header"));
        }
        let mut rows = 0;
        for line in lines.take_while(|l| !l.starts_with('(')) {
            let (name, rest) = match line.split_once(" failed: ") {
                Some((head, reason)) => {
                    let name = head.split_whitespace().next().unwrap_or("");
                    (name.to_string(), format!("refused: {reason} | | | | |"))
                }
                None => {
                    let cols: Vec<&str> = line.split_whitespace().collect();
                    let n = cols.len();
                    if n < 6 {
                        return Err(what(&format!("a row with {n} columns: {line:?}")));
                    }
                    let figure = |c: &str| c.replace('/', " / ");
                    (
                        cols[..n - 5].join(" "),
                        format!(
                            "{} | {} | {} | {} | {} |",
                            if cols[n - 5] == "-" {
                                "–".into()
                            } else {
                                figure(cols[n - 5])
                            },
                            figure(cols[n - 4]),
                            figure(cols[n - 3]),
                            figure(cols[n - 2]),
                            cols[n - 1]
                        ),
                    )
                }
            };
            let name = format!("{name}{without}");
            rows += 1;
            if seen.contains(&name) {
                continue;
            }
            table.push_str(&format!("| {name} | {rest}\n"));
            seen.push(name);
        }
        if rows == 0 {
            return Err(what("no rows"));
        }
    }
    Ok(table)
}

/// `lab-stage --variants`'s lines as a table: the stage, its settings, the worst max error of no
/// compensation, `auto` and the textbook P–I, and what `auto` picked.
fn variants_table(out: &str) -> Result<String, String> {
    let mut table = String::from(
        "| stage | changes (`--set`) | none | textbook P–I | auto | auto picked |\n\
         |---|---|---:|---:|---:|---|\n",
    );
    let mut lines = out.lines().skip_while(|l| !l.starts_with("stage "));
    if lines.next().is_none() {
        return Err("no `stage` header".into());
    }
    let mut rows = 0;
    for line in lines.filter(|l| !l.trim().is_empty()) {
        let (head, settings) = line
            .rsplit_once(" / ")
            .ok_or_else(|| format!("no ` / ` in {line:?}"))?;
        let cols: Vec<&str> = head.split_whitespace().collect();
        let n = cols.len();
        if n < 5 || cols[n - 4..n - 1].iter().any(|c| c.parse::<f64>().is_err()) {
            return Err(format!("not a stage's line: {line:?}"));
        }
        let settings = match settings.trim() {
            "-" => "–".to_string(),
            s => format!("`{}`", s.replace(',', ", ")),
        };
        table.push_str(&format!(
            "| {} | {settings} | {} | {} | {} | {} |\n",
            cols[..n - 4].join(" "),
            cols[n - 4],
            cols[n - 2],
            cols[n - 3],
            cols[n - 1]
        ));
        rows += 1;
    }
    if rows == 0 {
        return Err("no stages".into());
    }
    Ok(table)
}

/// `learn`'s summary of each run as one row: the feedforward alone (and shaped, with input
/// shaping), the learned and the replayed errors, the reduction, and `(not met)` beside a
/// figure that misses its goal (RMS ≥ 20× lower, max ≤ 0.1 %, replay max ≤ 0.2 %).
fn learn_table(runs: &[Run]) -> Result<String, String> {
    let mut table = String::from(
        "| waveform | run | feedforward alone RMS % | shaped feedforward alone RMS % | learned max % | learned RMS % | RMS reduction | replay max % | RMS below 15 kHz % | RMS 15 kHz–Nyquist % |\n\
         |---|---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for run in runs {
        let arg = |flag: &str| {
            run.args
                .iter()
                .position(|a| *a == flag)
                .and_then(|i| run.args.get(i + 1))
        };
        let what = |e: &str| format!("`{TOOL} {}`: {e}", run.args.join(" "));
        let waveform = arg("--waveform").ok_or_else(|| what("no --waveform"))?;
        let (shape, hz) = waveform
            .split_once(':')
            .ok_or_else(|| what("a waveform is SHAPE:HZ"))?;
        let hz: f64 = hz.parse().map_err(|_| what("a waveform's frequency"))?;
        let label = if hz >= 1000.0 {
            format!("{} kHz {shape}", hz / 1000.0)
        } else {
            format!("{hz} Hz {shape}")
        };
        let shaped = arg("--shape-hz").is_some();
        // The summary table's row for `name`: its four figures.
        let row = |name: &str| -> Result<Vec<String>, String> {
            let line = run
                .out
                .lines()
                .find(|l| l.starts_with(&format!("| {name} |")))
                .ok_or_else(|| what(&format!("no `{name}` row")))?;
            let cols: Vec<String> = line
                .trim_matches('|')
                .split('|')
                .skip(1)
                .map(|c| c.trim().to_string())
                .collect();
            if cols.len() == 4 {
                Ok(cols)
            } else {
                Err(what(&format!(
                    "the `{name}` row has {} figures",
                    cols.len()
                )))
            }
        };
        let met = |goal: &str| -> Result<&str, String> {
            let line = run
                .out
                .lines()
                .find(|l| l.starts_with(&format!("goal: {goal}")))
                .ok_or_else(|| what(&format!("no goal `{goal}`")))?;
            Ok(if line.ends_with(": met") {
                ""
            } else {
                " (not met)"
            })
        };
        let alone = row("inverse P–I feedforward alone")?;
        let shaped_alone = if shaped {
            row("shaped feedforward alone")?[1].clone()
        } else {
            "—".into()
        };
        let learned = row("learned (last period)")?;
        let replay = row("replayed, sensor off")?;
        let reduction = run
            .out
            .lines()
            .find_map(|l| l.strip_prefix("RMS reduction "))
            .and_then(|l| l.split(';').next())
            .ok_or_else(|| what("no `RMS reduction`"))?;
        table.push_str(&format!(
            "| {label} | {} | {} | {shaped_alone} | {}{} | {} | {reduction}{} | {}{} | {} | {} |\n",
            if shaped {
                "shaping, corner 23 kHz"
            } else {
                "no shaping, corner 18 kHz"
            },
            alone[1],
            learned[0],
            met("max")?,
            learned[1],
            met("RMS")?,
            replay[0],
            met("replay")?,
            learned[2],
            learned[3],
        ));
    }
    Ok(table)
}

/// Thousands grouped by a space, as the book writes counts (`1 573`).
fn grouped(n: u64) -> String {
    let digits = n.to_string();
    let mut out = String::new();
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i) % 3 == 0 {
            out.push(' ');
        }
        out.push(c);
    }
    out
}

/// A bench configuration's name (`inverse-pi16+pi16-observer+pi+drift`) as the book writes it
/// (`inverse P–I 16 + P–I 16 observer + PI + drift`); a part it does not know stays as it is.
fn config_label(name: &str) -> String {
    fn model(m: &str) -> String {
        if let Some(gpi) = m.strip_prefix("gpi") {
            if let Some((n, zones)) = gpi.split_once('x') {
                return format!("generalised P–I {n} ({zones} dead zones)");
            }
        }
        if let Some(n) = m.strip_prefix("pi").filter(|n| n.parse::<u32>().is_ok()) {
            return format!("P–I {n}");
        }
        match m {
            "duhem" => "Duhem".into(),
            "bouc-wen" => "Bouc–Wen".into(),
            other => other.into(),
        }
    }
    name.split('+')
        .map(|part| {
            if let Some(m) = part.strip_prefix("inverse-") {
                format!("inverse {}", model(m))
            } else if let Some(m) = part.strip_suffix("-observer") {
                format!("{} observer", model(m))
            } else if let Some(n) = part.strip_prefix("creep") {
                format!("creep {n}")
            } else {
                match part {
                    "pi" => "PI".into(),
                    "pid" => "PID".into(),
                    other => other.into(),
                }
            }
        })
        .collect::<Vec<_>>()
        .join(" + ")
}

/// The streamed scenarios the first table takes each configuration's worst of.
const STREAMED: [&str; 5] = [
    "triangle",
    "sine-750Hz",
    "full-range-steps",
    "random",
    "nested-loops",
];

/// The scan, analog-input and trigger-input scenarios, with their columns' titles.
const SCANNED: [(&str, &str); 8] = [
    ("scan-raster-triggers", "raster"),
    ("scan-lissajous-triggers", "Lissajous"),
    ("scan-spiral-triggers", "spiral"),
    ("scan-raster-learning", "raster + learning"),
    ("scan-spiral-learning", "spiral + learning"),
    (
        "scan-spiral-on-trigger-learning",
        "spiral started by the input's edges + learning",
    ),
    ("analog-input", "analog input"),
    ("triangle-on-trigger", "stream, the input's edges"),
];

/// `site` without its source lines (`recorder.rs:799` → `recorder.rs`): the page names the
/// function and the file, and does not move with every edit above the line.
fn without_lines(site: &str) -> String {
    let mut out = String::new();
    let mut rest = site;
    while let Some(at) = rest.find(".rs:") {
        out.push_str(&rest[..at + 3]);
        rest = rest[at + 4..].trim_start_matches(|c: char| c.is_ascii_digit());
    }
    out.push_str(rest);
    out
}

/// The whole-interrupt bench's figures (`target/figures/tick-cost.json`, written by
/// `tests/irq_bench.rs` when every assertion holds) as the tick-cost page's tables.
fn tick_cost(out: &str) -> Result<String, String> {
    use serde_json::Value;
    let v: Value = serde_json::from_str(out).map_err(|e| format!("not the bench's JSON: {e}"))?;
    let field = |v: &Value, k: &str| -> Result<u64, String> {
        v.get(k)
            .and_then(Value::as_u64)
            .ok_or_else(|| format!("no number `{k}` in {v}"))
    };
    let sysclk = v
        .get("sysclk_hz")
        .and_then(Value::as_f64)
        .ok_or("no `sysclk_hz`")?;
    let (scan, learning, analog, trigger) = (
        field(&v, "scan_cycles")?,
        field(&v, "learning_cycles")?,
        field(&v, "analog_cycles")?,
        field(&v, "trigger_cycles")?,
    );
    // Every feature on: a scan, the learning, the trigger input armed.
    let every_charge = scan + learning + trigger;
    let rows = v.get("rows").and_then(Value::as_array).ok_or("no `rows`")?;
    let budgets = v
        .get("budgets")
        .and_then(Value::as_object)
        .ok_or("no `budgets`")?;
    // Each measured row: (configuration, scenario) → (instructions, cycles 0 WS, cycles 5 WS).
    let mut measured: Vec<(&str, &str, [u64; 3])> = Vec::new();
    for r in rows {
        let name = r
            .get("name")
            .and_then(Value::as_str)
            .ok_or("a row has no name")?;
        let counts = [
            field(r, "instructions_max")?,
            field(r, "cycles_max")?,
            field(r, "cycles_max_ws5")?,
        ];
        let (config, scenario) = name.split_once('/').unwrap_or((name, ""));
        measured.push((config, scenario, counts));
    }
    let boot = measured.first().ok_or("no rows")?.2;
    // The configurations in the order the bench ran them.
    let mut configs: Vec<&str> = Vec::new();
    for (c, s, _) in &measured {
        if !s.is_empty() && !configs.contains(c) {
            configs.push(c);
        }
    }
    // The worst of each count over a configuration's scenarios that `pick` selects.
    let worst = |config: &str, pick: &dyn Fn(&str) -> bool| -> Result<[u64; 3], String> {
        let mut w = [0u64; 3];
        let mut any = false;
        for (_, _, c) in measured.iter().filter(|(c, s, _)| *c == config && pick(s)) {
            any = true;
            for i in 0..3 {
                w[i] = w[i].max(c[i]);
            }
        }
        if any {
            Ok(w)
        } else {
            Err(format!("{config}: no such scenario measured"))
        }
    };
    let triple = |c: [u64; 3]| format!("{} / {} / {}", grouped(c[0]), grouped(c[1]), grouped(c[2]));
    let rate = |cycles: u64| {
        let hz = (sysclk / cycles as f64 / 100.0).floor() as u64 * 100;
        format!("{} Hz", grouped(hz))
    };
    let predicted = |config: &str| -> Result<u64, String> {
        budgets
            .get(config)
            .and_then(Value::as_u64)
            .ok_or_else(|| format!("{config}: no prediction"))
    };

    let mut t = String::new();
    t.push_str(
        "Worst tick of each configuration, instructions / cycles at 0 WS / cycles at 5 WS: streamed \
         (the worst of triangle, sine, full-range steps, random, nested loops) and with every \
         feature on (the worst of the scans with the learning, each with its trigger outputs, one \
         of them started by the trigger input's edges, the capture of all seven signals and \
         telemetry's tap of all seven on every tick). \"Predicted\" is the tick budget's \
         (cycles, 5 WS), with the scan's ",
    );
    t.push_str(&format!(
        "({scan}), the learning's ({learning}) and the armed trigger input's ({trigger}) charges \
         for every feature on; the highest admitted rate is the highest control rate whose \
         period holds that prediction.\n\n"
    ));
    t.push_str("| configuration | streamed | every feature on | predicted | predicted, every feature | highest admitted rate, streamed | highest admitted rate, every feature |\n");
    t.push_str("|---|---:|---:|---:|---:|---:|---:|\n");
    t.push_str(&format!(
        "| boot: bypass, no model, nothing running | {} | – | – | – | – | – |\n",
        triple(boot)
    ));
    for config in &configs {
        let streamed = worst(config, &|s| STREAMED.contains(&s))?;
        let every = worst(config, &|s| {
            s.starts_with("scan-") && s.ends_with("-learning")
        })?;
        let p = predicted(config)?;
        t.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} |\n",
            config_label(config),
            triple(streamed),
            triple(every),
            grouped(p),
            grouped(p + every_charge),
            rate(p),
            rate(p + every_charge),
        ));
    }

    t.push_str(&format!(
        "\nEach scan pattern (200 Hz on x, ±0.8, trigger pulses of 2 ticks), alone and with the \
         learning on; the spiral started by the trigger input's rising edge every 150 ticks (the \
         input armed again before each, a capture armed on the first); the analog setpoint input \
         as the source (budget's charge: {analog} cycles); and a stream the input's edges start \
         again, a capture armed on the first (the armed input's charge: {trigger} cycles); worst \
         tick, instructions / cycles at 5 WS:\n\n"
    ));
    t.push_str("| configuration |");
    for (_, title) in SCANNED {
        t.push_str(&format!(" {title} |"));
    }
    t.push_str("\n|---|");
    t.push_str(&"---:|".repeat(SCANNED.len()));
    t.push('\n');
    for config in &configs {
        t.push_str(&format!("| {} |", config_label(config)));
        for (scenario, _) in SCANNED {
            let c = worst(config, &|s| s == scenario)?;
            t.push_str(&format!(" {} / {} |", grouped(c[0]), grouped(c[2])));
        }
        t.push('\n');
    }

    let parts = v
        .get("part_names")
        .and_then(Value::as_array)
        .ok_or("no `part_names`")?;
    t.push_str(
        "\nEach configuration's worst streamed tick, cycles at 5 WS by the part of the tick its \
         source belongs to, against the tick budget's prediction:\n\n| configuration |",
    );
    for p in parts {
        t.push_str(&format!(" {} |", p.as_str().unwrap_or("?")));
    }
    t.push_str(" total | predicted | predicted / measured |\n|---|");
    t.push_str(&"---:|".repeat(parts.len() + 3));
    t.push('\n');
    for w in v
        .get("worst_by_config")
        .and_then(Value::as_array)
        .ok_or("no `worst_by_config`")?
    {
        let config = w.get("config").and_then(Value::as_str).ok_or("no config")?;
        let total = field(w, "cycles_ws5")?;
        let p = field(w, "predicted")?;
        let cells: Vec<String> = w
            .get("parts")
            .and_then(Value::as_array)
            .ok_or("no parts")?
            .iter()
            .map(|c| grouped(c.as_u64().unwrap_or(0)))
            .collect();
        t.push_str(&format!(
            "| {} | {} | {} | {} | {:.2} |\n",
            config_label(config),
            cells.join(" | "),
            grouped(total),
            grouped(p),
            p as f64 / total as f64
        ));
    }

    let reference = configs.first().ok_or("no configuration")?;
    if let Some(by_file) = v.get("worst_by_file").and_then(|f| f.get(*reference)) {
        let files = by_file
            .get("files")
            .and_then(Value::as_array)
            .ok_or("no files")?;
        t.push_str(&format!(
            "\nThe reference configuration's ({}) worst streamed tick by source file (`(no \
             line)`: the exception's entry and return, code without line information):\n\n\
             | source file | cycles (5 WS) |\n|---|---:|\n",
            config_label(reference)
        ));
        let mut total = 0;
        for f in files {
            let name = f
                .get(0)
                .and_then(Value::as_str)
                .ok_or("a file has no name")?;
            let c = f
                .get(1)
                .and_then(Value::as_u64)
                .ok_or("a file has no cycles")?;
            total += c;
            t.push_str(&format!("| `{name}` | {} |\n", grouped(c)));
        }
        t.push_str(&format!("| **total** | **{}** |\n", grouped(total)));
    }

    let shipped = v.get("shipped_worst").ok_or("no `shipped_worst`")?;
    t.push_str(&format!(
        "\nThe shipped P–I and Duhem configurations' worst tick: **{} instructions, {} cycles at \
         0 WS, {} at 5 WS** (goal {} cycles at 0 WS: {}); the generalised P–I + creep \
         configuration's: {} instructions.\n",
        grouped(field(shipped, "instructions")?),
        grouped(field(shipped, "cycles")?),
        grouped(field(shipped, "cycles_ws5")?),
        grouped(field(&v, "goal_cycles")?),
        if field(shipped, "cycles")? <= field(&v, "goal_cycles")? {
            "met"
        } else {
            "not met"
        },
        grouped(field(&v, "family_worst_instructions")?),
    ));

    t.push_str(
        "\nThe critical sections outside the tick that hold it off (from the instruction that \
         masks it to the one that unmasks it), longest first:\n\n\
         | where (function, source line) | times | instructions | cycles (0 WS) | cycles (5 WS) | µs at 5 WS |\n\
         |---|---:|---:|---:|---:|---:|\n",
    );
    for h in v
        .get("held_off")
        .and_then(Value::as_array)
        .ok_or("no `held_off`")?
    {
        let c5 = field(h, "cycles_ws5")?;
        t.push_str(&format!(
            "| `{}` | {} | {} | {} | {} | {:.1} |\n",
            without_lines(h.get("site").and_then(Value::as_str).ok_or("no site")?),
            grouped(field(h, "count")?),
            grouped(field(h, "instructions")?),
            grouped(field(h, "cycles")?),
            grouped(c5),
            c5 as f64 / sysclk * 1e6
        ));
    }
    let stack = v.get("stack").ok_or("no `stack`")?;
    t.push_str(&format!(
        "\nThe bench image's stack high-water mark over every scenario: {} bytes of the {} its \
         static RAM leaves (reserve {}).\n",
        grouped(field(stack, "used")?),
        grouped(field(stack, "room")?),
        grouped(field(stack, "reserve")?),
    ));
    Ok(t)
}

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
    let mut stale = Vec::new();
    for f in FIGURES {
        let named = names.contains(&f.name);
        // Run: what is named, or with no names every checked figure; `--check` only checked ones.
        let wanted = named || (names.is_empty() && f.checked);
        if !wanted || (check && !f.checked) {
            if names.is_empty() && !f.checked && !check {
                println!(
                    "{}: {} left as it is (timings: `cargo xtask figures {}` writes it)",
                    f.page, f.name, f.name
                );
            }
            continue;
        }
        let path = root.join(f.page);
        let page = std::fs::read_to_string(&path)
            .map_err(|e| format!("{}: cannot read: {e}", path.display()))?;
        let mut runs = Vec::new();
        for args in f.runs {
            runs.push(Run {
                args,
                out: output(root, f.source, args).map_err(|e| format!("{}: {e}", f.name))?,
            });
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

#[cfg(test)]
mod tests {
    use super::*;

    const GOLDEN: &str = "set                   ticks    bytes  outputs CRC  drive LSB16  estimate LSB16  code    ambiguous  underrun/range/slew/adc/dac/drift
bypass                 2400    48011  1234abcd       0.0001       0.0000    0.4997     13      50/338/746/0/7/0
ipi8-pi-open           2400    48011  00ff00ff       1.0507       0.5686    0.4997      4      50/497/801/33/7/253
total 96022 bytes in 2 sets
tests/golden/vectors.bin is up to date
";

    #[test]
    fn test_output_loses_the_harness_lines_and_keeps_what_the_test_printed() {
        let out = "\nrunning 2 tests\ntest a ... | x |\n|---|\n| 1 |\nok\ntest b ... first line\nok\n\ntest result: ok. 2 passed\n";
        assert_eq!(test_printed(out), "| x |\n|---|\n| 1 |\nfirst line\n");
        assert_eq!(
            test_markdown(out).unwrap(),
            "| x |\n|---|\n| 1 |\n\nfirst line\n"
        );
        assert!(test_markdown("running 1 test\ntest a ... ok\n").is_err());
    }

    #[test]
    fn criterion_results_become_a_row_each() {
        let out = "pi_step/forward/8       time:   [5.5 ns 5.6 ns 5.7 ns]\n\
                   Found 3 outliers among 100 measurements (3.00%)\n\
                   duhem_step/inverse\n                        time:   [23.9 ns 24.1 ns 24.4 ns]\n\
                   change: [-1.0% +0.2% +1.1%] (p = 0.70 > 0.05)\n";
        assert_eq!(
            criterion_table(out).unwrap(),
            "| benchmark | time per iteration |\n|---|---:|\n| `pi_step/forward/8` | 5.6 ns |\n| `duhem_step/inverse` | 24.1 ns |\n"
        );
        assert!(criterion_table("nothing measured\n").is_err());
        assert!(criterion_table("x time: [1 ns]\n").is_err());
    }

    #[test]
    fn bench_configurations_read_as_the_book_writes_them() {
        assert_eq!(
            config_label("inverse-pi16+pi16-observer+pi+drift"),
            "inverse P–I 16 + P–I 16 observer + PI + drift"
        );
        assert_eq!(
            config_label("inverse-gpi32x8+creep6+gpi32x8-observer+pid+notch+shaping+drift"),
            "inverse generalised P–I 32 (8 dead zones) + creep 6 + generalised P–I 32 (8 dead zones) observer + PID + notch + shaping + drift"
        );
        assert_eq!(
            config_label("inverse-bouc-wen+bouc-wen-observer"),
            "inverse Bouc–Wen + Bouc–Wen observer"
        );
        assert_eq!(grouped(7), "7");
        assert_eq!(grouped(1573), "1 573");
        assert_eq!(grouped(100800), "100 800");
        assert_eq!(grouped(1234567), "1 234 567");
    }

    /// A bench output of one configuration with every scenario the tables read.
    fn bench_json() -> String {
        let mut rows = vec![r#"{"name": "boot (defaults: bypass, no model)", "ticks": 10, "instructions_mean": 300.0, "instructions_max": 326, "cycles_max": 569, "cycles_max_ws5": 689}"#.to_string()];
        let scenarios = STREAMED
            .iter()
            .chain(SCANNED.iter().map(|(s, _)| s))
            .chain(["reload-and-mode-switches", "load"].iter());
        for (i, s) in scenarios.enumerate() {
            rows.push(format!(
                r#"{{"name": "inverse-pi16+pi16-observer+pi+drift/{s}", "ticks": 100, "instructions_mean": 800.0, "instructions_max": {}, "cycles_max": {}, "cycles_max_ws5": {}}}"#,
                900 + i,
                1400 + i,
                1570 + i
            ));
        }
        format!(
            r#"{{"sysclk_hz": 168000000.0, "goal_cycles": 600, "scan_cycles": 150, "learning_cycles": 90,
            "analog_cycles": 32, "trigger_cycles": 200, "part_names": ["fixed", "P–I banks"],
            "stack": {{"used": 30000, "room": 55000, "reserve": 49152}},
            "budgets": {{"inverse-pi16+pi16-observer+pi+drift": 1666}},
            "rows": [{}],
            "worst_by_config": [{{"config": "inverse-pi16+pi16-observer+pi+drift", "parts": [1066, 507], "cycles_ws5": 1573, "cycles": 1408, "instructions": 899, "predicted": 1666}}],
            "worst_by_file": {{"inverse-pi16+pi16-observer+pi+drift": {{"row": "x", "files": [["prandtl_ishlinskii.rs", 400], ["(no line)", 22]]}}}},
            "shipped_worst": {{"instructions": 1000, "cycles": 1550, "cycles_ws5": 1740}},
            "family_worst_instructions": 1558,
            "held_off": [{{"site": "read_capture_piece, recorder.rs:770", "count": 12, "instructions": 276, "cycles": 500, "cycles_ws5": 591}}]}}"#,
            rows.join(", ")
        )
    }

    #[test]
    fn the_bench_output_becomes_the_tick_cost_tables() {
        let t = tick_cost(&bench_json()).unwrap();
        // The boot row, then the configuration: streamed is the worst of the five streamed
        // scenarios (the fifth, index 4); every feature on the worst scan with the learning
        // (the spiral on the trigger + learning, index 10); the rates from the prediction and
        // its charges (scan, learning, trigger: 1 666 + 150 + 90 + 200).
        assert!(
            t.contains("| boot: bypass, no model, nothing running | 326 / 569 / 689 | – |"),
            "{t}"
        );
        assert!(
            t.contains("| inverse P–I 16 + P–I 16 observer + PI + drift | 904 / 1 404 / 1 574 | 910 / 1 410 / 1 580 | 1 666 | 2 106 | 100 800 Hz | 79 700 Hz |"),
            "{t}"
        );
        // The scans: raster is index 5, the stream on the trigger index 12 (instructions /
        // 5 WS).
        assert!(t.contains("| 905 / 1 575 | 906 / 1 576 | 907 / 1 577 | 908 / 1 578 | 909 / 1 579 | 910 / 1 580 | 911 / 1 581 | 912 / 1 582 |"), "{t}");
        assert!(t.contains("| 1 066 | 507 | 1 573 | 1 666 | 1.06 |"), "{t}");
        assert!(
            t.contains(
                "| `prandtl_ishlinskii.rs` | 400 |\n| `(no line)` | 22 |\n| **total** | **422** |"
            ),
            "{t}"
        );
        assert!(t.contains("**1 000 instructions, 1 550 cycles at 0 WS, 1 740 at 5 WS** (goal 600 cycles at 0 WS: not met)"), "{t}");
        assert!(
            t.contains("| `read_capture_piece, recorder.rs` | 12 | 276 | 500 | 591 | 3.5 |"),
            "{t}"
        );
        assert_eq!(
            without_lines("handle, register/basepri_max.rs:24 in recorder.rs:799"),
            "handle, register/basepri_max.rs in recorder.rs"
        );
        assert!(t.contains("30 000 bytes of the 55 000"), "{t}");
        // A bench output without a scenario the tables read is an error, not a gap.
        let without = bench_json().replace("scan-spiral-learning", "something-else");
        assert!(tick_cost(&without).is_err());
        assert!(tick_cost("not json").is_err());
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
    fn golden_lines_become_the_table() {
        let t = golden_distances(GOLDEN).unwrap();
        assert!(t.contains("| `bypass` | 0.0001 | 0.0000 | 0.4997 | 13 | 50/338/746/0/7/0 |\n"));
        assert!(
            t.contains("| `ipi8-pi-open` | 1.0507 | 0.5686 | 0.4997 | 4 | 50/497/801/33/7/253 |\n")
        );
        assert!(t.ends_with("\n2 sets, 96022 bytes in `tests/golden/vectors.bin`.\n"));
        // A lost line is an error, not a shorter table.
        let cut = GOLDEN.replace("bypass                 2400", "");
        assert!(golden_distances(&cut).is_err());
        assert!(golden_distances("").is_err());
    }

    #[test]
    fn markdown_output_keeps_its_tables_and_drops_the_files_written() {
        let out = "title one\n| a | b |\n|---|---:|\n| x | 1 |\n\nsecond line\nthird\n| c |\n|---|\n| y |\n\nwrote out/x.png\n";
        assert_eq!(
            markdown(out).unwrap(),
            "title one\n\n| a | b |\n|---|---:|\n| x | 1 |\n\nsecond line\n\nthird\n\n| c |\n|---|\n| y |\n"
        );
        // Output without a table is an error, not an empty figure.
        assert!(markdown("wrote out/x.png\n").is_err());
        assert!(markdown("just text\n").is_err());
    }

    #[test]
    fn tune_summary_leaves_out_the_response() {
        let out = "       200 Hz    -4.17 dB      -3.8°\n     10258 Hz    -2.23 dB    -112.4°\nfit: gain 0.6\ntuned: kp 0.05\n| a |\n|---:|\n| 1 |\n";
        assert_eq!(
            tune_summary(out).unwrap(),
            "fit: gain 0.6\n\ntuned: kp 0.05\n\n| a |\n|---:|\n| 1 |\n"
        );
        assert!(tune_summary("       200 Hz    -4.17 dB      -3.8°\n").is_err());
    }

    #[test]
    fn ranking_lines_become_rows_with_their_standing() {
        let out = [
            "ranking (fitted on t < 5.1502 s, scored on 5.1502 <= t < 5.95 s):",
            "  (legend)",
            "  1.  P-I (16 uniform operators)               forward  1.30 % (RMS 0.38 %)  inverse  1.59 %  tracking  1.02 %",
            "  2.  P-I (4 uniform operators) + creep (1 mode) forward  1.10 % (RMS 0.39 %)  inverse  1.81 %  tracking  1.84 %  (inverse 1.64 × its forward: at the record's noise floor)",
            "  -.  Bouc-Wen + creep (1 mode)                forward  0.90 % (RMS 0.23 %)  inverse 14.58 %  tracking 13.55 %  set aside: inverse max 14.58 % is 16.22 × its forward max 0.90 % and more",
            "  -.  Duhem + creep (1 mode)                   forward  1.11 % (RMS 0.30 %)  inverse 17.58 %  tracking 15.66 %  not admitted: the board at 100 kHz would refuse it: it needs 1732 cycles per tick, more",
            "  -.  Duhem                                    not fitted: too few samples",
            "picked: P-I",
            "identified P-I (16 uniform operators) from x",
            "  held-out (predict vs measured x): max 1.16 %  RMS 0.30 %  (20251 samples)",
            "  inverse held-out (compensate u vs measured u): max 1.47 %  RMS 0.33 %  (20251 samples)",
        ]
        .join("\n");
        let out = out.as_str();
        let runs = [Run {
            args: &["identify", "--data", "data/a.csv", "--tick-rate", "100000"],
            out: out.into(),
        }];
        let table = ranking_table(&runs).unwrap();
        let rows: Vec<&str> = table.lines().skip(2).collect();
        assert_eq!(
            rows,
            [
                "| `a`, 100 kHz | P-I (16 uniform operators) | 1.30 % | 1.59 % | 1.02 % | **picked** (held out: forward 1.16 %, inverse 1.47 %) |",
                "|  | P-I (4 uniform operators) + creep (1 mode) | 1.10 % | 1.81 % | 1.84 % | 2. inverse 1.64 × its fit: at the noise floor |",
                "|  | Bouc-Wen + creep (1 mode) | 0.90 % | 14.58 % | 13.55 % | set aside: inverse 16.22 × its fit, far from the best |",
                "|  | Duhem + creep (1 mode) | 1.11 % | 17.58 % | 15.66 % | not admitted: 1732 cycles per tick |",
                "|  | Duhem | — | — | — | not fitted: too few samples |",
            ]
        );
        let kept = ranking_only(out).unwrap();
        assert!(
            kept.contains("picked: P-I") && kept.contains("inverse held-out"),
            "{kept}"
        );
    }

    #[test]
    fn verbatim_output_is_a_text_block() {
        assert_eq!(
            verbatim("\nline 1  \n  line 2\nwrote a.png\n\n").unwrap(),
            "```text\nline 1\n  line 2\n```\n"
        );
        assert!(verbatim("wrote a.png\n").is_err());
    }

    #[test]
    fn learn_runs_become_rows_with_their_unmet_goals_marked() {
        let out = "| run | max % | RMS % | RMS below 15 kHz % | RMS 15 kHz–Nyquist % |\n\
                   |---|---:|---:|---:|---:|\n\
                   | inverse P–I feedforward alone | 1.9294 | 1.3000 | 1.2855 | 0.1939 |\n\
                   | learned (last period) | 0.7359 | 0.2212 | 0.0092 | 0.2210 |\n\
                   | replayed, sensor off | 0.7336 | 0.2199 | 0.0084 | 0.2198 |\n\n\
                   RMS reduction 5.9×; 50 tables posted, 0 periods missed\n\
                   goal: RMS ≥ 20× lower than feedforward alone: NOT met\n\
                   goal: max ≤ 0.1 % of the stroke: NOT met\n\
                   goal: replay (sensor off) max ≤ 0.2 %: met\n";
        let runs = [Run {
            args: &["learn", "--waveform", "triangle:250"],
            out: out.into(),
        }];
        let table = learn_table(&runs).unwrap();
        assert!(
            table.ends_with(
                "| 250 Hz triangle | no shaping, corner 18 kHz | 1.3000 | — | 0.7359 (not met) | \
                 0.2212 | 5.9× (not met) | 0.7336 | 0.0092 | 0.2210 |\n"
            ),
            "{table}"
        );
        // A shaped run needs its shaped row; a missing row is an error, not a blank.
        let shaped = [Run {
            args: &["learn", "--waveform", "triangle:250", "--shape-hz", "21807"],
            out: out.into(),
        }];
        assert!(learn_table(&shaped).is_err());
    }

    #[test]
    fn identify_runs_become_a_row_per_model_and_a_column_pair_per_record() {
        let out = |model: &str, fwd: &str, inv: &str| {
            format!(
                "identified {model} from data/x.csv\n  fit      (predict vs measured x): max 9 %  RMS 9 %\n  \
                 held-out (predict vs measured x): max {fwd}  (20251 samples)\n  \
                 inverse held-out (compensate u vs measured u): max {inv}  (20251 samples)\n"
            )
        };
        let runs = [
            Run {
                args: &[
                    "identify",
                    "--model",
                    "pi",
                    "--creep",
                    "--data",
                    "data/a.csv",
                    "--fit-until",
                    "5",
                ],
                out: out(
                    "P-I (17 uniform operators) + creep (2 modes)",
                    "0.83 %  RMS 0.18 %",
                    "1.29 %  RMS 0.24 %",
                ),
            },
            Run {
                args: &[
                    "identify",
                    "--model",
                    "pi",
                    "--creep",
                    "--data",
                    "data/b.csv",
                    "--fit-until",
                    "16",
                ],
                out: out(
                    "P-I (17 uniform operators) + creep (1 mode)",
                    "1.44 %  RMS 0.70 %",
                    "2.08 %  RMS 0.89 %",
                ),
            },
        ];
        let table = identify_table(&runs).unwrap();
        assert!(
            table.ends_with(
                "| P-I (17 uniform operators) + creep | 0.83 / 0.18 % | 1.29 / 0.24 % | 1.44 / 0.70 % | 2.08 / 0.89 % |\n"
            ),
            "{table}"
        );
        assert!(
            table.starts_with("| model | `a` (`--fit-until 5`)"),
            "{table}"
        );
        // A run without its held-out line is an error, not an empty cell.
        let cut = [Run {
            args: runs[0].args,
            out: runs[0].out.replace("held-out (predict", "(predict"),
        }];
        assert!(identify_table(&cut).is_err());
    }

    #[test]
    fn lab_stage_rows_of_every_run_become_one_table() {
        let runs = [
            Run {
                args: &["lab-stage"],
                out: "Lab stage (seed 1)\nmethod     held-out max/rms   triangle  minor loops  multisine  worst max\n\
                      none    -   10.47/5.46   10.47/4.80   10.50/5.06   10.50\n\
                      auto: gpi+creep   1.58/0.79   0.66/0.29   0.63/0.23   0.62/0.23   0.66\n\
                      (max/rms error in %)\n"
                    .into(),
            },
            Run {
                args: &["lab-stage", "--model", "duhem"],
                out: "method     held-out\nnone    -   10.47/5.46   10.47/4.80   10.50/5.06   10.50\n\
                      duhem     - failed: Duhem does not fit this record\n(max/rms)\n"
                    .into(),
            },
        ];
        assert_eq!(
            lab_stage_table(&runs).unwrap(),
            "| method | held-out (last cycle) | triangle | minor loops | multisine | worst max |\n\
             |---|---:|---:|---:|---:|---:|\n\
             | none | – | 10.47 / 5.46 | 10.47 / 4.80 | 10.50 / 5.06 | 10.50 |\n\
             | auto: gpi+creep | 1.58 / 0.79 | 0.66 / 0.29 | 0.63 / 0.23 | 0.62 / 0.23 | 0.66 |\n\
             | duhem | refused: Duhem does not fit this record | | | | |\n"
        );
        let headless = [Run {
            args: &["lab-stage"],
            out: "none - 1/1 1/1 1/1 1/1 1\n".into(),
        }];
        assert!(lab_stage_table(&headless).is_err());
    }

    #[test]
    fn variant_lines_become_the_table() {
        let out = "Worst max tracking error\n\
                   stage                      none     auto       pi  auto picked / settings\n\
                   default                   10.50     0.66     4.42  gpi+creep / -\n\
                   no creep                   8.88     0.74     3.63  gpi / creep_per_decade=0,noise_rms_nm=5\n";
        assert_eq!(
            variants_table(out).unwrap(),
            "| stage | changes (`--set`) | none | textbook P–I | auto | auto picked |\n\
             |---|---|---:|---:|---:|---|\n\
             | default | – | 10.50 | 4.42 | 0.66 | gpi+creep |\n\
             | no creep | `creep_per_decade=0, noise_rms_nm=5` | 8.88 | 3.63 | 0.74 | gpi |\n"
        );
        assert!(variants_table("default 10.50 0.66 4.42 gpi / -\n").is_err());
        assert!(variants_table("stage none auto pi\ndefault x y z gpi / -\n").is_err());
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
