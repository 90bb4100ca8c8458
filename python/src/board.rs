//! The `Board` class: a board behind the protocol client (a serial port, a socket or the
//! in-process simulated board), its requests, streams, captures and calibration, and
//! `settings_schema`.

use crate::convert::{array, json_to_py, vector, wire_values};
use crate::errors::{
    board_error, link_error, param_file_error, path_error, port_error, run_error, table_error,
    tune_error,
};
use crate::params::Params;
use hal_sim::port::{open_send, PortError, PortSpec, DEFAULT_BAUD};
use hal_sim::sim_camera::CameraConfig;
use hal_sim::sim_device::{SimDevice, SimDeviceConfig};
use numpy::PyArray1;
use pyo3::exceptions::{
    PyConnectionError, PyRuntimeError, PyTimeoutError, PyTypeError, PyValueError,
};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::ops::ControlFlow;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};
use twinstack::config::settings::Mode;
use twinstack::control::feedback::FeedbackSettings;
use twinstack::control::notch::NotchDesign;
use twinstack::dual_stage::{CoarseState, CoarseStatus};
use twinstack::fixed_point::{signal_from_f64, signal_to_f64};
use twinstack::protocol::messages::{CoarseMove, LearnState};
use twinstack::protocol::messages::{
    Request, SequenceConfig, StreamControl, Trigger, TriggerEdge, UnderrunPolicy, WaveShape,
};
use twinstack::services::learning::LearnSettings;
use twinstack::services::recorder::Channel;
use twinstack::sources::analog_input::{AnalogInputConfig, AnalogRequest, OnFault};
use twinstack::sources::scan::{ScanRequest, FRAME, LINE, PIXEL};
use twinstack_identify::param_file::ParamFile;
use twinstack_identify::preview::ResonancePreview;
use twinstack_link::board_requests::{self, LoadRefused};
use twinstack_link::capture::{self, CaptureError};
use twinstack_link::client::{Client, LinkError};
use twinstack_link::learning;
use twinstack_link::scan_timing::{parse_pattern, pattern_kind, run_scan, ScanRunError};
use twinstack_link::sequence_run::{run_sequence, SequenceError, SequenceOptions};
use twinstack_link::setpoint_file::divider_for_rate;
use twinstack_link::settings_path;
use twinstack_link::streamer::{stream_setpoints_until, StartOn, StreamOptions};
use twinstack_link::telemetry::{RunError, TelemetryRun};
use twinstack_link::Transport;

// The default baud in `Board`'s signature (a literal, so Python shows it) is the CLI's.
const _: () = assert!(DEFAULT_BAUD == 3_000_000);

/// How often a stream asks the interpreter whether Ctrl-C was pressed.
const SIGNAL_CHECK: Duration = Duration::from_millis(50);

pub(crate) type BoardClient = Client<Box<dyn Transport + Send>>;

/// `start_on`: `"now"`, `"rising"` or `"falling"` (the trigger input's edge).
fn parse_start_on(start_on: &str) -> PyResult<TriggerEdge> {
    match start_on {
        "now" => Ok(TriggerEdge::Off),
        "rising" => Ok(TriggerEdge::Rising),
        "falling" => Ok(TriggerEdge::Falling),
        other => Err(PyValueError::new_err(format!(
            "start_on {other:?}: expected \"now\", \"rising\" or \"falling\""
        ))),
    }
}

pub(crate) fn parse_mode(name: &str) -> PyResult<Mode> {
    board_requests::parse_mode(name).ok_or_else(|| {
        PyValueError::new_err(format!(
            "mode {name:?}: expected \"bypass\", \"open-loop\" or \"closed-loop\""
        ))
    })
}

pub(crate) fn parse_trigger(name: &str) -> PyResult<Trigger> {
    match name.to_ascii_lowercase().as_str() {
        "now" => Ok(Trigger::Now),
        "stream" => Ok(Trigger::StreamStart),
        "waveform" => Ok(Trigger::WaveformStart),
        _ => Err(PyValueError::new_err(format!(
            "trigger {name:?}: expected \"now\", \"stream\" or \"waveform\""
        ))),
    }
}

pub(crate) fn signal_list(signals: &Bound<'_, PyAny>) -> PyResult<String> {
    if let Ok(s) = signals.extract::<String>() {
        return Ok(s);
    }
    let names: Vec<String> = signals.extract().map_err(|_| {
        PyTypeError::new_err(
            "signals: give a list of names (setpoint, left, right, sensor, estimate, error) or one comma-separated string",
        )
    })?;
    Ok(names.join(","))
}

/// A board: a serial device, `tcp:HOST:PORT` (a virtual board, QEMU), `unix:PATH`, or `"sim"`.
#[pyclass(module = "twinstack")]
pub(crate) struct Board {
    port: String,
    client: Mutex<Option<BoardClient>>,
    /// A stream this board left playing with `more`: the next `stream` continues it.
    stream_open: AtomicBool,
}

impl Board {
    /// Runs `f` on the client without the interpreter's lock.
    fn with<T: Send>(
        &self,
        py: Python<'_>,
        f: impl FnOnce(&mut BoardClient) -> Result<T, LinkError> + Send,
    ) -> PyResult<T> {
        self.with_py(py, |client| {
            f(client).map_err(|e| Python::attach(|py| link_error(py, e)))
        })
    }

    /// Runs `f` on the client (without the interpreter's lock unless `f` takes it back).
    fn with_py<T: Send>(
        &self,
        py: Python<'_>,
        f: impl FnOnce(&mut BoardClient) -> PyResult<T> + Send,
    ) -> PyResult<T> {
        let mut guard = self.client.try_lock().map_err(|_| {
            PyRuntimeError::new_err(
                "the board is in use by another thread (one call at a time per Board)",
            )
        })?;
        let client: &mut BoardClient = guard.as_mut().ok_or_else(|| {
            PyRuntimeError::new_err(format!("{}: the board is closed", self.port))
        })?;
        py.detach(|| f(client))
    }

    /// Waits for the capture armed on the board and reads it back in physical units: `t`,
    /// then one column per signal.
    fn read_capture(&self, py: Python<'_>, timeout: Duration) -> PyResult<Vec<(String, Vec<f64>)>> {
        self.with_py(py, |client| {
            let err = |e: LinkError| Python::attach(|py| link_error(py, e));
            let settings = client.read_params().map_err(err)?;
            // Ctrl-C (a signal) stops the wait at the next poll, its exception raised; the
            // capture stays armed on the board, to be fetched later.
            let mut interrupt = None;
            let waited = capture::wait_and_read_or_stop(client, timeout, |_, _| {
                signal_taken(&mut interrupt)
            });
            let (status, window) = waited.map_err(|e| match e {
                CaptureError::Link(l) => err(l),
                e @ CaptureError::NotDone { .. } => PyTimeoutError::new_err(e.to_string()),
                e @ CaptureError::Stopped { .. } => interrupt
                    .take()
                    .unwrap_or_else(|| PyRuntimeError::new_err(e.to_string())),
            })?;
            let recording = capture::convert(&status, &settings, &window)
                .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
            let mut out = vec![("t".to_string(), recording.t)];
            for c in recording.columns {
                out.push((c.channel.name().to_string(), c.values));
            }
            Ok(out)
        })
    }

