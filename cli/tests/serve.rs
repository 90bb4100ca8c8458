//! Several clients on one board through the server ([`twinstack_link::server::serve`]): a
//! stream beside a 10 Hz status poller, telemetry beside a stream, and a second writer
//! refused with the reason. The board is the simulated one behind an adapter's 16 ms ± 4 ms,
//! run by the server in step with the wall clock; the clients are TCP clients, as the CLI and
//! the Python package are. The assertions are counts (answers, underruns, samples), not
//! timings.

use std::net::TcpListener;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread;
use std::time::Duration;

use hal_sim::sim_device::{LinkDelay, SimDevice, SimDeviceConfig};
use twinstack::protocol::messages::{Mode, NackReason, StreamControl, UnderrunPolicy};
use twinstack_link::client::{Client, LinkError};
use twinstack_link::server::{serve, ServeReport};
use twinstack_link::socket::SocketTransport;
use twinstack_link::streamer::{stream_setpoints, StreamOptions};

#[path = "support/view_client.rs"]
mod view_client;

struct Server {
    address: String,
    stop: Arc<AtomicBool>,
    handle: thread::JoinHandle<(SimDevice, ServeReport)>,
}

impl Server {
    fn start() -> Server {
        Self::start_with(0.0)
    }

    /// The server on a board whose link damages `error_rate` of its bytes.
    fn start_with(error_rate: f64) -> Server {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let address = format!("127.0.0.1:{}", listener.local_addr().unwrap().port());
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let handle = thread::spawn(move || {
            let config = SimDeviceConfig {
                link: LinkDelay::ADAPTER,
                link_error_rate: error_rate,
                ..SimDeviceConfig::paper()
            };
            let mut device = SimDevice::new(config).unwrap();
            let report = serve(listener, &mut device, &flag).expect("serve");
            (device, report)
        });
        Server {
            address,
            stop,
            handle,
        }
    }

    fn client(&self) -> Client<SocketTransport> {
        let mut c = Client::new(SocketTransport::tcp(&self.address).unwrap());
        c.set_timeout(Duration::from_secs(10));
        c
    }

    fn finish(self) -> (SimDevice, ServeReport) {
        self.stop.store(true, Ordering::Relaxed);
        self.handle.join().unwrap()
    }
}

fn sine(n: usize) -> Vec<i16> {
    (0..n)
        .map(|i| (0.9 * (i as f64 * 2e-3).sin() * 32767.0) as i16)
        .collect()
}

/// A stream of `n` setpoints by one client while `beside` runs on another (in a thread,
/// until the stream ends); returns the stream's underruns (checked against the board's
/// counter), what `beside` returned, and the server's report.
fn stream_beside<R: Send + 'static>(
    n: usize,
    beside: impl FnOnce(Client<SocketTransport>, Arc<AtomicBool>) -> R + Send + 'static,
) -> (u32, R, ServeReport) {
    let server = Server::start();
    let mut streamer = server.client();
    // The stream's client owns the board from its first write on (the rate, the policy).
    let done = Arc::new(AtomicBool::new(false));
    let other = server.client();
    let flag = done.clone();
    let options = StreamOptions {
        underrun: Some(UnderrunPolicy::Hold),
        ..StreamOptions::default()
    };
    // The stream's first write makes its client the owner before the other one starts.
    streamer.set_mode(Mode::Bypass).unwrap();
    let side = thread::spawn(move || beside(other, flag));
    let r = stream_setpoints(&mut streamer, &sine(n), &options, |_| {}).expect("stream");
    done.store(true, Ordering::Relaxed);
    let side = side.join().unwrap();
    assert_eq!(r.accepted, n);
    let (device, report) = server.finish();
    let counted = device.control().telemetry().underruns;
    assert_eq!(
        r.underruns_during_stream(),
        counted.wrapping_sub(r.before.underruns),
        "the streamer's count is the board's counter"
    );
    (r.underruns_during_stream(), side, report)
}

