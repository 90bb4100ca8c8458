//! `hal-sim compensate --params PARAMS.json --data IN.csv --out OUT.csv`: IN's `t,x` are the
//! desired readings; writes `t,u,x` with `u` the drive from the library's fixed-point inverse
//! (inverse P–I or inverse Duhem) and `x` copied.

use crate::measured_data::{ColumnNames, Columns, MeasuredData};
use crate::output_file::{csv_t_u_x, Staged};
use crate::param_file::ParamFile;
use std::path::PathBuf;

/// Arguments of `compensate`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Parameter file written by `identify`.
    #[arg(long)]
    pub params: PathBuf,
    /// Input CSV with columns t and x (the desired reading).
    #[arg(long)]
    pub data: PathBuf,
    /// Names of the t, u, x columns in the CSV when it calls them something else (matched
    /// without unit suffix and case, like the header): `--columns t=time,u=drive,x=sensor`.
    #[arg(long, value_name = "t=NAME,u=NAME,x=NAME")]
    pub columns: Option<ColumnNames>,
    /// Output CSV (t,u,x).
    #[arg(long)]
    pub out: PathBuf,
}

/// Runs `compensate`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let (_, model) = ParamFile::load(&args.params)?;
    let data = MeasuredData::read_with(
        &args.data,
        Columns::TimeOutput,
        &args.columns.clone().unwrap_or_default(),
    )?;
    let x = data.x.as_deref().unwrap_or_default();
    let u = model
        .compensate(&data.t, x)
        .map_err(|e| anyhow::anyhow!("{}: {e}", args.params.display()))?;
    let outside = model.reading_outside_range(x);
    if outside > 0 {
        eprintln!(
            "warning: {}: {outside} desired readings outside the model's output range were clamped to it",
            args.data.display()
        );
    }
    let mut out = Staged::new();
    out.write(&args.out, csv_t_u_x(&data.t, &u, x).as_bytes())?;
    out.commit()?;
    println!("wrote {} ({} samples)", args.out.display(), data.len());
    Ok(())
}
