//! The firmware's start-up and task bodies, one per target, behind one type: [`setup`] brings
//! up the board the image is built for and returns a [`Board`], whatever the target; the RTIC
//! shells (`src/bin/twinstack-*.rs`, through `src/bin/firmware/app.rs`) only bind interrupts
//! to [`tick`], [`command`], [`Receiver::drain`], `uplink_done` (a board) and [`CoarseStage::run`].
//!
//! What differs per target is chosen here, at compile time, by type alias (static dispatch:
//! no trait object, no branch on the tick path):
//!
//! | | board (`twinstack-fw`, `-fw-dual`, `-feather`) | QEMU (`emulator` feature) |
//! |---|---|---|
//! | clock | HSE → PLL 168 MHz ([`super::clocks`]) | HSI 16 MHz |
//! | control tick | TIM2 update ([`super::control_timer`]) | SysTick |
//! | [`Uplink`] (frames out) | DMA, double-buffered ([`super::usart::DmaTx`]) | polled, bounded ([`super::usart::UsartTx`]) |
//! | [`Storage`] (parameter record) | flash sector 11 ([`super::param_flash::FlashStorage`]) | read-only |
//! | setpoint queue, capture | CCM RAM ([`super::ccm`]) | SRAM (QEMU models no CCM) |
//! | coarse axis (`dual-stage`) | TIM1 steps, TIM8/TIM4 encoders, TIM3 pace ([`super::coarse_stage`]) | [`IdealAxis`](crate::dual_stage::ideal_axis::IdealAxis), paced by the tick ([`CoarsePacer`]) |

use heapless::spsc::{Consumer, Producer, Queue};
use rtic_core::Mutex;
use stm32f4xx_hal::pac::{self, Interrupt};

use crate::board::Hardware;
use crate::command_handler::{start_services, CommandHandler, Locks, MAX_RESPONSE};
use crate::config::param_store::{self, ParamSource};
use crate::control::Controller;
use crate::control_loop::{SetpointQueue, SETPOINT_QUEUE_LEN};
use crate::services::consumer::Services;

use crate::services::recorder::SplitStore;
use crate::services::snapshot::SnapshotRing;
use crate::services::telemetry::{FrameLink, TelemetryQueue, TelemetrySample, TELEMETRY_QUEUE_LEN};

use super::adc::SensorInput;
use super::control_timer::ControlTimer;
use super::dac::InternalDac;
use super::tick::{BoardLocks, ControlTick, ServiceSide, SRAM_SLOTS};
use super::watchdog::Watchdog;
use super::{clocks, param_flash, pins, profile, safe_state, usart};

/// Received bytes waiting for the command handler: 2 047 bytes, 6.8 ms of the line at 3
/// Mbaud: the largest frame (1 575 bytes with its delimiter) whole, with 472 bytes to
/// spare, while the command task is kept from draining the queue (the receive interrupt
/// outranks it; in QEMU a burst from the host starves it until the burst ends). The
/// streaming chapter has the analysis.
pub const RX_QUEUE: usize = 2048;

/// The command task's interrupt (a software interrupt: nothing raises EXTI0 but [`pend`]).
/// Every image binds its command task here.
pub const COMMAND_IRQ: Interrupt = Interrupt::EXTI0;

/// The services' task's interrupt (a software interrupt: the tick pends it once a batch of
/// snapshots, [`crate::services::snapshot::BATCH`]). Every image binds its services task here.
pub const SERVICES_IRQ: Interrupt = Interrupt::EXTI2;

/// The parameter storage: flash sector 11 on a board.
#[cfg(not(feature = "emulator"))]
pub type Storage = param_flash::FlashStorage;
/// The parameter storage: read-only in the emulator (QEMU does not model the flash interface).
#[cfg(feature = "emulator")]
pub type Storage = crate::config::param_store::ReadOnlyStorage<'static>;

/// Where outgoing frames go, responses and telemetry alike: the link's TX by DMA,
/// double-buffered, on a board.
#[cfg(not(feature = "emulator"))]
pub type Uplink = usart::DmaTx;
/// Where outgoing frames go: polled TX in the emulator (QEMU models no DMA), each byte's wait
/// bounded ([`usart::UsartTx::write_all`]).
#[cfg(feature = "emulator")]
pub type Uplink = usart::UsartTx;

