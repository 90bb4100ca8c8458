//! Sustained setpoint throughput of the host streamer (`twinstack_link::streamer`).
//!
//! ```text
//! cargo run --release -p twinstack-cli --example stream_throughput                 # in-process
//! cargo run --release -p twinstack-cli --example stream_throughput -- --emulator ELF [--seconds S]
//! cargo run --release -p twinstack-cli --example stream_throughput -- --port PORT   # a real board
//! ```
//!
//! **In-process** (`SimDevice`: the library's command handler and control loop on a UART
//! modelled at the board's link rate, `LINK_BAUD`, 10 bits a byte, simulated time): streams
//! 10 s of setpoints at one per
//! tick — a ±0.95 sine, and a full-range stream whose every sample would take 3 bytes as a
//! varint (packed, both take two) — at 50 kHz, then at higher tick rates up to the board's
//! highest, 100 kHz. Reports setpoints per
//! second of board time, underruns counted by the board while the stream still had setpoints
//! to deliver, refusals, wire bytes per setpoint and the line's utilisation.
//!
//! **Emulator** (`--emulator ELF`: the firmware's emulator image `twinstack-emu`, `cargo
//! build-emu`): boots
//! QEMU's netduinoplus2 with USART1 on a Unix socket, once per row, and streams the same sine
//! for `--seconds` of the guest's ticks (default 10) at dividers 1, 2 and 4, with QEMU's
//! clock following the host's and with `-icount shift=0,sleep=on`. QEMU's UART is not paced
//! at a baud rate and hands the guest one byte per interrupt, so this measures QEMU and the
//! emulated firmware, not the board's link. Needs `qemu-system-arm` on the PATH.

use hal_sim::port::{self, PortSpec};
use hal_sim::sim_device::{SimDevice, SimDeviceConfig};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use twinstack::protocol::messages::UnderrunPolicy;
use twinstack::protocol::LINK_BAUD;
use twinstack_link::client::Client;
use twinstack_link::streamer::{stream_setpoints, StreamOptions, StreamReport};
use twinstack_link::Transport;

fn sine(n: usize, rate: f64) -> Vec<i16> {
    (0..n)
        .map(|i| {
            let t = i as f64 / rate;
            (0.95 * (std::f64::consts::TAU * 37.0 * t).sin() * 32768.0).round() as i16
        })
        .collect()
}

/// Every sample ≥ 2^13 in magnitude (3 bytes as a postcard zigzag varint).
fn worst_case(n: usize) -> Vec<i16> {
    (0..n)
        .map(|i| {
            let v = 9000 + ((i * 7919) % 22_000) as i16;
            if i % 2 == 0 {
                v
            } else {
                -v
            }
        })
        .collect()
}

fn stream<T: Transport>(
    client: &mut Client<T>,
    samples: &[i16],
) -> Result<(StreamReport, f64), String> {
    stream_divided(client, samples, 1)
}

fn stream_divided<T: Transport>(
    client: &mut Client<T>,
    samples: &[i16],
    divider: u16,
) -> Result<(StreamReport, f64), String> {
    let options = StreamOptions {
        divider,
        underrun: Some(UnderrunPolicy::Hold),
        ..StreamOptions::default()
    };
    let wall = Instant::now();
    let r = stream_setpoints(client, samples, &options, |_| {}).map_err(|e| e.to_string())?;
    Ok((r, wall.elapsed().as_secs_f64()))
}

fn print_report(label: &str, r: &StreamReport, tick_rate: f64, baud: Option<f64>, wall: f64) {
    let end = r.drained.unwrap_or(r.after_last_batch);
    // Board time from the first status to the one right after the last ACK, plus the queue
    // it still held (played at one setpoint per tick).
    let ticks = r.after_last_batch.ticks.wrapping_sub(r.before.ticks) as f64
        + r.after_last_batch.queue_fill as f64;
    let seconds = ticks / tick_rate;
    let per_setpoint = r.link.bytes_sent as f64 / r.accepted.max(1) as f64;
    let utilisation = baud
        .map(|b| {
            format!(
                "{:5.1} %",
                100.0 * r.link.bytes_sent as f64 * 10.0 / b / seconds
            )
        })
        .unwrap_or_else(|| "   -   ".into());
    println!(
        "{label:<34} {:>8} {:>8.3} {:>9.0} {:>9} {:>5} {:>6.3} {:>6.3} {utilisation} {:>7.2}",
        r.accepted,
        seconds,
        r.accepted as f64 / seconds,
        r.underruns_during_stream(),
        r.nacks.len(),
        per_setpoint,
        r.link.bytes_received as f64 / r.accepted.max(1) as f64,
        wall
    );
    if end.overruns.wrapping_sub(r.before.overruns) != 0 {
        println!(
            "    ({} overruns)",
            end.overruns.wrapping_sub(r.before.overruns)
        );
    }
}

