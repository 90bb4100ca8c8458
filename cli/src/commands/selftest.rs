//! `twinstack selftest --port PORT [--echoes N] [--tick-seconds S] [--skip CHECK]… [--json]`:
//! what works on a freshly flashed board, one line per check — `PASS`, `FAIL` or `SKIP`, the
//! figure measured, and on `FAIL` what to fix — then a summary; exits 1 when a check fails.
//!
//! The checks, in the order they run (the book's selftest page has the wiring and the table
//! of faults):
//!
//! 1. **safe state**: the board's status — idle (no stream, waveform, scan or sequence
//!    driving the outputs) and no tick overran its period. A busy board fails here, and the
//!    checks that move the outputs or write the flash are skipped.
//! 2. **link**: `--echoes` frames of random content and length (0 to [`MAX_ECHO`] bytes)
//!    echoed by the board ([`Request::Echo`]) and compared byte for byte, with the board's
//!    and the host's corrupt-frame counters before and after.
//! 3. **tick rate**: the board's tick counter read twice `--tick-seconds` apart, each read
//!    bracketed by its round trip, against the rate the board reports; the tolerance is what
//!    the brackets leave plus `--tick-tolerance-ppm`.
//! 4. **loopback**: with a jumper from the left DAC channel to the sensor ADC's input, a few
//!    output levels streamed in bypass (range and slew limits hold) and the ADC's reading
//!    captured beside the DAC's code: the ADC must read what the DAC drives.
//! 5. **flash**: the settings in force stored, recalled and read back; what flash held before
//!    is put back.
//! 6. **watchdog**: last, because it resets the board: a drill ([`Request::WatchdogDrill`])
//!    stops the tick feeding the watchdog, and the board must start again within
//!    [`DRILL_WAIT`] reporting the watchdog as the cause
//!    ([`StatusReport::WATCHDOG_RESET`]); the settings in force before go back in force
//!    after (the reset boots on the stored ones).

use super::board_link::{connect_with, BoardClient, PortArgs};
use hal_sim::port::PortSpec;
use std::io::Write;
use std::time::{Duration, Instant};
use twinstack::board::WATCHDOG_TIMEOUT_MS;
use twinstack::config::settings::{Mode, SensorSettings, Settings};
use twinstack::protocol::frame::FrameError;
use twinstack::protocol::messages::{
    CaptureRequest, CaptureState, Image, NackReason, Request, Response, StatusReport, Trigger,
    MAX_ECHO,
};
use twinstack::services::recorder::Channel;
use twinstack_link::client::LinkError;
use twinstack_link::streamer::{stream_setpoints, StreamOptions};
use twinstack_link::Transport;

/// The checks, by the names `--skip` takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum CheckName {
    /// Idle outputs, no overrun.
    SafeState,
    /// The reset cause.
    Watchdog,
    /// Echoed frames.
    Link,
    /// Ticks against the host's clock.
    TickRate,
    /// DAC → ADC through the jumper.
    Loopback,
    /// Store, recall, compare.
    Flash,
}

impl CheckName {
    /// The name printed and taken by `--skip`.
    pub fn name(self) -> &'static str {
        match self {
            CheckName::SafeState => "safe-state",
            CheckName::Watchdog => "watchdog",
            CheckName::Link => "link",
            CheckName::TickRate => "tick-rate",
            CheckName::Loopback => "loopback",
            CheckName::Flash => "flash",
        }
    }
}

/// Arguments of `selftest`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// Frames echoed by the link check (random content, random length up to the largest
    /// frame).
    #[arg(long, default_value_t = 200, value_name = "N")]
    pub echoes: u32,
    /// Seed of the echoes' random content (the same frames every run).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Seconds between the tick rate check's two reads of the tick counter (longer narrows
    /// what the link's round trips leave uncertain).
    #[arg(long, default_value_t = 1.0, value_name = "S")]
    pub tick_seconds: f64,
    /// The clocks' tolerance the tick rate check allows beyond the round trips' bracket,
    /// parts per million (a crystal and the host's clock: tens of ppm each).
    #[arg(long, default_value_t = 500.0, value_name = "PPM")]
    pub tick_tolerance_ppm: f64,
    /// Largest difference between what the ADC reads and what the DAC drives in the loopback
    /// check, percent of full scale.
    #[arg(long, default_value_t = 2.0, value_name = "PCT")]
    pub loopback_tolerance_pct: f64,
    /// A check not to run (repeatable): e.g. `--skip loopback` on a board without the jumper.
    #[arg(long, value_enum, value_name = "CHECK")]
    pub skip: Vec<CheckName>,
    /// `--port sim` only: the in-process board without its loopback jumper (the sensor ADC
    /// reads the stage's sensor). By default it has the jumper, as the bench this command
    /// expects.
    #[arg(long)]
    pub sim_open_loopback: bool,
    /// `--port sim` only: every flash write of the in-process board fails.
    #[arg(long)]
    pub sim_fail_flash_writes: bool,
    /// `--port sim` only: the in-process board's watchdog never fires.
    #[arg(long)]
    pub sim_no_watchdog: bool,
    /// One JSON object on stdout (each check's name, outcome, figures and hint, and the
    /// counts) instead of lines.
    #[arg(long)]
    pub json: bool,
}