/// A response frame the uplink could not take yet (both transmit buffers on the line): the
/// command task keeps it here and reads no further request until it has gone.
pub type Outbox = heapless::Vec<u8, MAX_RESPONSE>;

/// The receive side of the link and the handler's byte queue.
pub struct Receiver {
    rx: usart::UsartRx,
    bytes: Producer<'static, u8, RX_QUEUE>,
}

impl Receiver {
    /// Moves the received bytes into the handler's queue and pends the command task. A full
    /// queue drops the byte: the frame it belongs to fails its CRC and is NACKed; the decoder
    /// resynchronises at the next delimiter.
    pub fn drain(&mut self) {
        let bytes = &mut self.bytes;
        self.rx.drain(|b| {
            let _ = bytes.enqueue(b);
        });
        pend(COMMAND_IRQ);
    }
}

/// Everything the command task owns.
pub struct CommandSide {
    handler: CommandHandler<Storage>,
    bytes_in: Consumer<'static, u8, RX_QUEUE>,
    setpoints_in: Producer<'static, i16, SETPOINT_QUEUE_LEN>,
    telemetry_out: Consumer<'static, TelemetrySample, TELEMETRY_QUEUE_LEN>,
}

/// The statics the RTIC shell places for [`setup`] (its `init`'s local resources: in `.bss`,
/// never on the stack).
pub struct Statics {
    /// The received bytes' queue.
    pub rx_queue: &'static mut Queue<u8, RX_QUEUE>,
    /// Telemetry's queue, from the services' tap to the command task's packer.
    pub telemetry_queue: &'static mut TelemetryQueue,
    /// The SRAM part of the capture buffer.
    pub record_buffer: &'static mut [i16; SRAM_SLOTS],
}

/// The board, brought up: what the RTIC shell hands to its tasks, the same type on every
/// target.
pub struct Board {
    /// The control interrupt's resources (shared with the command task through
    /// [`BoardLocks`]).
    pub tick: ControlTick,
    /// The services' resources (the recorder, telemetry's tap; shared with the command task
    /// through [`BoardLocks`]).
    pub services: ServiceSide,
    /// The link's receive side.
    pub receiver: Receiver,
    /// The link's transmit side.
    pub uplink: Uplink,
    /// The coarse axis's task state (empty without `dual-stage`).
    pub coarse: CoarseStage,
    /// What paces the coarse task from the tick (nothing on a board: TIM3 paces it).
    pub pacer: CoarsePacer,
    /// The command task's own state.
    pub command: CommandSide,
}

/// Pends `irq` (a software-raised task).
fn pend(irq: Interrupt) {
    cortex_m::peripheral::NVIC::pend(irq);
}