fn header() {
    println!(
        "{:<34} {:>8} {:>8} {:>9} {:>9} {:>5} {:>6} {:>6} {:>7} {:>7}",
        "", "setpts", "board s", "setpt/s", "underrun", "nacks", "B/sp↑", "B/sp↓", "line", "wall s"
    );
}

fn in_process(seconds: f64) -> Result<(), String> {
    println!(
        "in-process SimDevice, {} Mbaud (10 bits/byte), divider 1, hold on underrun:",
        f64::from(LINK_BAUD) / 1e6
    );
    header();
    for rate in [50_000.0, 60_000.0, 70_000.0, 80_000.0, 90_000.0, 100_000.0] {
        let n = (seconds * rate) as usize;
        for (name, samples) in [("sine ±0.95", sine(n, rate)), ("full range", worst_case(n))] {
            let mut config = SimDeviceConfig::paper();
            config.board.plant.dt = 1.0 / rate;
            let dev = SimDevice::new(config).map_err(|e| e.to_string())?;
            let mut client = Client::new(dev);
            let label = format!("{name} @ {} kHz", rate / 1000.0);
            match stream(&mut client, &samples) {
                Ok((r, wall)) => print_report(&label, &r, rate, Some(f64::from(LINK_BAUD)), wall),
                Err(e) => println!("{label:<34} failed: {e}"),
            }
        }
    }
    Ok(())
}

/// A host → board line that damages one bit in every `every`-th frame sent.
struct LossyLine<T> {
    inner: T,
    every: u64,
    frames: u64,
    damaged: u64,
}

impl<T: Transport> Transport for LossyLine<T> {
    fn send(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.frames += 1;
        if self.frames.is_multiple_of(self.every) && bytes.len() > 4 {
            let mut copy = bytes.to_vec();
            let mid = copy.len() / 2;
            copy[mid] ^= 0x08;
            self.damaged += 1;
            return self.inner.send(&copy);
        }
        self.inner.send(bytes)
    }

    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> std::io::Result<usize> {
        self.inner.receive(buf, timeout)
    }
}

fn lossy(seconds: f64) -> Result<(), String> {
    println!();
    println!(
        "in-process, 50 kHz, {} Mbaud, one bit flipped in every N-th host → board frame:",
        f64::from(LINK_BAUD) / 1e6
    );
    println!(
        "{:<34} {:>8} {:>9} {:>8} {:>7} {:>9} {:>8} {:>10}",
        "", "setpts", "damaged", "nacks", "resent", "underrun", "crc err", "batches"
    );
    for every in [1000u64, 100, 20] {
        let dev = SimDevice::new(SimDeviceConfig::paper()).map_err(|e| e.to_string())?;
        let mut client = Client::new(LossyLine {
            inner: dev,
            every,
            frames: 0,
            damaged: 0,
        });
        let samples = sine((seconds * 50_000.0) as usize, 50_000.0);
        let (r, _) = stream(&mut client, &samples)?;
        let line = client.transport();
        let end = r.drained.unwrap_or(r.after_last_batch);
        println!(
            "{:<34} {:>8} {:>9} {:>8} {:>7} {:>9} {:>8} {:>10}",
            format!("every {every}th frame damaged"),
            r.accepted,
            line.damaged,
            r.nacks.len(),
            r.resent_batches,
            r.underruns_during_stream(),
            end.crc_errors.wrapping_sub(r.before.crc_errors),
            // Each batch taken exactly once: the board's sequence number moved by the count.
            if r.accepted == samples.len()
                && line
                    .inner
                    .handler()
                    .next_seq()
                    .wrapping_sub(r.before.next_seq) as usize
                    == samples.len().div_ceil(96) % 65_536
            {
                "each once"
            } else {
                "WRONG"
            }
        );
    }
    Ok(())
}

struct Qemu {
    child: Child,
    dir: std::path::PathBuf,
}

