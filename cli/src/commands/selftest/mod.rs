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
//!    captured beside the DAC's code: the ADC must read what the DAC drives; then a step
//!    streamed one setpoint a tick and captured every tick: a DAC write must show in the
//!    reading [`SENSOR_DELAY_TICKS`](twinstack::control::feedback::SENSOR_DELAY_TICKS) ticks
//!    later, the delay the feedback, the drift check and the learning assume.
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

mod flash;
mod link;
mod loopback;
mod tick_rate;
mod watchdog;

use flash::flash;
use link::link;
use loopback::loopback;
use tick_rate::tick_rate;
use watchdog::watchdog;
pub use watchdog::DRILL_WAIT;

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
    /// `--port sim` only: the in-process board's sensor reading lags this many conversions
    /// (the board's timing is 1; 0 rehearses converters timed otherwise, which the loopback
    /// check's delay measurement fails).
    #[arg(long, value_name = "N")]
    pub sim_sensor_latency: Option<usize>,
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
    if (args.sim_open_loopback
        || args.sim_fail_flash_writes
        || args.sim_no_watchdog
        || args.sim_sensor_latency.is_some())
        && spec != Some(&PortSpec::Sim)
    {
        return Err(UsageError(
            "--sim-open-loopback, --sim-sensor-latency, --sim-fail-flash-writes and \
             --sim-no-watchdog fit the in-process board (--port sim); a virtual board takes \
             --loopback, --fail-flash-writes and --no-watchdog itself"
                .to_string(),
        )
        .into());
    }
    if let Some(n) = args.sim_sensor_latency {
        let most = hal_sim::converters::internal_adc::MAX_LATENCY;
        if n > most {
            return Err(UsageError(format!(
                "--sim-sensor-latency {n}: the simulated ADC lags at most {most} conversions"
            ))
            .into());
        }
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
        if let Some(n) = args.sim_sensor_latency {
            config.sensor_latency = n;
        }
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

/// Time on the link's clock: the in-process board's simulated time, else the wall clock since
/// `origin`.
fn link_now(client: &BoardClient, origin: Instant) -> Duration {
    client
        .transport()
        .clock()
        .unwrap_or_else(|| origin.elapsed())
}

fn nack_of(e: &LinkError) -> Option<NackReason> {
    match e {
        LinkError::Nack { reason, .. } => Some(*reason),
        _ => None,
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