/// A check's outcome.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    /// It works.
    Pass,
    /// It does not: the line says what to fix.
    Fail,
    /// Not run, or not observable here: the line says why.
    Skip,
}

impl Outcome {
    /// `PASS`, `FAIL`, `SKIP`.
    pub fn word(self) -> &'static str {
        match self {
            Outcome::Pass => "PASS",
            Outcome::Fail => "FAIL",
            Outcome::Skip => "SKIP",
        }
    }
}

/// One check's result: what it measured, and on a failure what to fix.
#[derive(Clone, Debug)]
pub struct CheckResult {
    /// Which check.
    pub check: CheckName,
    /// Pass, fail, skip.
    pub outcome: Outcome,
    /// What was measured (or why it was skipped).
    pub detail: String,
    /// What to fix (failures).
    pub hint: Option<String>,
    /// The figures, for `--json`.
    pub figures: serde_json::Value,
}

impl CheckResult {
    fn pass(check: CheckName, detail: String, figures: serde_json::Value) -> Self {
        Self {
            check,
            outcome: Outcome::Pass,
            detail,
            hint: None,
            figures,
        }
    }

    fn fail(check: CheckName, detail: String, hint: &str, figures: serde_json::Value) -> Self {
        Self {
            check,
            outcome: Outcome::Fail,
            detail,
            hint: Some(hint.to_string()),
            figures,
        }
    }

    fn skip(check: CheckName, why: String) -> Self {
        Self {
            check,
            outcome: Outcome::Skip,
            detail: why,
            hint: None,
            figures: serde_json::Value::Null,
        }
    }

    /// The check's line: `PASS link       …`, a failure's hint after a colon.
    pub fn line(&self) -> String {
        let mut line = format!(
            "{} {:<10} {}",
            self.outcome.word(),
            self.check.name(),
            self.detail
        );
        if let Some(hint) = &self.hint {
            line.push_str(": ");
            line.push_str(hint);
        }
        line
    }

    fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "check": self.check.name(),
            "outcome": self.outcome.word(),
            "detail": self.detail,
            "hint": self.hint,
            "figures": self.figures,
        })
    }
}

/// The selftest's verdict: some check failed (`main` exits 1).
#[derive(Debug, thiserror::Error)]
#[error("selftest: {failed} of {ran} checks failed ({names})")]
pub struct SelftestFailed {
    /// Checks failed.
    pub failed: usize,
    /// Checks run (not skipped).
    pub ran: usize,
    /// Their names, comma-separated.
    pub names: String,
}

fn validate(args: &Args, spec: Option<&PortSpec>) -> anyhow::Result<()> {
    use super::board_link::UsageError;
    if args.echoes == 0 || args.echoes > 100_000 {
        return Err(UsageError(format!(
            "--echoes {}: must be from 1 to 100000",
            args.echoes
        ))
        .into());
    }
    if !(args.tick_seconds.is_finite() && (0.2..=3600.0).contains(&args.tick_seconds)) {
        return Err(UsageError(format!(
            "--tick-seconds {}: must be from 0.2 to 3600 seconds",
            args.tick_seconds
        ))
        .into());
    }
    if !(args.tick_tolerance_ppm.is_finite()
        && (0.0..=100_000.0).contains(&args.tick_tolerance_ppm))
    {
        return Err(UsageError(format!(
            "--tick-tolerance-ppm {}: must be from 0 to 100000",
            args.tick_tolerance_ppm
        ))
        .into());
    }
    if !(args.loopback_tolerance_pct.is_finite()
        && args.loopback_tolerance_pct > 0.0
        && args.loopback_tolerance_pct <= 50.0)
    {
        return Err(UsageError(format!(
            "--loopback-tolerance-pct {}: must be above 0 and at most 50",
            args.loopback_tolerance_pct
        ))
        .into());
    }
    if (args.sim_open_loopback || args.sim_fail_flash_writes || args.sim_no_watchdog)
        && spec != Some(&PortSpec::Sim)
    {
        return Err(UsageError(
            "--sim-open-loopback, --sim-fail-flash-writes and --sim-no-watchdog fit the in-process \
             board (--port sim); a virtual board takes --loopback, --fail-flash-writes and \
             --no-watchdog itself"
                .to_string(),
        )
        .into());
    }
    Ok(())
}

