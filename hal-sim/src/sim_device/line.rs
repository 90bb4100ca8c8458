//! The modelled UART between the host and the simulated board: bytes in flight each way at
//! the baud rate, behind the adapter's delays, the board's two transmit buffers, injected bit
//! errors, and the [`Transport`] the host's client talks to.

use super::*;

/// The adapter's delays: `latency ± jitter`, from xorshift64*.
#[derive(Clone, Debug)]
pub(super) struct Delays {
    pub(super) latency_ns: u64,
    pub(super) jitter_ns: u64,
    pub(super) state: u64,
}

impl Delays {
    pub(super) fn new(link: LinkDelay) -> Self {
        Self {
            latency_ns: link.latency.as_nanos() as u64,
            jitter_ns: link.jitter.as_nanos().min(link.latency.as_nanos()) as u64,
            state: link.seed.max(1),
        }
    }

    /// The next transfer's delay, ns.
    pub(super) fn next(&mut self) -> u64 {
        if self.jitter_ns == 0 {
            return self.latency_ns;
        }
        self.state ^= self.state >> 12;
        self.state ^= self.state << 25;
        self.state ^= self.state >> 27;
        let r = self.state.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11; // 53 bits
        let span = 2 * self.jitter_ns + 1;
        self.latency_ns - self.jitter_ns + ((r as u128 * span as u128) >> 53) as u64
    }
}

/// The most bytes the host → board line holds in flight (sent, not yet arrived): 256 KiB,
/// over four times what a stream within the board's credits has in flight. Bytes beyond it
/// are dropped as an adapter's full buffer drops them ([`LineCounters::bytes_dropped`]).
pub const MAX_BACKLOG: usize = 256 << 10;

/// Bytes the modelled UART carried, each way.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LineCounters {
    /// Host → board bytes (sent to the board, arrived or not).
    pub bytes_in: u64,
    /// Of them, bytes dropped because the line's backlog was full ([`MAX_BACKLOG`]): a client
    /// sending faster than the line carries, without end.
    pub bytes_dropped: u64,
    /// Board → host bytes put on the line (responses and telemetry).
    pub bytes_out: u64,
    /// Of them, telemetry frames' bytes.
    pub telemetry_bytes_out: u64,
    /// Telemetry frames put on the line.
    pub telemetry_frames: u64,
}

/// The board → host line: bytes with their arrival times, and the board's two transmit
/// buffers (a frame holds one until its last byte has left).
pub(super) struct TxLine {
    /// Bytes with the time they reach the host (after the adapter's delay).
    pub(super) bytes: VecDeque<(u64, u8)>,
    pub(super) free_ns: u64,
    /// When the last byte reaches the host: the adapter keeps the order.
    pub(super) delivered_ns: u64,
    pub(super) delays: Delays,
    /// When each frame still holding a buffer has left.
    pub(super) frame_ends: VecDeque<u64>,
    pub(super) byte_ns: u64,
    pub(super) counters: LineCounters,
}

/// The board's transmit buffers (the firmware's DMA double buffer).
const TX_BUFFERS: usize = 2;

impl TxLine {
    /// Puts `frame` on the line after what is there, not before `at`.
    pub(super) fn transmit(&mut self, frame: &[u8], at: u64) {
        let start = self.free_ns.max(at);
        let delay = self.delays.next();
        for (i, &b) in frame.iter().enumerate() {
            let arrives = (start + (i as u64 + 1) * self.byte_ns + delay).max(self.delivered_ns);
            self.delivered_ns = arrives;
            self.bytes.push_back((arrives, b));
        }
        self.free_ns = start + frame.len() as u64 * self.byte_ns;
        self.frame_ends.push_back(self.free_ns);
        self.counters.bytes_out += frame.len() as u64;
    }

    /// Whether a transmit buffer is free at `now`.
    pub(super) fn buffer_free(&mut self, now: u64) -> bool {
        while self.frame_ends.front().is_some_and(|&end| end <= now) {
            self.frame_ends.pop_front();
        }
        self.frame_ends.len() < TX_BUFFERS
    }
}

/// Corrupts a fraction of the bytes on the link: one bit flipped in each byte hit (xorshift64*
/// from a seed: the same bytes every run).
#[derive(Clone, Debug)]
pub(super) struct LinkErrors {
    /// Threshold on a 53-bit draw: `rate × 2^53`.
    pub(super) threshold: u64,
    pub(super) state: u64,
}

impl LinkErrors {
    pub(super) fn new(rate: f64, seed: u64) -> Self {
        Self {
            threshold: (rate.clamp(0.0, 1.0) * (1u64 << 53) as f64) as u64,
            state: seed.wrapping_mul(0xD1B5_4A32_D192_ED03) | 1,
        }
    }

    pub(super) fn draw(&mut self) -> u64 {
        self.state ^= self.state >> 12;
        self.state ^= self.state << 25;
        self.state ^= self.state >> 27;
        self.state.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11
    }

    /// `byte`, or it with one bit flipped.
    pub(super) fn pass(&mut self, byte: u8) -> u8 {
        if self.threshold == 0 || self.draw() >= self.threshold {
            return byte;
        }
        byte ^ 1 << (self.draw() % 8)
    }
}

impl<D: AnalogDualDac, A: AnalogSensorAdc> Transport for SimDevice<D, A> {
    /// Queues `bytes` on the host → board line, behind the adapter's delay (returns at once;
    /// simulated time does not move).
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        // The adapter hands the write to the UART `delay` later; the UART then sends the
        // bytes one after the other, after what it is still sending.
        let delay = self.rx_delays.next();
        let mut t = self.rx_line_free_ns.max(self.now_ns + delay);
        self.tx.counters.bytes_in += bytes.len() as u64;
        // A full adapter drops what does not fit (an overrun): the backlog, and the memory it
        // takes, stay bounded whatever a client sends.
        let room = MAX_BACKLOG.saturating_sub(self.rx.len());
        let (bytes, dropped) = bytes.split_at(bytes.len().min(room));
        self.tx.counters.bytes_dropped += dropped.len() as u64;
        for &b in bytes {
            t += self.byte_ns;
            let b = self.errors.pass(b);
            self.rx.push_back((t, b));
        }
        self.rx_line_free_ns = t;
        Ok(())
    }

    /// Advances simulated time until response bytes have arrived (or `timeout` of simulated
    /// time has passed: `Ok(0)`), then returns those that have arrived, up to `buf.len()`.
    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        if buf.is_empty() {
            return Ok(0);
        }
        let end = self.now_ns.saturating_add(timeout.as_nanos() as u64);
        loop {
            let arrived = self
                .tx
                .bytes
                .front()
                .is_some_and(|&(at, _)| at <= self.now_ns);
            if arrived {
                let mut n = 0;
                while n < buf.len() {
                    match self.tx.bytes.front() {
                        Some(&(at, b)) if at <= self.now_ns => {
                            buf[n] = self.errors.pass(b);
                            n += 1;
                            self.tx.bytes.pop_front();
                        }
                        _ => break,
                    }
                }
                return Ok(n);
            }
            if self.now_ns + self.tick_ns > end {
                return Ok(0);
            }
            self.step();
        }
    }

    /// Simulated time: the client's timeouts run on it.
    fn clock(&self) -> Option<Duration> {
        Some(self.now())
    }
}
