//! The firmware image itself, booted in QEMU's `netduinoplus2` (an STM32F405): it must answer
//! the status query on USART1, its control tick must run, and the parameter record in flash
//! must be honoured (or refused with defaults and a flag).
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
use twinstack::status_report::{StatusReport, STATUS_REQUEST};

/// Address of the parameter sector (flash sector 11).
const PARAM_SECTOR: u32 = 0x080E_0000;

/// A running QEMU with USART1 on a Unix socket; killed and cleaned up on drop.
struct Emulator {
    child: Child,
    uart: UnixStream,
    scratch: PathBuf,
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
        let elf = support::build_image("twinstack-fw", &["emulator"]);
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
        };
        emu.wait_until_listening();
        emu
    }

    /// Bytes sent before the firmware has enabled USART1 are lost, so ask until it answers
    /// (within 20 s), then discard any further answers to the repeated requests.
    fn wait_until_listening(&mut self) {
        let start = Instant::now();
        self.uart
            .set_read_timeout(Some(Duration::from_millis(500)))
            .expect("read timeout");
        let mut byte = [0u8; 1];
        loop {
            self.uart
                .write_all(&[STATUS_REQUEST])
                .expect("write to USART1");
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
        self.uart
            .set_read_timeout(Some(Duration::from_secs(10)))
            .expect("read timeout");
    }

    /// Sends `bytes` and reads one reply line.
    fn query(&mut self, bytes: &[u8]) -> String {
        self.uart.write_all(bytes).expect("write to USART1");
        let mut line = Vec::new();
        let mut byte = [0u8; 1];
        while byte[0] != b'\n' {
            match self.uart.read(&mut byte) {
                Ok(1) => line.push(byte[0]),
                Ok(_) => panic!("USART1 closed after {:?}", String::from_utf8_lossy(&line)),
                Err(e) => panic!(
                    "no status reply from the firmware ({e}); got so far {:?}",
                    String::from_utf8_lossy(&line)
                ),
            }
            assert!(
                line.len() < 512,
                "reply line too long: {:?}",
                String::from_utf8_lossy(&line)
            );
        }
        String::from_utf8(line).expect("reply is ASCII")
    }
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
    // A byte that is not a request is ignored; the request after it is answered once.
    let first = emu.query(&[b'x', STATUS_REQUEST]);
    let a = StatusReport::parse_line(&first).unwrap_or_else(|e| panic!("{e}: {first:?}"));
    std::thread::sleep(Duration::from_millis(300));
    let second = emu.query(&[STATUS_REQUEST]);
    let b = StatusReport::parse_line(&second).unwrap_or_else(|e| panic!("{e}: {second:?}"));
    assert!(
        b.ticks > a.ticks,
        "tick counter did not advance: {first:?} then {second:?}"
    );
    assert_eq!(a.tick_rate_hz, BoardSettings::DEFAULT.tick_rate_hz);
    // No setpoints are streamed, so every tick is an underrun.
    assert!(b.underruns > 0 && b.underruns <= b.ticks, "{second:?}");
    // Nothing was stored in the emulated flash: defaults, and the reason is reported.
    assert!(
        matches!(b.params, "erased" | "bad-magic"),
        "params flag should say why the defaults run: {second:?}"
    );
}

#[test]
fn a_stored_parameter_record_sets_the_tick_rate() {
    let stored = BoardSettings {
        tick_rate_hz: 20_000,
        safe_state: SafeState::Zero,
    };
    let mut emu = Emulator::boot("stored", Some(&record_of(&stored)));
    let line = emu.query(&[STATUS_REQUEST]);
    let s = StatusReport::parse_line(&line).unwrap_or_else(|e| panic!("{e}: {line:?}"));
    assert_eq!(s.params, "stored", "{line:?}");
    assert_eq!(s.tick_rate_hz, 20_000, "{line:?}");
}

#[test]
fn a_record_with_a_bad_crc_boots_on_defaults_and_says_so() {
    let mut record = record_of(&BoardSettings {
        tick_rate_hz: 20_000,
        safe_state: SafeState::Zero,
    });
    record[HEADER_LEN] ^= 0x40; // corrupt the stored rate; the CRC no longer matches
    let mut emu = Emulator::boot("bad-crc", Some(&record));
    let line = emu.query(&[STATUS_REQUEST]);
    let s = StatusReport::parse_line(&line).unwrap_or_else(|e| panic!("{e}: {line:?}"));
    assert_eq!(s.params, "bad-crc", "{line:?}");
    assert_eq!(
        s.tick_rate_hz,
        BoardSettings::DEFAULT.tick_rate_hz,
        "{line:?}"
    );
    assert!(s.ticks > 0, "the tick runs on defaults: {line:?}");
}
