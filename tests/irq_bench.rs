//! The whole control interrupt, every invocation, from QEMU's instruction trace.
//!
//! `cargo test --test irq_bench -- --nocapture` builds the `irq-bench` image (`qemu-images/`:
//! the firmware's SysTick binding and `ControlTick::run`, with an idle task that plays the
//! host through the command handler), runs it under
//! `qemu-system-arm -icount shift=0 -singlestep -d exec,nochain,int` with the trace streamed
//! through a FIFO (written 16 KiB at a time: [`support::trace_buffer`]), and counts, for
//! every SysTick invocation, the instructions from its first to its exception return —
//! RTIC's prologue and epilogue, the stream, the controller, the recorder, telemetry's tap
//! (six signals every tick), the watchdog. Each instruction is then
//! costed from the Cortex-M4 TRM's timing table (assumptions in [`cycles`]) for a cycle
//! estimate at 0 and at 5 flash wait states.
//!
//! It prints one row per configuration and scenario (instructions mean / max, cycles max,
//! CPU at 50 / 100 / 200 kHz) and asserts what is deterministic: every scenario ran; the worst
//! instruction count stays within [`WORST_INSTRUCTIONS`]; the first tick after a reload or a
//! mode switch costs at most [`SWAP_OVERHEAD`] instructions more than the tick after it.
//!
//! When every assertion holds it writes what it measured to `target/figures/tick-cost.json`
//! ([`FIGURES_JSON`]), from which `cargo xtask figures tick-cost` writes the tick-cost page's
//! tables (and `cargo xtask figures --check` compares the page with it).

mod support;

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use twinstack::config::tick_budget::{ServicesLoad, FP_CONTEXT_CYCLES};
use twinstack::sources::SetpointSource;

/// The worst instruction count of any tick, asserted (deterministic under `-icount`): the
/// figure the bench measures, rounded up by a margin of 1–2 %. Lower it when the tick
/// gets cheaper; raising it needs a reason in the commit. It bounds the shipped
/// configurations ([`SHIPPED_CONFIGS`]) in every scenario: the image captures all seven
/// recorder signals and runs continuous telemetry's tap at its worst on every tick, samples
/// the trigger input and drives the pulse outputs (one BSRR store), tests input shaping, and
/// streams, scans (raster, Lissajous figure, spiral), learns and takes the trigger input's
/// edges; the dearest scenario is the spiral started by the input's edges with the learning
/// feedforward on (P–I 17: 947 measured, the firmware's binding of the tick included).
const WORST_INSTRUCTIONS: u64 = 960;
// The longest critical section outside the tick (`support::HELD_OFF_INSTRUCTIONS`): here the
// dearest is the board's waveform generator started under the tick's lock, 140 measured. A
// capture's or a record's read-back copies its pieces under the services' lock
// (`recorder::PIECE_SLOTS`), which masks the services' priority and below, never the tick.
use support::HELD_OFF_INSTRUCTIONS;
/// Most instructions the learning feedforward, on, adds to a configuration's worst tick (its
/// table read, its error store and, at a period's end, the flips).
const LEARNING_EXTRA: u64 = 120;
/// The configuration of the model family measured on its own: what `twinstack calibrate`
/// loads by default where the generalised P–I wins, as on the simulated lab stage (N = 17,
/// 8 dead zones, as compensator and observer, with four creep modes in series): the shape
/// identification fits.
const FAMILY_CONFIG: &str = "inverse-gpi17x8+creep4+gpi17x8-observer+pi+drift";
/// Its bound, instructions (the worst measured, rounded up by about 1 %), over the same
/// scenarios as [`WORST_INSTRUCTIONS`]: the dearest is the spiral scan with the learning
/// feedforward on (883 measured: its creep's modes take turns, one a tick).
const FAMILY_WORST_INSTRUCTIONS: u64 = 890;
/// The configurations [`WORST_INSTRUCTIONS`] bounds: the P–I and Duhem ones (P–I 16, the
/// reference configuration of the tick's cost, and P–I 17 without an observer, what `twinstack
/// calibrate --model pi` loads by default at 100 kHz).
const SHIPPED_CONFIGS: [&str; 3] = [
    "inverse-pi16+pi16-observer+pi+drift",
    "inverse-duhem+duhem-observer+pi+drift",
    "inverse-pi17+pi",
];
/// What `twinstack calibrate` (and `identify --tick-rate 100000`) loads at 100 kHz where the
/// P–I, the model family's generalised P–I + creep or Duhem + creep wins: the model as the
/// compensator only, a sensor and PI feedback (no observer, so no drift check). Each must be
/// admitted at 100 kHz by the tick budget, and its measured worst interrupt (streamed, or on
/// the board's waveform generator) fit the period's share
/// ([`twinstack::config::tick_budget::TICK_SHARE_PERCENT`]). Bouc–Wen with its output map and
/// creep (`inverse-bouc-wen+map6+creep4+pi`, also measured) does not fit.
const HUNDRED_KHZ_CONFIGS: [&str; 3] = [
    "inverse-pi17+pi",
    "inverse-gpi17x8+creep4+pi",
    "inverse-duhem+creep4+pi",
];
/// How many configurations the image runs (its `configs::COUNT`), each through every
/// scenario.
const CONFIGURATIONS: usize = 11;
/// The most the tick budget's prediction may exceed a configuration's measured worst tick,
/// as a factor: a prediction looser than this refuses configurations that would fit.
const LOOSEST_PREDICTION: f64 = 1.25;
/// Most instructions a reload's swap tick may cost beyond the tick after it.
const SWAP_OVERHEAD: i64 = 50;
/// The goal: the whole handler's worst case in cycles (0 wait states).
const GOAL_CYCLES: u64 = 600;
/// Core clock, Hz.
const SYSCLK_HZ: f64 = 168e6;
/// Exception entry and return, cycles (TRM: 12 in, 10 out; no floating-point context).
const ENTRY_EXIT_CYCLES: u64 = 22;
/// Where the bench writes its figures, relative to the workspace root (read by `cargo xtask
/// figures tick-cost`).
const FIGURES_JSON: &str = "target/figures/tick-cost.json";

/// What one instruction is, from the image's disassembly.
#[derive(Clone, Debug)]
struct Insn {
    size: u32,
    /// Inlined from the tick's rebase (the first tick after a swap or a mode switch).
    swap: bool,
    /// Which part of the tick its source line belongs to.
    part: Part,
    /// Its source line (an index into the disassembly's [`Code::lines`]).
    line: u32,
    /// The function it is in (an index into the disassembly's [`Code::functions`]).
    function: u32,
    /// It masks the tick: `cpsid`, or a `msr basepri_max` whose level (the immediate last
    /// moved into its register) is the tick's priority or above. RTIC's lock on the services'
    /// resource raises `BASEPRI` to priority 2 only, which the tick still preempts.
    masks_tick: bool,
    /// It lifts that mask: the lock's restore, or interrupts on ([`lifts_mask`]).
    unmasks_tick: bool,
    /// It can change the flow ([`support::can_branch`]).
    branch: bool,
    /// Its cycles when it does not branch ([`support::base_cycles`]).
    base_cycles: u64,
    /// A floating-point instruction (`v…`: the FPU's loads, stores, moves and arithmetic).
    fp: bool,
}

/// `BASEPRI` at the tick's priority (3): RTIC's `(16 − 3) << 4` on the STM32F4's four
/// priority bits. A level at or below it (numerically) masks the tick.
const TICK_BASEPRI: u32 = 0xD0;

/// A map keyed by an instruction's address or a source line's index, looked up once or twice
/// per traced instruction (hundreds of millions): hashed by one multiplication ([`KeyHasher`])
/// rather than the standard library's SipHash, which guards against keys an adversary picks.
type KeyMap<V> = HashMap<u32, V, BuildHasherDefault<KeyHasher>>;

/// [`KeyMap`]'s hash of a `u32`: the key times an odd constant (the golden ratio's 64-bit
/// fraction), its high half folded onto the low one so that every bit of the key reaches the
/// bucket index (addresses are even: their lowest bit alone would leave half the buckets
/// empty).
#[derive(Default)]
struct KeyHasher(u64);

