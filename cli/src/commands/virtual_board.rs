//! `twinstack virtual-board --listen tcp:HOST:PORT|pty [--speed X] [--tick-rate HZ]`: the
//! simulated board and stage ([`hal_sim::virtual_board`]) as a long-running server on a TCP port
//! or (Unix) a pseudo-terminal, paced in real time, keeping its state from one client (`twinstack
//! load/stream/record/status --port tcp:HOST:PORT` or `--port /dev/pts/N`) to the next. Runs
//! until killed (Ctrl-C). The first line on stdout says where it listens.

use hal_sim::port::{PortSpec, DEFAULT_BAUD};
use hal_sim::sim_device::SimDeviceConfig;
use hal_sim::virtual_board;
use std::io::Write;
use std::net::TcpListener;
use std::sync::atomic::AtomicBool;

/// Arguments of `virtual-board`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Where to listen: tcp:HOST:PORT (port 0: the OS picks one; the address is printed), or
    /// `pty` (Unix: a pseudo-terminal, its path printed, for programs that want a serial
    /// device).
    #[arg(long)]
    pub listen: String,
    /// Simulated seconds per wall-clock second (0: as fast as possible). Everything on the
    /// board runs on it, so 1.02 is a board whose clock runs 2 % fast (what `twinstack
    /// selftest`'s tick rate check finds).
    #[arg(long, default_value_t = 1.0)]
    pub speed: f64,
    /// The board's control rate, Hz.
    #[arg(long, default_value_t = 50_000.0, value_name = "HZ")]
    pub tick_rate: f64,
    /// Baud rate of the board's modelled UART (the pace of its bytes in simulated time).
    #[arg(long, default_value_t = DEFAULT_BAUD)]
    pub baud: u32,
    /// Serve the dual-stage board (the piezo stage on the ball screw, its coarse axis behind
    /// `twinstack coarse`) instead of the default one; TCP only, 50 kHz.
    #[arg(long)]
    pub dual_stage: bool,
    /// The USB–serial adapter the board is reached through (in simulated time).
    #[command(flatten)]
    pub link: crate::board_link::LinkArgs,
    /// A simulated camera on the trigger input at this frame rate: it starts when a sequence
    /// is armed (`twinstack sequence`) and stops when it is disarmed.
    #[arg(long, value_name = "HZ")]
    pub camera_hz: Option<f64>,
    /// With --camera-hz: frames per sequence, then the camera stops (0: until disarmed).
    #[arg(long, default_value_t = 0, requires = "camera_hz")]
    pub camera_frames: u32,
    /// With --camera-hz: each exposure starts on the settled output (settled → camera
    /// trigger-in) instead of free-running.
    #[arg(long, requires = "camera_hz")]
    pub camera_on_settled: bool,
    /// A jumper from the left DAC channel to the sensor ADC's input, in place of the sensor
    /// (the wiring `twinstack selftest` checks the converters with): the ADC reads the DAC.
    #[arg(long)]
    pub loopback: bool,
    /// Every flash write fails (the sector is left erased), as a worn or locked flash would.
    #[arg(long)]
    pub fail_flash_writes: bool,
    /// The board's watchdog never fires (as if the firmware had not started it): a
    /// watchdog drill is acknowledged and the board does not reset.
    #[arg(long)]
    pub no_watchdog: bool,
    /// What drives the analog setpoint input's pin (0–3.3 V, `twinstack analog`): `open`, a
    /// voltage (e.g. 1.65), or `sine:MEAN,AMPLITUDE,HZ` (volts, volts, Hz). The pin reads as
    /// the board's 12-bit ADC converts it, clipped to 0–3.3 V.
    #[arg(long, default_value = "open", value_name = "SPEC")]
    pub analog_input: hal_sim::analog_source::AnalogSource,
}

