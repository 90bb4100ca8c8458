//! [`SocketTransport`]: a stream socket to an emulated UART — QEMU's
//! `-chardev socket,path=SOCK,server=on` (Unix) or `-serial tcp::PORT,server` (TCP).
//!
//! The Unix-domain variant exists on Unix hosts only (`#[cfg(unix)]`); TCP works everywhere,
//! Windows included.

use super::Transport;
use std::io::{self, Read, Write};
use std::net::TcpStream;
#[cfg(unix)]
use std::os::unix::net::UnixStream;
#[cfg(unix)]
use std::path::Path;
use std::time::Duration;

/// A connected Unix or TCP stream socket.
#[derive(Debug)]
pub enum SocketTransport {
    /// A Unix-domain socket (Unix hosts only).
    #[cfg(unix)]
    Unix(UnixStream),
    /// A TCP connection.
    Tcp(TcpStream),
}

impl SocketTransport {
    /// Connects to the Unix socket at `path` (Unix hosts only).
    #[cfg(unix)]
    pub fn unix(path: &Path) -> io::Result<Self> {
        UnixStream::connect(path)
            .map(Self::Unix)
            .map_err(|e| io::Error::new(e.kind(), format!("{}: {e}", path.display())))
    }

    /// Connects to `address` (`host:port`).
    pub fn tcp(address: &str) -> io::Result<Self> {
        let s = TcpStream::connect(address)
            .map_err(|e| io::Error::new(e.kind(), format!("{address}: {e}")))?;
        s.set_nodelay(true)?;
        Ok(Self::Tcp(s))
    }
}

fn closed() -> io::Error {
    io::Error::new(
        io::ErrorKind::UnexpectedEof,
        "the board closed the link (emulator exited?)",
    )
}

impl Transport for SocketTransport {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        match self {
            #[cfg(unix)]
            Self::Unix(s) => s.write_all(bytes),
            Self::Tcp(s) => s.write_all(bytes),
        }
    }

    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        // `set_read_timeout(Some(0))` is an error: wait at least 1 µs.
        let timeout = Some(timeout.max(Duration::from_micros(1)));
        let r = match self {
            #[cfg(unix)]
            Self::Unix(s) => s.set_read_timeout(timeout).and_then(|_| s.read(buf)),
            Self::Tcp(s) => s.set_read_timeout(timeout).and_then(|_| s.read(buf)),
        };
        match r {
            Ok(0) if !buf.is_empty() => Err(closed()),
            Ok(n) => Ok(n),
            Err(e) if crate::transport::nothing_received(e.kind()) => Ok(0),
            Err(e) => Err(e),
        }
    }
}
