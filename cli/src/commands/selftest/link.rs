//! The link check: frames of random content and length echoed by the board and compared
//! byte for byte, with both sides' corrupt-frame counters before and after.
use super::*;

/// xorshift64*: the echoes' lengths and bytes.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
}

/// The echoes' lengths: the largest and the empty one first, then random.
fn echo_payload(i: u32, rng: &mut Rng) -> Vec<u8> {
    let len = match i {
        0 => MAX_ECHO,
        1 => 0,
        _ => (rng.next() % (MAX_ECHO as u64 + 1)) as usize,
    };
    (0..len).map(|_| (rng.next() >> 56) as u8).collect()
}

pub(super) fn link(
    client: &mut BoardClient,
    echoes: u32,
    seed: u64,
) -> anyhow::Result<CheckResult> {
    let check = CheckName::Link;
    let before = retry(client, |c| c.status())?;
    let host_before = client.counters().corrupt_frames;
    let timeout = client.timeout();
    let mut rng = Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    let (mut intact, mut damaged_in, mut lost, mut differ, mut bytes) =
        (0u32, 0u32, 0u32, 0u32, 0u64);
    let mut unknown = 0u32;
    let mut rtt_max = Duration::ZERO;
    let origin = Instant::now();
    for i in 0..echoes {
        let payload = echo_payload(i, &mut rng);
        bytes += payload.len() as u64;
        let request =
            Request::Echo(heapless::Vec::from_slice(&payload).expect("at most MAX_ECHO bytes"));
        let start = link_now(client, origin);
        // Sent once, not retried: a damaged frame is what this check counts.
        client.send(&request)?;
        match client.receive(timeout)? {
            Some(Response::Echo(back)) if back.as_slice() == payload.as_slice() => {
                intact += 1;
                rtt_max = rtt_max.max(link_now(client, origin).saturating_sub(start));
            }
            Some(Response::Echo(_)) => differ += 1,
            Some(Response::Nack {
                reason: NackReason::Frame(FrameError::UnknownType),
            }) => unknown += 1,
            Some(Response::Nack {
                reason: NackReason::Frame(_),
            }) => damaged_in += 1,
            Some(_) => {
                // Another answer (a late one): start the next echo on a clean line.
                differ += 1;
                client.resync(Duration::from_millis(20))?;
            }
            None => {
                lost += 1;
                client.resync(Duration::from_millis(20))?;
            }
        }
    }
    let after = retry(client, |c| c.status())?;
    let crc = after.crc_errors.wrapping_sub(before.crc_errors);
    let frame = after.frame_errors.wrapping_sub(before.frame_errors);
    let host = client.counters().corrupt_frames - host_before;
    let figures = serde_json::json!({
        "echoes": echoes,
        "intact": intact,
        "damaged_to_board": damaged_in,
        "lost": lost,
        "differing": differ,
        "unanswered_type": unknown,
        "bytes": bytes,
        "board_crc_errors": crc,
        "board_frame_errors": frame,
        "host_corrupt_frames": host,
        "max_round_trip_ms": rtt_max.as_secs_f64() * 1e3,
    });
    if unknown == echoes {
        return Ok(CheckResult::fail(
            check,
            format!("the board answered none of {echoes} echoes: it does not know the request"),
            "its firmware predates the echo: build and flash the current image (cargo build-fw, probe-rs), then run the selftest again",
            figures,
        ));
    }
    let bad = echoes - intact;
    let counted = format!(
        "board counted {crc} CRC and {frame} other frame errors, host skipped {host} corrupt frames"
    );
    if bad > 0 || crc > 0 || frame > 0 || host > 0 {
        return Ok(CheckResult::fail(
            check,
            format!(
                "{bad} of {echoes} echoes corrupted ({damaged_in} damaged on the way to the board, {lost} lost or damaged on the way back, {differ} answered wrong; {counted})"
            ),
            "check the adapter's ground and the baud rate on both ends (3 Mbaud by default: --baud), shorten the cable, keep it away from the amplifier's high-voltage leads",
            figures,
        ));
    }
    Ok(CheckResult::pass(
        check,
        format!(
            "{echoes} echoes of 0…{MAX_ECHO} bytes ({bytes} bytes each way) came back intact; {counted}; slowest round trip {:.1} ms",
            rtt_max.as_secs_f64() * 1e3
        ),
        figures,
    ))
}
