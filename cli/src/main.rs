//! `twinstack`, the command-line tool of the twinstack board (see `twinstack --help`): the
//! binary of the `twinstack-cli` package.

use clap::{Parser, Subcommand};
use twinstack_cli::commands;

/// Host tools for the twinstack piezo front-end.
#[derive(Debug, Parser)]
#[command(name = "twinstack", version, about, after_help = commands::EXIT_CODES)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// One variant per subcommand, each delegating to `twinstack_cli::commands::<name>::run`.
#[derive(Debug, Subcommand)]
enum Command {
    /// The main job: the first paper's 750 Hz study on the simulated board and stage —
    /// identification tables, tracking with each compensator, PNG figures.
    Demo(commands::demo::Args),
    /// Fit a hysteresis model to a measured CSV (by default the best of the family on held-out
    /// data: P–I, generalised P–I, Bouc–Wen, Duhem) and write a parameter file and a figure.
    Identify(commands::identify::Args),
    /// Calibrate the stage in one command: excite it with the board's waveform generator,
    /// record drive and sensor, identify the best model, write the parameter file and a PNG,
    /// load and store the settings, and report the tracking error before and after.
    Calibrate(commands::calibrate::Args),
    /// Run the fixed-point forward model on a drive record.
    Predict(commands::compensate::Args),
    /// Run the fixed-point inverse model on a desired-output record.
    Compensate(commands::compensate::CompensateArgs),
    /// Sensor feedback around the compensator on the simulated stage: the tracking table
    /// (none / feedforward / feedback / both) and the step with and without the notch.
    ClosedLoop(commands::closed_loop::Args),
    /// Learning feedforward for periodic motion (iterative learning control): the learning
    /// curve, the table against the feedforward alone, the frozen replay; in process on the
    /// simulated stage, or on a board with --port.
    Learn(commands::learn::Args),
    /// Stream a setpoint CSV to the board (within its credits) and play it.
    #[command(after_help = commands::stream::EXIT_CODES)]
    Stream(commands::stream::Args),
    /// Load a parameter file onto the board (optionally storing it to flash).
    Load(commands::load::Args),
    /// Read back the settings in force on the board (JSON, physical units).
    Params(commands::params::Args),
    /// Read one setting by its path (/feedback/kp), from the board or a parameter file.
    Get(commands::settings::GetArgs),
    /// Change one setting by its path: on the board (validated and swapped in bumplessly, as
    /// any load) or in a parameter file.
    Set(commands::settings::SetArgs),
    /// List every settings path with what it holds (--schema).
    Settings(commands::settings::SchemaArgs),
    /// What each configuration (parameter files, or every model calibrate can pick) costs the
    /// control tick, and the highest rate the board admits it at: as loaded, without its
    /// observer, with the learning, a scan, the trigger input, a capture and telemetry beside it.
    Budget(commands::budget::Args),
    /// Switch the board's mode (bypass, open-loop, closed-loop), bumpless.
    Mode(commands::params::ModeArgs),
    /// Reload the settings stored in the board's flash.
    Recall(commands::params::RecallArgs),
    /// Print the board's status and telemetry.
    Status(commands::status::Args),
    /// What works on a freshly flashed board, one line per check (safe state, link
    /// integrity, tick rate against the host's clock, DAC→ADC loopback, flash store and
    /// recall) with what to fix; exits 1 when a check fails.
    Selftest(commands::selftest::Args),
    /// Start the board's waveform generator.
    Waveform(commands::waveform::Args),
    /// Run a scan pattern (raster, Lissajous, spiral) on the board with its trigger outputs,
    /// and report the trigger timing.
    Scan(commands::scan::Args),
    /// Step through a list of positions, one per edge on the trigger input (a camera's TTL),
    /// with a settled output; reports early and missed edges and the trigger-to-motion time.
    Sequence(commands::sequence::Args),
    /// The analog setpoint input: start it (the board follows a voltage on its input pin,
    /// compensated), stop it, or read its state.
    Analog(commands::analog::Args),
    /// Stop the stream or the waveform generator (the output holds).
    Stop(commands::stop::Args),
    /// Capture a signal with the board's recorder into a CSV.
    Record(commands::record::Args),
    /// Continuous telemetry: stream signals off the board while it runs, into a CSV and a PNG
    /// (exits 1 if any sample did not arrive).
    Telemetry(commands::telemetry::Args),
    /// A live view of the board in the browser: telemetry plots, status, mode, waveform and
    /// scan controls, the last tune's Bode plot and the calibration's ranking.
    View(commands::view::Args),
    /// Generate the golden vectors (the tick's recorded runs the board must reproduce) and
    /// check them against the stored file and the f64 reference, or write them (--write).
    Golden(commands::golden::Args),
    /// The dual-actuated stage (ball screw + piezo) in simulation: a 5 mm move and a
    /// trajectory larger than the piezo's stroke (coarse only / dual).
    DualStage(commands::dual_stage::Args),
    /// The tracking table on a simulated lab stage outside the model family: identify from
    /// 2 s of 10 Hz excitation, then track a triangle, nested minor loops and a multisine open
    /// loop with each model's compensator and with none.
    LabStage(commands::lab_stage::Args),
    /// The dual-actuated stage's coarse axis: home, move --to-mm X, jog, stop, status (a
    /// dual-stage board; `--port sim` is the simulated dual-stage board).
    #[command(subcommand_required = true)]
    Coarse(commands::coarse::Args),
    /// Measure the stage's frequency response, fit its resonance, place the notch and choose
    /// PI gains for the margins (or check given gains); print margins and bandwidth, write a
    /// Bode PNG, and with --load load them.
    Tune(commands::tune::Args),
    /// Serve the simulated board over TCP (tcp:HOST:PORT), paced in real time, keeping its
    /// state from one command to the next (--port tcp:HOST:PORT), until killed.
    VirtualBoard(commands::virtual_board::Args),
    /// Share one board among several clients over TCP (tcp:HOST:PORT): one owns the stream
    /// and settings at a time, the others read (status, telemetry, records), until killed.
    Serve(commands::serve::Args),
}