/// Brings the board up: clocks, pins, the parameter record (stored settings if they hold at
/// the tick rate, else the compiled-in bypass ones), both controllers, converters, link,
/// watchdog, the control timer (started last but one: the watchdog starts before it) and, with
/// `dual-stage`, the coarse axis. `syst` is SysTick (the emulator's tick; unused on a board).
/// `image` names the image in the start-up log.
///
/// Panics only on what cannot happen at a cold boot (a singleton taken twice, the compiled-in
/// settings refused); the panic handler drives the safe state.
///
/// The loop (8 KiB) is built in its static ([`super::tick::control_loop`]) and the queues
/// and the capture buffer are statics too, so the `Board` carries references to them, not
/// their bytes; inlined into the shell's `init`, so that what it does carry is not copied up
/// through a second frame.
#[inline(always)]
pub fn setup(
    dp: pac::Peripherals,
    syst: cortex_m::peripheral::SYST,
    statics: Statics,
    image: &str,
) -> Board {
    // Why the MCU started (read and cleared before anything can reset it again).
    let reset = super::reset_cause::ResetCause::take(&dp.RCC);
    if reset.is_watchdog() {
        defmt::warn!("started after a watchdog reset");
    } else {
        defmt::info!("reset cause: {=str}", reset.as_str());
    }
    let (record, source) = param_store::load_record(
        param_flash::record_window(),
        &Hardware::driver_board(Hardware::DEFAULT_CONTROL_RATE_HZ as f64),
    );
    match source {
        ParamSource::Stored => defmt::info!("settings loaded from flash"),
        ParamSource::Defaults(_) => {
            defmt::warn!(
                "parameter record refused ({=str}): defaults, bypass",
                source.as_str()
            )
        }
    }

    let (mut rcc, bus) = clocks::configure(dp.RCC);
    // The board profile's pins (driver board or Feather: `hardware::pins`).
    let pins = pins::configure(dp.GPIOA, dp.GPIOB, dp.GPIOC, &mut rcc);
    let triggers = pins.triggers;

    // The timer's rate is fixed before the controller is built, so the drive's slew limit per
    // tick matches the real period.
    let timer = start_timer(dp.TIM2, syst, &rcc, &bus, record.control_rate_hz);
    let rate = timer.rate_hz();
    let hardware = Hardware::driver_board(rate as f64);

    // The stored settings if they hold at the rate the timer runs, else the compiled-in ones
    // (bypass, no model), which hold at every rate the board runs.
    let stored_analog = record.analog;
    let Ok((settings, config, defaults)) = param_store::boot(record, source, &hardware) else {
        panic!("compiled-in settings refused");
    };
    let (Some(active), Some(spare)) = (
        cortex_m::singleton!(ACTIVE: Controller = Controller::new(config)),
        cortex_m::singleton!(SPARE: Controller = Controller::new(config)),
    ) else {
        panic!("controllers already taken");
    };
    let capture_buffer = SplitStore::new(statics.record_buffer, capture_second_part());
    // Built in its static: the loop (8 KiB) never sits on the boot's stack.
    let Some(control) = super::tick::control_loop(active, spare, rate) else {
        panic!("control loop already taken");
    };
    let mut handler = CommandHandler::new(hardware, settings, defaults, storage());
    handler.set_watchdog_reset(reset.is_watchdog());
    // The stored analog setpoint input starts before the first tick: stand-alone, no host.
    if !defaults {
        if let Some(prepared) = handler.boot_analog(stored_analog, &config) {
            control.start_analog(prepared);
        }
    }
    let (safe_left, safe_right) = control.safe_codes();
    safe_state::arm(safe_left, safe_right);
    // With a sensor the observer runs below the tick, from its first snapshot on.
    let mut services = Services::new(capture_buffer);
    start_services(&config, control, &mut services);

    let dac = InternalDac::new(dp.DAC, &rcc, (safe_left, safe_right));
    let adc = SensorInput::new(dp.ADC1, &dp.ADC_COMMON, &rcc);
    let (link_usart, link_dma) = profile::link_peripherals(dp.USART1, dp.USART3, dp.DMA1, dp.DMA2);
    let (uplink, rx) = start_link(link_usart, link_dma, &rcc, &bus);
    let watchdog = Watchdog::start(dp.IWDG, &dp.DBGMCU);

    // The coarse axis (`dual-stage`): settings refused for this tick rate leave it idle, not
    // the board.
    let coarse_io = CoarseIo {
        #[cfg(all(feature = "dual-stage", not(feature = "emulator")))]
        pins: pins.coarse,
        tim1: dp.TIM1,
        tim3: dp.TIM3,
        tim4: dp.TIM4,
        tim8: dp.TIM8,
    };
    let (coarse, pacer) = CoarseStage::start(coarse_io, &rcc, &bus, rate, control, &config);
    // The analog setpoint input (ADC2: PC3, the Feather's A3), after every port's split.
    let adc = adc.with_setpoint_input(super::setpoint_adc::SetpointChannel::new(dp.ADC2, &rcc));
    let Some(setpoint_queue) = setpoint_queue() else {
        panic!("setpoint queue already taken");
    };
    let (setpoints_in, setpoints) = setpoint_queue.split();
    let (bytes, bytes_in) = statics.rx_queue.split();
    let (telemetry, telemetry_out) = statics.telemetry_queue.split();
    let Some(snapshot_ring) = snapshot_ring() else {
        panic!("snapshot ring already taken");
    };
    let (snapshots, snapshots_out) = snapshot_ring.split();
    defmt::info!(
        "{=str} ({=str}) up: sysclk {=u32} Hz, tick {=u32} Hz",
        image,
        profile::NAME,
        bus.sysclk_hz,
        rate
    );
    log_pll();
    Board {
        tick: ControlTick {
            control,
            adc,
            dac,
            timer,
            watchdog,
            setpoints,
            snapshots,
            triggers,
        },
        services: ServiceSide {
            services,
            snapshots: snapshots_out,
            telemetry,
        },
        receiver: Receiver { rx, bytes },
        uplink,
        coarse,
        pacer,
        command: CommandSide {
            handler,
            bytes_in,
            setpoints_in,
            telemetry_out,
        },
    }
}

