//! Linear least squares, plain and with non-negativity constraints (Lawson–Hanson NNLS).
//!
//! Rows are accumulated into the normal equations `G = AᵀWA`, `b = AᵀWy` (so a fit over tens of
//! thousands of samples needs only `n × n` memory), columns are scaled to unit norm before
//! solving, and each sub-problem is solved by Cholesky with a tiny ridge so that collinear or
//! idle columns (a play operator that never moves) cannot make it fail.
//!
//! The non-negative solver is Lawson and Hanson's active-set method ("Solving Least Squares
//! Problems", 1974, ch. 23), run on the normal equations, with an optional set of *free*
//! variables (an offset, say) that are never constrained.

/// Why a least-squares problem could not be solved.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum LeastSquaresError {
    /// No rows were added, or every row had zero weight.
    #[error("no data rows to fit")]
    NoRows,
    /// A row or target value was NaN or infinite.
    #[error("a regressor or target is not finite")]
    NotFinite,
    /// The active-set iteration did not converge within its bound.
    #[error("non-negative least squares did not converge")]
    NotConverged,
}

/// Normal equations of a weighted linear least-squares problem `min Σ w_k (a_kᵀθ − y_k)²`.
#[derive(Clone, Debug)]
pub struct NormalEquations {
    n: usize,
    gram: Vec<f64>,
    rhs: Vec<f64>,
    yy: f64,
    rows: usize,
    finite: bool,
}

/// Relative ridge added to the (unit) diagonal of every sub-problem.
const RIDGE: f64 = 1e-12;

impl NormalEquations {
    /// An empty problem with `n` unknowns.
    pub fn new(n: usize) -> Self {
        Self {
            n,
            gram: vec![0.0; n * n],
            rhs: vec![0.0; n],
            yy: 0.0,
            rows: 0,
            finite: true,
        }
    }

    /// Number of unknowns.
    pub fn unknowns(&self) -> usize {
        self.n
    }

    /// Adds the row `a` (length `n`) with target `y` and weight `weight ≥ 0`.
    pub fn add_row(&mut self, a: &[f64], y: f64, weight: f64) {
        debug_assert_eq!(a.len(), self.n);
        if weight <= 0.0 {
            return;
        }
        if !(y.is_finite() && a.iter().all(|v| v.is_finite())) {
            self.finite = false;
            return;
        }
        for i in 0..self.n {
            let wa = weight * a[i];
            if wa == 0.0 {
                continue;
            }
            self.rhs[i] += wa * y;
            let row = &mut self.gram[i * self.n..(i + 1) * self.n];
            for (g, &aj) in row[i..].iter_mut().zip(&a[i..]) {
                *g += wa * aj;
            }
        }
        self.yy += weight * y * y;
        self.rows += 1;
    }

    fn g(&self, i: usize, j: usize) -> f64 {
        let (i, j) = if i <= j { (i, j) } else { (j, i) };
        self.gram[i * self.n + j]
    }

    /// Weighted residual sum of squares of the solution `theta`.
    pub fn residual_sum_of_squares(&self, theta: &[f64]) -> f64 {
        let mut r = self.yy;
        for i in 0..self.n {
            r -= 2.0 * theta[i] * self.rhs[i];
            for j in 0..self.n {
                r += theta[i] * self.g(i, j) * theta[j];
            }
        }
        r.max(0.0)
    }

    /// The unconstrained least-squares solution.
    pub fn solve(&self) -> Result<Vec<f64>, LeastSquaresError> {
        self.solve_constrained(&vec![false; self.n])
    }

