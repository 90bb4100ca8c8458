//! Steps 2 and 3 of a calibration: excite the stage with the excitation streamed in bypass,
//! record drive and sensor with its recorder, identify the model, and the checks before a load.

use super::*;

/// What step 3 identified from the excitation, checked for loading.
pub(super) struct Measured {
    pub(super) predicted: Vec<f64>,
    pub(super) id: Identification,
    pub(super) label: String,
    pub(super) reason: String,
    pub(super) ranking: Vec<Candidate>,
    pub(super) file: ParamFile,
    pub(super) held_out: ErrorFigures,
    pub(super) clamped: bool,
}

/// What step 2 recorded: the excitation, and how.
pub(super) struct Excited {
    pub(super) excitation: MeasuredData,
    pub(super) decimation: u16,
    pub(super) tick_rate_hz: u32,
    pub(super) underran: bool,
}

/// Steps 2 and 3: excite and record ([`excite`]), identify what the board runs with `beside`
/// cycles a tick of its own beside the model, and the checks before a load
/// ([`identify_excited`]). Loads nothing.
pub(super) fn measure<T: Transport>(
    client: &mut Client<T>,
    options: &CalibrateOptions,
    board: &Settings,
    progress: &mut impl FnMut(Progress),
) -> Result<(Excited, Measured), CalibrateError> {
    let excited = excite(client, options, board, progress)?;
    let measured = identify_excited(&excited, options, board, 0, progress)?;
    Ok((excited, measured))
}

/// Step 2: the excitation streamed in bypass and recorded.
pub(super) fn excite<T: Transport>(
    client: &mut Client<T>,
    options: &CalibrateOptions,
    board: &Settings,
    progress: &mut impl FnMut(Progress),
) -> Result<Excited, CalibrateError> {
    // 2. Excite and record.
    progress(Progress::Step("exciting the stage"));
    let facts = client
        .capture_status()
        .map_err(link("the recorder's capacity"))?;
    let rate = facts.tick_rate_hz.max(1) as f64;
    // Streamed in bypass: each setpoint is the drive. The capture records the drive the
    // board applied (the left stack) beside the sensor, so a stream that underran on a slow
    // link still gives a true record, only a different one.
    let divider = options.stream_divider;
    let samples = options.excitation_setpoints(rate / divider as f64);
    let ticks = samples.len() as u64 * divider as u64;
    let mask = Channel::Left.bit() | Channel::Sensor.bit();
    let (decimation, frames) = decimation_for(ticks, rate, options.sample_rate_hz, &facts, 2);
    options.check_resolved(rate / divider as f64, rate / decimation as f64)?;
    client
        .arm_capture(CaptureRequest {
            signals: mask,
            samples: frames,
            pre_trigger: 0,
            trigger: Trigger::StreamStart,
            decimation,
        })
        .map_err(link("arming the recorder"))?;
    let stream = options.stream_options(rate);
    let streamed = match stream_setpoints(client, &samples, &stream, |sent| {
        progress(Progress::Count {
            what: "setpoints sent",
            done: sent as u64,
        })
    }) {
        Ok(r) => r,
        Err(source) => {
            // Best effort: the stream stopped, the output holding where it is (the error at
            // hand says more than a failure to stop).
            let _ = client.stream(StreamControl::Stop);
            return Err(CalibrateError::Stream {
                step: "streaming the excitation",
                source,
            });
        }
    };
    let budget = Duration::from_secs_f64(2.0 * ticks as f64 / rate + 10.0);
    let (cap, window) = capture::wait_and_read(client, budget, |what, n| {
        progress(Progress::Count {
            what,
            done: n as u64,
        })
    })
    .map_err(|source| CalibrateError::Capture {
        step: "recording the excitation",
        source,
    })?;
    let recording =
        capture::convert(&cap, board, &window).map_err(|source| CalibrateError::Convert {
            step: "the excitation",
            source,
        })?;
    let excitation = excitation_record(&recording, board, &options.output_unit)?;
    Ok(Excited {
        excitation,
        decimation: cap.decimation,
        tick_rate_hz: facts.tick_rate_hz,
        underran: streamed.underran(),
    })
}

