//! Physics checks of the simulated plant against the paper's identified figures (see the book, docs/src/reference/physics.md),
//! all at the 50 kHz control rate the firmware runs.
//!
//! Resonance and damping are read from the sampled step response: a sampled second-order mode
//! obeys `x_{k+1} = c1 x_k + c2 x_{k−1} + c0` exactly, with `c2 = −r²`, `c1 = 2r cos θ`,
//! `r = e^{−ζωn dt}`, `θ = ωd dt`; a least-squares fit of `c0, c1, c2` over the ringing gives
//! `ωn` and `ζ` even with only 2.3 samples per period of the 21.8 kHz mode.
//!
//! Tolerances: `ωn` within 1 % (the accuracy the model is held to). `a0` and `ζ`: the
//! unidirectional figures are reproduced within 0.5 %; the differential ones within 1.5 %,
//! because the paper's three differential figures are mutually inconsistent by 2.1 % and the
//! derivation splits that between `a0` and `ζ` (see `hal_sim::plant::stage`). A tighter check
//! against the model's own constants (0.2 %) separates integration error from that.

use hal_sim::plant::{
    Configuration, Mechanics, Plant, PlantConfig, SecondOrder, StageParams,
    DEFAULT_CONTACT_STIFFNESS,
};
use proptest::prelude::*;

const BIAS: f64 = 70.0;
const STEP: f64 = 5.0;

fn linear(configuration: Configuration, mechanics: Mechanics, dt: f64) -> Plant {
    let mut cfg = PlantConfig::paper(configuration).without_hysteresis();
    cfg.mechanics = mechanics;
    cfg.dt = dt;
    Plant::new(&cfg).unwrap()
}

fn coupled() -> Mechanics {
    Mechanics::Coupled {
        contact_stiffness: DEFAULT_CONTACT_STIFFNESS,
    }
}

/// Drives `(ū + v, ū − v)` (differential) or `u_l = ū + v` (unidirectional).
fn drive(plant: &mut Plant, v: f64) -> f64 {
    plant.step(BIAS + v, BIAS - v)
}

/// Settles at the bias, then steps `v` by [`STEP`] volts; returns the displacement before the
/// step and the samples after it (40 ms).
fn step_response(plant: &mut Plant) -> (f64, Vec<f64>) {
    let settle = (0.04 / plant.dt()) as usize;
    let mut before = 0.0;
    for _ in 0..settle {
        before = drive(plant, 0.0);
    }
    let after = (0..settle).map(|_| drive(plant, STEP)).collect();
    (before, after)
}

/// Least-squares fit of `x_{k+1} = c1 x_k + c2 x_{k−1} + c0`; returns `(ωn, ζ)`.
fn second_order_from_samples(x: &[f64], dt: f64) -> (f64, f64) {
    let mut ata = [[0.0f64; 3]; 3];
    let mut atb = [0.0f64; 3];
    for k in 1..x.len() - 1 {
        let row = [x[k], x[k - 1], 1.0];
        for i in 0..3 {
            for j in 0..3 {
                ata[i][j] += row[i] * row[j];
            }
            atb[i] += row[i] * x[k + 1];
        }
    }
    let c = solve3(ata, atb);
    let r = (-c[1]).sqrt();
    let theta = (c[0] / (2.0 * r)).acos();
    let sigma = -r.ln() / dt;
    let omega_d = theta / dt;
    let omega_n = (sigma * sigma + omega_d * omega_d).sqrt();
    (omega_n, sigma / omega_n)
}

fn solve3(mut a: [[f64; 3]; 3], mut b: [f64; 3]) -> [f64; 3] {
    for col in 0..3 {
        let pivot = (col..3)
            .max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))
            .unwrap();
        a.swap(col, pivot);
        b.swap(col, pivot);
        for row in col + 1..3 {
            let f = a[row][col] / a[col][col];
            let pivot_row = a[col];
            for (v, p) in a[row].iter_mut().zip(pivot_row.iter()).skip(col) {
                *v -= f * p;
            }
            b[row] -= f * b[col];
        }
    }
    let mut x = [0.0; 3];
    for row in (0..3).rev() {
        let s: f64 = (row + 1..3).map(|k| a[row][k] * x[k]).sum();
        x[row] = (b[row] - s) / a[row][row];
    }
    x
}

struct Measured {
    a0: f64,
    omega_n: f64,
    zeta: f64,
}

