//! How fast a record moves: the fastest motion in its drive, against which `identify` holds
//! the fastest motion the user will run (`identify --fastest-hz`).
//!
//! A model fitted on a record has seen the rates the record moves at and no faster: creep
//! modes and dynamics faster than its motion are folded into its gain, so its compensator
//! holds at those rates and drifts from the stage above them (a model fitted on a 1 Hz record
//! tracks 200 Hz poorly; `twinstack calibrate --fastest-hz` sweeps up to the rate named).
//!
//! **The measure.** The drive is cut at its turning points, each confirmed once the drive has
//! come back from it by [`MIN_SWING`] of its span (a peak-and-valley filter: a reversal
//! smaller than that, a minor loop or noise, is part of the swing it interrupts). Each swing
//! between two turning points is half a cycle of motion; the fastest motion is the highest
//! `1 / (2 × its duration)` over the swings. A swing's size, not a speed or the time between
//! any two reversals: a minor loop of a few percent of the span that reverses in milliseconds
//! (the default excitation's nested loops) is not fast motion of the stage, and a sine over
//! [`MIN_SWING`] of the span or more reads at its frequency. The start of the record is not a
//! turning point: the first swing counted ends at the second turn. One odd swing sets the figure,
//! so it is "about": a swing that is only part of a half cycle reads faster than the motion
//! it belongs to.

/// The least swing, as a fraction of the drive's span, between two turning points: a fifth
/// of the span.
pub const MIN_SWING: f64 = 0.2;

/// A record falls short of a fastest motion named when its own is slower than this fraction
/// of it ([`falls_short`]): an octave short.
pub const SHORT_OF: f64 = 0.5;

/// Whether a record whose fastest motion is `fastest` ([`fastest_motion_hz`]) falls short of
/// the fastest motion the user names, `named_hz`: slower than [`SHORT_OF`] of it, or no
/// motion at all. `calibrate --fastest-hz`'s own record never does: its sweep swings by a
/// fifth of the span up to at least 0.57 of the rate named, over every range it takes (its
/// half-sine window is 0.25 of its peak at 92 % of its length, a geometric sweep of at most
/// 1 000 times its start there at least 0.57 of the way up).
///
/// ```
/// use twinstack_identify::identification::coverage::falls_short;
/// assert!(falls_short(Some(10.0), 200.0));
/// assert!(!falls_short(Some(150.0), 200.0));
/// assert!(falls_short(None, 5.0));
/// ```
pub fn falls_short(fastest: Option<f64>, named_hz: f64) -> bool {
    fastest.is_none_or(|f| f < SHORT_OF * named_hz)
}

/// A rate in words: whole hertz from 10 Hz up, a tenth below.
fn hz(f: f64) -> String {
    if f >= 10.0 {
        format!("{f:.0} Hz")
    } else {
        format!("{f:.1} Hz")
    }
}

/// What a record's fastest motion ([`fastest_motion_hz`] of its fitted part) says, in words:
/// what `identify` and `calibrate` print.
///
/// ```
/// use twinstack_identify::identification::coverage::seen;
/// assert_eq!(
///     seen(Some(37.2)),
///     "the fitted part swings by a fifth of its span or more at up to about 37 Hz"
/// );
/// ```
pub fn seen(fastest: Option<f64>) -> String {
    match fastest {
        Some(f) => format!(
            "the fitted part swings by a fifth of its span or more at up to about {}",
            hz(f)
        ),
        None => "the fitted part's drive never swings by a fifth of its span".into(),
    }
}

/// The fastest motion a user may name, Hz: 20 samples a cycle at the board's fastest control
/// rate (100 kHz), the most `calibrate --fastest-hz` sweeps.
pub const MAX_NAMED_HZ: f64 = 5_000.0;