/// Runs `selftest`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let spec = match &args.port.port {
        Some(p) => Some(p.parse::<PortSpec>()?),
        None => None,
    };
    validate(args, spec.as_ref())?;
    let mut client = connect_with(&args.port, |config| {
        config.loopback = !args.sim_open_loopback;
        config.failing_flash = args.sim_fail_flash_writes;
        config.watchdog = !args.sim_no_watchdog;
    })?;
    let mut results = Vec::new();
    let json = args.json;
    let mut emit = |r: CheckResult| {
        if !json {
            println!("{}", r.line());
            let _ = std::io::stdout().flush();
        }
        results.push(r);
    };
    let skipped = |c: CheckName| args.skip.contains(&c);
    let skip_flag = |c: CheckName| CheckResult::skip(c, format!("--skip {}", c.name()));

    // The board as found: everything else depends on it answering, and on it being idle.
    let first = retry(&mut client, |c| c.status())?;
    let image = first.image();
    let idle = busy_flags(&first).is_empty();
    for check in [
        CheckName::SafeState,
        CheckName::Link,
        CheckName::TickRate,
        CheckName::Loopback,
        CheckName::Flash,
        CheckName::Watchdog,
    ] {
        if skipped(check) {
            emit(skip_flag(check));
            continue;
        }
        let busy = || {
            CheckResult::skip(
                check,
                format!(
                    "the board is busy ({}): it was not disturbed",
                    busy_flags(&first).join(", ")
                ),
            )
        };
        let result = match check {
            CheckName::SafeState => safe_state(&first),
            CheckName::Watchdog if !idle => busy(),
            CheckName::Watchdog => watchdog(&mut client, &first)?,
            CheckName::Link => link(&mut client, args.echoes, args.seed)?,
            CheckName::TickRate => tick_rate(&mut client, image, args)?,
            CheckName::Loopback if !idle => busy(),
            CheckName::Loopback => loopback(&mut client, image, args.loopback_tolerance_pct)?,
            CheckName::Flash if !idle => busy(),
            CheckName::Flash => flash(&mut client)?,
        };
        emit(result);
    }
    let count = |o: Outcome| results.iter().filter(|r| r.outcome == o).count();
    let (pass, fail, skip) = (
        count(Outcome::Pass),
        count(Outcome::Fail),
        count(Outcome::Skip),
    );
    let failed: Vec<&str> = results
        .iter()
        .filter(|r| r.outcome == Outcome::Fail)
        .map(|r| r.check.name())
        .collect();
    if json {
        println!(
            "{}",
            serde_json::json!({
                "image": image.name(),
                "tick_rate_hz": first.tick_rate_hz,
                "checks": results.iter().map(CheckResult::json).collect::<Vec<_>>(),
                "pass": pass,
                "fail": fail,
                "skip": skip,
            })
        );
    } else {
        println!(
            "selftest of the {} image: {pass} PASS, {fail} FAIL, {skip} SKIP",
            image.name()
        );
    }
    if fail > 0 {
        return Err(SelftestFailed {
            failed: fail,
            ran: pass + fail,
            names: failed.join(", "),
        }
        .into());
    }
    Ok(())
}

/// Runs `f`, again (twice at most, the line resynchronised first) when its answer was lost:
/// every request the selftest repeats this way is idempotent (reads, a load of the same
/// settings, a store of the same record).
fn retry<R>(
    client: &mut BoardClient,
    mut f: impl FnMut(&mut BoardClient) -> Result<R, LinkError>,
) -> Result<R, LinkError> {
    let mut attempt = 0;
    loop {
        match f(client) {
            Err(LinkError::Timeout { .. } | LinkError::Unexpected { .. }) if attempt < 2 => {
                attempt += 1;
                client.resync(Duration::from_millis(20))?;
            }
            other => return other,
        }
    }
}

/// What keeps the board busy (driving its outputs, or sending).
fn busy_flags(s: &StatusReport) -> Vec<&'static str> {
    [
        (StatusReport::STREAMING, "streaming"),
        (StatusReport::WAVEFORM, "waveform"),
        (StatusReport::SCANNING, "scanning"),
        (StatusReport::SEQUENCE, "sequence armed"),
        (StatusReport::TELEMETRY, "telemetry"),
        (StatusReport::RECORDING, "recording"),
    ]
    .into_iter()
    .filter(|&(bit, _)| s.has(bit))
    .map(|(_, name)| name)
    .collect()
}

fn safe_state(s: &StatusReport) -> CheckResult {
    let check = CheckName::SafeState;
    let busy = busy_flags(s);
    let figures = serde_json::json!({
        "busy": busy,
        "overruns": s.overruns,
        "limit_hits": s.limit_hits,
        "defaults": s.has(StatusReport::DEFAULTS),
        "mode": twinstack_link::board_requests::mode_name(s.mode()),
    });
    let settings = if s.has(StatusReport::DEFAULTS) {
        "on the compiled-in defaults (no valid stored settings)"
    } else {
        "on its settings"
    };
    if !busy.is_empty() {
        return CheckResult::fail(
            check,
            format!("the board is driving its outputs or sending ({})", busy.join(", ")),
            "stop it (twinstack stop; telemetry stops with its client) and run the selftest on an idle board",
            figures,
        );
    }
    if s.overruns > 0 && s.image() == Image::Emulator {
        return CheckResult::pass(
            check,
            format!(
                "idle, outputs held; {} of {} ticks overran, which in QEMU says how fast the host emulates the tick, not what a board does (its tick cost is measured on instruction counts); {} mode, {settings}",
                s.overruns,
                s.ticks,
                twinstack_link::board_requests::mode_name(s.mode()),
            ),
            figures,
        );
    }
    if s.overruns > 0 {
        return CheckResult::fail(
            check,
            format!(
                "{} ticks overran their period since start-up",
                s.overruns
            ),
            "the tick's work does not fit its period: load smaller models or run a lower control rate (twinstack load refuses settings the tick budget rejects; an overrun on the defaults is a firmware or clock fault)",
            figures,
        );
    }
    CheckResult::pass(
        check,
        format!(
            "idle, outputs held, no tick overran in {} ticks; {} mode, {settings}; {} ticks clipped by the range or slew limits",
            s.ticks,
            twinstack_link::board_requests::mode_name(s.mode()),
            s.limit_hits
        ),
        figures,
    )
}

