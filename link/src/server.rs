//! [`serve`]: one board link shared by several clients over TCP — a stream from a script, a
//! status poller, a live view — each speaking the board's own protocol, as if it had the
//! board to itself (`--port tcp:HOST:PORT`).
//!
//! **Who may do what.** Reading is open to everyone: `Status`, `ReadParams`, `ReadRecord`,
//! `CaptureStatus`, `ReadCapture`, `CoarseStatus`, `Echo`, and the learning's `Status` and
//! `ReadTable`. Everything that changes the board (setpoints, stream control, modes,
//! settings, recorder and capture arming, waveforms, scans, triggers, the coarse axis, the
//! learning) belongs to one client at a time, the **owner**: the first client to send such a
//! request, until it disconnects. Telemetry has its own owner on the same rule (the first to
//! start it), so a live view can watch a stream that another client drives. A request from
//! anyone else is answered, without reaching the board, with the NACK
//! [`NackReason::NotOwner`], which says why.
//!
//! **Order.** The board answers each request once, in order; the server forwards requests in
//! the order they arrive and hands each response to the client whose request it answers, so
//! every client sees its own answers in its own order. A refusal is queued in the same order.
//! Unsolicited telemetry frames go to the telemetry's owner. A client has at most
//! [`MAX_IN_FLIGHT`] requests on their way; past that it is not read until answers come.
//!
//! **A damaged answer.** Line noise can cut one answer in two or join two, so after a
//! damaged frame from the board the answers on their way can no longer be matched to their
//! requests by their order. The server then forwards nothing more and drops the board's
//! answers until it has sent none for [`QUIET`]; every request that was on its way is then
//! answered with a `Frame` NACK (the client resends, as it does on a damaged line), and the
//! order starts afresh. No client is ever handed another's answer.
//!
//! **Time.** A simulated board (`--port sim`, whose transport keeps its own clock) is run in
//! step with the wall clock, as the virtual board is; a real link runs by itself.

use std::collections::VecDeque;
use std::io::{self, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use twinstack::protocol::decoder::FrameDecoder;
use twinstack::protocol::frame::{self, FrameError, MAX_ENCODED};
use twinstack::protocol::messages::{AnalogRequest, LearnRequest, NackReason, Request, Response};

use super::Transport;

/// Bytes a client may leave unread before it is dropped (a client that stopped reading must
/// not hold the board's responses for everyone).
const MAX_BACKLOG: usize = 4 << 20;

/// The longest a turn waits for the board when nothing else happens.
const TURN: Duration = Duration::from_millis(1);

/// Requests of one client on their way to the board (or to the server's own refusal, in its
/// place in the order) at most: a client past it is not read
/// until its answers come (TCP holds its sender back), so a client that floods requests
/// neither grows the server's memory nor queues minutes of the board's time ahead of the
/// others' requests.
pub const MAX_IN_FLIGHT: usize = 32;

/// After a damaged answer from the board, how long the board must send no answer before the
/// order is taken as known again (see [`serve`]'s resynchronisation).
pub const QUIET: Duration = Duration::from_millis(50);

/// What a request needs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Access {
    /// Reads only: anyone.
    Read,
    /// Starts or stops telemetry: the telemetry's owner.
    Telemetry,
    /// Changes the board: the owner.
    Write,
}

/// The access `request` needs (see the module doc).
///
/// ```
/// use twinstack_link::server::{access, Access};
/// use twinstack::protocol::messages::{Request, StreamControl};
/// assert_eq!(access(&Request::Status), Access::Read);
/// assert_eq!(access(&Request::Stream(StreamControl::Start)), Access::Write);
/// ```
pub fn access(request: &Request) -> Access {
    match request {
        Request::Status
        | Request::ReadParams
        | Request::ReadRecord { .. }
        | Request::CaptureStatus
        | Request::ReadCapture { .. }
        | Request::CoarseStatus
        | Request::Echo(_)
        | Request::Analog(AnalogRequest::Status)
        | Request::Learn(LearnRequest::Status | LearnRequest::ReadTable { .. }) => Access::Read,
        Request::Telemetry(_) => Access::Telemetry,
        _ => Access::Write,
    }
}

/// What [`serve`] did, returned when it stops.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ServeReport {
    /// Clients accepted.
    pub clients: u64,
    /// Requests forwarded to the board.
    pub forwarded: u64,
    /// Requests refused because another client owns what they change.
    pub refused: u64,
    /// Responses from the board that answered no request (none on a working link).
    pub unmatched: u64,
    /// Damaged frames from the board (each followed by a resynchronisation).
    pub damaged: u64,
}

