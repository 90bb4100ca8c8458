//! `twinstack view --port P [--listen 127.0.0.1:8080] [--signals …] [--rate 2000] [--tune
//! tune.json] [--calibration cal.json]`: a live view of the board in the browser. Serves a
//! local web page (plain HTML and JavaScript drawn on `<canvas>`, nothing fetched from the
//! internet) that plots the board's telemetry as it arrives — setpoint, sensor, error and
//! both stacks by default — shows its status and the link's counters, switches the mode,
//! starts and stops the waveform generator and a scan, and draws the last tune's Bode plot
//! (`twinstack tune --json > tune.json`) and the calibration's ranking (`twinstack calibrate
//! --json > cal.json`). Works against any `--port`: the simulated board (paced to the wall
//! clock), a virtual board, the emulator, a real board.
//!
//! One thread owns the board link: it receives telemetry in 20 ms steps, asks the status
//! every 250 ms and carries out the page's commands between two steps. Telemetry reaches the
//! page over Server-Sent Events (`/events`) in physical units, one message per step with the
//! index of its first sample, so the page counts what it received against what the board
//! produced: nothing is dropped in between without the page showing it (a page that falls
//! more than [`BACKLOG`] messages behind is told how many it missed).
//!
//! The page's commands are HTTP POSTs of JSON (`/api/mode`, `/api/waveform`, `/api/scan`,
//! `/api/stop`, `/api/telemetry`); a refusal by the board comes back with its field and
//! limit, as on the command line. The server binds to 127.0.0.1 unless told otherwise: anyone
//! who can reach its port can drive the stage.

use super::board_link::{connect, BoardClient, PortArgs};
use anyhow::{bail, Context};
use serde_json::{json, Value};
use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{self, Receiver, Sender, SyncSender, TrySendError};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};
use twinstack::protocol::messages::{
    Request, ScanRequest, StreamControl, TelemetryFrame, TriggerConfig, TriggerEdge, WaveShape,
};
use twinstack::services::recorder::Channel;
use twinstack_link::board_requests;
use twinstack_link::capture::signal_mask;
use twinstack_link::scan_timing::parse_pattern;
use twinstack_link::telemetry::TelemetryRecord;

/// Messages the server keeps for a page that is behind (at 20 ms each, 40 s).
pub const BACKLOG: usize = 2000;
/// How long the board thread receives telemetry between two looks at the page's commands.
const STEP: Duration = Duration::from_millis(20);
/// How often the status is asked.
const STATUS_EVERY: Duration = Duration::from_millis(250);
/// The largest request head and body the server reads.
const MAX_HEAD: usize = 16 * 1024;
const MAX_BODY: usize = 4 * 1024;
/// Commands from the page waiting for the board at most: one more is refused at once (503),
/// not queued without end.
const COMMAND_QUEUE: usize = 8;
/// How long a command's request waits for the board's answer; a command still queued then
/// is not carried out.
const COMMAND_TIMEOUT: Duration = Duration::from_secs(10);
/// A command from the page, where its answer goes, and when its request stops waiting.
type Queued = (Command, Sender<Reply>, Instant);

const INDEX_HTML: &str = include_str!("../../assets/view/index.html");
const VIEW_JS: &str = include_str!("../../assets/view/view.js");

/// Arguments of `view`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// Address to serve the page on (`127.0.0.1:0`: any free port, printed).
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub listen: String,
    /// Telemetry signals, comma-separated: setpoint, left, right, sensor, estimate, error.
    #[arg(long, default_value = "setpoint,sensor,error,left,right")]
    pub signals: String,
    /// Samples per second of each signal (the board's tick rate / a whole number).
    #[arg(long, default_value_t = 2000.0)]
    pub rate: f64,
    /// The last tune's figures (`twinstack tune --json > FILE`), for the Bode plot.
    #[arg(long)]
    pub tune: Option<PathBuf>,
    /// The calibration's figures (`twinstack calibrate --json > FILE`), for the ranking.
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// Serve for this many seconds, then stop telemetry and exit (default: until killed).
    #[arg(long, value_parser = super::parse_positive_seconds)]
    pub duration: Option<f64>,
}