/// TIM2 at `rate_hz`, triggering the sensor's conversion (a board).
#[cfg(not(feature = "emulator"))]
fn start_timer(
    tim2: pac::TIM2,
    _syst: cortex_m::peripheral::SYST,
    rcc: &pac::RCC,
    bus: &clocks::BusClocks,
    rate_hz: u32,
) -> ControlTimer {
    ControlTimer::start(tim2, rcc, bus, rate_hz)
}

/// SysTick at `rate_hz` (the emulator: QEMU does not raise TIM2's update interrupt).
#[cfg(feature = "emulator")]
fn start_timer(
    _tim2: pac::TIM2,
    syst: cortex_m::peripheral::SYST,
    _rcc: &pac::RCC,
    bus: &clocks::BusClocks,
    rate_hz: u32,
) -> ControlTimer {
    ControlTimer::start(syst, bus, rate_hz)
}

/// The link: receive by DMA ring, transmit by DMA (a board).
#[cfg(not(feature = "emulator"))]
fn start_link(
    link: profile::LinkUsart,
    dma: profile::LinkDma,
    rcc: &pac::RCC,
    bus: &clocks::BusClocks,
) -> (Uplink, usart::UsartRx) {
    let (tx, rx) = usart::configure(link, dma, rcc, bus);
    (usart::DmaTx::new(tx, rcc), rx)
}

/// The link: receive by RXNE interrupt, polled transmit (the emulator: QEMU models no DMA).
#[cfg(feature = "emulator")]
fn start_link(
    link: profile::LinkUsart,
    _dma: profile::LinkDma,
    rcc: &pac::RCC,
    bus: &clocks::BusClocks,
) -> (Uplink, usart::UsartRx) {
    usart::configure(link, rcc, bus)
}

/// The parameter sector, writable (a board).
#[cfg(not(feature = "emulator"))]
fn storage() -> Storage {
    param_flash::FlashStorage::new()
}

/// The parameter sector, read-only (the emulator).
#[cfg(feature = "emulator")]
fn storage() -> Storage {
    crate::config::param_store::ReadOnlyStorage(param_flash::record_window())
}

/// The capture buffer's second part: 24 KiB of CCM RAM on a board.
#[cfg(not(feature = "emulator"))]
fn capture_second_part() -> &'static mut [i16] {
    let Some(half) = super::ccm::capture_half() else {
        panic!("CCM buffer already taken");
    };
    half
}

/// The capture buffer's second part: none in the emulator (QEMU 7.2's `netduinoplus2` models
/// no CCM: the SRAM part only).
#[cfg(feature = "emulator")]
fn capture_second_part() -> &'static mut [i16] {
    &mut []
}

/// The setpoint queue: in CCM RAM on a board (only the core touches it).
#[cfg(not(feature = "emulator"))]
fn setpoint_queue() -> Option<&'static mut SetpointQueue> {
    super::ccm::setpoint_queue()
}

/// The snapshot ring: in CCM RAM on a board (only the core touches it).
#[cfg(not(feature = "emulator"))]
fn snapshot_ring() -> Option<&'static mut SnapshotRing> {
    super::ccm::snapshot_ring()
}

/// The snapshot ring: in SRAM in the emulator (QEMU models no CCM); `Some` the first time.
#[cfg(feature = "emulator")]
fn snapshot_ring() -> Option<&'static mut SnapshotRing> {
    static TAKEN: core::sync::atomic::AtomicBool = core::sync::atomic::AtomicBool::new(false);
    static mut RING: SnapshotRing = heapless::spsc::Queue::new();
    // SAFETY: `RING` is reached only here.
    unsafe { super::ccm::take_once(&TAKEN, core::ptr::addr_of_mut!(RING)) }
}