/// xorshift64*: the echoes' lengths and bytes.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
}

/// The echoes' lengths: the largest and the empty one first, then random.
fn echo_payload(i: u32, rng: &mut Rng) -> Vec<u8> {
    let len = match i {
        0 => MAX_ECHO,
        1 => 0,
        _ => (rng.next() % (MAX_ECHO as u64 + 1)) as usize,
    };
    (0..len).map(|_| (rng.next() >> 56) as u8).collect()
}

fn link(client: &mut BoardClient, echoes: u32, seed: u64) -> anyhow::Result<CheckResult> {
    let check = CheckName::Link;
    let before = retry(client, |c| c.status())?;
    let host_before = client.counters().corrupt_frames;
    let timeout = client.timeout();
    let mut rng = Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    let (mut intact, mut damaged_in, mut lost, mut differ, mut bytes) =
        (0u32, 0u32, 0u32, 0u32, 0u64);
    let mut unknown = 0u32;
    let mut rtt_max = Duration::ZERO;
    let origin = Instant::now();
    for i in 0..echoes {
        let payload = echo_payload(i, &mut rng);
        bytes += payload.len() as u64;
        let request =
            Request::Echo(heapless::Vec::from_slice(&payload).expect("at most MAX_ECHO bytes"));
        let start = link_now(client, origin);
        // Sent once, not retried: a damaged frame is what this check counts.
        client.send(&request)?;
        match client.receive(timeout)? {
            Some(Response::Echo(back)) if back.as_slice() == payload.as_slice() => {
                intact += 1;
                rtt_max = rtt_max.max(link_now(client, origin).saturating_sub(start));
            }
            Some(Response::Echo(_)) => differ += 1,
            Some(Response::Nack {
                reason: NackReason::Frame(FrameError::UnknownType),
            }) => unknown += 1,
            Some(Response::Nack {
                reason: NackReason::Frame(_),
            }) => damaged_in += 1,
            Some(_) => {
                // Another answer (a late one): start the next echo on a clean line.
                differ += 1;
                client.resync(Duration::from_millis(20))?;
            }
            None => {
                lost += 1;
                client.resync(Duration::from_millis(20))?;
            }
        }
    }
    let after = retry(client, |c| c.status())?;
    let crc = after.crc_errors.wrapping_sub(before.crc_errors);
    let frame = after.frame_errors.wrapping_sub(before.frame_errors);
    let host = client.counters().corrupt_frames - host_before;
    let figures = serde_json::json!({
        "echoes": echoes,
        "intact": intact,
        "damaged_to_board": damaged_in,
        "lost": lost,
        "differing": differ,
        "unanswered_type": unknown,
        "bytes": bytes,
        "board_crc_errors": crc,
        "board_frame_errors": frame,
        "host_corrupt_frames": host,
        "max_round_trip_ms": rtt_max.as_secs_f64() * 1e3,
    });
    if unknown == echoes {
        return Ok(CheckResult::fail(
            check,
            format!("the board answered none of {echoes} echoes: it does not know the request"),
            "its firmware predates the echo: build and flash the current image (cargo build-fw, probe-rs), then run the selftest again",
            figures,
        ));
    }
    let bad = echoes - intact;
    let counted = format!(
        "board counted {crc} CRC and {frame} other frame errors, host skipped {host} corrupt frames"
    );
    if bad > 0 || crc > 0 || frame > 0 || host > 0 {
        return Ok(CheckResult::fail(
            check,
            format!(
                "{bad} of {echoes} echoes corrupted ({damaged_in} damaged on the way to the board, {lost} lost or damaged on the way back, {differ} answered wrong; {counted})"
            ),
            "check the adapter's ground and the baud rate on both ends (3 Mbaud by default: --baud), shorten the cable, keep it away from the amplifier's high-voltage leads",
            figures,
        ));
    }
    Ok(CheckResult::pass(
        check,
        format!(
            "{echoes} echoes of 0…{MAX_ECHO} bytes ({bytes} bytes each way) came back intact; {counted}; slowest round trip {:.1} ms",
            rtt_max.as_secs_f64() * 1e3
        ),
        figures,
    ))
}

/// Time on the link's clock: the in-process board's simulated time, else the wall clock since
/// `origin`.
fn link_now(client: &BoardClient, origin: Instant) -> Duration {
    client
        .transport()
        .clock()
        .unwrap_or_else(|| origin.elapsed())
}

/// A status read and the host's clock at its send and at its answer.
fn bracketed_status(
    client: &mut BoardClient,
    origin: Instant,
) -> anyhow::Result<(StatusReport, f64, f64)> {
    // The best of three: the shortest round trip brackets the board's reading tightest.
    let mut best: Option<(StatusReport, f64, f64)> = None;
    for _ in 0..3 {
        let sent = origin.elapsed().as_secs_f64();
        let s = retry(client, |c| c.status())?;
        let answered = origin.elapsed().as_secs_f64();
        if best.as_ref().is_none_or(|b| answered - sent < b.2 - b.1) {
            best = Some((s, sent, answered));
        }
    }
    Ok(best.expect("three reads"))
}

