//! `twinstack serve --port PORT --listen tcp:HOST:PORT`: owns the board's link and shares it
//! with several clients ([`twinstack_link::server`]): each connects with `--port tcp:HOST:PORT`
//! (the CLI, the Python package, a live view) as if it had the board to itself. One client at
//! a time owns the stream and the settings (the first to change anything, until it leaves),
//! another the telemetry; everyone may read status, records and settings; a request that
//! would change what another client owns is refused with the reason. Runs until killed
//! (Ctrl-C). The first line on stdout says where it listens.

use crate::board_link::{port_spec, PortArgs};
use hal_sim::port::{self, PortSpec};
use std::io::Write;
use std::net::TcpListener;
use std::sync::atomic::AtomicBool;
use std::time::Duration;
use twinstack_link::server;

/// Arguments of `serve`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// Where clients connect: tcp:HOST:PORT (port 0: the OS picks one; the address is
    /// printed).
    #[arg(long)]
    pub listen: String,
}

/// Runs `serve`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let address = match args.listen.parse::<PortSpec>()? {
        PortSpec::Tcp(address) => address,
        _ => anyhow::bail!(
            "--listen {}: give tcp:HOST:PORT (e.g. tcp:127.0.0.1:4100)",
            args.listen
        ),
    };
    let spec = port_spec(&args.port)?;
    let link = args.port.link.delay()?;
    let error_rate = args.port.link.error_rate()?;
    // The simulated board with the link's faults asked for, as every other command opens it.
    let mut board: Box<dyn twinstack_link::Transport + Send> = match spec {
        PortSpec::Sim => Box::new(
            hal_sim::sim_device::SimDevice::new(hal_sim::sim_device::SimDeviceConfig {
                baud: args.port.baud,
                link,
                link_error_rate: error_rate,
                ..hal_sim::sim_device::SimDeviceConfig::paper()
            })
            .map_err(|e| anyhow::anyhow!("the simulated board: {e}"))?,
        ),
        _ => port::open_with_link(&spec, args.port.baud, link)?,
    };
    // A clean line: whatever the board sent before is not an answer to anyone.
    board.send(&[0])?;
    let mut sink = [0u8; 512];
    while board.receive(&mut sink, Duration::from_millis(50))? > 0 {}
    let listener = TcpListener::bind(&address)
        .map_err(|e| anyhow::anyhow!("cannot listen on {address}: {e}"))?;
    println!(
        "serving {} on tcp:{} (Ctrl-C stops it)",
        args.port.port.as_deref().unwrap_or("the board"),
        listener.local_addr()?
    );
    std::io::stdout().flush()?;
    let stop = AtomicBool::new(false);
    server::serve(listener, &mut board, &stop)?;
    Ok(())
}
