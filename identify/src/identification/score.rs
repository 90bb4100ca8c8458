//! Modelling error figures, as the papers report them: max and RMS of `model − measured`, in
//! % of the measured signal's span over the scored samples.

// Defined with the parameter file that records them (below identification).
pub use crate::param_file::ErrorFigures;

/// Scores `model` against `measured` over the samples `range` (indices into both).
/// `None` if the range is empty or the measured signal is flat there.
pub fn score(
    measured: &[f64],
    model: &[f64],
    range: std::ops::Range<usize>,
) -> Option<ErrorFigures> {
    let m = measured.get(range.clone())?;
    let p = model.get(range)?;
    if m.is_empty() {
        return None;
    }
    let (lo, hi) = m
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    let span = hi - lo;
    if span.is_nan() || span <= 0.0 {
        return None;
    }
    let (mut max, mut sq) = (0.0f64, 0.0);
    for (a, b) in m.iter().zip(p) {
        let e = (b - a).abs();
        max = max.max(e);
        sq += e * e;
    }
    Some(ErrorFigures {
        max_pct: 100.0 * max / span,
        rms_pct: 100.0 * (sq / m.len() as f64).sqrt() / span,
        samples: m.len(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_are_in_percent_of_the_measured_span_over_the_scored_range_only() {
        let measured = [100.0, 0.0, 10.0, 0.0, 10.0];
        let model = [0.0, 1.0, 10.0, 0.0, 9.0];
        let s = score(&measured, &model, 1..5).unwrap();
        assert!((s.max_pct - 10.0).abs() < 1e-12);
        assert!((s.rms_pct - 100.0 * (2.0f64 / 4.0).sqrt() / 10.0).abs() < 1e-12);
        assert_eq!(s.samples, 4);
        assert!(score(&measured, &model, 2..2).is_none());
        assert!(score(&[1.0, 1.0], &[0.0, 0.0], 0..2).is_none());
    }
}