/// The setpoint queue: in SRAM in the emulator (QEMU models no CCM); `Some` the first time.
#[cfg(feature = "emulator")]
fn setpoint_queue() -> Option<&'static mut SetpointQueue> {
    static TAKEN: core::sync::atomic::AtomicBool = core::sync::atomic::AtomicBool::new(false);
    static mut QUEUE: SetpointQueue = heapless::spsc::Queue::new();
    // SAFETY: `QUEUE` is reached only here.
    unsafe { super::ccm::take_once(&TAKEN, core::ptr::addr_of_mut!(QUEUE)) }
}

/// The PLL's settings, read back, in the start-up log (a board).
#[cfg(not(feature = "emulator"))]
fn log_pll() {
    let pll = clocks::Pll::read_back();
    defmt::info!(
        "PLL: HSE {=u32} Hz / M {=u32} × N {=u32} / P {=u32}; / Q {=u32} (48 MHz clock)",
        profile::HSE_HZ,
        pll.m,
        pll.n,
        pll.p,
        pll.q
    );
}

/// The emulator runs on HSI: no PLL to log.
#[cfg(feature = "emulator")]
fn log_pll() {}

/// The control tick's task body, for the image's tick binding (TIM2 on a board, SysTick in
/// the emulator): [`ControlTick::run`] in one lock; the services' task pended once a batch of
/// snapshots, the command task at a learning period's end; the coarse task paced where no
/// timer of its own paces it.
#[inline(always)]
pub fn tick(tick: &mut impl Mutex<T = ControlTick>, pacer: &mut CoarsePacer) {
    let wake = tick.lock(|t| t.run());
    if wake.services {
        pend(SERVICES_IRQ);
    }
    if wake.command {
        pend(COMMAND_IRQ);
    }
    pacer.step();
}

/// The services' task body ([`SERVICES_IRQ`], priority 2, below the tick): a batch of the
/// snapshots the tick pushed, served ([`ServiceSide::run_batch`]), the task pended again while
/// the ring holds more (it was held off for a few ticks: it catches up a batch a turn, so no
/// turn costs more than a batch); the command task pended when a telemetry frame's worth of
/// samples is queued (woken by that fill level, never per tick).
#[inline(always)]
pub fn services(services: &mut impl Mutex<T = ServiceSide>) {
    let (wake, more) = services.lock(|s| s.run_batch());
    if more {
        pend(SERVICES_IRQ);
    }
    if wake {
        pend(COMMAND_IRQ);
    }
}

/// The body of the uplink's transmit-complete interrupt (a board's TX DMA stream): the
/// waiting frame goes on the line, and the command task may fill the freed buffer.
#[cfg(not(feature = "emulator"))]
pub fn uplink_done(uplink: &mut impl Mutex<T = Uplink>) {
    uplink.lock(|u| u.on_complete());
    pend(COMMAND_IRQ);
}

/// The command task's body: queued bytes → frames → one response frame per request; then,
/// while a transmit buffer is free, the telemetry frames that are due; then the learning's
/// work at a period boundary. A response waiting in the `outbox` goes first; while it cannot,
/// no request is read (the bytes stay queued) and the task returns: the transmit-complete
/// interrupt wakes it again. No spinning on the uplink: every loop here ends with its queue.
pub fn command(
    tick: impl Mutex<T = ControlTick>,
    services: impl Mutex<T = ServiceSide>,
    uplink: &mut impl Mutex<T = Uplink>,
    side: &mut CommandSide,
    outbox: &mut Outbox,
) {
    let mut control = BoardLocks { tick, services };
    let mut blocked = !send(uplink, outbox);
    while !blocked {
        let Some(b) = side.bytes_in.dequeue() else {
            break;
        };
        let Some(frame) = side
            .handler
            .push_byte(b, &mut side.setpoints_in, &mut control)
        else {
            continue;
        };
        // Frames are at most MAX_RESPONSE bytes: the outbox holds one.
        let _ = outbox.extend_from_slice(frame);
        blocked = !send(uplink, outbox);
        let (left, right) = control.lock(|c| c.safe_codes());
        safe_state::arm(left, right);
    }
    // Telemetry fills the line between responses; at most one frame waits for it.
    while !blocked && side.handler.telemetry_due(&side.telemetry_out) && uplink.lock(|u| u.ready())
    {
        let Some(frame) = side.handler.pack_telemetry(&mut side.telemetry_out) else {
            break;
        };
        let _ = outbox.extend_from_slice(frame);
        blocked = !send(uplink, outbox);
    }
    // The learning's work at a period boundary (returns at once when there is none).
    let _ = side.handler.service_learning(&mut control);
}

