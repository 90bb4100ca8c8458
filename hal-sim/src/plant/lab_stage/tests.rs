use super::*;

fn preisach() -> Preisach {
    Preisach::new(&PreisachDensity::default())
}

/// The Everett function against a brute-force integral of the cell densities.
#[test]
fn everett_function_matches_a_fine_numerical_integral() {
    let p = Preisach::new(&PreisachDensity {
        levels: 7,
        ..PreisachDensity::default()
    });
    let n = p.n as f64;
    let brute = |a: f64, b: f64| {
        let m = 1400;
        let h = 1.0 / m as f64;
        let mut s = 0.0;
        for i in 0..m {
            for j in 0..m {
                let (al, be) = ((i as f64 + 0.5) * h, (j as f64 + 0.5) * h);
                if be > al || al > a || be < b {
                    continue;
                }
                let (ci, cj) = ((al * n) as usize, (be * n) as usize);
                let area = if ci == cj { 0.5 } else { 1.0 } / (n * n);
                s += p.cell(ci, cj) / area * h * h;
            }
        }
        s
    };
    for (a, b) in [
        (1.0, 0.0),
        (0.73, 0.21),
        (0.5, 0.45),
        (0.31, 0.29),
        (0.9, 0.6),
    ] {
        let e = p.everett(a, b);
        assert!((e - brute(a, b)).abs() < 3e-3, "E({a}, {b}) = {e}");
    }
    assert!((p.everett(1.0, 0.0) - 1.0).abs() < 1e-12);
    assert_eq!(p.everett(0.3, 0.6), 0.0);
}

/// A brute-force relay grid (every relay's state kept) agrees with the memory-based run
/// at the cell boundaries, where the smeared cells and point relays coincide.
#[test]
fn memory_run_equals_a_grid_of_relays_on_grid_points() {
    let mut p = preisach();
    let n = p.n;
    let mut up = vec![false; n * (n + 1) / 2];
    // Inputs on cell boundaries: relay (i, j) switches up when v ≥ (i+1)/n, down when
    // v ≤ j/n.
    let path = [
        40usize, 10, 35, 20, 30, 25, 45, 5, 50, 0, 22, 18, 27, 3, 49, 1,
    ];
    for &level in &path {
        let v = level as f64 / n as f64;
        p.set(v);
        for i in 0..n {
            for j in 0..=i {
                let k = i * (i + 1) / 2 + j;
                if level > i {
                    up[k] = true;
                }
                if level <= j {
                    up[k] = false;
                }
            }
        }
        let grid: f64 = up
            .iter()
            .zip(&p.cells)
            .map(|(&s, &w)| if s { w } else { 0.0 })
            .sum();
        assert!(
            (p.output() - grid).abs() < 1e-12,
            "after {level}: {} vs {grid}",
            p.output()
        );
    }
}

#[test]
fn wiping_out_removes_nested_loops() {
    let mut p = preisach();
    for v in [0.9, 0.2, 0.7, 0.4, 0.6, 0.5] {
        p.set(v);
    }
    assert_eq!(p.memory_len(), 6, "0 and five reversals");
    p.set(0.95);
    assert_eq!(
        p.memory_len(),
        1,
        "above every maximum: only the rest point"
    );
    let at = p.output();
    p.set(0.1);
    p.set(0.95);
    assert!((p.output() - at).abs() < 1e-12, "closed loop returns");
}

#[test]
fn the_density_is_not_a_function_of_alpha_minus_beta() {
    let d = PreisachDensity::default();
    let (low, high) = (d.density(0.3, 0.1), d.density(0.9, 0.7));
    assert!(
        (low - high).abs() > 0.2 * low,
        "same α − β, densities {low} and {high}"
    );
}
