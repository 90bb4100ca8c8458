//! Streaming over a realistic link: the simulated board behind a USB–serial adapter's latency
//! and jitter ([`LinkDelay::ADAPTER`], 16 ms ± 4 ms each way), at 50 kHz and 100 kHz with
//! divider 1. The streamer's underrun count is the board's own counter, read here straight
//! from the board (not over the link). Time is simulated: these are counts, not timings.

use std::time::Duration;

use hal_sim::sim_device::{full_range_triangle, LinkDelay, SimDevice, SimDeviceConfig};
use twinstack::control_loop::SETPOINT_CAPACITY;
use twinstack::protocol::messages::{Request, Response, UnderrunPolicy};
use twinstack_link::client::Client;
use twinstack_link::streamer::{stream_setpoints, StreamOptions, StreamReport};

fn device(rate_hz: f64, baud: u32, link: LinkDelay) -> Client<SimDevice> {
    Client::new(SimDevice::new(SimDeviceConfig::paper_at(rate_hz, baud, link)).expect("device"))
}

/// Streams `samples` (hold policy) and checks the report's count against the board's own
/// counter, then returns the report.
fn stream_and_check(client: &mut Client<SimDevice>, samples: &[i16]) -> StreamReport {
    let before = client.transport().control().telemetry().underruns;
    let options = StreamOptions {
        underrun: Some(UnderrunPolicy::Hold),
        ..StreamOptions::default()
    };
    let r = stream_setpoints(client, samples, &options, |_| {}).expect("stream");
    assert_eq!(r.accepted, samples.len());
    let dev = client.transport();
    let counted = dev.control().telemetry().underruns.wrapping_sub(before);
    assert_eq!(
        r.underruns_during_stream(),
        counted,
        "the streamer's count is the board's counter: {r:?}"
    );
    assert!(!dev.control().telemetry().streaming, "the stream ended");
    r
}

#[test]
fn ten_seconds_at_50_and_100_khz_through_an_adapter_s_latency_never_run_dry() {
    for rate in [50_000.0, 100_000.0] {
        let mut client = device(rate, hal_sim::port::DEFAULT_BAUD, LinkDelay::ADAPTER);
        // Ten seconds: fifty queues' worth at 100 kHz, a hundred at 50 kHz.
        let n = (10.0 * rate) as usize;
        let samples = full_range_triangle(n, 5000);
        let r = stream_and_check(&mut client, &samples);
        assert_eq!(r.underruns_during_stream(), 0, "{rate} Hz: {r:?}");
        assert!(!r.primed_whole, "the stream outlasted the queue");
        assert!(r.nacks.is_empty(), "{:?}", r.nacks);
        // Pipelined: far more than one batch in flight to cover the round trip.
        assert!(r.max_unacked > 10 * 96, "{rate} Hz: {r:?}");
        // The board played every setpoint: it ticked at least once per setpoint.
        let end = r.drained.expect("drained");
        assert!(end.ticks.wrapping_sub(r.before.ticks) as usize >= n);
        // Two bytes and a bit a setpoint on the line (packed batches), whatever the values.
        let per = r.link.bytes_sent as f64 / n as f64;
        assert!(per < 2.2, "{per} bytes a setpoint");
    }
}

#[test]
fn a_link_too_slow_for_the_rate_underruns_and_the_count_is_the_board_s() {
    // 1 Mbaud carries 100 000 bytes/s: under 47 000 packed setpoints/s, for a 100 kHz
    // stream. The queue primes full, then runs dry again and again.
    let mut client = device(100_000.0, 1_000_000, LinkDelay::ADAPTER);
    let samples = full_range_triangle(SETPOINT_CAPACITY + 30_000, 4000);
    let r = stream_and_check(&mut client, &samples);
    assert!(r.underruns_during_stream() > 10_000, "{r:?}");
    // The ticks after the end are not counted: the stream finished by itself.
    let dev = client.transport();
    let after = dev.control().telemetry().underruns;
    client.wait(Duration::from_millis(50)).unwrap();
    assert_eq!(client.transport().control().telemetry().underruns, after);
}

#[test]
fn the_adapter_s_latency_is_on_every_round_trip() {
    for (link, at_least, below) in [
        (LinkDelay::IDEAL, Duration::ZERO, Duration::from_millis(1)),
        (
            LinkDelay::ADAPTER,
            Duration::from_millis(24),
            Duration::from_millis(41),
        ),
    ] {
        let mut client = device(50_000.0, 3_000_000, link);
        for _ in 0..5 {
            let start = client.transport().now();
            assert!(matches!(
                client.request(&Request::Status).unwrap(),
                Response::Status(_)
            ));
            let rtt = client.transport().now() - start;
            assert!(rtt >= at_least && rtt < below, "{link:?}: {rtt:?}");
        }
    }
}

#[test]
fn a_jitter_larger_than_the_latency_is_refused() {
    let e = LinkDelay::new(Duration::from_millis(2), Duration::from_millis(3)).unwrap_err();
    assert!(e.to_string().contains("exceeds its latency"), "{e}");
    let config = SimDeviceConfig {
        link: LinkDelay {
            latency: Duration::from_millis(1),
            jitter: Duration::from_millis(2),
            seed: 7,
        },
        ..SimDeviceConfig::paper()
    };
    assert!(SimDevice::new(config).is_err());
}

