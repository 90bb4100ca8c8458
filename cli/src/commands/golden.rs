//! `twinstack golden [--write] [--dir DIR]`: generates the golden vectors from the committed
//! parameter files and either compares them with `DIR/vectors.bin` (default) or writes them
//! there (`--write`). Either way it prints each set's size and digest and how far its outputs
//! are from the `f64` reference tick; it fails if a set exceeds the reference bounds, or (without
//! `--write`) if the stored file differs from what the tick now produces.

use anyhow::{anyhow, bail};
use std::path::PathBuf;
use twinstack::control::TickFlags;
use twinstack_golden::{VectorSet, VectorSets};
use twinstack_identify::golden::{
    default_dir, generate, reference_tick, sets, REGENERATE, VECTOR_FILE,
};
use twinstack_link::output_file::Staged;

/// Arguments of `golden`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Write the vectors (otherwise: check the stored ones against a fresh generation).
    #[arg(long)]
    pub write: bool,
    /// Golden directory (holds params/ and vectors.bin); default: the repository's tests/golden.
    #[arg(long)]
    pub dir: Option<PathBuf>,
}

fn parse(file: &[u8]) -> anyhow::Result<Vec<VectorSet<'_>>> {
    VectorSets::new(file)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| anyhow!("{e:?}"))
}

/// Ticks with each flag: underrun, range limit, slew limit, ADC error, DAC error, drift.
pub fn flag_counts(set: &VectorSet<'_>) -> [usize; 6] {
    let bits = [
        TickFlags::UNDERRUN,
        TickFlags::RANGE_LIMIT,
        TickFlags::SLEW_LIMIT,
        TickFlags::ADC_ERROR,
        TickFlags::DAC_ERROR,
        TickFlags::DRIFT,
    ];
    bits.map(|b| set.outputs().filter(|o| o.flags & b != 0).count())
}

/// Runs `golden`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let dir = args.dir.clone().unwrap_or_else(default_dir);
    let defs = sets::definitions(&dir)?;
    let (generated, file) = generate::generate_all(&defs)?;
    let fresh = parse(&file)?;
    println!(
        "set                   ticks    bytes  outputs CRC  drive LSB16  estimate LSB16  code    ambiguous  underrun/range/slew/adc/dac/drift"
    );
    let mut out_of_bounds = Vec::new();
    for set in &fresh {
        let a = reference_tick::check(set)?;
        let counts = flag_counts(set);
        println!(
            "{:<20} {:>6} {:>8}  {:08x}     {:>8.4}     {:>8.4}    {:.4}  {:>5}      {}",
            set.name(),
            set.ticks(),
            set.record_len(),
            set.outputs_crc(),
            a.drive_lsb16,
            a.estimate_lsb16,
            a.code_error,
            a.ambiguous,
            counts.map(|c| c.to_string()).join("/")
        );
        if !a.holds() {
            out_of_bounds.push(format!("{a:?}"));
        }
    }
    println!("total {} bytes in {} sets", file.len(), generated.len());
    if !out_of_bounds.is_empty() {
        bail!(
            "outputs outside the f64 reference's bounds (nothing written):\n{}",
            out_of_bounds.join("\n")
        );
    }
    let path = dir.join(VECTOR_FILE);
    if args.write {
        let mut out = Staged::new();
        out.write(&path, &file)?;
        out.commit()?;
        println!("wrote {}", path.display());
        return Ok(());
    }
    let stored = std::fs::read(&path).map_err(|e| anyhow!("{}: {e}", path.display()))?;
    if stored == file {
        println!("{} is up to date", path.display());
        return Ok(());
    }
    let stored_sets = parse(&stored).map_err(|e| anyhow!("{}: {e}", path.display()))?;
    for (new, old) in fresh.iter().zip(&stored_sets) {
        if new.name() != old.name() {
            bail!(
                "{}: set {} where {} was expected",
                path.display(),
                old.name(),
                new.name()
            );
        }
        if let Some(k) = new.outputs().zip(old.outputs()).position(|(a, b)| a != b) {
            println!(
                "{}: tick {k}: stored {:?}, now {:?}",
                new.name(),
                old.output(k as u32),
                new.output(k as u32)
            );
        }
    }
    bail!(
        "{} differs from what the tick now produces; if the change is intended, regenerate with `{REGENERATE}`",
        path.display()
    )
}
