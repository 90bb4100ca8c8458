//! Rate independence of the compensators as the board runs them: the same trajectory
//! compensated at 10 kHz and at 100 kHz gives the same drive at the instants both rates
//! sample, within one code of the board's DAC, for every model: the P–I and the generalised
//! P–I (their output depends on the order of the input's values only) and Duhem and Bouc–Wen
//! (integrated exactly in the input, [`twinstack::models::relaxation`]; their compensators
//! solve for the step to the rounding).

use twinstack::board::Hardware;
use twinstack::config::settings::{
    representative_bouc_wen, representative_duhem, representative_gpi, representative_pi, Model,
    Settings,
};
use twinstack_identify::stage_model::{Hysteresis, StageModel};

/// The model as the board's parameter file holds it, on the board's default ranges.
fn stage(model: Model) -> StageModel {
    let hysteresis = match model {
        Model::PrandtlIshlinskii(p) => Hysteresis::Pi(p),
        Model::GeneralisedPi(g) => Hysteresis::GeneralisedPi(g),
        Model::Duhem(d) => Hysteresis::Duhem(d),
        Model::BoucWen(b) => Hysteresis::BoucWen(b),
    };
    StageModel {
        hysteresis,
        scaling: Settings::default().ranges,
        output_sign: 1.0,
        sensor_lag_s: 0.0,
        creep: None,
        output_map: None,
    }
}

/// A 500 Hz triangle over 10–90 % of the output range, with shrinking reversals (nested minor
/// loops) after two full cycles, sampled at `rate`; its turning points every millisecond, on
/// both rates' grids.
fn triangle(model: &StageModel, rate: f64) -> (Vec<f64>, Vec<f64>) {
    let (lo, hi) = (model.scaling.output_min, model.scaling.output_max);
    let (a, b) = (lo + 0.1 * (hi - lo), lo + 0.9 * (hi - lo));
    let mid = 0.5 * (a + b);
    let ticks_per_ms = (rate / 1e3).round() as usize;
    let legs = 12;
    let mut t = Vec::new();
    let mut x = Vec::new();
    let mut from = a;
    for leg in 0..legs {
        // Full legs, then each leg's end closer to the middle.
        let shrink = if leg < 4 {
            1.0
        } else {
            0.8f64.powi(leg as i32 - 3)
        };
        let to = if leg % 2 == 0 {
            mid + shrink * (b - mid)
        } else {
            mid - shrink * (mid - a)
        };
        for k in 0..ticks_per_ms {
            let s = k as f64 / ticks_per_ms as f64;
            t.push((leg * ticks_per_ms + k) as f64 / rate);
            x.push(from + s * (to - from));
        }
        from = to;
    }
    (t, x)
}

/// Largest difference of the drive, volts, between the two rates at the slow rate's instants.
fn drive_difference(model: &StageModel) -> f64 {
    let (t_slow, x_slow) = triangle(model, 10_000.0);
    let (t_fast, x_fast) = triangle(model, 100_000.0);
    let slow = model.compensate(&t_slow, &x_slow).unwrap();
    let fast = model.compensate(&t_fast, &x_fast).unwrap();
    slow.iter()
        .enumerate()
        .map(|(i, u)| (u - fast[10 * i]).abs())
        .fold(0.0, f64::max)
}

#[test]
fn every_model_gives_the_same_drive_at_10_and_100_khz() {
    let hw = Hardware::driver_board(100_000.0);
    let code = hw.amplifier_full_scale / f64::from(hw.dac_full_scale);
    for (name, model) in [
        ("P–I 17", representative_pi(17).unwrap()),
        ("P–I 32", representative_pi(32).unwrap()),
        ("generalised P–I 16", representative_gpi(16).unwrap()),
        ("Duhem", representative_duhem()),
        ("Bouc–Wen", representative_bouc_wen()),
    ] {
        let d = drive_difference(&stage(model));
        println!("{name}: drive at 10 kHz vs 100 kHz differs by at most {d:.4} V (one DAC code: {code:.4} V)");
        assert!(
            d <= code,
            "{name}: {d} V apart, more than a DAC code ({code} V)"
        );
    }
}
