//! The timeline every vector set runs: six segments of [`SEGMENT`] ticks at 50 kHz.
//!
//! | ticks | segment | what it exercises |
//! |---|---|---|
//! | 0–399 | full-range sine, ±1.0, 200 ticks per cycle | every play operator, the range limits at the peaks |
//! | 400–799 | decaying sine about 0.1 (40 ticks per cycle) | nested minor loops (wiping out) |
//! | 800–1199 | steps of 50 ticks: ±1, 0, 1.5, `i32::MAX`, `i32::MIN`, 0.5, −0.25 | steps to and beyond the limits, slew limiting, the setpoint clamp |
//! | 1200–1599 | ±0.9 square (24 ticks), then ±0.9 sine (16 ticks per cycle) | a drive that is slew-limited most of the time |
//! | 1600–1999 | streamed through [`SetpointStream`] (divider 4) with the queue left dry twice | underruns under the hold policy (`None`), then ramp-to-rest |
//! | 2000–2399 | ±0.5 sine with ADC read failures, DAC write failures, ±1 holds, a final underrun | the fault flags and the integrator hold |
//!
//! The ADC codes are not part of the timeline: [`super::generate`] reads them off a sensor
//! model driven by the tick's own DAC codes.

use std::f64::consts::PI;
use twinstack::fixed_point::signal_from_f64 as q;
use twinstack::sources::setpoint_stream::{setpoint_to_wire, SetpointStream, Underrun};
use twinstack_golden::TickInput;

/// Ticks per segment.
pub const SEGMENT: usize = 400;
/// Ticks in the scenario.
pub const TICKS: usize = 6 * SEGMENT;

/// The scenario's inputs, ADC codes left at 0.
pub fn timeline() -> Vec<TickInput> {
    let mut out = Vec::with_capacity(TICKS);
    let some = |y: f64| TickInput {
        setpoint: Some(q(y)),
        ..TickInput::default()
    };
    // Full-range sine.
    for k in 0..SEGMENT {
        out.push(some((2.0 * PI * k as f64 / 200.0).sin()));
    }
    // Minor loops: a decaying oscillation about 0.1.
    for k in 0..SEGMENT {
        let t = k as f64;
        out.push(some(
            0.1 + 0.8 * (-t / 120.0).exp() * (2.0 * PI * t / 40.0).sin(),
        ));
    }
    // Steps, held 50 ticks each.
    let steps = [
        Some(q(1.0)),
        Some(q(-1.0)),
        Some(0),
        Some(q(1.5)),
        Some(i32::MAX),
        Some(i32::MIN),
        Some(q(0.5)),
        Some(q(-0.25)),
    ];
    for s in steps {
        for _ in 0..SEGMENT / steps.len() {
            out.push(TickInput {
                setpoint: s,
                ..TickInput::default()
            });
        }
    }
    // Slew: square, then a fast sine.
    for k in 0..SEGMENT / 2 {
        out.push(some(if (k / 12) % 2 == 0 { 0.9 } else { -0.9 }));
    }
    for k in 0..SEGMENT / 2 {
        out.push(some(0.9 * (2.0 * PI * k as f64 / 16.0).sin()));
    }
    // Streamed, with underruns.
    let last = out.last().and_then(|i| i.setpoint).unwrap_or(0);
    out.extend(streamed(last));
    // Faults.
    for k in 0..SEGMENT {
        let mut i = some(0.5 * (2.0 * PI * k as f64 / 100.0).sin());
        i.adc_fails = (50..80).contains(&k) || [150, 151, 200].contains(&k);
        i.dac_fails = (100..106).contains(&k) || k == 300;
        if (350..360).contains(&k) {
            i.setpoint = Some(q(1.0));
        } else if (360..370).contains(&k) {
            i.setpoint = Some(q(-1.0));
        } else if k >= 390 {
            i.setpoint = None;
        }
        out.push(i);
    }
    out
}

/// The streamed segment: a host sends one Q1.15 sample of a ±0.6 sine every 4 ticks into the
/// board's queue, which [`SetpointStream`] interpolates (divider 4). The host goes quiet for
/// ticks 80–119 of the segment (hold policy: the stream returns `None`) and, after switching
/// the policy to ramp-to-rest, for ticks 200–259 (the stream walks the setpoint to 0).
fn streamed(start: i32) -> Vec<TickInput> {
    let mut queue: heapless::spsc::Queue<i16, 16> = heapless::spsc::Queue::new();
    let (mut producer, mut consumer) = queue.split();
    let mut stream = SetpointStream::new(start);
    stream.set_divider(4);
    stream.start();
    let mut out = Vec::with_capacity(SEGMENT);
    let mut sample = 0usize;
    for k in 0..SEGMENT {
        if k == 160 {
            stream.set_underrun(Underrun::RampToRest {
                rest: 0,
                step: q(0.01),
            });
        }
        if k == 300 {
            stream.set_underrun(Underrun::Hold);
        }
        let quiet = (80..120).contains(&k) || (200..260).contains(&k);
        if k % 4 == 0 && !quiet {
            let y = 0.6 * (2.0 * PI * sample as f64 / 50.0).sin();
            sample += 1;
            // The queue has room: one sample goes in per sample taken out.
            let _ = producer.enqueue(setpoint_to_wire(q(y)));
        }
        out.push(TickInput {
            setpoint: stream.next(&mut consumer),
            ..TickInput::default()
        });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_timeline_has_every_case_it_promises() {
        let t = timeline();
        assert_eq!(t.len(), TICKS);
        let stream = &t[4 * SEGMENT..5 * SEGMENT];
        let underruns = stream.iter().filter(|i| i.setpoint.is_none()).count();
        assert!(underruns > 20, "hold underruns: {underruns}");
        // The ramp to rest reaches 0 during the second quiet spell.
        assert!(stream[200..260].iter().any(|i| i.setpoint == Some(0)));
        assert!(t.iter().any(|i| i.setpoint == Some(i32::MIN)));
        assert_eq!(t.iter().filter(|i| i.adc_fails).count(), 33);
        assert_eq!(t.iter().filter(|i| i.dac_fails).count(), 7);
        assert_eq!(t.last().unwrap().setpoint, None);
    }
}