    /// What `stream` sends for `values` at `rate`: the board's Q1.15 setpoints (shaped for
    /// `resonance` if given), the divider and the board's tick rate. Refused, naming the
    /// value, where `stream` would refuse them; nothing is sent.
    fn stream_samples(
        &self,
        py: Python<'_>,
        values: &[f64],
        rate: Option<f64>,
        normalised: bool,
        resonance: Option<(f64, f64)>,
    ) -> PyResult<(Vec<i16>, u16, f64)> {
        let (status, settings) = self.with(py, |c| Ok((c.status()?, c.read_params()?)))?;
        let tick_rate = status.tick_rate_hz.max(1) as f64;
        let samples = wire_values(values, normalised, &settings, "setpoints")?;
        let divider = match rate {
            None => 1,
            Some(r) => divider_for_rate(tick_rate, r).map_err(PyValueError::new_err)?,
        };
        let samples = match resonance {
            Some((hz, zeta)) => ResonancePreview::new(hz, zeta, tick_rate)
                .and_then(|p| p.shape_stream_for(&samples, &settings, divider))
                .map_err(|e| PyValueError::new_err(format!("resonance: {e}; nothing was sent")))?,
            None => samples,
        };
        Ok((samples, divider, tick_rate))
    }

    /// Sends a coarse command and, with `wait`, waits for the axis to come to rest: its
    /// status, a fault it ended in raised as `RuntimeError`.
    fn coarse_command<'py>(
        &self,
        py: Python<'py>,
        request: &Request,
        wait: bool,
        timeout: f64,
    ) -> PyResult<Bound<'py, PyAny>> {
        let limit = seconds(timeout, "timeout")?;
        let status = self.with_py(py, |c| {
            let err = |e: LinkError| Python::attach(|py| link_error(py, e));
            c.coarse(request).map_err(err)?;
            if !wait {
                return c.coarse_status().map_err(err);
            }
            board_requests::wait_until_coarse_settled(c, limit).map_err(|e| match e {
                board_requests::CoarseWaitError::Link(l) => err(l),
                e @ board_requests::CoarseWaitError::Busy { .. } => {
                    PyTimeoutError::new_err(e.to_string())
                }
            })
        })?;
        if wait && (status.faults != 0 || status.state == CoarseState::Fault) {
            let faults: Vec<&str> = CoarseStatus::fault_names(status.faults).collect();
            return Err(PyRuntimeError::new_err(format!(
                "the coarse axis ended in a fault: {} (home it again to clear it)",
                if faults.is_empty() {
                    "-".to_string()
                } else {
                    faults.join(", ")
                }
            )));
        }
        json_to_py(py, &board_requests::coarse_status_json(&status))
    }

    fn fetch_dict<'py>(&self, py: Python<'py>, timeout: f64) -> PyResult<Bound<'py, PyDict>> {
        let columns = self.read_capture(py, seconds(timeout, "timeout")?)?;
        let d = PyDict::new(py);
        for (name, values) in columns {
            d.set_item(name, array(py, values))?;
        }
        Ok(d)
    }
}

/// Whether a signal (Ctrl-C) has come, for a wait on the board to stop at its next poll:
/// its exception is kept in `taken`, to be raised once the wait has stopped.
fn signal_taken(taken: &mut Option<PyErr>) -> ControlFlow<()> {
    match Python::attach(|py| py.check_signals()) {
        Ok(()) => ControlFlow::Continue(()),
        Err(e) => {
            *taken = Some(e);
            ControlFlow::Break(())
        }
    }
}

pub(crate) fn seconds(s: f64, name: &str) -> PyResult<Duration> {
    if s > 0.0 && s <= MAX_SECONDS {
        Ok(Duration::from_secs_f64(s))
    } else {
        Err(PyValueError::new_err(format!(
            "{name} {s}: must be a number of seconds above 0 and at most 86400"
        )))
    }
}

/// The longest wait or duration an argument takes, seconds: a day.
pub(crate) const MAX_SECONDS: f64 = 86_400.0;

#[pymethods]
impl Board {
    /// Connects to the board at `port` and cleans the line.
    #[new]
    #[pyo3(signature = (port, baud=3_000_000, timeout=2.0, sim_camera_hz=None, sim_camera_frames=0, sim_camera_on_settled=false))]
    fn new(
        py: Python<'_>,
        port: &str,
        baud: u32,
        timeout: f64,
        sim_camera_hz: Option<f64>,
        sim_camera_frames: u32,
        sim_camera_on_settled: bool,
    ) -> PyResult<Self> {
        let timeout = seconds(timeout, "timeout")?;
        let spec: PortSpec = port.parse().map_err(port_error)?;
        let camera = match sim_camera_hz {
            // The camera's options without the camera: refused, not ignored.
            None if sim_camera_frames != 0 || sim_camera_on_settled => {
                return Err(PyValueError::new_err(
                    "sim_camera_frames and sim_camera_on_settled describe the simulated camera: give its frame rate too (sim_camera_hz)",
                ))
            }
            None => None,
            Some(_) if spec != PortSpec::Sim => {
                return Err(PyValueError::new_err(format!(
                    "sim_camera_hz: only with port \"sim\" (this is {port:?})"
                )))
            }
            Some(hz) => {
                let config = SimDeviceConfig::paper();
                let rate = 1.0 / config.board.plant.dt;
                Some(
                    CameraConfig::at_rate(hz, rate, sim_camera_frames, sim_camera_on_settled)
                        .map_err(|e| PyValueError::new_err(format!("sim_camera_hz: {e}")))?,
                )
            }
        };
        let client = py.detach(|| -> Result<BoardClient, Result<PortError, LinkError>> {
            let transport: Box<dyn Transport + Send> = match camera {
                Some(camera) => {
                    let config = SimDeviceConfig {
                        baud,
                        camera: Some(camera),
                        ..SimDeviceConfig::paper()
                    };
                    Box::new(SimDevice::new(config).map_err(|e| Ok(PortError::Sim(e.to_string())))?)
                }
                None => open_send(&spec, baud).map_err(Ok)?,
            };
            let mut client = Client::new(transport);
            client.set_timeout(timeout);
            client.resync(Duration::from_millis(20)).map_err(Err)?;
            Ok(client)
        });
        let client = client.map_err(|e| match e {
            Ok(p) => port_error(p),
            Err(l) => link_error(py, l),
        })?;
        Ok(Self {
            port: port.to_string(),
            client: Mutex::new(Some(client)),
            stream_open: AtomicBool::new(false),
        })
    }

    /// The port this board was opened on.
    #[getter]
    fn port(&self) -> &str {
        &self.port
    }

