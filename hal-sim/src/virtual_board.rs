//! The virtual board: one [`SimDevice`] — the simulated stage, the library's control loop and
//! command handler, exactly as `--port sim` runs them — kept alive as a server, its UART served
//! over TCP, its simulated time paced by the wall clock.
//!
//! Unlike `--port sim` (a fresh board for every command), the board outlives its clients: one
//! client at a time talks to it; when that client disconnects the board keeps running with its
//! state (settings loaded, stream position, recorder) and the next client finds it as the last
//! one left it. So `twinstack load`, `twinstack stream`, `twinstack record` can rehearse a workflow on
//! one board, as they would on the real one.
//!
//! **Pacing.** Each turn of the loop forwards what the client sent to the device's UART, runs
//! the device forward by the wall-clock time elapsed × `speed` (at most [`MAX_STEP`] of
//! simulated time per turn, so the socket is served between steps), and writes the response
//! bytes that have arrived to the client. Time a turn could not run (the host descheduled the
//! server, or was busy) is owed and run in the next turns, so the board's clock keeps the wall
//! clock's rate, as a board's crystal does (`twinstack selftest` measures it); only a debt
//! beyond [`MAX_DEBT`] (a host too slow for real time) is dropped, and the board then runs
//! slower than real time. Before the client's bytes go onto the board's line the whole debt is
//! run, so a request is answered at the board time it was sent, not behind it. `speed` 0 runs as fast as possible ([`MAX_STEP`] per turn). The
//! board runs while no client is connected, too.
//!
//! **Pseudo-terminal** (Unix, [`serve_pty`]): the board's UART is the master side of a pty; a
//! client opens the slave's path (`/dev/pts/N`) as it would a USB–UART adapter. A client is
//! connected while the slave is open (the master's reads fail with no slave open), one at a
//! time as the client's exclusive open enforces.

