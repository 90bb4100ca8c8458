//! `twinstack load --port PORT --params PARAMS.json [--mode …] [--store] [overrides] [--set PATH=VALUE …]`: sends the
//! settings a parameter file carries as one parameter load (the board validates them whole,
//! prepares them off the tick and swaps them in with the drive continuous), optionally
//! storing them to flash.
//!
//! What the file leaves out is kept from the board: a file from `identify` has no sensor
//! calibration and no feedback gains, so the board's present ones are read back
//! (`ReadParams`) and kept. The command line overrides any of them. Every gain has one unit
//! everywhere: `ki` per second, `limit` a fraction of the drive range.
//!
//! A model whose input range reaches beyond what the drive can apply (a ±150 V model onto a
//! 0…140 V drive: the limit would clip every excursion past it) is refused before anything is
//! sent ([`unreachable_input`]), unless `--clamp` accepts it with a warning.

use super::board_link::{connect, PortArgs};
use super::params::ModeArg;
use std::path::PathBuf;
use twinstack::config::settings::{FeedbackSettings, Model, PreviewDesign, Settings};
use twinstack::control::drive::{Configuration, SafeState};
use twinstack_identify::param_file::ParamFile;
use twinstack_link::board_requests::{check_load, keep_from_board, LoadRefused};
use twinstack_link::settings_path;

/// Arguments of `load`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The board.
    #[command(flatten)]
    pub port: PortArgs,
    /// Parameter file written by `identify` (or by hand).
    #[arg(long)]
    pub params: PathBuf,
    /// Mode to enter once loaded [default: the file's].
    #[arg(long, value_enum)]
    pub mode: Option<ModeArg>,
    /// Also write the settings to the board's flash, to boot in this mode.
    #[arg(long, value_enum)]
    pub store: Option<ModeArg>,
    /// Drive only the left stack (the right one idles at the minimum voltage).
    #[arg(long)]
    pub unidirectional: bool,
    /// Bias ū, volts.
    #[arg(long)]
    pub bias: Option<f64>,
    /// Lowest stack voltage, volts.
    #[arg(long, allow_negative_numbers = true)]
    pub min_voltage: Option<f64>,
    /// Highest stack voltage, volts.
    #[arg(long)]
    pub max_voltage: Option<f64>,
    /// Slew limit, volts per second.
    #[arg(long)]
    pub slew_rate: Option<f64>,
    /// Where the outputs go on a fault.
    #[arg(long, value_enum)]
    pub safe_state: Option<SafeArg>,
    /// PI feedback: proportional gain (drive fraction per displacement fraction).
    #[arg(long)]
    pub kp: Option<f64>,
    /// PI feedback: integral gain, per second.
    #[arg(long)]
    pub ki: Option<f64>,
    /// Largest feedback correction, fraction of the drive range (0…1].
    #[arg(long)]
    pub correction_limit: Option<f64>,
    /// No sensor feedback (open loop and bypass only).
    #[arg(long, conflicts_with_all = ["kp", "ki", "correction_limit"])]
    pub no_feedback: bool,
    /// Any setting by its path, after the file and the flags above: `--set /feedback/kp=0.1`
    /// (repeatable; `twinstack settings --schema` lists the paths; the value is JSON or a bare
    /// word).
    #[arg(long = "set", value_name = "PATH=VALUE", value_parser = parse_assignment)]
    pub set: Vec<(String, String)>,
    /// Load a model whose input range the drive cannot reach in full (the drive is then
    /// clipped at its limits), with a warning, instead of refusing it.
    #[arg(long)]
    pub clamp: bool,
    /// Run the preview on the board: every setpoint, whatever its source, shaped for the
    /// stage's resonance before the compensator, the feedback aiming at the setpoint itself
    /// (corners without ringing; the trajectory 4 ticks late). The resonance is the one the
    /// parameter file holds (what `twinstack calibrate` measured).
    #[arg(long, conflicts_with = "no_preview")]
    pub preview: bool,
    /// No preview, even where the board runs one (which a file without one otherwise keeps).
    #[arg(long)]
    pub no_preview: bool,
}

pub use twinstack_link::board_requests::unreachable_input;

/// `--safe-state` values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum SafeArg {
    /// Both stacks at the bias.
    Bias,
    /// Both stacks at 0 V.
    Zero,
}

/// The settings `args` ask for: the file's, with what it leaves out taken from `board` (the
/// settings in force on the board) and the command line's overrides on top.
pub fn settings_for(args: &Args, file: &Settings, board: Option<&Settings>) -> Settings {
    let mut s = keep_from_board(file, board);
    if args.no_preview {
        s.preview = None;
    }
    if args.unidirectional {
        s.drive.configuration = Configuration::Unidirectional;
    }
    s.drive.bias = args.bias.unwrap_or(s.drive.bias);
    s.drive.min_voltage = args.min_voltage.unwrap_or(s.drive.min_voltage);
    s.drive.max_voltage = args.max_voltage.unwrap_or(s.drive.max_voltage);
    s.drive.slew_rate = args.slew_rate.unwrap_or(s.drive.slew_rate);
    if let Some(safe) = args.safe_state {
        s.drive.safe_state = match safe {
            SafeArg::Bias => SafeState::Bias,
            SafeArg::Zero => SafeState::Zero,
        };
    }
    if args.no_feedback {
        s.feedback = None;
    } else if args.kp.is_some() || args.ki.is_some() || args.correction_limit.is_some() {
        let base = s.feedback.unwrap_or(FeedbackSettings::DEFAULT);
        s.feedback = Some(FeedbackSettings {
            kp: args.kp.unwrap_or(base.kp),
            ki: args.ki.unwrap_or(base.ki),
            limit: args.correction_limit.unwrap_or(base.limit),
            ..base
        });
    }
    if let Some(m) = args.mode {
        s.mode = m.into();
    }
    s
}

