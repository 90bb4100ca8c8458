//! The firmware image itself, booted in QEMU's `netduinoplus2` (an STM32F405): it must answer
//! protocol frames on USART1 (status, setpoint batches, stream control, a parameter load, the
//! recorder; a corrupted frame NACKed), its control tick must run, it must boot in bypass on
//! the compiled-in settings, read back what it was loaded with bit for bit, and the parameter
//! record in flash must be honoured (or refused with defaults and a flag); a fuzzed exchange
//! (mutated frames that pass the CRC, cut frames, junk) gets one response per frame.
//!
//! Builds the `emulator` image (`cargo build-emu`) into `target/firmware`, installing the
//! Rust target and `qemu-system-arm` first if they are missing (see `tests/support`).

mod support;

use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::Child;
use std::time::{Duration, Instant};

use twinstack::board::Hardware;
use twinstack::config::param_store::{StoredRecord, HEADER_LEN, MAX_RECORD};
use twinstack::config::settings::{
    representative_duhem, representative_pi, FeedbackSettings, Model, Settings,
};
use twinstack::control::drive::SafeState;
use twinstack::protocol::decoder::FrameDecoder;
use twinstack::protocol::frame::{self, FrameError, MAX_ENCODED};
use twinstack::protocol::messages::*;
use twinstack::refusal::{Field, ModelField, Refusal, Rule};

/// Address of the parameter sector (flash sector 11).
const PARAM_SECTOR: u32 = 0x080E_0000;

/// A running QEMU with USART1 on a Unix socket; killed and cleaned up on drop.
struct Emulator {
    child: Child,
    uart: UnixStream,
    scratch: PathBuf,
    decoder: FrameDecoder,
    /// The image booted (for its symbols).
    elf: PathBuf,
}

impl Drop for Emulator {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.scratch);
    }
}

impl Emulator {
    /// Boots the emulator image; `record`, if given, is loaded at the parameter sector.
    fn boot(name: &str, record: Option<&[u8]>) -> Self {
        Self::boot_with(name, record, &[])
    }