use std::io::{self, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use crate::converters::{AnalogDualDac, AnalogSensorAdc};
use crate::sim_device::{SimDevice, SimDeviceConfig};
use twinstack_link::Transport;

/// Most simulated time run per turn of the loop.
pub const MAX_STEP: Duration = Duration::from_millis(10);

/// Most simulated time owed to the wall clock before the excess is dropped.
pub const MAX_DEBT: Duration = Duration::from_secs(1);

/// How long a turn waits for the client's bytes before running the board.
const POLL: Duration = Duration::from_micros(100);

/// How long a turn sleeps while no client is connected.
const IDLE: Duration = Duration::from_millis(1);

/// How long a write to the client may block before the client is dropped.
const WRITE_TIMEOUT: Duration = Duration::from_secs(2);

/// The line's backlog, as the simulated board bounds it (bytes beyond it are dropped, so a
/// client that floods the line costs bounded memory, and its close is seen behind its flood
/// at once).
pub use crate::sim_device::MAX_BACKLOG;

/// Why the server could not run.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The simulated device could not be built.
    #[error("the simulated board: {0}")]
    Device(#[from] crate::sim_device::SimDeviceError),
    /// `speed` is negative or not finite.
    #[error("speed {0}: must be a finite number ≥ 0 (0: as fast as possible)")]
    Speed(f64),
    /// The listening socket failed.
    #[error("listening socket: {0}")]
    Io(#[from] io::Error),
}

/// What [`serve`] did, returned when it stops.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ServeReport {
    /// Clients served (connections accepted while the board was free).
    pub clients: u64,
    /// Connections refused because another client was connected.
    pub refused: u64,
    /// Ticks the board ran.
    pub ticks: u64,
    /// Bytes from clients dropped because the line's backlog was full ([`MAX_BACKLOG`]).
    pub bytes_dropped: u64,
}

/// Builds a [`SimDevice`] from `config` and serves it on `listener` (see the module doc) until
/// `stop` is set. `speed`: simulated seconds per wall-clock second (0: as fast as possible).
pub fn serve(
    listener: TcpListener,
    config: SimDeviceConfig,
    speed: f64,
    stop: &AtomicBool,
) -> Result<ServeReport, ServeError> {
    if !(speed.is_finite() && speed >= 0.0) {
        return Err(ServeError::Speed(speed));
    }
    let device = SimDevice::new(config)?;
    serve_device(listener, device, speed, stop)
}

/// [`serve`] with a device already built (any state, either board: the default or the
/// dual-stage one, [`crate::coarse_rig::DualStageDevice`]).
pub fn serve_device<D: AnalogDualDac, A: AnalogSensorAdc>(
    listener: TcpListener,
    mut device: SimDevice<D, A>,
    speed: f64,
    stop: &AtomicBool,
) -> Result<ServeReport, ServeError> {
    if !(speed.is_finite() && speed >= 0.0) {
        return Err(ServeError::Speed(speed));
    }
    listener.set_nonblocking(true)?;
    let mut report = ServeReport::default();
    let mut client: Option<TcpStream> = None;
    let mut clock = Pacer::new(speed);
    let mut buf = [0u8; 4096];
    while !stop.load(Ordering::Relaxed) {
        // New connections: the first is served, the rest are closed while it is connected.
        loop {
            match listener.accept() {
                Ok((stream, _)) => {
                    // The client may have left without the server noticing yet (`hal-sim
                    // load` then at once `twinstack stream`): check before refusing.
                    if client.as_mut().is_some_and(|c| !is_open(c, &mut device)) {
                        client = None;
                    }
                    if client.is_some() {
                        report.refused += 1;
                        drop(stream);
                    } else if let Ok(stream) = prepare(stream) {
                        // A new line: nothing of the last client's is left on it.
                        device.hang_up();
                        report.clients += 1;
                        client = Some(stream);
                    }
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                // A connection that failed before it was accepted: not the server's problem.
                Err(e) if is_connection_error(&e) => continue,
                Err(e) => return Err(e.into()),
            }
        }
        // The client's bytes onto the board's UART (waiting up to `POLL` for them).
        let mut connected = true;
        match client.as_mut() {
            Some(stream) => match stream.read(&mut buf) {
                Ok(0) => connected = false,
                Ok(n) => {
                    // The bytes arrive now on the wall clock: the board's clock first catches
                    // up with it, so that what it answers is read at the time it is asked.
                    device.run_for(clock.catch_up(device.now()));
                    device.send(&buf[..n])?
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                    ) => {}
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(_) => connected = false,
            },
            None => std::thread::sleep(IDLE),
        }
        // The board runs.
        device.run_for(clock.step(device.now()));
        // Its responses to the client.
        if connected {
            if let Some(stream) = client.as_mut() {
                connected = forward_output(&mut device, stream, &mut buf).is_ok();
            }
        }
        if !connected {
            client = None;
        }
    }
    report.ticks = device.ticks();
    report.bytes_dropped = device.line().bytes_dropped;
    Ok(report)
}

/// [`serve`] on a pseudo-terminal: `master` is the master side of a pty pair (its slave closed:
/// clients open the slave's path). Runs until `stop` is set.
#[cfg(unix)]
pub fn serve_pty(
    mut master: serialport::TTYPort,
    config: SimDeviceConfig,
    speed: f64,
    stop: &AtomicBool,
) -> Result<ServeReport, ServeError> {
    use serialport::SerialPort as _;
    if !(speed.is_finite() && speed >= 0.0) {
        return Err(ServeError::Speed(speed));
    }
    let mut device = SimDevice::new(config)?;
    master.set_timeout(POLL).map_err(io::Error::from)?;
    let mut report = ServeReport::default();
    let mut clock = Pacer::new(speed);
    let mut buf = [0u8; 4096];
    let mut connected = false;
    while !stop.load(Ordering::Relaxed) {
        match master.read(&mut buf) {
            Ok(n) if n > 0 => {
                if !connected {
                    // A new line: nothing of the last client's is left on it.
                    device.hang_up();
                    report.clients += 1;
                    connected = true;
                }
                device.run_for(clock.catch_up(device.now()));
                device.send(&buf[..n])?;
            }
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock
                        | io::ErrorKind::TimedOut
                        | io::ErrorKind::Interrupted
                ) => {}
            // No slave open (EIO on Linux, a hang-up elsewhere): nobody is connected.
            _ => {
                connected = false;
                std::thread::sleep(IDLE);
            }
        }
        device.run_for(clock.step(device.now()));
        if connected {
            connected = forward_output(&mut device, &mut master, &mut buf).is_ok();
        } else {
            discard_output(&mut device);
        }
    }
    report.ticks = device.ticks();
    report.bytes_dropped = device.line().bytes_dropped;
    Ok(report)
}

fn prepare(stream: TcpStream) -> io::Result<TcpStream> {
    stream.set_nonblocking(false)?;
    stream.set_nodelay(true)?;
    stream.set_read_timeout(Some(POLL))?;
    stream.set_write_timeout(Some(WRITE_TIMEOUT))?;
    Ok(stream)
}

/// The client has not closed its end (nor reset it). Bytes it sent before closing are read
/// onto the board's line first (at most [`OPEN_CHECK_READS`] reads: a client still sending is
/// open), so that a close behind them is seen.
fn is_open<D: AnalogDualDac, A: AnalogSensorAdc>(
    stream: &mut TcpStream,
    device: &mut SimDevice<D, A>,
) -> bool {
    let mut buf = [0u8; 4096];
    for _ in 0..OPEN_CHECK_READS {
        match stream.peek(&mut buf[..1]) {
            Ok(0) => return false,
            Ok(_) => match stream.read(&mut buf) {
                Ok(0) => return false,
                Ok(n) => {
                    if device.send(&buf[..n]).is_err() {
                        return false;
                    }
                }
                Err(e) => return is_waiting(&e),
            },
            Err(e) => return is_waiting(&e),
        }
    }
    true
}

/// Reads the open check makes before it takes a client that keeps sending as open.
const OPEN_CHECK_READS: usize = 16;

/// A read that found nothing yet on a connection still open.
fn is_waiting(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut | io::ErrorKind::Interrupted
    )
}

