//! The host's protocol client and streamer against a scripted fake board (a `Transport` that
//! decodes request frames and answers them like the firmware's handler): credits are never
//! exceeded, batches are numbered in order, refusals become typed errors or go-back-N
//! resends, timeouts are reported, garbage on the line is skipped.

use std::time::Duration;
use support::fake_board::FakeBoard;
use twinstack::protocol::frame::{self, FrameError, MAX_ENCODED};
use twinstack::protocol::messages::{NackReason, Request, Response, StreamControl, UnderrunPolicy};
use twinstack::refusal::{Field, ModelField, Refusal, Rule};
use twinstack_link::client::{Client, LinkError};
use twinstack_link::streamer::{stream_setpoints, StreamOptions};

mod support;

fn ramp(n: usize) -> Vec<i16> {
    (0..n).map(|i| ((i * 37) % 60_000) as i16).collect()
}

#[test]
fn the_streamer_never_exceeds_its_credits_and_everything_plays_in_order() {
    // A queue that is no multiple of the batch size, played at 50 kHz.
    let mut client = Client::new(FakeBoard::new(250, 50_000.0));
    let samples = ramp(20_000);
    let report =
        stream_setpoints(&mut client, &samples, &StreamOptions::default(), |_| {}).expect("stream");
    let board = client.transport();
    assert_eq!(board.over_credit, 0, "a batch exceeded the credits");
    assert_eq!(
        board.played, samples,
        "every setpoint played once, in order"
    );
    assert_eq!(report.accepted, samples.len());
    assert_eq!(report.underruns_during_stream(), 0, "{report:?}");
    assert!(report.max_unacked <= 250);
    // Consecutive sequence numbers from 0, and more than one batch in flight at times.
    for (i, (seq, _)) in board.batches.iter().enumerate() {
        assert_eq!(*seq as usize, i);
    }
    assert!(
        report.max_unacked > 96,
        "batches were pipelined: {report:?}"
    );
    // Started once the queue was primed, finished behind the last batch, stopped after the
    // drain.
    assert_eq!(
        board.log,
        vec![
            Request::Stream(StreamControl::Rate { divider: 1 }),
            Request::Stream(StreamControl::Start),
            Request::Stream(StreamControl::Finish),
            Request::Stream(StreamControl::Stop),
        ]
    );
    assert_eq!(report.drained.map(|s| s.queue_fill), Some(0));
}

#[test]
fn the_first_batch_adopts_the_sequence_number_the_board_expects_when_its_status_does_not_say() {
    let mut board = FakeBoard::new(400, 50_000.0);
    board.expected_seq = 65_530; // and it wraps on the way
    board.status_seq = Some(0); // (a status that does not tell, as protocol version 1's)
    let mut client = Client::new(board);
    let samples = ramp(3000);
    let options = StreamOptions {
        underrun: Some(UnderrunPolicy::Hold),
        ..StreamOptions::default()
    };
    let report = stream_setpoints(&mut client, &samples, &options, |_| {}).expect("stream");
    let board = client.transport();
    assert_eq!(board.played, samples);
    assert_eq!(board.over_credit, 0);
    // One refused probe-batch, then one in flight only until the first ACK.
    assert_eq!(
        report.nacks,
        vec![NackReason::OutOfSequence { expected: 65_530 }]
    );
    assert_eq!(board.batches[1].0, 65_530);
    assert_eq!(board.batches.last().unwrap().0, 65_530u16.wrapping_add(31));
    assert!(board.log.contains(&Request::Stream(StreamControl::Underrun(
        UnderrunPolicy::Hold
    ))));
}

#[test]
fn a_batch_damaged_on_the_line_is_resent_with_those_after_it_and_nothing_is_lost_or_doubled() {
    let mut board = FakeBoard::new(1000, 50_000.0);
    board
        .refuse
        .insert(4, NackReason::Frame(FrameError::BadCrc));
    board.refuse.insert(12, NackReason::QueueFull);
    let mut client = Client::new(board);
    let samples = ramp(6000);
    let report =
        stream_setpoints(&mut client, &samples, &StreamOptions::default(), |_| {}).expect("stream");
    let board = client.transport();
    assert_eq!(board.played, samples, "nothing lost, nothing doubled");
    assert_eq!(report.nacks.len(), 2, "{:?}", report.nacks);
    assert!(report.resent_batches >= 2, "{report:?}");
    assert_eq!(report.underruns_during_stream(), 0);
}

#[test]
fn a_refusal_that_cannot_be_retried_ends_the_stream_with_what_was_accepted() {
    let mut board = FakeBoard::new(300, 50_000.0);
    let refusal = Refusal::new(Field::Divider, Rule::AtLeast(1.0));
    board.refuse.insert(3, NackReason::Refused(refusal));
    let mut client = Client::new(board);
    let err = stream_setpoints(&mut client, &ramp(2000), &StreamOptions::default(), |_| {})
        .expect_err("refused");
    assert!(matches!(
        err.source,
        LinkError::Nack {
            reason: NackReason::Refused(r),
            ..
        } if r == refusal
    ));
    assert_eq!(err.accepted, 3 * 96);
    let text = err.to_string();
    assert!(text.contains("288 of 2000"), "{text}");
}

#[test]
fn endless_refusals_give_up_after_the_retry_limit() {
    let mut board = FakeBoard::new(300, 50_000.0);
    for i in 0..100 {
        board
            .refuse
            .insert(i, NackReason::Frame(FrameError::BadCrc));
    }
    let mut client = Client::new(board);
    let options = StreamOptions {
        max_retries: 5,
        ..StreamOptions::default()
    };
    let err = stream_setpoints(&mut client, &ramp(500), &options, |_| {}).expect_err("gives up");
    assert_eq!(err.accepted, 0);
    assert_eq!(client.transport().setpoint_requests, 6);
}

