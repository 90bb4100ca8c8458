//! The host's end of the board link: how bytes reach a board (a serial port, a pty, QEMU's
//! UART, or the simulated board in-process) and the protocol client built on it.
//!
//! [`Transport`] is the one seam: the client speaks frames over any transport, so the same
//! host code streams to the real board, the emulator image and the in-process twin.

pub mod transport;

pub use transport::Transport;
