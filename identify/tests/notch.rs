//! The library's fixed-point notch against the `f64` biquad of the same coefficients
//! ([`twinstack_identify::reference::Biquad`]).

use twinstack::control::notch::{Notch, NotchDesign, NotchState};
use twinstack::fixed_point::{signal_from_f64, signal_to_f64};
use twinstack_identify::reference::Biquad;

/// The differential stage's resonance, as wide as the one in the demo.
fn stage_notch() -> NotchDesign {
    NotchDesign {
        frequency_hz: 21_800.0,
        q: 2.0,
        depth: 0.0,
    }
}

#[test]
fn fixed_point_notch_follows_the_f64_reference() {
    for rate in [50_000.0, 100_000.0] {
        let c = stage_notch().coefficients(rate).unwrap();
        let notch = Notch::from_coefficients(&c);
        let mut reference = Biquad::new(c.b, c.a);
        let mut state = NotchState::default();
        let mut worst: f64 = 0.0;
        let mut seed = 7u32;
        for k in 0..20_000 {
            // A chirp through the notch plus a step and noise, within ±0.9.
            let t = k as f64 / rate;
            let chirp = 0.4 * libm::sin(2.0 * std::f64::consts::PI * (500.0 + 1.2e6 * t) * t);
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let noise = (seed >> 8) as f64 / (1u32 << 24) as f64 * 0.1 - 0.05;
            let step = if k > 10_000 { 0.4 } else { -0.2 };
            let x = signal_from_f64(chirp + noise + step);
            let y = signal_to_f64(notch.step(&mut state, x));
            let r = reference.step(signal_to_f64(x));
            worst = worst.max((y - r).abs());
        }
        // Q2.30 coefficients and rounding: far below a 16-bit LSB (1.5e-5 of the range).
        assert!(worst < 1e-6, "{rate}: fixed point vs f64 differ by {worst}");
    }
}
