//! [`Transport`]: a byte pipe to a board.

use std::io;
use std::time::Duration;

/// A byte pipe to a board: a serial device, a pty, a socket to QEMU's UART, or the simulated
/// board in-process (which advances its simulated time while the host waits).
pub trait Transport {
    /// Sends all of `bytes` (blocking until they are handed to the link).
    fn send(&mut self, bytes: &[u8]) -> io::Result<()>;

    /// Receives what has arrived, up to `buf.len()` bytes, waiting at most `timeout` for the
    /// first byte. Returns the number of bytes read; `Ok(0)` means the timeout passed with
    /// nothing received (not end of stream).
    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize>;

    /// The transport's own clock, if it simulates time (the in-process board: simulated time
    /// since it was built); `None` for a real link, whose waits are wall-clock time. A client
    /// that keeps receiving (telemetry frames between responses) measures its timeouts on it.
    fn clock(&self) -> Option<Duration> {
        None
    }
}

/// Whether a failed read of a link received nothing, and the caller should go on waiting: its
/// timeout passed (`TimedOut`, or `WouldBlock` on some back ends), or a signal interrupted the
/// wait (`Interrupted`, `EINTR`: a child process exiting, a terminal resize) — not an error of
/// the link.
///
/// ```
/// use std::io::ErrorKind;
/// use twinstack_link::transport::nothing_received;
/// assert!(nothing_received(ErrorKind::Interrupted));
/// assert!(!nothing_received(ErrorKind::BrokenPipe));
/// ```
pub fn nothing_received(kind: io::ErrorKind) -> bool {
    matches!(
        kind,
        io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted
    )
}

impl<T: Transport + ?Sized> Transport for Box<T> {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        (**self).send(bytes)
    }

    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        (**self).receive(buf, timeout)
    }

    fn clock(&self) -> Option<Duration> {
        (**self).clock()
    }
}