/// Runs `virtual-board`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let address = match args.listen.parse::<PortSpec>()? {
        PortSpec::Tcp(address) => Some(address),
        PortSpec::Serial(p) if p == "pty" => None,
        _ => anyhow::bail!(
            "--listen {}: give tcp:HOST:PORT (e.g. tcp:127.0.0.1:4000) or pty",
            args.listen
        ),
    };
    if !(args.speed.is_finite() && args.speed >= 0.0) {
        anyhow::bail!(
            "--speed {}: must be a number ≥ 0 (0: as fast as possible)",
            args.speed
        );
    }
    if !(args.tick_rate.is_finite() && args.tick_rate > 0.0) {
        anyhow::bail!(
            "--tick-rate {}: must be a positive number of Hz",
            args.tick_rate
        );
    }
    if args.baud == 0 {
        anyhow::bail!("--baud must be positive");
    }
    let link = args.link.delay()?;
    let mut config = SimDeviceConfig::paper_at(args.tick_rate, args.baud, link);
    config.link_error_rate = args.link.error_rate()?;
    config.loopback = args.loopback;
    config.failing_flash = args.fail_flash_writes;
    config.watchdog = !args.no_watchdog;
    config.analog_input = args.analog_input;
    if args.dual_stage
        && (args.loopback
            || args.fail_flash_writes
            || args.no_watchdog
            || args.analog_input != hal_sim::analog_source::AnalogSource::Disconnected
            || config.link_error_rate > 0.0)
    {
        anyhow::bail!(
            "--loopback, --fail-flash-writes, --no-watchdog, --analog-input and --link-error-rate are faults and wiring of the default board, not --dual-stage"
        );
    }
    if let Some(hz) = args.camera_hz {
        if args.dual_stage {
            anyhow::bail!(
                "--camera-hz: the simulated camera is on the default board, not --dual-stage"
            );
        }
        config.camera = Some(
            hal_sim::sim_camera::CameraConfig::at_rate(
                hz,
                args.tick_rate,
                args.camera_frames,
                args.camera_on_settled,
            )
            .map_err(|e| anyhow::anyhow!("--camera-hz: {e}"))?,
        );
    }
    let speed = if args.speed == 0.0 {
        "as fast as possible".to_string()
    } else {
        format!("{}× real time", args.speed)
    };
    let Some(address) = address else {
        if args.dual_stage {
            anyhow::bail!(
                "--dual-stage: serve it on tcp:HOST:PORT (the pty server runs the default board)"
            );
        }
        return serve_pty(config, args.speed, &speed);
    };
    let listener = TcpListener::bind(&address)
        .map_err(|e| anyhow::anyhow!("cannot listen on {address}: {e}"))?;
    let local = listener.local_addr()?;
    let which = if args.dual_stage { "dual-stage " } else { "" };
    println!("virtual {which}board listening on tcp:{local} ({speed}; Ctrl-C stops it)");
    std::io::stdout().flush()?;
    let stop = AtomicBool::new(false);
    if args.dual_stage {
        let device = hal_sim::coarse_rig::DualStageDevice::dual_stage(
            &hal_sim::coarse_rig::DualStageDeviceConfig {
                baud: args.baud,
                link,
                ..hal_sim::coarse_rig::DualStageDeviceConfig::paper()
            },
        )?;
        virtual_board::serve_device(listener, device, args.speed, &stop)?;
        return Ok(());
    }
    virtual_board::serve(listener, config, args.speed, &stop)?;
    Ok(())
}

/// `--listen pty`: a pty pair, its slave closed so that clients open its path.
#[cfg(unix)]
fn serve_pty(config: SimDeviceConfig, speed: f64, pace: &str) -> anyhow::Result<()> {
    use serialport::SerialPort as _;
    let (master, slave) = serialport::TTYPort::pair()
        .map_err(|e| anyhow::anyhow!("cannot open a pseudo-terminal: {e}"))?;
    let Some(path) = slave.name() else {
        anyhow::bail!("the pseudo-terminal has no path");
    };
    drop(slave);
    println!("virtual board on pty {path} ({pace}; Ctrl-C stops it)");
    std::io::stdout().flush()?;
    let stop = AtomicBool::new(false);
    virtual_board::serve_pty(master, config, speed, &stop)?;
    Ok(())
}

/// `--listen pty` where there are no pseudo-terminals.
#[cfg(not(unix))]
fn serve_pty(_: SimDeviceConfig, _: f64, _: &str) -> anyhow::Result<()> {
    anyhow::bail!(
        "--listen pty: pseudo-terminals are a Unix facility, not available on {}: use \
         --listen tcp:127.0.0.1:PORT and --port tcp:127.0.0.1:PORT",
        std::env::consts::OS
    )
}