/// A command from the page to the board thread, with where its answer goes.
enum Command {
    Mode(String),
    Waveform(Value),
    Scan(Value),
    Stop,
    Telemetry(bool),
}

type Reply = Result<String, String>;

/// What the page is sent: telemetry and status messages, numbered, and the latest status.
#[derive(Default)]
struct Hub {
    /// `(number, SSE text)`, oldest first, at most [`BACKLOG`].
    messages: VecDeque<(u64, Arc<String>)>,
    next: u64,
    /// The latest status event (sent first to a page that connects).
    status: Option<Arc<String>>,
    /// The run's description (sent first to a page that connects).
    hello: Option<Arc<String>>,
    closed: bool,
}

struct Shared {
    hub: Mutex<Hub>,
    changed: Condvar,
    stop: AtomicBool,
}

impl Shared {
    fn publish(&self, event: &str, data: &Value) {
        let text = Arc::new(format!("event: {event}\ndata: {data}\n\n"));
        let mut hub = self.hub.lock().unwrap_or_else(|e| e.into_inner());
        match event {
            "status" => hub.status = Some(text.clone()),
            "hello" => hub.hello = Some(text.clone()),
            _ => {}
        }
        let n = hub.next;
        hub.next += 1;
        hub.messages.push_back((n, text));
        while hub.messages.len() > BACKLOG {
            hub.messages.pop_front();
        }
        drop(hub);
        self.changed.notify_all();
    }
}

/// The telemetry of one run as the board thread follows it: counts like
/// [`TelemetryRecord`]'s, without keeping the samples.
#[derive(Clone, Copy, Debug, Default)]
struct Counts {
    run: u32,
    frames: u64,
    frames_missing: u64,
    samples: u64,
    /// The next sample index expected (the board's count of samples so far).
    expected: u64,
    lost_on_board: u32,
    produced: Option<u64>,
    next_seq: u16,
}

impl Counts {
    fn json(&self) -> Value {
        json!({
            "run": self.run,
            "frames": self.frames,
            "frames_missing": self.frames_missing,
            "samples": self.samples,
            "expected": self.expected,
            "missing": self.produced.unwrap_or(self.expected).saturating_sub(self.samples),
            "lost_on_board": self.lost_on_board,
            "produced": self.produced,
        })
    }
}

/// The board thread's telemetry run.
struct Telemetry {
    mask: u8,
    decimation: u16,
    rate_hz: f64,
    counts: Counts,
    running: bool,
}

/// Runs `view`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let mask = signal_mask(&args.signals).map_err(|e| anyhow::anyhow!("--signals {e}"))?;
    if let Some(d) = args.duration {
        super::check_positive_seconds("--duration", d)?;
    }
    let read_json = |flag: &str, path: &Option<PathBuf>| -> anyhow::Result<Option<Value>> {
        let Some(path) = path else { return Ok(None) };
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("{flag} {}: cannot read it", path.display()))?;
        let v: Value = serde_json::from_str(&text)
            .with_context(|| format!("{flag} {}: not JSON", path.display()))?;
        Ok(Some(v))
    };
    let tune = read_json("--tune", &args.tune)?;
    if let Some(t) = &tune {
        if !t["points"].is_array() {
            bail!(
                "--tune {}: no \"points\" (write it with `twinstack tune --json`)",
                args.tune
                    .as_ref()
                    .map(|p| p.display().to_string())
                    .unwrap_or_default()
            );
        }
    }
    let calibration = read_json("--calibration", &args.calibration)?;
    if let Some(c) = &calibration {
        if !c["ranking"].is_array() {
            bail!(
                "--calibration {}: no \"ranking\" (write it with `twinstack calibrate --json`)",
                args.calibration
                    .as_ref()
                    .map(|p| p.display().to_string())
                    .unwrap_or_default()
            );
        }
    }
    let mut client = connect(&args.port)?;
    let telemetry = super::telemetry::start(&mut client, &args.signals, args.rate)?;
    let listener = TcpListener::bind(&args.listen)
        .with_context(|| format!("--listen {}: cannot serve there", args.listen))?;
    let addr = listener.local_addr()?;
    println!(
        "view of {} on http://{addr}/ ({} at {} samples/s)",
        args.port.port.as_deref().unwrap_or("?"),
        args.signals,
        telemetry.rate.rate_hz
    );
    let shared = Arc::new(Shared {
        hub: Mutex::new(Hub::default()),
        changed: Condvar::new(),
        stop: AtomicBool::new(false),
    });
    let (commands, inbox) = mpsc::sync_channel::<Queued>(COMMAND_QUEUE);
    let files = Arc::new((tune, calibration));
    {
        let shared = shared.clone();
        let commands = commands.clone();
        let files = files.clone();
        std::thread::Builder::new()
            .name("view http".into())
            .spawn(move || serve(listener, shared, commands, files))?;
    }
    let state = Telemetry {
        mask,
        decimation: telemetry.rate.decimation,
        rate_hz: telemetry.rate.rate_hz,
        counts: Counts::default(),
        running: true,
    };
    let port_name = args.port.port.clone().unwrap_or_default();
    let result = board_loop(
        &mut client,
        state,
        &shared,
        &inbox,
        &port_name,
        args.duration.map(Duration::from_secs_f64),
    );
    shared.stop.store(true, Ordering::SeqCst);
    shared.hub.lock().unwrap_or_else(|e| e.into_inner()).closed = true;
    shared.changed.notify_all();
    let _ = client.stop_telemetry();
    result
}

