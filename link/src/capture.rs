//! Multi-signal captures on the host (protocol v4's `Capture`): signal names ↔ the board's
//! mask, waiting for a capture and reading its window back, and the window in physical units
//! (stack volts, displacement in the model's output unit) as CSV (the command-line tool draws it).
//!
//! The conversion uses what the board reports: the settings in force (`ReadParams`: the
//! output range the normalised signals span) and the capture status (the DAC's full-scale
//! code and the amplifier's full-scale volts, the tick rate, the pre-trigger frames kept).
//! Slot formats: see [`twinstack::services::recorder`].

use crate::client::{Client, LinkError};
use crate::Transport;
use std::ops::ControlFlow;
use std::time::Duration;
use twinstack::config::settings::Settings;
use twinstack::protocol::messages::{CaptureState, CaptureStatus};
use twinstack::services::recorder::Channel;

/// Why a signal list was refused.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum SignalListError {
    /// A name that is no signal.
    #[error(
        "unknown signal {0:?} (signals: setpoint, left, right, sensor, estimate, error, triggers)"
    )]
    Unknown(String),
    /// A signal named twice.
    #[error("signal {0:?} is listed twice")]
    Twice(String),
    /// No signal at all.
    #[error("the signal list is empty (signals: setpoint, left, right, sensor, estimate, error, triggers)")]
    Empty,
}

/// The board's mask for a comma-separated list of signal names (`setpoint,left,sensor`).
///
/// ```
/// use twinstack_link::capture::signal_mask;
/// assert_eq!(signal_mask("setpoint, left").unwrap(), 0b11);
/// assert!(signal_mask("setpoint,voltage").is_err());
/// ```
pub fn signal_mask(list: &str) -> Result<u8, SignalListError> {
    let mut mask = 0u8;
    for name in list.split(',').map(str::trim).filter(|n| !n.is_empty()) {
        let channel = Channel::ALL
            .into_iter()
            .find(|c| c.name().eq_ignore_ascii_case(name))
            .ok_or_else(|| SignalListError::Unknown(name.to_string()))?;
        if mask & channel.bit() != 0 {
            return Err(SignalListError::Twice(name.to_string()));
        }
        mask |= channel.bit();
    }
    if mask == 0 {
        return Err(SignalListError::Empty);
    }
    Ok(mask)
}

/// One signal of a capture, in physical units.
#[derive(Clone, Debug, PartialEq)]
pub struct Column {
    /// Which signal.
    pub channel: Channel,
    /// Its unit: `V` for the stacks, the output unit (`um`) for the displacements.
    pub unit: &'static str,
    /// The values, physical.
    pub values: Vec<f64>,
    /// The values as the board stored them (Q1.15, DAC code, Q2.14: see the module doc).
    pub raw: Vec<i16>,
}

/// A capture's window in physical units: time from the trigger, and one column per signal.
#[derive(Clone, Debug, PartialEq)]
pub struct Recording {
    /// Seconds from the trigger frame (negative before it).
    pub t: Vec<f64>,
    /// The signals, in frame order.
    pub columns: Vec<Column>,
}

impl Recording {
    /// The column of `channel`, if captured.
    pub fn column(&self, channel: Channel) -> Option<&Column> {
        self.columns.iter().find(|c| c.channel == channel)
    }
}

/// Why a window could not be converted.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum ConvertError {
    /// The window's length is not the status's `window_slots`, or no whole frames.
    #[error("the window holds {got} values, the capture status says {want} ({signals} signals per frame)")]
    Length {
        /// Values read.
        got: usize,
        /// Values the status announces.
        want: u32,
        /// Signals per frame.
        signals: u32,
    },
    /// The status reports no DAC full scale or tick rate.
    #[error("the capture status reports a DAC full scale of {dac} and a tick rate of {rate} Hz")]
    Facts {
        /// DAC full scale.
        dac: u16,
        /// Tick rate.
        rate: u32,
    },
}

