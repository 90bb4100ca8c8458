//! The fixed-point accuracy figures the README quotes stay within their stated bounds.

use hal_sim::accuracy::measure;

#[test]
fn fixed_point_stays_within_the_documented_bounds_of_the_f64_reference() {
    let rows = measure(2026, 6, 3000);
    for r in &rows {
        eprintln!(
            "{:<24} max {:.4} LSB16  rms {:.4} LSB16  ({} samples)",
            r.model, r.max_lsb16, r.rms_lsb16, r.samples
        );
        assert!(r.samples > 0, "{} compared nothing", r.model);
        let bound = if r.model.starts_with("inverse") {
            0.5
        } else {
            0.1
        };
        assert!(
            r.max_lsb16 <= bound,
            "{}: {} LSB16 > {bound}",
            r.model,
            r.max_lsb16
        );
    }
}