/// Hands the outbox's frame (if any) to the uplink in one short lock and empties it; `false`,
/// the frame kept, while both transmit buffers are taken.
fn send(uplink: &mut impl Mutex<T = Uplink>, outbox: &mut Outbox) -> bool {
    if outbox.is_empty() || uplink.lock(|u| u.send_frame(outbox)) {
        outbox.clear();
        true
    } else {
        false
    }
}

/// The peripherals the coarse axis may take (the timers stay unused without `dual-stage`).
struct CoarseIo {
    #[cfg(all(feature = "dual-stage", not(feature = "emulator")))]
    pins: pins::CoarsePins,
    #[cfg_attr(
        not(all(feature = "dual-stage", not(feature = "emulator"))),
        allow(dead_code)
    )]
    tim1: pac::TIM1,
    #[cfg_attr(
        not(all(feature = "dual-stage", not(feature = "emulator"))),
        allow(dead_code)
    )]
    tim3: pac::TIM3,
    #[cfg_attr(
        not(all(feature = "dual-stage", not(feature = "emulator"))),
        allow(dead_code)
    )]
    tim4: pac::TIM4,
    #[cfg_attr(
        not(all(feature = "dual-stage", not(feature = "emulator"))),
        allow(dead_code)
    )]
    tim8: pac::TIM8,
}

#[cfg(feature = "dual-stage")]
pub use coarse::{CoarsePacer, CoarseStage};
#[cfg(not(feature = "dual-stage"))]
pub use no_coarse::{CoarsePacer, CoarseStage};

#[cfg(not(feature = "dual-stage"))]
mod no_coarse {
    use super::{CoarseIo, ControlTick, Mutex};
    use crate::control::ControlConfig;
    use crate::hardware::clocks::BusClocks;
    use crate::hardware::tick::BoardLoop;
    use stm32f4xx_hal::pac::RCC;

    /// Without `dual-stage` there is no coarse stage (TIM3 never starts; the task's binding
    /// never fires).
    pub struct CoarseStage;

    /// Nothing to pace.
    pub struct CoarsePacer;

    impl CoarsePacer {
        /// Nothing.
        #[inline(always)]
        pub fn step(&mut self) {}
    }

    impl CoarseStage {
        pub(super) fn start(
            _io: CoarseIo,
            _rcc: &RCC,
            _bus: &BusClocks,
            _rate: u32,
            _control: &mut BoardLoop,
            _config: &ControlConfig,
        ) -> (Self, CoarsePacer) {
            (Self, CoarsePacer)
        }

        /// Nothing.
        pub fn run(&mut self, _tick: &mut impl Mutex<T = ControlTick>) {}
    }
}

#[cfg(feature = "dual-stage")]
mod coarse {
    use super::{CoarseIo, ControlTick, Mutex};
    use crate::board::QuadratureEncoder;
    use crate::config::tick_budget::{check_with, Beside};
    use crate::control::ControlConfig;
    use crate::dual_stage::{
        CoarseStatus, CoarseSupervisor, CoarseTake, DualStage, DualStageSettings, FineSetpoints,
        LoopExchange, PreparedCoarse, SupervisorSettings,
    };
    use crate::hardware::clocks::BusClocks;
    use crate::hardware::tick::BoardLoop;
    use crate::sources::SetpointSource;
    use stm32f4xx_hal::pac::RCC;

    #[cfg(feature = "emulator")]
    use crate::dual_stage::ideal_axis::{AxisEncoder, AxisSteps, AxisSwitches, IdealAxis};
    #[cfg(not(feature = "emulator"))]
    use crate::hardware::coarse_stage::{
        BoardSwitches, CoarseTimer, LinearEncoder, MotorEncoder, StepOutput,
    };