fn tick_rate(client: &mut BoardClient, image: Image, args: &Args) -> anyhow::Result<CheckResult> {
    let check = CheckName::TickRate;
    if client.transport().clock().is_some() {
        return Ok(CheckResult::skip(
            check,
            "the in-process simulated board runs on simulated time, not the wall clock: \
             there is no clock to compare (a virtual board, twinstack virtual-board, is paced \
             by the wall clock)"
                .to_string(),
        ));
    }
    if image == Image::Emulator {
        return Ok(CheckResult::skip(
            check,
            "QEMU emulates the tick's timer on the host's clock, with no crystal behind it: a \
             rate measured there says how fast the host emulates, not how a board's clock runs"
                .to_string(),
        ));
    }
    let origin = Instant::now();
    let (a, a_sent, a_back) = bracketed_status(client, origin)?;
    let wait = args.tick_seconds - (origin.elapsed().as_secs_f64() - a_back);
    if wait > 0.0 {
        std::thread::sleep(Duration::from_secs_f64(wait));
    }
    let (b, b_sent, b_back) = bracketed_status(client, origin)?;
    let configured = b.tick_rate_hz as f64;
    let ticks = b.ticks.wrapping_sub(a.ticks) as f64;
    // The board read its counter somewhere inside each round trip.
    let (shortest, longest) = (b_sent - a_back, b_back - a_sent);
    let interval = 0.5 * (shortest + longest);
    let measured = ticks / interval;
    let tolerance = args.tick_tolerance_ppm * 1e-6;
    let low = ticks / longest * (1.0 - tolerance);
    let high = if shortest > 0.0 {
        ticks / shortest * (1.0 + tolerance)
    } else {
        f64::INFINITY
    };
    let bracket_pct = 100.0 * 0.5 * (longest - shortest) / interval;
    let error_pct = 100.0 * (measured / configured - 1.0);
    let figures = serde_json::json!({
        "configured_hz": configured,
        "measured_hz": measured,
        "error_pct": error_pct,
        "interval_s": interval,
        "bracket_pct": bracket_pct,
        "round_trips_ms": [(a_back - a_sent) * 1e3, (b_back - b_sent) * 1e3],
        "tolerance_ppm": args.tick_tolerance_ppm,
        "ticks": ticks,
    });
    let detail = format!(
        "{configured:.0} Hz configured, {measured:.0} Hz measured over {interval:.3} s ({error_pct:+.2} %); the round trips ({:.1} ms, {:.1} ms) leave ±{bracket_pct:.2} %, plus {} ppm for the clocks",
        (a_back - a_sent) * 1e3,
        (b_back - b_sent) * 1e3,
        args.tick_tolerance_ppm
    );
    if b.tick_rate_hz == 0 {
        return Ok(CheckResult::fail(
            check,
            "the board reports a tick rate of 0 Hz".to_string(),
            "its firmware predates the field: flash the current image",
            figures,
        ));
    }
    if ticks == 0.0 {
        return Ok(CheckResult::fail(
            check,
            format!("the tick counter did not move in {interval:.3} s"),
            "the control timer is not running: check the firmware's clock tree (the crystal, HSE, must start) and that the timer interrupt is enabled",
            figures,
        ));
    }
    if !(low..=high).contains(&configured) {
        let way = if measured > configured {
            "fast"
        } else {
            "slow"
        };
        return Ok(CheckResult::fail(
            check,
            detail,
            &format!(
                "the board's clock runs {:.2} % {way}: check the crystal (HSE) fitted against the one the firmware's clock tree assumes and the PLL settings; a board left on its internal RC oscillator is off by up to 1 %",
                error_pct.abs()
            ),
            figures,
        ));
    }
    Ok(CheckResult::pass(check, detail, figures))
}

/// Levels the loopback check drives, normalised setpoints (−1…1 of the range).
const LOOPBACK_LEVELS: [f64; 5] = [-0.6, -0.3, 0.0, 0.3, 0.6];
/// Streamed setpoints per ramp and per plateau.
const RAMP: usize = 20;
const PLATEAU: usize = 30;
/// Ticks per streamed setpoint.
const LOOPBACK_DIVIDER: u16 = 50;

fn q15(x: f64) -> i16 {
    twinstack_link::setpoint_file::q1_15(x)
}

