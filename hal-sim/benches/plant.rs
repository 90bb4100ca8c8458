//! Criterion benchmarks of one 50 kHz control period: the coupled plant alone, and the whole
//! emulated board with internal and with external SPI converters.
//!
//! `cargo bench -p hal-sim --bench plant`. At 50 kHz a period is 20 µs of simulated time, so
//! `20 µs / (time per iteration)` is the real-time factor.

use criterion::{criterion_group, criterion_main, Criterion};
use hal_sim::plant::{Configuration, Plant, PlantConfig};
use hal_sim::sim_board::{BoardConfig, ExternalBoard, InternalBoard};
use std::hint::black_box;
use twinstack::board::{DacCode, DualDac, SensorAdc};

fn periods(c: &mut Criterion) {
    let mut plant = Plant::new(&PlantConfig::paper(Configuration::Differential)).unwrap();
    let mut k = 0u32;
    c.bench_function("coupled plant step (Duhem truth)", |b| {
        b.iter(|| {
            k = k.wrapping_add(1);
            let v = 70.0 * (k as f64 * 0.0942).sin();
            black_box(plant.step(black_box(70.0 + v), black_box(70.0 - v)))
        })
    });

    let config = BoardConfig::paper(Configuration::Differential);
    let mut internal = InternalBoard::internal(&config).unwrap();
    let mut external = ExternalBoard::external(&config).unwrap();
    let mut n = 0u16;
    c.bench_function("board period, internal converters", |b| {
        b.iter(|| {
            n = (n + 1) % 2048;
            black_box(internal.read().unwrap());
            internal
                .write_both(DacCode(1000 + n), DacCode(3000 - n))
                .unwrap();
        })
    });
    c.bench_function("board period, SPI converters", |b| {
        b.iter(|| {
            n = (n + 1) % 2048;
            black_box(external.read().unwrap());
            external
                .write_both(DacCode(20_000 + n), DacCode(40_000 - n))
                .unwrap();
        })
    });
}

criterion_group!(benches, periods);
criterion_main!(benches);
