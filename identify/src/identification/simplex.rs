//! Derivative-free minimisation by the Nelder–Mead simplex method (standard coefficients:
//! reflection 1, expansion 2, contraction ½, shrink ½), with a bounded number of evaluations.
//! Used where the cost is a simulation (the Duhem output error), which has no handy gradient.

/// Minimises `cost` from `start`, with initial simplex steps `steps`, using at most
/// `max_evaluations` evaluations; stops early when the costs across the simplex differ by
/// less than `tolerance` (relative). Non-finite costs are treated as +∞.
pub fn minimise<const N: usize>(
    cost: impl Fn(&[f64; N]) -> f64,
    start: [f64; N],
    steps: [f64; N],
    max_evaluations: usize,
    tolerance: f64,
) -> [f64; N] {
    let f = |x: &[f64; N]| {
        let c = cost(x);
        if c.is_finite() {
            c
        } else {
            f64::INFINITY
        }
    };
    let mut points: Vec<([f64; N], f64)> = Vec::with_capacity(N + 1);
    points.push((start, f(&start)));
    for i in 0..N {
        let mut p = start;
        p[i] += steps[i];
        points.push((p, f(&p)));
    }
    let mut evaluations = N + 1;
    let along = |from: &[f64; N], to: &[f64; N], t: f64| -> [f64; N] {
        let mut out = [0.0; N];
        for i in 0..N {
            out[i] = from[i] + t * (to[i] - from[i]);
        }
        out
    };
    while evaluations < max_evaluations {
        points.sort_by(|a, b| a.1.total_cmp(&b.1));
        let (best, worst) = (points[0].1, points[N].1);
        if worst.is_finite() && (worst - best).abs() <= tolerance * (best.abs() + tolerance) {
            break;
        }
        let mut centroid = [0.0; N];
        for (p, _) in &points[..N] {
            for i in 0..N {
                centroid[i] += p[i] / N as f64;
            }
        }
        let worst_point = points[N].0;
        let reflected = along(&centroid, &worst_point, -1.0);
        let fr = f(&reflected);
        evaluations += 1;
        if fr < points[0].1 {
            let expanded = along(&centroid, &worst_point, -2.0);
            let fe = f(&expanded);
            evaluations += 1;
            points[N] = if fe < fr {
                (expanded, fe)
            } else {
                (reflected, fr)
            };
        } else if fr < points[N - 1].1 {
            points[N] = (reflected, fr);
        } else {
            let contracted = if fr < points[N].1 {
                along(&centroid, &reflected, 0.5)
            } else {
                along(&centroid, &worst_point, 0.5)
            };
            let fc = f(&contracted);
            evaluations += 1;
            if fc < points[N].1.min(fr) {
                points[N] = (contracted, fc);
            } else {
                let best_point = points[0].0;
                for p in points.iter_mut().skip(1) {
                    let q = along(&best_point, &p.0, 0.5);
                    *p = (q, f(&q));
                    evaluations += 1;
                }
            }
        }
    }
    points.sort_by(|a, b| a.1.total_cmp(&b.1));
    points[0].0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_the_minimum_of_a_shifted_quadratic_valley() {
        let x = minimise(
            |v: &[f64; 2]| (v[0] - 3.0).powi(2) + 10.0 * (v[1] + 1.0).powi(2),
            [0.0, 0.0],
            [1.0, 1.0],
            2000,
            1e-14,
        );
        assert!(
            (x[0] - 3.0).abs() < 1e-4 && (x[1] + 1.0).abs() < 1e-4,
            "{x:?}"
        );
    }

    #[test]
    fn never_returns_a_point_worse_than_the_start_even_with_infinite_costs() {
        let cost = |v: &[f64; 1]| {
            if v[0] > 0.5 {
                f64::NAN
            } else {
                (v[0] - 0.4).abs()
            }
        };
        let x = minimise(cost, [0.0], [1.0], 200, 1e-12);
        assert!(cost(&x) <= cost(&[0.0]));
    }
}