/// Step 3: identify from the excitation what the board runs at its rate with `beside` cycles
/// a tick of its own beside the model (0, or what its refusal of a first load showed:
/// a dual-stage image's coarse task), and the checks before a load (the fit, the drive's
/// reach). Loads nothing.
pub(super) fn identify_excited(
    excited: &Excited,
    options: &CalibrateOptions,
    board: &Settings,
    beside: u32,
    progress: &mut impl FnMut(Progress),
) -> Result<Measured, CalibrateError> {
    let excitation = &excited.excitation;
    let rate = excited.tick_rate_hz.max(1) as f64;
    // 3. Identify.
    progress(Progress::Step("identifying"));
    let fit_until = options.excitation_s() - 1.0 / options.excitation_hz;
    let mut id_options = IdentifyOptions::new(options.model.unwrap_or(ModelKind::Pi), fit_until);
    id_options.operators = options.operators.unwrap_or(DEFAULT_OPERATORS);
    // Its own tracking check captures with the model loaded, at the sample rate's decimation
    // or coarser ([`decimation_for`]): the services are charged too.
    let least = (rate / options.sample_rate_hz)
        .ceil()
        .clamp(1.0, u16::MAX as f64) as u16;
    let rate_limit = BoardRate::sizing(rate, options.operators.is_some())
        .capturing(least)
        .beside(beside);
    id_options.lag = options.lag;
    // Only a model the board runs at its control rate with its drive, sensor and feedback:
    // the tick budget the board applies at load ([`twinstack::config::tick_budget`]), applied here
    // first, so that `auto` picks among what the board takes.
    let runs_on_board = |fitted: &IdentifyOptions, id: &Identification| {
        let mut settings = ParamFile::from_model(&id.model, &options.output_unit, None)
            .with_observer(fitted.observer)
            .settings;
        settings.drive = board.drive;
        settings.sensor = board.sensor;
        settings.feedback = board.feedback;
        admission_at(&settings, &rate_limit)
    };
    // What was fitted: the size, and the observer (left out where the rate has no time for it).
    let (id, operators, observer, label, reason, ranking) = match options.model {
        Some(_) => {
            let asked = Size::of(&id_options);
            let (fitted, id) = identify_admitted(excitation, id_options.clone(), &runs_on_board)?;
            // What was kept: "+ creep" only if the fit kept one.
            let label = fitted.label_of_fit(&id.model);
            let reason = match Size::of(&fitted).sized_down_note(&asked) {
                Some(note) => format!("{label} (asked for; {note})"),
                None => format!("{label} (asked for)"),
            };
            (
                id,
                fitted.operators,
                fitted.observer,
                label,
                reason,
                Vec::new(),
            )
        }
        None => {
            let auto =
                identify_auto_admitting(excitation, &id_options.candidates(), runs_on_board)?;
            let picked = auto.options.clone();
            let ranking = auto.ranking.iter().map(candidate).collect();
            let label = picked.label_of_fit(&auto.identification.model);
            (
                auto.identification,
                picked.operators,
                picked.observer,
                label,
                auto.reason,
                ranking,
            )
        }
    };
    let (record, predicted) = identification_record(excitation, &id, fit_until, operators)?;
    if record.held_out.max_pct > options.max_held_out_pct {
        return Err(CalibrateError::DoesNotFit {
            model: label,
            max_pct: record.held_out.max_pct,
            limit: options.max_held_out_pct,
        });
    }
    let held_out = record.held_out;
    let mut file = ParamFile::from_model(&id.model, &options.output_unit, Some(record))
        .with_observer(observer);

    // The settings to load: the board's drive, sensor and gains kept.
    file.settings.drive = board.drive;
    file.settings.sensor = board.sensor;
    file.settings.feedback = board.feedback;
    let clamped = match twinstack_link::board_requests::unreachable_input(&file.settings) {
        Some(((model_lo, model_hi), (drive_lo, drive_hi))) if !options.clamp => {
            return Err(CalibrateError::Unreachable {
                model_lo,
                model_hi,
                drive_lo,
                drive_hi,
            })
        }
        Some(_) => true,
        None => false,
    };
    Ok(Measured {
        predicted,
        id,
        label,
        reason,
        ranking,
        file,
        held_out,
        clamped,
    })
}

fn candidate(r: &Ranked) -> Candidate {
    Candidate {
        label: r.label.clone(),
        validation: r.validation.clone(),
        inverse: r.inverse,
        tracking: r.tracking,
        compensated_max_pct: r.compensated(),
        set_aside: r.set_aside.clone(),
        summary: r.summary(),
    }
}

/// Ticks per frame and frames for a capture of `signals` signals over `ticks` ticks: at most
/// `sample_rate_hz`, and few enough frames for the board's slots.
pub(super) fn decimation_for(
    ticks: u64,
    rate: f64,
    sample_rate_hz: f64,
    facts: &CaptureStatus,
    signals: u32,
) -> (u16, u32) {
    let max_frames = (facts.capacity / signals).max(1) as u64;
    let by_rate = (rate / sample_rate_hz).ceil().max(1.0) as u64;
    let by_slots = ticks.div_ceil(max_frames).max(1);
    let decimation = by_rate.max(by_slots).min(u16::MAX as u64);
    let frames = ticks.div_ceil(decimation).clamp(1, max_frames);
    (decimation as u16, frames as u32)
}