fn measure(plant: &mut Plant) -> Measured {
    let dt = plant.dt();
    let (before, after) = step_response(plant);
    let a0 = (after[after.len() - 1] - before) / STEP;
    // The first 3 ms of ringing (≈ 1.3 decay time constants) carry the mode clearly above
    // rounding.
    let n = (3e-3 / dt) as usize;
    let (omega_n, zeta) = second_order_from_samples(&after[..n], dt);
    eprintln!(
        "{:?} dt {dt:e}: a0 {a0:.5} µm/V, ωn {omega_n:.5e} rad/s, ζ {zeta:.5}",
        plant.configuration()
    );
    Measured { a0, omega_n, zeta }
}

fn rel(a: f64, b: f64) -> f64 {
    a / b - 1.0
}

const CONFIGURATIONS: [Configuration; 2] =
    [Configuration::Unidirectional, Configuration::Differential];

fn paper_tolerance(configuration: Configuration) -> f64 {
    match configuration {
        Configuration::Unidirectional => 0.005,
        Configuration::Differential => 0.015,
    }
}

#[test]
fn dc_gain_matches_the_papers_a0_in_both_configurations_and_models() {
    for configuration in CONFIGURATIONS {
        let paper = SecondOrder::paper(configuration);
        let model = StageParams::paper().second_order(configuration);
        for mechanics in [coupled(), Mechanics::Reduced] {
            let m = measure(&mut linear(configuration, mechanics, 2e-5));
            let e = rel(m.a0, paper.a0_um_per_volt);
            assert!(
                e.abs() < paper_tolerance(configuration),
                "{configuration:?} {mechanics:?}: a0 {} vs paper {} ({e:+.4})",
                m.a0,
                paper.a0_um_per_volt
            );
            assert!(rel(m.a0, model.a0_um_per_volt).abs() < 0.002);
        }
    }
}

#[test]
fn resonance_matches_the_papers_omega_n_within_one_percent_at_50_khz() {
    for configuration in CONFIGURATIONS {
        let paper = SecondOrder::paper(configuration);
        for mechanics in [coupled(), Mechanics::Reduced] {
            let m = measure(&mut linear(configuration, mechanics, 2e-5));
            let e = rel(m.omega_n, paper.omega_n);
            assert!(
                e.abs() < 0.01,
                "{configuration:?} {mechanics:?}: ωn {} vs paper {} ({e:+.4})",
                m.omega_n,
                paper.omega_n
            );
        }
    }
}

#[test]
fn step_response_damping_matches_the_papers_zeta() {
    for configuration in CONFIGURATIONS {
        let paper = SecondOrder::paper(configuration);
        let model = StageParams::paper().second_order(configuration);
        for mechanics in [coupled(), Mechanics::Reduced] {
            let m = measure(&mut linear(configuration, mechanics, 2e-5));
            let e = rel(m.zeta, paper.zeta);
            assert!(
                e.abs() < paper_tolerance(configuration),
                "{configuration:?} {mechanics:?}: ζ {} vs paper {} ({e:+.4})",
                m.zeta,
                paper.zeta
            );
            assert!(rel(m.zeta, model.zeta).abs() < 0.002);
        }
    }
}

/// The exact discretisation is exact: 20 periods of 1 µs land on the same samples as one
/// period of 20 µs, through the ringing of the 21.8 kHz mode and the MHz tip modes.
#[test]
fn samples_do_not_depend_on_the_integration_period() {
    for configuration in CONFIGURATIONS {
        let mut slow = linear(configuration, coupled(), 2e-5);
        let mut fast = linear(configuration, coupled(), 1e-6);
        for k in 0..500 {
            let v = if k < 250 { 20.0 } else { -35.0 };
            let xs = drive(&mut slow, v);
            let mut xf = 0.0;
            for _ in 0..20 {
                xf = drive(&mut fast, v);
            }
            assert!(
                (xs - xf).abs() < 1e-9 * (1.0 + xs.abs()),
                "{k}: {xs} vs {xf}"
            );
            let (ts, tf) = (slow.tips_um(), fast.tips_um());
            assert!((ts[0] - tf[0]).abs() < 1e-9 * (1.0 + ts[0].abs()));
        }
    }
}

