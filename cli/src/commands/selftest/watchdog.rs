//! The watchdog check: a drill stops the tick feeding the watchdog, and the board must start
//! again reporting the watchdog as the cause, the settings in force before back in force.
use super::*;

/// How long the watchdog check waits for the board to start again after the drill: the
/// watchdog's timeout ([`WATCHDOG_TIMEOUT_MS`]), the boot, and the link's round trips, with
/// room to spare.
pub const DRILL_WAIT: Duration = Duration::from_secs(2);

pub(super) fn watchdog(
    client: &mut BoardClient,
    first: &StatusReport,
) -> anyhow::Result<CheckResult> {
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
