//! `twinstack view` over plain HTTP (the browser test is `python/tests/test_view.py`): the page
//! and its script are served, telemetry arrives as Server-Sent Events with every sample
//! counted, a mode switch reaches the board, and malformed or hostile requests are refused
//! with a reason, never a crash.

use std::process::Command;

#[path = "support/view_client.rs"]
mod view_client;

use view_client::{events, get, http, post, start};

#[test]
fn the_page_telemetry_and_a_mode_switch_over_http() {
    let view = start(&["--signals", "setpoint,sensor", "--rate", "1000"]);
    let (code, html) = get(&view.addr, "/");
    assert_eq!(code, 200);
    assert!(html.contains("twinstack view") && html.contains("/view.js"));
    let (code, js) = get(&view.addr, "/view.js");
    assert_eq!(code, 200);
    assert!(js.contains("EventSource"));
    let (code, tune) = get(&view.addr, "/api/tune");
    assert_eq!(code, 404);
    assert!(tune.contains("--tune"));

    // Some telemetry, then a mode switch, then pause: the samples counted against the end
    // frame's count.
    let mut received = 0u64;
    let mut start: Option<u64> = None;
    let mut switched = false;
    let mut paused = false;
    let addr = view.addr.clone();
    let evs = events(&view.addr, |event, v| {
        match event {
            "samples" => {
                // The first sample this connection saw: the run began before it.
                start.get_or_insert(v["first"].as_u64().unwrap());
                received += v["n"].as_u64().unwrap();
                assert_eq!(
                    v["signals"].as_object().unwrap().len(),
                    2,
                    "setpoint and sensor"
                );
            }
            "status" if !switched && received > 200 => {
                let (code, answer) = post(&addr, "/api/mode", r#"{"mode": "closed-loop"}"#);
                assert_eq!(
                    (code, answer["ok"].as_str()),
                    (200, Some("mode closed-loop"))
                );
                switched = true;
            }
            "status" if switched && !paused && v["mode"] == "closed-loop" => {
                let (code, answer) = post(&addr, "/api/telemetry", r#"{"run": false}"#);
                assert_eq!(code, 200, "{answer}");
                paused = true;
            }
            _ => {}
        }
        paused && v["counts"]["produced"].is_u64()
    });
    let (_, last) = evs.last().unwrap();
    let produced = last["counts"]["produced"].as_u64().unwrap();
    assert!(produced > 200);
    let start = start.unwrap();
    assert_eq!(
        received,
        produced - start,
        "every sample the board produced from the first this client saw reached it"
    );
    assert_eq!(last["counts"]["missing"], 0);
    assert!(evs
        .iter()
        .any(|(e, v)| e == "status" && v["mode"] == "closed-loop"));
}

#[test]
fn bad_requests_are_refused_with_a_reason() {
    let view = start(&["--signals", "sensor", "--rate", "500"]);
    let (code, v) = post(&view.addr, "/api/mode", r#"{"mode": "feedback"}"#);
    assert_eq!(code, 422);
    assert!(v["error"].as_str().unwrap().contains("expected \"bypass\""));
    let (code, v) = post(&view.addr, "/api/mode", "not json");
    assert_eq!(code, 400);
    assert!(v["error"].as_str().unwrap().contains("not JSON"));
    let (code, v) = post(
        &view.addr,
        "/api/waveform",
        r#"{"amplitude": 1.5, "frequency": 10}"#,
    );
    assert_eq!(code, 422);
    assert!(v["error"].as_str().unwrap().contains("amplitude"), "{v}");
    let (code, v) = post(&view.addr, "/api/scan", r#"{"pattern": "zigzag"}"#);
    assert_eq!(code, 422);
    assert!(v["error"].as_str().unwrap().starts_with("scan:"), "{v}");
    let (code, _) = post(&view.addr, "/api/launch", "{}");
    assert_eq!(code, 400);
    let (code, _) = get(&view.addr, "/etc/passwd");
    assert_eq!(code, 404);
    // A body larger than the server reads, and a head that is not HTTP.
    let (code, v) = http(
        &view.addr,
        b"POST /api/mode HTTP/1.1\r\nContent-Length: 100000000\r\n\r\n",
    );
    assert_eq!(code, 400, "{v}");
    let (code, _) = http(&view.addr, b"\x00\x01garbage\r\n\r\n");
    assert_eq!(code, 400);
    // A head line that never ends is cut at the head's bound (16 KiB), where the server read
    // to its end first, holding gigabytes; a chunked body is refused, not read as a request.
    let mut endless = b"GET /".to_vec();
    endless.resize(16 * 1024 + 1, b'A');
    let (code, v) = http(&view.addr, &endless);
    assert_eq!(code, 400, "{v}");
    assert!(v.contains("over 16384 bytes"), "{v}");
    let (code, v) = http(
        &view.addr,
        b"POST /api/mode HTTP/1.1\r\nTransfer-Encoding: chunked\r\n\r\n",
    );
    assert_eq!(code, 400, "{v}");
    assert!(v.contains("Content-Length"), "{v}");
    // Still serving.
    let (code, _) = get(&view.addr, "/");
    assert_eq!(code, 200);
}

#[test]
fn a_missing_or_wrong_figure_file_is_an_error_naming_it() {
    let out = Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args([
            "view",
            "--port",
            "sim",
            "--listen",
            "127.0.0.1:0",
            "--tune",
            "/nonexistent/tune.json",
        ])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--tune /nonexistent/tune.json"), "{err}");
}
