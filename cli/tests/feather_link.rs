//! The Feather profile's image in QEMU (`twinstack-feather-emu`, `cargo build-emu-feather`):
//! the application on the Adafruit Feather STM32F405 Express's pins, with the emulator's clock
//! and tick. QEMU's `netduinoplus2` is the same chip; what it models of the Feather profile is
//! the host link on USART3 (its third `-serial`) and the GPIO writes (logged by `-d unimp`):
//!
//! * the host tools talk to it over USART3 — status (the tick runs), the settings read back,
//!   a load read back as sent — and USART1, the driver board's link, stays silent;
//! * its pins are set up where the bring-up chapter wires them: A0/A1/A2 (PA4–PA6) analog, TX/RX
//!   (PB10/PB11) in AF7, and every tick's trigger word lands in GPIOC's `BSRR` (D13, D12, D11,
//!   D5), none in GPIOA's;
//! * `twinstack selftest` runs its bring-up checks over USART3: the safe state and the link
//!   pass, and what QEMU does not model skips, each saying why.
//!
//! Builds the image into `target/firmware` (the root crate's `tests/support`).

#[path = "../../tests/support/mod.rs"]
mod support;

use hal_sim::port::{self, PortSpec};
use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::Child;
use std::time::{Duration, Instant};
use twinstack::protocol::frame;
use twinstack::protocol::messages::{Image, Mode, Request};
use twinstack_link::client::Client;
use twinstack_link::Transport;

/// QEMU running the Feather's emulator image: USART1 and USART3 on Unix sockets, the
/// unimplemented-device log in the scratch directory; killed on drop.
struct Qemu {
    child: Child,
    scratch: PathBuf,
}

impl Drop for Qemu {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.scratch);
    }
}

impl Qemu {
    fn usart1(&self) -> PathBuf {
        self.scratch.join("usart1.sock")
    }
    fn usart3(&self) -> PathBuf {
        self.scratch.join("usart3.sock")
    }
    fn unimp_log(&self) -> PathBuf {
        self.scratch.join("unimp.log")
    }
}

