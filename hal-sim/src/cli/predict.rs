//! `hal-sim predict --params PARAMS.json --data IN.csv --out OUT.csv`: the forward model
//! (the library's fixed-point observer) on IN's `t,u`; writes `t,u,x` with `x` the model's
//! predicted reading.

use crate::measured_data::{ColumnNames, Columns, MeasuredData};
use crate::output_file::{csv_t_u_x, Staged};
use crate::param_file::ParamFile;
use std::path::PathBuf;

/// Arguments of `predict`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Parameter file written by `identify`.
    #[arg(long)]
    pub params: PathBuf,
    /// Input CSV with columns t and u.
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

/// Runs `predict`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let (_, model) = ParamFile::load(&args.params)?;
    let data = MeasuredData::read_with(
        &args.data,
        Columns::TimeDrive,
        &args.columns.clone().unwrap_or_default(),
    )?;
    let u = data.u.as_deref().unwrap_or_default();
    let x = model
        .predict(&data.t, u)
        .map_err(|e| anyhow::anyhow!("{}: {e}", args.params.display()))?;
    let outside = model.drive_outside_range(u);
    if outside > 0 {
        eprintln!(
            "warning: {}: {outside} drive samples outside the model's input range were clamped to it",
            args.data.display()
        );
    }
    let mut out = Staged::new();
    out.write(&args.out, csv_t_u_x(&data.t, u, &x).as_bytes())?;
    out.commit()?;
    println!("wrote {} ({} samples)", args.out.display(), data.len());
    Ok(())
}