/// Checks a fastest motion the user names (`identify --fastest-hz`, Python's `fastest_hz`):
/// a positive number of Hz, at most [`MAX_NAMED_HZ`]; else the rule it breaks, in words.
///
/// ```
/// use twinstack_identify::identification::coverage::check_named;
/// assert!(check_named(200.0).is_ok());
/// assert!(check_named(1e9).unwrap_err().contains("at most 5000 Hz"));
/// assert!(check_named(f64::NAN).is_err());
/// ```
pub fn check_named(named_hz: f64) -> Result<(), String> {
    if named_hz > 0.0 && named_hz <= MAX_NAMED_HZ {
        Ok(())
    } else {
        Err(format!(
            "{named_hz}: must be a number of Hz above 0 and at most {MAX_NAMED_HZ} Hz (20 samples a cycle at the board's fastest 100 kHz)"
        ))
    }
}

/// Where a record whose fastest motion is `fastest` falls short of the fastest motion the
/// user names ([`falls_short`]), the advice, in words (`None` where it does not): what
/// `identify --fastest-hz` prints and Python's `identify(fastest_hz=…)` warns.
///
/// ```
/// use twinstack_identify::identification::coverage::advice;
/// assert_eq!(advice(Some(12.0), 20.0), None);
/// assert!(advice(Some(1.0), 200.0).unwrap().contains("calibrate --fastest-hz 200"));
/// ```
pub fn advice(fastest: Option<f64>, named_hz: f64) -> Option<String> {
    if !falls_short(fastest, named_hz) {
        return None;
    }
    let seen = match fastest {
        Some(f) => format!("the model has seen motion up to about {}", hz(f)),
        None => "the model has seen no swing of a fifth of the span".into(),
    };
    Some(format!(
        "{seen} and you will run {}: creep and dynamics faster than the record are folded into \
         its gain, and its compensator may not hold there; record an excitation that reaches it \
         (`twinstack calibrate --fastest-hz {named_hz}` sweeps up to it)",
        hz(named_hz)
    ))
}

/// [`fastest_motion_hz`] over `rows` of the record (the fitted part, say): `None` where the
/// rows are not all in both `t` and `u`.
pub fn fastest_motion_in(t: &[f64], u: &[f64], rows: core::ops::Range<usize>) -> Option<f64> {
    fastest_motion_hz(t.get(rows.clone())?, u.get(rows)?)
}