/// The coupled model approaches its `K_0 → ∞` reduction as the contact stiffens, and is
/// already within 0.1 % of it with the default contact.
#[test]
fn coupled_model_tends_to_its_reduction_as_the_contact_stiffens() {
    for configuration in CONFIGURATIONS {
        let reduced = measure(&mut linear(configuration, Mechanics::Reduced, 2e-5)).omega_n;
        let ki = StageParams::paper().stack_stiffness;
        let gaps: Vec<f64> = [5.0, 20.0, DEFAULT_CONTACT_STIFFNESS / ki]
            .iter()
            .map(|ratio| {
                let mechanics = Mechanics::Coupled {
                    contact_stiffness: ratio * ki,
                };
                rel(
                    measure(&mut linear(configuration, mechanics, 2e-5)).omega_n,
                    reduced,
                )
                .abs()
            })
            .collect();
        assert!(
            gaps[0] > gaps[1] && gaps[1] > gaps[2],
            "{configuration:?}: {gaps:?}"
        );
        assert!(gaps[2] < 1e-3, "{configuration:?}: {gaps:?}");
    }
}

#[test]
fn differential_drive_has_the_higher_gain_and_resonance() {
    let uni = measure(&mut linear(Configuration::Unidirectional, coupled(), 2e-5));
    let diff = measure(&mut linear(Configuration::Differential, coupled(), 2e-5));
    assert!(diff.a0 > 1.2 * uni.a0);
    assert!(diff.omega_n > 1.2 * uni.omega_n);
}

/// Bow of a hysteresis loop: the centre line of the loop (mean of the ascending and descending
/// branches) at the middle of the drive, minus its chord, as a fraction of the output range.
/// A point-symmetric loop has none.
fn loop_bow(plant: &mut Plant, amplitude: f64) -> f64 {
    let n = 5000; // 100 ms per cycle at 50 kHz: a 10 Hz triangle, quasi-static.
    let tri = |k: usize| {
        let p = (k % n) as f64 / n as f64;
        amplitude
            * if p < 0.5 {
                4.0 * p - 1.0
            } else {
                3.0 - 4.0 * p
            }
    };
    let mut x = vec![0.0; 2 * n];
    // Ramp up to −amplitude slowly, then two cycles; keep the second.
    for k in 0..n / 4 {
        drive(plant, -amplitude * k as f64 / (n / 4) as f64);
    }
    for (k, xk) in x.iter_mut().enumerate() {
        *xk = drive(plant, tri(k));
    }
    let cycle = &x[n..];
    // Ascending samples at v = −A, 0, +A are k = 0, n/4, n/2; descending at v = 0 is 3n/4.
    let (lo, hi) = (cycle[0], cycle[n / 2]);
    let mid = 0.5 * (cycle[n / 4] + cycle[3 * n / 4]);
    (mid - 0.5 * (lo + hi)) / (hi - lo)
}

#[test]
fn skewed_stacks_bend_the_unidirectional_loop_but_not_the_differential_one() {
    let uni = loop_bow(
        &mut Plant::new(&PlantConfig::paper(Configuration::Unidirectional)).unwrap(),
        BIAS,
    );
    let diff = loop_bow(
        &mut Plant::new(&PlantConfig::paper(Configuration::Differential)).unwrap(),
        BIAS,
    );
    eprintln!("loop bow: unidirectional {uni:+.4}, differential {diff:+.4}");
    assert!(uni.abs() > 0.02, "unidirectional bow {uni}");
    assert!(
        diff.abs() < 0.2 * uni.abs(),
        "differential bow {diff} vs {uni}"
    );
    // And without skew neither loop is bent.
    let mut cfg = PlantConfig::paper(Configuration::Unidirectional);
    cfg.left.skew = 0.0;
    let straight = loop_bow(&mut Plant::new(&cfg).unwrap(), BIAS);
    assert!(straight.abs() < 0.2 * uni.abs(), "unskewed bow {straight}");
}

/// At rest the charges follow `Q_l = C e_l + T x_l`, `Q_r = C e_r − T x_r` with the tips where
/// the static equations of the book's docs/src/reference/physics.md put them (solved here independently of the simulator).
#[test]
fn charges_at_rest_follow_the_constitutive_equations() {
    let s = StageParams::paper();
    let k0 = DEFAULT_CONTACT_STIFFNESS;
    let ki = s.stack_stiffness * k0 / (k0 - s.stack_stiffness);
    let t = s.force_factor * (ki + k0) / k0;
    let (ul, ur) = (100.0, 40.0);
    let mut plant = linear(Configuration::Differential, coupled(), 2e-5);
    for _ in 0..4000 {
        plant.step(ul, ur);
    }
    // Static equations: K x = f.
    let k = [
        [ki + k0, -k0, 0.0],
        [-k0, s.stage_stiffness + 2.0 * k0, -k0],
        [0.0, -k0, ki + k0],
    ];
    let x = solve3(k, [t * ul, 0.0, -t * ur]);
    let [xl, xr] = plant.tips_um();
    assert!((xl * 1e-6 / x[0] - 1.0).abs() < 1e-6);
    assert!((xr * 1e-6 / x[2] - 1.0).abs() < 1e-6);
    let [ql, qr] = plant.charges_coulombs();
    assert!((ql / (s.capacitance * ul + t * x[0]) - 1.0).abs() < 1e-6);
    assert!((qr / (s.capacitance * ur - t * x[2]) - 1.0).abs() < 1e-6);
    // Pushing stack: its tip extends and its charge exceeds the clamped C·u.
    assert!(x[0] > 0.0 && ql > s.capacitance * ul);
}

