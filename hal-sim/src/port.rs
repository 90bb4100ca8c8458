//! `--port` values and opening them: a serial device path (or a pty such as `/dev/pts/3`),
//! `unix:PATH` (QEMU's `-chardev socket,path=PATH,server=on`), `tcp:HOST:PORT` (QEMU's
//! `-serial tcp::PORT,server`), or `sim` (the simulated board in-process). `unix:` needs a
//! Unix host; elsewhere (Windows) it is refused with [`PortError::UnixSocketUnsupported`] and
//! `tcp:` is the way to an emulator.

use crate::sim_device::{LinkDelay, SimDevice, SimDeviceConfig};
use std::path::PathBuf;
use twinstack_link::serial::{SerialError, SerialTransport};
use twinstack_link::socket::SocketTransport;
use twinstack_link::Transport;

/// Default baud rate of the board link: the board's (`twinstack::hardware::usart::BAUD`), 3
/// Mbaud, which FT232R, CP2102N and FT232H adapters make exactly.
pub const DEFAULT_BAUD: u32 = twinstack::protocol::LINK_BAUD;

/// Where the board is.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PortSpec {
    /// The simulated board, in-process.
    Sim,
    /// A serial device or pty.
    Serial(String),
    /// A Unix socket (refused when opened on a host without them).
    Unix(PathBuf),
    /// A TCP address `host:port`.
    Tcp(String),
}

/// Why a port could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum PortError {
    /// An empty `--port`.
    #[error("--port is empty: give a serial device (e.g. /dev/ttyUSB0), unix:PATH, tcp:HOST:PORT or sim")]
    Empty,
    /// The serial device could not be opened.
    #[error(transparent)]
    Serial(#[from] SerialError),
    /// The socket could not be connected.
    #[error("cannot connect: {0}")]
    Socket(std::io::Error),
    /// `unix:PATH` on a host without Unix-domain sockets.
    #[error("unix:{}: Unix-domain sockets are not available on {platform}: use tcp:HOST:PORT (QEMU's -serial tcp::PORT,server)", path.display())]
    UnixSocketUnsupported {
        /// The socket path asked for.
        path: PathBuf,
        /// The host platform (`std::env::consts::OS`).
        platform: &'static str,
    },
    /// The in-process board could not be made.
    #[error("the simulated board: {0}")]
    Sim(String),
}

impl std::str::FromStr for PortSpec {
    type Err = PortError;

    fn from_str(s: &str) -> Result<Self, PortError> {
        let s = s.trim();
        if s.is_empty() {
            return Err(PortError::Empty);
        }
        Ok(if s == "sim" {
            PortSpec::Sim
        } else if let Some(p) = s.strip_prefix("unix:") {
            PortSpec::Unix(PathBuf::from(p))
        } else if let Some(a) = s.strip_prefix("tcp:") {
            PortSpec::Tcp(a.to_string())
        } else {
            PortSpec::Serial(s.to_string())
        })
    }
}

/// Opens `spec`; `baud` sets a serial device's rate and the simulated board's modelled rate
/// (sockets ignore it). `sim` is a fresh [`SimDevice`] (the paper's stage,
/// [`SimDeviceConfig::paper`], on an ideal link: [`open_with_link`] puts an adapter's delay on
/// it) living as long as the returned transport: it starts from boot every time it is opened.
pub fn open(spec: &PortSpec, baud: u32) -> Result<Box<dyn Transport>, PortError> {
    let transport: Box<dyn Transport> = open_send(spec, baud)?;
    Ok(transport)
}

/// [`open`] for a caller that moves the link between threads (the Python package releases
/// the interpreter's lock while it waits on the board): every transport is `Send`.
pub fn open_send(spec: &PortSpec, baud: u32) -> Result<Box<dyn Transport + Send>, PortError> {
    open_with_link(spec, baud, LinkDelay::IDEAL)
}

/// [`open_send`] with the simulated board's link behind an adapter delaying each transfer by
/// `link` (other ports have their own).
pub fn open_with_link(
    spec: &PortSpec,
    baud: u32,
    link: LinkDelay,
) -> Result<Box<dyn Transport + Send>, PortError> {
    Ok(match spec {
        PortSpec::Sim => open_sim(baud, link)?,
        PortSpec::Serial(path) => Box::new(SerialTransport::open(path, baud)?),
        PortSpec::Unix(path) => open_unix(path)?,
        PortSpec::Tcp(addr) => Box::new(SocketTransport::tcp(addr).map_err(PortError::Socket)?),
    })
}

#[cfg(unix)]
fn open_unix(path: &std::path::Path) -> Result<Box<dyn Transport + Send>, PortError> {
    Ok(Box::new(
        SocketTransport::unix(path).map_err(PortError::Socket)?,
    ))
}

#[cfg(not(unix))]
fn open_unix(path: &std::path::Path) -> Result<Box<dyn Transport + Send>, PortError> {
    Err(PortError::UnixSocketUnsupported {
        path: path.to_path_buf(),
        platform: std::env::consts::OS,
    })
}

fn open_sim(baud: u32, link: LinkDelay) -> Result<Box<dyn Transport + Send>, PortError> {
    let config = SimDeviceConfig {
        baud,
        link,
        ..SimDeviceConfig::paper()
    };
    let device = SimDevice::new(config).map_err(|e| PortError::Sim(e.to_string()))?;
    Ok(Box::new(device))
}

/// The serial ports the system reports (`serialport::available_ports`), as
/// `"available serial ports: /dev/ttyUSB0, /dev/ttyACM0"` or `"no serial ports found"`, each
/// followed by the other kinds of port.
pub fn available_ports() -> String {
    let names: Vec<String> = serialport::available_ports()
        .map(|ports| ports.into_iter().map(|p| p.port_name).collect())
        .unwrap_or_default();
    let serial = if names.is_empty() {
        "no serial ports found".to_string()
    } else {
        format!("available serial ports: {}", names.join(", "))
    };
    format!("{serial} (other ports: tcp:HOST:PORT, unix:SOCKET, sim)")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unix_sockets_are_a_unix_only_port() {
        let spec: PortSpec = "unix:/tmp/uart.sock".parse().unwrap();
        assert_eq!(spec, PortSpec::Unix(PathBuf::from("/tmp/uart.sock")));
        let e = PortError::UnixSocketUnsupported {
            path: PathBuf::from("/tmp/uart.sock"),
            platform: "windows",
        };
        assert_eq!(
            e.to_string(),
            "unix:/tmp/uart.sock: Unix-domain sockets are not available on windows: use tcp:HOST:PORT (QEMU's -serial tcp::PORT,server)"
        );
        match open(&spec, DEFAULT_BAUD) {
            // On Unix a missing socket is a connection error; elsewhere the port is refused.
            Err(PortError::Socket(_)) if cfg!(unix) => {}
            Err(PortError::UnixSocketUnsupported { platform, .. }) if !cfg!(unix) => {
                assert_eq!(platform, std::env::consts::OS)
            }
            Err(other) => panic!("{other}"),
            Ok(_) => panic!("connected to a socket that does not exist"),
        }
    }
}