struct Client {
    id: u64,
    stream: TcpStream,
    decoder: FrameDecoder,
    out: Vec<u8>,
    open: bool,
    /// Bytes read and not yet decoded (the client reached [`MAX_IN_FLIGHT`] midway).
    unread: VecDeque<u8>,
    /// Its requests on their way to the board.
    in_flight: usize,
}

/// Who each answer on the way goes to, in the board's order.
enum Pending {
    /// The board's next response answers this client.
    Board(u64),
    /// The server's own answer (a refusal, its reason), in its place in the order.
    Local(u64, NackReason),
}

/// Serves the board behind `board` to the clients that connect to `listener` (see the module
/// doc) until `stop` is set. The board's link is used only by this function meanwhile.
pub fn serve<T: Transport + ?Sized>(
    listener: TcpListener,
    board: &mut T,
    stop: &AtomicBool,
) -> io::Result<ServeReport> {
    listener.set_nonblocking(true)?;
    let mut report = ServeReport::default();
    let mut clients: Vec<Client> = Vec::new();
    let mut next_id = 0u64;
    let mut owner: Option<u64> = None;
    let mut telemetry_owner: Option<u64> = None;
    let mut pending: VecDeque<Pending> = VecDeque::new();
    let mut from_board = FrameDecoder::new();
    // Since when the board has been heard while the order of its answers is being found
    // again (after a damaged answer).
    let mut resync: Option<Instant> = None;
    let mut buf = vec![0u8; 8192];
    let mut frame_out = [0u8; MAX_ENCODED + 1];
    let start = Instant::now();
    let board_start = board.clock();
    while !stop.load(Ordering::Relaxed) {
        // New clients.
        loop {
            match listener.accept() {
                Ok((stream, _)) => {
                    stream.set_nonblocking(true)?;
                    let _ = stream.set_nodelay(true);
                    report.clients += 1;
                    clients.push(Client {
                        id: next_id,
                        stream,
                        decoder: FrameDecoder::new(),
                        out: Vec::new(),
                        open: true,
                        unread: VecDeque::new(),
                        in_flight: 0,
                    });
                    next_id += 1;
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                Err(_) => break,
            }
        }
        // Their requests, in the order they arrive (none while the order is being found again
        // after a damaged answer, and none from a client with its fill on the way).
        let mut busy = false;
        for c in clients
            .iter_mut()
            .filter(|c| c.open && resync.is_none() && c.in_flight < MAX_IN_FLIGHT)
        {
            if c.unread.is_empty() {
                let n = match c.stream.read(&mut buf) {
                    Ok(0) => {
                        c.open = false;
                        continue;
                    }
                    Ok(n) => n,
                    Err(e)
                        if matches!(
                            e.kind(),
                            io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted
                        ) =>
                    {
                        continue
                    }
                    Err(_) => {
                        c.open = false;
                        continue;
                    }
                };
                c.unread.extend(&buf[..n]);
            }
            busy = true;
            while c.in_flight < MAX_IN_FLIGHT {
                let Some(byte) = c.unread.pop_front() else {
                    break;
                };
                let request = match c.decoder.push(byte) {
                    None => continue,
                    Some(Ok(body)) => frame::decode_body::<Request>(body),
                    Some(Err(e)) => Err(e),
                };
                let request = match request {
                    Ok(r) => r,
                    Err(e) => {
                        c.in_flight += 1;
                        pending.push_back(Pending::Local(c.id, NackReason::Frame(e)));
                        continue;
                    }
                };
                let holder = match access(&request) {
                    Access::Read => None,
                    Access::Write => Some(&mut owner),
                    Access::Telemetry => Some(&mut telemetry_owner),
                };
                let allowed = match holder {
                    None => true,
                    Some(h) => *h.get_or_insert(c.id) == c.id,
                };
                if !allowed {
                    report.refused += 1;
                    c.in_flight += 1;
                    pending.push_back(Pending::Local(c.id, NackReason::NotOwner));
                    continue;
                }
                let Ok(len) = frame::encode(&request, &mut frame_out) else {
                    c.in_flight += 1;
                    pending.push_back(Pending::Local(
                        c.id,
                        NackReason::Frame(FrameError::TooLarge),
                    ));
                    continue;
                };
                board.send(&frame_out[..len])?;
                report.forwarded += 1;
                c.in_flight += 1;
                pending.push_back(Pending::Board(c.id));
            }
        }
        // The board's answers. A simulated board runs as far as the wall clock says.
        let wait = match (board.clock(), board_start) {
            (Some(now), Some(at_start)) => {
                let due = start.elapsed();
                let ran = now.saturating_sub(at_start);
                if ran >= due {
                    if !busy {
                        std::thread::sleep(Duration::from_micros(200));
                    }
                    Duration::ZERO
                } else {
                    (due - ran).min(Duration::from_millis(5))
                }
            }
            _ if busy => Duration::from_micros(1),
            _ => TURN,
        };
        let n = board.receive(&mut buf, wait)?;
        for &byte in &buf[..n] {
            let decoded = match from_board.push(byte) {
                None => continue,
                Some(Ok(body)) => frame::decode_body::<Response>(body),
                Some(Err(e)) => Err(e),
            };
            let Ok(response) = decoded else {
                // A damaged answer: the answers on their way no longer match their requests
                // by order. Wait for the board to go quiet (below).
                report.damaged += 1;
                resync = Some(Instant::now());
                continue;
            };
            if matches!(response, Response::Telemetry(_)) {
                if let Some(c) = clients
                    .iter_mut()
                    .find(|c| Some(c.id) == telemetry_owner && c.open)
                {
                    push_frame(c, &response);
                }
                continue;
            }
            if resync.is_some() {
                // An answer while the order is unknown: to nobody, and the board not quiet yet.
                resync = Some(Instant::now());
                continue;
            }
            deliver(&mut pending, &mut clients, &mut report, response);
        }
        if resync.is_some_and(|since| since.elapsed() >= QUIET) {
            // Quiet: every request that was on its way is answered with a NACK, in order.
            while let Some(p) = pending.pop_front() {
                let (id, reason) = match p {
                    Pending::Board(id) => (id, NackReason::Frame(FrameError::BadCrc)),
                    Pending::Local(id, reason) => (id, reason),
                };
                if let Some(c) = clients.iter_mut().find(|c| c.id == id) {
                    c.in_flight = c.in_flight.saturating_sub(1);
                    if c.open {
                        push_frame(c, &Response::Nack { reason });
                    }
                }
            }
            from_board = FrameDecoder::new();
            resync = None;
        }
        flush_local(&mut pending, &mut clients);
        // Writes, and the clients that left.
        for c in clients.iter_mut().filter(|c| c.open && !c.out.is_empty()) {
            match c.stream.write(&c.out) {
                Ok(n) => {
                    c.out.drain(..n);
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted
                    ) => {}
                Err(_) => c.open = false,
            }
            if c.out.len() > MAX_BACKLOG {
                c.open = false;
            }
        }
        for c in clients.iter().filter(|c| !c.open) {
            if owner == Some(c.id) {
                owner = None;
            }
            if telemetry_owner == Some(c.id) {
                telemetry_owner = None;
            }
        }
        clients.retain(|c| c.open);
    }
    Ok(report)
}

/// The board's answer to the oldest request on the way, to its client, after any refusals
/// queued before it.
fn deliver(
    pending: &mut VecDeque<Pending>,
    clients: &mut [Client],
    report: &mut ServeReport,
    response: Response,
) {
    flush_local(pending, clients);
    let Some(Pending::Board(id)) = pending.pop_front() else {
        report.unmatched += 1;
        return;
    };
    if let Some(c) = clients.iter_mut().find(|c| c.id == id) {
        c.in_flight = c.in_flight.saturating_sub(1);
        if c.open {
            push_frame(c, &response);
        }
    }
    flush_local(pending, clients);
}

/// The server's own answers at the head of the order.
fn flush_local(pending: &mut VecDeque<Pending>, clients: &mut [Client]) {
    while let Some(Pending::Local(..)) = pending.front() {
        let Some(Pending::Local(id, reason)) = pending.pop_front() else {
            break;
        };
        if let Some(c) = clients.iter_mut().find(|c| c.id == id) {
            c.in_flight = c.in_flight.saturating_sub(1);
            if c.open {
                push_frame(c, &Response::Nack { reason });
            }
        }
    }
}

fn push_frame(c: &mut Client, response: &Response) {
    let mut out = [0u8; MAX_ENCODED + 1];
    if let Ok(n) = frame::encode(response, &mut out) {
        c.out.extend_from_slice(&out[..n]);
    }
}