fn boot(name: &str) -> Qemu {
    let elf = support::build_image(
        support::FIRMWARE,
        "twinstack-feather-emu",
        &["emulator", "feather"],
    );
    let scratch =
        std::env::temp_dir().join(format!("twinstack-feather-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&scratch);
    std::fs::create_dir_all(&scratch).expect("scratch directory");
    let mut qemu = Qemu {
        child: support::emulator_command(&elf)
            .arg("-chardev")
            .arg(format!(
                "socket,id=u1,path={},server=on,wait=off",
                scratch.join("usart1.sock").display()
            ))
            .arg("-chardev")
            .arg(format!(
                "socket,id=u3,path={},server=on,wait=off",
                scratch.join("usart3.sock").display()
            ))
            // USART1, USART2, USART3: QEMU's first three serial ports.
            .args(["-serial", "chardev:u1", "-serial", "null"])
            .args(["-serial", "chardev:u3"])
            .args(["-d", "unimp", "-D"])
            .arg(scratch.join("unimp.log"))
            .spawn()
            .expect("qemu-system-arm starts"),
        scratch,
    };
    // QEMU creates the sockets before it runs the image.
    let start = Instant::now();
    while !(qemu.usart1().exists() && qemu.usart3().exists()) {
        if let Ok(Some(status)) = qemu.child.try_wait() {
            panic!("QEMU exited before opening its sockets: {status}");
        }
        assert!(start.elapsed() < Duration::from_secs(20), "no QEMU sockets");
        std::thread::sleep(Duration::from_millis(50));
    }
    qemu
}

/// Asks for the status over `socket` until the firmware answers (it enables its USART a moment
/// after boot; bytes before that are lost).
fn connect(socket: &Path) -> Client<Box<dyn Transport>> {
    let transport = port::open(&PortSpec::Unix(socket.to_path_buf()), 0).expect("socket opens");
    let mut client = Client::new(transport);
    client.set_timeout(Duration::from_millis(300));
    let start = Instant::now();
    loop {
        client.resync(Duration::from_millis(50)).expect("resync");
        if client.status().is_ok() {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "the Feather image never answered on USART3 in 20 s"
        );
    }
    client.set_timeout(Duration::from_secs(5));
    client
}

#[test]
fn the_feather_image_answers_on_usart3_and_keeps_usart1_silent() {
    let qemu = boot("link");
    let mut client = connect(&qemu.usart3());
    let a = client.status().expect("status");
    client.wait(Duration::from_millis(200)).unwrap();
    let b = client.status().expect("status");
    assert!(b.ticks > a.ticks, "the tick did not advance: {a:?} {b:?}");
    assert_eq!(b.image(), Image::Emulator, "{b:?}");
    assert_eq!(b.mode(), Mode::Bypass, "{b:?}");

    // The compiled-in settings read back; a load (open loop, a representative P–I model on
    // the default ranges) reads back as sent.
    let defaults = client.read_params().expect("the settings");
    assert_eq!(defaults, twinstack::config::settings::Settings::default());
    let loaded = twinstack::config::settings::Settings {
        compensator: Some(twinstack::config::settings::representative_pi(16).unwrap()),
        mode: Mode::OpenLoop,
        ..defaults
    };
    client.load_params(&loaded).expect("the load is taken");
    assert_eq!(client.read_params().unwrap(), loaded, "read back as sent");
    assert_eq!(client.status().unwrap().mode(), Mode::OpenLoop);

    // USART1 (the driver board's link) is not the Feather's: a status request there gets
    // nothing back.
    let mut usart1 = UnixStream::connect(qemu.usart1()).expect("USART1's socket");
    usart1
        .set_read_timeout(Some(Duration::from_millis(300)))
        .unwrap();
    let mut request = vec![0u8; frame::MAX_ENCODED + 1];
    let n = frame::encode(&Request::Status, &mut request).unwrap();
    let mut byte = [0u8; 1];
    for _ in 0..3 {
        usart1.write_all(&request[..n]).unwrap();
        assert!(
            !matches!(usart1.read(&mut byte), Ok(1)),
            "the Feather image answered on USART1"
        );
    }
    // USART3 still answers.
    assert!(client.status().unwrap().ticks > b.ticks);
}

/// `(port, register offset, value)` of each write QEMU logged to an unimplemented device.
fn gpio_writes(log: &str) -> Vec<(String, u32, u32)> {
    let hex = |s: &str| u32::from_str_radix(s.trim().trim_start_matches("0x"), 16).ok();
    log.lines()
        .filter(|l| l.starts_with("GPIO") && l.contains("device write"))
        .filter_map(|l| {
            let port = l.split(':').next()?.to_string();
            let offset = hex(l.split("offset ").nth(1)?.split(',').next()?)?;
            let value = hex(l.rsplit("value ").next()?.trim_end_matches(')'))?;
            Some((port, offset, value))
        })
        .collect()
}

#[test]
fn the_feather_image_sets_its_pins_up_on_the_feather_s_header() {
    const MODER: u32 = 0x00;
    const PUPDR: u32 = 0x0C;
    const BSRR: u32 = 0x18;
    const AFRH: u32 = 0x24;
    let qemu = boot("pins");
    let mut client = connect(&qemu.usart3());
    let first = client.status().unwrap().ticks;
    // A few thousand ticks' worth of trigger writes.
    while client.status().unwrap().ticks < first + 2_000 {
        client.wait(Duration::from_millis(50)).unwrap();
    }
    let log = std::fs::read_to_string(qemu.unimp_log()).expect("the unimp log");
    let writes = gpio_writes(&log);
    let wrote = |port: &str, offset: u32, value: u32| {
        writes
            .iter()
            .any(|(p, o, v)| p == port && *o == offset && *v == value)
    };
    // QEMU's GPIO reads 0, so each read-modify-write of a mode register shows one pin's bits.
    // A0, A1 (the DAC) and A2 (the sensor) analog: MODER 0b11 at bits 2n.
    for pin in [4, 5, 6] {
        assert!(
            wrote("GPIOA", MODER, 0b11 << (2 * pin)),
            "PA{pin} not analog"
        );
    }
    // TX/RX: PB10/PB11 alternate (MODER 0b10) function 7 (AFRH).
    for pin in [10, 11] {
        assert!(wrote("GPIOB", MODER, 0b10 << (2 * pin)), "PB{pin} not AF");
        assert!(
            wrote("GPIOB", AFRH, 7 << (4 * (pin - 8))),
            "PB{pin} not AF7"
        );
    }
    // D13, D12, D11, D5 (PC1–PC3, PC7) outputs; D6 (PC6) pulled down.
    for pin in [1, 2, 3, 7] {
        assert!(
            wrote("GPIOC", MODER, 0b01 << (2 * pin)),
            "PC{pin} not an output"
        );
    }
    assert!(wrote("GPIOC", PUPDR, 0b10 << 12), "PC6 not pulled down");
    // The driver board's sensor pin (PA0) and link pins (PA9/PA10) are left alone.
    for (pin, bits) in [(0, 0b11), (9, 0b10), (10, 0b10)] {
        assert!(
            !wrote("GPIOA", MODER, bits << (2 * pin)),
            "PA{pin} configured"
        );
    }
    // Every tick writes the trigger outputs in one GPIOC BSRR store, all four pins set or
    // reset; GPIOA's BSRR is never written.
    let words: Vec<u32> = writes
        .iter()
        .filter(|(p, o, _)| p == "GPIOC" && *o == BSRR)
        .map(|w| w.2)
        .collect();
    assert!(words.len() > 1000, "{} GPIOC BSRR writes", words.len());
    let full = |w: u32| twinstack::sources::scan::bsrr_word(((w >> 1) & 7) as u8) == w;
    assert!(
        words.iter().filter(|&&w| full(w)).count() > 1000,
        "{:x?}",
        &words[..8]
    );
    assert!(
        !writes.iter().any(|(p, o, _)| p == "GPIOA" && *o == BSRR),
        "a trigger word went to GPIOA"
    );
}

/// The bring-up chapter's first command on the Feather, in QEMU: `twinstack selftest` over
/// USART3. The safe state and the link (echoes through QEMU's UART) pass; the tick rate (no
/// crystal behind QEMU's timer), the loopback (no DAC or ADC conversion), the flash (no
/// parameter storage in QEMU) and the watchdog (none modelled: the image refuses the drill)
/// skip, each saying why; none fails.
#[test]
fn the_feather_image_passes_its_selftest_where_qemu_models_the_chip() {
    let qemu = boot("selftest");
    drop(connect(&qemu.usart3())); // the firmware answers on USART3
    let port = format!("unix:{}", qemu.usart3().display());
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args(["selftest", "--port", &port, "--echoes", "30", "--json"])
        .output()
        .expect("twinstack runs");
    let out = String::from_utf8_lossy(&o.stdout);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{out}{err}");
    let report: serde_json::Value = serde_json::from_str(out.trim()).expect("one JSON object");
    assert_eq!(report["image"], "emulator", "{report}");
    let outcomes: Vec<(String, String, String)> = report["checks"]
        .as_array()
        .expect("checks")
        .iter()
        .map(|c| {
            (
                c["check"].as_str().unwrap().to_string(),
                c["outcome"].as_str().unwrap().to_string(),
                c["detail"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    let expected = [
        ("safe-state", "PASS", "idle"),
        ("link", "PASS", "30 echoes"),
        ("tick-rate", "SKIP", "no crystal"),
        ("loopback", "SKIP", "no DAC"),
        ("flash", "SKIP", "no parameter storage"),
        ("watchdog", "SKIP", "QEMU models none"),
    ];
    assert_eq!(outcomes.len(), expected.len(), "{report}");
    for ((name, outcome, detail), (want_name, want, needle)) in outcomes.iter().zip(expected) {
        assert_eq!(
            (name.as_str(), outcome.as_str()),
            (want_name, want),
            "{report}"
        );
        assert!(
            detail.contains(needle),
            "{name}: {needle:?} not in {detail}"
        );
    }
}
