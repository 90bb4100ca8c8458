//! `twinstack view` as a child process and a plain-HTTP client of it (the page, the JSON API,
//! Server-Sent Events), for the tests that drive the view (included with `#[path]`).
#![allow(dead_code)] // each test binary uses its own subset

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The view's process (killed when dropped) and the address it serves on.
pub struct View {
    pub child: Child,
    pub addr: String,
}

impl Drop for View {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `twinstack view --port sim` on any free port, with `extra` arguments.
pub fn start(extra: &[&str]) -> View {
    start_on("sim", extra)
}

/// `twinstack view --port PORT` on any free port, with `extra` arguments; returns once it
/// has printed its address.
pub fn start_on(port: &str, extra: &[&str]) -> View {
    let mut child = Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args(["view", "--port", port, "--listen", "127.0.0.1:0"])
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let url = line
        .split_whitespace()
        .find(|w| w.starts_with("http://"))
        .unwrap_or_else(|| panic!("no address in {line:?}"));
    let addr = url
        .trim_start_matches("http://")
        .trim_end_matches('/')
        .to_string();
    View { child, addr }
}

/// One request on a fresh connection: (status, body).
pub fn http(addr: &str, raw: &[u8]) -> (u16, String) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    s.write_all(raw).unwrap();
    let mut reader = BufReader::new(s);
    let mut status = String::new();
    reader.read_line(&mut status).unwrap();
    let code: u16 = status.split_whitespace().nth(1).unwrap().parse().unwrap();
    let mut length = 0usize;
    loop {
        let mut h = String::new();
        reader.read_line(&mut h).unwrap();
        if h == "\r\n" {
            break;
        }
        if let Some(v) = h.to_ascii_lowercase().strip_prefix("content-length:") {
            length = v.trim().parse().unwrap();
        }
    }
    let mut body = vec![0; length];
    reader.read_exact(&mut body).unwrap();
    (code, String::from_utf8(body).unwrap())
}

/// `GET path`: (status, body).
pub fn get(addr: &str, path: &str) -> (u16, String) {
    http(
        addr,
        format!("GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n").as_bytes(),
    )
}

/// `POST path` with a JSON body: (status, the JSON answer).
pub fn post(addr: &str, path: &str, body: &str) -> (u16, serde_json::Value) {
    let (code, text) = http(
        addr,
        format!(
            "POST {path} HTTP/1.1\r\nHost: x\r\nContent-Length: {}\r\n\r\n{body}",
            body.len()
        )
        .as_bytes(),
    );
    (code, serde_json::from_str(&text).unwrap())
}

/// Reads Server-Sent Events until `done` says so: (event, data) pairs.
pub fn events(
    addr: &str,
    mut done: impl FnMut(&str, &serde_json::Value) -> bool,
) -> Vec<(String, serde_json::Value)> {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    s.write_all(b"GET /events HTTP/1.1\r\nHost: x\r\n\r\n")
        .unwrap();
    let mut reader = BufReader::new(s);
    let mut out = Vec::new();
    let mut event = String::new();
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        assert!(Instant::now() < deadline, "no end to the events");
        let mut line = String::new();
        if reader.read_line(&mut line).unwrap() == 0 {
            return out;
        }
        if let Some(e) = line.strip_prefix("event: ") {
            event = e.trim().to_string();
        } else if let Some(d) = line.strip_prefix("data: ") {
            let v: serde_json::Value = serde_json::from_str(d.trim()).unwrap();
            let stop = done(&event, &v);
            out.push((event.clone(), v));
            if stop {
                return out;
            }
        }
    }
}

/// Pauses the view's telemetry (`POST /api/telemetry {"run": false}`): the board's end frame
/// then carries the count it produced.
pub fn pause(addr: &str) {
    let (code, answer) = post(addr, "/api/telemetry", r#"{"run": false}"#);
    assert_eq!(code, 200, "{answer}");
}

/// The last event carries the board's count of samples produced: `received`, counted from the
/// sample numbered `first` (the first this client saw), is all of them, and none is missing.
pub fn assert_every_sample_arrived(
    events: &[(String, serde_json::Value)],
    received: u64,
    first: Option<u64>,
) {
    let (_, last) = events.last().expect("events");
    let produced = last["counts"]["produced"]
        .as_u64()
        .expect("the board's count");
    assert_eq!(
        received,
        produced - first.expect("samples"),
        "every sample the board produced from the first this client saw reached it"
    );
    assert_eq!(last["counts"]["missing"], 0);
}
