//! Learning feedforward on the simulated differential stage. With input
//! shaping (the feedforward's notch on the resonance `twinstack tune` fits, and the learning's
//! corner raised above it) the max and replay goals are met on every waveform and frequency,
//! and the RMS reaches the floor the sensor and the resonance band leave (the RMS goal, 20×
//! below a feedforward that already tracks within 0.07–0.24 % RMS, lies under it); without
//! shaping, the goals it meets are held and, for those it does not, the figures it reaches
//! (so a regression fails) and the reason (the 21.8 kHz resonance band, which the learning
//! does not act on there).
//! Deterministic: seeded noise, simulated time.

use std::sync::OnceLock;
use twinstack_cli::closed_loop::{identify_model, ClosedLoopOptions};
use twinstack_cli::learn::{run_with, LearnOptions, LearnReport};

/// Both runs at 50 kHz with the command's defaults (50 periods, gain 0.3, corner 18 kHz, no
/// lead), on the P–I model identified on the same board.
fn reports() -> &'static [LearnReport; 2] {
    static REPORTS: OnceLock<[LearnReport; 2]> = OnceLock::new();
    REPORTS.get_or_init(|| runs(["sine:750", "triangle:200"]))
}

/// The P–I model identified on the simulated board at 50 kHz (once per test process).
fn model() -> &'static twinstack_identify::stage_model::StageModel {
    static MODEL: OnceLock<twinstack_identify::stage_model::StageModel> = OnceLock::new();
    MODEL.get_or_init(|| identify_model(50_000.0, &ClosedLoopOptions::default()).unwrap())
}

fn runs(waveforms: [&str; 2]) -> [LearnReport; 2] {
    waveforms.map(|w| {
        let mut o = LearnOptions::new(w.parse().unwrap());
        o.out_dir = None;
        run_with(&o, model()).unwrap()
    })
}

/// The runs with input shaping ([`LearnOptions::shaped`]: the notch on the tuned resonance,
/// 21 807 Hz, Q ½, depth 0.0173; corner 23 kHz).
fn shaped_runs<const N: usize>(waveforms: [&str; N]) -> [LearnReport; N] {
    waveforms.map(|w| {
        let mut o = LearnOptions::shaped(w.parse().unwrap());
        o.out_dir = None;
        run_with(&o, model()).unwrap()
    })
}

fn shaped_reports() -> &'static [LearnReport; 2] {
    static REPORTS: OnceLock<[LearnReport; 2]> = OnceLock::new();
    REPORTS.get_or_init(|| shaped_runs(["sine:750", "triangle:200"]))
}