impl Hasher for KeyHasher {
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0.rotate_left(8) ^ u64::from(b)).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        }
    }

    fn write_u32(&mut self, key: u32) {
        self.0 = u64::from(key).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    }

    fn finish(&self) -> u64 {
        self.0 ^ (self.0 >> 32)
    }
}

/// The image's instructions by address, and the source lines they come from.
struct Code {
    insns: KeyMap<Insn>,
    /// `file:line`, by index; the file's path shortened to what follows `src/`.
    lines: Vec<String>,
    /// The functions' symbols (mangled), by index.
    functions: Vec<String>,
}

/// The parts of the tick the bench attributes cycles to, by the source file an instruction's
/// line (inlined or not) comes from: the parts [`twinstack::config::tick_budget`] costs apart.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Part {
    /// Everything else: RTIC, stream, sensor, drive, recorder, telemetry, DAC, watchdog.
    Fixed = 0,
    /// P–I banks (`prandtl_ishlinskii.rs`, `play_operator.rs`).
    PlayOperators,
    /// The generalised P–I's dead-zone maps.
    DeadZones,
    /// Creep, both sides.
    Creep,
    /// Duhem, both directions.
    Duhem,
    /// Bouc–Wen, both directions.
    BoucWen,
    /// The exponential relaxation in the input that Duhem and Bouc–Wen share
    /// (`relaxation.rs`: their `q`, `φ` and their compensators' step).
    Relaxation,
    /// Feedback (PI(D)), the notches and the preview.
    Feedback,
    /// The services below the tick (recorder, telemetry's tap): their task's share per tick.
    Services,
}

const PARTS: usize = 9;
const PART_NAMES: [&str; PARTS] = [
    "fixed",
    "P–I banks",
    "dead zones",
    "creep",
    "Duhem",
    "Bouc–Wen",
    "relaxation (Duhem, Bouc–Wen)",
    "feedback, notches, preview",
    "services (share)",
];

fn part_of(file: &str) -> Part {
    let name = file.rsplit('/').next().unwrap_or(file);
    match name {
        "prandtl_ishlinskii.rs" | "play_operator.rs" => Part::PlayOperators,
        "generalised_pi.rs" | "output_map.rs" => Part::DeadZones,
        "creep.rs" => Part::Creep,
        "duhem.rs" => Part::Duhem,
        "bouc_wen.rs" => Part::BoucWen,
        "relaxation.rs" => Part::Relaxation,
        "feedback.rs" | "notch.rs" | "preview.rs" => Part::Feedback,
        _ => Part::Fixed,
    }
}

/// The lines of the tick's rebase blocks in `src/control/mod.rs` (each `if self.rebase { … }`:
/// the transfer's start and input shaping's settling, inlined into the interrupt: their
/// instructions mark the first tick after a swap or a mode switch).
fn rebase_lines() -> Vec<std::ops::RangeInclusive<u32>> {
    let src = std::fs::read_to_string(support::workspace_root().join("src/control/mod.rs"))
        .expect("read src/control/mod.rs");
    let lines: Vec<&str> = src.lines().collect();
    let mut blocks = Vec::new();
    for (start, line) in lines.iter().enumerate() {
        if line.trim() != "if self.rebase {" {
            continue;
        }
        let indent = line.len() - line.trim_start().len();
        let end = lines[start..]
            .iter()
            .position(|l| l.len() > indent && l.trim() == "}" && l.len() - 1 == indent)
            .map(|n| start + n)
            .expect("the rebase block ends");
        blocks.push((start as u32 + 2)..=(end as u32));
    }
    assert!(
        !blocks.is_empty(),
        "the tick's rebase block is in src/control/mod.rs"
    );
    blocks
}

fn objdump() -> PathBuf {
    support::objdump()
}

/// Every instruction of the image by address.
fn disassemble(elf: &Path) -> Code {
    let out = Command::new(objdump())
        .args(["-d", "-l", "--triple=thumbv7em-none-eabihf"])
        .arg(elf)
        .output()
        .expect("llvm-objdump runs");
    assert!(out.status.success(), "llvm-objdump failed");
    let swap_lines = rebase_lines();
    let mut in_swap = false;
    let mut part = Part::Fixed;
    let mut map = KeyMap::default();
    let mut lines: Vec<String> = vec!["(no line)".to_string()];
    let mut index: HashMap<String, u32> = HashMap::new();
    let mut at = 0u32;
    let mut project = String::from("(no line)");
    let mut functions: Vec<String> = vec![String::new()];
    // The last instructions in address order, within the function: RTIC's lock moves its
    // level into a register (`movs r1, #208`) some instructions before the
    // `msr basepri_max, r1`.
    let mut recent: std::collections::VecDeque<(String, String)> = Default::default();
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        if let Some(source) = line.strip_prefix("; ") {
            // `; /path/src/control/mod.rs:123`: the source line of the instructions that follow.
            if let Some((file, n)) = source.rsplit_once(':') {
                in_swap = file.ends_with("/src/control/mod.rs")
                    && n.parse::<u32>()
                        .is_ok_and(|n| swap_lines.iter().any(|r| r.contains(&n)));
                let short = match file.rfind("/src/") {
                    Some(i) => &file[i + 5..],
                    None => file.rsplit('/').next().unwrap_or(file),
                };
                // A line of Rust's library or of a dependency (an iterator's `next`, `min`, a
                // volatile store) belongs to the project line whose code it was inlined into:
                // the nearest one before it in the disassembly.
                let key = if file.starts_with("/rustc/") || file.contains("/.cargo/registry/") {
                    format!("{short}:{n} in {project}")
                } else {
                    part = part_of(file);
                    project = format!("{short}:{n}");
                    project.clone()
                };
                at = *index.entry(key.clone()).or_insert_with(|| {
                    lines.push(key);
                    (lines.len() - 1) as u32
                });
            }
            continue;
        }
        if let Some(label) = line.strip_suffix(">:") {
            // A label (`08001234 <symbol>:`): a function's, or an ARM mapping symbol (`$t`,
            // `$d`: Thumb code or data follows) inside one. What a register held before it
            // says nothing after it.
            recent.clear();
            if let Some((_, symbol)) = label.split_once(" <") {
                if !symbol.starts_with('$') {
                    functions.push(symbol.to_string());
                }
            }
            continue;
        }
        let Some((addr, rest)) = line.trim_start().split_once(": ") else {
            continue;
        };
        let Ok(addr) = u32::from_str_radix(addr, 16) else {
            continue;
        };
        let mut parts = rest.split('\t').filter(|p| !p.trim().is_empty());
        let (Some(bytes), Some(mnemonic)) = (parts.next(), parts.next()) else {
            continue;
        };
        let size = bytes.split_whitespace().count() as u32;
        if size != 2 && size != 4 {
            continue;
        }
        let mnemonic = mnemonic.trim().to_string();
        let operands = parts.next().unwrap_or("").trim().to_string();
        let masks_tick = if mnemonic == "msr" && operands.starts_with("basepri_max") {
            // The level is the immediate last moved into its register: the nearest earlier
            // instruction (in address order, within the function) that writes the register
            // must be a `mov` of an immediate; anything else leaves it unknown, assumed to
            // mask.
            let register = operands.rsplit(',').next().unwrap_or("").trim();
            let level = recent
                .iter()
                .rev()
                .find(|(m, o)| writes_register(m, o, register))
                .and_then(|(m, o)| {
                    let (_, v) = o.split_once(", #")?;
                    m.starts_with("mov").then(|| v.trim().parse::<u32>().ok())?
                });
            level.is_none_or(|level| level != 0 && level <= TICK_BASEPRI)
        } else {
            mnemonic == "cpsid"
        };
        let (unmasks_tick, branch, base) = (
            lifts_mask(&mnemonic, &operands),
            support::can_branch(&mnemonic, &operands),
            support::base_cycles(&mnemonic, &operands),
        );
        let fp = mnemonic.starts_with('v');
        recent.push_back((mnemonic, operands));
        // A level hoisted out of a read-back loop sits up to about 20 instructions before its
        // `msr` (a `mov.w r6, #224` ahead of the loop's bounds checks).
        if recent.len() > 32 {
            recent.pop_front();
        }
        map.insert(
            addr,
            Insn {
                size,
                swap: in_swap,
                part,
                line: at,
                function: (functions.len() - 1) as u32,
                masks_tick,
                unmasks_tick,
                branch,
                base_cycles: base,
                fp,
            },
        );
    }
    Code {
        insns: map,
        lines,
        functions,
    }
}

