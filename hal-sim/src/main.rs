//! `twinstack`, the command-line tool of the twinstack board (see `twinstack --help`): the
//! binary of the `hal-sim` package.

use clap::{Parser, Subcommand};
use hal_sim::cli;

/// Host tools for the twinstack piezo front-end.
#[derive(Debug, Parser)]
#[command(name = "twinstack", version, about, after_help = cli::EXIT_CODES)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// One variant per subcommand, each delegating to `hal_sim::cli::<name>::run`.
#[derive(Debug, Subcommand)]
enum Command {
    /// The main job: the first paper's 750 Hz study on the simulated board and stage —
    /// identification tables, tracking with each compensator, PNG figures.
    Demo(cli::demo::Args),
    /// Fit a hysteresis model to a measured CSV (by default the best of the family on held-out
    /// data: P–I, generalised P–I, Bouc–Wen, Duhem) and write a parameter file and a figure.
    Identify(cli::identify::Args),
    /// Calibrate the stage in one command: excite it with the board's waveform generator,
    /// record drive and sensor, identify the best model, write the parameter file and a PNG,
    /// load and store the settings, and report the tracking error before and after.
    Calibrate(cli::calibrate::Args),
    /// Run the fixed-point forward model on a drive record.
    Predict(cli::compensate::Args),
    /// Run the fixed-point inverse model on a desired-output record.
    Compensate(cli::compensate::Args),
    /// Sensor feedback around the compensator on the simulated stage: the tracking table
    /// (none / feedforward / feedback / both) and the step with and without the notch.
    ClosedLoop(cli::closed_loop::Args),
    /// Learning feedforward for periodic motion (iterative learning control): the learning
    /// curve, the table against the feedforward alone, the frozen replay; in process on the
    /// simulated stage, or on a board with --port.
    Learn(cli::learn::Args),
    /// Stream a setpoint CSV to the board (within its credits) and play it.
    #[command(after_help = cli::stream::EXIT_CODES)]
    Stream(cli::stream::Args),
    /// Load a parameter file onto the board (optionally storing it to flash).
    Load(cli::load::Args),
    /// Read back the settings in force on the board (JSON, physical units).
    Params(cli::params::Args),
    /// Switch the board's mode (bypass, open-loop, closed-loop), bumpless.
    Mode(cli::params::ModeArgs),
    /// Reload the settings stored in the board's flash.
    Recall(cli::params::RecallArgs),
    /// Print the board's status and telemetry.
    Status(cli::status::Args),
    /// What works on a freshly flashed board, one line per check (safe state, link
    /// integrity, tick rate against the host's clock, DAC→ADC loopback, flash store and
    /// recall) with what to fix; exits 1 when a check fails.
    Selftest(cli::selftest::Args),
    /// Start the board's waveform generator.
    Waveform(cli::waveform::Args),
    /// Run a scan pattern (raster, Lissajous, spiral) on the board with its trigger outputs,
    /// and report the trigger timing.
    Scan(cli::scan::Args),
    /// Step through a list of positions, one per edge on the trigger input (a camera's TTL),
    /// with a settled output; reports early and missed edges and the trigger-to-motion time.
    Sequence(cli::sequence::Args),
    /// The analog setpoint input: start it (the board follows a voltage on its input pin,
    /// compensated), stop it, or read its state.
    Analog(cli::analog::Args),
    /// Stop the stream or the waveform generator (the output holds).
    Stop(cli::stop::Args),
    /// Capture a signal with the board's recorder into a CSV.
    Record(cli::record::Args),
    /// Continuous telemetry: stream signals off the board while it runs, into a CSV and a PNG
    /// (exits 1 if any sample did not arrive).
    Telemetry(cli::telemetry::Args),
    /// A live view of the board in the browser: telemetry plots, status, mode, waveform and
    /// scan controls, the last tune's Bode plot and the calibration's ranking.
    View(cli::view::Args),
    /// Generate the golden vectors (the tick's recorded runs the board must reproduce) and
    /// check them against the stored file and the f64 reference, or write them (--write).
    Golden(cli::golden::Args),
    /// The dual-actuated stage (ball screw + piezo) in simulation: a 5 mm move and a
    /// trajectory larger than the piezo's stroke (coarse only / dual).
    DualStage(cli::dual_stage::Args),
    /// The tracking table on a simulated lab stage outside the model family: identify from
    /// 2 s of 10 Hz excitation, then track a triangle, nested minor loops and a multisine open
    /// loop with each model's compensator and with none.
    LabStage(cli::lab_stage::Args),
    /// The dual-actuated stage's coarse axis: home, move --to-mm X, jog, stop, status (a
    /// dual-stage board; `--port sim` is the simulated dual-stage board).
    #[command(subcommand_required = true)]
    Coarse(cli::coarse::Args),
    /// Measure the stage's frequency response, fit its resonance, place the notch and choose
    /// PI gains for the margins (or check given gains); print margins and bandwidth, write a
    /// Bode PNG, and with --load load them.
    Tune(cli::tune::Args),
    /// Serve the simulated board over TCP (tcp:HOST:PORT), paced in real time, keeping its
    /// state from one command to the next (--port tcp:HOST:PORT), until killed.
    VirtualBoard(cli::virtual_board::Args),
    /// Share one board among several clients over TCP (tcp:HOST:PORT): one owns the stream
    /// and settings at a time, the others read (status, telemetry, records), until killed.
    Serve(cli::serve::Args),
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
            return std::process::ExitCode::from(cli::EXIT_USAGE);
        }
    };
    let result = match &cli.command {
        Command::Demo(a) => cli::demo::run(a),
        Command::Identify(a) => cli::identify::run(a),
        Command::Calibrate(a) => cli::calibrate::run(a),
        Command::Predict(a) => cli::compensate::run(a, cli::compensate::Direction::Forward),
        Command::Compensate(a) => cli::compensate::run(a, cli::compensate::Direction::Inverse),
        Command::ClosedLoop(a) => cli::closed_loop::run(a),
        Command::Learn(a) => cli::learn::run(a),
        Command::Stream(a) => cli::stream::run(a),
        Command::Load(a) => cli::load::run(a),
        Command::Params(a) => cli::params::run(a),
        Command::Mode(a) => cli::params::run_mode(a),
        Command::Recall(a) => cli::params::run_recall(a),
        Command::Status(a) => cli::status::run(a),
        Command::Selftest(a) => cli::selftest::run(a),
        Command::Waveform(a) => cli::waveform::run(a),
        Command::Scan(a) => cli::scan::run(a),
        Command::Sequence(a) => cli::sequence::run(a),
        Command::Analog(a) => cli::analog::run(a),
        Command::Stop(a) => cli::stop::run(a),
        Command::Record(a) => cli::record::run(a),
        Command::Telemetry(a) => cli::telemetry::run(a),
        Command::View(a) => cli::view::run(a),
        Command::Golden(a) => cli::golden::run(a),
        Command::DualStage(a) => cli::dual_stage::run(a),
        Command::LabStage(a) => cli::lab_stage::run(a),
        Command::VirtualBoard(a) => cli::virtual_board::run(a),
        Command::Serve(a) => cli::serve::run(a),
        Command::Tune(a) => cli::tune::run(a),
        Command::Coarse(a) => cli::coarse::run(a),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) if e.downcast_ref::<cli::stream::Underran>().is_some() => {
            eprintln!("warning: {e}");
            std::process::ExitCode::from(cli::stream::EXIT_UNDERRUN)
        }
        Err(e) if e.downcast_ref::<cli::board_link::UsageError>().is_some() => {
            eprintln!("error: {e} (see twinstack --help)");
            std::process::ExitCode::from(cli::EXIT_USAGE)
        }
        Err(e) => {
            // Each error's message already includes its cause.
            eprintln!("error: {e}");
            std::process::ExitCode::from(cli::EXIT_ERROR)
        }
    }
}
