//! The loopback check: with a jumper from the left DAC channel to the sensor ADC's input, a
//! few output levels streamed in bypass and the ADC's reading captured beside the DAC's code;
//! then a step streamed one setpoint a tick and captured every tick, which measures the loop's
//! delay: how many ticks after a tick writes the DAC the sensor reading shows it. The feedback's
//! reference, the drift check and the learning assume
//! [`SENSOR_DELAY_TICKS`](twinstack::control::feedback::SENSOR_DELAY_TICKS); a board whose
//! converters are timed otherwise fails here.
use super::*;
use twinstack::control::feedback::SENSOR_DELAY_TICKS;

/// The delay step's two levels (normalised setpoints) and the ticks streamed at each, one
/// setpoint a tick, captured every tick from the stream's start.
const STEP_LEVELS: (f64, f64) = (-0.3, 0.3);
const STEP_TICKS: usize = 48;
/// Ticks averaged at each end of the step for its levels before and after.
const STEP_ENDS: usize = 12;
/// The measured delay may be this far from a whole number of ticks (the converters' noise on
/// the crossing's interpolation).
const DELAY_TOLERANCE_TICKS: f64 = 0.35;

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

pub(super) fn loopback(
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
    let measured = drive_and_capture(client).and_then(|m| Ok((m, step_and_capture(client)?)));
    // Whatever happened, the settings in force go back (the output holds where the stream
    // left it: where it started).
    let restored = retry(client, |c| c.load_params(&original));
    let ((pairs, dac_full_scale), step) = measured?;
    restored.map_err(|e| {
        anyhow::anyhow!("loopback: the settings in force could not be put back: {e}")
    })?;
    let delay = loop_delay(&step, dac_full_scale);
    let points: Vec<(f64, f64)> = pairs
        .iter()
        .map(|&(dac, sensor)| fractions(dac, sensor, dac_full_scale))
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
        "delay_ticks": delay,
        "expected_delay_ticks": SENSOR_DELAY_TICKS,
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
    let Some(delay) = delay else {
        return Ok(CheckResult::fail(
            check,
            format!("{detail}; the step streamed one setpoint a tick did not show in the capture"),
            "the DAC and the ADC follow each other at rest but not a step: look for a filter or a slow buffer between the jumper and the ADC input",
            figures,
        ));
    };
    let detail = format!(
        "{detail}; a DAC write shows in the reading {delay:.2} ticks later (the feedback assumes {SENSOR_DELAY_TICKS})"
    );
    if (delay - SENSOR_DELAY_TICKS as f64).abs() > DELAY_TOLERANCE_TICKS {
        return Ok(CheckResult::fail(
            check,
            detail,
            "the converters are not timed as the firmware expects (the ADC started by TIM2's channel 2 before each tick, the DAC latched by TIM2's update): a modified image, or a filter on the jumper slower than a tick",
            figures,
        ));
    }
    Ok(CheckResult::pass(check, detail, figures))
}

/// Ticks from a DAC write to the sensor reading that shows it, from `(left code, sensor)`
/// pairs captured every tick across a step (the code of a DAC whose full scale is
/// `dac_full_scale`): where each series crosses halfway between its own levels before and
/// after the step (each averaged over [`STEP_ENDS`] ticks, so the converters' gain and offset
/// do not matter), interpolated between ticks; the reading's crossing less the code's. `None`
/// if either series does not step (by a tenth of its full scale) or never crosses.
pub(super) fn loop_delay(pairs: &[(i16, i16)], dac_full_scale: u16) -> Option<f64> {
    if pairs.len() < 3 * STEP_ENDS {
        return None;
    }
    let (code, reading): (Vec<f64>, Vec<f64>) = pairs
        .iter()
        .map(|&(dac, sensor)| fractions(dac, sensor, dac_full_scale))
        .unzip();
    Some(crossing(&reading)? - crossing(&code)?)
}

/// A captured `(left DAC code, sensor)` pair as fractions of each converter's full scale: the
/// code is unsigned (up to 65 535 on a 16-bit DAC), the reading Q1.15 over the ADC's span.
fn fractions(dac: i16, sensor: i16, dac_full_scale: u16) -> (f64, f64) {
    (
        dac as u16 as f64 / dac_full_scale.max(1) as f64,
        (sensor as f64 / 32768.0 + 1.0) / 2.0,
    )
}

/// Where `x` first crosses halfway between its mean over the first and over the last
/// [`STEP_ENDS`] values, in (fractional) indices; `None` if those means are within a tenth of
/// full scale (`x` in fractions of it) or it never crosses.
fn crossing(x: &[f64]) -> Option<f64> {
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (before, after) = (mean(&x[..STEP_ENDS]), mean(&x[x.len() - STEP_ENDS..]));
    if (after - before).abs() < 0.1 {
        return None;
    }
    let mid = 0.5 * (before + after);
    let up = after > before;
    (1..x.len()).find_map(|k| {
        let (a, b) = (x[k - 1] - mid, x[k] - mid);
        let crossed = if up {
            a < 0.0 && b >= 0.0
        } else {
            a > 0.0 && b <= 0.0
        };
        crossed.then(|| (k - 1) as f64 + a / (a - b))
    })
}

