//! Golden vectors: the tick computes, on the host and on the Cortex-M4, exactly the outputs
//! stored in `tests/golden/vectors.bin`.
//!
//! * On the host: every set's stored inputs go through `twinstack_golden::replay` (the
//!   library's `Controller::tick`); every output must equal the stored one. A difference means
//!   the tick's behaviour changed: if that was intended, regenerate the vectors (the
//!   `f64`-reference check in `identify/tests/golden.rs` then shows the new ones are right).
//! * On the target: the `golden-replay` image (`qemu-images/src/bin/golden-replay/`) runs the
//!   same replay in QEMU's netduinoplus2 (STM32F405, Cortex-M4F) and reports, per set, the fingerprint of
//!   the configuration it built, the CRC-32 of its outputs and the first differing tick; they
//!   must equal the host's, bit for bit.

mod support;

use std::time::Duration;
use twinstack::config::settings::{Mode, Model};
use twinstack_golden::{config_fingerprint, replay, ReplayResult, VectorSet, VectorSets};

const REGENERATE: &str = "cargo run --release -p twinstack-cli -- golden --write";

fn vector_file() -> Vec<u8> {
    let path = support::workspace_root().join("tests/golden/vectors.bin");
    std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn sets(file: &[u8]) -> Vec<VectorSet<'_>> {
    VectorSets::new(file)
        .collect::<Result<Vec<_>, _>>()
        .unwrap_or_else(|e| {
            panic!("tests/golden/vectors.bin is malformed: {e:?}; regenerate with `{REGENERATE}`")
        })
}

fn host_replay(set: &VectorSet<'_>) -> ReplayResult {
    replay(set).unwrap_or_else(|e| {
        panic!(
            "set {}: the stored configuration no longer builds ({e:?}); regenerate with `{REGENERATE}`",
            set.name()
        )
    })
}

/// A model as the coverage lists name it.
fn model_name(model: &Option<Model>) -> String {
    match model {
        None => "none".into(),
        Some(Model::PrandtlIshlinskii(p)) => format!("P–I N={}", p.thresholds.len()),
        Some(Model::Duhem(_)) => "Duhem".into(),
        Some(Model::GeneralisedPi(g)) => format!(
            "GPI N={} D={}",
            g.pi.thresholds.len(),
            g.dead_zones.thresholds.len()
        ),
        Some(Model::BoucWen(_)) => "Bouc-Wen".into(),
    }
}

#[test]
fn the_vector_sets_cover_every_compensator_observer_and_mode() {
    let file = vector_file();
    let sets = sets(&file);
    let mut compensators = Vec::new();
    let mut observers = Vec::new();
    let mut modes = Vec::new();
    let mut drift_limit_closed = false;
    let mut creep_modes = 0;
    let mut mapped_with_creep = false;
    for set in &sets {
        let s = set.recipe().expect("recipe decodes").settings;
        if s.compensator.is_some() && s.observer.is_some() {
            creep_modes = creep_modes.max(s.creep.as_ref().map_or(0, |c| c.weights.len()));
            mapped_with_creep |= s.output_map.is_some() && s.creep.is_some();
        }
        compensators.push(model_name(&s.compensator));
        observers.push(model_name(&s.observer));
        modes.push(s.mode);
        drift_limit_closed |= s.mode == Mode::ClosedLoop
            && s.observer.is_some()
            && s.sensor.as_ref().is_some_and(|x| x.drift_limit.is_some());
        assert!(
            set.ticks() >= 2000,
            "set {}: {} ticks",
            set.name(),
            set.ticks()
        );
    }
    for want in [
        "none",
        "P–I N=8",
        "P–I N=16",
        "P–I N=32",
        "Duhem",
        "GPI N=16 D=6",
    ] {
        assert!(
            compensators.iter().any(|c| c == want),
            "no set with compensator {want}"
        );
    }
    for want in ["none", "P–I N=8", "P–I N=16", "Duhem", "GPI N=16 D=6"] {
        assert!(
            observers.iter().any(|c| c == want),
            "no set with observer {want}"
        );
    }
    for want in [Mode::Bypass, Mode::OpenLoop, Mode::ClosedLoop] {
        assert!(modes.contains(&want), "no set in {want:?}");
    }
    assert!(drift_limit_closed, "no closed-loop set with a drift limit");
    assert!(
        creep_modes >= 4,
        "no set with a compensator, an observer and 4 creep modes"
    );
    assert!(
        mapped_with_creep,
        "no set with a compensator, an observer, an output map and creep"
    );
    // Every flag the tick can raise is raised somewhere (the drift flag by the set with a
    // drift limit).
    use twinstack::control::TickFlags as F;
    let raised = sets
        .iter()
        .flat_map(|s| s.outputs())
        .fold(0u8, |acc, o| acc | o.flags);
    for (flag, name) in [
        (F::UNDERRUN, "underrun"),
        (F::RANGE_LIMIT, "range limit"),
        (F::SLEW_LIMIT, "slew limit"),
        (F::ADC_ERROR, "ADC error"),
        (F::DAC_ERROR, "DAC error"),
        (F::DRIFT, "drift"),
    ] {
        assert!(raised & flag != 0, "no set raises the {name} flag");
    }
}