fn loopback(
    client: &mut BoardClient,
    image: Image,
    tolerance_pct: f64,
) -> anyhow::Result<CheckResult> {
    let check = CheckName::Loopback;
    if image == Image::Emulator {
        return Ok(CheckResult::skip(
            check,
            "QEMU models no DAC and no ADC conversion of it: there is nothing to loop back"
                .to_string(),
        ));
    }
    let original = retry(client, |c| c.read_params())?;
    // The sensor ADC read over the whole output range, so that the capture's sensor signal is
    // the ADC's fraction of full scale; bypass, so that the DAC follows the setpoints.
    let test = Settings {
        mode: Mode::Bypass,
        sensor: Some(SensorSettings {
            displacement_at_zero: original.ranges.output_min,
            displacement_at_full_scale: original.ranges.output_max,
            drift_limit: None,
        }),
        ..original.clone()
    };
    if let Err(e) = retry(client, |c| c.load_params(&test)) {
        return Ok(CheckResult::fail(
            check,
            format!("the board refused bypass with the ADC read over the output range: {e}"),
            "load settings the board accepts (twinstack load) and run the selftest again",
            serde_json::Value::Null,
        ));
    }
    let measured = drive_and_capture(client);
    // Whatever happened, the settings in force go back (the output holds where the stream
    // left it: where it started).
    let restored = retry(client, |c| c.load_params(&original));
    let (pairs, dac_full_scale) = measured?;
    restored.map_err(|e| {
        anyhow::anyhow!("loopback: the settings in force could not be put back: {e}")
    })?;
    let fs = dac_full_scale.max(1) as f64;
    let points: Vec<(f64, f64)> = pairs
        .iter()
        .map(|&(dac, sensor)| {
            (
                dac as u16 as f64 / fs,
                (sensor as f64 / 32768.0 + 1.0) / 2.0,
            )
        })
        .collect();
    let (dac_lo, dac_hi) = span(points.iter().map(|p| p.0));
    let (adc_lo, adc_hi) = span(points.iter().map(|p| p.1));
    let worst = points
        .iter()
        .map(|&(d, a)| (a - d).abs())
        .fold(0.0, f64::max);
    let slope = fit_slope(&points);
    let figures = serde_json::json!({
        "frames": points.len(),
        "dac_span": [dac_lo, dac_hi],
        "adc_span": [adc_lo, adc_hi],
        "worst_difference_pct": 100.0 * worst,
        "slope": slope,
        "tolerance_pct": tolerance_pct,
    });
    if dac_hi - dac_lo < 0.1 {
        return Ok(CheckResult::fail(
            check,
            format!(
                "the DAC moved over {:.1} % of full scale only ({:.3}…{:.3})",
                100.0 * (dac_hi - dac_lo),
                dac_lo,
                dac_hi
            ),
            "the settings' drive window is too narrow for the check (twinstack params shows it); load wider limits or --skip loopback",
            figures,
        ));
    }
    let detail = format!(
        "the DAC drove {dac_lo:.3}…{dac_hi:.3} of full scale, the ADC read {adc_lo:.3}…{adc_hi:.3} (slope {slope:.3}, worst difference {:.2} % of full scale over {} frames)",
        100.0 * worst,
        points.len()
    );
    if 100.0 * worst > tolerance_pct {
        return Ok(CheckResult::fail(
            check,
            detail,
            "fit the jumper from the left DAC channel (PA4) to the sensor ADC input (PA0 on the driver board, A2/PA6 on the Feather), the sensor unplugged, or --skip loopback on a board without it; a jumper fitted and a slope far from 1 is a converter or reference fault",
            figures,
        ));
    }
    Ok(CheckResult::pass(check, detail, figures))
}

fn span(values: impl Iterator<Item = f64>) -> (f64, f64) {
    values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    })
}

/// Least-squares slope of y on x.
fn fit_slope(points: &[(f64, f64)]) -> f64 {
    let n = points.len().max(1) as f64;
    let mx = points.iter().map(|p| p.0).sum::<f64>() / n;
    let my = points.iter().map(|p| p.1).sum::<f64>() / n;
    let sxy: f64 = points.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let sxx: f64 = points.iter().map(|p| (p.0 - mx) * (p.0 - mx)).sum();
    if sxx > 0.0 {
        sxy / sxx
    } else {
        0.0
    }
}

/// Streams the loopback's levels from where the output is back to it, capturing the left
/// DAC code and the sensor beside it; returns the pairs and the DAC's full-scale code.
fn drive_and_capture(client: &mut BoardClient) -> anyhow::Result<(Vec<(i16, i16)>, u16)> {
    // Where the output is: the setpoint in force (one captured frame).
    let start = capture(client, Channel::Setpoint.bit(), 1, 1)?;
    let s0 = start.0.first().copied().unwrap_or(0) as f64 / 32768.0;
    let mut samples = Vec::new();
    let mut from = s0;
    for &level in LOOPBACK_LEVELS.iter().chain(std::iter::once(&s0)) {
        for i in 1..=RAMP {
            samples.push(q15(from + (level - from) * i as f64 / RAMP as f64));
        }
        samples.extend(std::iter::repeat_n(q15(level), PLATEAU));
        from = level;
    }
    let status = retry(client, |c| c.status())?;
    let capacity = retry(client, |c| c.capture_status())?.capacity.max(2);
    // The stream, and half a second for the requests that start it.
    let rate = status.tick_rate_hz.max(1);
    let ticks = samples.len() as u32 * LOOPBACK_DIVIDER as u32 + rate / 2;
    let decimation = (2 * ticks).div_ceil(capacity).clamp(1, u16::MAX as u32) as u16;
    let frames = ticks / decimation as u32;
    let mask = Channel::Left.bit() | Channel::Sensor.bit();
    retry(client, |c| {
        c.arm_capture(CaptureRequest {
            signals: mask,
            samples: frames,
            pre_trigger: 0,
            trigger: Trigger::Now,
            decimation,
        })
    })?;
    let options = StreamOptions {
        divider: LOOPBACK_DIVIDER,
        tick_rate_hz: rate as f64,
        ..StreamOptions::default()
    };
    stream_setpoints(client, &samples, &options, |_| {})
        .map_err(|e| anyhow::anyhow!("loopback: streaming the levels: {e}"))?;
    let (values, dac_fs) = wait_capture(client, frames * 2)?;
    Ok((
        values.chunks_exact(2).map(|p| (p[0], p[1])).collect(),
        dac_fs,
    ))
}