    /// The least-squares solution with `θ_i ≥ 0` for every `i` where `non_negative[i]`;
    /// the other unknowns are free. Columns that are identically zero get `θ_i = 0`.
    pub fn solve_constrained(&self, non_negative: &[bool]) -> Result<Vec<f64>, LeastSquaresError> {
        if !self.finite {
            return Err(LeastSquaresError::NotFinite);
        }
        if self.rows == 0 {
            return Err(LeastSquaresError::NoRows);
        }
        let n = self.n;
        // Unit-norm column scaling: θ_i = s_i θ'_i with s_i = 1/√G_ii.
        let scale: Vec<f64> = (0..n)
            .map(|i| {
                let d = self.g(i, i);
                if d > 0.0 {
                    1.0 / d.sqrt()
                } else {
                    0.0
                }
            })
            .collect();
        let usable: Vec<bool> = scale.iter().map(|&s| s > 0.0).collect();
        let gs = |i: usize, j: usize| self.g(i, j) * scale[i] * scale[j];
        let bs: Vec<f64> = (0..n).map(|i| self.rhs[i] * scale[i]).collect();

        let solve_on = |passive: &[bool]| -> Vec<f64> {
            let idx: Vec<usize> = (0..n).filter(|&i| passive[i]).collect();
            let m = idx.len();
            let mut a = vec![0.0; m * m];
            let mut b = vec![0.0; m];
            for (p, &i) in idx.iter().enumerate() {
                b[p] = bs[i];
                for (q, &j) in idx.iter().enumerate() {
                    a[p * m + q] = gs(i, j) + if p == q { RIDGE } else { 0.0 };
                }
            }
            let z = cholesky_solve(&mut a, &mut b, m);
            let mut out = vec![0.0; n];
            for (p, &i) in idx.iter().enumerate() {
                out[i] = z[p];
            }
            out
        };

        // Free (and usable) variables start passive; constrained ones start at zero.
        let mut passive: Vec<bool> = (0..n).map(|i| usable[i] && !non_negative[i]).collect();
        let mut x = solve_on(&passive);
        let constrained: Vec<bool> = (0..n).map(|i| usable[i] && non_negative[i]).collect();
        let tol = 1e-12;
        let mut outer = 0;
        loop {
            outer += 1;
            if outer > 3 * n + 10 {
                return Err(LeastSquaresError::NotConverged);
            }
            // Gradient of ½‖b − Gx‖ direction: w = b − G x.
            let w: Vec<f64> = (0..n)
                .map(|i| bs[i] - (0..n).map(|j| gs(i, j) * x[j]).sum::<f64>())
                .collect();
            let candidate = (0..n)
                .filter(|&i| constrained[i] && !passive[i] && w[i] > tol)
                .max_by(|&a, &b| w[a].total_cmp(&w[b]));
            let Some(j) = candidate else { break };
            passive[j] = true;
            let mut inner = 0;
            loop {
                inner += 1;
                if inner > 3 * n + 10 {
                    return Err(LeastSquaresError::NotConverged);
                }
                let z = solve_on(&passive);
                let infeasible: Vec<usize> = (0..n)
                    .filter(|&i| passive[i] && constrained[i] && z[i] <= 0.0)
                    .collect();
                if infeasible.is_empty() {
                    x = z;
                    break;
                }
                let alpha = infeasible
                    .iter()
                    .map(|&i| x[i] / (x[i] - z[i]))
                    .fold(f64::INFINITY, f64::min);
                for i in 0..n {
                    x[i] += alpha * (z[i] - x[i]);
                }
                for i in 0..n {
                    if passive[i] && constrained[i] && x[i] <= tol {
                        passive[i] = false;
                        x[i] = 0.0;
                    }
                }
            }
        }
        Ok((0..n).map(|i| x[i] * scale[i]).collect())
    }
}