/// The excitation as a `t,u,x` record (left stack volts, sensor in the output unit), after
/// checking that the sensor moved and did not saturate.
fn excitation_record(
    recording: &Recording,
    board: &Settings,
    unit: &str,
) -> Result<MeasuredData, CalibrateError> {
    let column = |c: Channel| recording.column(c).cloned();
    let (Some(left), Some(sensor)) = (column(Channel::Left), column(Channel::Sensor)) else {
        return Err(CalibrateError::MissingSignals);
    };
    let range = |v: &[i16]| {
        v.iter().fold((i32::MAX, i32::MIN), |(l, h), &q| {
            (l.min(q as i32), h.max(q as i32))
        })
    };
    let (q_lo, q_hi) = range(&sensor.raw);
    // (Saturating: an empty capture reads as the widest negative span, i.e. flat.)
    let lsb = q_hi.saturating_sub(q_lo);
    // Fewer than 64 steps of the reading (0.2 % of the output range): no stage to identify.
    if lsb < 64 {
        let (d_lo, d_hi) = left
            .values
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
                (l.min(v), h.max(v))
            });
        let span = board.ranges.norm_to_output(q_hi as f64 / 32768.0)
            - board.ranges.norm_to_output(q_lo as f64 / 32768.0);
        return Err(CalibrateError::SensorFlat {
            span: span.abs(),
            unit: unit.into(),
            lsb,
            drive_lo: d_lo,
            drive_hi: d_hi,
        });
    }
    let at_ends = sensor
        .raw
        .iter()
        .filter(|&&q| q == i16::MAX || q == i16::MIN)
        .count();
    // A few samples at an end can be noise; one in a hundred is a clipped loop.
    if at_ends * 100 > sensor.raw.len() {
        return Err(CalibrateError::SensorSaturated {
            lo: board.ranges.output_min,
            hi: board.ranges.output_max,
            unit: unit.into(),
            count: at_ends,
            total: sensor.raw.len(),
        });
    }
    let t0 = recording.t.first().copied().unwrap_or(0.0);
    Ok(MeasuredData {
        path: "calibrate-excitation".into(),
        t: recording.t.iter().map(|t| t - t0).collect(),
        u: Some(left.values),
        x: Some(sensor.values),
    })
}

/// The figures `identify` writes into the parameter file, and the model's prediction.
fn identification_record(
    data: &MeasuredData,
    id: &Identification,
    fit_until: f64,
    operators: usize,
) -> Result<(IdentificationRecord, Vec<f64>), CalibrateError> {
    let (t, u, x) = (
        &data.t,
        data.u.as_deref().unwrap_or_default(),
        data.x.as_deref().unwrap_or_default(),
    );
    let n = t.len();
    let model = &id.model;
    let lib = |e: twinstack::ParamError| CalibrateError::Model(e.to_string());
    let predicted = model.predict(t, u).map_err(lib)?;
    let reference = model.predict_reference(t, u).map_err(lib)?;
    let drive = model.compensate_measured(t, x).map_err(lib)?;
    let drive_reference = model.compensate_measured_reference(t, x).map_err(lib)?;
    let (fit_from, held) = (id.motion.first_fitted, id.held_out_from);
    let flat = || CalibrateError::Model("the recorded output is flat: cannot score".into());
    let aimed = n - model.lag_samples(t).min(n.saturating_sub(held + 1));
    let record = IdentificationRecord {
        data: data.path.display().to_string(),
        fit_until_s: fit_until,
        fit_from_s: t.get(fit_from).copied().unwrap_or(0.0),
        operators,
        thresholds: "uniform".into(),
        lag_samples: id.lag_samples,
        lag_estimated: id.lag_estimated,
        outliers: id.outliers,
        fit: score(x, &predicted, fit_from..held).ok_or_else(flat)?,
        held_out: score(x, &predicted, held..n).ok_or_else(flat)?,
        inverse_held_out: score(u, &drive, held..aimed).ok_or_else(flat)?,
        fixed_vs_reference_max_pct: score(&reference, &predicted, fit_from..n)
            .ok_or_else(flat)?
            .max_pct,
        inverse_fixed_vs_reference_max_pct: score(&drive_reference, &drive, fit_from..n)
            .ok_or_else(flat)?
            .max_pct,
        notes: id.notes.clone(),
        fastest_motion_hz: crate::identification::coverage::fastest_motion_in(t, u, fit_from..held),
    };
    Ok((record, predicted))
}