#[test]
fn the_host_tick_reproduces_the_stored_vectors() {
    let file = vector_file();
    for set in sets(&file) {
        let r = host_replay(&set);
        let config = set.recipe().unwrap().build().unwrap();
        assert_eq!(
            config_fingerprint(&config),
            set.config_fingerprint(),
            "set {}: the configuration the library builds from the recipe changed (fixed-point \
             conversion or model layout); if intended, regenerate with `{REGENERATE}`",
            set.name()
        );
        if let Some(m) = r.first_mismatch {
            panic!(
                "set {}: tick {}: stored {:?}, the tick now gives {:?}.\nThe tick's behaviour \
                 changed; if intended, regenerate with `{REGENERATE}` (its f64-reference check \
                 shows whether the new outputs are right).",
                set.name(),
                m.tick,
                m.expected,
                m.actual
            );
        }
        assert_eq!(r.ticks, set.ticks());
        assert!(r.matches(&set), "set {}: {r:?}", set.name());
    }
}

/// One `GOLDEN` line of the replay image.
#[derive(Debug, PartialEq)]
struct BoardResult {
    set: String,
    ticks: u32,
    config: u32,
    expected_config: u32,
    outputs: u32,
    expected: u32,
    first_diff: Option<u32>,
}

fn parse_line(line: &str) -> Result<BoardResult, String> {
    let rest = line
        .strip_prefix("GOLDEN ")
        .ok_or_else(|| format!("not a GOLDEN line: {line:?}"))?;
    let field = |key: &str| -> Result<&str, String> {
        rest.split(' ')
            .find_map(|kv| kv.strip_prefix(key).and_then(|v| v.strip_prefix('=')))
            .ok_or_else(|| format!("field {key} missing in {line:?}"))
    };
    let hex = |key: &str| -> Result<u32, String> {
        u32::from_str_radix(field(key)?, 16).map_err(|e| format!("{key} in {line:?}: {e}"))
    };
    let first_diff = match field("first_diff")? {
        "none" => None,
        k => Some(
            k.parse()
                .map_err(|e| format!("first_diff in {line:?}: {e}"))?,
        ),
    };
    Ok(BoardResult {
        set: field("set")?.to_string(),
        ticks: field("ticks")?
            .parse()
            .map_err(|e| format!("ticks in {line:?}: {e}"))?,
        config: hex("config")?,
        expected_config: hex("expected_config")?,
        outputs: hex("outputs")?,
        expected: hex("expected")?,
        first_diff,
    })
}

fn run_board() -> String {
    let elf = support::build_image(support::QEMU_IMAGES, "golden-replay", &[]);
    support::run_to_exit(
        &elf,
        &["-serial", "null"],
        "the golden-replay image",
        Duration::from_secs(300),
    )
}

#[test]
fn the_board_computes_exactly_what_the_host_computes() {
    let file = vector_file();
    let sets = sets(&file);
    let out = run_board();
    assert!(
        out.lines()
            .any(|l| l == format!("GOLDEN-END sets={}", sets.len())),
        "the replay image did not finish every set:\n{out}"
    );
    let board: Vec<BoardResult> = out
        .lines()
        .filter(|l| l.starts_with("GOLDEN "))
        .map(|l| parse_line(l).unwrap_or_else(|e| panic!("{e}")))
        .collect();
    assert_eq!(board.len(), sets.len(), "one line per set:\n{out}");
    for (set, b) in sets.iter().zip(&board) {
        assert_eq!(b.set, set.name(), "sets out of order:\n{out}");
        let host = host_replay(set);
        let diff_line = out
            .lines()
            .find(|l| l.starts_with(&format!("GOLDEN-DIFF set={} ", set.name())))
            .unwrap_or("");
        // The core guarantee: the board's run equals the host's run.
        assert_eq!(
            b.config,
            host.config_fingerprint,
            "set {}: the board built a different configuration from the same recipe than the host",
            set.name()
        );
        assert_eq!(
            (b.ticks, b.outputs, b.first_diff),
            (
                host.ticks,
                host.outputs_crc,
                host.first_mismatch.map(|m| m.tick)
            ),
            "set {}: the board's outputs differ from the host's (board first differs from the \
             stored vectors at {:?}, host at {:?}):\n{diff_line}",
            set.name(),
            b.first_diff,
            host.first_mismatch
        );
        // And both equal the stored vectors.
        assert_eq!(
            (b.expected_config, b.expected),
            (set.config_fingerprint(), set.outputs_crc()),
            "set {}: the image embeds other vectors than tests/golden/vectors.bin",
            set.name()
        );
        assert!(
            b.first_diff.is_none() && b.outputs == b.expected && b.config == b.expected_config,
            "set {}: the board's outputs differ from the stored vectors:\n{diff_line}\nIf the \
             tick changed on purpose, regenerate with `{REGENERATE}`",
            set.name()
        );
    }
    println!("{out}");
}

#[test]
fn board_lines_parse_and_malformed_ones_are_refused() {
    let r = parse_line(
        "GOLDEN set=a-1 ticks=5 config=0000000a expected_config=0000000a outputs=ff expected=fe first_diff=3",
    )
    .unwrap();
    assert_eq!(
        (r.set.as_str(), r.ticks, r.outputs, r.expected),
        ("a-1", 5, 255, 254)
    );
    assert_eq!(r.first_diff, Some(3));
    assert!(parse_line("GOLDEN set=a ticks=x").is_err());
    assert!(parse_line("GOLDEN-END sets=1").is_err());
}