#[test]
fn a_stream_and_a_10_hz_status_poller_share_the_board_and_nothing_is_lost() {
    let (underruns, (polls, answers, ticks), report) = stream_beside(40_000, |mut poller, done| {
        let (mut polls, mut answers, mut ticks) = (0u32, 0u32, Vec::new());
        while !done.load(Ordering::Relaxed) {
            polls += 1;
            let s = poller.status().expect("every poll is answered");
            answers += 1;
            ticks.push(s.ticks);
            thread::sleep(Duration::from_millis(100));
        }
        (polls, answers, ticks)
    });
    assert_eq!(underruns, 0);
    assert!(
        polls >= 3,
        "the poller ran beside the stream: {polls} polls"
    );
    assert_eq!(polls, answers);
    // Each poll got its own answer: the board's time only moves on.
    assert!(ticks.windows(2).all(|w| w[1] > w[0]), "{ticks:?}");
    assert_eq!(report.refused, 0);
    assert_eq!(report.unmatched, 0);
}

#[test]
fn telemetry_runs_beside_a_stream_owned_by_another_client() {
    let (underruns, frames, _) = stream_beside(40_000, |mut viewer, done| {
        // Setpoint and sensor, every 10th tick: 10 000 values/s.
        viewer
            .start_telemetry(0b1001, 10)
            .expect("telemetry is the viewer's");
        let mut frames = Vec::new();
        while !done.load(Ordering::Relaxed) {
            frames.extend(viewer.collect_telemetry(Duration::from_millis(50)).unwrap());
        }
        viewer.stop_telemetry().unwrap();
        frames.extend(
            viewer
                .collect_telemetry(Duration::from_millis(200))
                .unwrap(),
        );
        frames
    });
    assert_eq!(underruns, 0);
    assert!(frames.len() > 20, "{} telemetry frames", frames.len());
    // Consecutive, nothing lost on the board or on the way.
    assert!(frames.iter().all(|f| f.lost == 0));
    assert!(frames
        .windows(2)
        .all(|w| w[1].seq == w[0].seq.wrapping_add(1)));
}

/// A client that floods requests and never reads its answers is held to its share: another
/// client's status is answered promptly throughout (it used to wait behind every request the
/// flood had queued, minutes of the board's time), and the flooder is dropped once its
/// unread answers pass the server's bound.
#[test]
fn a_client_flooding_requests_does_not_hold_up_the_others() {
    use std::io::Write;
    let server = Server::start();
    let mut frame = [0u8; twinstack::protocol::frame::MAX_ENCODED + 1];
    let n = twinstack::protocol::frame::encode(
        &twinstack::protocol::messages::Request::Status,
        &mut frame,
    )
    .unwrap();
    let flood: Vec<u8> = frame[..n].repeat(100_000);
    let mut flooder = std::net::TcpStream::connect(&server.address).unwrap();
    let writer = thread::spawn(move || {
        let _ = flooder.write_all(&flood);
        flooder
    });
    thread::sleep(Duration::from_millis(200));
    let mut poller = server.client();
    poller.set_timeout(Duration::from_secs(2));
    for _ in 0..10 {
        assert!(poller.status().is_ok(), "a status behind the flood");
        thread::sleep(Duration::from_millis(50));
    }
    drop(writer.join().unwrap());
    let (_, report) = server.finish();
    assert!(report.forwarded < 100_000, "{report:?}");
}

/// On a link that damages bytes (a frame cut in two, two joined), no client is ever handed
/// another's answer: each gets its own answers or a NACK, which it resends.
#[test]
fn a_damaged_link_never_hands_one_client_another_s_answer() {
    let server = Server::start_with(0.002);
    let mut a = server.client();
    let mut b = server.client();
    a.set_timeout(Duration::from_secs(2));
    b.set_timeout(Duration::from_secs(2));
    let reader = thread::spawn(move || {
        let mut wrong = 0;
        for _ in 0..150 {
            if let Err(LinkError::Unexpected { .. }) = b.read_params() {
                wrong += 1;
            }
        }
        wrong
    });
    let mut wrong = 0;
    for _ in 0..150 {
        if let Err(LinkError::Unexpected { .. }) = a.status() {
            wrong += 1;
        }
    }
    let wrong_b = reader.join().unwrap();
    let (_, report) = server.finish();
    assert_eq!((wrong, wrong_b), (0, 0), "{report:?}");
    assert!(report.damaged > 0, "the link damaged nothing: {report:?}");
}