#[test]
fn a_nack_is_a_typed_error_that_names_the_request_and_the_reason() {
    let mut client = Client::new(FakeBoard::new(100, 1000.0));
    let set = twinstack::config::settings::Settings {
        compensator: Some(twinstack::config::settings::representative_duhem()),
        mode: twinstack::config::settings::Mode::OpenLoop,
        ..twinstack::config::settings::Settings::default()
    };
    let err = client.load_params(&set).expect_err("refused");
    assert!(matches!(
        err,
        LinkError::Nack {
            request: "LoadParams",
            reason: NackReason::Refused(Refusal {
                field: Field::Compensator(ModelField::Weight(1)),
                rule: Rule::NotInvertible,
            })
        }
    ));
    // The message names the field and the rule.
    let text = err.to_string();
    assert!(text.contains("LoadParams"), "{text}");
    assert!(text.contains("compensator.weights[0]"), "{text}");
    assert!(text.contains("non-invertible"), "{text}");
    let err = client
        .stream(StreamControl::Rate { divider: 0 })
        .expect_err("refused");
    assert!(
        err.to_string()
            .contains("stream divider must be at least 1"),
        "{err}"
    );
}

#[test]
fn a_silent_board_is_a_timeout_not_a_hang() {
    let mut board = FakeBoard::new(100, 1000.0);
    board.mute = true;
    let mut client = Client::new(board);
    client.set_timeout(Duration::from_millis(20));
    let err = client.status().expect_err("times out");
    assert!(
        matches!(
            err,
            LinkError::Timeout {
                request: "Status",
                ..
            }
        ),
        "{err}"
    );
}

#[test]
fn garbage_on_the_line_is_skipped_and_the_next_frame_decodes() {
    let mut board = FakeBoard::new(100, 1000.0);
    // Noise ending in a delimiter, a frame with a flipped bit, a lone delimiter.
    let mut bad = [0u8; MAX_ENCODED + 1];
    let n = frame::encode(&Response::Ack { credits: 7 }, &mut bad).unwrap();
    bad[2] ^= 0x10;
    let mut garbage = b"twinstack status ticks=1\n\x00".to_vec();
    garbage.extend_from_slice(&bad[..n]);
    garbage.push(0);
    board.garbage = Some(garbage);
    board.queue.extend([1, 2, 3]);
    let mut client = Client::new(board);
    let s = client.status().expect("status after the garbage");
    assert_eq!(s.queue_fill, 3);
    assert_eq!(client.counters().corrupt_frames, 2);
}

#[test]
fn the_recording_is_read_in_chunks_and_its_length_is_checked() {
    let mut board = FakeBoard::new(100, 1000.0);
    board.recording = (0..300).map(|i| i * 1000 - 7).collect();
    let mut client = Client::new(board);
    let mut seen = Vec::new();
    let values = client
        .read_recording(300, |n| seen.push(n))
        .expect("read back");
    assert_eq!(values, client.transport().recording);
    assert_eq!(seen, vec![64, 128, 192, 256, 300]);
    // Fewer values on the board than asked for: an error, not a short file.
    let err = client.read_recording(301, |_| {}).expect_err("short");
    assert!(err.to_string().contains("holds 300 values"), "{err}");
}

#[test]
fn a_board_that_never_frees_its_queue_ends_the_stream_instead_of_hanging() {
    // The board accepts batches but never plays them (its stream is stuck).
    let mut client = Client::new(FakeBoard::new(200, 0.0));
    client.set_timeout(Duration::from_millis(100));
    let err = stream_setpoints(&mut client, &ramp(1000), &StreamOptions::default(), |_| {})
        .expect_err("stalls");
    assert!(err.to_string().contains("not playing the stream"), "{err}");
    assert_eq!(err.accepted, 192, "two batches fit the queue");
}

#[test]
fn the_stream_numbers_its_batches_from_the_board_s_next_sequence_number() {
    let mut board = FakeBoard::new(400, 50_000.0);
    board.expected_seq = 1234;
    let mut client = Client::new(board);
    let report = stream_setpoints(&mut client, &ramp(1000), &StreamOptions::default(), |_| {})
        .expect("stream");
    assert!(report.nacks.is_empty(), "{:?}", report.nacks);
    assert_eq!(client.transport().batches[0].0, 1234);
}

#[test]
fn a_request_damaged_on_the_line_is_sent_again_but_not_forever() {
    let mut board = FakeBoard::new(100, 1000.0);
    board.refuse_status = 2;
    let mut client = Client::new(board);
    assert!(client.status().is_ok(), "two damaged, the third arrives");
    client.transport_mut().refuse_status = 3;
    let err = client.status().expect_err("gives up");
    assert!(err.to_string().contains("CRC mismatch"), "{err}");
}

#[test]
fn a_credit_probe_damaged_on_the_line_is_asked_again() {
    // A small queue forces credit probes (status requests 1, 2, …; 0 is the one before the
    // stream); some of them arrive damaged.
    let mut board = FakeBoard::new(150, 50_000.0);
    board.refuse_status_at = vec![1, 3, 4, 9];
    let mut client = Client::new(board);
    let samples = ramp(3000);
    let r =
        stream_setpoints(&mut client, &samples, &StreamOptions::default(), |_| {}).expect("stream");
    assert_eq!(r.accepted, 3000);
    assert_eq!(client.transport().played, samples);
    assert_eq!(
        r.nacks,
        vec![NackReason::Frame(FrameError::BadCrc); 4],
        "each damaged probe seen and asked again"
    );
}
