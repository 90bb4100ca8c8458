//! The parameter file's model run on a record, either way:
//!
//! * `twinstack predict --params PARAMS.json --data IN.csv --out OUT.csv`: the forward model (the
//!   library's fixed-point observer) on IN's `t,u`; writes `t,u,x` with `x` the predicted
//!   reading;
//! * `twinstack compensate --params PARAMS.json --data IN.csv --out OUT.csv`: IN's `t,x` are the
//!   desired readings; writes `t,u,x` with `u` the drive from the library's fixed-point inverse
//!   and `x` copied. With a sensor lag of `L` samples the drive leads by `L`; its last `L`
//!   samples aim at the last desired reading (held), and the run says so. Every sample is
//!   inverted exactly, as the board inverts its setpoints; with `--measured` IN's `x` is a
//!   sensor's record and is followed through its noise band
//!   ([`twinstack_identify::stage_model::NoiseBand`]), as identification scores an inverse.
//!   With `--preview` (the resonance `twinstack calibrate` measured into the parameter file)
//!   or `--resonance-hz F --resonance-damping Z` (what `twinstack tune` fits and prints) the
//!   planned trajectory is shaped first so that the stage's resonance does not ring at its
//!   corners ([`twinstack_identify::preview`]): IN's samples must be evenly spaced.

use std::path::{Path, PathBuf};
use twinstack_identify::param_file::ParamFile;
use twinstack_identify::preview::Resonance;
use twinstack_link::measured_data::{ColumnNames, Columns, MeasuredData};
use twinstack_link::output_file::{csv_t_u_x, Staged};

/// Arguments of `predict` and `compensate`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Parameter file written by `identify`.
    #[arg(long)]
    pub params: PathBuf,
    /// Input CSV: columns t and u (the drive) for `predict`, t and x (the desired reading)
    /// for `compensate`.
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

/// Arguments of `compensate`: those of `predict`, and what the desired readings are.
#[derive(Debug, clap::Args)]
pub struct CompensateArgs {
    #[command(flatten)]
    pub run: Args,
    /// The desired readings are a sensor's record (with its noise), not a planned trajectory:
    /// follow them through a band of 3σ of their noise (σ from their second differences,
    /// printed), so that the noise is not taken for motion, as `identify` scores an inverse.
    /// Without it every sample is inverted exactly, as the board inverts its setpoints.
    #[arg(long)]
    pub measured: bool,
    /// Shape the planned trajectory ahead of time so that the stage's resonance does not ring
    /// at its corners: the resonance's frequency, Hz, as `twinstack tune` fits it (with
    /// --resonance-damping). The desired readings are then what the stage reads a sample's
    /// end; the t column must be evenly spaced (its rate is the drive's).
    #[arg(long, requires = "resonance_damping", conflicts_with_all = ["measured", "preview"])]
    pub resonance_hz: Option<f64>,
    /// The resonance's damping ratio, in (0, 1), as `twinstack tune` fits it (with
    /// --resonance-hz).
    #[arg(long, requires = "resonance_hz")]
    pub resonance_damping: Option<f64>,
    /// Shape the planned trajectory for the resonance the parameter file holds (what
    /// `twinstack calibrate` measured), as --resonance-hz/--resonance-damping would.
    #[arg(long, conflicts_with = "measured")]
    pub preview: bool,
}

impl CompensateArgs {
    /// The resonance the trajectory is to be shaped for, as the flags ask it.
    pub fn preview(&self) -> Preview {
        Preview::from_flags(self.resonance_hz.zip(self.resonance_damping), self.preview)
    }
}

/// Whether and for which resonance a planned trajectory is shaped
/// ([`twinstack_identify::preview::ResonancePreview`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Preview {
    /// Not shaped.
    None,
    /// For the resonance given on the command line.
    Given(Resonance),
    /// For the resonance the parameter file holds.
    FromFile,
}

impl Preview {
    /// What `--resonance-hz/--resonance-damping` (`given`) and `--preview` (`from_file`) ask
    /// for (`compensate` and `stream` alike; clap keeps them apart).
    pub fn from_flags(given: Option<(f64, f64)>, from_file: bool) -> Self {
        match (given, from_file) {
            (Some((frequency_hz, damping)), _) => Self::Given(Resonance {
                frequency_hz,
                damping,
            }),
            (None, true) => Self::FromFile,
            (None, false) => Self::None,
        }
    }

    /// The resonance to shape for and the flags that asked for it (to name them in an
    /// error): the one given, or the one the parameter file `file` (read from `path`) holds,
    /// refused naming the file where it holds none.
    pub fn resonance(
        self,
        file: Option<&ParamFile>,
        path: &Path,
    ) -> anyhow::Result<Option<(Resonance, String)>> {
        Ok(match self {
            Self::None => None,
            Self::Given(r) => Some((r, "--resonance-hz/--resonance-damping".into())),
            Self::FromFile => {
                let r = file.and_then(|f| f.resonance).ok_or_else(|| {
                    anyhow::anyhow!(
                        "--preview: {} holds no resonance (`twinstack calibrate` or `twinstack tune --params` measures it into the file; or give --resonance-hz and --resonance-damping, as `twinstack tune` prints them)",
                        path.display()
                    )
                })?;
                Some((r, format!("--preview: the resonance of {}", path.display())))
            }
        })
    }
}