/// Solves `A z = b` for symmetric positive-definite `A` (row-major `m × m`, overwritten).
/// A non-positive pivot (numerically singular) gets its unknown set to zero.
fn cholesky_solve(a: &mut [f64], b: &mut [f64], m: usize) -> Vec<f64> {
    // In-place lower Cholesky factor.
    let mut ok = vec![true; m];
    for j in 0..m {
        let mut d = a[j * m + j];
        for k in 0..j {
            d -= a[j * m + k] * a[j * m + k];
        }
        if d <= 0.0 {
            ok[j] = false;
            a[j * m + j] = 1.0;
            for i in (j + 1)..m {
                a[i * m + j] = 0.0;
            }
            continue;
        }
        let d = d.sqrt();
        a[j * m + j] = d;
        for i in (j + 1)..m {
            let mut s = a[i * m + j];
            for k in 0..j {
                s -= a[i * m + k] * a[j * m + k];
            }
            a[i * m + j] = s / d;
        }
    }
    // Forward then back substitution.
    for i in 0..m {
        let mut s = if ok[i] { b[i] } else { 0.0 };
        for k in 0..i {
            s -= a[i * m + k] * b[k];
        }
        b[i] = if ok[i] { s / a[i * m + i] } else { 0.0 };
    }
    for i in (0..m).rev() {
        let mut s = if ok[i] { b[i] } else { 0.0 };
        for k in (i + 1)..m {
            s -= a[k * m + i] * b[k];
        }
        b[i] = if ok[i] { s / a[i * m + i] } else { 0.0 };
    }
    b.to_vec()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn problem(rows: &[(Vec<f64>, f64)]) -> NormalEquations {
        let mut ne = NormalEquations::new(rows[0].0.len());
        for (a, y) in rows {
            ne.add_row(a, *y, 1.0);
        }
        ne
    }

    #[test]
    fn unconstrained_solution_recovers_an_exact_linear_model() {
        let rows: Vec<_> = (0..20)
            .map(|k| {
                let t = k as f64 * 0.1;
                (vec![1.0, t, t * t], 2.0 - 3.0 * t + 0.5 * t * t)
            })
            .collect();
        let th = problem(&rows).solve().unwrap();
        for (got, want) in th.iter().zip([2.0, -3.0, 0.5]) {
            assert!((got - want).abs() < 1e-6, "{th:?}");
        }
    }

    #[test]
    fn a_negative_unconstrained_weight_is_pinned_at_zero_and_the_rest_refitted() {
        // y = 1·a − 0.5·b exactly; with b ≥ 0 the best is b = 0 and a refitted.
        let rows: Vec<_> = (0..30)
            .map(|k| {
                let a = (k as f64 * 0.7).sin();
                let b = 0.3 * a + (k as f64 * 1.3).cos();
                (vec![a, b], a - 0.5 * b)
            })
            .collect();
        let ne = problem(&rows);
        let th = ne.solve_constrained(&[true, true]).unwrap();
        assert_eq!(th[1], 0.0);
        assert!(th[0] > 0.0);
        // Optimal on the remaining column: a·y / a·a.
        let (ay, aa) = rows
            .iter()
            .fold((0.0, 0.0), |(s, q), (r, y)| (s + r[0] * y, q + r[0] * r[0]));
        assert!((th[0] - ay / aa).abs() < 1e-9);
        // A free variable may go negative.
        let th = ne.solve_constrained(&[true, false]).unwrap();
        assert!((th[1] + 0.5).abs() < 1e-9, "{th:?}");
    }

    #[test]
    fn an_idle_column_gets_zero_weight_instead_of_failing() {
        let rows: Vec<_> = (0..10)
            .map(|k| (vec![k as f64, 0.0], 2.0 * k as f64))
            .collect();
        let th = problem(&rows).solve_constrained(&[true, true]).unwrap();
        assert!((th[0] - 2.0).abs() < 1e-9);
        assert_eq!(th[1], 0.0);
    }

    #[test]
    fn empty_or_non_finite_problems_are_refused() {
        assert_eq!(
            NormalEquations::new(2).solve(),
            Err(LeastSquaresError::NoRows)
        );
        let mut ne = NormalEquations::new(1);
        ne.add_row(&[f64::NAN], 1.0, 1.0);
        assert_eq!(ne.solve(), Err(LeastSquaresError::NotFinite));
    }

    proptest! {
        /// NNLS optimality (KKT): θ ≥ 0, and no single coordinate can be moved to lower the
        /// residual — so it is never worse than the best non-negative single-column fit.
        #[test]
        fn nnls_solution_is_feasible_and_beats_every_single_column(
            seed in proptest::collection::vec(-1.0f64..1.0, 40),
            target in proptest::collection::vec(-1.0f64..1.0, 10),
        ) {
            let rows: Vec<_> = (0..10).map(|k| (seed[4 * k..4 * k + 4].to_vec(), target[k])).collect();
            let ne = problem(&rows);
            let th = ne.solve_constrained(&[true; 4]).unwrap();
            prop_assert!(th.iter().all(|&v| v >= 0.0));
            let best = ne.residual_sum_of_squares(&th);
            for c in 0..4 {
                let (ay, aa) = rows.iter().fold((0.0, 0.0), |(s, q), (r, y)| (s + r[c] * y, q + r[c] * r[c]));
                let mut single = vec![0.0; 4];
                single[c] = if aa > 0.0 { (ay / aa).max(0.0) } else { 0.0 };
                prop_assert!(best <= ne.residual_sum_of_squares(&single) + 1e-9);
            }
        }
    }
}
