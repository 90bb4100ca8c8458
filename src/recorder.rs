//! The data recorder: captures one signal of the control tick into a fixed RAM buffer, one
//! value every `decimation` ticks, for the host to read back in chunks.
//!
//! Armed from the protocol (`Record { signal, count, decimation }`), it captures on the tick
//! path at O(1) cost per tick (a countdown, and on a capture tick one store) and stops by
//! itself when `count` values are in. Reading back ([`Recorder::read`]) copies at most
//! [`MAX_CHUNK`] values from any offset below what has been captured so far, so the host may
//! read while the capture is still running. Re-arming discards the previous capture.
//!
//! Values are Q2.30, normalised like the signal they come from: setpoint and sensor/estimate
//! as normalised displacement (±1 over the model's output range), drive as model-normalised
//! drive (±1 over the model's input range).
//!
//! The buffer is whatever the board gives it (`B: AsMut<[i32]>`): the firmware hands it a
//! `&'static mut [i32; RECORD_CAPACITY]` in static RAM, the simulator a `Vec<i32>`.

use crate::control::TickReport;

/// Most recorder values one read returns (one response chunk).
pub const MAX_CHUNK: usize = 64;

/// Signals the recorder can capture.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Signal {
    /// The setpoint, Q2.30.
    Setpoint,
    /// The applied drive, Q2.30 model-normalised.
    Drive,
    /// The sensor reading, Q2.30.
    Sensor,
    /// The observer's estimate, Q2.30.
    Estimate,
}

/// Values the board's recorder holds: 16384 × 4 bytes = 64 KiB, half of the STM32F405's
/// 128 KiB of SRAM (the rest of the firmware needs under 16 KiB of static RAM and stack). At
/// 50 kHz and decimation 1 that is 0.33 s; decimation stretches it.
pub const RECORD_CAPACITY: usize = 16 * 1024;

/// Why an arm or a read was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum RecordError {
    /// `count` is 0 or more than the buffer holds, or `decimation` is 0.
    BadRequest,
    /// The read offset is past the values captured so far.
    OffsetPastEnd,
}

/// The recorder and its buffer.
#[derive(Debug)]
pub struct Recorder<B> {
    buffer: B,
    signal: Signal,
    /// Values armed for.
    count: u32,
    /// Values captured.
    len: u32,
    decimation: u16,
    /// Ticks until the next capture (0: capture on this tick).
    countdown: u16,
}

impl<B: AsRef<[i32]> + AsMut<[i32]>> Recorder<B> {
    /// An idle recorder over `buffer` (its length is the most values one capture can hold).
    pub fn new(buffer: B) -> Self {
        Self {
            buffer,
            signal: Signal::Setpoint,
            count: 0,
            len: 0,
            decimation: 1,
            countdown: 0,
        }
    }

    /// Most values a capture can hold.
    pub fn capacity(&self) -> usize {
        self.buffer.as_ref().len()
    }

    /// Arms a capture of `count` values of `signal`, one every `decimation` ticks, starting
    /// with the next tick; the previous capture is discarded. Refused (and nothing changed)
    /// if `count` is 0 or above the capacity, or `decimation` is 0.
    pub fn arm(&mut self, signal: Signal, count: u32, decimation: u16) -> Result<(), RecordError> {
        if count == 0 || count as usize > self.capacity() || decimation == 0 {
            return Err(RecordError::BadRequest);
        }
        self.signal = signal;
        self.count = count;
        self.len = 0;
        self.decimation = decimation;
        self.countdown = 0;
        Ok(())
    }

    /// Whether a capture is running (armed and not yet full).
    pub fn is_capturing(&self) -> bool {
        self.len < self.count
    }

    /// Values captured so far.
    pub fn recorded(&self) -> u32 {
        self.len
    }

    /// The signal being (or last) captured.
    pub fn signal(&self) -> Signal {
        self.signal
    }

    /// Which signal the tick must supply: `Some` when this tick captures, so the tick reads
    /// an extra input (the sensor, when feedback is off) only on the ticks that need it.
    #[inline(always)]
    pub fn wants(&self) -> Option<Signal> {
        if self.len < self.count && self.countdown == 0 {
            Some(self.signal)
        } else {
            None
        }
    }

