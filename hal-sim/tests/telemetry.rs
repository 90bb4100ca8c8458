//! Continuous telemetry on the in-process board (`SimDevice`: the library's command handler,
//! control loop and telemetry on a UART modelled at the board's link rate (`LINK_BAUD`), 10 bits a byte, simulated time
//! — deterministic counts, not timings).
//!
//! `cargo test -p hal-sim --test telemetry -- --nocapture` prints the figures of
//! `docs/src/results/throughput.md` (telemetry): bytes per second each way, the line's
//! utilisation, and the highest signals × rate that fits beside a 50 k/s setpoint stream.

use std::time::Duration;

use hal_sim::sim_device::{SimDevice, SimDeviceConfig};
use twinstack::protocol::messages::{NackReason, UnderrunPolicy};
use twinstack::refusal::{Field, Rule};
use twinstack::services::recorder::Channel;
use twinstack_link::client::{Client, LinkError};
use twinstack_link::streamer::{stream_setpoints, StreamOptions};
use twinstack_link::telemetry::{wait_for_end, TelemetryRecord};

/// The board's link (`LINK_BAUD`), 8N1: bytes per second each way.
const LINE_BYTES_PER_S: f64 = twinstack::protocol::LINK_BAUD as f64 / 10.0;
const RATE_HZ: f64 = 50_000.0;

/// Every sample ≥ 2^13 in magnitude: 3 bytes each on the wire (the setpoints' worst case).
fn worst_case(n: usize) -> Vec<i16> {
    (0..n)
        .map(|i| {
            let v = 9000 + ((i * 7919) % 22_000) as i16;
            if i % 2 == 0 {
                v
            } else {
                -v
            }
        })
        .collect()
}

struct Figures {
    record: TelemetryRecord,
    seconds: f64,
    bytes_in_per_s: f64,
    bytes_out_per_s: f64,
    telemetry_bytes_per_s: f64,
    underruns: u32,
    overflows: u32,
    setpoints: Vec<i16>,
}

/// Streams `seconds` of worst-case setpoints at one per tick (50 k/s) while telemetry of
/// `signals` every `decimation` ticks runs; stops telemetry and waits for its end frame.
fn run(signals: u8, decimation: u16, seconds: f64) -> Figures {
    let dev = SimDevice::new(SimDeviceConfig::paper()).unwrap();
    let mut client = Client::new(dev);
    let setpoints = worst_case((seconds * RATE_HZ) as usize);
    let line0 = client.transport().line();
    let t0 = client.transport().now();
    client.start_telemetry(signals, decimation).unwrap();
    let options = StreamOptions {
        underrun: Some(UnderrunPolicy::Hold),
        ..StreamOptions::default()
    };
    let report = stream_setpoints(&mut client, &setpoints, &options, |_| {}).unwrap();
    client.stop_telemetry().unwrap();
    let mut record = TelemetryRecord::new(signals, decimation);
    assert!(
        wait_for_end(&mut client, &mut record, Duration::from_secs(1)).unwrap(),
        "the end frame came"
    );
    let secs = (client.transport().now() - t0).as_secs_f64();
    let line = client.transport().line();
    Figures {
        seconds: secs,
        bytes_in_per_s: (line.bytes_in - line0.bytes_in) as f64 / secs,
        bytes_out_per_s: (line.bytes_out - line0.bytes_out) as f64 / secs,
        telemetry_bytes_per_s: (line.telemetry_bytes_out - line0.telemetry_bytes_out) as f64 / secs,
        underruns: report.underruns_during_stream(),
        overflows: client.transport().services().telemetry().overflows(),
        record,
        setpoints,
    }
}