    /// Status and telemetry, as a dict.
    fn status<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let s = self.with(py, |c| c.status())?;
        json_to_py(py, &board_requests::status_json(&s))
    }

    /// Loads a parameter file's settings.
    #[pyo3(signature = (params, clamp=false, mode=None, store=None, preview=None))]
    fn load(
        &self,
        py: Python<'_>,
        params: &Params,
        clamp: bool,
        mode: Option<&str>,
        store: Option<&str>,
        preview: Option<bool>,
    ) -> PyResult<()> {
        let mode = mode.map(parse_mode).transpose()?;
        let store = store.map(parse_mode).transpose()?;
        let mut file = params.file.settings.clone();
        if preview == Some(true) {
            let Some(r) = params.file.resonance else {
                return Err(PyValueError::new_err(
                    "preview=True needs the stage's resonance, which the parameter file does not hold (calibrate measures it); nothing was loaded",
                ));
            };
            file.preview = Some(twinstack::control::preview::PreviewDesign {
                frequency_hz: r.frequency_hz,
                damping: r.damping,
            });
        }
        let board = self.with(py, |c| Ok(c.read_params().ok()))?;
        let mut settings = board_requests::keep_from_board(&file, board.as_ref());
        if preview == Some(false) {
            settings.preview = None;
        }
        if let Some(m) = mode {
            settings.mode = m;
        }
        match board_requests::check_load(&settings, params.model.output_sign, clamp) {
            Ok(None) => {}
            Ok(Some(warning)) => {
                let warnings = py.import("warnings")?;
                let category = py.get_type::<pyo3::exceptions::PyRuntimeWarning>();
                warnings.call_method1(
                    "warn",
                    (
                        format!("{warning} (clamp=True: loading it anyway)"),
                        category,
                        2,
                    ),
                )?;
            }
            Err(e) => {
                let field = match &e {
                    LoadRefused::Drive(r) => r.field.to_string(),
                    LoadRefused::InvertedSensor => "output_sign".to_string(),
                    LoadRefused::Unreachable { .. } => "ranges.input".to_string(),
                };
                let hint = match e {
                    LoadRefused::Drive(_) | LoadRefused::InvertedSensor => "nothing was sent",
                    LoadRefused::Unreachable { .. } => {
                        "identify the model within the drive's range, or pass clamp=True to load it anyway; nothing was loaded"
                    }
                };
                return Err(board_error(
                    py,
                    format!("{e}; {hint}"),
                    "LoadParams",
                    Some(field),
                    e.to_string(),
                    None,
                    None,
                ));
            }
        }
        self.with(py, |c| {
            c.load_params(&settings)?;
            if let Some(boot) = store {
                c.store_params(boot)?;
            }
            Ok(())
        })
    }

    /// The settings in force on the board, as a dict (physical units).
    fn params<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let s = self.with(py, |c| c.read_params())?;
        let v = serde_json::to_value(&s).map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
        json_to_py(py, &v)
    }

    /// One setting by its path (``"/feedback/kp"``; :func:`settings_schema` lists them), as
    /// the Python value of its JSON (``None`` for a part that is not set); ``KeyError`` names
    /// a path that names nothing.
    fn get<'py>(&self, py: Python<'py>, path: &str) -> PyResult<Bound<'py, PyAny>> {
        let s = self.with(py, |c| c.read_params())?;
        let v = settings_path::get(&s, path).map_err(path_error)?;
        json_to_py(py, &v)
    }

    /// Changes one setting by its path and loads the settings whole (the board validates
    /// them, prepares them off the tick and swaps them in bumplessly); returns the value the
    /// board then holds. ``KeyError`` names a path that names nothing, ``ValueError`` a value
    /// of the wrong type, ``BoardError`` the board's refusal (field and limit).
    fn set<'py>(
        &self,
        py: Python<'py>,
        path: &str,
        value: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        // A numpy scalar or array as the Python number or list it holds; NaN and infinity,
        // which JSON has not, refused naming the path (as a number beyond f64 is).
        let value = if value.hasattr("tolist")? {
            value.call_method0("tolist")?
        } else {
            value.clone()
        };
        let kwargs = PyDict::new(py);
        kwargs.set_item("allow_nan", false)?;
        let text: String = py
            .import("json")?
            .call_method("dumps", (&value,), Some(&kwargs))
            .map_err(|e| {
                PyValueError::new_err(format!(
                    "{path}: {}: not a value the settings hold ({})",
                    value.repr().map_or_else(|_| "?".into(), |r| r.to_string()),
                    e.value(py)
                ))
            })?
            .extract()?;
        let value: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| PyValueError::new_err(format!("{path}: {text:.40}: {e}")))?;
        let held = self.with(py, |c| {
            let s = c.read_params()?;
            let new = match settings_path::set(&s, path, value.clone()) {
                Ok(new) => new,
                Err(e) => return Ok(Err(e)),
            };
            c.load_params(&new)?;
            Ok(Ok(c.read_params()?))
        })?;
        let held = held.map_err(path_error)?;
        let v = settings_path::get(&held, path).map_err(path_error)?;
        json_to_py(py, &v)
    }

    /// The setpoints `stream` would send for these arguments, normalised (−1…1, the board's
    /// Q1.15 values): with `resonance`, shaped for the stage's resonance as `stream` shapes
    /// them. Nothing is sent; refused as `stream` refuses them.
    #[pyo3(signature = (setpoints, resonance, rate=None, normalised=false))]
    fn shaped<'py>(
        &self,
        py: Python<'py>,
        setpoints: &Bound<'py, PyAny>,
        resonance: Option<(f64, f64)>,
        rate: Option<f64>,
        normalised: bool,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let values = vector(py, setpoints, "setpoints")?;
        let (samples, _, _) = self.stream_samples(py, &values, rate, normalised, resonance)?;
        Ok(array(
            py,
            samples.iter().map(|&q| q as f64 / 32768.0).collect(),
        ))
    }

    /// Switches the control mode (bumpless).
    fn mode(&self, py: Python<'_>, mode: &str) -> PyResult<()> {
        let m = parse_mode(mode)?;
        self.with(py, |c| c.set_mode(m))
    }

    /// Streams setpoints and waits until they have played; with `resonance` (its frequency,
    /// Hz, and damping ratio) shaped first for the stage's resonance
    /// (`twinstack_identify::preview::ResonancePreview::shape_stream`). With `more`, more
    /// setpoints follow in the next call: the stream plays on without its end, and the next
    /// `stream` queues its setpoints behind these (`StreamOptions::more`, `continues`). With
    /// `start_on` `"rising"` or `"falling"` the queue is primed and the trigger input armed:
    /// the stream starts on that edge (a camera's frame), waited for at most `edge_timeout`
    /// seconds (then `TimeoutError`, the input disarmed, the setpoints left queued).
    #[pyo3(signature = (setpoints, rate=None, normalised=false, underrun=None, wait=true, resonance=None, more=false, start_on="now", edge_timeout=60.0))]
    #[allow(clippy::too_many_arguments)] // the Python keyword arguments, one each
    fn stream<'py>(
        &self,
        py: Python<'py>,
        setpoints: &Bound<'py, PyAny>,
        rate: Option<f64>,
        normalised: bool,
        underrun: Option<&str>,
        wait: bool,
        resonance: Option<(f64, f64)>,
        more: bool,
        start_on: &str,
        edge_timeout: f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        let edge = parse_start_on(start_on)?;
        let edge_wait = seconds(edge_timeout, "edge_timeout")?;
        if more && wait {
            return Err(PyValueError::new_err(
                "more=True: the stream plays on after this call and cannot be waited for: pass wait=False (and wait on the last part)",
            ));
        }
        let values = vector(py, setpoints, "setpoints")?;
        let underrun = match underrun {
            None => None,
            Some("hold") => Some(UnderrunPolicy::Hold),
            Some("ramp-to-bias") | Some("ramp_to_bias") => Some(UnderrunPolicy::RampToBias),
            Some(other) => {
                return Err(PyValueError::new_err(format!(
                    "underrun {other:?}: expected \"hold\" or \"ramp-to-bias\""
                )))
            }
        };
        let (samples, divider, tick_rate) =
            self.stream_samples(py, &values, rate, normalised, resonance)?;
        let options = StreamOptions {
            divider,
            underrun,
            tick_rate_hz: tick_rate,
            drain: wait,
            more,
            continues: self.stream_open.load(Ordering::Relaxed),
            start_on: (edge != TriggerEdge::Off).then_some(StartOn {
                edge,
                pulse_ticks: 2,
                wait: edge_wait,
            }),
            ..StreamOptions::default()
        };
        // Left open only by a part that was sent whole.
        self.stream_open.store(false, Ordering::Relaxed);
        let report = self.with_py(py, |client| {
            // Ctrl-C: asked of the interpreter every SIGNAL_CHECK, with its lock taken back
            // for the question only.
            let mut interrupt: Option<PyErr> = None;
            let mut last = Instant::now();
            let r = stream_setpoints_until(
                client,
                &samples,
                &options,
                |_| {},
                || {
                    if last.elapsed() < SIGNAL_CHECK {
                        return false;
                    }
                    last = Instant::now();
                    signal_taken(&mut interrupt).is_break()
                },
            );
            match r {
                Ok(report) => Ok(report),
                Err(e) => {
                    if let Some(signal) = interrupt {
                        // Tell the board to stop; the signal's exception goes up.
                        let _ = client.stream(StreamControl::Stop);
                        return Err(signal);
                    }
                    Err(Python::attach(|py| {
                        let message = e.to_string();
                        match e.source {
                            LinkError::Nack { .. } => {
                                let err = link_error(py, e.source);
                                let _ = err.value(py).setattr("accepted", e.accepted);
                                err
                            }
                            LinkError::Timeout { .. } | LinkError::NoEdge { .. } => {
                                PyTimeoutError::new_err(message)
                            }
                            LinkError::Io(_) => PyConnectionError::new_err(message),
                            _ => PyRuntimeError::new_err(message),
                        }
                    }))
                }
            }
        })?;
        self.stream_open.store(more, Ordering::Relaxed);
        let end = report.drained.unwrap_or(report.after_last_batch);
        let d = PyDict::new(py);
        d.set_item("accepted", report.accepted)?;
        d.set_item("divider", divider)?;
        d.set_item("batches", report.batches)?;
        d.set_item("resent_batches", report.resent_batches)?;
        d.set_item("refused_and_retried", report.nacks.len())?;
        d.set_item("underruns", report.underruns_during_stream())?;
        d.set_item("underran", report.underran())?;
        d.set_item(
            "seconds",
            end.ticks.wrapping_sub(report.before.ticks) as f64 / tick_rate,
        )?;
        d.set_item("drained", report.drained.is_some())?;
        d.set_item("bytes_sent", report.link.bytes_sent)?;
        Ok(d)
    }

    /// Runs a TTL-stepped sequence: `positions` loaded through the setpoint queue (topped up
    /// as edges consume it), one per edge on the trigger input; returns the counts.
    #[pyo3(signature = (positions, window=0.005, settle_ticks=25, edge="rising", normalised=false, mode=None, idle=5.0))]
    #[allow(clippy::too_many_arguments)]
    fn sequence<'py>(
        &self,
        py: Python<'py>,
        positions: &Bound<'py, PyAny>,
        window: f32,
        settle_ticks: u16,
        edge: &str,
        normalised: bool,
        mode: Option<&str>,
        idle: f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        let values = vector(py, positions, "positions")?;
        let edge = match edge {
            "rising" => TriggerEdge::Rising,
            "falling" => TriggerEdge::Falling,
            other => {
                return Err(PyValueError::new_err(format!(
                    "edge {other:?}: expected \"rising\" or \"falling\""
                )))
            }
        };
        let config = SequenceConfig {
            edge,
            window,
            settle_ticks,
        };
        config
            .check()
            .map_err(|r| PyValueError::new_err(format!("{} {}", r.field, r.rule)))?;
        let mode = mode.map(parse_mode).transpose()?;
        let idle = seconds(idle, "idle")?;
        let settings = self.with(py, |c| c.read_params())?;
        let samples = wire_values(&values, normalised, &settings, "positions")?;
        let options = SequenceOptions {
            config,
            idle,
            poll: Duration::from_millis(20),
            timing: true,
        };
        let report = self.with_py(py, |client| {
            let err = |e: LinkError| Python::attach(|py| link_error(py, e));
            if let Some(m) = mode {
                client.set_mode(m).map_err(err)?;
            }
            // Ctrl-C (a signal) stops the wait at the next poll, the sequence disarmed.
            let mut interrupt = None;
            let run = run_sequence(client, &samples, &options, |_| signal_taken(&mut interrupt));
            run.map_err(|e| match e {
                SequenceError::Link(l) => err(l),
                SequenceError::Stopped { .. } if interrupt.is_some() => {
                    interrupt.take().expect("checked")
                }
                other => PyRuntimeError::new_err(other.to_string()),
            })
        })?;
        let d = PyDict::new(py);
        d.set_item("positions", samples.len())?;
        d.set_item("sent", report.sent)?;
        d.set_item("steps", report.status.steps)?;
        d.set_item("early", report.status.early)?;
        d.set_item("missed", report.status.missed)?;
        d.set_item("complete", report.complete)?;
        d.set_item("ticks_to_motion", report.timing.map(|t| t.ticks_to_motion))?;
        Ok(d)
    }

    /// Makes the board's analog setpoint input the setpoint source: the input's span (0 V to
    /// 3.3 V at the pin) times `gain` plus `offset`, normalised displacement; filtered by a
    /// one-pole low-pass at `corner_hz` (none: unfiltered); below `lost_below` or above
    /// `over_above` (fractions of the span) the input is faulty and the output holds
    /// (`on_fault="hold"`) or ramps to rest (`"ramp-to-rest"`) at `rate` (normalised per
    /// second, also the rate it walks back at). Settings checked here first: a refusal raises
    /// `ValueError` naming the field, nothing sent.
    #[pyo3(signature = (gain=2.0, offset=-1.0, corner_hz=None, lost_below=0.0, over_above=1.0, on_fault="hold", rate=10.0))]
    #[allow(clippy::too_many_arguments)]
    fn analog(
        &self,
        py: Python<'_>,
        gain: f32,
        offset: f32,
        corner_hz: Option<f32>,
        lost_below: f32,
        over_above: f32,
        on_fault: &str,
        rate: f32,
    ) -> PyResult<()> {
        let on_fault = match on_fault {
            "hold" => OnFault::Hold,
            "ramp-to-rest" => OnFault::RampToRest,
            other => {
                return Err(PyValueError::new_err(format!(
                    "on_fault {other:?}: expected \"hold\" or \"ramp-to-rest\""
                )))
            }
        };
        let config = AnalogInputConfig {
            gain,
            offset,
            corner_hz,
            lost_below,
            over_above,
            on_fault,
            rate,
            start_at_boot: false,
        };
        let tick_rate = self.with(py, |c| c.status())?.tick_rate_hz as f64;
        config
            .check(tick_rate)
            .map_err(|r| PyValueError::new_err(format!("refused: {r}; nothing was sent")))?;
        self.with(py, |c| {
            c.expect_ack(&Request::Analog(AnalogRequest::Start(config)))
                .map(drop)
        })
    }

    /// The analog input's state: `running`, `lost`, `over_range`, `faults`, `reading`
    /// (fraction of the span) and `setpoint` (normalised).
    fn analog_status<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let s = self.with(py, |c| c.analog_status())?;
        json_to_py(py, &board_requests::analog_status_json(&s))
    }

    /// Stops the setpoint stream, the waveform or the analog input; the output holds where
    /// it is.
    fn stop(&self, py: Python<'_>) -> PyResult<()> {
        self.with(py, |c| c.stream(StreamControl::Stop))
    }

    /// Starts the board's waveform generator (normalised units).
    #[pyo3(signature = (amplitude, frequency, shape="sine", offset=0.0))]
    fn waveform(
        &self,
        py: Python<'_>,
        amplitude: f64,
        frequency: f64,
        shape: &str,
        offset: f64,
    ) -> PyResult<()> {
        let shape = match shape.to_ascii_lowercase().as_str() {
            "sine" => WaveShape::Sine,
            "triangle" => WaveShape::Triangle,
            other => {
                return Err(PyValueError::new_err(format!(
                    "shape {other:?}: expected \"sine\" or \"triangle\""
                )))
            }
        };
        let w = board_requests::waveform(shape, offset, amplitude, frequency, None)
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        self.with(py, |c| c.waveform(w))
    }

    /// Arms a multi-signal capture without waiting for it (see `fetch`).
    #[pyo3(signature = (signals, samples, trigger="now", pre=0, decimation=1))]
    fn arm(
        &self,
        py: Python<'_>,
        signals: &Bound<'_, PyAny>,
        samples: u32,
        trigger: &str,
        pre: u32,
        decimation: u16,
    ) -> PyResult<()> {
        let signals = signal_list(signals)?;
        let trigger = parse_trigger(trigger)?;
        let request = board_requests::capture_request(&signals, samples, pre, trigger, decimation)
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        self.with(py, |c| c.arm_capture(request))
    }

    /// Waits for the capture armed before and reads it back in physical units.
    #[pyo3(signature = (timeout=30.0))]
    fn fetch<'py>(&self, py: Python<'py>, timeout: f64) -> PyResult<Bound<'py, PyDict>> {
        self.fetch_dict(py, timeout)
    }

    /// Records several signals at once and returns them in physical units.
    #[pyo3(signature = (signals, samples, trigger="now", pre=0, decimation=1, timeout=30.0))]
    #[allow(clippy::too_many_arguments)]
    fn record<'py>(
        &self,
        py: Python<'py>,
        signals: &Bound<'py, PyAny>,
        samples: u32,
        trigger: &str,
        pre: u32,
        decimation: u16,
        timeout: f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        seconds(timeout, "timeout")?;
        self.arm(py, signals, samples, trigger, pre, decimation)?;
        self.fetch_dict(py, timeout)
    }

    /// Continuous telemetry (`twinstack telemetry`): the board sends `signals` (as `record`'s)
    /// at the rate nearest `rate` samples per second (the tick rate divided by a whole
    /// number) while it runs whatever it runs, for `seconds` of samples; then telemetry stops
    /// and its end frame is awaited. Returns a dict of float64 arrays in physical units, `t`
    /// (s from the first sample; a gap shows as a jump) and one per signal, with `rate_hz`,
    /// `decimation`, `samples` (received), `missing` (taken by the board, not received),
    /// `lost_on_board` (of them, dropped on the board: its queue full), `frames_damaged` and
    /// `complete` (nothing missing, the end frame came). Anything missing also raises a
    /// `RuntimeWarning` saying how much and why. A rate the board's link cannot carry for
    /// that many signals raises `BoardError` naming the most it can; a rate beyond the tick
    /// rate, or `seconds` not positive, `ValueError`.
    #[pyo3(signature = (signals, rate=10000.0, seconds=1.0))]
    fn telemetry<'py>(
        &self,
        py: Python<'py>,
        signals: &Bound<'py, PyAny>,
        rate: f64,
        seconds: f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        self::seconds(seconds, "seconds")?;
        let list = signal_list(signals)?;
        let mask = capture::signal_mask(&list)
            .map_err(|e| PyValueError::new_err(format!("signals {list:?}: {e}")))?;
        let (recording, run, ended) = self.with_py(py, |client| {
            let fail = |e: RunError| Python::attach(|py| run_error(py, e));
            let mut run = TelemetryRun::start(client, mask, rate).map_err(fail)?;
            let wanted = (seconds * run.rate.rate_hz).ceil() as u64;
            // Ctrl-C (a signal) stops the run at the next frame, its exception raised.
            let mut interrupt = None;
            let collected = run.collect(client, wanted, |_| signal_taken(&mut interrupt));
            if let Err(e) = collected {
                return Err(interrupt.take().unwrap_or_else(|| fail(e)));
            }
            let (recording, ended) = run.finish(client).map_err(fail)?;
            Ok((recording, run, ended))
        })?;
        if let Some(shortfall) = run.shortfall(ended) {
            let warnings = py.import("warnings")?;
            let category = py.get_type::<pyo3::exceptions::PyRuntimeWarning>();
            warnings.call_method1("warn", (format!("telemetry: {shortfall}"), category, 2))?;
        }
        let d = PyDict::new(py);
        d.set_item("t", array(py, recording.t))?;
        for c in recording.columns {
            d.set_item(c.channel.name(), array(py, c.values))?;
        }
        let r = &run.record;
        d.set_item("rate_hz", run.rate.rate_hz)?;
        d.set_item("decimation", run.rate.decimation)?;
        d.set_item("samples", r.samples())?;
        d.set_item("missing", r.missing())?;
        d.set_item("lost_on_board", r.lost_on_board())?;
        d.set_item("frames_damaged", r.frames_missing())?;
        d.set_item("complete", ended && r.missing() == 0)?;
        Ok(d)
    }

    /// Runs a scan pattern generated on the board (`twinstack scan`) with its pixel, line and
    /// frame trigger outputs (pulses of `pulse` ticks; the trigger input off), and reads it
    /// back: `pattern` as `twinstack scan --pattern` takes it
    /// (`"raster:lines=64,pixels=64,turn=40"`, `"lissajous:hz=20,x=3,y=2"`,
    /// `"spiral:hz=200,turns=10"`, with their optional fields), `ticks_per_pixel`, `frames`
    /// (0: endless, stopped once the capture is read). The setpoint and the trigger levels are
    /// captured from the scan's start (its approach, then the frames, as far as the board's
    /// buffer goes) and compared with the library's replay of the pattern. Returns a dict:
    /// `t` (s from the scan's start), `setpoint` (the output unit of the settings in force),
    /// `y` (the replay's slow axis, normalised, for another axis to follow; NaN during the
    /// approach), `pixel`, `line`, `frame` (the outputs' levels, bool arrays), `figures`
    /// (each clock's pulses, jitter and width against the replay, the turnaround-to-line
    /// time, as `twinstack scan --json`), `truncated` (the capture ended before the scan) and
    /// `kind` (the pattern parsed: `"raster"`, `"lissajous"` or `"spiral"`).
    /// `start_on` `"rising"` or `"falling"` arms the trigger input: the scan waits for that
    /// edge (a camera's frame starts it), and `timeout` counts from the request. A pattern the
    /// board would refuse raises `ValueError` naming the field, nothing sent; a scan that
    /// differs from the replay raises `RuntimeError`; no capture within `timeout` seconds
    /// `TimeoutError`.
    #[pyo3(signature = (pattern, ticks_per_pixel=4, frames=1, pulse=2, timeout=60.0, start_on="now"))]
    #[allow(clippy::too_many_arguments)]
    fn scan<'py>(
        &self,
        py: Python<'py>,
        pattern: &str,
        ticks_per_pixel: u16,
        frames: u16,
        pulse: u16,
        timeout: f64,
        start_on: &str,
    ) -> PyResult<Bound<'py, PyDict>> {
        let budget = seconds(timeout, "timeout")?;
        let start_on = parse_start_on(start_on)?;
        let pattern = parse_pattern(pattern)
            .map_err(|e| PyValueError::new_err(format!("pattern {pattern:?}: {e}")))?;
        let kind = pattern_kind(&pattern);
        let request = ScanRequest {
            pattern,
            ticks_per_pixel,
            frames,
            on_trigger: false,
        };
        let run = self.with_py(py, |client| {
            run_scan(client, request, pulse, start_on, budget).map_err(|e| {
                Python::attach(|py| match e {
                    ScanRunError::Link(l) => link_error(py, l),
                    ScanRunError::Capture(CaptureError::Link(l)) => link_error(py, l),
                    e @ ScanRunError::Capture(CaptureError::NotDone { .. }) => {
                        PyTimeoutError::new_err(e.to_string())
                    }
                    e @ ScanRunError::Refused(_) => PyValueError::new_err(e.to_string()),
                    e => PyRuntimeError::new_err(e.to_string()),
                })
            })
        })?;
        let f = &run.figures;
        if f.x_mismatches > 0 || f.trigger_mismatches > 0 {
            return Err(PyRuntimeError::new_err(format!(
                "the board's scan differs from the library's replay: {} setpoints, {} trigger ticks",
                f.x_mismatches, f.trigger_mismatches
            )));
        }
        let d = PyDict::new(py);
        let setpoint = run
            .recording
            .column(Channel::Setpoint)
            .map(|c| c.values.clone())
            .unwrap_or_default();
        d.set_item("t", array(py, run.recording.t.clone()))?;
        d.set_item("setpoint", array(py, setpoint))?;
        let y = run
            .replay
            .iter()
            .map(|r| r.map_or(f64::NAN, |(_, y)| y))
            .collect();
        d.set_item("y", array(py, y))?;
        for (name, bit) in [("pixel", PIXEL), ("line", LINE), ("frame", FRAME)] {
            let levels: Vec<bool> = run.triggers.iter().map(|&t| t as u8 & bit != 0).collect();
            d.set_item(name, PyArray1::from_vec(py, levels))?;
        }
        let figures = serde_json::to_value(f)
            .map_err(|e| PyRuntimeError::new_err(format!("the scan's figures: {e}")))?;
        d.set_item("figures", json_to_py(py, &figures)?)?;
        d.set_item("truncated", run.truncated())?;
        d.set_item("kind", kind)?;
        Ok(d)
    }

    /// Starts the board's learning feedforward (the book's chapter "Learning") for a periodic motion
    /// of `period_ticks` ticks (2 … 512; a whole number of the motion's cycles: 200 for a
    /// 750 Hz sine at 50 kHz): it learns, period by period, the correction that takes the
    /// error its sensor sees out of the motion, and plays it on the feedforward. `gain`
    /// (0 < L ≤ 1.5), `cutoff_hz` (the robustness filter's corner, below half the tick rate),
    /// `lead_ticks` (0 … 64, below the period), `limit` (the largest correction, a fraction of
    /// the drive range); `reset` empties the table first (else learning goes on from the table
    /// in force). Settings checked here first: a refusal raises `ValueError` naming the
    /// `learning.*` field, nothing sent; a board without a sensor refuses to learn
    /// (`BoardError`).
    #[pyo3(signature = (period_ticks, gain=0.3, cutoff_hz=3000.0, lead_ticks=1, limit=0.25, reset=true))]
    #[allow(clippy::too_many_arguments)]
    fn learn(
        &self,
        py: Python<'_>,
        period_ticks: u16,
        gain: f64,
        cutoff_hz: f64,
        lead_ticks: u16,
        limit: f64,
        reset: bool,
    ) -> PyResult<()> {
        let settings = LearnSettings {
            period_ticks,
            gain,
            cutoff_hz,
            lead_ticks,
            limit,
        };
        let tick_rate = self.with(py, |c| c.status())?.tick_rate_hz as f64;
        settings
            .build(tick_rate)
            .map_err(|r| PyValueError::new_err(format!("refused: {r}; nothing was sent")))?;
        self.with(py, |c| {
            learning::configure(c, settings)?;
            if reset {
                learning::reset(c)?;
            }
            learning::set_state(c, LearnState::Learning)
        })
    }

    /// Switches the learning: `"learning"` (its sensor's error updates the table each
    /// period), `"frozen"` (the table plays as it is; no sensor needed) or `"off"` (nothing
    /// plays; the table is kept).
    fn learn_state(&self, py: Python<'_>, state: &str) -> PyResult<()> {
        let state = match state {
            "learning" => LearnState::Learning,
            "frozen" => LearnState::Frozen,
            "off" => LearnState::Off,
            other => {
                return Err(PyValueError::new_err(format!(
                    "state {other:?}: expected \"learning\", \"frozen\" or \"off\""
                )))
            }
        };
        self.with(py, |c| learning::set_state(c, state))
    }

    /// The learning's state: `state`, `period_ticks`, `periods` (completed since it was
    /// configured), `updates` (tables posted), `missed` (periods its task could not serve),
    /// and the last period's error as its sensor saw it, `error_max` and `error_rms`, in the
    /// output unit of the settings in force.
    fn learn_status<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let (s, settings) = self.with(py, |c| Ok((learning::status(c)?, c.read_params()?)))?;
        let half = settings.ranges.output_half_span();
        let d = PyDict::new(py);
        let state = match s.state {
            LearnState::Off => "off",
            LearnState::Learning => "learning",
            LearnState::Frozen => "frozen",
        };
        d.set_item("state", state)?;
        d.set_item("period_ticks", s.period_ticks)?;
        d.set_item("periods", s.periods)?;
        d.set_item("updates", s.updates)?;
        d.set_item("missed", s.missed)?;
        d.set_item("error_max", signal_to_f64(s.last.max) * half)?;
        d.set_item("error_rms", signal_to_f64(s.last.rms) * half)?;
        Ok(d)
    }

    /// The learned table playing now: one correction a tick of the period, normalised drive
    /// (±1 is the drive range's half span), to keep with the motion it was learned on and
    /// play again with `learn_load_table`.
    fn learn_table<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let table = self.with_py(py, |c| {
            learning::read_table(c).map_err(|e| Python::attach(|py| table_error(py, e)))
        })?;
        Ok(array(py, table.into_iter().map(signal_to_f64).collect()))
    }

    /// Plays `table` (as `learn_table` returns it: one normalised correction a tick of the
    /// configured period) from the next period boundary, in the learning's state (frozen: as
    /// it is; learning: as the start of further learning); the board limits each value to the
    /// configured limit. A table of another length, or a value that is not finite or beyond
    /// ±2, raises `ValueError` naming its position, nothing sent.
    fn learn_load_table(&self, py: Python<'_>, table: &Bound<'_, PyAny>) -> PyResult<()> {
        let values = vector(py, table, "table")?;
        let mut q = Vec::with_capacity(values.len());
        for (i, v) in values.iter().enumerate() {
            if !(v.is_finite() && v.abs() < 2.0) {
                return Err(PyValueError::new_err(format!(
                    "table[{i}] = {v}: a correction is a finite normalised drive within ±2"
                )));
            }
            q.push(signal_from_f64(*v));
        }
        self.with_py(py, |c| {
            learning::write_table(c, &q).map_err(|e| Python::attach(|py| table_error(py, e)))
        })
    }

    /// Homes the dual-actuated stage's coarse axis (a board with one: the dual-stage images,
    /// `twinstack virtual-board --dual-stage`): it seeks its home switch and sets its travel
    /// around it, clearing a latched fault. With `wait`, returns the status once the homing
    /// has ended (at most `timeout` seconds, else `TimeoutError`), and raises `RuntimeError`
    /// naming the faults if it did not home; without, returns the status at once.
    #[pyo3(signature = (wait=true, timeout=120.0))]
    fn coarse_home<'py>(
        &self,
        py: Python<'py>,
        wait: bool,
        timeout: f64,
    ) -> PyResult<Bound<'py, PyAny>> {
        self.coarse_command(py, &Request::CoarseHome, wait, timeout)
    }

    /// Moves the coarse axis to `to_mm` (from the home reference; a homed axis, the target
    /// within the travel) at `speed` mm/s and `accel` mm/s² (at most the stage's). The board
    /// refuses what it cannot do (`BoardError` naming the field and the limit). With `wait`,
    /// returns the status once the move has ended (`RuntimeError` naming the faults if it
    /// ended in one).
    #[pyo3(signature = (to_mm, speed=10.0, accel=200.0, wait=true, timeout=120.0))]
    fn coarse_move<'py>(
        &self,
        py: Python<'py>,
        to_mm: f64,
        speed: f64,
        accel: f64,
        wait: bool,
        timeout: f64,
    ) -> PyResult<Bound<'py, PyAny>> {
        let request = Request::CoarseMove(CoarseMove {
            target_mm: to_mm,
            velocity_mm_s: speed,
            acceleration_mm_s2: accel,
        });
        self.coarse_command(py, &request, wait, timeout)
    }

    /// Jogs the coarse axis at `speed` mm/s (positive toward the upper limit) until
    /// `coarse_stop`, or the soft travel limit.
    fn coarse_jog(&self, py: Python<'_>, speed: f64) -> PyResult<()> {
        self.with(py, |c| {
            c.coarse(&Request::CoarseJog {
                velocity_mm_s: speed,
            })
        })
    }

    /// Stops the coarse axis: it brakes at the move's acceleration, no step lost, still homed.
    fn coarse_stop(&self, py: Python<'_>) -> PyResult<()> {
        self.with(py, |c| c.coarse(&Request::CoarseStop))
    }

    /// Hands the piezo back from the coarse axis (at rest) to its own sources: `stream`,
    /// `waveform`, `scan`, `sequence` and the analog input play on it while the carriage
    /// holds. The next `coarse_home`, `coarse_move` or `coarse_jog` takes it again (refused,
    /// `BoardError` busy, while one of those sources runs); `coarse_status()["piezo"]` says
    /// which owns it.
    fn coarse_release(&self, py: Python<'_>) -> PyResult<()> {
        self.with(py, |c| c.coarse(&Request::CoarseRelease))
    }

    /// The coarse axis's status: `state` (`unhomed`, `homing`, `idle`, `moving`, `jogging`,
    /// `stopping`, `fault`), `homed`, `position_mm`, `setpoint_mm`, `following_error_um`,
    /// `faults` and `switches` (lists of names), `fine_setpoint` (the piezo's, normalised),
    /// `ticks`, and `piezo`: `"coarse"` while the piezo follows the coarse axis, `"own"` once
    /// `coarse_release` handed it back. A board without a coarse axis raises `BoardError`.
    fn coarse_status<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let (s, board) = self.with(py, |c| Ok((c.coarse_status()?, c.status()?)))?;
        let mut v = board_requests::coarse_status_json(&s);
        v["piezo"] = if board.has(twinstack::protocol::messages::StatusReport::COARSE) {
            "coarse"
        } else {
            "own"
        }
        .into();
        json_to_py(py, &v)
    }

    /// Calibrates the stage behind the board in one call (`twinstack calibrate`): excites it
    /// with the identification excitation streamed in bypass (full-range cycles, decaying
    /// minor loops, nested off-centre loops, a multisine),
    /// records drive and sensor, identifies the best model of the family (or `model`), loads
    /// it, verifies by tracking a test trajectory before (bypass) and after (open loop), and
    /// stores it to flash unless `store` is false. Returns a dict: `params` (a `Params`, the
    /// file `twinstack calibrate` writes), `model`, `reason`, `held_out` / `before` / `after`
    /// (`max_pct`, `rms_pct`), `stored`, `clamped`, `excitation_underran` (the excitation's
    /// stream found the queue empty: identified on the drive as applied), `resonance` (the
    /// stage's resonance measured after the excitation as `tune` measures it,
    /// `(frequency_hz, damping)`, also in `params.resonance`; `None` with `resonance=False`
    /// or where no resonance fitted the response, then `resonance_not_fitted` says why).
    /// Board refusals raise `BoardError`; a stage
    /// that cannot be calibrated (no sensor, a sensor that does not follow the drive, a fit
    /// that does not fit) raises `RuntimeError` saying which. `fastest_hz` names the fastest
    /// motion the stage will run (`calibrate --fastest-hz`): the excitation sweeps up to it
    /// before its multisine; one the board would not stream and record with 20 samples a
    /// cycle raises `RuntimeError` naming `fastest_hz` before anything moves.
    #[pyo3(signature = (store=true, clamp=false, model=None, resonance=true, fastest_hz=None))]
    fn calibrate<'py>(
        &self,
        py: Python<'py>,
        store: bool,
        clamp: bool,
        model: Option<&str>,
        resonance: bool,
        fastest_hz: Option<f64>,
    ) -> PyResult<Bound<'py, PyAny>> {
        use twinstack_identify::calibrate::{
            calibrate, CalibrateError, CalibrateOptions, ResonanceOutcome,
        };
        use twinstack_identify::identification::run::{parse_model, ModelChoice};
        let model = match model
            .map(parse_model)
            .transpose()
            .map_err(PyValueError::new_err)?
        {
            None | Some(ModelChoice::Auto) => None,
            Some(ModelChoice::Only(kind)) => Some(kind),
        };
        let options = CalibrateOptions {
            model,
            clamp,
            store: store.then_some(twinstack::config::settings::Mode::Bypass),
            resonance,
            fastest_hz,
            ..CalibrateOptions::default()
        };
        let report = self.with_py(py, |client| {
            calibrate(client, &options, |_| {}).map_err(|e| match e {
                CalibrateError::Link { source, .. } => Python::attach(|py| link_error(py, source)),
                other => PyRuntimeError::new_err(other.to_string()),
            })
        })?;
        let (file, stage) = ParamFile::parse(Path::new("<calibrate>"), &report.file.to_json())
            .map_err(param_file_error)?;
        let figures = |max: f64, rms: f64| serde_json::json!({"max_pct": max, "rms_pct": rms});
        let out = json_to_py(
            py,
            &serde_json::json!({
                "model": report.model,
                "reason": report.reason,
                "held_out": figures(report.held_out.max_pct, report.held_out.rms_pct),
                "before": figures(report.before.max_pct, report.before.rms_pct),
                "after": figures(report.after.max_pct, report.after.rms_pct),
                "stored": report.stored.is_some(),
                "clamped": report.clamped,
                "excitation_underran": report.excitation_underran,
                "resonance_not_fitted": match &report.resonance {
                    ResonanceOutcome::NotFitted(why) => Some(why.as_str()),
                    _ => None,
                },
            }),
        )?;
        // A tuple, as `Params.resonance` gives it.
        out.set_item(
            "resonance",
            file.resonance.map(|r| (r.frequency_hz, r.damping)),
        )?;
        out.set_item("params", Params::from_file(file, stage))?;
        Ok(out)
    }

    /// Tunes the board's feedback in one call (`twinstack tune`): measures the stage's
    /// frequency response with the board's generator and recorder (in bypass; the mode is
    /// restored), fits the resonance and the loop's delay, and designs the PI gains and the
    /// notch for at least `phase_margin` degrees and `gain_margin` dB (the fit's gain 1.4
    /// times higher too, and at most 0.5 % ringing of a step on the model); with `kp` and `ki`
    /// (and `notch_hz`, `notch_q`, `notch_depth`, `limit`) it checks that gain set instead.
    /// `load` loads the result (the other settings kept). Returns what `twinstack tune --json`
    /// prints: `rate_hz`, `points` (`frequency_hz`, `magnitude_db`, `phase_deg`), `fit`
    /// (`gain`, `resonance_hz`, `zeta`, `delay_ticks`, `rms_db`, `rms_deg`), `goals`,
    /// `feedback` (the settings chosen or checked), `figures` (their margins, bandwidths,
    /// ringing on the fit), `shaping`, `before` (the board's gains before and their verdict),
    /// `loaded`, `board_timing`. Margins that are not finite or negative, `kp` without `ki`
    /// (or the reverse), `notch_hz` without them, or a gain set the board would refuse at its
    /// rate raise `ValueError` naming it, before anything moves; a checked set the fitted
    /// model says is unstable or short of the margins `ValueError` (nothing loaded); no gains
    /// meeting the margins, or a response that does not fit, `RuntimeError`.
    ///
    /// `progress`, a callable, is given each point as it is measured (the coarse sweep, then
    /// the points about the resonance), as a dict: `frequency_hz`, `magnitude_db`,
    /// `phase_deg` (as in `points`), `drive_volts` (the drive's amplitude, left-stack volts)
    /// and `sensor_amplitude` (the sensor's, output unit). An exception it raises stops the
    /// sweep and goes up; Ctrl-C stops it too (`KeyboardInterrupt`). After a stop the
    /// generator is stopped, the board's mode restored and nothing loaded.
    #[pyo3(signature = (phase_margin=45.0, gain_margin=6.0, load=false, kp=None, ki=None, notch_hz=None, notch_q=2.0, notch_depth=0.0, limit=0.25, progress=None))]
    #[allow(clippy::too_many_arguments)] // the Python keyword arguments, one each
    fn tune<'py>(
        &self,
        py: Python<'py>,
        phase_margin: f64,
        gain_margin: f64,
        load: bool,
        kp: Option<f64>,
        ki: Option<f64>,
        notch_hz: Option<f64>,
        notch_q: f64,
        notch_depth: f64,
        limit: f64,
        progress: Option<Py<PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        use twinstack_identify::tune::{tune, SweepEvent, TuneError, TuneOptions};
        if let Some(p) = &progress {
            if !p.bind(py).is_callable() {
                return Err(PyTypeError::new_err(format!(
                    "progress {}: must be a callable taking one point (a dict), or None; nothing was measured",
                    p.bind(py).get_type().name()?
                )));
            }
        }
        for (name, v, unit) in [
            ("phase_margin", phase_margin, "degrees"),
            ("gain_margin", gain_margin, "dB"),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(PyValueError::new_err(format!(
                    "{name} {v}: must be a finite number of {unit}, at least 0; nothing was measured"
                )));
            }
        }
        let check = match (kp, ki) {
            (Some(kp), Some(ki)) => Some(FeedbackSettings {
                notch: notch_hz.map(|frequency_hz| NotchDesign {
                    frequency_hz,
                    q: notch_q,
                    depth: notch_depth,
                }),
                ..FeedbackSettings::pi(kp, ki, limit)
            }),
            (None, None) => {
                if let Some(f) = notch_hz {
                    return Err(PyValueError::new_err(format!(
                        "notch_hz {f}: the notch of a gain set to check, given with kp and ki; nothing was measured"
                    )));
                }
                None
            }
            _ => {
                return Err(PyValueError::new_err(
                    "kp and ki: give both (a gain set to check) or neither (a design); nothing was measured",
                ))
            }
        };
        // A gain set the board would refuse at its rate is refused before the sweep.
        if let Some(settings) = &check {
            let rate = self.with(py, |c| c.status())?.tick_rate_hz as f64;
            settings.build(rate).map_err(|r| {
                PyValueError::new_err(format!("refused at {rate} Hz: {r}; nothing was measured"))
            })?;
        }
        let options = TuneOptions {
            phase_margin_deg: phase_margin,
            gain_margin_db: gain_margin,
            check,
            load,
            ..TuneOptions::default()
        };
        let report = self.with_py(py, |client| {
            // The caller's `progress` with each point, and Ctrl-C asked of the interpreter every
            // SIGNAL_CHECK (its lock taken back for the call or the question only): an
            // exception from either stops the sweep, and goes up.
            let mut raised: Option<PyErr> = None;
            let mut last = Instant::now();
            let r = tune(client, &options, |event| {
                if let (SweepEvent::Point(p), Some(callable)) = (event, &progress) {
                    let called = Python::attach(|py| -> PyResult<()> {
                        let d = PyDict::new(py);
                        d.set_item("frequency_hz", p.frequency_hz)?;
                        d.set_item("magnitude_db", p.magnitude_db())?;
                        d.set_item("phase_deg", p.phase_deg())?;
                        d.set_item("drive_volts", p.drive_volts)?;
                        d.set_item("sensor_amplitude", p.sensor_amplitude)?;
                        callable.call1(py, (d,))?;
                        Ok(())
                    });
                    if let Err(e) = called {
                        raised = Some(e);
                        return ControlFlow::Break(());
                    }
                }
                if last.elapsed() < SIGNAL_CHECK {
                    return ControlFlow::Continue(());
                }
                last = Instant::now();
                signal_taken(&mut raised)
            });
            let report = r.map_err(|e| match (e, raised) {
                // Stopped by the caller: the generator stopped, the mode restored, nothing
                // loaded; the caller's exception (or the signal's) goes up.
                (TuneError::Stopped { .. }, Some(raised)) => raised,
                (e @ TuneError::Refused(_), _) => PyValueError::new_err(format!(
                    "kp {}, ki {}: {e}",
                    kp.unwrap_or_default(),
                    ki.unwrap_or_default()
                )),
                (e, _) => Python::attach(|py| tune_error(py, e)),
            })?;
            Ok(report.to_json())
        })?;
        json_to_py(py, &report)
    }

    /// Writes the settings in force to the board's flash, to boot in `boot_mode`.
    #[pyo3(signature = (boot_mode="bypass"))]
    fn store(&self, py: Python<'_>, boot_mode: &str) -> PyResult<()> {
        let m = parse_mode(boot_mode)?;
        self.with(py, |c| c.store_params(m))
    }

    /// Reloads the settings stored in the board's flash.
    fn recall(&self, py: Python<'_>) -> PyResult<()> {
        self.with(py, |c| c.recall_params())
    }

    /// Closes the link (a `"sim"` board is gone with it). Further calls raise.
    fn close(&self) -> PyResult<()> {
        let mut guard = self
            .client
            .try_lock()
            .map_err(|_| PyRuntimeError::new_err("the board is in use by another thread"))?;
        guard.take();
        Ok(())
    }

    /// The board itself (`with Board(port) as board:`).
    fn __enter__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    /// Closes the board at the end of a `with` block.
    #[pyo3(signature = (*_args))]
    fn __exit__(&self, _args: &Bound<'_, pyo3::types::PyTuple>) -> PyResult<bool> {
        self.close()?;
        Ok(false)
    }

    /// `Board("port")`.
    fn __repr__(&self) -> String {
        format!("Board({:?})", self.port)
    }
}

/// Every settings path with what it holds, as ``(path, kind)`` pairs (``twinstack settings
/// --schema``): traced from the settings type, so it lists exactly what the board takes.
#[pyfunction]
pub(crate) fn settings_schema() -> Vec<(String, String)> {
    settings_path::schema()
        .into_iter()
        .map(|e| (e.path, e.kind))
        .collect()
}