/// Which way the model runs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Direction {
    /// Drive in, predicted reading out (`predict`).
    Forward,
    /// Desired reading in, drive out (`compensate`): a measured record (`--measured`) or a
    /// planned trajectory.
    Inverse {
        /// The desired readings are a sensor's record.
        measured: bool,
        /// The planned trajectory's preview.
        preview: Preview,
    },
}

/// Runs `predict` ([`Direction::Forward`]) or `compensate` ([`Direction::Inverse`]).
pub fn run(args: &Args, direction: Direction) -> anyhow::Result<()> {
    let (file, model) = ParamFile::load(&args.params)?;
    let columns = match direction {
        Direction::Forward => Columns::TimeDrive,
        Direction::Inverse { .. } => Columns::TimeOutput,
    };
    let data = MeasuredData::read_with(
        &args.data,
        columns,
        &args.columns.clone().unwrap_or_default(),
    )?;
    let model_error = |e| anyhow::anyhow!("{}: {e}", args.params.display());
    let (u, x, outside, what) = match direction {
        Direction::Forward => {
            let u = data.u.clone().unwrap_or_default();
            let x = model.predict(&data.t, &u).map_err(model_error)?;
            let outside = model.drive_outside_range(&u);
            (
                u,
                x,
                outside,
                "drive samples outside the model's input range",
            )
        }
        Direction::Inverse { measured, preview } => {
            let x = data.x.clone().unwrap_or_default();
            let preview = match preview.resonance(Some(&file), &args.params)? {
                Some((r, flags)) => Some(
                    r.preview_at_times(&data.t)
                        .map_err(|e| anyhow::anyhow!("{flags}: {e}"))?,
                ),
                None => None,
            };
            let u = if let Some(p) = &preview {
                eprintln!(
                    "note: preview: shaped for a resonance at {} Hz, damping {}, at {:.0} Hz (the trajectory taken as resting at its last reading after it)",
                    p.resonance_hz, p.zeta, p.rate_hz
                );
                let (lo, hi) = model.reading_range();
                let shaped = p.shape_within(&x, lo, hi).map_err(|e| {
                    anyhow::anyhow!("{}: {e}; nothing was written", args.data.display())
                })?;
                model.compensate(&data.t, &shaped)
            } else if measured {
                model
                    .compensate_measured_with_band(&data.t, &x)
                    .map(|(u, band)| {
                        match band {
                            Some(band) => eprintln!(
                                "note: --measured: the readings' noise RMS is {:.4} (second differences), so reversals within ±{:.4} are taken for noise",
                                band.noise_rms,
                                band.width_norm * model.scaling.output_half_span()
                            ),
                            None => eprintln!(
                                "note: --measured: a P–I or generalised P–I model's inverse takes the readings as they come (its memory closes every loop the noise makes)"
                            ),
                        }
                        u
                    })
            } else {
                model.compensate(&data.t, &x)
            }
            .map_err(model_error)?;
            // With a sensor lag of L samples the drive at sample k aims at the reading at
            // k + L (between two readings for a half L); the last ⌈L⌉ samples have none, so
            // they aim at the last reading (held).
            let lag = 0.5 * model.lag_half_samples(&data.t) as f64;
            let last = model.lag_samples(&data.t).min(data.len().saturating_sub(1));
            if last > 0 {
                eprintln!(
                    "note: the sensor lags the drive by {lag} sample{}: the drive leads the desired reading by as much, and its last {last} sample{} aim at the last desired reading (t = {} s), there being no later one",
                    if lag == 1.0 { "" } else { "s" },
                    if last == 1 { "" } else { "s" },
                    data.t.last().copied().unwrap_or_default()
                );
            }
            // A drive held at an end of the model's input range is a reading the model cannot
            // reach from inside it: said, not left to be found on the stage.
            let railed = model.drive_at_range_end(&u);
            if railed > 0 {
                eprintln!(
                    "warning: {}: {railed} of {} drive samples sit at an end of the model's input range ({}…{} V): the model reaches those desired readings only from beyond it",
                    args.data.display(),
                    u.len(),
                    model.scaling.input_min,
                    model.scaling.input_max
                );
            }
            let outside = model.reading_outside_range(&x);
            (
                u,
                x,
                outside,
                "desired readings outside the model's output range",
            )
        }
    };
    if outside > 0 {
        eprintln!(
            "warning: {}: {outside} {what} were clamped to it",
            args.data.display()
        );
    }
    let mut out = Staged::new();
    out.write(&args.out, &csv_t_u_x(&data.t, &u, &x)?)?;
    out.commit()?;
    println!("wrote {} ({} samples)", args.out.display(), data.len());
    Ok(())
}
