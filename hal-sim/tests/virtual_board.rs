//! The virtual board's TCP server against a client that floods it: the line's backlog stays
//! bounded (bytes beyond it are dropped, as a full adapter drops them) and the next client is
//! answered at once (the line is free when a client hangs up).

use std::io::Write;
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use hal_sim::sim_device::SimDeviceConfig;
use hal_sim::virtual_board::{serve, MAX_BACKLOG};
use twinstack_link::client::Client;
use twinstack_link::socket::SocketTransport;

#[test]
fn a_client_that_floods_the_line_is_held_back_and_the_next_is_answered_at_once() {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let address = listener.local_addr().unwrap().to_string();
    let stop = Arc::new(AtomicBool::new(false));
    let server = {
        let stop = stop.clone();
        std::thread::spawn(move || serve(listener, SimDeviceConfig::paper(), 1.0, &stop))
    };

    // The flood: 32 MB of bytes that are no frame.
    let mut flood = TcpStream::connect(&address).unwrap();
    flood
        .set_write_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let chunk = vec![b'A'; 1 << 16];
    let start = Instant::now();
    for _ in 0..512 {
        flood.write_all(&chunk).unwrap();
    }
    // Taken at the socket's pace, not the line's 3 Mbaud (32 MB there is 110 s).
    assert!(
        start.elapsed() < Duration::from_secs(30),
        "{:?}",
        start.elapsed()
    );
    drop(flood);

    // The next client is answered within its usual timeout (it used to wait behind the
    // flood's time on the line).
    std::thread::sleep(Duration::from_millis(100));
    let mut client = Client::new(SocketTransport::tcp(&address).unwrap());
    client.resync(Duration::from_millis(50)).ok();
    let status = client.status();
    stop.store(true, Ordering::Relaxed);
    assert!(status.is_ok(), "{status:?}");
    let report = server.join().unwrap().unwrap();
    // Bounded: all but the line's backlog (and what it carried meanwhile) was dropped, where
    // it was all queued, 16 bytes of memory a byte.
    assert!(
        report.bytes_dropped > (32 << 20) - 2 * MAX_BACKLOG as u64,
        "{report:?}"
    );
}
