//! `twinstack stop --port PORT`: stops the setpoint stream or the waveform generator; the
//! output holds where it is (queued setpoints stay queued).

use super::board_link::{connect, PortArgs};
use twinstack::protocol::messages::StreamControl;

/// Arguments of `stop`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
}

/// Runs `stop`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let mut client = connect(&args.port)?;
    client.stream(StreamControl::Stop)?;
    println!("stopped");
    Ok(())
}
