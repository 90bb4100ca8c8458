//! `twinstack dual-stage`: the dual-actuated stage (ball screw + piezo) in simulation — a 5 mm
//! move (settling time, final error against the linear encoder's resolution, peak piezo
//! stroke used) and a trajectory larger than the piezo's stroke tracked by the coarse stage
//! alone and by both (error table).

use hal_sim::dual_stage_sim::{
    five_mm_move, track_large_trajectory, DualStageSimConfig, Trajectory,
};
use twinstack::dual_stage::DualMode;

/// Arguments of `dual-stage`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Length of the move, mm.
    #[arg(long, default_value_t = 5.0)]
    pub distance_mm: f64,
    /// Seconds of the large trajectory tracked (the first 0.2 s are not scored).
    #[arg(long, default_value_t = 2.0)]
    pub seconds: f64,
}

/// Runs `dual-stage`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    if !(args.distance_mm.is_finite() && args.distance_mm.abs() <= 25.0 && args.distance_mm != 0.0)
    {
        anyhow::bail!(
            "--distance-mm {} must be a non-zero length within ±25 mm (the stage's travel)",
            args.distance_mm
        );
    }
    if !(args.seconds.is_finite() && (0.5..=60.0).contains(&args.seconds)) {
        anyhow::bail!("--seconds {} must be within 0.5…60", args.seconds);
    }
    let config = DualStageSimConfig::paper();
    let m = five_mm_move(&config, args.distance_mm * 1e3)?;
    println!(
        "Move of {} mm (trapezoid {} mm/s, {} mm/s²), dual stage",
        args.distance_mm,
        config.dual.move_velocity_um_s / 1e3,
        config.dual.move_acceleration_um_s2 / 1e3
    );
    println!("  planned move                  {:8.3} s", m.move_time_s);
    if m.settled {
        println!(
            "  settling (1 ms mean to ±{} nm) {:8.1} ms after the plan ends",
            m.resolution_nm,
            m.settling_time_s * 1e3
        );
    } else {
        println!(
            "  settling (1 ms mean to ±{} nm)  did not settle",
            m.resolution_nm
        );
    }
    println!(
        "  final error (mean, last 20 ms) {:8.2} nm (noise {:.2} nm rms, max |e| {:.2} nm; linear encoder {} nm)",
        m.final_error_nm, m.final_jitter_nm, m.final_error_max_nm, m.resolution_nm
    );
    println!(
        "  peak piezo stroke used       {:8.2} µm of ±{} µm window (range-limit ticks {}, clamps {})",
        m.peak_piezo_um, m.window_um, m.range_limited_ticks, m.fine_clamps
    );
    println!(
        "  largest error during the move {:7.3} µm; largest change of the error in one tick {:.1} nm ({:+.1} ms from the start of the move)",
        m.max_error_during_move_um,
        m.largest_jump_nm,
        m.largest_jump_at_s * 1e3
    );

    let trajectory = Trajectory::larger_than_the_stroke();
    println!();
    println!(
        "Tracking {} µm at {} Hz + {} µm at {} Hz for {} s (scored after 0.2 s)",
        trajectory.amplitude_um,
        trajectory.slow_hz,
        trajectory.ripple_um,
        trajectory.fast_hz,
        args.seconds
    );
    println!("mode           max µm    RMS µm   peak piezo µm");
    for (name, mode) in [
        ("coarse only", DualMode::CoarseOnly),
        ("dual", DualMode::Dual),
    ] {
        let r = track_large_trajectory(&config, mode, trajectory, args.seconds, 0.2)?;
        println!(
            "{name:<12} {:8.3}  {:8.4}  {:10.2}",
            r.max_um, r.rms_um, r.peak_piezo_um
        );
    }
    Ok(())
}
