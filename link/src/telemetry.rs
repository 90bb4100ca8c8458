//! Continuous telemetry on the host (protocol v5): the board's unsolicited frames, as the
//! client sets them aside ([`crate::Client::take_telemetry`]), put back together into
//! one record, with everything that did not arrive accounted for.
//!
//! Two ways a sample can be missing, both announced: the board's queue was full (the frame
//! after the gap starts later and its `lost` says how many), or a frame was damaged on the
//! line (its sequence number is missing). The end frame, sent once telemetry is stopped,
//! gives the number of samples the run produced, so samples lost at the tail are counted
//! too: [`TelemetryRecord::missing`] is exactly what the host did not get.
//!
//! ```
//! use twinstack_link::telemetry::TelemetryRecord;
//! use twinstack::protocol::messages::TelemetryFrame;
//! let frame = |seq, first, lost, end, values: &[i16]| TelemetryFrame {
//!     seq, first, signals: 0b1001, lost, end, values: twinstack::heapless::Vec::from_slice(values).unwrap(),
//! };
//! let mut r = TelemetryRecord::new(0b1001, 5);
//! r.add(&frame(0, 0, 0, false, &[1, 2, 3, 4])).unwrap(); // samples 0, 1
//! r.add(&frame(1, 5, 3, false, &[5, 6])).unwrap();       // 2, 3, 4 dropped on the board
//! r.add(&frame(2, 6, 3, true, &[])).unwrap();            // stopped after 6 samples
//! assert_eq!((r.samples(), r.produced(), r.lost_on_board(), r.missing()), (3, Some(6), 3, 3));
//! ```

use crate::capture::{self, ConvertError, Recording};
use crate::client::{Client, LinkError};
use crate::Transport;
use std::ops::ControlFlow;
use std::time::Duration;
use twinstack::config::settings::Settings;
use twinstack::protocol::messages::{CaptureState, CaptureStatus, NackReason, TelemetryFrame};
use twinstack::refusal::{Field, Rule};

/// Why a frame does not belong to the record.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum TelemetryError {
    /// A frame of other signals (another run's).
    #[error("a telemetry frame of signal mask {got:#04b}, the run's is {want:#04b}")]
    Signals {
        /// The frame's mask.
        got: u8,
        /// The record's.
        want: u8,
    },
    /// Values that are not whole samples.
    #[error("a telemetry frame of {values} values for {signals} signals")]
    Partial {
        /// Values in the frame.
        values: usize,
        /// Signals per sample.
        signals: usize,
    },
    /// A frame that goes back in time (a restarted run).
    #[error("a telemetry frame starting at sample {first}, after sample {after} was received")]
    Backwards {
        /// The frame's first sample.
        first: u32,
        /// The next sample expected.
        after: u32,
    },
}

/// One telemetry run's samples as received, and what is missing.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TelemetryRecord {
    signals: u8,
    per_sample: usize,
    decimation: u16,
    /// Index of each received sample.
    indices: Vec<u32>,
    /// Their values, sample after sample.
    values: Vec<i16>,
    next_seq: u16,
    frames: u64,
    /// Frames whose sequence number never arrived.
    frames_missing: u64,
    /// The next sample index expected.
    expected: u32,
    lost_on_board: u32,
    end: Option<u32>,
}

impl TelemetryRecord {
    /// An empty record of the signals of `signals` (mask), one sample every `decimation`
    /// ticks.
    pub fn new(signals: u8, decimation: u16) -> Self {
        Self {
            signals,
            per_sample: (signals.count_ones() as usize).max(1),
            decimation,
            indices: Vec::new(),
            values: Vec::new(),
            next_seq: 0,
            frames: 0,
            frames_missing: 0,
            expected: 0,
            lost_on_board: 0,
            end: None,
        }
    }

    /// Adds a frame (in the order received).
    pub fn add(&mut self, frame: &TelemetryFrame) -> Result<(), TelemetryError> {
        if frame.signals != self.signals {
            return Err(TelemetryError::Signals {
                got: frame.signals,
                want: self.signals,
            });
        }
        if !frame.values.len().is_multiple_of(self.per_sample) {
            return Err(TelemetryError::Partial {
                values: frame.values.len(),
                signals: self.per_sample,
            });
        }
        if frame.first < self.expected {
            return Err(TelemetryError::Backwards {
                first: frame.first,
                after: self.expected,
            });
        }
        self.frames_missing += frame.seq.wrapping_sub(self.next_seq) as u64;
        self.next_seq = frame.seq.wrapping_add(1);
        self.frames += 1;
        self.lost_on_board = self.lost_on_board.max(frame.lost);
        let n = (frame.values.len() / self.per_sample) as u32;
        self.indices.extend(frame.first..frame.first + n);
        self.values.extend_from_slice(&frame.values);
        self.expected = frame.first + n;
        if frame.end {
            self.end = Some(frame.first);
        }
        Ok(())
    }