    /// [`Emulator::boot`] with `extra` arguments for QEMU (`{scratch}` in them is replaced
    /// by the scratch directory).
    fn boot_with(name: &str, record: Option<&[u8]>, extra: &[&str]) -> Self {
        let elf = support::build_image(support::FIRMWARE, "twinstack-emu", &["emulator"]);
        let scratch =
            std::env::temp_dir().join(format!("twinstack-emu-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&scratch);
        std::fs::create_dir_all(&scratch).expect("scratch directory");
        let socket = scratch.join("uart.sock");
        let mut cmd = support::emulator_command(&elf);
        cmd.arg("-chardev")
            .arg(format!(
                "socket,id=u1,path={},server=on,wait=on",
                socket.display()
            ))
            .args(["-serial", "chardev:u1"])
            .arg("-monitor")
            .arg(format!(
                "unix:{},server=on,wait=off",
                scratch.join("monitor.sock").display()
            ));
        for a in extra {
            cmd.arg(a.replace("{scratch}", &scratch.display().to_string()));
        }
        if let Some(bytes) = record {
            let file = scratch.join("record.bin");
            std::fs::write(&file, bytes).expect("record file");
            cmd.arg("-device").arg(format!(
                "loader,file={},addr={PARAM_SECTOR:#x}",
                file.display()
            ));
        }
        let child = cmd.spawn().expect("qemu-system-arm starts");
        let uart = connect(&socket, Duration::from_secs(20));
        let mut emu = Emulator {
            child,
            uart,
            scratch,
            decoder: FrameDecoder::new(),
            elf,
        };
        emu.wait_until_listening();
        emu
    }

    /// Bytes sent before the firmware has enabled USART1 are lost, so ask for the status until
    /// a byte comes back (within 20 s), then discard the answers to the repeated requests and
    /// resynchronise with an empty frame.
    fn wait_until_listening(&mut self) {
        let start = Instant::now();
        self.uart
            .set_read_timeout(Some(Duration::from_millis(500)))
            .expect("read timeout");
        let status = encoded(&Request::Status);
        let mut byte = [0u8; 1];
        loop {
            self.uart.write_all(&status).expect("write to USART1");
            if let Ok(1) = self.uart.read(&mut byte) {
                break;
            }
            assert!(
                start.elapsed() < Duration::from_secs(20),
                "the firmware never answered on USART1"
            );
        }
        // Drain: stop after 500 ms of silence.
        let mut sink = [0u8; 256];
        while let Ok(n) = self.uart.read(&mut sink) {
            if n == 0 {
                break;
            }
        }
        self.decoder = FrameDecoder::new();
        self.uart
            .set_read_timeout(Some(Duration::from_secs(10)))
            .expect("read timeout");
    }

    /// Reads one response frame.
    fn response(&mut self) -> Response {
        let mut byte = [0u8; 1];
        let mut seen = 0usize;
        loop {
            match self.uart.read(&mut byte) {
                Ok(1) => {}
                Ok(_) => panic!("USART1 closed"),
                Err(e) => panic!("no response from the firmware ({e}) after {seen} bytes"),
            }
            seen += 1;
            assert!(seen <= MAX_ENCODED + 1, "response longer than a frame");
            if let Some(body) = self.decoder.push(byte[0]) {
                let body = body.expect("response frame sound").to_vec();
                return frame::decode_body(&body).expect("response decodes");
            }
        }
    }

    /// Sends `request` and reads its response.
    fn request(&mut self, request: &Request) -> Response {
        self.uart
            .write_all(&encoded(request))
            .expect("write to USART1");
        self.response()
    }

    /// The stack the run has used so far and the room the image leaves it, bytes: QEMU's
    /// monitor dumps the SRAM (`pmemsave`) and [`support::stack_used`] finds the lowest word
    /// the run changed in the stack painted at reset.
    fn stack_used(&mut self) -> (u32, u32) {
        let dump = self.scratch.join("sram.bin");
        let mut monitor = connect(&self.scratch.join("monitor.sock"), Duration::from_secs(5));
        // The file name quoted: unquoted, the monitor reads its `/` as a division.
        writeln!(
            monitor,
            "pmemsave 0x20000000 0x20000 \"{}\"",
            dump.display()
        )
        .expect("monitor");
        let start = Instant::now();
        loop {
            if std::fs::metadata(&dump).is_ok_and(|m| m.len() == 0x20000) {
                break;
            }
            assert!(start.elapsed() < Duration::from_secs(10), "no SRAM dump");
            std::thread::sleep(Duration::from_millis(50));
        }
        std::thread::sleep(Duration::from_millis(100));
        let ram = std::fs::read(&dump).expect("SRAM dump");
        support::stack_used(&self.elf, &ram).unwrap_or_else(|e| panic!("{e}"))
    }

    fn status(&mut self) -> StatusReport {
        match self.request(&Request::Status) {
            Response::Status(s) => s,
            other => panic!("not a status report: {other:?}"),
        }
    }
}

fn encoded(request: &Request) -> Vec<u8> {
    let mut out = vec![0u8; MAX_ENCODED + 1];
    let n = frame::encode(request, &mut out).expect("fits a frame");
    out.truncate(n);
    out
}

fn connect(socket: &Path, within: Duration) -> UnixStream {
    let start = Instant::now();
    loop {
        match UnixStream::connect(socket) {
            Ok(s) => return s,
            Err(e) if start.elapsed() > within => {
                panic!(
                    "QEMU's USART1 socket {} never accepted: {e}",
                    socket.display()
                )
            }
            Err(_) => std::thread::sleep(Duration::from_millis(50)),
        }
    }
}

fn record_of(record: &StoredRecord) -> Vec<u8> {
    let mut buf = [0u8; MAX_RECORD];
    let n = record.encode(&mut buf).expect("record fits");
    buf[..n].to_vec()
}

/// Open-loop settings whose floats do not round-trip through anything narrower than f64.
fn awkward_settings() -> Settings {
    let mut s = Settings {
        compensator: Some(representative_pi(16).unwrap()),
        observer: Some(representative_duhem()),
        feedback: Some(FeedbackSettings::pi(0.1 + 0.2, 1000.0 / 3.0, 0.1)),
        mode: Mode::OpenLoop,
        ..Settings::default()
    };
    s.drive.bias = 70.0 + 1e-12;
    s.drive.slew_rate = 1.0e6 / 3.0;
    s.ranges.output_max = 70.0 - f64::EPSILON * 64.0;
    s
}

/// The settings' postcard bytes: f64s as their 8 raw bytes, so equal bytes are equal bits.
fn bits(s: &Settings) -> Vec<u8> {
    let mut buf = [0u8; 4096];
    postcard::to_slice(s, &mut buf).expect("fits").to_vec()
}

#[test]
fn emulator_answers_a_status_query_and_its_tick_counter_advances() {
    let mut emu = Emulator::boot("status", None);
    let a = emu.status();
    std::thread::sleep(Duration::from_millis(300));
    let b = emu.status();
    assert!(
        b.ticks > a.ticks,
        "tick counter did not advance: {a:?} then {b:?}"
    );
    assert_eq!(a.tick_rate_hz, Hardware::DEFAULT_CONTROL_RATE_HZ);
    // Nothing streams: no underruns; the whole queue is free.
    assert_eq!((b.underruns, b.queue_fill), (0, 0), "{b:?}");
    assert_eq!(
        b.credits as usize,
        (twinstack::control_loop::EMULATOR_SETPOINT_QUEUE_LEN - 1)
    );
    // Nothing was stored in the emulated flash: the compiled-in settings, flagged.
    assert!(b.has(StatusReport::DEFAULTS), "{b:?}");
    assert_eq!(b.mode(), Mode::Bypass);
    // The image says which it is: the emulator, not the board image.
    assert_eq!(b.image(), Image::Emulator, "{b:?}");
}

#[test]
fn a_fresh_emulator_reports_bypass_on_its_first_status_query_and_reads_back_the_defaults() {
    let mut emu = Emulator::boot("fresh", None);
    let first = emu.status();
    assert_eq!(first.mode(), Mode::Bypass, "{first:?}");
    assert!(first.has(StatusReport::DEFAULTS), "{first:?}");
    assert_eq!(
        emu.request(&Request::ReadParams),
        Response::Params(Settings::default())
    );
}

#[test]
fn a_load_over_the_uart_reads_back_bit_for_bit() {
    let mut emu = Emulator::boot("readback", None);
    let sent = awkward_settings();
    assert!(matches!(
        emu.request(&Request::LoadParams(sent.clone())),
        Response::Ack { .. }
    ));
    let back = match emu.request(&Request::ReadParams) {
        Response::Params(s) => s,
        other => panic!("not the settings: {other:?}"),
    };
    assert_eq!(back, sent);
    assert_eq!(
        bits(&back),
        bits(&sent),
        "an f64 changed its bits on the way"
    );
    let s = emu.status();
    assert_eq!(s.mode(), Mode::OpenLoop, "{s:?}");
    assert!(!s.has(StatusReport::DEFAULTS), "{s:?}");
    // A refused load (NaN) names its field and leaves the settings read back as they were.
    let mut nan = sent.clone();
    nan.drive.slew_rate = f64::NAN;
    assert_eq!(
        emu.request(&Request::LoadParams(nan)),
        Response::Nack {
            reason: NackReason::Refused(Refusal::new(Field::SlewRate, Rule::NotFinite))
        }
    );
    match emu.request(&Request::ReadParams) {
        Response::Params(s) => assert_eq!(bits(&s), bits(&sent)),
        other => panic!("not the settings: {other:?}"),
    }
}

#[test]
fn emulator_streams_setpoints_loads_parameters_records_and_nacks_a_bad_frame() {
    let mut emu = Emulator::boot("protocol", None);
    // A corrupted frame: NACKed with its reason and counted; nothing else changes.
    let mut bad = encoded(&Request::Stream(StreamControl::Start));
    bad[2] ^= 0x01;
    emu.uart.write_all(&bad).expect("write");
    assert_eq!(
        emu.response(),
        Response::Nack {
            reason: NackReason::Frame(FrameError::BadCrc)
        }
    );
    assert_eq!(emu.status().crc_errors, 1);
    // Queue a ramp (two batches), one setpoint every 10 ticks, interpolated.
    let ramp: Vec<i16> = (0..192).map(|k| (k * 100) as i16).collect();
    let free = (twinstack::control_loop::EMULATOR_SETPOINT_QUEUE_LEN - 1) as u16;
    for seq in 0..2u16 {
        let part = &ramp[96 * seq as usize..96 * (seq as usize + 1)];
        assert_eq!(
            emu.request(&Request::Setpoints(SetpointBatch {
                seq,
                samples: twinstack::heapless::Vec::from_slice(part).unwrap(),
            })),
            Response::Ack {
                credits: free - 96 * (seq + 1)
            }
        );
    }
    // A batch with a stale sequence number is refused; nothing queued is lost.
    assert_eq!(
        emu.request(&Request::Setpoints(SetpointBatch {
            seq: 0,
            samples: twinstack::heapless::Vec::from_slice(&ramp[..8]).unwrap(),
        })),
        Response::Nack {
            reason: NackReason::OutOfSequence { expected: 2 }
        }
    );
    assert_eq!(emu.status().queue_fill, 192);
    assert!(matches!(
        emu.request(&Request::Stream(StreamControl::Rate { divider: 10 })),
        Response::Ack { .. }
    ));
    // Record the setpoint for 4000 ticks (80 ms), then start: the ramp takes 1920 ticks.
    assert!(matches!(
        emu.request(&Request::Record(RecordRequest {
            signal: Signal::Setpoint,
            count: 4000,
            decimation: 1,
        })),
        Response::Ack { .. }
    ));
    assert!(matches!(
        emu.request(&Request::Stream(StreamControl::Start)),
        Response::Ack { .. }
    ));
    // QEMU's ticks are not wall-clock ticks: wait for the capture to complete.
    let start = Instant::now();
    let s = loop {
        let s = emu.status();
        if !s.has(StatusReport::RECORDING) {
            break s;
        }
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "capture stuck: {s:?}"
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    assert_eq!(s.queue_fill, 0, "{s:?}");
    assert!(s.underruns > 0, "the stream ran dry and holds: {s:?}");
    assert_eq!(s.recorded, 4000, "{s:?}");
    let mut values = Vec::new();
    while values.len() < 4000 {
        match emu.request(&Request::ReadRecord {
            offset: values.len() as u32,
        }) {
            Response::RecordChunk { values: v, .. } => values.extend_from_slice(&v),
            other => panic!("{other:?}"),
        }
    }
    // Every streamed setpoint was reached, in order, exactly 10 ticks after the one before.
    // (The first, 0, is also where the board rests in bypass on the defaults, before the
    // stream starts: it is checked 10 ticks before the second.)
    let at: Vec<usize> = ramp[1..]
        .iter()
        .map(|&x| {
            values
                .iter()
                .position(|&v| v == (x as i32) << 15)
                .unwrap_or_else(|| panic!("setpoint {x} never reached: {values:?}"))
        })
        .collect();
    assert!(at.windows(2).all(|w| w[1] == w[0] + 10), "{at:?}");
    assert!(
        at[0] >= 10 && values[at[0] - 10] == (ramp[0] as i32) << 15,
        "{at:?}"
    );
    // A parameter load: validated, swapped in, reported.
    let mut params = awkward_settings();
    assert!(matches!(
        emu.request(&Request::LoadParams(params.clone())),
        Response::Ack { .. }
    ));
    let s = emu.status();
    assert_eq!(s.mode(), Mode::OpenLoop);
    assert!(!s.has(StatusReport::DEFAULTS));
    // One that cannot be inverted is refused with its reason; the mode stays.
    if let Some(Model::PrandtlIshlinskii(p)) = &mut params.compensator {
        p.weights[0] = -1.0;
    }
    assert_eq!(
        emu.request(&Request::LoadParams(params)),
        Response::Nack {
            reason: NackReason::Refused(Refusal::new(
                Field::Compensator(ModelField::Weight(1)),
                Rule::NotInvertible
            ))
        }
    );
    assert_eq!(emu.status().mode(), Mode::OpenLoop);
}

#[test]
fn a_stored_parameter_record_sets_the_tick_rate_and_boots_in_its_mode() {
    let mut settings = awkward_settings();
    settings.drive.safe_state = SafeState::Zero;
    let stored = StoredRecord {
        control_rate_hz: 20_000,
        settings: settings.clone(),
        analog: None,
    };
    let mut emu = Emulator::boot("stored", Some(&record_of(&stored)));
    let s = emu.status();
    assert_eq!(s.tick_rate_hz, 20_000, "{s:?}");
    assert_eq!(s.mode(), Mode::OpenLoop, "{s:?}");
    assert!(!s.has(StatusReport::DEFAULTS), "{s:?}");
    match emu.request(&Request::ReadParams) {
        Response::Params(back) => assert_eq!(bits(&back), bits(&settings)),
        other => panic!("not the settings: {other:?}"),
    }
}

#[test]
fn a_record_with_a_bad_crc_boots_on_defaults_and_says_so() {
    let mut record = record_of(&StoredRecord {
        control_rate_hz: 20_000,
        settings: awkward_settings(),
        analog: None,
    });
    record[HEADER_LEN] ^= 0x40; // corrupt the stored rate; the CRC no longer matches
    let mut emu = Emulator::boot("bad-crc", Some(&record));
    let s = emu.status();
    assert_eq!(s.tick_rate_hz, Hardware::DEFAULT_CONTROL_RATE_HZ, "{s:?}");
    assert!(s.has(StatusReport::DEFAULTS), "{s:?}");
    assert_eq!(s.mode(), Mode::Bypass, "{s:?}");
    assert!(s.ticks > 0, "the tick runs on defaults: {s:?}");
}

/// The v4 capture on the emulator image: armed on the stream's start with pre-trigger frames,
/// it holds the streamed setpoints exactly (Q1.15) and both stacks' DAC codes (in bypass on
/// the defaults, differential: their sum stays at twice the bias, within rounding); the
/// emulator's buffer is the SRAM half (QEMU models no CCM RAM).
#[test]
fn emulator_captures_a_streamed_run_with_several_signals() {
    let mut emu = Emulator::boot("capture", None);
    let samples: Vec<i16> = (0..96).map(|k| (k * 200 - 9_600) as i16).collect();
    assert!(matches!(
        emu.request(&Request::Setpoints(SetpointBatch {
            seq: 0,
            samples: twinstack::heapless::Vec::from_slice(&samples).unwrap(),
        })),
        Response::Ack { .. }
    ));
    let mask = 0b111; // setpoint, left, right
    assert!(matches!(
        emu.request(&Request::Capture(CaptureRequest {
            signals: mask,
            samples: 200,
            pre_trigger: 20,
            trigger: Trigger::StreamStart,
            decimation: 1,
        })),
        Response::Ack { .. }
    ));
    let status = |emu: &mut Emulator| match emu.request(&Request::CaptureStatus) {
        Response::Capture(s) => s,
        other => panic!("{other:?}"),
    };
    let first = status(&mut emu);
    assert_eq!(
        first.capacity,
        // The SRAM part only: QEMU models no CCM RAM (the board's other 12 288 slots).
        (twinstack::services::recorder::CAPTURE_SLOTS - 12 * 1024) as u32,
        "{first:?}"
    );
    assert_eq!(first.state, CaptureState::Armed);
    // Let the ring fill its pre-trigger frames before the start.
    let start = Instant::now();
    while status(&mut emu).captured < 20 {
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "no pre-trigger frames"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(matches!(
        emu.request(&Request::Stream(StreamControl::Start)),
        Response::Ack { .. }
    ));
    let s = loop {
        let s = status(&mut emu);
        if s.state == CaptureState::Done {
            break s;
        }
        assert!(
            start.elapsed() < Duration::from_secs(40),
            "capture stuck: {s:?}"
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    assert_eq!((s.pre_available, s.window_slots), (20, 600), "{s:?}");
    let mut window = Vec::new();
    while window.len() < 600 {
        match emu.request(&Request::ReadCapture {
            offset: window.len() as u32,
            count: 256,
        }) {
            Response::CaptureChunk { values, .. } => window.extend_from_slice(&values),
            other => panic!("{other:?}"),
        }
    }
    let frames: Vec<&[i16]> = window.chunks(3).collect();
    // Before the start the board rests at 0 (bypass on the defaults); then the 96 setpoints.
    assert!(
        frames[..20].iter().all(|f| f[0] == 0),
        "{:?}",
        &frames[..20]
    );
    let streamed: Vec<i16> = frames[20..116].iter().map(|f| f[0]).collect();
    assert_eq!(streamed, samples);
    // Differential drive about a 70 V bias on 150 V / 4095: left + right ≈ 2 × 1911.
    for f in &frames {
        let sum = f[1] as u16 as i32 + f[2] as u16 as i32;
        assert!((sum - 3822).abs() <= 2, "{f:?}");
    }
    let left: Vec<u16> = frames[20..116].iter().map(|f| f[1] as u16).collect();
    assert!(
        left.windows(2).all(|w| w[1] >= w[0]),
        "the left stack follows the ramp: {left:?}"
    );
    assert!(left[95] > left[0] + 500, "{left:?}");
}

/// Sends `request` and returns its response, with the telemetry frames that came before it.
fn answer_amid_telemetry(emu: &mut Emulator, request: &Request) -> (Response, Vec<TelemetryFrame>) {
    emu.uart
        .write_all(&encoded(request))
        .expect("write to USART1");
    let mut frames = Vec::new();
    loop {
        match emu.response() {
            Response::Telemetry(f) => frames.push(f),
            other => return (other, frames),
        }
    }
}

#[test]
fn emulator_sends_telemetry_between_its_responses() {
    let mut emu = Emulator::boot("telemetry", None);
    // Both stacks every 50 ticks; the emulator sends the frames through the polled TX, as the
    // board sends them by DMA.
    let start = Request::Telemetry(TelemetryRequest::Start {
        signals: 0b110,
        decimation: 50,
    });
    assert!(matches!(
        answer_amid_telemetry(&mut emu, &start).0,
        Response::Ack { .. }
    ));
    let mut frames = Vec::new();
    // Requests keep their answers while telemetry flows, and a rate beyond the line is refused
    // with the decimation it needs (the running telemetry goes on).
    for _ in 0..10 {
        let (r, f) = answer_amid_telemetry(&mut emu, &Request::Status);
        frames.extend(f);
        let Response::Status(s) = r else {
            panic!("{r:?}")
        };
        assert!(s.has(StatusReport::TELEMETRY), "{s:?}");
        std::thread::sleep(Duration::from_millis(100));
    }
    let too_fast = Request::Telemetry(TelemetryRequest::Start {
        signals: 0b11_1111,
        decimation: 1,
    });
    let (r, f) = answer_amid_telemetry(&mut emu, &too_fast);
    frames.extend(f);
    assert_eq!(
        r,
        Response::Nack {
            reason: NackReason::Refused(Refusal::new(
                Field::TelemetryDecimation,
                Rule::AtLeast(6.0)
            ))
        }
    );
    let (r, f) = answer_amid_telemetry(&mut emu, &Request::Telemetry(TelemetryRequest::Stop));
    frames.extend(f);
    assert!(matches!(r, Response::Ack { .. }), "{r:?}");
    // After the stop: what was queued, then the end frame.
    while !frames.last().is_some_and(|f| f.end) {
        match emu.response() {
            Response::Telemetry(f) => frames.push(f),
            other => panic!("{other:?} after the stop's answer"),
        }
    }
    assert!(frames.len() >= 3, "{} frames", frames.len());
    let mut next = 0u32;
    for (i, f) in frames.iter().enumerate() {
        assert_eq!(
            (f.seq as usize, f.first, f.lost, f.signals),
            (i, next, 0, 0b110)
        );
        // Differential drive about the 70 V bias, 150 V / 4095: left + right ≈ 2 × 1911.
        for pair in f.values.chunks(2) {
            let sum = pair[0] as u16 as i32 + pair[1] as u16 as i32;
            assert!((sum - 3822).abs() <= 2, "{pair:?}");
        }
        next += f.values.len() as u32 / 2;
    }
    let end = frames.last().unwrap();
    assert!(end.end && end.values.is_empty() && end.first == next && next > 10);
    let s = emu.status();
    assert!(!s.has(StatusReport::TELEMETRY), "{s:?}");
}

/// The stack's high-water mark after the image's deepest paths: boot (the resources built in
/// `init`), parameter loads of each model family (validation and `Controller::prepare` off
/// the tick), a store refused by the read-only flash, a recall, the learning configured and
/// learning on a waveform (its `service` at every period boundary), a capture and telemetry.
/// `memory.x` reserves `_stack_reserve` for the stack and the link fails if the static RAM
/// leaves less; this holds the measured use to at most three quarters of that reserve.
#[test]
fn the_stack_stays_within_its_reserve_on_the_deepest_paths() {
    let mut emu = Emulator::boot("stack", None);
    let reserve = support::elf_symbol(&emu.elf, "_stack_reserve")
        .unwrap_or_else(|e| panic!("{e}"))
        .expect("memory.x defines _stack_reserve");
    let (boot, room) = emu.stack_used();
    let mut settings = awkward_settings();
    settings.mode = Mode::ClosedLoop;
    for model in [
        representative_pi(16).unwrap(),
        twinstack::config::settings::representative_gpi(16).unwrap(),
        representative_duhem(),
        twinstack::config::settings::representative_bouc_wen(),
    ] {
        settings.compensator = Some(model);
        let r = emu.request(&Request::LoadParams(settings.clone()));
        assert!(matches!(r, Response::Ack { .. }), "{r:?}");
    }
    settings.compensator = Some(representative_pi(16).unwrap());
    assert!(matches!(
        emu.request(&Request::LoadParams(settings.clone())),
        Response::Ack { .. }
    ));
    let _ = emu.request(&Request::StoreParams {
        boot_mode: Mode::Bypass,
    });
    let _ = emu.request(&Request::RecallParams);
    let _ = emu.request(&Request::ReadParams);
    let learn = twinstack::services::learning::LearnSettings::for_period(200);
    assert!(matches!(
        emu.request(&Request::Learn(LearnRequest::Configure(learn))),
        Response::Ack { .. }
    ));
    assert!(matches!(
        emu.request(&Request::Waveform(Waveform {
            shape: WaveShape::Sine,
            offset: 0,
            amplitude: 8000,
            frequency_mhz: 750_000,
            decay: None,
        })),
        Response::Ack { .. }
    ));
    let r = emu.request(&Request::Learn(LearnRequest::State(LearnState::Learning)));
    assert!(matches!(r, Response::Ack { .. }), "{r:?}");
    assert!(matches!(
        emu.request(&Request::Capture(CaptureRequest {
            signals: 0b11_1111,
            samples: 1000,
            pre_trigger: 0,
            trigger: Trigger::Now,
            decimation: 1,
        })),
        Response::Ack { .. }
    ));
    let start = Instant::now();
    let updates = loop {
        let Response::Learn(s) = emu.request(&Request::Learn(LearnRequest::Status)) else {
            panic!("no learning status");
        };
        if s.updates >= 5 {
            break s.updates;
        }
        assert!(start.elapsed() < Duration::from_secs(30), "{s:?}");
        std::thread::sleep(Duration::from_millis(100));
    };
    let (used, room_after) = emu.stack_used();
    assert_eq!(room, room_after);
    println!(
        "stack: {boot} bytes after boot, {used} after loads, store, recall, {updates} learning \
         updates and a capture; reserve {reserve}, room left by the static RAM {room}"
    );
    assert!(room >= reserve, "static RAM leaves {room} < {reserve}");
    assert!(
        used <= reserve / 4 * 3,
        "the stack reached {used} bytes: more than 3/4 of its {reserve}-byte reserve"
    );
}

/// The scan's trigger outputs on the GPIO registers: QEMU's `netduinoplus2` models no GPIO, so
/// GPIOA is an unimplemented-device region whose writes `-d unimp` logs, each with its offset
/// and value. The tick writes BSRR (offset 0x18) once per tick, so the logged BSRR words are
/// the outputs tick by tick: their rising edges must fall exactly where the library's replay
/// of the pattern puts them (the line clock every 60 ticks, the pixel clock every 4 ticks of
/// each trace), and the board's own capture of the trigger levels must be that same sequence.
#[test]
fn emulator_scan_pulses_the_gpio_outputs_at_the_pattern_s_ticks() {
    use twinstack::sources::scan::{
        bsrr_word, RasterScan, ScanGenerator, ScanPattern, TriggerOutputs, FRAME, LINE, PIXEL,
    };
    let mut emu = Emulator::boot_with("scan", None, &["-d", "unimp", "-D", "{scratch}/unimp.log"]);
    let request = ScanRequest {
        pattern: ScanPattern::Raster(RasterScan::centred(4, 10, 20, 0.5)),
        ticks_per_pixel: 4,
        frames: 1,
        on_trigger: false,
    };
    let pulse = 2;
    assert!(matches!(
        emu.request(&Request::Trigger(TriggerConfig {
            pulse_ticks: pulse,
            input: TriggerEdge::Off,
            start_stream: false,
        })),
        Response::Ack { .. }
    ));
    let samples = 400u32;
    assert!(matches!(
        emu.request(&Request::Capture(CaptureRequest {
            signals: 1 | 1 << 6, // setpoint, triggers
            samples,
            pre_trigger: 0,
            trigger: Trigger::ScanStart,
            decimation: 1,
        })),
        Response::Ack { .. }
    ));
    assert!(
        matches!(emu.request(&Request::Scan(request)), Response::Ack { .. }),
        "the emulator refused the scan"
    );
    let start = Instant::now();
    let status = loop {
        let s = match emu.request(&Request::CaptureStatus) {
            Response::Capture(s) => s,
            other => panic!("{other:?}"),
        };
        if s.state == CaptureState::Done {
            break s;
        }
        assert!(
            start.elapsed() < Duration::from_secs(40),
            "capture stuck: {s:?}"
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    let mut window = Vec::new();
    while window.len() < status.window_slots as usize {
        match emu.request(&Request::ReadCapture {
            offset: window.len() as u32,
            count: 256,
        }) {
            Response::CaptureChunk { values, .. } => window.extend_from_slice(&values),
            other => panic!("{other:?}"),
        }
    }
    let captured: Vec<u8> = window
        .iter()
        .skip(1)
        .step_by(2)
        .map(|&t| (t & 7) as u8)
        .collect();
    // The replay: the library's generator and pulse stretcher, from the first frame clock.
    let rate = status.tick_rate_hz as f64;
    let mut g = ScanGenerator::new(&request, rate, 1 << 28, pulse).unwrap();
    g.start(g.start_point().0);
    let mut out = TriggerOutputs::new(pulse);
    let replay: Vec<u8> = (0..1000)
        .map(|_| out.tick(g.next_sample().events))
        .collect();
    let from = |v: &[u8]| v.iter().position(|&l| l & FRAME != 0).unwrap();
    let (c0, r0) = (from(&captured), from(&replay));
    let n = (captured.len() - c0).min(replay.len() - r0);
    assert!(n > 300, "{n}");
    assert_eq!(
        &captured[c0..c0 + n],
        &replay[r0..r0 + n],
        "the board's capture vs the replay"
    );
    // The GPIO writes QEMU logged: `GPIOA: unimplemented device write (size 4, offset 0x018,
    // value 0x…)`. Each BSRR word is one tick's outputs.
    // (QEMU keeps logging every tick, so the scan's lines are long written out.)
    let log = std::fs::read_to_string(emu.scratch.join("unimp.log")).expect("the unimp log");
    let words: Vec<u32> = log
        .lines()
        .filter(|l| l.starts_with("GPIOA") && l.contains("device write"))
        .filter_map(|l| {
            let hex = |s: &str| u32::from_str_radix(s.trim().trim_start_matches("0x"), 16).ok();
            let offset = hex(l.split("offset ").nth(1)?.split(',').next()?)?;
            let value = hex(l.rsplit("value ").next()?.trim_end_matches(')'))?;
            (offset == 0x18).then_some(value)
        })
        .collect();
    assert!(words.len() > 1000, "{} BSRR writes logged", words.len());
    // From the first tick on (the HAL's pin set-up writes a few single-pin words first),
    // every word writes all four outputs (the scan's three and a sequence's settled output,
    // low here): a set or a reset bit for each.
    let full = |w: u32| bsrr_word(((w >> 1) & 7) as u8) == w;
    let first = words.iter().position(|&w| full(w)).unwrap();
    assert!(first < 8, "{:x?}", &words[..first]);
    let words = &words[first..];
    assert!(
        words.iter().all(|&w| full(w)),
        "partial BSRR words: {:x?}",
        words
            .iter()
            .filter(|&&w| !full(w))
            .take(5)
            .collect::<Vec<_>>()
    );
    let levels: Vec<u8> = words.iter().map(|&w| ((w >> 1) & 7) as u8).collect();
    // The pattern's stretch of the register trace is the replay's, tick for tick.
    let want = &replay[r0..r0 + n];
    let at = levels
        .windows(want.len())
        .position(|w| w == want)
        .expect("the replayed trigger levels in the BSRR writes");
    let edges = |bit: u8| -> Vec<usize> {
        (at + 1..at + n)
            .filter(|&k| levels[k] & bit != 0 && levels[k - 1] & bit == 0)
            .map(|k| k - at)
            .collect()
    };
    // Line clock: ticks 0, 60, 120, 180 from the first frame clock (10 × 4 + 20 per line);
    // frame clock once; the pixel clock every 4 ticks within each 40-tick trace.
    assert_eq!(edges(LINE), vec![60, 120, 180]);
    assert!(levels[at] & (LINE | FRAME) == LINE | FRAME);
    assert!(edges(FRAME).is_empty());
    let pixels = edges(PIXEL);
    let want_pixels: Vec<usize> = (0..4)
        .flat_map(|line| (0..10).map(move |p| line * 60 + p * 4))
        .filter(|&k| k > 0)
        .collect();
    assert_eq!(pixels, want_pixels);
    // And the register sequence around it: outputs low before the scan.
    assert!(levels[..at].iter().rev().take(20).all(|&l| l == 0));
}

/// A frame around `message` (postcard bytes, tag first) with a correct CRC, so that a
/// mutated message reaches the firmware's decoder rather than stopping at the CRC.
fn framed(message: &[u8]) -> Vec<u8> {
    let mut out = vec![0u8; MAX_ENCODED + 1];
    let n = frame::encode_message_bytes(message, &mut out).expect("fits a frame");
    out.truncate(n);
    out
}

/// The firmware itself under a protocol fuzzer, as a stop-and-wait host would meet it: 400
/// chunks (valid frames of most request types, the same with their encoded fields mutated
/// and the CRC made to match, frames cut short, junk), each answered before the next goes.
/// Every frame gets exactly one response (telemetry frames aside), and afterwards the board
/// still answers and its tick still runs. Deterministic (a fixed xorshift sequence).
#[test]
fn the_firmware_answers_every_frame_of_a_fuzzed_exchange_and_keeps_ticking() {
    let mut emu = Emulator::boot("fuzz", None);
    let seeds = [
        Request::Status,
        Request::Setpoints(SetpointBatch {
            seq: 0,
            samples: twinstack::heapless::Vec::from_slice(&[0, 9000, -9000, 100]).unwrap(),
        }),
        Request::Stream(StreamControl::Start),
        Request::Stream(StreamControl::Stop),
        Request::Stream(StreamControl::Rate { divider: 5 }),
        Request::Mode(Mode::OpenLoop),
        Request::Mode(Mode::Bypass),
        Request::LoadParams(awkward_settings()),
        Request::StoreParams {
            boot_mode: Mode::Bypass,
        },
        Request::Waveform(Waveform {
            shape: WaveShape::Sine,
            offset: 0,
            amplitude: 9000,
            frequency_mhz: 100_000,
            decay: None,
        }),
        Request::Record(RecordRequest {
            signal: twinstack::services::recorder::Signal::Drive,
            count: 100,
            decimation: 1,
        }),
        Request::ReadRecord { offset: 0 },
        Request::ReadParams,
        Request::Capture(CaptureRequest {
            signals: 0x7f,
            samples: 50,
            pre_trigger: 0,
            trigger: twinstack::services::recorder::Trigger::Now,
            decimation: 1,
        }),
        Request::CaptureStatus,
        Request::ReadCapture {
            offset: 0,
            count: 64,
        },
        Request::Telemetry(TelemetryRequest::Start {
            signals: 0b1,
            decimation: 500,
        }),
        Request::Telemetry(TelemetryRequest::Stop),
        Request::Learn(LearnRequest::Status),
        Request::CoarseStatus,
    ];
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let (mut run, mut sent, mut answered, mut telemetry) = (0usize, 0usize, 0usize, 0usize);
    let frames_in = |bytes: &[u8], run: &mut usize| {
        let mut frames = 0;
        for &b in bytes {
            if b == 0 {
                frames += usize::from(*run > 0);
                *run = 0;
            } else {
                *run += 1;
            }
        }
        frames
    };
    for _ in 0..400 {
        let seed = encoded(&seeds[next() as usize % seeds.len()]);
        let bytes = match next() % 8 {
            0 | 1 => seed,
            2..=5 => {
                // The message inside the seed's frame.
                let mut d = FrameDecoder::new();
                let mut message = Vec::new();
                for &b in &seed {
                    if let Some(Ok(body)) = d.push(b) {
                        message = frame::message_bytes(body).expect("a sound seed").to_vec();
                    }
                }
                for _ in 0..1 + next() % 3 {
                    let at = next() as usize % message.len().max(1);
                    let value = [0u8, 1, 0x7f, 0x80, 0xff, next() as u8][next() as usize % 6];
                    match next() % 4 {
                        0 if message.len() > 1 => {
                            message.remove(at);
                        }
                        1 => message.insert(at, value),
                        _ if !message.is_empty() => message[at] = value,
                        _ => {}
                    }
                }
                framed(&message)
            }
            6 => {
                let mut cut = seed;
                cut.truncate(next() as usize % cut.len());
                cut
            }
            _ => (0..next() % 40).map(|_| next() as u8).collect(),
        };
        let frames = frames_in(&bytes, &mut run);
        sent += frames;
        emu.uart.write_all(&bytes).expect("write to USART1");
        let mut due = frames;
        while due > 0 {
            match emu.response() {
                Response::Telemetry(_) => telemetry += 1,
                _ => {
                    answered += 1;
                    due -= 1;
                }
            }
        }
    }
    assert!(sent > 250, "the exchange sent {sent} frames");
    // A missing response stalls the loop above (no answer within its timeout); a surplus one
    // shifts every later answer by one and shows here. Close a frame left open and ask for
    // the status: the responses before the status's are exactly the closed frame's.
    let closing = frames_in(&[0], &mut run);
    emu.uart.write_all(&[0]).expect("write to USART1");
    emu.uart
        .write_all(&encoded(&Request::Status))
        .expect("write to USART1");
    let mut before_status = 0;
    let ticks = loop {
        match emu.response() {
            Response::Telemetry(_) => {}
            Response::Status(s) => break s.ticks,
            _ => before_status += 1,
        }
    };
    assert_eq!(
        before_status, closing,
        "one response per frame ({answered} answered)"
    );
    std::thread::sleep(Duration::from_millis(50));
    let later = loop {
        if let (Response::Status(s), _) = answer_amid_telemetry(&mut emu, &Request::Status) {
            break s.ticks;
        }
    };
    assert!(
        later > ticks,
        "the tick runs ({telemetry} telemetry frames seen)"
    );
}

/// What an independent fuzzer found the 32-bit board answering differently from the host
/// build, each now answered alike: a learning-table write whose offset wraps past its bound
/// (the fuzzer's frame itself), telemetry at decimation 0, and a record longer than this
/// image's buffer (its own figure, named).
#[test]
fn the_board_answers_the_fuzzer_s_findings_as_the_host_build_does() {
    let mut emu = Emulator::boot("findings", None);
    let last = (twinstack::services::learning::MAX_BINS - 2) as f64;
    for offset in [u32::MAX, u32::MAX - 1, 1 << 31] {
        assert_eq!(
            emu.request(&Request::Learn(LearnRequest::WriteTable {
                offset,
                values: twinstack::heapless::Vec::from_slice(&[1, 2]).unwrap(),
            })),
            Response::Nack {
                reason: NackReason::Refused(Refusal::new(Field::RecordOffset, Rule::AtMost(last)))
            },
            "offset {offset:#x}"
        );
    }
    // The fuzzer's message bytes as it sent them (it was acknowledged, and nothing written),
    // framed with the current version: `Learn`, `WriteTable`, offset u32::MAX, one value.
    let mut frame = [0u8; 32];
    let n = twinstack::protocol::frame::encode_body_bytes(
        &[
            twinstack::protocol::frame::PROTOCOL_VERSION,
            0x14,
            0x05,
            0xff,
            0xff,
            0xff,
            0xff,
            0x0f,
            0x01,
            0x02,
        ],
        &mut frame,
    )
    .expect("frames");
    emu.uart.write_all(&frame[..n]).expect("write");
    assert_eq!(
        emu.response(),
        Response::Nack {
            // One value: the last offset it may start at is one further.
            reason: NackReason::Refused(Refusal::new(
                Field::RecordOffset,
                Rule::AtMost(last + 1.0)
            ))
        },
        "the fuzzer's frame is refused"
    );
    assert_eq!(
        emu.request(&Request::Telemetry(TelemetryRequest::Start {
            signals: 0b11_1111,
            decimation: 0
        })),
        Response::Nack {
            reason: NackReason::Refused(Refusal::new(
                Field::TelemetryDecimation,
                Rule::AtLeast(6.0)
            ))
        }
    );
    let cap = twinstack::services::recorder::EMULATOR_RECORD_CAPACITY as u32;
    let record = |count| {
        Request::Record(RecordRequest {
            signal: twinstack::services::recorder::Signal::Drive,
            count,
            decimation: 1,
        })
    };
    assert_eq!(
        emu.request(&record(cap + 1)),
        Response::Nack {
            reason: NackReason::Refused(Refusal::new(Field::RecordCount, Rule::AtMost(cap as f64)))
        }
    );
    assert!(matches!(emu.request(&record(cap)), Response::Ack { .. }));
}

/// Every firmware image's own tick binding (the board's TIM2, the emulator's SysTick, each
/// feature set the gates build), and the dual-stage images' coarse task (the board's TIM3, the
/// emulator's EXTI1), reach no panic path: nothing they can branch or call to, directly or
/// through what they call, panics. Nor does any reach a 64-bit library division
/// ([`support::library_divisions`]): what they divide by a setting is prepared off them (the
/// emulator's model of the coarse axis, `IdealAxis`, too).
/// Static, from each image's disassembly.
#[test]
fn the_firmware_tick_links_no_panic_path() {
    let images: [(&str, &[&str], &str, Option<&str>); 6] = [
        ("twinstack-fw", &[], "TIM2", None),
        ("twinstack-fw-dual", &["dual-stage"], "TIM2", Some("TIM3")),
        ("twinstack-feather", &["feather"], "TIM2", None),
        ("twinstack-emu", &["emulator"], "SysTick", None),
        (
            "twinstack-emu-dual",
            &["emulator", "dual-stage"],
            "SysTick",
            Some("EXTI1"),
        ),
        (
            "twinstack-feather-emu",
            &["emulator", "feather"],
            "SysTick",
            None,
        ),
    ];
    for (bin, features, tick, coarse) in images {
        let elf = support::build_image(support::FIRMWARE, bin, features);
        for root in [Some(tick), coarse].into_iter().flatten() {
            let panics = support::panic_paths(&elf, root);
            assert!(
                panics.is_empty(),
                "{bin} {features:?}: {root} reaches {panics:?}"
            );
            let divisions = support::library_divisions(&elf, root);
            assert!(
                divisions.is_empty(),
                "{bin} {features:?}: {root} reaches 64-bit library divisions {divisions:?}"
            );
        }
        // Nor does it touch the FPU outside the floating-point models' own steps: the tick
        // of an integer model, or of none, pays no floating-point context.
        let fpu = support::floating_point_functions(&elf, tick, "step_out_of_line");
        assert!(
            fpu.is_empty(),
            "{bin} {features:?}: {tick} runs floating-point instructions outside the \
             floating-point models' steps: {fpu:?}"
        );
    }
}