/// With shaping, on both waveforms: the max and replay goals are met with margin (max ≤
/// 0.05 %, replayed with the sensor off ≤ 0.1 %; measured: sine 0.041 %, replay 0.041 %;
/// triangle 0.039 %, 0.048 %), the RMS is at the floor the sensor and the resonance band leave
/// (≤ 0.02 %: 0.018 %, 0.014 %), and below the band the learning takes the error down more
/// than 20× (to 0.002 %). The RMS goal, 20× below the feedforward alone, is not met: that
/// feedforward, timed by its drive's hold, already tracks within 0.11 % RMS, and 20× below it
/// lies under that floor (measured: 6.5×, 6.5×).
#[test]
fn with_shaping_the_learning_meets_the_max_and_replay_goals_at_its_floor() {
    for r in shaped_reports() {
        assert!(r.shaping.is_some() && r.shaped_feedforward.is_some());
        let goals = r.goals();
        for (goal, met) in &goals[1..] {
            assert!(
                met,
                "{}: {goal}: {:?} {:?}",
                r.waveform, r.learned, r.replay
            );
        }
        assert!(
            r.rms_reduction >= 5.0,
            "{}: {}",
            r.waveform,
            r.rms_reduction
        );
        assert!(r.learned.max_pct <= 0.05, "{}: {:?}", r.waveform, r.learned);
        assert!(r.learned.rms_pct <= 0.02, "{}: {:?}", r.waveform, r.learned);
        assert!(r.replay.max_pct <= 0.1, "{}: {:?}", r.waveform, r.replay);
        assert_eq!(r.missed, 0);
        let (ff, l) = (r.feedforward, r.learned);
        assert!(
            l.below_band_rms_pct < ff.below_band_rms_pct / 20.0,
            "{}: {l:?} vs {ff:?}",
            r.waveform
        );
        // The resonance band is no longer what is left alone: the learning took it down to
        // below half of what the unshaped learning leaves there (0.037–0.082 %).
        assert!(l.band_rms_pct < 0.02, "{}: {:?}", r.waveform, r.learned);
        // The curve falls 2× within 10 periods, and every period from the 30th on is within
        // the max goal and 5× below the feedforward alone (it converges more slowly than
        // without shaping: the sine's periods 30–50 lie within 0.014–0.018 % RMS).
        assert!(
            r.curve[9].rms_pct < r.feedforward.rms_pct / 2.0,
            "{}",
            r.waveform
        );
        assert!(
            r.curve[29..]
                .iter()
                .all(|p| p.rms_pct < r.feedforward.rms_pct / 5.0 && p.max_pct <= 0.1),
            "{}: {:?}",
            r.waveform,
            &r.curve[29..]
        );
    }
}

/// The same learning settings without the notch (corner 23 kHz on the bare stage) diverge:
/// it is the shaping that lets the learning act above the resonance. The divergence guard
/// switches that learning off once its error grows past twice its best: the stage is back to
/// the feedforward alone (no worse than without learning); the shaped learning never trips it.
#[test]
fn without_the_shaping_the_shaped_learning_diverges_and_its_guard_stops_it() {
    let mut o = LearnOptions::shaped("sine:750".parse().unwrap());
    o.out_dir = None;
    o.shaping = None;
    let bare = run_with(&o, model()).unwrap();
    let shaped = &shaped_reports()[0];
    assert!(
        !bare.goals()[0].1 && !bare.goals()[1].1,
        "{:?}",
        bare.learned
    );
    assert_eq!(
        bare.guard_stops, 1,
        "the guard stopped the diverging learning"
    );
    assert_eq!(
        shaped.guard_stops, 0,
        "the converging learning never trips it"
    );
    let worst = bare.curve.iter().map(|p| p.rms_pct).fold(0.0, f64::max);
    assert!(
        worst > 2.0 * bare.feedforward.rms_pct,
        "the learning diverged before the guard: {:?}",
        bare.curve
    );
    assert!(
        bare.learned.rms_pct <= 1.05 * bare.feedforward.rms_pct,
        "stopped, the stage is back to the feedforward alone: {:?} vs {:?}",
        bare.learned,
        bare.feedforward
    );
}

/// The second frequencies with the same shaped settings: the 500 Hz and 1 kHz sines and the
/// 100 Hz and 250 Hz triangles (its 87th harmonic on the resonance) meet the max and replay
/// goals (measured max 0.014, 0.032, 0.031, 0.078 %), and below the resonance band the learning
/// takes the error down more than 20×; the RMS reduction is 5.5–13.9× (the feedforward alone
/// is already within 0.07–0.24 % RMS).
#[test]
fn with_shaping_at_the_second_frequencies() {
    let reports = shaped_runs(["sine:500", "sine:1000", "triangle:100", "triangle:250"]);
    for r in &reports {
        for (goal, met) in &r.goals()[1..] {
            assert!(
                met,
                "{}: {goal}: {:?} {:?}",
                r.waveform, r.learned, r.replay
            );
        }
        assert!(
            r.rms_reduction >= 5.0,
            "{}: {}",
            r.waveform,
            r.rms_reduction
        );
        let (ff, l) = (r.feedforward, r.learned);
        assert!(
            l.below_band_rms_pct < ff.below_band_rms_pct / 20.0,
            "{}: {l:?} vs {ff:?}",
            r.waveform
        );
    }
}

