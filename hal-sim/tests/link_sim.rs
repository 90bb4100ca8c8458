//! The host's client, streamer and parameter load against the board in-process
//! ([`SimDevice`]: the library's command handler and control loop on a modelled 3 Mbaud
//! UART behind a USB–serial adapter's 16 ms ± 4 ms): a 10-second stream at 50 kHz without underrun or loss, a parameter load from an
//! `identify` file, a corrupted frame NACKed with nothing lost, and a recorder capture that
//! matches what was streamed. Time is simulated: these are counts, not timings.

use hal_sim::sim_device::{LinkDelay, SimDevice, SimDeviceConfig};
use twinstack::config::settings::{representative_pi, Model};
use twinstack::protocol::frame::{self, FrameError, MAX_ENCODED};
use twinstack::protocol::messages::{
    Mode, NackReason, RecordRequest, Request, Response, SetpointBatch, Signal, StatusReport,
    StreamControl, UnderrunPolicy,
};
use twinstack::refusal::{Field, ModelField, Refusal, Rule};
use twinstack_identify::param_file::ParamFile;
use twinstack_identify::stage_model::{Hysteresis, StageModel};
use twinstack_link::client::{Client, LinkError};
use twinstack_link::streamer::{stream_setpoints, StreamOptions};

/// The simulated board behind a USB–serial adapter's latency (16 ms ± 4 ms each way).
fn device() -> Client<SimDevice> {
    let config = SimDeviceConfig {
        link: LinkDelay::ADAPTER,
        ..SimDeviceConfig::paper()
    };
    Client::new(SimDevice::new(config).expect("device"))
}

/// `n` setpoints of a ±0.95 sine at `hz` (50 kHz samples), Q1.15.
fn sine(n: usize, hz: f64) -> Vec<i16> {
    (0..n)
        .map(|i| {
            let t = i as f64 / 50_000.0;
            (0.95 * (2.0 * std::f64::consts::PI * hz * t).sin() * 32768.0).round() as i16
        })
        .collect()
}

#[test]
fn ten_seconds_at_50_khz_stream_without_underrun_or_loss() {
    let mut client = device();
    let samples = sine(500_000, 37.0);
    let options = StreamOptions {
        underrun: Some(UnderrunPolicy::Hold),
        ..StreamOptions::default()
    };
    let r = stream_setpoints(&mut client, &samples, &options, |_| {}).expect("stream");
    assert_eq!(r.accepted, samples.len());
    assert!(r.nacks.is_empty(), "{:?}", r.nacks);
    // The board's own counter, read while the queue still held the tail of the stream (so
    // every tick of the stream so far is counted, and none after it).
    assert!(
        r.after_last_batch.queue_fill > 0,
        "{:?}",
        r.after_last_batch
    );
    assert_eq!(r.underruns_during_stream(), 0, "{r:?}");
    assert_eq!(r.after_last_batch.overruns, 0);
    assert_eq!(
        r.after_last_batch.crc_errors + r.after_last_batch.frame_errors,
        0
    );
    // Nothing lost: every setpoint was accepted once, the queue drained, and the stage holds
    // the last one.
    let drained = r.drained.expect("drained");
    assert_eq!(drained.queue_fill, 0);
    let dev = client.transport();
    let t = dev.control().telemetry();
    assert!(!t.streaming, "stopped after the drain");
    // 500 000 setpoints at one per tick: the stream took ≥ 10 s of board time.
    let ticks = drained.ticks.wrapping_sub(r.before.ticks) as usize;
    assert!(ticks >= samples.len(), "{ticks} ticks");
    // Every sequence number was used once.
    assert_eq!(
        dev.handler().next_seq() as usize,
        (r.before.next_seq as usize + samples.len().div_ceil(96)) % 65_536
    );
}