/// Converts a complete capture's `window` (as read, frame-interleaved) to physical units with
/// the board's `status` and its settings in force.
pub fn convert(
    status: &CaptureStatus,
    settings: &Settings,
    window: &[i16],
) -> Result<Recording, ConvertError> {
    let channels: Vec<Channel> = Channel::of_mask(status.signals).collect();
    let n = channels.len();
    if n == 0 || window.len() != status.window_slots as usize || !window.len().is_multiple_of(n) {
        return Err(ConvertError::Length {
            got: window.len(),
            want: status.window_slots,
            signals: n as u32,
        });
    }
    if status.dac_full_scale == 0 || status.tick_rate_hz == 0 {
        return Err(ConvertError::Facts {
            dac: status.dac_full_scale,
            rate: status.tick_rate_hz,
        });
    }
    let frames = window.len() / n;
    let dt = status.decimation.max(1) as f64 / status.tick_rate_hz as f64;
    let t = (0..frames)
        .map(|i| (i as f64 - status.pre_available as f64) * dt)
        .collect();
    let ranges = &settings.ranges;
    let volts_per_code = status.amplifier_full_scale as f64 / status.dac_full_scale as f64;
    let columns = channels
        .iter()
        .enumerate()
        .map(|(k, &channel)| {
            let raw: Vec<i16> = window.iter().skip(k).step_by(n).copied().collect();
            let values = raw
                .iter()
                .map(|&q| match channel {
                    Channel::Setpoint | Channel::Sensor | Channel::Estimate => {
                        ranges.norm_to_output(q as f64 / 32768.0)
                    }
                    Channel::Left | Channel::Right => q as u16 as f64 * volts_per_code,
                    Channel::Error => q as f64 / 16384.0 * ranges.output_half_span(),
                    // Bits, not a quantity: the levels as they are.
                    Channel::Triggers => q as f64,
                })
                .collect();
            let unit = match channel {
                Channel::Left | Channel::Right => "V",
                Channel::Triggers => "bits",
                _ => "um",
            };
            Column {
                channel,
                unit,
                values,
                raw,
            }
        })
        .collect();
    Ok(Recording { t, columns })
}

/// The CSV text: `t [s]`, then `<signal> [<unit>]` per signal, one row per frame.
pub fn csv(recording: &Recording) -> Result<Vec<u8>, csv::Error> {
    crate::output_file::csv_bytes(|w| {
        let mut header = vec!["t [s]".to_string()];
        header.extend(
            recording
                .columns
                .iter()
                .map(|c| format!("{} [{}]", c.channel.name(), c.unit)),
        );
        w.write_record(&header)?;
        for (i, t) in recording.t.iter().enumerate() {
            let mut row = vec![format!("{t:.9}")];
            row.extend(recording.columns.iter().map(|c| c.values[i].to_string()));
            w.write_record(&row)?;
        }
        Ok(())
    })
}

/// Why waiting for or reading a capture failed.
#[derive(Debug, thiserror::Error)]
pub enum CaptureError {
    /// The link failed or the board refused.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// The capture did not complete in time.
    #[error(
        "the capture is {state:?} with {captured} of {samples} frames after {waited:.1} s: {hint}"
    )]
    NotDone {
        /// Where it is.
        state: CaptureState,
        /// Frames captured.
        captured: u32,
        /// Frames armed for.
        samples: u32,
        /// Seconds waited.
        waited: f64,
        /// What to check.
        hint: &'static str,
    },
    /// The caller stopped the wait ([`wait_and_read_or_stop`]).
    #[error(
        "the wait for the capture was stopped with {captured} frames captured after {waited:.1} s"
    )]
    Stopped {
        /// Frames captured.
        captured: u32,
        /// Seconds waited.
        waited: f64,
    },
}

/// Polls the capture status until the capture is done, for at most `budget`, then reads the
/// whole window. `progress` sees the frames captured, then the slots read.
pub fn wait_and_read<T: Transport>(
    client: &mut Client<T>,
    budget: Duration,
    mut progress: impl FnMut(&str, u32),
) -> Result<(CaptureStatus, Vec<i16>), CaptureError> {
    wait_and_read_or_stop(client, budget, |what, n| {
        progress(what, n);
        ControlFlow::Continue(())
    })
}

/// How often [`wait_and_read_or_stop`] asks the board whether its capture is done.
pub const POLL: Duration = Duration::from_millis(20);