    /// Adds frames in order; stops at the first that does not belong.
    pub fn add_all<'a>(
        &mut self,
        frames: impl IntoIterator<Item = &'a TelemetryFrame>,
    ) -> Result<(), TelemetryError> {
        frames.into_iter().try_for_each(|f| self.add(f))
    }

    /// Samples received.
    pub fn samples(&self) -> usize {
        self.indices.len()
    }

    /// Frames received.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Frames that never arrived (sequence numbers skipped): damaged on the line.
    pub fn frames_missing(&self) -> u64 {
        self.frames_missing
    }

    /// The samples the run produced, once its end frame has arrived.
    pub fn produced(&self) -> Option<u32> {
        self.end
    }

    /// Whether the end frame has arrived.
    pub fn is_complete(&self) -> bool {
        self.end.is_some()
    }

    /// Samples the board dropped on a full queue, as the latest frame announced.
    pub fn lost_on_board(&self) -> u32 {
        self.lost_on_board
    }

    /// Samples not received: up to the end frame if it came, else up to the last sample
    /// received (gaps only).
    pub fn missing(&self) -> u64 {
        let produced = self.end.unwrap_or(self.expected) as u64;
        produced - self.indices.len() as u64
    }

    /// Each received sample's index (from 0 at the start).
    pub fn indices(&self) -> &[u32] {
        &self.indices
    }

    /// The values, sample after sample, each its signals in mask order.
    pub fn values(&self) -> &[i16] {
        &self.values
    }

    /// The signal mask.
    pub fn signals(&self) -> u8 {
        self.signals
    }

    /// The record in physical units (as a capture's: [`capture::convert`]) with `facts`, a
    /// capture status of the board (its DAC and amplifier full scale and tick rate), and
    /// the settings in force; `t` is seconds from the first sample of the run (a gap
    /// shows as a jump in `t`).
    pub fn recording(
        &self,
        facts: &CaptureStatus,
        settings: &Settings,
    ) -> Result<Recording, ConvertError> {
        let status = CaptureStatus {
            state: CaptureState::Done,
            signals: self.signals,
            samples: self.indices.len() as u32,
            pre_trigger: 0,
            pre_available: 0,
            captured: self.indices.len() as u32,
            window_slots: self.values.len() as u32,
            decimation: self.decimation,
            ..*facts
        };
        let mut recording = capture::convert(&status, settings, &self.values)?;
        let dt = self.decimation.max(1) as f64 / facts.tick_rate_hz.max(1) as f64;
        recording.t = self.indices.iter().map(|&i| i as f64 * dt).collect();
        Ok(recording)
    }
}

/// Receives until the end frame of the run in `record` has arrived (after
/// [`Client::stop_telemetry`]), for at most `budget`; frames set aside before are taken
/// first. `false` if the end never came.
pub fn wait_for_end<T: Transport>(
    client: &mut Client<T>,
    record: &mut TelemetryRecord,
    budget: Duration,
) -> Result<bool, WaitError> {
    let step = Duration::from_millis(10);
    let mut waited = Duration::ZERO;
    loop {
        record.add_all(&client.take_telemetry())?;
        if record.is_complete() {
            return Ok(true);
        }
        if waited >= budget {
            return Ok(false);
        }
        client.wait(step)?;
        waited += step;
    }
}

/// Why waiting for telemetry failed.
#[derive(Debug, thiserror::Error)]
pub enum WaitError {
    /// The link.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// A frame that does not belong to the run.
    #[error(transparent)]
    Frame(#[from] TelemetryError),
}

/// A run's sampling: one sample every `decimation` ticks, `rate_hz` samples a second.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RunRate {
    /// Ticks per sample.
    pub decimation: u16,
    /// Samples per second (the tick rate over the decimation).
    pub rate_hz: f64,
    /// The board's tick rate, Hz.
    pub tick_rate_hz: u32,
}

impl RunRate {
    /// The decimation nearest `rate` samples a second at `tick_rate_hz` (the board samples on
    /// whole ticks: the rate taken is `tick / decimation`, [`RunRate::rate_hz`]).
    ///
    /// ```
    /// use twinstack_link::telemetry::RunRate;
    /// let r = RunRate::nearest(50_000, 7_000.0).unwrap();
    /// assert_eq!((r.decimation, r.rate_hz), (7, 50_000.0 / 7.0));
    /// assert!(RunRate::nearest(50_000, 60_000.0).is_err());
    /// ```
    pub fn nearest(tick_rate_hz: u32, rate: f64) -> Result<Self, RateError> {
        if !(rate.is_finite() && rate > 0.0) {
            return Err(RateError::NotPositive { rate });
        }
        let tick = tick_rate_hz.max(1) as f64;
        if rate > tick {
            return Err(RateError::AboveTick { rate, tick_rate_hz });
        }
        let decimation = (tick / rate).round().max(1.0);
        if decimation > u16::MAX as f64 {
            return Err(RateError::BelowLeast {
                rate,
                least: tick / u16::MAX as f64,
                tick_rate_hz,
            });
        }
        let decimation = decimation as u16;
        Ok(Self {
            decimation,
            rate_hz: tick / decimation as f64,
            tick_rate_hz,
        })
    }

