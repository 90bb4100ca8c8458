//! [`SerialTransport`]: a serial device (a USB–UART adapter on the board's USART1, or a pty
//! such as the one QEMU's `-serial pty` prints) through the `serialport` crate, raw 8N1.

use super::Transport;
use std::io::{self, Read, Write};
use std::time::Duration;

/// Lowest baud rate accepted.
pub const MIN_BAUD: u32 = 1200;
/// Highest baud rate accepted (the STM32F405's USART1 tops out at 10.5 Mbaud).
pub const MAX_BAUD: u32 = 10_500_000;

/// Why a serial port could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum SerialError {
    /// The baud rate is outside [`MIN_BAUD`]…[`MAX_BAUD`].
    #[error("baud rate {0} is outside {MIN_BAUD}…{MAX_BAUD}")]
    BadBaud(u32),
    /// The device does not exist.
    #[error("{path}: no such serial device")]
    Missing {
        /// The device path.
        path: String,
    },
    /// The device exists but could not be opened (busy: another program has it open, or no
    /// permission), or it refused the settings.
    #[error("{path}: cannot open serial device: {reason}")]
    Open {
        /// The device path.
        path: String,
        /// What the OS said.
        reason: String,
    },
}

/// A serial device, raw 8N1, no flow control, opened exclusively.
pub struct SerialTransport {
    port: Box<dyn serialport::SerialPort>,
    timeout: Duration,
}

impl std::fmt::Debug for SerialTransport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SerialTransport")
            .field("port", &self.port.name())
            .finish()
    }
}

impl SerialTransport {
    /// Opens `path` at `baud` (8N1, raw, exclusive). A missing device, a busy one and a baud
    /// rate outside [`MIN_BAUD`]…[`MAX_BAUD`] are told apart in the error.
    pub fn open(path: &str, baud: u32) -> Result<Self, SerialError> {
        if !(MIN_BAUD..=MAX_BAUD).contains(&baud) {
            return Err(SerialError::BadBaud(baud));
        }
        if !std::path::Path::new(path).exists() {
            return Err(SerialError::Missing { path: path.into() });
        }
        let timeout = Duration::from_millis(100);
        let port = serialport::new(path, baud)
            .data_bits(serialport::DataBits::Eight)
            .parity(serialport::Parity::None)
            .stop_bits(serialport::StopBits::One)
            .flow_control(serialport::FlowControl::None)
            .timeout(timeout)
            .open()
            .map_err(|e| SerialError::Open {
                path: path.into(),
                reason: e.description,
            })?;
        // Bytes the board sent to an earlier client (a late answer to its last request) are
        // still in the adapter's buffer: they would be taken for the answer to this client's
        // first request.
        port.clear(serialport::ClearBuffer::All)
            .map_err(|e| SerialError::Open {
                path: path.into(),
                reason: e.description,
            })?;
        Ok(Self { port, timeout })
    }
}

impl Transport for SerialTransport {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.port.write_all(bytes)
    }

    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        // A zero timeout would mean "block forever" to some back ends: poll for 1 µs instead.
        let timeout = timeout.max(Duration::from_micros(1));
        if timeout != self.timeout {
            self.port.set_timeout(timeout).map_err(io::Error::from)?;
            self.timeout = timeout;
        }
        match self.port.read(buf) {
            Ok(n) => Ok(n),
            Err(e) if crate::transport::nothing_received(e.kind()) => Ok(0),
            Err(e) => Err(e),
        }
    }
}
