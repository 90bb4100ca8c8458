//! Simulated seconds per wall-clock second at a 50 kHz control rate.
//!
//! `cargo run --release -p hal-sim --example plant_speed [simulated_seconds]`
//!
//! Drives the paper's differential experiment (ū = 70 V, v = 70 sin(2π·750 t) V) open loop
//! through: the coupled plant alone (Duhem, then P–I truth hysteresis, then the reduced
//! model), and the whole emulated board (DAC → amplifiers → coupled plant → sensor → ADC)
//! with the internal converters and with the external SPI converters (library drivers on the
//! wire-level chip emulators). One core, no threads.

use hal_sim::plant::{Configuration, HysteresisModel, Mechanics, Plant, PlantConfig};
use hal_sim::sim_board::{BoardConfig, ExternalBoard, InternalBoard};
use std::hint::black_box;
use std::time::Instant;
use twinstack::board::{DacCode, DualDac, SensorAdc};

const RATE_HZ: f64 = 50_000.0;

fn drive(k: u64) -> (f64, f64) {
    let v = 70.0 * (core::f64::consts::TAU * 750.0 * k as f64 / RATE_HZ).sin();
    (70.0 + v, 70.0 - v)
}

fn report(name: &str, periods: u64, run: impl FnOnce()) {
    let start = Instant::now();
    run();
    let wall = start.elapsed().as_secs_f64();
    let simulated = periods as f64 / RATE_HZ;
    println!(
        "{name:<44} {:>9.1} ns/period  {:>8.0} × real time",
        wall / periods as f64 * 1e9,
        simulated / wall
    );
}

fn plant(config: &PlantConfig, periods: u64) {
    let mut p = match Plant::new(config) {
        Ok(p) => p,
        Err(e) => {
            eprintln!("plant: {e}");
            std::process::exit(1);
        }
    };
    for k in 0..periods {
        let (ul, ur) = drive(k);
        black_box(p.step(ul, ur));
    }
}

fn board<B: DualDac + SensorAdc>(board: &mut B, periods: u64) {
    let fs = board_full_scale(board);
    for k in 0..periods {
        let (ul, ur) = drive(k);
        let _ = black_box(board.read().is_ok());
        let code = |u: f64| DacCode((u / 150.0 * fs).round() as u16);
        if board.write_both(code(ul), code(ur)).is_err() {
            eprintln!("DAC write failed at period {k}");
            std::process::exit(1);
        }
    }
}

fn board_full_scale<B: DualDac>(b: &B) -> f64 {
    b.full_scale().0 as f64
}

fn main() {
    let seconds: f64 = match std::env::args().nth(1).map(|s| s.parse::<f64>()) {
        None => 10.0,
        Some(Ok(s)) if s.is_finite() && s > 0.0 => s,
        Some(_) => {
            eprintln!("usage: plant_speed [simulated_seconds > 0]");
            std::process::exit(2);
        }
    };
    let periods = (seconds * RATE_HZ) as u64;
    println!(
        "{seconds} simulated seconds at 50 kHz ({periods} periods), differential, 750 Hz drive"
    );

    let duhem = PlantConfig::paper(Configuration::Differential);
    report("coupled plant, Duhem truth", periods, || {
        plant(&duhem, periods)
    });
    let mut pi = duhem.clone();
    pi.left.model = HysteresisModel::default_pi();
    pi.right.model = HysteresisModel::default_pi();
    report("coupled plant, P–I truth (9 operators)", periods, || {
        plant(&pi, periods)
    });
    let mut reduced = duhem.clone();
    reduced.mechanics = Mechanics::Reduced;
    report("reduced plant, Duhem truth", periods, || {
        plant(&reduced, periods)
    });

    let config = BoardConfig::paper(Configuration::Differential);
    let (mut internal, mut external) = match (
        InternalBoard::internal(&config),
        ExternalBoard::external(&config),
    ) {
        (Ok(i), Ok(e)) => (i, e),
        (Err(e), _) | (_, Err(e)) => {
            eprintln!("board: {e}");
            std::process::exit(1);
        }
    };
    report("board, internal 12-bit DAC/ADC, coupled", periods, || {
        board(&mut internal, periods)
    });
    report(
        "board, SPI DAC8562 + ADS8689 emulated, coupled",
        periods,
        || board(&mut external, periods),
    );
}