/// A second frequency of each shape, with the same settings (not tuned to them): a 500 Hz
/// sine (100 ticks a cycle, period 200) and a 100 Hz triangle (500 ticks). The sine meets the
/// max and replay goals (0.076 %, 0.074 %); the triangle's max is bounded near what it reaches
/// (0.27 %, replay 0.27 %), its reversal's overshoot on the resonance. Below the resonance band
/// the learning takes both down more than 15× (17×, 32×); the band's ringing is what is left.
#[test]
fn a_second_frequency_of_each_shape() {
    let [sine, triangle] = runs(["sine:500", "triangle:100"]);
    assert!(sine.learned.max_pct <= 0.1, "{:?}", sine.learned);
    assert!(sine.replay.max_pct <= 0.2, "{:?}", sine.replay);
    assert!(triangle.learned.max_pct <= 0.3, "{:?}", triangle.learned);
    assert!(triangle.replay.max_pct <= 0.3, "{:?}", triangle.replay);
    for r in [&sine, &triangle] {
        let (ff, l) = (r.feedforward, r.learned);
        assert!(
            l.below_band_rms_pct < ff.below_band_rms_pct / 15.0,
            "{}: {l:?}",
            r.waveform
        );
        assert!(
            l.band_rms_pct > l.below_band_rms_pct,
            "{}: {l:?}",
            r.waveform
        );
    }
}

#[test]
fn the_learning_curve_falls_and_stays_down() {
    for r in reports() {
        assert_eq!(r.curve.len(), 50);
        assert_eq!(r.missed, 0, "{}", r.waveform);
        assert!(r.updates >= 48, "{}: {} updates", r.waveform, r.updates);
        // The first period plays the empty table: the feedforward's own error.
        assert!(
            r.curve[0].rms_pct > 0.9 * r.feedforward.rms_pct,
            "{}",
            r.waveform
        );
        // Below the resonance band, down by 3× within 10 periods (and 15× by the last, see
        // `what_is_left_is_the_resonance_band`); no period after 20 is worse than 1.5× the
        // last.
        assert!(
            r.curve[9].below_band_rms_pct < r.feedforward.below_band_rms_pct / 3.0,
            "{}: {:?}",
            r.waveform,
            r.curve[9]
        );
        let last = r.learned.rms_pct;
        assert!(
            r.curve[20..].iter().all(|p| p.rms_pct < 1.5 * last),
            "{}",
            r.waveform
        );
    }
}

/// Without shaping, the goals met: the triangle's replay with the sensor off ≤ 0.2 % max
/// (0.132 %); and the replay (a fresh board, no sensor) plays what was learned.
#[test]
fn the_goals_met_hold() {
    let [sine, triangle] = reports();
    assert!(triangle.replay.max_pct <= 0.2, "{:?}", triangle.replay);
    // The sine's replay is bounded near what it reaches (0.233 %): its resonance band.
    assert!(sine.replay.max_pct <= 0.26, "{:?}", sine.replay);
    for r in reports() {
        assert!(r.replay.rms_pct < 1.2 * r.learned.rms_pct, "{}", r.waveform);
    }
}