/// The fastest motion in the drive `u` sampled at the times `t` (see the module's
/// documentation), Hz: `None` for fewer than two samples, a time axis that does not rise, a
/// drive that is not finite, or one that never swings by [`MIN_SWING`] of its span between
/// two turning points.
///
/// ```
/// use twinstack_identify::identification::coverage::fastest_motion_hz;
/// let rate = 10_000.0;
/// // Two seconds of 5 Hz over the whole span, then 0.2 s of 120 Hz over a third of it.
/// let t: Vec<f64> = (0..22_000).map(|k| k as f64 / rate).collect();
/// let u: Vec<f64> = t
///     .iter()
///     .map(|&t| {
///         let w = std::f64::consts::TAU;
///         if t < 2.0 { (w * 5.0 * t).sin() } else { 0.33 * (w * 120.0 * t).sin() }
///     })
///     .collect();
/// let hz = fastest_motion_hz(&t, &u).unwrap();
/// assert!((110.0..130.0).contains(&hz), "{hz}");
/// // The first two seconds alone: 5 Hz.
/// let hz = fastest_motion_hz(&t[..20_000], &u[..20_000]).unwrap();
/// assert!((4.5..5.5).contains(&hz), "{hz}");
/// ```
pub fn fastest_motion_hz(t: &[f64], u: &[f64]) -> Option<f64> {
    let n = t.len().min(u.len());
    if n < 2 || !u[..n].iter().all(|v| v.is_finite()) || !t[..n].iter().all(|v| v.is_finite()) {
        return None;
    }
    if t[..n].windows(2).any(|w| w[1] <= w[0]) {
        return None;
    }
    let (lo, hi) = u[..n]
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    let swing = MIN_SWING * (hi - lo);
    if swing <= 0.0 {
        return None;
    }
    // The running extremum since the last turning point, and which way the drive goes
    // (`None` until it has first moved a swing from the start).
    let (mut extreme, mut at) = (u[0], 0usize);
    let (mut low, mut high) = (u[0], u[0]);
    let mut rising: Option<bool> = None;
    let mut last_turn: Option<usize> = None;
    let mut fastest: Option<f64> = None;
    for (k, &v) in u[..n].iter().enumerate() {
        match rising {
            None => {
                // Until the first swing: track both extremes, to know which way it goes. The
                // drive's start is not a turning point (a record may start mid-swing): the
                // first swing counted is the one after the first turn.
                low = low.min(v);
                high = high.max(v);
                if v - low >= swing {
                    rising = Some(true);
                    (extreme, at) = (v, k);
                } else if high - v >= swing {
                    rising = Some(false);
                    (extreme, at) = (v, k);
                }
            }
            Some(up) => {
                if (up && v > extreme) || (!up && v < extreme) {
                    (extreme, at) = (v, k);
                } else if (extreme - v).abs() >= swing {
                    // The drive has come back a swing from its extremum: that was a turn, and
                    // the swing since the turn before it is half a cycle.
                    if let Some(j) = last_turn {
                        // Times so close that the rate is not a finite number (a hostile time
                        // axis) say nothing.
                        let hz = 0.5 / (t[at] - t[j]);
                        if hz.is_finite() && hz > 0.0 {
                            fastest = Some(fastest.map_or(hz, |f| f.max(hz)));
                        }
                    }
                    last_turn = Some(at);
                    rising = Some(!up);
                    (extreme, at) = (v, k);
                }
            }
        }
    }
    fastest
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::excitation::Excitation;

    fn sampled(rate: f64, seconds: f64, f: impl Fn(f64) -> f64) -> (Vec<f64>, Vec<f64>) {
        let t: Vec<f64> = (0..=(seconds * rate) as usize)
            .map(|k| k as f64 / rate)
            .collect();
        let u = t.iter().map(|&t| f(t)).collect();
        (t, u)
    }

    #[test]
    fn a_sine_reads_at_its_frequency_and_its_swings_must_pass_the_least_swing() {
        for hz in [2.0, 13.0, 50.0, 180.0] {
            let (t, u) = sampled(20_000.0, 2.0, |t| (std::f64::consts::TAU * hz * t).sin());
            let got = fastest_motion_hz(&t, &u).unwrap();
            assert!(got >= hz / 1.02 && got <= hz * 1.02, "{hz} Hz read {got}");
        }
        // A slow full-span sine with a fast one on top whose swings, 0.16 / 2.16 of the
        // span, are below the least swing: the slow one's rate.
        let (t, u) = sampled(20_000.0, 2.0, |t| {
            let w = std::f64::consts::TAU;
            (w * 3.0 * t).sin() + 0.08 * (w * 300.0 * t).sin()
        });
        let got = fastest_motion_hz(&t, &u).unwrap();
        assert!(got < 4.0, "{got}");
        // Swings of 3 / 5 of the span count.
        let (t, u) = sampled(20_000.0, 2.0, |t| {
            let w = std::f64::consts::TAU;
            (w * 3.0 * t).sin() + 1.5 * (w * 300.0 * t).sin()
        });
        let got = fastest_motion_hz(&t, &u).unwrap();
        assert!((240.0..375.0).contains(&got), "{got}");
    }

    #[test]
    fn a_triangle_reads_as_its_fundamental_not_its_harmonics() {
        let (t, u) = sampled(10_000.0, 2.0, |t| {
            let phase = (10.0 * t).fract();
            1.0 - (2.0 * phase - 1.0).abs()
        });
        let got = fastest_motion_hz(&t, &u).unwrap();
        assert!((8.0..12.5).contains(&got), "{got}");
    }

    #[test]
    fn calibrates_excitation_reads_near_its_fastest_motion_and_never_falls_short_of_it() {
        let read = |e: &Excitation, rate: f64| {
            let t: Vec<f64> = (0..(e.duration_s() * rate) as usize)
                .map(|k| k as f64 / rate)
                .collect();
            let u: Vec<f64> = t.iter().map(|&t| e.at(t)).collect();
            fastest_motion_hz(&t, &u).unwrap()
        };
        // The default excitation: its nested loops sweep fifths of the span in about 13 ms,
        // its multisine and full cycles are slower.
        let default = read(&Excitation::DEFAULT, 20_000.0);
        assert!((30.0..45.0).contains(&default), "{default}");
        // With a sweep: its top tapers, so the record reads below the rate named (or at the
        // nested loops' rate, for a sweep slower than them), but never an octave below, over
        // the sweep ranges calibrate takes (up to 1 000 × 10 Hz).
        for named in [20.0, 200.0, 2_000.0, 10_000.0] {
            let swept = read(&Excitation::DEFAULT.reaching(named), 40.0 * named);
            assert!(swept <= named.max(default) * 1.01, "{named}: {swept}");
            assert!(swept >= 0.57 * named, "{named}: {swept}");
            assert!(!falls_short(Some(swept), named), "{named}: {swept}");
        }
        // The default excitation falls short of 200 Hz, not of 50.
        assert!(falls_short(Some(default), 200.0));
        assert!(!falls_short(Some(default), 50.0));
    }

    proptest::proptest! {
        /// Any record, however hostile (values of any size or none at all, times that jump,
        /// repeat or go back): an answer or `None`, never a panic; an answer is positive and
        /// finite.
        #[test]
        fn any_record_gives_a_finite_rate_or_none(
            t in proptest::collection::vec(proptest::num::f64::ANY, 0..200),
            u in proptest::collection::vec(proptest::num::f64::ANY, 0..200),
            sorted in proptest::bool::ANY,
        ) {
            let mut t = t;
            if sorted {
                t.sort_by(f64::total_cmp);
            }
            if let Some(hz) = fastest_motion_hz(&t, &u) {
                proptest::prop_assert!(hz.is_finite() && hz > 0.0, "{hz}");
            }
            let n = t.len().min(u.len());
            proptest::prop_assert_eq!(fastest_motion_in(&t, &u, 0..n), fastest_motion_hz(&t, &u));
            proptest::prop_assert_eq!(fastest_motion_in(&t, &u, 0..n + 1), None);
        }
    }

    #[test]
    fn the_motion_is_said_and_advice_given_only_an_octave_short() {
        assert!(seen(Some(0.52)).ends_with("about 0.5 Hz"));
        assert!(seen(None).contains("never swings"));
        assert_eq!(advice(Some(12.0), 24.0), None);
        let a = advice(Some(0.5), 200.0).unwrap();
        assert!(
            a.starts_with("the model has seen motion up to about 0.5 Hz and you will run 200 Hz")
                && a.contains("calibrate --fastest-hz 200"),
            "{a}"
        );
        assert!(advice(None, 5.0)
            .unwrap()
            .starts_with("the model has seen no swing"));
    }

    #[test]
    fn records_it_cannot_read_are_none() {
        let rate = 10_000.0;
        let (t, u) = sampled(rate, 1.0, |t| (std::f64::consts::TAU * 5.0 * t).sin());
        assert_eq!(fastest_motion_hz(&t[..1], &u[..1]), None);
        // Still.
        assert_eq!(fastest_motion_hz(&t, &vec![1.0; t.len()]), None);
        // Not finite.
        let mut bad = u.clone();
        bad[10] = f64::NAN;
        assert_eq!(fastest_motion_hz(&t, &bad), None);
        // A time axis that does not rise.
        assert_eq!(fastest_motion_hz(&vec![0.0; t.len()], &u), None);
        // Not a whole swing after the first turning point.
        assert_eq!(fastest_motion_hz(&t[..60], &u[..60]), None);
        // A time axis that goes back.
        let mut back = t.clone();
        back[100] = back[98];
        assert_eq!(fastest_motion_hz(&back, &u), None);
        // Times so close that no rate is finite: none.
        let u4 = [0.0, 1.0, 0.0, 1.0];
        assert_eq!(fastest_motion_hz(&[0.0, 1e-320, 2e-320, 3e-320], &u4), None);
        // Mismatched lengths read the common part.
        assert!(fastest_motion_hz(&t, &u[..5_000]).is_some());
    }
}
