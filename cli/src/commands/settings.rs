//! Settings by path: `twinstack get PATH`, `twinstack set PATH VALUE` (on a board, or in a
//! parameter file with `--file`) and `twinstack settings --schema` (every path there is).
//!
//! A path names one value of the settings' JSON form (`/feedback/kp`, `/drive/slew_rate`,
//! `/compensator`; [`twinstack_link::settings_path`]). On a board, `set` reads the settings in
//! force, changes the one value and loads the whole settings back: the board validates them,
//! prepares them off the tick and swaps them in with the drive continuous, as for any load,
//! and a refusal names the field and its limit. Then it reads them back and prints the value
//! the board holds.

use super::board_link::{connect, PortArgs};
use std::path::PathBuf;
use twinstack_identify::param_file::ParamFile;
use twinstack_link::settings_path::{self, parse_value};

/// Where the settings are: a board, or a parameter file.
#[derive(Debug, clap::Args)]
pub struct Target {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// A parameter file (`identify`'s PARAMS.json) instead of a board: its `settings`.
    #[arg(long, value_name = "PARAMS.json")]
    pub file: Option<PathBuf>,
}

/// Arguments of `get`.
#[derive(Debug, clap::Args)]
pub struct GetArgs {
    /// The setting's path, e.g. /feedback/kp (`twinstack settings --schema` lists them); `/`
    /// for all of them.
    pub path: String,
    /// Where the settings are.
    #[command(flatten)]
    pub target: Target,
}

/// Arguments of `set`.
#[derive(Debug, clap::Args)]
pub struct SetArgs {
    /// The setting's path, e.g. /feedback/kp.
    pub path: String,
    /// The value, as JSON (0.1, true, null, [1, 2], {"kp": 0.1, …}) or a bare word for a
    /// choice (ClosedLoop).
    #[arg(allow_hyphen_values = true)]
    pub value: String,
    /// Where the settings are.
    #[command(flatten)]
    pub target: Target,
}

/// Arguments of `settings`.
#[derive(Debug, clap::Args)]
pub struct SchemaArgs {
    /// List every path the settings have, with what each holds (what `settings` prints).
    #[arg(long)]
    pub schema: bool,
    /// As JSON (a list of {path, kind}).
    #[arg(long)]
    pub json: bool,
}

/// Runs `get`.
pub fn run_get(args: &GetArgs) -> anyhow::Result<()> {
    let settings = match &args.target.file {
        Some(path) => ParamFile::load(path)?.0.settings,
        None => connect(&args.target.port)?.read_params()?,
    };
    let value = settings_path::get(&settings, &args.path)?;
    println!("{}", serde_json::to_string_pretty(&value)?);
    Ok(())
}

/// Runs `set`.
pub fn run_set(args: &SetArgs) -> anyhow::Result<()> {
    let value = parse_value(&args.value);
    match &args.target.file {
        Some(path) => {
            let (mut file, _) = ParamFile::load(path)?;
            file.settings = settings_path::set(&file.settings, &args.path, value)?;
            // The file is checked whole as `load` reads it before it is written.
            ParamFile::parse(path, &file.to_json()).map_err(|e| {
                anyhow::anyhow!("{} = {}: {e}; nothing was written", args.path, args.value)
            })?;
            file.save(path)?;
            let now = settings_path::get(&file.settings, &args.path)?;
            println!("{}: {} = {now}", path.display(), args.path);
        }
        None => {
            let mut client = connect(&args.target.port)?;
            let settings = client.read_params()?;
            let new = settings_path::set(&settings, &args.path, value)?;
            client.load_params(&new).map_err(|e| {
                anyhow::anyhow!(
                    "{} = {}: {e}; the board kept its settings",
                    args.path,
                    args.value
                )
            })?;
            let held = client.read_params()?;
            let now = settings_path::get(&held, &args.path)?;
            println!("the board holds {} = {now}", args.path);
        }
    }
    Ok(())
}

/// Runs `settings`.
pub fn run_schema(args: &SchemaArgs) -> anyhow::Result<()> {
    let schema = settings_path::schema();
    if args.json {
        println!("{}", serde_json::to_string_pretty(&schema)?);
    } else {
        let width = schema.iter().map(|e| e.path.len()).max().unwrap_or(0);
        for e in &schema {
            println!("{:width$}  {}", e.path, e.kind);
        }
    }
    Ok(())
}