fn is_connection_error(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionAborted
            | io::ErrorKind::ConnectionReset
            | io::ErrorKind::ConnectionRefused
    )
}

/// Bytes that have arrived from the board by now (does not advance simulated time: a zero
/// timeout on [`SimDevice`]'s `receive`).
fn forward_output<D: AnalogDualDac, A: AnalogSensorAdc>(
    device: &mut SimDevice<D, A>,
    stream: &mut impl Write,
    buf: &mut [u8],
) -> io::Result<()> {
    loop {
        let n = device.receive(buf, Duration::ZERO)?;
        if n == 0 {
            return Ok(());
        }
        stream.write_all(&buf[..n])?;
    }
}

/// Bytes from the board with nobody on the line: dropped, as a serial line drops them.
#[cfg(unix)]
fn discard_output<D: AnalogDualDac, A: AnalogSensorAdc>(device: &mut SimDevice<D, A>) {
    let mut buf = [0u8; 512];
    while matches!(device.receive(&mut buf, Duration::ZERO), Ok(n) if n > 0) {}
}

/// Simulated time to run per turn: wall-clock time × speed, carried over between turns (so
/// fractions of a tick are not lost), at most [`MAX_STEP`] a turn; the rest is owed to the next
/// turns up to [`MAX_DEBT`], beyond which it is dropped (a host too slow for real time runs
/// the board slower).
struct Pacer {
    speed: f64,
    start: Instant,
    /// Simulated time (device clock) the wall clock says the board should have reached.
    target: Duration,
    /// Wall-clock time accounted for.
    wall: Duration,
}

impl Pacer {
    fn new(speed: f64) -> Self {
        Self {
            speed,
            start: Instant::now(),
            target: Duration::ZERO,
            wall: Duration::ZERO,
        }
    }

    fn step(&mut self, now: Duration) -> Duration {
        if self.speed == 0.0 {
            return MAX_STEP;
        }
        let wall = self.start.elapsed();
        let elapsed = wall.saturating_sub(self.wall);
        self.wall = wall;
        self.target = self.target.max(now) + elapsed.mul_f64(self.speed);
        let owed = self.target.saturating_sub(now);
        if owed > MAX_DEBT {
            self.target = now + MAX_DEBT;
        }
        owed.min(MAX_STEP)
    }

    /// All the simulated time owed now (at most [`MAX_DEBT`]), to run before bytes that
    /// arrive now are put on the board's line: a board's clock does not lag the requests.
    fn catch_up(&mut self, now: Duration) -> Duration {
        if self.speed == 0.0 {
            return Duration::ZERO;
        }
        let wall = self.start.elapsed();
        let elapsed = wall.saturating_sub(self.wall);
        self.wall = wall;
        self.target = (self.target.max(now) + elapsed.mul_f64(self.speed)).min(now + MAX_DEBT);
        self.target.saturating_sub(now)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_pacer_caps_each_step_and_keeps_fractions() {
        let mut p = Pacer::new(0.0);
        assert_eq!(p.step(Duration::ZERO), MAX_STEP);
        let mut p = Pacer::new(1.0);
        p.start -= Duration::from_millis(25);
        // 25 ms behind (the server was descheduled): capped steps until the debt is run.
        assert_eq!(p.step(Duration::ZERO), MAX_STEP);
        assert_eq!(p.step(Duration::from_millis(10)), MAX_STEP);
        // The board ran 19 ms of the 20 (whole ticks): the 1 ms left is still owed.
        let owed = p.step(Duration::from_millis(19));
        assert!(owed >= Duration::from_millis(6), "{owed:?}");
        assert!(owed < Duration::from_millis(9), "{owed:?}");
        // A host far too slow: the debt beyond MAX_DEBT is dropped.
        let mut p = Pacer::new(1.0);
        p.start -= Duration::from_secs(5);
        assert_eq!(p.step(Duration::ZERO), MAX_STEP);
        assert!(
            p.target <= MAX_DEBT + Duration::from_millis(50),
            "{:?}",
            p.target
        );
    }

    #[test]
    fn a_bad_speed_is_refused() {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let stop = AtomicBool::new(false);
        for speed in [-1.0, f64::NAN, f64::INFINITY] {
            let e = serve(
                listener.try_clone().unwrap(),
                SimDeviceConfig::paper(),
                speed,
                &stop,
            )
            .unwrap_err();
            assert!(matches!(e, ServeError::Speed(_)), "{e}");
        }
    }
}
