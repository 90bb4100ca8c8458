//! What every board command shares: `--port`, `--baud`, `--timeout-ms`, and connecting.

use crate::link::port::{self, PortSpec, DEFAULT_BAUD};
use crate::link::{Client, Transport};
use std::time::Duration;

/// Where the board is and how to talk to it.
#[derive(Debug, clap::Args)]
pub struct PortArgs {
    /// Serial device or pty (/dev/ttyUSB0, /dev/pts/3), unix:SOCKET or tcp:HOST:PORT (QEMU's
    /// UART), or `sim` for the simulated board in-process.
    #[arg(long)]
    pub port: String,
    /// Baud rate of a serial device (and of the simulated board's modelled UART).
    #[arg(long, default_value_t = DEFAULT_BAUD)]
    pub baud: u32,
    /// How long to wait for each response, milliseconds.
    #[arg(long, default_value_t = 2000, value_name = "MS")]
    pub timeout_ms: u64,
}

/// The board behind `--port`, through a client with a clean line.
pub type BoardClient = Client<Box<dyn Transport>>;

/// Opens the port and resynchronises the line.
pub fn connect(args: &PortArgs) -> anyhow::Result<BoardClient> {
    if args.timeout_ms == 0 {
        anyhow::bail!("--timeout-ms must be at least 1");
    }
    let spec: PortSpec = args.port.parse()?;
    let transport = port::open(&spec, args.baud)?;
    let mut client = Client::new(transport);
    client.set_timeout(Duration::from_millis(args.timeout_ms));
    client.resync(Duration::from_millis(20))?;
    Ok(client)
}
