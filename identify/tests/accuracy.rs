//! The fixed-point accuracy figures the README quotes stay within their stated bounds.

use twinstack_identify::accuracy::measure;

#[test]
fn fixed_point_stays_within_the_documented_bounds_of_the_f64_reference() {
    let rows = measure(2026, 6, 3000);
    // The benchmarks page's table (`cargo xtask figures accuracy`, with `--nocapture`).
    println!("| model | max error (LSB16) | RMS error (LSB16) | bound (LSB16) | samples |");
    println!("|---|---:|---:|---:|---:|");
    for r in &rows {
        println!(
            "| {} | {:.4} | {:.4} | {:.2} | {} |",
            r.model, r.max_lsb16, r.rms_lsb16, r.bound_lsb16, r.samples
        );
    }
    for r in &rows {
        assert!(r.samples > 0, "{} compared nothing", r.model);
        // Scalar models: their fixed bounds; P–I-based ones: the bank's gain `Σ|w|` times
        // 1.5 steps of its Q1.15 grid (see `twinstack_identify::accuracy`), never looser than 96 LSB16.
        let bound = r.bound_lsb16;
        assert!(bound > 0.0 && bound <= 96.0, "{}: bound {bound}", r.model);
        assert!(
            r.max_lsb16 <= bound,
            "{}: {} LSB16 > {bound}",
            r.model,
            r.max_lsb16
        );
    }
}