    /// Whether the rate taken differs from the rate asked for (not the tick rate over a
    /// whole number).
    pub fn differs_from(&self, rate: f64) -> bool {
        (self.rate_hz - rate).abs() > 1e-9 * rate
    }
}

/// Why a telemetry rate cannot be had.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RateError {
    /// Not a positive number.
    #[error("rate {rate}: must be a positive number of samples per second")]
    NotPositive {
        /// The rate asked for.
        rate: f64,
    },
    /// Faster than the board ticks.
    #[error("rate {rate}: the board ticks at {tick_rate_hz} Hz, the most a signal can have")]
    AboveTick {
        /// The rate asked for.
        rate: f64,
        /// The board's tick rate.
        tick_rate_hz: u32,
    },
    /// Slower than the longest decimation.
    #[error("rate {rate}: at least {least:.3} samples per second at {tick_rate_hz} Hz")]
    BelowLeast {
        /// The rate asked for.
        rate: f64,
        /// The least rate there is.
        least: f64,
        /// The board's tick rate.
        tick_rate_hz: u32,
    },
}

/// A telemetry run under way on a board: its samples as received, and its rate.
#[derive(Debug)]
pub struct TelemetryRun {
    /// The samples received, and what is missing.
    pub record: TelemetryRecord,
    /// Its sampling.
    pub rate: RunRate,
}