/// The board thread: telemetry, status, commands, until `duration` or a link error.
fn board_loop(
    client: &mut BoardClient,
    mut tel: Telemetry,
    shared: &Shared,
    inbox: &Receiver<Queued>,
    port: &str,
    duration: Option<Duration>,
) -> anyhow::Result<()> {
    let mut settings = client.read_params()?;
    let facts = client.capture_status()?;
    let names: Vec<&str> = Channel::of_mask(tel.mask).map(|c| c.name()).collect();
    let hello = |tel: &Telemetry, settings: &twinstack::config::settings::Settings| {
        json!({
            "port": port,
            "signals": names,
            "rate_hz": tel.rate_hz,
            "run": tel.counts.run,
            "output_range": [settings.ranges.output_min, settings.ranges.output_max],
            "drive_range": [settings.drive.min_voltage, settings.drive.max_voltage],
        })
    };
    shared.publish("hello", &hello(&tel, &settings));
    let wall0 = Instant::now();
    let sim0 = client.transport().clock();
    let mut last_status: Option<Instant> = None;
    loop {
        if duration.is_some_and(|d| wall0.elapsed() >= d) || shared.stop.load(Ordering::SeqCst) {
            return Ok(());
        }
        while let Ok((command, reply, deadline)) = inbox.try_recv() {
            // A command whose request has been answered "did not answer" is not carried out
            // after all (the page was told it failed).
            if Instant::now() >= deadline {
                let _ = reply.send(Err("not carried out: its request timed out".into()));
                continue;
            }
            let restart = matches!(command, Command::Telemetry(true));
            let answer = execute(client, &mut tel, shared, command);
            if answer.is_ok() {
                settings = client.read_params()?;
                if restart {
                    shared.publish("hello", &hello(&tel, &settings));
                }
            }
            let _ = reply.send(answer);
        }
        let frames = client.collect_telemetry(STEP)?;
        if !frames.is_empty() {
            let batch = convert(&mut tel, &frames, &facts, &settings)?;
            shared.publish("samples", &batch);
        }
        if last_status.is_none_or(|t| t.elapsed() >= STATUS_EVERY) {
            let status = client.status()?;
            let mut s = board_requests::status_json(&status);
            s["telemetry"] = tel.counts.json();
            s["telemetry"]["running"] = json!(tel.running);
            let link = client.counters();
            s["host_link"] = json!({
                "bytes_sent": link.bytes_sent,
                "bytes_received": link.bytes_received,
                "corrupt_frames": link.corrupt_frames,
                "telemetry_frames": link.telemetry_frames,
            });
            shared.publish("status", &s);
            last_status = Some(Instant::now());
        }
        // The simulated board runs as fast as the host computes: keep it to the wall clock.
        if let (Some(start), Some(now)) = (sim0, client.transport().clock()) {
            let simulated = now.saturating_sub(start);
            let wall = wall0.elapsed();
            if simulated > wall {
                std::thread::sleep(simulated - wall);
            }
        }
    }
}