    /// One tick: captures the chosen signal if this is a capture tick. `setpoint` is the
    /// setpoint in force (Q2.30), `sensor` the measured displacement (Q2.30; the tick's own
    /// reading, or the one taken for the recorder). O(1), no panic path.
    #[inline(always)]
    pub fn capture(&mut self, setpoint: i32, sensor: i32, report: &TickReport) {
        if self.len >= self.count {
            return;
        }
        if self.countdown > 0 {
            self.countdown -= 1;
            return;
        }
        let value = match self.signal {
            Signal::Setpoint => setpoint,
            Signal::Drive => report.drive,
            Signal::Sensor => sensor,
            Signal::Estimate => report.estimate,
        };
        if let Some(slot) = self.buffer.as_mut().get_mut(self.len as usize) {
            *slot = value;
        }
        self.len += 1;
        self.countdown = self.decimation - 1;
    }

    /// Copies up to `out`'s capacity of captured values from `offset` into `out` (cleared
    /// first). An offset equal to the values captured gives an empty chunk (nothing more yet);
    /// one past it is refused.
    pub fn read(
        &self,
        offset: u32,
        out: &mut heapless::Vec<i32, MAX_CHUNK>,
    ) -> Result<(), RecordError> {
        out.clear();
        if offset > self.len {
            return Err(RecordError::OffsetPastEnd);
        }
        let end = self.len.min(offset.saturating_add(MAX_CHUNK as u32));
        let values = self
            .buffer
            .as_ref()
            .get(offset as usize..end as usize)
            .unwrap_or(&[]);
        // `values` holds at most MAX_CHUNK values, so this cannot fail.
        let _ = out.extend_from_slice(values);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::board::DacCode;
    use crate::control::TickFlags;
    use std::vec;

    fn report(k: i32) -> TickReport {
        TickReport {
            left: DacCode(0),
            right: DacCode(0),
            estimate: 10 * k,
            measured: 0,
            drive: 100 * k,
            flags: TickFlags(0),
        }
    }

    #[test]
    fn captures_every_nth_tick_and_stops_when_full() {
        let mut r = Recorder::new(vec![0; 8]);
        r.arm(Signal::Drive, 3, 2).unwrap();
        for k in 0..10 {
            r.capture(k, 0, &report(k));
        }
        assert!(!r.is_capturing());
        let mut out = heapless::Vec::new();
        r.read(0, &mut out).unwrap();
        assert_eq!(&out[..], &[0, 200, 400]);
        r.read(1, &mut out).unwrap();
        assert_eq!(&out[..], &[200, 400]);
        r.read(3, &mut out).unwrap();
        assert!(out.is_empty());
        assert_eq!(r.read(4, &mut out), Err(RecordError::OffsetPastEnd));
    }

    #[test]
    fn each_signal_comes_from_its_source() {
        for (signal, want) in [
            (Signal::Setpoint, 7),
            (Signal::Drive, 700),
            (Signal::Estimate, 70),
            (Signal::Sensor, -5),
        ] {
            let mut r = Recorder::new(vec![0; 4]);
            r.arm(signal, 1, 1).unwrap();
            assert_eq!(r.wants(), Some(signal));
            r.capture(7, -5, &report(7));
            assert_eq!(r.wants(), None);
            let mut out = heapless::Vec::new();
            r.read(0, &mut out).unwrap();
            assert_eq!(&out[..], &[want], "{signal:?}");
        }
    }

    #[test]
    fn bad_arms_are_refused_and_change_nothing() {
        let mut r = Recorder::new(vec![0; 4]);
        r.arm(Signal::Setpoint, 2, 1).unwrap();
        r.capture(1, 0, &report(1));
        for (count, decimation) in [(0, 1), (5, 1), (2, 0)] {
            assert_eq!(
                r.arm(Signal::Drive, count, decimation),
                Err(RecordError::BadRequest)
            );
        }
        assert_eq!((r.recorded(), r.signal()), (1, Signal::Setpoint));
    }

    #[test]
    fn chunks_are_at_most_max_chunk_long() {
        let mut r = Recorder::new(vec![0; 200]);
        r.arm(Signal::Setpoint, 200, 1).unwrap();
        for k in 0..200 {
            r.capture(k, 0, &report(k));
        }
        let mut out = heapless::Vec::new();
        r.read(100, &mut out).unwrap();
        assert_eq!(out.len(), MAX_CHUNK);
        assert_eq!(out[0], 100);
        r.read(180, &mut out).unwrap();
        assert_eq!(out.len(), 20);
    }
}
