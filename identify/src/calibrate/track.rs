//! The last step of a calibration: a test trajectory tracked before and after compensation.

use super::*;

/// The capture a tracking of `setpoints` conditioned setpoints takes: its ticks, and the
/// decimation and frames that fit the board's capture slots ([`decimation_for`]).
pub(super) fn tracking_capture(
    facts: &CaptureStatus,
    setpoints: usize,
    options: &CalibrateOptions,
) -> (u64, u16, u32) {
    let rate = facts.tick_rate_hz.max(1) as f64;
    let ticks = setpoints as u64 * options.stream_divider as u64;
    let (decimation, frames) = decimation_for(ticks, rate, options.sample_rate_hz, facts, 2);
    (ticks, decimation, frames)
}

/// Streams `trajectory` (after [`trajectory::with_conditioning`] from `x_rest`) in the mode in
/// force, records the setpoint and the sensor from the stream's start and scores the sensor
/// against the setpoint over the trajectory.
pub(super) fn track<T: Transport>(
    client: &mut Client<T>,
    trajectory: &trajectory::Trajectory,
    x_rest: f64,
    options: &CalibrateOptions,
    settings: &Settings,
    step: &'static str,
) -> Result<(Tracking, Recording), CalibrateError> {
    let facts = client.capture_status().map_err(link(step))?;
    let rate = facts.tick_rate_hz.max(1) as f64;
    let setpoint_rate = rate / options.stream_divider as f64;
    let (x, first) = trajectory::with_conditioning(trajectory, x_rest, setpoint_rate);
    let samples: Vec<i16> = x
        .iter()
        .map(|&v| q1_15(settings.ranges.output_to_norm(v)))
        .collect();
    let (ticks, decimation, frames) = tracking_capture(&facts, x.len(), options);
    client
        .arm_capture(CaptureRequest {
            signals: Channel::Setpoint.bit() | Channel::Sensor.bit(),
            samples: frames,
            pre_trigger: 0,
            trigger: Trigger::StreamStart,
            decimation,
        })
        .map_err(link(step))?;
    let stream = options.stream_options(rate);
    let r = stream_setpoints(client, &samples, &stream, |_| {})
        .map_err(|source| CalibrateError::Stream { step, source })?;
    let seconds = ticks as f64 / rate;
    let budget = Duration::from_secs_f64(2.0 * seconds + 10.0);
    let (cap, window) = capture::wait_and_read(client, budget, |_, _| {})
        .map_err(|source| CalibrateError::Capture { step, source })?;
    let recording = capture::convert(&cap, settings, &window)
        .map_err(|source| CalibrateError::Convert { step, source })?;
    let empty = Vec::new();
    let column = |c: Channel| recording.column(c).map_or(&empty, |c| &c.values);
    let (setpoint, sensor) = (column(Channel::Setpoint), column(Channel::Sensor));
    // Scored from the trajectory's first setpoint to its last (the lead-in is not).
    let dt = cap.decimation.max(1) as f64 / rate;
    let start = ((first as f64 / setpoint_rate) / dt).ceil() as usize;
    let end = ((x.len() as f64 / setpoint_rate) / dt).floor() as usize;
    let end = end.min(setpoint.len()).min(sensor.len());
    let figures = score(setpoint, sensor, start.min(end)..end).unwrap_or(ErrorFigures {
        max_pct: f64::NAN,
        rms_pct: f64::NAN,
        samples: 0,
    });
    Ok((
        Tracking {
            max_pct: figures.max_pct,
            rms_pct: figures.rms_pct,
            samples: figures.samples,
            underran: r.underran(),
        },
        recording,
    ))
}