/// Counts `frames` and converts their samples to physical units: `{run, first, n, dt,
/// signals: {name: [values]}}`.
fn convert(
    tel: &mut Telemetry,
    frames: &[TelemetryFrame],
    facts: &twinstack::protocol::messages::CaptureStatus,
    settings: &twinstack::config::settings::Settings,
) -> anyhow::Result<Value> {
    let mut record = TelemetryRecord::new(tel.mask, tel.decimation);
    let c = &mut tel.counts;
    let first = frames.first().map_or(c.expected, |f| f.first as u64);
    for f in frames {
        if (f.first as u64) < c.expected {
            // A frame of an earlier run still on the line: not this run's.
            continue;
        }
        record.add(f)?;
        c.frames += 1;
        c.frames_missing += f.seq.wrapping_sub(c.next_seq) as u64;
        c.next_seq = f.seq.wrapping_add(1);
        c.lost_on_board = c.lost_on_board.max(f.lost);
        let n = (f.values.len() / (tel.mask.count_ones() as usize).max(1)) as u64;
        c.samples += n;
        c.expected = f.first as u64 + n;
        if f.end {
            c.produced = Some(f.first as u64);
        }
    }
    let recording = record.recording(facts, settings)?;
    let mut signals = serde_json::Map::new();
    for col in &recording.columns {
        let values: Vec<Value> = col
            .values
            .iter()
            .map(|v| json!((v * 1e4).round() / 1e4))
            .collect();
        signals.insert(col.channel.name().to_string(), Value::Array(values));
    }
    Ok(json!({
        "run": c.run,
        "first": first,
        "n": record.samples(),
        "dt": 1.0 / tel.rate_hz,
        "signals": signals,
        "counts": c.json(),
    }))
}

/// Carries out a command from the page.
fn execute(
    client: &mut BoardClient,
    tel: &mut Telemetry,
    shared: &Shared,
    command: Command,
) -> Reply {
    let link = |e: twinstack_link::LinkError| e.to_string();
    match command {
        Command::Mode(name) => {
            let mode = board_requests::parse_mode(&name).ok_or_else(|| {
                format!("mode {name:?}: expected \"bypass\", \"open-loop\" or \"closed-loop\"")
            })?;
            client.set_mode(mode).map_err(link)?;
            Ok(format!("mode {}", board_requests::mode_name(mode)))
        }
        Command::Waveform(v) => {
            let num = |k: &str, default: Option<f64>| -> Result<f64, String> {
                match v.get(k) {
                    None | Some(Value::Null) => default.ok_or(format!("waveform: no {k:?}")),
                    Some(x) => x.as_f64().ok_or(format!("waveform: {k} is not a number")),
                }
            };
            let shape = match v.get("shape").and_then(Value::as_str).unwrap_or("sine") {
                "sine" => WaveShape::Sine,
                "triangle" => WaveShape::Triangle,
                other => return Err(format!("waveform: shape {other:?}: sine or triangle")),
            };
            let (a, f, o) = (
                num("amplitude", None)?,
                num("frequency", None)?,
                num("offset", Some(0.0))?,
            );
            let w = board_requests::waveform(shape, o, a, f, None)
                .map_err(|e| format!("waveform: {e}"))?;
            client.waveform(w).map_err(link)?;
            Ok(format!("waveform {a} at {f} Hz"))
        }
        Command::Scan(v) => {
            let spec = v
                .get("pattern")
                .and_then(Value::as_str)
                .ok_or("scan: no \"pattern\"")?;
            let pattern = parse_pattern(spec).map_err(|e| format!("scan: {e}"))?;
            let ticks_per_pixel = match v.get("ticks_per_pixel") {
                None | Some(Value::Null) => 4,
                Some(x) => x
                    .as_u64()
                    .and_then(|n| u16::try_from(n).ok())
                    .ok_or("scan: ticks_per_pixel is not a whole number of ticks (1…65535)")?,
            };
            client
                .expect_ack(&Request::Trigger(TriggerConfig {
                    pulse_ticks: 2,
                    input: TriggerEdge::Off,
                    start_stream: false,
                }))
                .map_err(link)?;
            client
                .expect_ack(&Request::Scan(ScanRequest {
                    pattern,
                    ticks_per_pixel,
                    frames: 0,
                    on_trigger: false,
                }))
                .map_err(link)?;
            Ok(format!("scanning {spec} until stopped"))
        }
        Command::Stop => {
            client.stream(StreamControl::Stop).map_err(link)?;
            Ok("stopped: the output holds".into())
        }
        Command::Telemetry(true) if tel.running => Ok("telemetry already running".into()),
        Command::Telemetry(false) if !tel.running => Ok("telemetry already stopped".into()),
        Command::Telemetry(true) => {
            client
                .start_telemetry(tel.mask, tel.decimation)
                .map_err(link)?;
            tel.running = true;
            tel.counts = Counts {
                run: tel.counts.run + 1,
                ..Counts::default()
            };
            Ok(format!("telemetry run {} started", tel.counts.run))
        }
        Command::Telemetry(false) => {
            client.stop_telemetry().map_err(link)?;
            // The end frame carries the number of samples produced: wait for it here so the
            // page's count can be checked against it.
            let until = Instant::now() + Duration::from_secs(2);
            while tel.counts.produced.is_none() && Instant::now() < until {
                let frames = client.collect_telemetry(STEP).map_err(link)?;
                if !frames.is_empty() {
                    let facts = client.capture_status().map_err(link)?;
                    let settings = client.read_params().map_err(link)?;
                    let batch =
                        convert(tel, &frames, &facts, &settings).map_err(|e| e.to_string())?;
                    shared.publish("samples", &batch);
                }
            }
            tel.running = false;
            match tel.counts.produced {
                Some(n) => Ok(format!("telemetry stopped after {n} samples")),
                None => Err("telemetry stopped, but its end frame never came".into()),
            }
        }
    }
}