#[test]
fn the_recorder_captures_what_was_streamed() {
    let mut client = device();
    let samples = sine(4000, 250.0);
    client
        .arm_recorder(RecordRequest {
            signal: Signal::Setpoint,
            count: 15_000,
            decimation: 1,
        })
        .expect("armed");
    let r =
        stream_setpoints(&mut client, &samples, &StreamOptions::default(), |_| {}).expect("stream");
    assert_eq!(r.accepted, samples.len());
    // Let the capture finish, then read it back in chunks.
    while client.status().unwrap().recorded < 15_000 {
        client.wait(std::time::Duration::from_millis(5)).unwrap();
    }
    let values = client.read_recording(15_000, |_| {}).expect("read back");
    assert_eq!(values.len(), 15_000);
    let want: Vec<i32> = samples.iter().map(|&s| (s as i32) << 15).collect();
    let start = values
        .windows(want.len())
        .position(|w| w == want.as_slice())
        .unwrap_or_else(|| {
            let first_change = values.iter().position(|&v| v != values[0]);
            panic!(
                "the streamed setpoints are not in the capture in order: first change {first_change:?}, want[..3] {:?}, values near {:?}, report {r:?}",
                &want[..3],
                first_change.map(|i| &values[i.saturating_sub(2)..(i + 5).min(values.len())])
            )
        });
    // Before the stream started the setpoint held still; after the end it holds the last one.
    assert!(values[..start].iter().all(|&v| v == values[0]));
    assert!(values[start + want.len()..]
        .iter()
        .all(|&v| v == *want.last().unwrap()));
    // Past the capture there is nothing to read: no values are made up.
    match client.read_record(15_000) {
        Ok(v) => assert!(v.is_empty(), "{v:?}"),
        Err(e) => assert!(matches!(
            e,
            LinkError::Nack {
                reason: NackReason::Refused(Refusal {
                    field: Field::RecordOffset,
                    ..
                }),
                ..
            }
        )),
    }
    assert!(client.read_recording(15_001, |_| {}).is_err());
}

fn queue_without_playing(client: &mut Client<SimDevice>, n: usize) -> StatusReport {
    let s = client.status().unwrap();
    let batch = SetpointBatch {
        seq: s.next_seq,
        samples: (0..n as i16).collect(),
    };
    assert!(matches!(
        client.request(&Request::Setpoints(batch)).unwrap(),
        Response::Ack { .. }
    ));
    client.status().unwrap()
}

#[test]
fn a_parameter_file_loads_and_a_non_invertible_one_is_refused_with_nothing_lost() {
    let mut client = device();
    let queued = queue_without_playing(&mut client, 50);
    assert_eq!(queued.queue_fill, 50);
    // What `twinstack load` sends for an identified P–I model, open loop.
    let Model::PrandtlIshlinskii(mut p) = representative_pi(16).unwrap() else {
        unreachable!()
    };
    // The model's offset places the loading curve inside the board's output range.
    p.offset = -28.0;
    let model = StageModel {
        hysteresis: Hysteresis::Pi(p),
        scaling: twinstack::Scaling::new(0.0, 140.0, -45.0, 45.0).unwrap(),
        output_sign: 1.0,
        sensor_lag_s: 0.0,
        creep: None,
        output_map: None,
    };
    let mut good = ParamFile::from_model(&model, "um", None).settings;
    // As `twinstack load` does: the board's sensor and gains, which the file does not carry.
    let board = client.read_params().unwrap();
    good.sensor = board.sensor;
    good.feedback = board.feedback;
    client.load_params(&good).expect("loaded");
    client.wait(std::time::Duration::from_millis(1)).unwrap();
    let s = client.status().unwrap();
    assert_eq!(s.mode(), Mode::OpenLoop);
    assert_eq!(client.transport().handler().settings(), &good);
    assert_eq!(client.read_params().unwrap(), good);
    assert_eq!(s.queue_fill, 50, "the load lost nothing queued");
    client.store_params(Mode::OpenLoop).expect("stored");

    // A weight that makes the loading curve fall: not invertible, refused, nothing changes.
    let mut bad = good.clone();
    if let Some(Model::PrandtlIshlinskii(p)) = &mut bad.compensator {
        p.weights[0] = -0.5;
    }
    let err = client.load_params(&bad).expect_err("refused");
    assert!(
        matches!(
            err,
            LinkError::Nack {
                reason: NackReason::Refused(Refusal {
                    field: Field::Compensator(ModelField::Weight(1)),
                    rule: Rule::NotInvertible
                }),
                ..
            }
        ),
        "{err}"
    );
    assert_eq!(client.transport().handler().settings(), &good);
    let s = client.status().unwrap();
    assert_eq!(s.queue_fill, 50);
    assert_eq!(s.mode(), Mode::OpenLoop);
    client.recall_params().expect("recalled");
    assert_eq!(client.transport().handler().settings(), &good);
}