/// Why a telemetry run could not start or go on.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The rate asked for.
    #[error(transparent)]
    Rate(#[from] RateError),
    /// More values a second than the board's link carries.
    #[error(
        "rate {rate}: the board refused it ({refusal}): {signals} signals at most {most} samples/s each at {tick_rate_hz} Hz ({values} values/s in all, what its link carries)"
    )]
    TooFast {
        /// The rate asked for.
        rate: f64,
        /// The board's refusal.
        refusal: twinstack::refusal::Refusal,
        /// Signals in the run.
        signals: u32,
        /// The most samples a second each.
        most: f64,
        /// The board's tick rate.
        tick_rate_hz: u32,
        /// The values a second the board's telemetry sends at most.
        values: u32,
    },
    /// The caller stopped the run ([`TelemetryRun::collect`]'s `progress` answered
    /// [`ControlFlow::Break`]); telemetry was told to stop.
    #[error("stopped after {got} of {wanted} samples")]
    Stopped {
        /// Samples received or accounted missing.
        got: u64,
        /// Samples asked for.
        wanted: u64,
    },
    /// Not every sample asked for came within the time allowed.
    #[error("{got} of {wanted} samples after {waited_s:.1} s: is the board ticking?")]
    Stalled {
        /// Samples received or accounted missing.
        got: u64,
        /// Samples asked for.
        wanted: u64,
        /// Seconds waited.
        waited_s: f64,
    },
    /// The link.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// A frame that does not belong to the run.
    #[error(transparent)]
    Frame(#[from] TelemetryError),
    /// The samples could not be put in physical units.
    #[error(transparent)]
    Convert(#[from] ConvertError),
}

impl From<WaitError> for RunError {
    fn from(e: WaitError) -> Self {
        match e {
            WaitError::Link(l) => Self::Link(l),
            WaitError::Frame(f) => Self::Frame(f),
        }
    }
}

impl TelemetryRun {
    /// Starts the board's telemetry of `signals` (a channel mask) at the rate nearest `rate`
    /// samples a second ([`RunRate::nearest`]). A rate the board's link cannot carry for that
    /// many signals is refused naming the most it can.
    pub fn start<T: Transport>(
        client: &mut Client<T>,
        signals: u8,
        rate: f64,
    ) -> Result<Self, RunError> {
        let tick_rate_hz = client.status()?.tick_rate_hz.max(1);
        let run_rate = RunRate::nearest(tick_rate_hz, rate)?;
        match client.start_telemetry(signals, run_rate.decimation) {
            Err(LinkError::Nack {
                request,
                reason: NackReason::Refused(r),
            }) if r.field == Field::TelemetryDecimation => {
                let Rule::AtLeast(least) = r.rule else {
                    return Err(LinkError::Nack {
                        request,
                        reason: NackReason::Refused(r),
                    }
                    .into());
                };
                return Err(RunError::TooFast {
                    rate,
                    refusal: r,
                    signals: signals.count_ones(),
                    most: tick_rate_hz as f64 / least.max(1.0),
                    tick_rate_hz,
                    values: twinstack::services::telemetry::MAX_VALUES_PER_SECOND,
                });
            }
            other => other?,
        }
        Ok(Self {
            record: TelemetryRecord::new(signals, run_rate.decimation),
            rate: run_rate,
        })
    }

    /// Samples received or accounted missing so far.
    pub fn reached(&self) -> u64 {
        self.record.samples() as u64 + self.record.missing()
    }

    /// Receives until `wanted` samples have come (or are accounted missing), calling
    /// `progress` with the count as frames arrive; its [`ControlFlow::Break`] stops the run
    /// ([`RunError::Stopped`], telemetry told to stop). The samples come at their rate: after
    /// twice their duration plus the link's timeout without them (on the link's clock), the
    /// board is taken not to be sending them ([`RunError::Stalled`], telemetry stopped).
    pub fn collect<T: Transport>(
        &mut self,
        client: &mut Client<T>,
        wanted: u64,
        mut progress: impl FnMut(u64) -> ControlFlow<()>,
    ) -> Result<(), RunError> {
        let budget =
            Duration::from_secs_f64(2.0 * wanted as f64 / self.rate.rate_hz) + client.timeout();
        let step = Duration::from_millis(20);
        let start = client.now();
        while self.reached() < wanted {
            let waited = client.now().saturating_sub(start);
            if waited > budget {
                let _ = client.stop_telemetry();
                return Err(RunError::Stalled {
                    got: self.reached(),
                    wanted,
                    waited_s: waited.as_secs_f64(),
                });
            }
            let frames = client.collect_telemetry(step)?;
            self.record.add_all(&frames)?;
            if progress(self.reached().min(wanted)).is_break() {
                let _ = client.stop_telemetry();
                return Err(RunError::Stopped {
                    got: self.reached(),
                    wanted,
                });
            }
        }
        Ok(())
    }

    /// Stops the run and waits (2 s at most) for its end frame; returns the record in
    /// physical units ([`TelemetryRecord::recording`], with the settings in force) and
    /// whether the end frame came (without it, samples lost at the tail cannot be ruled
    /// out). What is missing is [`TelemetryRun::record`]'s to say.
    pub fn finish<T: Transport>(
        &mut self,
        client: &mut Client<T>,
    ) -> Result<(Recording, bool), RunError> {
        client.stop_telemetry()?;
        let ended = wait_for_end(client, &mut self.record, Duration::from_secs(2))?;
        let settings = client.read_params()?;
        let facts = client.capture_status()?;
        Ok((self.record.recording(&facts, &settings)?, ended))
    }

    /// What did not arrive, in a sentence, or `None` when nothing is missing and the end
    /// frame came.
    pub fn shortfall(&self, ended: bool) -> Option<String> {
        let r = &self.record;
        if !ended {
            return Some(
                "the board's end frame never came, so samples lost at the end cannot be ruled out"
                    .into(),
            );
        }
        (r.missing() > 0).then(|| {
            format!(
                "{} of the {} samples the board took did not arrive ({} dropped on the board, its queue full: a lower rate or fewer signals; the rest in {} frames damaged on the line): the gaps show in t",
                r.missing(),
                r.produced().unwrap_or(0),
                r.lost_on_board(),
                r.frames_missing()
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(seq: u16, first: u32, lost: u32, end: bool, values: &[i16]) -> TelemetryFrame {
        TelemetryFrame {
            seq,
            first,
            signals: 0b11,
            lost,
            end,
            values: heapless::Vec::from_slice(values).unwrap(),
        }
    }

    #[test]
    fn a_frame_lost_on_the_line_and_samples_lost_on_the_board_are_both_counted() {
        let mut r = TelemetryRecord::new(0b11, 1);
        r.add(&frame(0, 0, 0, false, &[1, 1, 2, 2])).unwrap();
        // Frame 1 (samples 2, 3) damaged on the line; 4 dropped on the board.
        r.add(&frame(2, 5, 1, false, &[5, 5])).unwrap();
        assert_eq!(
            (r.frames_missing(), r.missing(), r.produced()),
            (1, 3, None)
        );
        r.add(&frame(3, 9, 4, true, &[])).unwrap();
        assert_eq!(r.indices(), [0, 1, 5]);
        assert_eq!(
            (r.missing(), r.lost_on_board(), r.produced()),
            (6, 4, Some(9))
        );
        assert!(r.add(&frame(4, 0, 0, false, &[1, 1])).is_err());
        assert!(r.add(&frame(4, 9, 4, false, &[1])).is_err());
        let mut other = frame(4, 9, 4, false, &[]);
        other.signals = 1;
        assert!(r.add(&other).is_err());
    }
}