#[test]
fn hysteresis_voltage_is_what_the_stack_loses() {
    let mut plant = Plant::new(&PlantConfig::paper(Configuration::Differential)).unwrap();
    for k in 0..2000 {
        let v = 60.0 * (k as f64 * 0.003).sin();
        plant.step(BIAS + v, BIAS - v);
        let [ul, ur] = plant.drive_volts();
        let [el, er] = plant.effective_volts();
        let [hl, hr] = plant.hysteresis_volts();
        assert_eq!((ul - el, ur - er), (hl, hr));
    }
    // After a rise the ascending branch lags: v^h > 0 on the pushing stack.
    assert!(plant.hysteresis_volts()[0].abs() > 0.1);
}

#[test]
fn invalid_configurations_are_refused_with_their_reason() {
    use hal_sim::plant::{HysteresisError, PlantError, Stack};
    let base = PlantConfig::paper(Configuration::Differential);
    let mut c = base.clone();
    c.dt = 0.0;
    assert_eq!(Plant::new(&c), Err(PlantError::InvalidTimeStep(0.0)));
    let mut c = base.clone();
    c.stage.damping = f64::NAN;
    assert_eq!(Plant::new(&c), Err(PlantError::InvalidStage("damping")));
    let mut c = base.clone();
    c.mechanics = Mechanics::Coupled {
        contact_stiffness: 1e6,
    };
    assert!(matches!(
        Plant::new(&c),
        Err(PlantError::ContactTooSoft { .. })
    ));
    let mut c = base;
    c.right.skew = 1.5;
    assert_eq!(
        Plant::new(&c),
        Err(PlantError::Hysteresis {
            stack: Stack::Right,
            error: HysteresisError::SkewOutOfRange(1.5)
        })
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]

    /// Without hysteresis the plant is linear: the response to the sum of two drive sequences
    /// (about the bias) is the sum of the responses.
    #[test]
    fn linear_plant_obeys_superposition(
        a in proptest::collection::vec(-50.0f64..50.0, 200),
        b in proptest::collection::vec(-50.0f64..50.0, 200),
    ) {
        let run = |f: &dyn Fn(usize) -> f64| {
            let mut p = linear(Configuration::Differential, coupled(), 2e-5);
            (0..200).map(|k| p.step(f(k), -f(k))).collect::<Vec<_>>()
        };
        let xa = run(&|k| a[k]);
        let xb = run(&|k| b[k]);
        let xab = run(&|k| a[k] + b[k]);
        for k in 0..200 {
            prop_assert!((xab[k] - xa[k] - xb[k]).abs() < 1e-9 * (1.0 + xab[k].abs()));
        }
    }

    /// Any drive within the amplifier's range gives a finite displacement inside the BIBO bound
    /// of a lightly damped mode: static stroke × (ℓ1 norm of the impulse response ≈ 0.64/ζ),
    /// bounded here by stroke / ζ. A discretisation that went unstable would leave it.
    #[test]
    fn displacement_stays_finite_and_within_the_bibo_bound(
        drive in proptest::collection::vec((0.0f64..150.0, 0.0f64..150.0), 1..400),
    ) {
        let model = StageParams::paper().second_order(Configuration::Differential);
        // (u_l − u_r) spans ±150 V, i.e. v = ±75 V; the stacks' effective voltage may exceed
        // the drive by a few volts of hysteresis.
        let bound = model.a0_um_per_volt * 80.0 / model.zeta;
        let mut p = Plant::new(&PlantConfig::paper(Configuration::Differential)).unwrap();
        for (ul, ur) in drive {
            let x = p.step(ul, ur);
            prop_assert!(x.is_finite() && x.abs() < bound, "{x} µm");
        }
    }
}