#[test]
fn a_corrupted_frame_is_nacked_and_the_next_one_is_taken() {
    let mut client = device();
    let before = queue_without_playing(&mut client, 20);
    // A batch with one bit flipped inside: the CRC fails.
    let batch = Request::Setpoints(SetpointBatch {
        seq: before.next_seq,
        samples: (0..40).collect(),
    });
    let mut wire = [0u8; MAX_ENCODED + 1];
    let n = frame::encode(&batch, &mut wire).unwrap();
    wire[n / 2] ^= 0x04;
    client.send_raw(&wire[..n]).unwrap();
    let r = client
        .receive(client.timeout())
        .unwrap()
        .expect("an answer");
    assert_eq!(
        r,
        Response::Nack {
            reason: NackReason::Frame(FrameError::BadCrc)
        }
    );
    let after = client.status().unwrap();
    assert_eq!(
        after.queue_fill, 20,
        "nothing queued was lost, nothing added"
    );
    assert_eq!(after.crc_errors, before.crc_errors + 1);
    assert_eq!(after.next_seq, before.next_seq);
    // The same batch, intact, is accepted.
    assert!(matches!(
        client.request(&batch).unwrap(),
        Response::Ack { credits } if credits as usize == twinstack::control_loop::SETPOINT_CAPACITY - 60
    ));
    // And a stream afterwards plays.
    client.stream(StreamControl::Start).unwrap();
}

/// `n` distinct setpoints (a ramp from 1000 in steps of 50), none equal to the rest value.
fn ramp(n: usize, from: i16) -> Vec<i16> {
    (0..n)
        .map(|i| (from as i32 + 50 * i as i32).clamp(-32_000, 32_000) as i16)
        .collect()
}

/// Streams `samples` with the recorder capturing the setpoint, waits for the capture and
/// returns it (Q2.30) with the stream's report.
fn stream_and_capture(
    client: &mut Client<SimDevice>,
    samples: &[i16],
    drain: bool,
) -> (twinstack_link::streamer::StreamReport, Vec<i32>) {
    // The stream starts about six round trips of the link (each ≤ 40 ms: arming, status,
    // rate, the first batch, the rest, the start) after the arming.
    let count = samples.len() as u32 + 12_000;
    client
        .arm_recorder(RecordRequest {
            signal: Signal::Setpoint,
            count,
            decimation: 1,
        })
        .expect("armed");
    let options = StreamOptions {
        drain,
        ..StreamOptions::default()
    };
    let r = stream_setpoints(client, samples, &options, |_| {}).expect("stream");
    while client.status().unwrap().recorded < count {
        client.wait(std::time::Duration::from_millis(5)).unwrap();
    }
    let values = client.read_recording(count, |_| {}).expect("read back");
    (r, values)
}