impl Drop for Qemu {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// QEMU's modes for the emulator runs: its default (the guest's clock is the host's: when
/// QEMU runs the guest slower than the chip, the SysTick interrupts it cannot take are lost
/// and counted as overruns) and `-icount shift=0,sleep=on` (one instruction a nanosecond of
/// guest time, idle time at the host's pace: no tick is lost, the guest runs as fast as QEMU
/// executes it).
const QEMU_MODES: [(&str, &[&str]); 2] = [
    ("host clock", &[]),
    ("icount shift=0,sleep=on", &["-icount", "shift=0,sleep=on"]),
];

/// A booted emulator: QEMU (killed on drop), a client on its UART, its tick rate (Hz).
type Emulator = (Qemu, Client<Box<dyn Transport>>, f64);

/// Boots the emulator image with USART1 on a Unix socket and waits until it answers.
fn boot_emulator(elf: &str, extra: &[&str], run: usize) -> Result<Emulator, String> {
    let dir = std::env::temp_dir().join(format!("stream-throughput-{}-{run}", std::process::id()));
    std::fs::create_dir_all(&dir).map_err(|e| e.to_string())?;
    let sock = dir.join("uart.sock");
    let child = Command::new("qemu-system-arm")
        .args([
            "-machine",
            "netduinoplus2",
            "-cpu",
            "cortex-m4",
            "-nographic",
        ])
        .args([
            "-monitor",
            "none",
            "-semihosting-config",
            "enable=on,target=native",
        ])
        .args(extra)
        .arg("-chardev")
        .arg(format!(
            "socket,id=u1,path={},server=on,wait=on",
            sock.display()
        ))
        .args(["-serial", "chardev:u1", "-kernel", elf])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .map_err(|e| format!("qemu-system-arm: {e}"))?;
    let qemu = Qemu { child, dir };
    let spec = PortSpec::Unix(sock.clone());
    let start = Instant::now();
    let transport = loop {
        match port::open(&spec, 0) {
            Ok(t) => break t,
            Err(e) if start.elapsed() > Duration::from_secs(20) => return Err(e.to_string()),
            Err(_) => std::thread::sleep(Duration::from_millis(50)),
        }
    };
    let mut client = Client::new(transport);
    // The firmware enables USART1 a moment after boot: ask until it answers.
    client.set_timeout(Duration::from_millis(300));
    let mut status = None;
    while start.elapsed() < Duration::from_secs(20) {
        client
            .resync(Duration::from_millis(20))
            .map_err(|e| e.to_string())?;
        if let Ok(s) = client.status() {
            status = Some(s);
            break;
        }
    }
    let status = status.ok_or("the emulator never answered a status request")?;
    client.set_timeout(Duration::from_secs(10));
    Ok((qemu, client, status.tick_rate_hz as f64))
}

/// Streams `seconds` of the guest's ticks at dividers 1, 2 and 4 in each of QEMU's modes,
/// each on a freshly booted emulator.
fn emulator(elf: &str, seconds: f64) -> Result<(), String> {
    println!(
        "emulator ({elf}), QEMU netduinoplus2, USART1 on a Unix socket (not baud-paced), \
         {seconds} s of ticks per run, hold on underrun:"
    );
    println!(
        "{:<24} {:>4} {:>8} {:>8} {:>9} {:>9} {:>9} {:>7} {:>7} {:>6}",
        "QEMU",
        "div",
        "setpts",
        "guest s",
        "setpt/s",
        "underrun",
        "overruns",
        "wall s",
        "sp/wall",
        "guest×"
    );
    let mut run = 0;
    for (mode, extra) in QEMU_MODES {
        for divider in [1u16, 2, 4] {
            run += 1;
            let (_qemu, mut client, rate) = boot_emulator(elf, extra, run)?;
            let samples = sine(
                (seconds * rate / divider as f64) as usize,
                rate / divider as f64,
            );
            let (r, wall) = stream_divided(&mut client, &samples, divider)?;
            let end = r.drained.unwrap_or(r.after_last_batch);
            let guest = end.ticks.wrapping_sub(r.before.ticks) as f64 / rate;
            println!(
                "{mode:<24} {divider:>4} {:>8} {guest:>8.3} {:>9.0} {:>9} {:>9} {wall:>7.2} {:>7.0} {:>6.2}",
                r.accepted,
                r.accepted as f64 / guest,
                r.underruns_during_stream(),
                end.overruns.wrapping_sub(r.before.overruns),
                r.accepted as f64 / wall,
                guest / wall,
            );
        }
    }
    Ok(())
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let value = |flag: &str| {
        args.iter()
            .position(|a| a == flag)
            .and_then(|i| args.get(i + 1).cloned())
    };
    let seconds = match value("--seconds").map(|s| s.parse::<f64>()) {
        None => 10.0,
        Some(Ok(s)) if s > 0.0 && s.is_finite() => s,
        Some(_) => {
            eprintln!("--seconds needs a positive number");
            std::process::exit(2);
        }
    };
    let result = if let Some(elf) = value("--emulator") {
        emulator(&elf, seconds)
    } else if let Some(p) = value("--port") {
        p.parse::<PortSpec>()
            .map_err(|e| e.to_string())
            .and_then(|spec| port::open(&spec, port::DEFAULT_BAUD).map_err(|e| e.to_string()))
            .and_then(|t| {
                let mut client = Client::new(t);
                client
                    .resync(Duration::from_millis(20))
                    .map_err(|e| e.to_string())?;
                let rate = client.status().map_err(|e| e.to_string())?.tick_rate_hz as f64;
                header();
                let (r, wall) = stream(&mut client, &sine((seconds * rate) as usize, rate))?;
                print_report(&format!("sine ±0.95 on {p}"), &r, rate, None, wall);
                Ok(())
            })
    } else {
        in_process(seconds).and_then(|_| lossy(seconds))
    };
    if let Err(e) = result {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}