// ---------------------------------------------------------------------------------------
// HTTP

fn serve(
    listener: TcpListener,
    shared: Arc<Shared>,
    commands: SyncSender<Queued>,
    files: Arc<(Option<Value>, Option<Value>)>,
) {
    for stream in listener.incoming() {
        let Ok(stream) = stream else { continue };
        let shared = shared.clone();
        let commands = commands.clone();
        let files = files.clone();
        let _ = std::thread::Builder::new()
            .name("view client".into())
            .spawn(move || {
                let _ = handle(stream, &shared, &commands, &files);
            });
    }
}

/// A parsed request: method, path, body.
struct HttpRequest {
    method: String,
    path: String,
    body: Vec<u8>,
}

/// Reads one request (head at most [`MAX_HEAD`] bytes, body at most [`MAX_BODY`]).
fn read_request(reader: &mut BufReader<TcpStream>) -> Result<Option<HttpRequest>, String> {
    let mut head = Vec::new();
    loop {
        let before = head.len();
        // At most what the head has left, so a line that never ends is cut at the bound
        // (reading to its end first held all of it: gigabytes from one client).
        let left = (MAX_HEAD + 1 - before) as u64;
        let n = reader
            .by_ref()
            .take(left)
            .read_until(b'\n', &mut head)
            .map_err(|e| e.to_string())?;
        if n == 0 {
            return if head.is_empty() {
                Ok(None)
            } else {
                Err("connection closed inside the request head".into())
            };
        }
        if head.len() > MAX_HEAD {
            return Err(format!("request head over {MAX_HEAD} bytes"));
        }
        if head[before..] == *b"\r\n" || head[before..] == *b"\n" {
            break;
        }
    }
    let mut headers = [httparse::EMPTY_HEADER; 32];
    let mut req = httparse::Request::new(&mut headers);
    match req.parse(&head) {
        Ok(httparse::Status::Complete(_)) => {}
        Ok(httparse::Status::Partial) => return Err("incomplete request head".into()),
        Err(e) => return Err(format!("bad request head: {e}")),
    }
    // A chunked body would be read as the next request: refused, not misread.
    if req
        .headers
        .iter()
        .any(|h| h.name.eq_ignore_ascii_case("transfer-encoding"))
    {
        return Err("Transfer-Encoding is not taken: send the body with a Content-Length".into());
    }
    let length = req
        .headers
        .iter()
        .find(|h| h.name.eq_ignore_ascii_case("content-length"))
        .map(|h| {
            std::str::from_utf8(h.value)
                .ok()
                .and_then(|s| s.trim().parse::<usize>().ok())
                .ok_or("Content-Length is not a number")
        })
        .transpose()?
        .unwrap_or(0);
    if length > MAX_BODY {
        return Err(format!(
            "request body of {length} bytes, at most {MAX_BODY}"
        ));
    }
    let mut body = vec![0; length];
    reader.read_exact(&mut body).map_err(|e| e.to_string())?;
    Ok(Some(HttpRequest {
        method: req.method.unwrap_or("").to_string(),
        path: req.path.unwrap_or("/").to_string(),
        body,
    }))
}