/// Whether the instruction `mnemonic operands` (may) write `register`: its first operand for
/// an instruction that writes one, any register of a load-multiple's or a pop's list.
/// Over-approximated (an unknown level is assumed to mask the tick).
fn writes_register(mnemonic: &str, operands: &str, register: &str) -> bool {
    let m = mnemonic.trim_end_matches(".w").trim_end_matches(".n");
    if m.starts_with("pop") || m.starts_with("ldm") {
        return operands
            .split([',', '{', '}', '!'])
            .any(|r| r.trim() == register);
    }
    if m.starts_with("bl") {
        // A call: the caller-saved registers hold whatever the callee left.
        return ["r0", "r1", "r2", "r3", "r12"].contains(&register);
    }
    let branch = m.starts_with('b') && !m.starts_with("bic") && !m.starts_with("bf");
    let reads_only = [
        "str", "cmp", "cmn", "tst", "teq", "cb", "push", "msr", "it", "vstr", "vstm", "stm",
        "vcmp", "dmb", "dsb", "isb", "nop", "cps",
    ];
    if branch || reads_only.iter().any(|p| m.starts_with(p)) {
        return false;
    }
    operands
        .split(',')
        .next()
        .is_some_and(|r| r.trim() == register)
}

/// Cycles of one executed instruction (Cortex-M4 TRM, table "Cortex-M4 instruction set
/// summary", 0 wait states), given whether it branched (`taken`: the next instruction is not
/// the one after it). Assumptions: loads 2 cycles (no pipelining of neighbouring loads
/// assumed), stores 2; LDM/STM/PUSH/POP 1 + registers; a taken branch, call, return or a
/// load/pop into `pc` adds a pipeline refill of 3 (the TRM's P ranges 1–3; we take the worst);
/// SDIV/UDIV 12 (worst); multiply and multiply-accumulate (including 64-bit) 1; `IT` 1 (the
/// TRM lets it fold; we count it); VFP: VDIV/VSQRT 14, VLDR/VSTR 2, VMLA/VMLS 3, others 1.
///
/// Computed once per instruction of the image ([`support::base_cycles`]), not per traced one.
fn cycles(i: &Insn, taken: bool) -> u64 {
    i.base_cycles + if taken { 3 } else { 0 }
}

/// One SysTick invocation.
#[derive(Clone, Copy, Debug, Default)]
struct Tick {
    instructions: u64,
    cycles: u64,
    cycles_ws5: u64,
    swap: bool,
    /// It executed a floating-point instruction, and was charged the interrupted code's
    /// floating-point context ([`twinstack::config::tick_budget::FP_CONTEXT_CYCLES`]) there.
    fpu: bool,
    /// `cycles_ws5` by [`Part`].
    parts: [u64; PARTS],
}

/// One segment's worst tick (5 WS) by source line: `(line index, cycles)`.
type Breakdown = Vec<(u32, u64)>;

/// The longest critical section seen at one place outside the tick: from the instruction
/// that masks the tick (`msr basepri_max`, RTIC's lock; or `cpsid i`) to the one that
/// unmasks it. A tick due meanwhile waits for it, so the longest section is the tick's
/// worst start latency.
#[derive(Clone, Copy, Debug, Default)]
struct Section {
    instructions: u64,
    cycles: u64,
    cycles_ws5: u64,
    /// Times a section started at this place.
    count: u64,
}

/// Whether `mnemonic operands` lifts the mask (the lock's restore, or interrupts on).
fn lifts_mask(mnemonic: &str, operands: &str) -> bool {
    mnemonic == "msr" && (operands.starts_with("basepri,") || operands.starts_with("primask"))
        || mnemonic == "cpsie"
}

