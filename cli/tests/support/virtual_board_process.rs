//! `twinstack virtual-board` as a child process on an OS-picked TCP port, for the tests that
//! drive the CLI against it (included with `#[path]` by those tests only).

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// The virtual board's process, killed when dropped.
pub struct VirtualBoard(pub Child);

impl Drop for VirtualBoard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts `twinstack virtual-board --listen tcp:127.0.0.1:0` with `extra` arguments (`--speed
/// 0` runs it as fast as it goes); returns it and the `tcp:` address it printed.
pub fn start(extra: &[&str]) -> (VirtualBoard, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args(["virtual-board", "--listen", "tcp:127.0.0.1:0"])
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("twinstack virtual-board starts");
    let stdout = child.stdout.take().expect("piped stdout");
    let board = VirtualBoard(child);
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut line = String::new();
        let _ = BufReader::new(stdout).read_line(&mut line);
        let _ = tx.send(line);
    });
    let line = rx
        .recv_timeout(Duration::from_secs(20))
        .expect("the server printed its address");
    let port = line
        .split_whitespace()
        .find(|w| w.starts_with("tcp:127.0.0.1:"))
        .unwrap_or_else(|| panic!("no address in {line:?}"))
        .to_string();
    (board, port)
}