fn respond(stream: &mut TcpStream, code: u16, kind: &str, body: &[u8]) -> std::io::Result<()> {
    let reason = match code {
        200 => "OK",
        400 => "Bad Request",
        404 => "Not Found",
        405 => "Method Not Allowed",
        422 => "Unprocessable Entity",
        _ => "Service Unavailable",
    };
    write!(
        stream,
        "HTTP/1.1 {code} {reason}\r\nContent-Type: {kind}\r\nContent-Length: {}\r\nCache-Control: no-store\r\n\r\n",
        body.len()
    )?;
    stream.write_all(body)?;
    stream.flush()
}

fn respond_json(stream: &mut TcpStream, code: u16, v: &Value) -> std::io::Result<()> {
    respond(stream, code, "application/json", v.to_string().as_bytes())
}

fn handle(
    stream: TcpStream,
    shared: &Shared,
    commands: &SyncSender<Queued>,
    files: &(Option<Value>, Option<Value>),
) -> std::io::Result<()> {
    let mut out = stream.try_clone()?;
    let mut reader = BufReader::new(stream);
    loop {
        let req = match read_request(&mut reader) {
            Ok(Some(r)) => r,
            Ok(None) => return Ok(()),
            Err(e) => return respond_json(&mut out, 400, &json!({ "error": e })),
        };
        let path = req.path.split('?').next().unwrap_or("/");
        match (req.method.as_str(), path) {
            ("GET", "/") | ("GET", "/index.html") => respond(
                &mut out,
                200,
                "text/html; charset=utf-8",
                INDEX_HTML.as_bytes(),
            )?,
            ("GET", "/view.js") => respond(
                &mut out,
                200,
                "text/javascript; charset=utf-8",
                VIEW_JS.as_bytes(),
            )?,
            ("GET", "/events") => return events(out, shared),
            ("GET", "/api/tune") => match &files.0 {
                Some(v) => respond_json(&mut out, 200, v)?,
                None => respond_json(&mut out, 404, &json!({"error": "no --tune file given"}))?,
            },
            ("GET", "/api/calibration") => match &files.1 {
                Some(v) => respond_json(&mut out, 200, v)?,
                None => respond_json(
                    &mut out,
                    404,
                    &json!({"error": "no --calibration file given"}),
                )?,
            },
            ("GET", "/api/status") => {
                let hub = shared.hub.lock().unwrap_or_else(|e| e.into_inner());
                let status = hub.status.clone();
                drop(hub);
                let v = status
                    .and_then(|s| {
                        let data = s.lines().find_map(|l| l.strip_prefix("data: "))?;
                        serde_json::from_str::<Value>(data).ok()
                    })
                    .unwrap_or(Value::Null);
                respond_json(&mut out, 200, &v)?
            }
            ("POST", p) if p.starts_with("/api/") => {
                let (code, v) = match command(p, &req.body) {
                    Err(e) => (400, json!({ "error": e })),
                    Ok(c) => {
                        let (tx, rx) = mpsc::channel();
                        let deadline = Instant::now() + COMMAND_TIMEOUT;
                        match commands.try_send((c, tx, deadline)) {
                            Err(TrySendError::Disconnected(_)) => {
                                (503, json!({"error": "the board link has ended"}))
                            }
                            Err(TrySendError::Full(_)) => (
                                503,
                                json!({"error": format!("{COMMAND_QUEUE} commands are waiting for the board already: not taken, try again")}),
                            ),
                            Ok(()) => match rx.recv_timeout(COMMAND_TIMEOUT) {
                                Ok(Ok(m)) => (200, json!({ "ok": m })),
                                Ok(Err(e)) => (422, json!({ "error": e })),
                                Err(_) => (503, json!({"error": "the board did not answer"})),
                            },
                        }
                    }
                };
                respond_json(&mut out, code, &v)?
            }
            ("GET", _) | ("POST", _) => respond_json(
                &mut out,
                404,
                &json!({"error": format!("no such page: {path}")}),
            )?,
            (m, _) => respond_json(
                &mut out,
                405,
                &json!({"error": format!("method {m} not allowed")}),
            )?,
        }
    }
}