/// [`wait_and_read`], stopped by its caller: `progress` sees the frames captured at each
/// poll (every [`POLL`]), then the slots read, and answers [`ControlFlow::Break`] at a poll
/// to stop the wait ([`CaptureError::Stopped`]; the capture stays as it is on the board).
pub fn wait_and_read_or_stop<T: Transport>(
    client: &mut Client<T>,
    budget: Duration,
    mut progress: impl FnMut(&str, u32) -> ControlFlow<()>,
) -> Result<(CaptureStatus, Vec<i16>), CaptureError> {
    // Measured on the link's clock (the board's own for the in-process board), round trips
    // and all: not the sum of the sleeps between polls.
    let start = client.now();
    let status = loop {
        let s = client.capture_status()?;
        let waited = client.now().saturating_sub(start);
        // Every answer is honoured, the last poll's too: a caller that stops (a signal taken
        // while it was asked) is never left running.
        if progress("captured", s.captured).is_break() {
            return Err(CaptureError::Stopped {
                captured: s.captured,
                waited: waited.as_secs_f64(),
            });
        }
        if s.state == CaptureState::Done {
            break s;
        }
        if waited >= budget {
            return Err(CaptureError::NotDone {
                state: s.state,
                captured: s.captured,
                samples: s.samples,
                waited: waited.as_secs_f64(),
                hint: match s.state {
                    CaptureState::Armed => {
                        "the trigger never came (start the stream or the waveform)"
                    }
                    CaptureState::Idle => {
                        "no capture is armed (another client re-armed the recorder?)"
                    }
                    _ => "is the board ticking?",
                },
            });
        }
        client.wait(POLL)?;
    };
    let window = client.read_capture_window(status.window_slots, |n| {
        let _ = progress("read", n);
    })?;
    Ok((status, window))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn signal_lists_name_each_signal_once() {
        assert_eq!(
            signal_mask("setpoint,left,right,sensor,estimate,error").unwrap(),
            0b11_1111
        );
        assert_eq!(signal_mask("Sensor").unwrap(), Channel::Sensor.bit());
        assert_eq!(
            signal_mask("left,left"),
            Err(SignalListError::Twice("left".into()))
        );
        assert_eq!(signal_mask(" , "), Err(SignalListError::Empty));
        assert!(matches!(
            signal_mask("drive"),
            Err(SignalListError::Unknown(_))
        ));
    }

    #[test]
    fn the_window_converts_to_volts_and_micrometres() {
        let status = CaptureStatus {
            state: CaptureState::Done,
            signals: Channel::Setpoint.bit() | Channel::Left.bit() | Channel::Error.bit(),
            samples: 3,
            pre_trigger: 1,
            pre_available: 1,
            captured: 3,
            window_slots: 9,
            decimation: 2,
            capacity: 100,
            tick_rate_hz: 50_000,
            dac_full_scale: 4095,
            amplifier_full_scale: 150.0,
        };
        // The default settings: 0…70 µm output range.
        let settings = Settings::default();
        let window = [-32768, 0, 0, 0, 4095, 8192, 16384, 2048, -16384];
        let r = convert(&status, &settings, &window).unwrap();
        assert_eq!(r.t, [-40e-6, 0.0, 40e-6]);
        let sp = r.column(Channel::Setpoint).unwrap();
        assert_eq!(sp.values, [0.0, 35.0, 52.5]);
        let left = r.column(Channel::Left).unwrap();
        assert_eq!(left.values[1], 150.0);
        assert!((left.values[2] - 2048.0 * 150.0 / 4095.0).abs() < 1e-12);
        // Q2.14: 0.5 of the normalised range is a quarter of the stroke.
        assert_eq!(r.column(Channel::Error).unwrap().values, [0.0, 17.5, -35.0]);
        let text = String::from_utf8(csv(&r).unwrap()).unwrap();
        assert!(text.starts_with("t [s],setpoint [um],left [V],error [um]\n"));
        assert_eq!(text.lines().count(), 4);
        assert!(convert(&status, &settings, &window[..8]).is_err());
    }
}