/// `PATH=VALUE` of `--set`, split at the first `=`.
fn parse_assignment(text: &str) -> Result<(String, String), String> {
    match text.split_once('=') {
        Some((path, value)) if path.starts_with('/') => Ok((path.to_string(), value.to_string())),
        _ => Err(format!(
            "`{text}`: expected PATH=VALUE, e.g. /feedback/kp=0.1"
        )),
    }
}

/// The settings `load` sends: [`settings_for`], then each `--set` in order.
pub fn settings_with_paths(
    args: &Args,
    file: &Settings,
    board: Option<&Settings>,
) -> Result<Settings, settings_path::PathError> {
    let mut settings = settings_for(args, file, board);
    for (path, value) in &args.set {
        settings = settings_path::set(&settings, path, settings_path::parse_value(value))?;
    }
    Ok(settings)
}

/// The file's settings, with `--preview` the preview for the resonance the file holds;
/// refused, naming the file, where it holds none.
pub fn with_preview(args: &Args, file: &ParamFile) -> anyhow::Result<Settings> {
    let mut s = file.settings.clone();
    if args.preview {
        let Some(r) = file.resonance else {
            anyhow::bail!(
                "{}: --preview needs the stage's resonance, which the file does not hold \
                 (`twinstack calibrate` measures it into the file; or give it with \
                 --set '/preview={{\"frequency_hz\":F,\"damping\":Z}}'); nothing was loaded",
                args.params.display()
            );
        };
        s.preview = Some(PreviewDesign {
            frequency_hz: r.frequency_hz,
            damping: r.damping,
        });
    }
    Ok(s)
}

/// Runs `load`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let (file, model) = ParamFile::load(&args.params)?;
    let file_settings = with_preview(args, &file)?;
    let mut client = connect(&args.port)?;
    let board = client.read_params().ok();
    let settings = settings_with_paths(args, &file_settings, board.as_ref())
        .map_err(|e| anyhow::anyhow!("--set {e}; nothing was loaded"))?;
    match check_load(&settings, model.output_sign, args.clamp) {
        Ok(None) => {}
        Ok(Some(warning)) => eprintln!(
            "warning: {}: {warning} (--clamp: loading it anyway)",
            args.params.display()
        ),
        Err(e @ (LoadRefused::InvertedSensor | LoadRefused::Drive(_))) => {
            anyhow::bail!("{}: {e}; nothing was sent", args.params.display())
        }
        Err(e) => anyhow::bail!(
            "{}: {e}; identify the model within the drive's range, or pass --clamp to load \
             it anyway; nothing was loaded",
            args.params.display()
        ),
    }
    client.load_params(&settings)?;
    let what = match &settings.compensator {
        Some(Model::PrandtlIshlinskii(p)) => format!("P–I, {} operators", p.thresholds.len()),
        Some(Model::Duhem(_)) => "Duhem".to_string(),
        Some(Model::GeneralisedPi(p)) => format!(
            "generalised P–I, {} operators, {} dead zones",
            p.pi.thresholds.len(),
            p.dead_zones.thresholds.len()
        ),
        Some(Model::BoucWen(_)) => "Bouc-Wen".to_string(),
        None => "no compensator".to_string(),
    };
    let d = &settings.drive;
    println!(
        "loaded {} ({what}), mode {:?}, drive {:?} {}…{} V bias {} V",
        args.params.display(),
        settings.mode,
        d.configuration,
        d.min_voltage,
        d.max_voltage,
        d.bias
    );
    // What the file left to the board (the stage's settings, not the model's): named, so
    // that a closed loop on gains the file does not hold is not a surprise.
    // A setting the file has none of, sent as the board holds it.
    macro_rules! kept_from_board {
        ($($field:ident),*) => {
            [$((
                stringify!($field),
                file_settings.$field.is_none()
                    && settings.$field.is_some()
                    && board.as_ref().is_some_and(|b| b.$field == settings.$field),
            )),*]
        };
    }
    let kept: Vec<&str> = kept_from_board!(sensor, feedback, shaping, preview)
        .into_iter()
        .filter_map(|(name, kept)| kept.then_some(name))
        .collect();
    if !kept.is_empty() {
        println!(
            "kept from the board (the file has none): {}{}",
            kept.join(", "),
            settings
                .feedback
                .filter(|_| kept.contains(&"feedback"))
                .map_or(String::new(), |f| format!(" (kp {}, ki {})", f.kp, f.ki))
        );
    }
    if let Some(p) = &settings.preview {
        println!(
            "preview: setpoints shaped for the resonance at {:.0} Hz, damping {:.4} (the stage follows them {} ticks late)",
            p.frequency_hz,
            p.damping,
            twinstack::control::preview::PREVIEW_DELAY_TICKS
        );
    }
    if let Some(boot) = args.store {
        client.store_params(boot.into())?;
        println!(
            "stored to flash (boots in {:?})",
            twinstack::config::settings::Mode::from(boot)
        );
    }
    Ok(())
}
