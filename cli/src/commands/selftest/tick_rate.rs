//! The tick-rate check: the board's tick counter read twice, each read bracketed by its round
//! trip, against the rate the board reports.
use super::*;

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

pub(super) fn tick_rate(
    client: &mut BoardClient,
    image: Image,
    args: &Args,
) -> anyhow::Result<CheckResult> {
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
