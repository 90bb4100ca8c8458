//! The loopback check: with a jumper from the left DAC channel to the sensor ADC's input, a
//! few output levels streamed in bypass and the ADC's reading captured beside the DAC's code.
use super::*;

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
