//! `twinstack-link`: the host's end of the board link — how bytes reach a board (a serial
//! port, a pty, QEMU's UART, a TCP socket, or the simulated board in-process) and the protocol
//! client built on it — and the files the host reads and writes.
//!
//! [`Transport`] is the one seam: the client speaks frames over any transport, so the same
//! host code streams to the real board, the emulator image and the in-process twin (the
//! `hal-sim` crate, above this one, implements it for the simulated board and opens `--port`
//! values).
//!
//! * [`serial`], [`socket`] — transports;
//! * [`client`] — [`client::Client`]: requests, responses, timeouts, NACKs as errors,
//!   recorder read-back;
//! * [`streamer`] — [`streamer::stream_setpoints`]: batches within credits, sequence numbers,
//!   go-back-N after a refusal;
//! * [`server`] — [`server::serve`]: one board link shared by several TCP clients, one
//!   owner of the stream and settings at a time;
//! * [`capture`], [`telemetry`], [`sequence_run`], [`scan_timing`], [`learning`] — a
//!   capture's read-back, the telemetry stream, triggered sequences, a scan run and its line
//!   timing, the learning's table kept and played again;
//! * [`board_requests`] — what the board commands and the Python package share: the settings a
//!   load sends and its checks, waveform and capture requests, the status as JSON;
//! * [`setpoint_file`], [`measured_data`], [`csv_table`] — the setpoint and measured-data CSVs;
//!   [`output_file`] — outputs written only when complete (the command-line tool draws the
//!   PNG figures: this crate, which the Python package uses too, has no plotting dependency).

pub mod board_requests;
pub mod capture;
pub mod client;
pub mod csv_table;
pub mod learning;
pub mod measured_data;
pub mod output_file;
pub mod scan_timing;
pub mod sequence_run;
pub mod serial;
pub mod server;
pub mod setpoint_file;
pub mod settings_path;
pub mod socket;
pub mod streamer;
pub mod telemetry;
pub mod transport;

pub use client::{Client, LinkError};
pub use transport::Transport;