/// Reads the trace: the ticks, grouped by the segments between `irq_bench_marker` calls, and
/// each segment's worst tick (5 WS) by source line.
fn parse_trace(mut reader: impl BufRead, code: &KeyMap<Insn>, functions: &[String]) -> Trace {
    // The bench image's marker between segments, by its function's index.
    let marker_function = functions
        .iter()
        .position(|f| f == "irq_bench_marker")
        .map(|i| i as u32);
    let mut segments: Vec<Vec<Tick>> = vec![Vec::new()];
    // The services' task's invocations, by segment (a tick preempting one is the tick's).
    let mut services: Vec<Vec<Tick>> = vec![Vec::new()];
    let mut serving: Option<Tick> = None;
    let mut serve_previous: Option<(u32, &Insn)> = None;
    // The services' invocation in progress by source line, and the dearest one's (5 WS).
    let mut serve_by_line: KeyMap<u64> = KeyMap::default();
    let mut serve_worst: (u64, Breakdown) = (0, Vec::new());
    let mut worst: Vec<(u64, Breakdown)> = vec![(0, Vec::new())];
    let mut by_line: KeyMap<u64> = KeyMap::default();
    let mut current: Option<Tick> = None;
    let mut previous: Option<(u32, &Insn)> = None;
    let mut in_marker = false;
    // Critical sections outside the tick, by the symbol and source line where each started.
    let mut sections: HashMap<String, Section> = HashMap::new();
    let mut open: Option<(String, Section)> = None;
    let mut idle_previous: Option<(u32, &Insn)> = None;
    // Sections count from the first tick on (RTIC's `init` runs with interrupts off before).
    let mut ticked = false;
    let settle = |t: &mut Tick,
                  by_line: &mut KeyMap<u64>,
                  prev: &Option<(u32, &Insn)>,
                  next_pc: Option<u32>| {
        if let Some((pc, insn)) = prev {
            let taken = insn.branch && next_pc.is_some_and(|n| n != pc + insn.size);
            let c = cycles(insn, taken);
            t.cycles += c;
            // 5 wait states, prefetch on, ART cache off: a taken branch's target misses the
            // prefetch buffer and waits the full 5.
            let c5 = c + if taken { 5 } else { 0 };
            t.cycles_ws5 += c5;
            t.parts[insn.part as usize] += c5;
            *by_line.entry(insn.line).or_insert(0) += c5;
            // The invocation's first floating-point instruction: the hardware saves the
            // interrupted code's floating-point registers there (lazy stacking), and the
            // return restores them. QEMU's trace shows neither; charged here, to the part and
            // the line that caused it.
            if insn.fp && !t.fpu {
                t.fpu = true;
                let context = u64::from(FP_CONTEXT_CYCLES);
                t.cycles += context;
                t.cycles_ws5 += context;
                t.parts[insn.part as usize] += context;
                *by_line.entry(insn.line).or_insert(0) += context;
            }
        }
    };
    // Hundreds of millions of lines: read into one buffer, and the instruction lines (nearly
    // all of them) are told apart by their prefix before any other line is searched.
    let mut buffer: Vec<u8> = Vec::with_capacity(256);
    loop {
        buffer.clear();
        match reader.read_until(b'\n', &mut buffer) {
            Ok(0) | Err(_) => break,
            Ok(_) => {}
        }
        let bytes = buffer.strip_suffix(b"\n").unwrap_or(&buffer);
        if let Some(rest) = bytes.strip_prefix(b"Trace 0: ") {
            let Some(pc) = instruction(rest) else {
                continue;
            };
            match current.as_mut() {
                Some(t) => {
                    t.instructions += 1;
                    settle(t, &mut by_line, &previous, Some(pc));
                    previous = code.get(&pc).map(|i| (pc, i));
                    if previous.is_some_and(|(_, i)| i.swap) {
                        t.swap = true;
                    }
                }
                None if serving.is_some() => {
                    if let Some(t) = serving.as_mut() {
                        t.instructions += 1;
                        settle(t, &mut serve_by_line, &serve_previous, Some(pc));
                        serve_previous = code.get(&pc).map(|i| (pc, i));
                    }
                }
                None => {
                    let insn = code.get(&pc);
                    if let Some((_, s)) = open.as_mut() {
                        if let Some((ppc, p)) = idle_previous {
                            let taken = p.branch && pc != ppc + p.size;
                            let c = cycles(p, taken);
                            s.instructions += 1;
                            s.cycles += c;
                            s.cycles_ws5 += c + if taken { 5 } else { 0 };
                        }
                    }
                    match insn {
                        Some(i) if ticked && open.is_none() && i.masks_tick => {
                            let site = format!("{} @ {}", functions[i.function as usize], i.line);
                            open = Some((site, Section::default()));
                        }
                        Some(i) if i.unmasks_tick => {
                            if let Some((site, mut s)) = open.take() {
                                // The unmasking instruction itself.
                                s.instructions += 1;
                                s.cycles += cycles(i, false);
                                s.cycles_ws5 += cycles(i, false);
                                let e = sections.entry(site).or_default();
                                e.count += 1;
                                if s.instructions > e.instructions {
                                    (e.instructions, e.cycles, e.cycles_ws5) =
                                        (s.instructions, s.cycles, s.cycles_ws5);
                                }
                            }
                        }
                        _ => {}
                    }
                    idle_previous = insn.map(|i| (pc, i));
                    let marker = insn.is_some_and(|i| Some(i.function) == marker_function);
                    if marker && !in_marker {
                        segments.push(Vec::new());
                        services.push(Vec::new());
                        worst.push((0, Vec::new()));
                    }
                    in_marker = marker;
                }
            }
            continue;
        }
        let line = String::from_utf8_lossy(bytes);
        if line.contains("taking pending nonsecure exception 15") {
            // A tick that preempts a section was not held back by it (a lock of a resource
            // the tick does not share).
            open = None;
            idle_previous = None;
            ticked = true;
            current = Some(Tick::default());
            by_line.clear();
            previous = None;
            continue;
        }
        if line.contains(SERVICES_EXCEPTION) {
            serving = Some(Tick::default());
            serve_previous = None;
            serve_by_line.clear();
            continue;
        }
        // The end of an exception: QEMU logs "Exception return: magic PC … previous exception
        // N" for every return, tail-chained or not ("successful exception return" follows
        // only when the core goes back to thread mode, not when it tail-chains into the
        // services' task the tick pended).
        let returned = line
            .strip_prefix("Exception return: ")
            .and_then(|l| l.rsplit_once("previous exception "))
            .and_then(|(_, n)| n.trim().parse::<u32>().ok());
        if returned == Some(SERVICES_EXCEPTION_NUMBER) && current.is_none() {
            if let Some(mut t) = serving.take() {
                settle(&mut t, &mut serve_by_line, &serve_previous, None);
                if t.cycles_ws5 > serve_worst.0 {
                    serve_worst = (
                        t.cycles_ws5,
                        serve_by_line.iter().map(|(&l, &c)| (l, c)).collect(),
                    );
                }
                serve_by_line.clear();
                t.cycles += 3 + ENTRY_EXIT_CYCLES;
                t.cycles_ws5 += 3 + 5 + ENTRY_EXIT_CYCLES;
                if let Some(seg) = services.last_mut() {
                    seg.push(t);
                }
                serve_previous = None;
                continue;
            }
        }
        if returned == Some(TICK_EXCEPTION_NUMBER) {
            if let Some(mut t) = current.take() {
                settle(&mut t, &mut by_line, &previous, None);
                // The last instruction (the return) refills the pipeline.
                t.cycles += 3;
                t.cycles_ws5 += 3 + 5;
                t.cycles += ENTRY_EXIT_CYCLES;
                t.cycles_ws5 += ENTRY_EXIT_CYCLES;
                t.parts[Part::Fixed as usize] += 3 + 5 + ENTRY_EXIT_CYCLES;
                *by_line.entry(0).or_insert(0) += 3 + 5 + ENTRY_EXIT_CYCLES;
                if let Some(seg) = segments.last_mut() {
                    seg.push(t);
                }
                if let Some(w) = worst.last_mut() {
                    if t.cycles_ws5 > w.0 {
                        *w = (
                            t.cycles_ws5,
                            by_line.iter().map(|(&l, &c)| (l, c)).collect(),
                        );
                    }
                }
            }
            previous = None;
            continue;
        }
    }
    Trace {
        segments,
        services,
        services_worst: serve_worst.1,
        breakdowns: worst.into_iter().map(|(_, b)| b).collect(),
        sections,
    }
}

/// An instruction line's address: QEMU's `-d exec` line after its `Trace 0: `, `<host
/// address> [<cs base>/<pc>/<flags>/<cflags>] <symbol>` (the symbol empty: QEMU runs the image
/// without its symbol table, and the functions are the disassembly's).
fn instruction(rest: &[u8]) -> Option<u32> {
    let open = rest.iter().position(|&b| b == b'[')?;
    let fields = &rest[open + 1..];
    let close = fields.iter().position(|&b| b == b']')?;
    let pc = fields[..close].split(|&b| b == b'/').nth(1)?;
    u32::from_str_radix(std::str::from_utf8(pc).ok()?, 16).ok()
}

/// What [`parse_trace`] reads.
struct Trace {
    /// The ticks, by segment (the segments between `irq_bench_marker` calls).
    segments: Vec<Vec<Tick>>,
    /// The services' task's invocations, by segment.
    services: Vec<Vec<Tick>>,
    /// The dearest invocation of the services' task by source line (5 WS).
    services_worst: Breakdown,
    /// Each segment's worst tick (5 WS) by source line.
    breakdowns: Vec<Breakdown>,
    /// Critical sections outside the tick, by where each started.
    sections: HashMap<String, Section>,
}

/// QEMU's log line for the services' task's interrupt: EXTI2 (IRQ 8, exception 24), the
/// firmware's `setup::SERVICES_IRQ`.
const SERVICES_EXCEPTION: &str = "taking pending nonsecure exception 24";
/// The services' task's exception number (EXTI2).
const SERVICES_EXCEPTION_NUMBER: u32 = 24;
/// The tick's exception number (SysTick).
const TICK_EXCEPTION_NUMBER: u32 = 15;

/// The services' cost a tick carries, cycles at 5 WS: the dearest invocation of the
/// services' task in `invocations`, shared by the [`BATCH`] ticks that wake it once (an
/// invocation that served more snapshots than a batch is charged to one batch: an
/// overestimate).
fn services_share(invocations: &[Tick]) -> u64 {
    let worst = invocations.iter().map(|t| t.cycles_ws5).max().unwrap_or(0);
    worst.div_ceil(BATCH)
}

/// Ticks per wake of the services' task.
const BATCH: u64 = twinstack::services::snapshot::BATCH as u64;

/// A legacy-mangled Rust symbol (`_ZN9twinstack8learning10post_table17h…E`) as its path
/// without the hash (`twinstack::services::learning::post_table`); anything else as it is.
fn demangled(symbol: &str) -> String {
    let Some(mut rest) = symbol.strip_prefix("_ZN") else {
        return symbol.to_string();
    };
    let mut parts = Vec::new();
    while let Some(digits) = rest.find(|c: char| !c.is_ascii_digit()).filter(|&d| d > 0) {
        let Ok(n) = rest[..digits].parse::<usize>() else {
            break;
        };
        let Some(part) = rest.get(digits..digits + n) else {
            break;
        };
        if !(part.starts_with('h') && part.len() == 17) {
            parts.push(
                part.replace("$LT$", "<")
                    .replace("$GT$", ">")
                    .replace("$u20$", " ")
                    .replace("..", "::"),
            );
        }
        rest = &rest[digits + n..];
    }
    if parts.is_empty() {
        symbol.to_string()
    } else {
        parts.join("::")
    }
}

