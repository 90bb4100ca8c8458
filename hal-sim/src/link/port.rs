//! `--port` values and opening them: a serial device path (or a pty such as `/dev/pts/3`),
//! `unix:PATH` (QEMU's `-chardev socket,path=PATH,server=on`), `tcp:HOST:PORT` (QEMU's
//! `-serial tcp::PORT,server`), or `sim` (the simulated board in-process).

use super::serial::{SerialError, SerialTransport};
use super::socket::SocketTransport;
use super::Transport;
use crate::sim_device::{SimDevice, SimDeviceConfig};
use std::path::PathBuf;

/// Default baud rate of the board link.
pub const DEFAULT_BAUD: u32 = 2_000_000;

/// Where the board is.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PortSpec {
    /// The simulated board, in-process.
    Sim,
    /// A serial device or pty.
    Serial(String),
    /// A Unix socket.
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
/// [`SimDeviceConfig::paper`]) living as long as the returned transport: it starts from boot
/// every time it is opened.
pub fn open(spec: &PortSpec, baud: u32) -> Result<Box<dyn Transport>, PortError> {
    Ok(match spec {
        PortSpec::Sim => open_sim(baud)?,
        PortSpec::Serial(path) => Box::new(SerialTransport::open(path, baud)?),
        PortSpec::Unix(path) => Box::new(SocketTransport::unix(path).map_err(PortError::Socket)?),
        PortSpec::Tcp(addr) => Box::new(SocketTransport::tcp(addr).map_err(PortError::Socket)?),
    })
}

fn open_sim(baud: u32) -> Result<Box<dyn Transport>, PortError> {
    let config = SimDeviceConfig {
        baud,
        ..SimDeviceConfig::paper()
    };
    let device = SimDevice::new(config).map_err(|e| PortError::Sim(e.to_string()))?;
    Ok(Box::new(device))
}