    /// The coarse stage's peripherals on a board: TIM1 step bursts, TIM8 / TIM4 encoders,
    /// GPIO switches.
    #[cfg(not(feature = "emulator"))]
    type CoarsePeripherals = (StepOutput, MotorEncoder, LinearEncoder, BoardSwitches);
    /// In the emulator (QEMU models neither TIM1, TIM8 nor the GPIOs): the library's model of
    /// them behind the same traits ([`IdealAxis`]).
    #[cfg(feature = "emulator")]
    type CoarsePeripherals = (
        AxisSteps<'static>,
        AxisEncoder<'static>,
        AxisEncoder<'static>,
        AxisSwitches<'static>,
    );

    /// What paces the coarse task on a board: its own timer, TIM3; nothing from the tick.
    #[cfg(not(feature = "emulator"))]
    pub struct CoarsePacer;

    #[cfg(not(feature = "emulator"))]
    impl CoarsePacer {
        /// Nothing: TIM3 paces the coarse task.
        #[inline(always)]
        pub fn step(&mut self) {}
    }

    /// What paces the coarse task in the emulator (QEMU's TIM3 update interrupt is
    /// unreliable): the tick pends its interrupt ([`COARSE_IRQ`]) every `every` ticks; 0:
    /// never (settings refused).
    #[cfg(feature = "emulator")]
    pub struct CoarsePacer {
        every: u32,
        since: u32,
    }

    /// The coarse task's interrupt in the emulator, pended by the tick.
    #[cfg(feature = "emulator")]
    pub const COARSE_IRQ: stm32f4xx_hal::pac::Interrupt = stm32f4xx_hal::pac::Interrupt::EXTI1;

    #[cfg(feature = "emulator")]
    impl CoarsePacer {
        /// Counts one tick; pends the coarse task at every `every`-th.
        #[inline(always)]
        pub fn step(&mut self) {
            self.since += 1;
            if self.every != 0 && self.since >= self.every {
                self.since = 0;
                super::pend(COARSE_IRQ);
            }
        }
    }

    /// Everything the coarse-stage task owns.
    pub struct CoarseStage {
        /// `None` when the dual-stage settings are refused for this tick rate (logged at boot).
        axis: Option<CoarseSupervisor>,
        io: CoarsePeripherals,
        /// The model behind `io` (emulator).
        #[cfg(feature = "emulator")]
        model: &'static IdealAxis,
        #[cfg(not(feature = "emulator"))]
        timer: CoarseTimer,
    }