/// No panic path is linked into the tick: nothing the SysTick handler can branch or call to,
/// directly or through what it calls, is one of `core::panicking`'s (an `i64::clamp` in the
/// scan's approach used to link `panic_fmt`). Static, from the image's disassembly.
/// The setpoint source a scenario runs, by its name's prefix (`<config>/scan-…`,
/// `/analog-…`, `/sequence-…`, `/coarse-…`; the stream otherwise).
fn source_of(name: &str) -> Option<SetpointSource> {
    let scenario = name.split('/').nth(1)?;
    Some(
        [
            ("scan-", SetpointSource::Scan),
            ("analog-", SetpointSource::Analog),
            ("sequence-", SetpointSource::Sequence),
            ("coarse-", SetpointSource::Coarse),
        ]
        .into_iter()
        .find_map(|(prefix, s)| scenario.starts_with(prefix).then_some(s))
        .unwrap_or(SetpointSource::Stream),
    )
}

#[test]
fn the_tick_links_no_panic_path() {
    let elf = support::build_image(support::QEMU_IMAGES, "irq-bench", &[]);
    let panics = support::panic_paths(&elf, "SysTick");
    assert!(panics.is_empty(), "the tick reaches {panics:?}");
}

/// The trace buffer the bench loads into QEMU holds the trace's file until its buffer is full
/// (and lets every line through at the end), and leaves every other file as it was opened: a
/// probe that writes as QEMU writes its log (line-buffered, flushed after each line) 12 400
/// bytes, more than glibc's own buffer and less than the trace buffer's, finds nothing written
/// before its close with the buffer on the file, and every line without it.
#[test]
fn the_trace_buffer_holds_qemu_s_log_until_it_is_full() {
    let Some(buffer) = support::trace_buffer() else {
        return; // off Linux: the bench runs without it
    };
    let source = support::workspace_root().join("tests/support/trace_buffer_probe.c");
    let probe = support::compile_c(&source, "trace-buffer-probe", &[]);
    let dir = support::firmware_target_dir();
    let run = |file: &str, traced: &str| {
        let path = dir.join(file);
        let out = Command::new(&probe)
            .arg(&path)
            .env("LD_PRELOAD", &buffer)
            .env("TWINSTACK_TRACE_FILE", dir.join(traced))
            .output()
            .expect("the probe runs");
        assert!(out.status.success(), "the probe failed: {out:?}");
        let before_close: u64 = String::from_utf8_lossy(&out.stdout)
            .trim()
            .parse()
            .expect("the probe prints a size");
        let after_close = std::fs::metadata(&path).expect("the probe's file").len();
        let _ = std::fs::remove_file(&path);
        (before_close, after_close)
    };
    let line = "Trace 0: 0x7f0000000000 [00000000/08000000/00000000/ff200000]\n".len() as u64;
    assert_eq!(
        run("probe-traced.log", "probe-traced.log"),
        (0, 200 * line),
        "the trace's file: held until the close, then every line"
    );
    assert_eq!(
        run("probe-other.log", "probe-traced.log"),
        (200 * line, 200 * line),
        "another file: written a line at a time, as opened"
    );
}

