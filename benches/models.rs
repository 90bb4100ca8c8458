//! Host benchmarks: one step of each model at N = 8, 16, 32 operators, and one control tick.
//!
//! Run: `cargo bench --bench models`. These are host (x86) figures; the target's cost is
//! counted in instructions in the emulator (see the README).

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use std::hint::black_box;
use twinstack::fixed_point::signal_from_f64 as q;
use twinstack::models::duhem::{Duhem, InverseDuhem};
use twinstack::models::prandtl_ishlinskii::{InversePrandtlIshlinskii, PrandtlIshlinskii};
use twinstack::{DuhemParams, PiParams, Scaling, Thresholds};

fn pi_params(n: usize) -> (PiParams, Scaling) {
    let r = Thresholds::Uniform.generate(n, 150.0).unwrap();
    let w: Vec<f64> = (0..n).map(|i| 0.1 / (1.0 + i as f64)).collect();
    let reach: f64 = w.iter().sum::<f64>() * 150.0;
    (
        PiParams::new(0.0, 0.0, &r, &w).unwrap(),
        Scaling::new(0.0, 150.0, -reach, reach).unwrap(),
    )
}

/// A slow sine in normalised units: 1000 samples per cycle, so every operator moves.
fn inputs() -> Vec<i32> {
    (0..1000)
        .map(|k| q(0.95 * (k as f64 * core::f64::consts::TAU / 1000.0).sin()))
        .collect()
}

fn prandtl_ishlinskii(c: &mut Criterion) {
    let u = inputs();
    let mut group = c.benchmark_group("pi_step");
    for n in [8, 16, 32] {
        let (p, s) = pi_params(n);
        let fwd = PrandtlIshlinskii::new(&p, &s).unwrap();
        let inv = InversePrandtlIshlinskii::new(&p, &s).unwrap();
        group.bench_with_input(BenchmarkId::new("forward", n), &n, |b, _| {
            let mut st = fwd.state_at_rest(0);
            let mut k = 0;
            b.iter(|| {
                k = (k + 1) % u.len();
                black_box(fwd.step(&mut st, black_box(u[k])))
            })
        });
        group.bench_with_input(BenchmarkId::new("inverse", n), &n, |b, _| {
            let mut st = inv.state_at_rest(0);
            let mut k = 0;
            b.iter(|| {
                k = (k + 1) % u.len();
                black_box(inv.step(&mut st, black_box(u[k] / 4)))
            })
        });
    }
    group.finish();
}

fn duhem(c: &mut Criterion) {
    let u = inputs();
    let p = DuhemParams {
        alpha: 0.02,
        beta: 0.1,
        gamma: 0.08,
        offset: 0.0,
    };
    let s = Scaling::new(0.0, 150.0, -2.0, 18.0).unwrap();
    let fwd = Duhem::new(&p, &s).unwrap();
    let inv = InverseDuhem::new(&p, &s).unwrap();
    let mut group = c.benchmark_group("duhem_step");
    group.bench_function("forward", |b| {
        let mut st = fwd.state_at(0, fwd.anhysteretic(0));
        let mut k = 0;
        b.iter(|| {
            k = (k + 1) % u.len();
            black_box(fwd.step(&mut st, black_box(u[k])))
        })
    });
    group.bench_function("inverse", |b| {
        let mut st = inv.model().state_at(0, fwd.anhysteretic(0));
        let mut k = 0;
        b.iter(|| {
            k = (k + 1) % u.len();
            black_box(inv.step(&mut st, black_box(u[k] / 2)))
        })
    });
    group.finish();
}

criterion_group!(benches, prandtl_ishlinskii, duhem);
criterion_main!(benches);
