use super::*;

#[test]
fn the_decimation_fits_the_run_into_the_slots_at_most_at_the_rate_asked() {
    let facts = CaptureStatus {
        capacity: 65_536,
        ..CaptureStatus::default()
    };
    // 2 s at 50 kHz, 2 signals, 10 kHz asked: every 5th tick, 20 000 frames.
    assert_eq!(
        decimation_for(100_000, 50_000.0, 10_000.0, &facts, 2),
        (5, 20_000)
    );
    // The emulator's 32 768 slots: every 7th tick.
    let half = CaptureStatus {
        capacity: 32_768,
        ..facts
    };
    let (d, f) = decimation_for(100_000, 50_000.0, 10_000.0, &half, 2);
    assert_eq!((d, f), (7, 14_286));
    assert!(f <= 16_384);
}

#[test]
fn the_excitation_streamed_starts_at_the_middle_and_sweeps_the_amplitude_without_a_jump() {
    let o = CalibrateOptions::default();
    let rate = 10_000.0;
    let s = o.excitation_setpoints(rate);
    // The lead-in (a quarter cycle, 25 ms at 10 Hz) and the 2 s excitation.
    assert!((o.excitation_s() - 2.025).abs() < 1e-12);
    assert_eq!(s.len(), 20_250);
    assert_eq!(s[0], 0);
    // The lead-in ends at the bottom of the swept range, where the excitation starts.
    let bottom = q1_15(-o.amplitude);
    assert!((s[250] - bottom).abs() <= 1, "{} vs {bottom}", s[250]);
    let (lo, hi) = s
        .iter()
        .fold((i16::MAX, i16::MIN), |(l, h), &v| (l.min(v), h.max(v)));
    assert!(
        (lo - bottom).abs() <= 1 && (hi + bottom).abs() <= 1,
        "{lo} {hi}"
    );
    // No step larger than the full cycles' own (2π·10 Hz × 0.97 of the half range).
    let largest = s
        .windows(2)
        .map(|w| (w[1] as i32 - w[0] as i32).abs())
        .max()
        .unwrap();
    assert!(largest <= 210, "{largest}");
    // Another amplitude scales it.
    let half = CalibrateOptions {
        amplitude: 0.5,
        ..o.clone()
    }
    .excitation_setpoints(rate);
    assert_eq!(half.len(), s.len());
    assert!((half[250] - q1_15(-0.5)).abs() <= 1);
}

#[test]
fn bad_options_are_named() {
    let bad = CalibrateOptions {
        excitation_hz: f64::NAN,
        ..CalibrateOptions::default()
    };
    assert!(bad
        .check()
        .unwrap_err()
        .to_string()
        .contains("excitation_hz"));
    let bad = CalibrateOptions {
        final_amplitude: 1.0,
        ..CalibrateOptions::default()
    };
    assert!(bad
        .check()
        .unwrap_err()
        .to_string()
        .contains("final_amplitude"));
    // A fastest motion at or below the excitation's frequency, beyond 1 000 times it, or not
    // a number: refused, naming both frequencies and the range.
    for fastest in [8.0, 10.0, 10_001.0, f64::NAN, f64::INFINITY, -5.0] {
        let bad = CalibrateOptions {
            fastest_hz: Some(fastest),
            ..CalibrateOptions::default()
        };
        let e = bad.check().unwrap_err();
        assert!(
            matches!(e, CalibrateError::FastestOutOfRange { excitation_hz, .. } if excitation_hz == 10.0),
            "{fastest}: {e}"
        );
        let text = e.to_string();
        assert!(
            text.contains("fastest_hz")
                && text.contains("10 Hz (excitation_hz)")
                && text.contains("10000 Hz"),
            "{text}"
        );
    }
    // The top of the range is allowed.
    let top = CalibrateOptions {
        fastest_hz: Some(10_000.0),
        ..CalibrateOptions::default()
    };
    assert!(top.check().is_ok());
}

#[test]
fn the_fastest_motion_named_is_swept_and_must_be_resolved_where_it_is_streamed_and_recorded() {
    let options = CalibrateOptions {
        fastest_hz: Some(200.0),
        ..CalibrateOptions::default()
    };
    assert!(options.check().is_ok());
    // The sweep adds its 0.4 s; the lead-in and the rest are the default's.
    let default = CalibrateOptions::default();
    assert!((options.excitation_s() - default.excitation_s() - 0.4).abs() < 1e-12);
    // 200 Hz wants 4 000 samples a second, streamed and recorded.
    assert!(options.check_resolved(10_000.0, 4_000.0).is_ok());
    // Where the stream is the limit only a slower motion helps; where the recorder's slots
    // are, a shorter excitation does too (the recorder holds it at a higher rate).
    for (stream, recorded, shorten) in [(3_999.0, 10_000.0, false), (10_000.0, 3_999.0, true)] {
        let e = options.check_resolved(stream, recorded).unwrap_err();
        assert!(
            matches!(e, CalibrateError::FastestUnresolved { fastest_hz, .. } if fastest_hz == 200.0),
            "{e}"
        );
        assert!(e.to_string().contains("fastest_hz = 200"), "{e}");
        assert_eq!(
            e.to_string().contains("shorten the excitation"),
            shorten,
            "{e}"
        );
    }
    // Beyond what calibrate records at all (`sample_rate_hz`), a shorter excitation does not
    // help.
    let e = CalibrateOptions {
        fastest_hz: Some(600.0),
        ..CalibrateOptions::default()
    }
    .check_resolved(20_000.0, 10_000.0)
    .unwrap_err();
    assert!(!e.to_string().contains("shorten"), "{e}");
    // Without a sweep the fastest motion is the multisine's 13 Hz tone.
    assert!(default.check_resolved(260.0, 260.0).is_ok());
    assert!(default.check_resolved(259.0, 10_000.0).is_err());
}

#[test]
fn the_test_trajectory_is_two_triangles_then_the_loops_within_the_range() {
    let tr = trajectory::test_trajectory((10.0, 50.0), 1000.0);
    let (lo, hi) =
        tr.x.iter()
            .fold((f64::MAX, f64::MIN), |(l, h), &v| (l.min(v), h.max(v)));
    assert!((lo - 10.0).abs() < 1e-9 && (hi - 50.0).abs() < 1e-9);
    // 1 s of triangle (4 sweeps at 4 spans/s) then ≈ 1.2 s of loops.
    assert!(tr.x.len() > 2000 && tr.x.len() < 2500, "{}", tr.x.len());
    assert!((tr.x[250] - 50.0).abs() < 1e-9 && (tr.x[500] - 10.0).abs() < 1e-9);
    // No jump where the loops start.
    assert!(tr.x.windows(2).all(|w| (w[1] - w[0]).abs() < 0.2));
}