/// Arms and reads a short capture.
fn capture(
    client: &mut BoardClient,
    mask: u8,
    samples: u32,
    decimation: u16,
) -> anyhow::Result<(Vec<i16>, u16)> {
    retry(client, |c| {
        c.arm_capture(CaptureRequest {
            signals: mask,
            samples,
            pre_trigger: 0,
            trigger: Trigger::Now,
            decimation,
        })
    })?;
    wait_capture(client, samples * mask.count_ones())
}

/// Waits for the capture armed to complete (at most 10 s) and reads its `slots`.
fn wait_capture(client: &mut BoardClient, slots: u32) -> anyhow::Result<(Vec<i16>, u16)> {
    let start = Instant::now();
    loop {
        let s = retry(client, |c| c.capture_status())?;
        if s.state == CaptureState::Done {
            let values = client.read_capture_window(slots.min(s.window_slots), |_| {})?;
            return Ok((values, s.dac_full_scale));
        }
        if start.elapsed() > Duration::from_secs(10) {
            anyhow::bail!("the capture did not complete in 10 s ({:?})", s.state);
        }
        if client.transport().clock().is_some() {
            client.wait(Duration::from_millis(5))?;
        } else {
            std::thread::sleep(Duration::from_millis(5));
        }
    }
}

/// The top-level fields of two settings that differ.
fn differing_fields(a: &Settings, b: &Settings) -> Vec<String> {
    let (a, b) = (serde_json::to_value(a), serde_json::to_value(b));
    match (a, b) {
        (Ok(serde_json::Value::Object(a)), Ok(serde_json::Value::Object(b))) => a
            .iter()
            .filter(|(k, v)| b.get(*k) != Some(v))
            .map(|(k, _)| k.clone())
            .collect(),
        _ => vec!["(unreadable)".to_string()],
    }
}

fn nack_of(e: &LinkError) -> Option<NackReason> {
    match e {
        LinkError::Nack { reason, .. } => Some(*reason),
        _ => None,
    }
}

fn flash(client: &mut BoardClient) -> anyhow::Result<CheckResult> {
    let check = CheckName::Flash;
    let in_force = retry(client, |c| c.read_params())?;
    // What flash holds: recalled (which puts it in force), read, then the settings in force
    // go back.
    let stored = match retry(client, |c| c.recall_params()) {
        Ok(()) => {
            let s = retry(client, |c| c.read_params())?;
            retry(client, |c| c.load_params(&in_force))?;
            Some(s)
        }
        Err(e) if nack_of(&e) == Some(NackReason::NothingStored) => None,
        Err(e) if nack_of(&e) == Some(NackReason::NoStorage) => {
            return Ok(CheckResult::skip(
                check,
                "the board has no parameter storage".to_string(),
            ))
        }
        Err(e) => return Err(e.into()),
    };
    let figures = |ok: bool| {
        serde_json::json!({
            "stored_before": stored.is_some(),
            "recalled_equal": ok,
        })
    };
    match retry(client, |c| c.store_params(in_force.mode)) {
        Ok(()) => {}
        Err(e) if nack_of(&e) == Some(NackReason::NoStorage) => {
            return Ok(CheckResult::skip(
                check,
                "the board has no parameter storage (it says so: the QEMU image models no flash \
                 interface)"
                    .to_string(),
            ))
        }
        Err(e) if nack_of(&e) == Some(NackReason::StoreFailed) => {
            let lost = if stored.is_some() {
                "the settings stored before may be lost (the board boots on its defaults if so)"
            } else {
                "flash held no settings before"
            };
            return Ok(CheckResult::fail(
                check,
                format!("writing the settings in force to flash failed (erase, program or read-back); {lost}"),
                "the parameter sector is worn, write-protected (option bytes) or the supply sagged during the write: check the option bytes with probe-rs, the board's 3.3 V under load, and store again (twinstack load --params FILE --store MODE)",
                figures(false),
            ));
        }
        Err(e) => return Err(e.into()),
    }
    retry(client, |c| c.recall_params())?;
    let recalled = retry(client, |c| c.read_params())?;
    let equal = recalled == in_force;
    // What flash held goes back: those settings stored (in their mode), then the settings
    // in force loaded again.
    let restored = match &stored {
        Some(s) => {
            let put_back = retry(client, |c| c.load_params(s))
                .and_then(|()| retry(client, |c| c.store_params(s.mode)));
            let again = retry(client, |c| c.load_params(&in_force));
            put_back
                .and(again)
                .map(|()| "the settings stored before were stored again")
        }
        None if equal => retry(client, |c| c.load_params(&in_force)).map(|()| {
            "flash held no settings before and now holds the settings in force (the \
                 protocol has no erase): the board boots on them"
        }),
        None => {
            retry(client, |c| c.load_params(&in_force)).map(|()| "flash held no settings before")
        }
    };
    let restored = restored
        .map(str::to_string)
        .unwrap_or_else(|e| format!("putting back what flash held failed: {e}"));
    if !equal {
        return Ok(CheckResult::fail(
            check,
            format!(
                "the settings recalled differ from those stored ({}); {restored}",
                differing_fields(&in_force, &recalled).join(", ")
            ),
            "the record read back is not the one written: a flash or firmware fault; reflash the current image and store again",
            figures(false),
        ));
    }
    Ok(CheckResult::pass(
        check,
        format!("the settings in force were stored, recalled and read back equal; {restored}"),
        figures(true),
    ))
}