#[test]
fn the_whole_interrupt_in_every_scenario() {
    let elf = support::build_image(support::QEMU_IMAGES, "irq-bench", &[]);
    let Code {
        insns: code,
        lines,
        functions,
    } = disassemble(&elf);
    assert!(code.len() > 1000, "the disassembly is the image's");
    assert!(
        functions.iter().any(|f| f == "irq_bench_marker"),
        "the disassembly names the bench's marker"
    );
    // QEMU runs the image without its symbol table: it would look up and print each
    // instruction's symbol, half of the trace's bytes, which the bench takes from the
    // disassembly instead.
    let stripped = elf.with_extension("stripped");
    let made = Command::new(support::objcopy())
        .arg("--strip-all")
        .arg(&elf)
        .arg(&stripped)
        .status()
        .expect("llvm-objcopy runs");
    assert!(made.success(), "llvm-objcopy --strip-all {}", elf.display());
    let (mut qemu, fifo) = support::traced_qemu(&stripped, "irq-bench");
    let child = qemu
        .args([
            "-serial",
            "null",
            "-icount",
            "shift=0,sleep=off",
            "-singlestep",
        ])
        .args(["-d", "exec,nochain,int", "-D"])
        .arg(&fifo)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("qemu-system-arm starts");
    let trace = std::fs::File::open(&fifo).expect("open the trace FIFO");
    let Trace {
        segments,
        services,
        services_worst,
        breakdowns,
        sections,
    } = parse_trace(BufReader::with_capacity(1 << 20, trace), &code, &functions);
    // Where the services' dearest invocation goes: its 20 dearest source lines.
    let mut dearest = services_worst.clone();
    dearest.sort_by_key(|&(_, c)| std::cmp::Reverse(c));
    println!(
        "The services' dearest invocation, {} cycles (5 WS), by source line:",
        dearest.iter().map(|&(_, c)| c).sum::<u64>()
    );
    for (l, c) in dearest.iter().take(20) {
        println!("    {c:5}  {}", lines[*l as usize]);
    }
    let out = child.wait_with_output().expect("qemu exits");
    let _ = std::fs::remove_file(&fifo);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && stdout.contains("DONE"),
        "irq-bench failed ({}):\n{stdout}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    let names: Vec<&str> = stdout
        .lines()
        .filter_map(|l| l.strip_prefix("SCENARIO "))
        .collect();
    // What the services ran in each scenario (`SERVICES <capture decimation> <telemetry
    // decimation> <pre-trigger window: 1>` after its `SCENARIO` line; none after a load's: charged at their worst).
    let mut loads: Vec<ServicesLoad> = Vec::new();
    for line in stdout.lines() {
        if line.starts_with("SCENARIO ") {
            loads.push(ServicesLoad::WORST);
        } else if let Some(d) = line.strip_prefix("SERVICES ") {
            let mut d = d
                .split(' ')
                .map(|d| d.parse::<u16>().expect("SERVICES <c> <t> <pre-trigger>"));
            if let Some(last) = loads.last_mut() {
                *last = ServicesLoad {
                    capture_decimation: d.next(),
                    telemetry_decimation: d.next(),
                    capture_pre_trigger: d.next() == Some(1),
                    ..ServicesLoad::default()
                };
            }
        }
    }
    assert_eq!(loads.len(), names.len(), "a load per scenario");
    assert_eq!(
        names.len(),
        // The image's 19 scenarios and the load, per configuration.
        CONFIGURATIONS * 20,
        "every scenario and load ran: {stdout}"
    );
    // The stack's high-water mark over the whole run (painted at reset, read back by the image
    // before it exits): within three quarters of the reserve memory.x keeps for it.
    let reserve = support::elf_symbol(&elf, "_stack_reserve")
        .unwrap_or_else(|e| panic!("{e}"))
        .expect("memory.x defines _stack_reserve");
    let (used, room) = stdout
        .lines()
        .find_map(|l| {
            let mut w = l.strip_prefix("STACK used ")?.split(" room ");
            Some((
                w.next()?.parse::<u32>().ok()?,
                w.next()?.parse::<u32>().ok()?,
            ))
        })
        .unwrap_or_else(|| panic!("no STACK line: {stdout}"));
    println!("stack: {used} bytes used of the {room} the static RAM leaves (reserve {reserve})");
    let mut figures = serde_json::json!({
        "sysclk_hz": SYSCLK_HZ,
        "tick_share_percent": twinstack::config::tick_budget::TICK_SHARE_PERCENT,
        "goal_cycles": GOAL_CYCLES,
        "scan_cycles": twinstack::config::tick_budget::SCAN_CYCLES,
        "learning_cycles": twinstack::config::tick_budget::LEARNING_CYCLES,
        "analog_cycles": twinstack::config::tick_budget::ANALOG_CYCLES,
        "sequence_cycles": twinstack::config::tick_budget::SEQUENCE_CYCLES,
        "coarse_cycles": twinstack::config::tick_budget::COARSE_CYCLES,
        "trigger_cycles": twinstack::config::tick_budget::TRIGGER_CYCLES,
        "services_base_cycles": twinstack::config::tick_budget::SERVICES_BASE_CYCLES,
        "capture_frame_cycles": twinstack::config::tick_budget::CAPTURE_FRAME_CYCLES,
        "telemetry_sample_cycles": twinstack::config::tick_budget::TELEMETRY_SAMPLE_CYCLES,
        "services_worst_cycles": ServicesLoad::WORST.cycles(),
        "part_names": PART_NAMES,
        "stack": { "used": used, "room": room, "reserve": reserve },
    });
    assert!(room >= reserve, "static RAM leaves {room} < {reserve}");
    assert!(
        used <= reserve / 4 * 3,
        "the stack reached {used} bytes: more than 3/4 of its {reserve}-byte reserve"
    );
    // Segment 0 is the boot (defaults: bypass, no model); the last follows the final marker.
    assert!(segments.len() > names.len(), "{} segments", segments.len());
    // The tick budget's prediction for each configuration, computed on the target: the
    // interrupt's, what its observer below the tick costs the services a snapshot, and the
    // pipeline's with every feature beside it.
    // The fourth number: 1 where the prediction charges the interrupt a floating-point
    // context (`tick_budget::interrupt_uses_fpu`).
    let predictions: HashMap<&str, [u64; 4]> = stdout
        .lines()
        .filter_map(|l| l.strip_prefix("BUDGET "))
        .map(|l| {
            let mut w = l.split(' ');
            let name = w.next().unwrap_or_default();
            let n: Vec<u64> = w
                .map(|c| {
                    c.parse()
                        .expect("BUDGET <name> <interrupt> <observer> <every feature> <FPU>")
                })
                .collect();
            (name, [n[0], n[1], n[2], n[3]])
        })
        .collect();
    // The interrupt's prediction alone, and each configuration's services load with its
    // observer below the tick (what the scenario's capture and telemetry add is per row).
    let budgets: HashMap<&str, u64> = predictions.iter().map(|(n, p)| (*n, p[0])).collect();
    let observing = |config: &str, load: ServicesLoad| {
        load.observing(predictions.get(config).map_or(0, |p| p[1] as u32))
    };
    assert!(
        !stdout.contains("BUDGET-REFUSED"),
        "the budget refused a benched configuration at the bench's 32 kHz: {stdout}"
    );
    assert_eq!(
        budgets.len(),
        CONFIGURATIONS,
        "every configuration has a prediction"
    );
    // What `twinstack budget` prints for each configuration: the pipeline's per tick alone
    // (the interrupt and, with an observer below the tick, the services serving it), and with
    // every feature beside it.
    let alone: HashMap<&str, u64> = predictions
        .keys()
        .map(|n| {
            (
                *n,
                budgets[n] + u64::from(observing(n, ServicesLoad::default()).cycles()),
            )
        })
        .collect();
    figures["budgets"] = serde_json::json!(alone);
    figures["interrupt_budgets"] = serde_json::json!(budgets);
    figures["every_feature_budgets"] = serde_json::json!(predictions
        .iter()
        .map(|(n, p)| (*n, p[2]))
        .collect::<HashMap<_, _>>());
    let mut figure_rows = Vec::new();

    println!();
    println!("Whole control interrupt (SysTick entry to exception return), QEMU netduinoplus2, -icount shift=0");
    println!("cycles: Cortex-M4 TRM estimate incl. 22 for exception entry/exit; 5 WS: +5 per taken branch");
    println!(
        "| configuration / scenario | ticks | instr mean | instr max | cycles max (0 WS) | cycles max (5 WS) | services max (5 WS) | tick + services share (5 WS) | CPU 50 kHz | CPU 100 kHz | CPU 200 kHz |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    let mut worst = Tick::default();
    // The model family's generalised P–I + creep has its own instruction bound.
    let mut family_worst = 0u64;
    let mut worst_at = Vec::new();
    let mut rows = vec![(
        "boot (defaults: bypass, no model)".to_string(),
        &segments[0],
    )];
    for (name, seg) in names.iter().zip(&segments[1..]) {
        rows.push((name.to_string(), seg));
    }
    // No tick touches the FPU unless its configuration's prediction charges the context it
    // costs: the boot (no model) never, the integer models' configurations never (their
    // ticks and the switches between two configurations, where the other may be a
    // floating-point one, apart).
    // (The services' task runs the observer's models inline and pays the context once a
    // batch whatever the model: within their measured charges.)
    for (row, (name, ticks)) in rows.iter().enumerate() {
        let config = name.split('/').next().unwrap_or(name);
        let charged = predictions.get(config).is_some_and(|p| p[3] == 1);
        let switching = name.ends_with("/load") || name.contains("reload");
        if let Some(at) = ticks.iter().position(|t| t.fpu) {
            assert!(
                charged || (row > 0 && switching),
                "{name}: tick {at} executed a floating-point instruction, which the tick \
                 budget does not charge this configuration (FP_CONTEXT_CYCLES)"
            );
        }
    }
    // What broke the tick budget's contract, reported together after the table.
    let mut failures: Vec<String> = Vec::new();
    // Per configuration: its worst tick (5 WS) outside the lifecycle scenario, with its parts.
    let mut by_config: Vec<(String, Tick, usize)> = Vec::new();
    // Per configuration: its worst interrupt (5 WS) over its streamed and generated scenarios,
    // the services' share below it aside.
    let mut streamed_interrupt: HashMap<String, u64> = HashMap::new();
    for (row, (name, ticks)) in rows.iter().enumerate() {
        assert!(!ticks.is_empty(), "{name}: no ticks traced");
        let n = ticks.len() as f64;
        let mean = ticks.iter().map(|t| t.instructions).sum::<u64>() as f64 / n;
        let max_i = ticks.iter().map(|t| t.instructions).max().unwrap_or(0);
        let at = ticks
            .iter()
            .position(|t| t.instructions == max_i)
            .unwrap_or(0);
        let max_c = ticks.iter().map(|t| t.cycles).max().unwrap_or(0);
        let max_c5 = ticks.iter().map(|t| t.cycles_ws5).max().unwrap_or(0);
        // The services below the tick, woken once a batch: their dearest invocation, and the
        // share of it each tick carries. What the budget predicts is the pipeline's: the
        // interrupt and that share.
        let served = &services[row];
        let services_max = served.iter().map(|t| t.cycles_ws5).max().unwrap_or(0);
        let share = services_share(served);
        let pipeline = max_c5 + share;
        let cpu = |rate: f64| 100.0 * max_c as f64 / (SYSCLK_HZ / rate);
        println!(
            "| {name} | {} | {mean:.1} | {max_i} | {max_c} | {max_c5} | {services_max} | {pipeline} | {:.0} % | {:.0} % | {:.0} % |",
            ticks.len(),
            cpu(50e3),
            cpu(100e3),
            cpu(200e3)
        );
        worst_at.push(format!("{name}: worst at tick {at} of {}", ticks.len()));
        figure_rows.push(serde_json::json!({
            "name": name,
            "ticks": ticks.len(),
            "instructions_mean": mean,
            "instructions_max": max_i,
            "cycles_max": max_c,
            "cycles_max_ws5": max_c5,
            "services_load": row.checked_sub(1).map(|i| [loads[i].capture_decimation, loads[i].telemetry_decimation]),
            "services_invocations": served.len(),
            "services_max_ws5": services_max,
            "pipeline_ws5": pipeline,
        }));
        let config = name.split('/').next().unwrap_or(name);
        if let Some(&predicted) = budgets.get(config) {
            // Every tick of the configuration's own scenarios stays within its prediction; in
            // the lifecycle scenario (a reload to another configuration and two mode
            // switches) within the larger of the two predictions.
            // Every scenario captures and streams telemetry: the services listen throughout,
            // charged beside the configuration as the command handler charges them, by their
            // decimations (the boot row has no load: `row` 0).
            let load = row.checked_sub(1).map_or(ServicesLoad::WORST, |i| loads[i]);
            let services = u64::from(observing(config, load).cycles());
            let interrupt_bound = if name.ends_with("/load") {
                // The previous configuration's last ticks and this one's first: no tick above
                // the dearest prediction.
                budgets.values().copied().max().unwrap_or(0)
            } else if let Some(source) = source_of(name)
                .filter(|s| *s != SetpointSource::Stream)
                .or_else(|| {
                    (name.ends_with("-learning") || name.contains("-on-trigger"))
                        .then_some(SetpointSource::Stream)
                })
            {
                // What runs beside the configuration in the interrupt, charged as the command
                // handler charges it: the learning, a scan, the analog input, a sequence, the
                // coarse ramp, the armed trigger input (the coarse task's own share runs below
                // the interrupt, in the dual-stage images).
                let beside = twinstack::config::tick_budget::Beside {
                    learning: name.ends_with("-learning"),
                    source,
                    coarse_task: 0,
                    trigger: name.contains("-on-trigger"),
                    services: ServicesLoad::default(),
                };
                predicted + u64::from(beside.cycles())
            } else if name.contains("reload") {
                let other = if config.starts_with("inverse-pi16") {
                    "inverse-duhem+duhem-observer+pi+drift"
                } else {
                    "inverse-pi16+pi16-observer+pi+drift"
                };
                predicted.max(budgets.get(other).copied().unwrap_or(0))
            } else {
                let interrupt = ticks.iter().map(|t| t.cycles_ws5).max().unwrap_or(0);
                let worst = streamed_interrupt.entry(config.to_string()).or_insert(0);
                *worst = (*worst).max(interrupt);
                let mut heaviest = ticks
                    .iter()
                    .max_by_key(|t| t.cycles_ws5)
                    .copied()
                    .unwrap_or_default();
                // The services' share is part of what the budget predicts (a part of its own,
                // the last column of the parts table).
                heaviest.cycles_ws5 += share;
                heaviest.parts[Part::Services as usize] += share;
                match by_config.iter_mut().find(|(c, _, _)| c == config) {
                    Some((_, t, _)) if t.cycles_ws5 >= heaviest.cycles_ws5 => {}
                    Some((_, t, r)) => (*t, *r) = (heaviest, row),
                    None => by_config.push((config.to_string(), heaviest, row)),
                }
                predicted
            };
            // The interrupt alone stays within what the budget predicts without the services,
            // and with their share, within the prediction with them.
            if max_c5 > interrupt_bound {
                failures.push(format!(
                    "{name}: the worst tick takes {max_c5} cycles (5 WS), more than the tick budget's {interrupt_bound} for the interrupt: raise src/config/tick_budget.rs's coefficients"
                ));
            }
            // A load's row holds the previous configuration's ticks and this one's, a
            // reload's the two configurations': their dearer services.
            let services = if name.ends_with("/load") {
                predictions
                    .keys()
                    .map(|c| u64::from(observing(c, load).cycles()))
                    .max()
                    .unwrap_or(services)
            } else if name.contains("reload") {
                predictions
                    .keys()
                    .filter(|c| {
                        **c == config
                            || **c == "inverse-duhem+duhem-observer+pi+drift"
                            || **c == "inverse-pi16+pi16-observer+pi+drift"
                    })
                    .map(|c| u64::from(observing(c, load).cycles()))
                    .max()
                    .unwrap_or(services)
            } else {
                services
            };
            // The services' share alone stays within their charge: the interrupt's margin
            // never pays for them.
            if share > services {
                failures.push(format!(
                    "{name}: the services' share of their dearest batch is {share} cycles a tick (5 WS), more than the {services} the tick budget charges them: raise src/services/consumer.rs's coefficients"
                ));
            }
            if let Some(r) = figure_rows.last_mut() {
                r["services_share_ws5"] = serde_json::json!(share);
                r["services_charge"] = serde_json::json!(services);
            }
            let bound = interrupt_bound + services;
            if pipeline > bound {
                failures.push(format!(
                    "{name}: the worst tick and its services' share take {pipeline} cycles (5 WS: {max_c5} + {share}), more than the tick budget's {bound} with the services: raise src/config/tick_budget.rs's coefficients"
                ));
            }
        }
        if config == FAMILY_CONFIG {
            family_worst = family_worst.max(max_i);
        } else if SHIPPED_CONFIGS.contains(&config) {
            for t in ticks.iter() {
                worst.instructions = worst.instructions.max(t.instructions);
                worst.cycles = worst.cycles.max(t.cycles);
                worst.cycles_ws5 = worst.cycles_ws5.max(t.cycles_ws5);
            }
        }
    }
    for line in &worst_at {
        println!("{line}");
    }
    figures["rows"] = serde_json::json!(figure_rows);
    let mut figure_parts = Vec::new();
    println!();
    println!(
        "Worst tick of each configuration (5 WS cycles) by part, and the tick budget's prediction:"
    );
    println!(
        "| configuration | {} | total | predicted | predicted / measured |",
        PART_NAMES.join(" | ")
    );
    println!("|---|{}---:|---:|---:|", "---:|".repeat(PARTS));
    for (config, t, row) in &by_config {
        // What the budget predicts with the services listening, as that scenario ran them.
        let load = row.checked_sub(1).map_or(ServicesLoad::WORST, |i| loads[i]);
        let predicted = budgets[config.as_str()] + u64::from(observing(config, load).cycles());
        let ratio = predicted as f64 / t.cycles_ws5 as f64;
        figure_parts.push(serde_json::json!({
            "config": config,
            "parts": t.parts,
            "cycles_ws5": t.cycles_ws5,
            "cycles": t.cycles,
            "instructions": t.instructions,
            "predicted": predicted,
        }));
        println!(
            "| {config} | {} | {} | {predicted} | {ratio:.2} |",
            t.parts.map(|c| c.to_string()).join(" | "),
            t.cycles_ws5
        );
        if ratio > LOOSEST_PREDICTION {
            failures.push(format!(
                "{config}: the tick budget predicts {predicted} cycles for a worst tick of {}: looser than {LOOSEST_PREDICTION}× (lower src/config/tick_budget.rs's coefficients)",
                t.cycles_ws5
            ));
        }
    }
    // Where each configuration's worst tick goes, by source file (5 WS cycles; "(no line)" is
    // the exception entry and return and code without line information); with
    // `IRQ_BENCH_LINES=N`, also its N dearest source lines.
    figures["worst_by_config"] = serde_json::json!(figure_parts);
    let mut figure_files = serde_json::Map::new();
    let detail: usize = std::env::var("IRQ_BENCH_LINES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    for (config, t, row) in &by_config {
        let Some(b) = breakdowns.get(*row) else {
            continue;
        };
        let mut files: HashMap<&str, u64> = HashMap::new();
        for &(l, c) in b {
            // A library line counts for the project file it was inlined into.
            let at = lines[l as usize].rsplit(" in ").next().unwrap_or("");
            let file = at.rsplit_once(':').map_or("(no line)", |(f, _)| f);
            *files.entry(file).or_insert(0) += c;
        }
        let mut files: Vec<_> = files.into_iter().collect();
        files.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(b.0)));
        let listed: Vec<String> = files.iter().map(|(f, c)| format!("{f} {c}")).collect();
        figure_files.insert(
            config.clone(),
            serde_json::json!({ "row": rows[*row].0, "files": files }),
        );
        println!(
            "{config}, worst tick ({} cycles at 5 WS, row {}) by file: {}",
            t.cycles_ws5,
            rows[*row].0,
            listed.join(", ")
        );
        if detail > 0 {
            let mut dear = b.clone();
            dear.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
            for &(l, c) in dear.iter().take(detail) {
                println!("    {c:5}  {}", lines[l as usize]);
            }
        }
    }
    if detail > 0 {
        // The boot row (row 0: bypass, no model): the interrupt's fixed part, line by line.
        if let Some(b) = breakdowns.first() {
            let mut dear = b.clone();
            dear.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
            println!("{}, worst tick by line:", rows[0].0);
            for &(l, c) in dear.iter().take(detail) {
                println!("    {c:5}  {}", lines[l as usize]);
            }
        }
    }
    figures["worst_by_file"] = serde_json::Value::Object(figure_files);
    assert_eq!(
        by_config.len(),
        budgets.len(),
        "every configuration was checked against its prediction"
    );
    figures["shipped_worst"] = serde_json::json!({
        "instructions": worst.instructions,
        "cycles": worst.cycles,
        "cycles_ws5": worst.cycles_ws5,
    });
    println!(
        "worst of the shipped P–I and Duhem configurations: {} instructions, {} cycles at 0 WS ({} at 5 WS); goal {GOAL_CYCLES} cycles: {}",
        worst.instructions,
        worst.cycles,
        worst.cycles_ws5,
        if worst.cycles <= GOAL_CYCLES {
            "met"
        } else {
            "NOT met"
        }
    );

    // The learning feedforward on (each tick reads one table entry and stores one error; the
    // period's end flips two indices): the same sine with and without it, per configuration.
    // Constant time: its worst tick (a period boundary among them) costs at most
    // LEARNING_EXTRA instructions more than the sine's worst without it.
    let row = |name: &str| rows.iter().find(|(n, _)| n == name).map(|(_, t)| *t);
    for config in names
        .iter()
        .filter_map(|n| n.strip_suffix("/sine-750Hz-learning"))
    {
        let (Some(on), Some(off)) = (
            row(&format!("{config}/sine-750Hz-learning")),
            row(&format!("{config}/sine-750Hz")),
        ) else {
            panic!("{config}: the learning rows are missing");
        };
        let stat = |t: &[Tick]| {
            let n = t.len() as f64;
            (
                t.iter().map(|t| t.instructions).sum::<u64>() as f64 / n,
                t.iter().map(|t| t.instructions).max().unwrap_or(0),
            )
        };
        let ((mean_on, max_on), (mean_off, max_off)) = (stat(&on[..]), stat(&off[..]));
        println!(
            "learning on, {config}: mean {mean_on:.1} (+{:.1}), max {max_on} (+{})",
            mean_on - mean_off,
            max_on as i64 - max_off as i64
        );
        assert!(
            max_on <= max_off + LEARNING_EXTRA,
            "{config}: learning adds {} instructions to the worst tick (asserted ≤ {LEARNING_EXTRA})",
            max_on as i64 - max_off as i64
        );
    }

    // The swap itself happens under the command handler's lock, not in the tick; the first tick
    // after a swap (or a mode switch) starts the fading transfer. In the lifecycle scenarios
    // (a reload and two mode switches while the stream moves, no setpoint jump) that tick is
    // compared with the tick after it (both run the new configuration, settling). The loads at
    // a scenario's start meet the scenario's first setpoint jump, whose cost is the models',
    // not the swap's: they are not compared.
    let mut swaps = 0;
    for (name, ticks) in rows.iter().filter(|(n, _)| n.contains("reload")) {
        for w in ticks.windows(2) {
            if w[0].swap {
                swaps += 1;
                let extra = w[0].instructions as i64 - w[1].instructions as i64;
                println!(
                    "first tick after a swap or mode switch in {name}: {} instructions, the next {} (+{extra})",
                    w[0].instructions, w[1].instructions
                );
                assert!(
                    extra <= SWAP_OVERHEAD,
                    "{name}: the swap tick costs {extra} instructions more than the next tick"
                );
            }
        }
    }
    assert!(
        swaps >= 6,
        "the lifecycle scenarios swap configurations and switch modes ({swaps} seen)"
    );
    // The tick's start latency: while the command handler, the learning's service or the
    // scenario player holds a lock on the tick's resource (or has interrupts off), a tick that
    // falls due waits. The image reads a capture back at the largest chunk and a record
    // (`READBACK`), so the handler's longest copies are among the sections seen.
    assert!(
        stdout.contains("READBACK done"),
        "the image read its capture and its record back: {stdout}"
    );
    let mut held: Vec<(String, Section)> = sections
        .into_iter()
        // The bench's own printing (semihosting, between scenarios) is not the firmware's.
        .filter(|(site, _)| !site.contains("semihosting"))
        .map(|(site, s)| {
            let (symbol, line) = site.rsplit_once(" @ ").unwrap_or((&site, "0"));
            let line = lines[line.parse::<usize>().unwrap_or(0)].clone();
            let symbol = demangled(symbol);
            (format!("{symbol}, {line}"), s)
        })
        .collect();
    held.sort_by(|a, b| b.1.instructions.cmp(&a.1.instructions).then(a.0.cmp(&b.0)));
    println!();
    println!("Critical sections that hold the tick off (from masking it to unmasking it), longest first:");
    println!("| where (function, source line) | times | instr max | cycles max (0 WS) | cycles max (5 WS) |");
    println!("|---|---:|---:|---:|---:|");
    let mut figure_sections = Vec::new();
    for (site, s) in held.iter().take(12) {
        println!(
            "| {site} | {} | {} | {} | {} |",
            s.count, s.instructions, s.cycles, s.cycles_ws5
        );
        figure_sections.push(serde_json::json!({
            "site": site,
            "count": s.count,
            "instructions": s.instructions,
            "cycles": s.cycles,
            "cycles_ws5": s.cycles_ws5,
        }));
    }
    figures["held_off"] = serde_json::json!(figure_sections);
    let (longest_site, longest) = held.first().cloned().unwrap_or_default();
    println!(
        "longest: {} instructions, {} cycles at 5 WS ({:.1} µs at 168 MHz): {longest_site}",
        longest.instructions,
        longest.cycles_ws5,
        longest.cycles_ws5 as f64 / SYSCLK_HZ * 1e6
    );
    println!("worst shipped tick: {} instructions", worst.instructions);
    // What calibrate loads at 100 kHz runs there: admitted by the budget, and its interrupt
    // measured within the period's share (the services' share below it aside: the budget's
    // prediction as loaded charges none).
    let hundred_khz = u64::from(twinstack::config::tick_budget::available_cycles(100_000.0));
    for config in HUNDRED_KHZ_CONFIGS {
        let predicted = budgets.get(config).copied().unwrap_or(u64::MAX);
        let Some(&interrupt) = streamed_interrupt.get(config) else {
            failures.push(format!("{config}: no streamed tick measured"));
            continue;
        };
        println!(
            "{config} at 100 kHz: interrupt {interrupt} measured, {predicted} predicted, of the {hundred_khz} cycles the period leaves"
        );
        if predicted > hundred_khz || interrupt > hundred_khz {
            failures.push(format!(
                "{config}: not admitted at 100 kHz ({predicted} cycles predicted, {interrupt} measured, of {hundred_khz})"
            ));
        }
    }
    // Every figure printed first, so that a failing run still shows all of them.
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    assert!(
        held.len() >= 5,
        "the trace shows the handler's locks on the tick ({} places)",
        held.len()
    );
    assert!(
        longest.instructions <= HELD_OFF_INSTRUCTIONS,
        "a critical section holds the tick off for {} instructions (asserted ≤ {HELD_OFF_INSTRUCTIONS}): {longest_site}",
        longest.instructions
    );
    assert!(
        worst.instructions <= WORST_INSTRUCTIONS,
        "the worst tick takes {} instructions (asserted ≤ {WORST_INSTRUCTIONS})",
        worst.instructions
    );
    println!("generalised P–I + creep: worst {family_worst} instructions");
    assert!(
        family_worst > 0 && family_worst <= FAMILY_WORST_INSTRUCTIONS,
        "the generalised P–I + creep tick takes {family_worst} instructions (asserted ≤ {FAMILY_WORST_INSTRUCTIONS})"
    );
    figures["family_worst_instructions"] = serde_json::json!(family_worst);
    // Every assertion held: the figures are the code's.
    let path = support::workspace_root().join(FIGURES_JSON);
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).expect("create target/figures");
    }
    let text = serde_json::to_string_pretty(&figures).expect("the figures serialise");
    std::fs::write(&path, text + "\n").unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    println!("wrote {}", path.display());
}