/// Asserts that `values` holds still, plays `samples` in order once, then holds the last.
fn played_in_order(values: &[i32], samples: &[i16], what: &str) {
    let want: Vec<i32> = samples.iter().map(|&s| (s as i32) << 15).collect();
    let start = values
        .windows(want.len())
        .position(|w| w == want.as_slice())
        .unwrap_or_else(|| panic!("{what}: the streamed setpoints are not in the capture"));
    assert!(
        values[..start].iter().all(|&v| v == values[0]),
        "{what}: something else played before the stream: {:?}",
        &values[..start.min(20)]
    );
    assert!(
        values[start + want.len()..]
            .iter()
            .all(|&v| v == *want.last().unwrap()),
        "{what}: the output did not hold the last setpoint"
    );
}

/// A record no longer than the free queue (≤ `SETPOINT_CAPACITY` setpoints on the simulated
/// board; one more is the first length that must wait for room) is acknowledged in full before
/// the streamer is ever short of credits: it must still be started and played, and leave
/// nothing queued for the next stream.
#[test]
fn records_shorter_than_the_queue_are_started_and_played_in_full() {
    let cap = twinstack::control_loop::SETPOINT_CAPACITY;
    for n in [1usize, 100, cap, cap + 1] {
        // The recorder holds fewer values than the queue: the long records are checked by
        // the board's counters and the next stream's start.
        let capture = n < 3000;
        let mut client = device();
        let capacity = {
            let s = client.status().unwrap();
            s.queue_fill as usize + s.credits as usize
        };
        assert_eq!(capacity, cap, "the lengths below straddle the queue");
        let first = ramp(n, 1000);
        let (r, values) = if capture {
            stream_and_capture(&mut client, &first, true)
        } else {
            let r = stream_setpoints(&mut client, &first, &StreamOptions::default(), |_| {})
                .expect("stream");
            (r, Vec::new())
        };
        assert_eq!(r.accepted, n, "{n}");
        let drained = r.drained.expect("drained");
        assert_eq!(drained.queue_fill, 0, "{n}: leftovers queued");
        assert_eq!(r.underruns_during_stream(), 0, "{n}: {r:?}");
        assert!(!r.underran(), "{n}");
        if capture {
            played_in_order(&values, &first, &format!("{n} setpoints"));
        }
        assert!(
            !client.transport().control().telemetry().streaming,
            "{n}: stopped after the drain"
        );
        // The next stream plays only its own setpoints: nothing was left over.
        let second = ramp(n.min(50), -1000);
        let (_, values) = stream_and_capture(&mut client, &second, true);
        assert_eq!(values[0], (*first.last().unwrap() as i32) << 15, "{n}");
        played_in_order(&values, &second, &format!("after {n} setpoints"));
    }
}

/// Without the drain (`twinstack stream --no-wait`) a short record is started and plays on
/// its own after the streamer returns.
#[test]
fn a_short_record_streamed_without_waiting_still_plays() {
    let mut client = device();
    let samples = ramp(100, 2000);
    let (r, values) = stream_and_capture(&mut client, &samples, false);
    assert!(r.drained.is_none());
    assert_eq!(client.status().unwrap().queue_fill, 0);
    played_in_order(&values, &samples, "--no-wait");
}

/// A few setpoints at a slow rate drain in their own time: the wait for the queue to play
/// out is what is left in it, not a whole batch's time (three setpoints at 10 Hz used to
/// block for 96 of them, 9.6 s).
#[test]
fn a_short_slow_stream_drains_in_its_own_time() {
    let mut client = device();
    let rate = client.status().expect("status").tick_rate_hz as f64;
    let options = StreamOptions {
        divider: (rate / 10.0) as u16,
        ..StreamOptions::default()
    };
    let start = client.now();
    let r = stream_setpoints(&mut client, &[0, 1000, 2000], &options, |_| {}).expect("stream");
    let took = (client.now() - start).as_secs_f64();
    assert_eq!(r.accepted, 3);
    assert!(r.drained.is_some());
    assert!((0.3..1.0).contains(&took), "took {took} s");
}