#[test]
fn a_second_writer_is_refused_with_the_reason_and_may_still_read() {
    let server = Server::start();
    let mut owner = server.client();
    let mut other = server.client();
    owner.stream(StreamControl::Rate { divider: 2 }).unwrap();
    // The other client may read …
    assert!(other.status().is_ok());
    assert!(other.read_params().is_ok());
    // … but not change the stream, the mode or the settings.
    for e in [
        other.stream(StreamControl::Start).unwrap_err(),
        other.set_mode(Mode::OpenLoop).unwrap_err(),
    ] {
        assert!(
            matches!(
                e,
                LinkError::Nack {
                    reason: NackReason::NotOwner,
                    ..
                }
            ),
            "{e}"
        );
        assert!(e.to_string().contains("another client"), "{e}");
    }
    // Once the owner leaves, the other client may take over.
    drop(owner);
    let mut tries = 0;
    while other.stream(StreamControl::Stop).is_err() {
        tries += 1;
        assert!(tries < 100, "the ownership was not released");
        thread::sleep(Duration::from_millis(20));
    }
    let (_, report) = server.finish();
    assert!(report.refused >= 2, "{report:?}");
    assert_eq!(report.clients, 2);
}

/// `twinstack view` is one more client of the server: it shows the board's telemetry with
/// every sample counted while another client streams, and a mode switch from the page is
/// refused with the reason while that client owns the board.
#[test]
fn the_live_view_reads_through_the_server_beside_a_stream() {
    let server = Server::start();
    let mut streamer = server.client();
    streamer.set_mode(Mode::Bypass).unwrap();
    let view = view_client::start_on(
        &format!("tcp:{}", server.address),
        &["--signals", "setpoint,sensor", "--rate", "1000"],
    );
    let done = Arc::new(AtomicBool::new(false));
    let flag = done.clone();
    let stream = thread::spawn(move || {
        let options = StreamOptions {
            underrun: Some(UnderrunPolicy::Hold),
            ..StreamOptions::default()
        };
        let r = stream_setpoints(&mut streamer, &sine(40_000), &options, |_| {}).expect("stream");
        flag.store(true, Ordering::Relaxed);
        (r, streamer)
    });
    let addr = view.addr.clone();
    let mut received = 0u64;
    let mut start: Option<u64> = None;
    let (mut refused, mut paused) = (false, false);
    let evs = view_client::events(&view.addr, |event, v| {
        match event {
            "samples" => {
                start.get_or_insert(v["first"].as_u64().unwrap());
                received += v["n"].as_u64().unwrap();
            }
            "status" if !refused && received > 200 => {
                let (code, answer) =
                    view_client::post(&addr, "/api/mode", r#"{"mode": "closed-loop"}"#);
                assert_eq!(code, 422, "{answer}");
                assert!(
                    answer["error"].as_str().unwrap().contains("another client"),
                    "{answer}"
                );
                refused = true;
            }
            "status" if refused && !paused && done.load(Ordering::Relaxed) => {
                view_client::pause(&addr);
                paused = true;
            }
            _ => {}
        }
        paused && v["counts"]["produced"].is_u64()
    });
    view_client::assert_every_sample_arrived(&evs, received, start);
    let (r, streamer) = stream.join().unwrap();
    assert_eq!(r.accepted, 40_000);
    assert_eq!(r.underruns_during_stream(), 0);
    drop((view, streamer));
    let (_, report) = server.finish();
    assert!(report.refused >= 1, "{report:?}");
}