/// Without shaping, the goals not met — the RMS reduction (≥ 20× asked; measured 1.4× on the
/// sine, 2.5× on the triangle), the max (≤ 0.1 % asked; 0.234 %, 0.139 %), the sine's replay —
/// and why: what is left is the resonance band's ringing (0.083 %, 0.037 % RMS above 15 kHz),
/// which the feedforward alone has as much of (its P–I's breakpoints excite the 21.8 kHz
/// resonance); below the band the learning reduces the error by more than 15× on both (to
/// 0.004 %).
#[test]
fn what_is_left_is_the_resonance_band() {
    let [sine, triangle] = reports();
    assert!(sine.learned.max_pct <= 0.26, "{:?}", sine.learned);
    assert!(triangle.learned.max_pct <= 0.16, "{:?}", triangle.learned);
    for r in reports() {
        let ff = r.feedforward;
        let l = r.learned;
        assert!(
            r.rms_reduction >= 1.3,
            "{}: {}",
            r.waveform,
            r.rms_reduction
        );
        assert!(
            l.below_band_rms_pct < ff.below_band_rms_pct / 15.0,
            "{}: below the band {} → {}",
            r.waveform,
            ff.below_band_rms_pct,
            l.below_band_rms_pct
        );
        // The band's ringing is what is left, and the feedforward alone has as much of it.
        assert!(
            l.band_rms_pct > 10.0 * l.below_band_rms_pct,
            "{}: {l:?}",
            r.waveform
        );
        assert!(
            l.band_rms_pct > 0.8 * ff.band_rms_pct,
            "{}: {l:?} vs {ff:?}",
            r.waveform
        );
    }
}

fn sim_port() -> twinstack_cli::board_link::PortArgs {
    twinstack_cli::board_link::PortArgs {
        port: Some("sim".into()),
        baud: 3_000_000,
        timeout_ms: 2000,
        link: Default::default(),
    }
}

/// Over the protocol, on the simulated board (its representative, not identified, model and
/// 12-bit converters): the board learns from its own sensor, and the frozen table keeps
/// what was learned.
#[test]
fn a_board_learns_over_the_protocol() {
    let mut o = LearnOptions::new("sine:750".parse().unwrap());
    o.out_dir = None;
    o.periods = 40;
    let r = twinstack_cli::learn_link::run(&sim_port(), &o, 0.5).unwrap();
    assert_eq!(r.image, "simulator");
    assert_eq!(r.period_ticks, 200);
    assert_eq!(r.curve.len(), 40);
    let ff = r.feedforward.iter().map(|p| p.rms_pct).fold(0.0, f64::max);
    let learned = r.curve[35..].iter().map(|p| p.rms_pct).fold(0.0, f64::max);
    let replay = r.replay.iter().map(|p| p.rms_pct).fold(0.0, f64::max);
    assert!(learned < ff / 20.0, "{ff} → {learned}");
    assert!(replay < 1.5 * learned, "{learned} → replay {replay}");
}

/// A refused learning request names the field and its limit, and changes nothing.
#[test]
fn the_board_refuses_what_it_cannot_learn() {
    use twinstack::protocol::messages::{LearnRequest, NackReason, Request, Response};
    use twinstack::refusal::{Field, Refusal, Rule};
    use twinstack::services::learning::{LearnSettings, LearnState};
    let mut client = twinstack_cli::board_link::connect(&sim_port()).unwrap();
    let mut ask = |r: LearnRequest| client.request(&Request::Learn(r)).unwrap();
    let refused = |field, rule| Response::Nack {
        reason: NackReason::Refused(Refusal::new(field, rule)),
    };
    assert_eq!(
        ask(LearnRequest::State(LearnState::Learning)),
        refused(Field::LearnPeriod, Rule::Required)
    );
    let mut s = LearnSettings::for_period(200);
    s.gain = 3.0;
    assert_eq!(
        ask(LearnRequest::Configure(s)),
        refused(Field::LearnGain, Rule::AtMost(1.5))
    );
    s.gain = 0.3;
    s.cutoff_hz = 40_000.0;
    assert_eq!(
        ask(LearnRequest::Configure(s)),
        refused(Field::LearnCutoff, Rule::Below(25_000.0))
    );
    match ask(LearnRequest::Status) {
        Response::Learn(st) => {
            assert_eq!(st.state, LearnState::Off);
            assert_eq!(st.period_ticks, 0, "nothing was configured");
        }
        other => panic!("{other:?}"),
    }
}