fn main() -> std::process::ExitCode {
    // Rust ignores SIGPIPE, so printing into a closed pipe (`twinstack identify … | head`)
    // panics; a command-line tool should just stop, as `cat` does.
    #[cfg(unix)]
    // SAFETY: called first thing in main, before any other thread exists; SIG_DFL is a
    // valid disposition for SIGPIPE.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            use clap::error::ErrorKind;
            if matches!(
                e.kind(),
                ErrorKind::DisplayHelp
                    | ErrorKind::DisplayVersion
                    | ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand
            ) {
                e.exit();
            }
            // One line: clap's first paragraph names the bad or missing argument(s).
            let text = e.to_string();
            let first: Vec<&str> = text
                .lines()
                .take_while(|l| !l.trim().is_empty())
                .map(str::trim)
                .collect();
            eprintln!("{} (see twinstack --help)", first.join(" "));
            return std::process::ExitCode::from(commands::EXIT_USAGE);
        }
    };
    let result = match &cli.command {
        Command::Demo(a) => commands::demo::run(a),
        Command::Identify(a) => commands::identify::run(a),
        Command::Calibrate(a) => commands::calibrate::run(a),
        Command::Predict(a) => {
            commands::compensate::run(a, commands::compensate::Direction::Forward)
        }
        Command::Compensate(a) => commands::compensate::run(
            &a.run,
            commands::compensate::Direction::Inverse {
                measured: a.measured,
                preview: a.preview(),
            },
        ),
        Command::ClosedLoop(a) => commands::closed_loop::run(a),
        Command::Learn(a) => commands::learn::run(a),
        Command::Stream(a) => commands::stream::run(a),
        Command::Load(a) => commands::load::run(a),
        Command::Params(a) => commands::params::run(a),
        Command::Get(a) => commands::settings::run_get(a),
        Command::Set(a) => commands::settings::run_set(a),
        Command::Settings(a) => commands::settings::run_schema(a),
        Command::Budget(a) => commands::budget::run(a),
        Command::Mode(a) => commands::params::run_mode(a),
        Command::Recall(a) => commands::params::run_recall(a),
        Command::Status(a) => commands::status::run(a),
        Command::Selftest(a) => commands::selftest::run(a),
        Command::Waveform(a) => commands::waveform::run(a),
        Command::Scan(a) => commands::scan::run(a),
        Command::Sequence(a) => commands::sequence::run(a),
        Command::Analog(a) => commands::analog::run(a),
        Command::Stop(a) => commands::stop::run(a),
        Command::Record(a) => commands::record::run(a),
        Command::Telemetry(a) => commands::telemetry::run(a),
        Command::View(a) => commands::view::run(a),
        Command::Golden(a) => commands::golden::run(a),
        Command::DualStage(a) => commands::dual_stage::run(a),
        Command::LabStage(a) => commands::lab_stage::run(a),
        Command::VirtualBoard(a) => commands::virtual_board::run(a),
        Command::Serve(a) => commands::serve::run(a),
        Command::Tune(a) => commands::tune::run(a),
        Command::Coarse(a) => commands::coarse::run(a),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) if e.downcast_ref::<commands::stream::Underran>().is_some() => {
            eprintln!("warning: {e}");
            std::process::ExitCode::from(commands::stream::EXIT_UNDERRUN)
        }
        Err(e)
            if e.downcast_ref::<commands::board_link::UsageError>()
                .is_some() =>
        {
            eprintln!("error: {e} (see twinstack --help)");
            std::process::ExitCode::from(commands::EXIT_USAGE)
        }
        Err(e) => {
            // Each error's message already includes its cause.
            eprintln!("error: {e}");
            std::process::ExitCode::from(commands::EXIT_ERROR)
        }
    }
}