/// Streams the delay step — [`STEP_LEVELS`], [`STEP_TICKS`] at each, one setpoint a tick —
/// after walking the output to its first level, capturing the left DAC code and the sensor
/// every tick from the step's stream start; then walks the output back to where it was.
fn step_and_capture(client: &mut BoardClient) -> anyhow::Result<Vec<(i16, i16)>> {
    let s0 = output_now(client)?;
    let rate = retry(client, |c| c.status())?.tick_rate_hz.max(1);
    let walk = |client: &mut BoardClient, from: f64, to: f64| {
        let samples: Vec<i16> = ramp_and_hold(from, to).collect();
        let options = StreamOptions {
            divider: LOOPBACK_DIVIDER,
            tick_rate_hz: rate as f64,
            ..StreamOptions::default()
        };
        stream_setpoints(client, &samples, &options, |_| {})
            .map_err(|e| anyhow::anyhow!("loopback: walking the output: {e}"))
    };
    let (low, high) = STEP_LEVELS;
    walk(client, s0, low)?;
    let stepped = stream_step(client, rate);
    // Back to where the output was, whether or not the step's capture came.
    let back = walk(client, high, s0);
    let values = stepped?;
    back?;
    Ok(values.chunks_exact(2).map(|p| (p[0], p[1])).collect())
}

/// The step itself, streamed at divider 1 from [`STEP_LEVELS`]' first level (where the output
/// already is) to its second, captured every tick from the stream's start.
fn stream_step(client: &mut BoardClient, rate: u32) -> anyhow::Result<Vec<i16>> {
    let (low, high) = STEP_LEVELS;
    let frames = 2 * STEP_TICKS as u32;
    retry(client, |c| {
        c.arm_capture(CaptureRequest {
            signals: Channel::Left.bit() | Channel::Sensor.bit(),
            samples: frames,
            pre_trigger: 0,
            trigger: Trigger::StreamStart,
            decimation: 1,
        })
    })?;
    let step: Vec<i16> = std::iter::repeat_n(q15(low), STEP_TICKS)
        .chain(std::iter::repeat_n(q15(high), STEP_TICKS))
        .collect();
    let options = StreamOptions {
        divider: 1,
        tick_rate_hz: rate as f64,
        ..StreamOptions::default()
    };
    stream_setpoints(client, &step, &options, |_| {})
        .map_err(|e| anyhow::anyhow!("loopback: streaming the step: {e}"))?;
    Ok(wait_capture(client, frames * 2)?.0)
}

/// Where the output is: the setpoint in force, normalised (one captured frame).
fn output_now(client: &mut BoardClient) -> anyhow::Result<f64> {
    let start = capture(client, Channel::Setpoint.bit(), 1, 1)?;
    Ok(start.0.first().copied().unwrap_or(0) as f64 / 32768.0)
}

/// The streamed setpoints that ramp from `from` to `to` in [`RAMP`] steps and hold `to` for
/// [`PLATEAU`].
fn ramp_and_hold(from: f64, to: f64) -> impl Iterator<Item = i16> {
    (1..=RAMP)
        .map(move |i| q15(from + (to - from) * i as f64 / RAMP as f64))
        .chain(std::iter::repeat_n(q15(to), PLATEAU))
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
    let s0 = output_now(client)?;
    let mut samples = Vec::new();
    let mut from = s0;
    for &level in LOOPBACK_LEVELS.iter().chain(std::iter::once(&s0)) {
        samples.extend(ramp_and_hold(from, level));
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A step in the code, and the reading `late` ticks behind it with a gain, an offset and a
    /// two-tick ramp (a slew limit): the delay comes out whole whatever the gain and offset,
    /// and a reading that does not step gives none.
    #[test]
    fn the_delay_is_where_the_reading_crosses_less_where_the_code_does() {
        let code = |k: usize| -> i16 {
            match k {
                0..=29 => 1000,
                30 => 2000,
                _ => 3000,
            }
        };
        for late in 0..4usize {
            let pairs: Vec<(i16, i16)> = (0..80usize)
                .map(|k| {
                    let c = code(k.saturating_sub(late)) as f64 / 4096.0;
                    // 0.97 gain, +0.01 offset, as a fraction of full scale, in Q1.15.
                    let r = ((0.97 * c + 0.01) * 2.0 - 1.0) * 32768.0;
                    (code(k), r as i16)
                })
                .collect();
            let d = loop_delay(&pairs, 4095).unwrap();
            assert!((d - late as f64).abs() < 0.02, "{late}: {d}");
        }
        let flat: Vec<(i16, i16)> = (0..80).map(|k| (code(k), 0)).collect();
        assert_eq!(loop_delay(&flat, 4095), None);
    }
}