/// 2 signals at 10 kHz each while setpoints stream in at 50 k/s, for 2 s of
/// simulated time: every sample arrives (no gap, no frame missing, nothing dropped on the
/// board), the setpoints stream without an underrun, and both directions stay within the
/// line.
#[test]
fn two_signals_at_10_khz_beside_a_50k_stream_lose_nothing() {
    let signals = Channel::Setpoint.bit() | Channel::Sensor.bit();
    let f = run(signals, 5, 2.0);
    let r = &f.record;
    println!(
        "2 signals @ 10 kHz + 50 k setpoints/s, {:.3} s: {} samples in {} frames, {} missing; \
         in {:.0} B/s ({:.1} %), out {:.0} B/s ({:.1} %; telemetry {:.0} B/s), underruns {:?}",
        f.seconds,
        r.samples(),
        r.frames(),
        r.missing(),
        f.bytes_in_per_s,
        100.0 * f.bytes_in_per_s / LINE_BYTES_PER_S,
        f.bytes_out_per_s,
        100.0 * f.bytes_out_per_s / LINE_BYTES_PER_S,
        f.telemetry_bytes_per_s,
        f.underruns
    );
    assert_eq!(f.underruns, 0, "the stream ran dry");
    assert_eq!(f.overflows, 0, "the board dropped samples");
    assert_eq!(
        (r.missing(), r.frames_missing(), r.lost_on_board()),
        (0, 0, 0)
    );
    let produced = r.produced().unwrap() as f64;
    assert!(
        produced >= 2.0 * 10_000.0,
        "{produced} samples: 2 s at 10 kHz or more"
    );
    assert!(f.bytes_in_per_s < LINE_BYTES_PER_S && f.bytes_out_per_s < LINE_BYTES_PER_S);
    // The telemetry's setpoints are the streamed ones, every fifth: find where the stream
    // started in the telemetry, then check every sample of the stream that it saw.
    let sp: Vec<i16> = r.values().iter().step_by(2).copied().collect();
    let start = sp.iter().position(|&v| v != sp[0]).unwrap();
    let phase = (0..5)
        .find(|&j| f.setpoints[j] == sp[start])
        .expect("the first streamed setpoint the telemetry saw is one of the first five");
    let seen: Vec<i16> = sp[start..]
        .iter()
        .copied()
        .take((f.setpoints.len() - phase) / 5)
        .collect();
    let want: Vec<i16> = f.setpoints[phase..].iter().step_by(5).copied().collect();
    assert_eq!(&seen[..], &want[..seen.len()]);
    assert!(seen.len() >= 19_000, "{} streamed samples seen", seen.len());
}

/// Up to the limit the board accepts (`MAX_VALUES_PER_SECOND`), telemetry beside the 50 k/s
/// stream loses nothing; the table is the throughput page's.
#[test]
fn every_rate_the_board_accepts_fits_beside_the_stream() {
    println!("| telemetry | values/s | setpoints/s | in B/s | out B/s | line out | samples | missing | underruns |");
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|");
    for (signals, decimation) in [
        (0b1001u8, 5u16),
        (0b1001, 2),
        (0b11_1111, 10),
        (0b1_1111, 5),
    ] {
        let f = run(signals, decimation, 0.5);
        let k = signals.count_ones();
        let values = k as f64 * RATE_HZ / decimation as f64;
        println!(
            "| {k} signals @ {:.0} Hz | {values:.0} | 50 000 | {:.0} | {:.0} | {:.1} % | {} | {} | {:?} |",
            RATE_HZ / decimation as f64,
            f.bytes_in_per_s,
            f.bytes_out_per_s,
            100.0 * f.bytes_out_per_s / LINE_BYTES_PER_S,
            f.record.samples(),
            f.record.missing(),
            f.underruns
        );
        assert_eq!(f.record.missing(), 0, "{k} signals / {decimation}");
        assert_eq!(f.underruns, 0, "{k} signals / {decimation}");
        assert!(f.bytes_out_per_s < LINE_BYTES_PER_S);
    }
}

/// Requests keep their answers while telemetry flows (the client sets the frames aside), and
/// a rate beyond the line is refused naming the decimation it needs.
#[test]
fn responses_are_demultiplexed_and_too_fast_a_rate_is_refused() {
    let mut client = Client::new(SimDevice::new(SimDeviceConfig::paper()).unwrap());
    match client.start_telemetry(0b11_1111, 1) {
        Err(LinkError::Nack {
            reason: NackReason::Refused(r),
            ..
        }) => {
            assert_eq!(
                (r.field, r.rule),
                (Field::TelemetryDecimation, Rule::AtLeast(6.0))
            );
            assert_eq!(r.to_string(), "telemetry decimation must be at least 6");
        }
        other => panic!("{other:?}"),
    }
    client.start_telemetry(Channel::Left.bit(), 1).unwrap();
    for _ in 0..20 {
        let s = client.status().unwrap();
        assert!(s.has(twinstack::protocol::messages::StatusReport::TELEMETRY));
        client.read_params().unwrap();
    }
    let frames = client.take_telemetry();
    assert!(
        frames.len() > 5,
        "{} frames while the requests ran",
        frames.len()
    );
    client.stop_telemetry().unwrap();
    let mut record = TelemetryRecord::new(Channel::Left.bit(), 1);
    record.add_all(&frames).unwrap();
    assert!(wait_for_end(&mut client, &mut record, Duration::from_secs(1)).unwrap());
    assert_eq!(record.missing(), 0);
    assert!(!client
        .status()
        .unwrap()
        .has(twinstack::protocol::messages::StatusReport::TELEMETRY));
}
