//! The firmware image itself, booted in QEMU's `netduinoplus2` (an STM32F405): it must answer
//! protocol frames on USART1 (status, setpoint batches, stream control, a parameter load, the
//! recorder; a corrupted frame NACKed), its control tick must run, and the parameter record in
//! flash must be honoured (or refused with defaults and a flag).
//!
//! Builds the `emulator` image (`cargo build-emu`) into `target/firmware`, installing the
//! Rust target and `qemu-system-arm` first if they are missing (see `tests/support`).

mod support;

use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::Child;
use std::time::{Duration, Instant};

use twinstack::param_store::{self, BoardSettings, SafeState, HEADER_LEN, MAX_RECORD};
use twinstack::protocol::decoder::FrameDecoder;
use twinstack::protocol::frame::{self, FrameError, MAX_ENCODED};
use twinstack::protocol::messages::*;

/// Address of the parameter sector (flash sector 11).
const PARAM_SECTOR: u32 = 0x080E_0000;

/// A running QEMU with USART1 on a Unix socket; killed and cleaned up on drop.
struct Emulator {
    child: Child,
    uart: UnixStream,
    scratch: PathBuf,
    decoder: FrameDecoder,
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
        let elf = support::build_image(support::FIRMWARE, "twinstack-fw", &["emulator"]);
        let scratch =
            std::env::temp_dir().join(format!("twinstack-emu-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&scratch);
        std::fs::create_dir_all(&scratch).expect("scratch directory");
        let socket = scratch.join("uart.sock");
        let mut cmd = support::qemu_command(&elf);
        cmd.arg("-chardev")
            .arg(format!(
                "socket,id=u1,path={},server=on,wait=on",
                socket.display()
            ))
            .args(["-serial", "chardev:u1"]);
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

fn record_of(settings: &BoardSettings) -> Vec<u8> {
    let mut buf = [0u8; MAX_RECORD];
    let n = param_store::encode(BoardSettings::VERSION, &settings.to_payload(), &mut buf)
        .expect("record fits");
    buf[..n].to_vec()
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
    assert_eq!(a.tick_rate_hz, BoardSettings::DEFAULT.tick_rate_hz);
    // Nothing streams: no underruns; the whole queue is free.
    assert_eq!((b.underruns, b.queue_fill), (0, 0), "{b:?}");
    assert_eq!(
        b.credits as usize,
        twinstack::control_loop::SETPOINT_CAPACITY
    );
    // Nothing was stored in the emulated flash: the compiled-in parameters, flagged.
    assert!(b.has(StatusReport::DEFAULTS), "{b:?}");
    assert_eq!(b.mode(), twinstack::settings::Mode::ClosedLoop);
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
    let free = twinstack::control_loop::SETPOINT_CAPACITY as u16;
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
    let at: Vec<usize> = ramp
        .iter()
        .map(|&x| {
            values
                .iter()
                .position(|&v| v == (x as i32) << 15)
                .unwrap_or_else(|| panic!("setpoint {x} never reached: {values:?}"))
        })
        .collect();
    assert!(at.windows(2).all(|w| w[1] == w[0] + 10), "{at:?}");
    // A parameter load: validated, swapped in, reported.
    let mut params = twinstack::default_config::boot_param_set(SafeState::Bias).unwrap();
    params.mode = twinstack::settings::Mode::OpenLoop;
    assert!(matches!(
        emu.request(&Request::LoadParams(params.clone())),
        Response::Ack { .. }
    ));
    let s = emu.status();
    assert_eq!(s.mode(), twinstack::settings::Mode::OpenLoop);
    assert!(!s.has(StatusReport::DEFAULTS));
    // One that cannot be inverted is refused with its reason; the mode stays.
    if let ModelParams::PrandtlIshlinskii { weights, .. } = &mut params.model {
        weights[0] = -1.0;
    }
    assert!(matches!(
        emu.request(&Request::LoadParams(params)),
        Response::Nack {
            reason: NackReason::InvalidParams(_)
        }
    ));
    assert_eq!(emu.status().mode(), twinstack::settings::Mode::OpenLoop);
}

#[test]
fn a_stored_parameter_record_sets_the_tick_rate() {
    let stored = BoardSettings {
        tick_rate_hz: 20_000,
        safe_state: SafeState::Zero,
    };
    let mut emu = Emulator::boot("stored", Some(&record_of(&stored)));
    let s = emu.status();
    assert_eq!(s.tick_rate_hz, 20_000, "{s:?}");
}

#[test]
fn a_record_with_a_bad_crc_boots_on_defaults_and_says_so() {
    let mut record = record_of(&BoardSettings {
        tick_rate_hz: 20_000,
        safe_state: SafeState::Zero,
    });
    record[HEADER_LEN] ^= 0x40; // corrupt the stored rate; the CRC no longer matches
    let mut emu = Emulator::boot("bad-crc", Some(&record));
    let s = emu.status();
    assert_eq!(s.tick_rate_hz, BoardSettings::DEFAULT.tick_rate_hz, "{s:?}");
    assert!(s.has(StatusReport::DEFAULTS), "{s:?}");
    assert!(s.ticks > 0, "the tick runs on defaults: {s:?}");
}