/// The command a POST asks for, its JSON body checked.
fn command(path: &str, body: &[u8]) -> Result<Command, String> {
    let v: Value = if body.is_empty() {
        Value::Null
    } else {
        serde_json::from_slice(body).map_err(|e| format!("{path}: the body is not JSON: {e}"))?
    };
    match path {
        "/api/mode" => v
            .get("mode")
            .and_then(Value::as_str)
            .map(|m| Command::Mode(m.to_string()))
            .ok_or_else(|| {
                "/api/mode: give {\"mode\": \"bypass\" | \"open-loop\" | \"closed-loop\"}".into()
            }),
        "/api/waveform" => Ok(Command::Waveform(v)),
        "/api/scan" => Ok(Command::Scan(v)),
        "/api/stop" => Ok(Command::Stop),
        "/api/telemetry" => v
            .get("run")
            .and_then(Value::as_bool)
            .map(Command::Telemetry)
            .ok_or_else(|| "/api/telemetry: give {\"run\": true | false}".into()),
        other => Err(format!("no such command: {other}")),
    }
}

/// Server-Sent Events: the run's description, the latest status, then every message as
/// it is published. A page that fell behind the backlog is told how many it missed.
fn events(mut out: TcpStream, shared: &Shared) -> std::io::Result<()> {
    out.write_all(
        b"HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nCache-Control: no-store\r\nConnection: close\r\n\r\n",
    )?;
    let hub = shared.hub.lock().unwrap_or_else(|e| e.into_inner());
    let mut next = hub.next;
    let first: Vec<Arc<String>> = [hub.hello.clone(), hub.status.clone()]
        .into_iter()
        .flatten()
        .collect();
    drop(hub);
    for m in first {
        out.write_all(m.as_bytes())?;
    }
    out.flush()?;
    loop {
        let mut hub = shared.hub.lock().unwrap_or_else(|e| e.into_inner());
        while hub.next == next && !hub.closed {
            let (h, _) = shared
                .changed
                .wait_timeout(hub, Duration::from_secs(15))
                .unwrap_or_else(|e| e.into_inner());
            hub = h;
            if hub.next == next && !hub.closed {
                break; // a comment line below keeps the connection alive
            }
        }
        if hub.closed {
            drop(hub);
            out.write_all(b"event: closed\ndata: {}\n\n")?;
            return out.flush();
        }
        let oldest = hub.messages.front().map_or(hub.next, |m| m.0);
        let mut batch: Vec<Arc<String>> = Vec::new();
        if next < oldest {
            batch.push(Arc::new(format!(
                "event: missed\ndata: {{\"messages\": {}}}\n\n",
                oldest - next
            )));
            next = oldest;
        }
        batch.extend(
            hub.messages
                .iter()
                .filter(|m| m.0 >= next)
                .map(|m| m.1.clone()),
        );
        let keepalive = batch.is_empty();
        next = hub.next;
        drop(hub);
        if keepalive {
            out.write_all(b": keep-alive\n\n")?;
        }
        for m in batch {
            out.write_all(m.as_bytes())?;
        }
        out.flush()?;
    }
}
