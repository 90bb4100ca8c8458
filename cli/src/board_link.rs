//! What every board command shares: `--port` (or `TWINSTACK_PORT`), `--baud`, `--timeout-ms`,
//! and connecting. When no port is given, or a serial device cannot be opened, the error lists
//! the serial ports the system has ([`port::available_ports`]).

use hal_sim::port::{self, PortError, PortSpec, DEFAULT_BAUD};
use std::time::Duration;
use twinstack_link::serial::SerialError;
use twinstack_link::{Client, Transport};

/// The environment variable `--port` falls back to.
pub const PORT_ENV: &str = "TWINSTACK_PORT";

/// Where the board is and how to talk to it.
#[derive(Debug, clap::Args)]
pub struct PortArgs {
    /// Serial device or pty (/dev/ttyUSB0, COM3, /dev/pts/3), unix:SOCKET or tcp:HOST:PORT
    /// (QEMU's UART, `twinstack virtual-board`), or `sim` for the simulated board in-process.
    /// Without it, the environment variable TWINSTACK_PORT; with neither, the error lists the
    /// serial ports found.
    #[arg(long, env = PORT_ENV, hide_env_values = true)]
    pub port: Option<String>,
    /// Baud rate of a serial device (and of the simulated board's modelled UART).
    #[arg(long, default_value_t = DEFAULT_BAUD)]
    pub baud: u32,
    /// How long to wait for each response, milliseconds.
    #[arg(long, default_value_t = 2000, value_name = "MS")]
    pub timeout_ms: u64,
    /// The simulated board's link (`--port sim`): the USB–serial adapter's latency each way.
    #[command(flatten)]
    pub link: LinkArgs,
}

/// The USB–serial adapter the simulated board is reached through (`--port sim`,
/// `virtual-board`): every transfer, each way, is delayed by latency ± jitter (uniform). The
/// default is an FTDI adapter's 16 ms latency timer.
#[derive(Clone, Copy, Debug, clap::Args)]
pub struct LinkArgs {
    /// Latency of each transfer on the simulated board's link, each way, ms (0: ideal).
    #[arg(long, default_value_t = 16.0, value_name = "MS")]
    pub link_latency_ms: f64,
    /// Jitter of that latency, ± ms (at most the latency).
    #[arg(long, default_value_t = 4.0, value_name = "MS")]
    pub link_jitter_ms: f64,
    /// Fraction of bytes the simulated board's link corrupts, each way (one bit flipped in
    /// each byte hit; 0: a sound link): a bad cable or a wrong baud rate, for rehearsing what
    /// the host does about it (`twinstack selftest`).
    #[arg(long, default_value_t = 0.0, value_name = "FRACTION")]
    pub link_error_rate: f64,
}

impl Default for LinkArgs {
    /// The flags' defaults: 16 ms ± 4 ms.
    fn default() -> Self {
        LinkArgs {
            link_latency_ms: 16.0,
            link_jitter_ms: 4.0,
            link_error_rate: 0.0,
        }
    }
}

impl LinkArgs {
    /// The delay model; a negative, non-finite or over-large value, or a jitter above the
    /// latency, is an error naming the flag.
    pub fn delay(&self) -> anyhow::Result<hal_sim::sim_device::LinkDelay> {
        let ms = |v: f64, flag: &str| -> anyhow::Result<Duration> {
            if !(v.is_finite() && (0.0..=10_000.0).contains(&v)) {
                anyhow::bail!("--{flag} {v}: must be a number of milliseconds from 0 to 10000");
            }
            Ok(Duration::from_secs_f64(v / 1e3))
        };
        let latency = ms(self.link_latency_ms, "link-latency-ms")?;
        let jitter = ms(self.link_jitter_ms, "link-jitter-ms")?;
        if jitter > latency {
            anyhow::bail!(
                "--link-jitter-ms {} exceeds --link-latency-ms {} (a delay cannot be negative)",
                self.link_jitter_ms,
                self.link_latency_ms
            );
        }
        Ok(hal_sim::sim_device::LinkDelay::new(latency, jitter)?)
    }

    /// The fraction of bytes corrupted; outside 0…1 (or not a number) is an error naming the
    /// flag.
    pub fn error_rate(&self) -> anyhow::Result<f64> {
        let r = self.link_error_rate;
        if !(r.is_finite() && (0.0..=1.0).contains(&r)) {
            anyhow::bail!("--link-error-rate {r}: must be a fraction of bytes from 0 to 1");
        }
        Ok(r)
    }
}

/// A command-line mistake found after parsing (no `--port` and no `TWINSTACK_PORT`): `main`
/// exits with 2, as for clap's own usage errors.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct UsageError(pub String);

/// The board behind `--port`, through a client with a clean line.
pub type BoardClient = Client<Box<dyn Transport>>;

/// The port `args` name (`--port`, else `TWINSTACK_PORT`, which clap has already read into
/// `--port`). No port at all is a [`UsageError`] that lists the ports found.
pub fn port_spec(args: &PortArgs) -> anyhow::Result<PortSpec> {
    let Some(port) = &args.port else {
        return Err(UsageError(format!(
            "no board port: give --port PORT or set {PORT_ENV}; {}",
            port::available_ports()
        ))
        .into());
    };
    Ok(port.parse()?)
}

/// Opens the port and resynchronises the line. A serial device that is missing or cannot be
/// opened is reported with the ports that are there.
pub fn connect(args: &PortArgs) -> anyhow::Result<BoardClient> {
    connect_with(args, |_| {})
}

/// [`connect`], with `sim` adjusting the in-process board's configuration before it is built
/// (`--port sim` only: what a command's own flags fit on the simulated bench).
pub fn connect_with(
    args: &PortArgs,
    sim: impl FnOnce(&mut hal_sim::sim_device::SimDeviceConfig),
) -> anyhow::Result<BoardClient> {
    if args.timeout_ms == 0 {
        anyhow::bail!("--timeout-ms must be at least 1");
    }
    let spec = port_spec(args)?;
    let link = args.link.delay()?;
    let error_rate = args.link.error_rate()?;
    let opened = match spec {
        PortSpec::Sim => {
            if args.baud == 0 {
                anyhow::bail!("--baud must be positive");
            }
            let mut config = hal_sim::sim_device::SimDeviceConfig {
                baud: args.baud,
                link,
                link_error_rate: error_rate,
                ..hal_sim::sim_device::SimDeviceConfig::paper()
            };
            sim(&mut config);
            let device = hal_sim::sim_device::SimDevice::new(config)
                .map_err(|e| anyhow::anyhow!("the simulated board: {e}"))?;
            Ok(Box::new(device) as Box<dyn Transport + Send>)
        }
        _ => port::open_with_link(&spec, args.baud, link),
    };
    let transport = match opened {
        Ok(t) => t as Box<dyn Transport>,
        Err(e @ PortError::Serial(SerialError::Missing { .. } | SerialError::Open { .. })) => {
            anyhow::bail!("{e}; {}", port::available_ports())
        }
        Err(e) => return Err(e.into()),
    };
    let mut client = Client::new(transport);
    client.set_timeout(Duration::from_millis(args.timeout_ms));
    client.resync(Duration::from_millis(20))?;
    Ok(client)
}