/// How long the watchdog check waits for the board to start again after the drill: the
/// watchdog's timeout ([`WATCHDOG_TIMEOUT_MS`]), the boot, and the link's round trips, with
/// room to spare.
pub const DRILL_WAIT: Duration = Duration::from_secs(2);

fn watchdog(client: &mut BoardClient, first: &StatusReport) -> anyhow::Result<CheckResult> {
    let check = CheckName::Watchdog;
    let before = retry(client, |c| c.status())?;
    let was_watchdog = before.has(StatusReport::WATCHDOG_RESET);
    let in_force = retry(client, |c| c.read_params())?;
    match client.expect_ack(&Request::WatchdogDrill) {
        Ok(_) => {}
        Err(e) if nack_of(&e) == Some(NackReason::Unsupported) => {
            return Ok(CheckResult::skip(
                check,
                format!(
                    "the {} image has no watchdog to drill, and says so{}",
                    first.image().name(),
                    if first.image() == Image::Emulator {
                        " (QEMU models none)"
                    } else {
                        ""
                    }
                ),
            ))
        }
        Err(e) if nack_of(&e) == Some(NackReason::Busy) => {
            return Ok(CheckResult::skip(
                check,
                "the board is busy (a setpoint source started): it was not disturbed".to_string(),
            ))
        }
        // The answer lost: the board may be resetting already; the wait below tells.
        Err(LinkError::Timeout { .. }) => {}
        Err(e) => return Err(e.into()),
    }
    // Until the board answers with its tick counter started again.
    let origin = Instant::now();
    let start = link_now(client, origin);
    let mut last_ticks = before.ticks;
    let restarted = loop {
        let waited = link_now(client, origin).saturating_sub(start);
        if waited > DRILL_WAIT {
            break None;
        }
        // A wall-clock link is polled every 20 ms; the in-process board's time moves with
        // the requests themselves.
        if client.transport().clock().is_none() {
            std::thread::sleep(Duration::from_millis(20));
        }
        match client.status() {
            // Answered by the board started again: back within the time to this answer.
            Ok(s) if s.ticks < last_ticks => {
                break Some((s, link_now(client, origin).saturating_sub(start)))
            }
            Ok(s) => last_ticks = s.ticks,
            // Silent while it resets: the line resynchronised, asked again.
            Err(LinkError::Timeout { .. } | LinkError::Unexpected { .. }) => {
                client.resync(Duration::from_millis(20))?;
            }
            Err(e) => return Err(e.into()),
        }
    };
    let figures = |reset: bool, flagged: bool, ms: Option<f64>| {
        serde_json::json!({
            "reset": reset,
            "cause_watchdog": flagged,
            "back_within_ms": ms,
            "previous_start_watchdog": was_watchdog,
        })
    };
    let Some((after, waited)) = restarted else {
        return Ok(CheckResult::fail(
            check,
            format!(
                "the board acknowledged the drill but did not reset within {} s (its tick \
                 counter kept counting): its watchdog is not running, and the board now runs \
                 without one",
                DRILL_WAIT.as_secs_f64()
            ),
            "power-cycle the board; a firmware image whose init does not start the IWDG, or a \
             debugger session that freezes it (DBGMCU), keeps it from firing: flash the \
             release image and run the selftest without a probe attached",
            figures(false, false, None),
        ));
    };
    let ms = waited.as_secs_f64() * 1e3;
    // The reset booted on the stored settings: the settings in force go back.
    let now = retry(client, |c| c.read_params())?;
    let restored = if now == in_force {
        "it came back on the settings in force before (they are the stored ones)".to_string()
    } else {
        match retry(client, |c| c.load_params(&in_force)) {
            Ok(()) => {
                "it came back on its stored settings; those in force before were loaded again"
                    .to_string()
            }
            Err(e) => format!(
                "it came back on its stored settings; loading those in force before failed: {e}"
            ),
        }
    };
    let previous = if was_watchdog {
        " (its start before this check was a watchdog reset too)"
    } else {
        ""
    };
    if !after.has(StatusReport::WATCHDOG_RESET) {
        return Ok(CheckResult::fail(
            check,
            format!(
                "the board restarted {ms:.0} ms after the drill but does not report the \
                 watchdog as the cause; {restored}"
            ),
            "a reset by the reset pin or a brown-out came first (check the 3.3 V supply and \
             NRST), or the image predates the reset-cause report: flash the current image",
            figures(true, false, Some(ms)),
        ));
    }
    Ok(CheckResult::pass(
        check,
        format!(
            "the drill reset the board within {ms:.0} ms (timeout {WATCHDOG_TIMEOUT_MS} ms), \
             the watchdog reported as the cause{previous}; {restored}"
        ),
        figures(true, true, Some(ms)),
    ))
}