/// A record streamed in parts, every call but the last with `more` and every one but the first
/// with `continues`, plays as one stream through the adapter's latency: no underrun, no stop
/// between the parts, the stream ended by the last. The same parts each streamed as a stream
/// of their own stop and start again between them: the board holds for round trips there.
#[test]
fn a_record_streamed_in_parts_plays_as_one_stream() {
    let rate = 50_000.0;
    let n = 60_000;
    let samples = full_range_triangle(n, 5000);
    let parts: Vec<&[i16]> = samples.chunks(20_000).collect();
    // Ticks from before the first part to the drained end, underruns, and whether it streams.
    let run = |continued: bool| {
        let mut client = device(rate, hal_sim::port::DEFAULT_BAUD, LinkDelay::ADAPTER);
        let underruns = client.transport().control().telemetry().underruns;
        let (mut first, mut end) = (0, 0);
        for (i, part) in parts.iter().enumerate() {
            let last = i + 1 == parts.len();
            let options = StreamOptions {
                underrun: Some(UnderrunPolicy::Hold),
                more: continued && !last,
                continues: continued && i > 0,
                drain: last,
                ..StreamOptions::default()
            };
            let r = stream_setpoints(&mut client, part, &options, |_| {}).expect("stream");
            assert_eq!(r.accepted, part.len());
            if i == 0 {
                first = r.before.ticks;
            }
            if last {
                end = r.drained.expect("drained").ticks;
            }
        }
        let t = client.transport().control().telemetry();
        (
            end.wrapping_sub(first) as usize,
            t.underruns.wrapping_sub(underruns),
            t.streaming,
        )
    };
    let (one, underruns, streaming) = run(true);
    assert_eq!(underruns, 0, "the parts came before the queue ran dry");
    assert!(!streaming, "the last part ended the stream");
    assert!(one >= n, "every setpoint played: {one} ticks");
    let (apart, _, _) = run(false);
    eprintln!("one stream {one} ticks, parts apart {apart}");
    assert!(
        apart > one + 1000,
        "each part a stream of its own holds between them: {apart} ticks against {one}"
    );
}

/// A stream started by the trigger input's edge ([`StreamOptions::start_on`]): the queue is
/// primed, the input armed, and the stream plays from the camera's first frame — a record the
/// queue holds whole and one four times the queue through the adapter's latency, neither
/// running dry. With nothing on the input, the wait ends with the input disarmed, nothing
/// played and the setpoints still queued.
#[test]
fn a_stream_started_by_the_input_s_edge_plays_from_the_camera_s_frame() {
    use hal_sim::sim_camera::CameraConfig;
    use twinstack::protocol::messages::{StatusReport, TriggerEdge};
    use twinstack_link::streamer::StartOn;
    let rate = 50_000.0;
    let start_on = |wait| StartOn {
        edge: TriggerEdge::Rising,
        pulse_ticks: 2,
        wait,
    };
    for n in [2_000, 4 * SETPOINT_CAPACITY] {
        let mut client = device(rate, hal_sim::port::DEFAULT_BAUD, LinkDelay::ADAPTER);
        // One frame 10 ms after the stream is armed to start on its edge.
        let camera = CameraConfig::at_rate(100.0, rate, 1, false).unwrap();
        client.transport_mut().set_camera(Some(camera));
        let samples = full_range_triangle(n, 5000);
        let options = StreamOptions {
            underrun: Some(UnderrunPolicy::Hold),
            start_on: Some(start_on(Duration::from_secs(1))),
            ..StreamOptions::default()
        };
        let r = stream_setpoints(&mut client, &samples, &options, |_| {}).expect("stream");
        assert_eq!(r.accepted, n);
        assert_eq!(r.underruns_during_stream(), 0, "{n}: {r:?}");
        assert_eq!(r.primed_whole, n < SETPOINT_CAPACITY);
        let end = r.drained.expect("drained");
        assert!(end.ticks.wrapping_sub(r.before.ticks) as usize >= n);
        let dev = client.transport();
        assert_eq!(
            dev.control().trigger_fired(),
            1,
            "the camera's edge started it"
        );
        assert!(!dev.control().telemetry().streaming, "the stream ended");
    }
    // Nothing on the input: the stream never starts.
    let mut client = device(rate, hal_sim::port::DEFAULT_BAUD, LinkDelay::IDEAL);
    let samples = full_range_triangle(2_000, 5000);
    let options = StreamOptions {
        start_on: Some(start_on(Duration::from_millis(50))),
        ..StreamOptions::default()
    };
    let e = stream_setpoints(&mut client, &samples, &options, |_| {}).unwrap_err();
    assert!(
        e.to_string()
            .contains("rising edge did not come within 50ms"),
        "{e}"
    );
    assert_eq!(e.accepted, 2_000);
    let s = client.status().unwrap();
    assert!(!s.has(StatusReport::TRIGGER_ARMED), "disarmed: {s:?}");
    assert!(!s.has(StatusReport::STREAMING));
    assert_eq!(s.queue_fill, 2_000, "the setpoints stay queued");
}
