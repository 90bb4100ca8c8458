//! The host's end of the board link: how bytes reach a board (a serial port, a pty, QEMU's
//! UART, or the simulated board in-process) and the protocol client built on it.
//!
//! [`Transport`] is the one seam: the client speaks frames over any transport, so the same
//! host code streams to the real board, the emulator image and the in-process twin.
//!
//! * [`serial`], [`socket`] — transports (`--port` values and opening them, the simulated
//!   board included, are [`crate::port`], above this module and the simulated board);
//! * [`client`] — [`client::Client`]: requests, responses, timeouts, NACKs as errors,
//!   recorder read-back;
//! * [`streamer`] — [`streamer::stream_setpoints`]: batches within credits, sequence numbers,
//!   go-back-N after a refusal;
//! * [`server`] — [`server::serve`]: one board link shared by several TCP clients, one
//!   owner of the stream and settings at a time;

pub mod client;
pub mod serial;
pub mod server;
pub mod socket;
pub mod streamer;
pub mod transport;

pub use client::{Client, LinkError};
pub use transport::Transport;