    impl CoarseStage {
        /// Starts the coarse axis at the paper stage's settings for the fine `rate`, and
        /// attaches its limits and status to the control loop, if `config` (the one in
        /// force) leaves the coarse task its share of each tick
        /// ([`crate::config::tick_budget::COARSE_TASK_CYCLES`]); else the axis stays idle.
        pub(super) fn start(
            io: CoarseIo,
            rcc: &RCC,
            bus: &BusClocks,
            rate: u32,
            control: &mut BoardLoop,
            config: &ControlConfig,
        ) -> (Self, CoarsePacer) {
            let dual_settings = DualStageSettings {
                fine_rate_hz: rate as f64,
                ..DualStageSettings::paper_stage()
            };
            #[cfg(not(feature = "emulator"))]
            let (mut io, timer) = {
                let coarse_rate = dual_settings.coarse_rate_hz as u32;
                let switches = io.pins.switches;
                let steps = StepOutput::new(io.tim1, io.pins.dir, rcc, bus, coarse_rate);
                let motor = MotorEncoder::new(io.tim8, rcc);
                let linear = LinearEncoder::new(io.tim4, rcc);
                let timer = CoarseTimer::start(io.tim3, rcc, bus, coarse_rate);
                ((steps, motor, linear, switches), timer)
            };
            #[cfg(feature = "emulator")]
            let (mut io, model) = {
                let _ = (io, rcc, bus);
                // The paper stage's screw: 0.3125 µm per microstep, 0.25 µm per motor count,
                // 5 nm per linear count; home switch 1 mm below the power-up position, limit
                // switches 2 mm below and 49 mm above (the travel is 50 mm from the home's −24).
                let Some(axis) = cortex_m::singleton!(AXIS: IdealAxis = IdealAxis::new(
                    312_500,
                    250_000,
                    5_000,
                    (-2_000_000_000, -1_000_000_000, 49_000_000_000),
                )) else {
                    panic!("coarse model already taken");
                };
                let axis: &'static IdealAxis = axis;
                (
                    (
                        axis.step_dir(),
                        axis.motor(),
                        axis.linear(),
                        axis.switches(),
                    ),
                    axis,
                )
            };
            let supervisor = match dual_settings.build() {
                Ok(config) => {
                    let dual = DualStage::new(config, 0, io.1.count(), io.2.count());
                    match SupervisorSettings::paper_stage()
                        .build(dual.config(), dual_settings.coarse_rate_hz)
                    {
                        Ok(c) => Some(CoarseSupervisor::new(dual, c)),
                        Err(e) => {
                            defmt::warn!(
                                "coarse stage idle: settings refused ({=str})",
                                e.as_str()
                            );
                            None
                        }
                    }
                }
                Err(e) => {
                    defmt::warn!("coarse stage idle: settings refused ({=str})", e.as_str());
                    None
                }
            };
            // The configuration in force leaves the coarse task its share of every tick, or
            // the axis stays idle (a load that fits beside it brings it back at the next boot).
            let supervisor = supervisor.filter(|axis| {
                let share = PreparedCoarse::new(axis.limits(), axis.status(), rate).share();
                let beside = Beside {
                    source: SetpointSource::Coarse,
                    coarse_task: share,
                    ..Beside::default()
                };
                let fits = check_with(config, rate as f64, beside).is_ok();
                if !fits {
                    defmt::warn!(
                        "coarse stage idle: the configuration in force leaves its task no {=u32} cycles a tick",
                        share
                    );
                }
                fits
            });
            #[cfg(feature = "emulator")]
            let pacer = CoarsePacer {
                every: supervisor
                    .as_ref()
                    .map_or(0, |s| s.dual().config().fine_ticks),
                since: 0,
            };
            #[cfg(not(feature = "emulator"))]
            let pacer = CoarsePacer;
            let mut stage = Self {
                axis: supervisor,
                io,
                #[cfg(feature = "emulator")]
                model,
                #[cfg(not(feature = "emulator"))]
                timer,
            };
            if let Some(axis) = stage.axis.as_mut() {
                control.attach_coarse(&PreparedCoarse::new(axis.limits(), axis.status(), rate));
            }
            (stage, pacer)
        }

        /// One coarse period ([`CoarseSupervisor::period`]): the handler's pending command and
        /// the piezo's last measurement taken in one short lock of the control tick, the
        /// supervisor's tick (a refused burst keeps its steps for the next tick), then, in a
        /// second short lock, its fine setpoints and status posted to the tick.
        pub fn run(&mut self, tick: &mut impl Mutex<T = ControlTick>) {
            #[cfg(not(feature = "emulator"))]
            self.timer.acknowledge();
            let Some(axis) = self.axis.as_mut() else {
                return;
            };
            let (steps, motor, linear, switches) = &mut self.io;
            // The emulator has no piezo (QEMU's ADC reads 0): no measurement; the model's
            // piezo sits where its setpoint is.
            let fine = axis.period(
                (steps, motor, linear, switches),
                &mut TickLock(tick),
                !cfg!(feature = "emulator"),
            );
            #[cfg(feature = "emulator")]
            self.model.set_piezo_pm(axis.dual().fine_to_pm(fine.to));
            #[cfg(not(feature = "emulator"))]
            let _ = fine;
        }
    }

    /// The coarse task's exchanges with the control loop, each in one short lock of the tick.
    struct TickLock<'a, M>(&'a mut M);

    impl<M: Mutex<T = ControlTick>> LoopExchange for TickLock<'_, M> {
        fn take(&mut self) -> CoarseTake {
            self.0.lock(|t| t.control.take_coarse())
        }

        fn post(&mut self, fine: &FineSetpoints, status: CoarseStatus) {
            self.0.lock(|t| t.control.post_coarse(fine, status));
        }
    }
}
