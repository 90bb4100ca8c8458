// The firmware application, shared by the two images: `twinstack-fw.rs` (the board) and
// `twinstack-emu.rs` (QEMU, feature `emulator`) each `include!` it after their crate
// attributes, so that the two builds write two files with two names (see twinstack-fw.rs for
// what the application does). Not a crate of its own: no `main.rs` here, so cargo makes no
// binary of this directory.

#[cfg(target_os = "none")]
use defmt_rtt as _;

#[cfg(target_os = "none")]
#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    twinstack::hardware::safe_state::stop_on_panic(info)
}

#[cfg(target_os = "none")]
#[cortex_m_rt::exception]
unsafe fn HardFault(_frame: &cortex_m_rt::ExceptionFrame) -> ! {
    twinstack::hardware::safe_state::stop_on_fault()
}

#[cfg(target_os = "none")]
#[rtic::app(device = stm32f4xx_hal::pac, peripherals = true)]
mod app {
    use heapless::spsc::{Consumer, Producer, Queue};
    use stm32f4xx_hal::pac::{self, Interrupt};

    use twinstack::board::Hardware;
    use twinstack::control::Controller;
    #[cfg(feature = "emulator")]
    use twinstack::control_loop::SetpointQueue;
    use twinstack::control_loop::{ControlLoop, SETPOINT_QUEUE_LEN};
    #[cfg(feature = "dual-stage")]
    use twinstack::dual_stage::{
        CoarseSupervisor, DualStage, DualStageSettings, SupervisorSettings,
    };
    use twinstack::hardware::adc::SensorInput;
    use twinstack::hardware::clocks;
    #[cfg(all(feature = "dual-stage", not(feature = "emulator")))]
    use twinstack::hardware::coarse_stage::{
        BoardSwitches, CoarseTimer, LinearEncoder, MotorEncoder, StepOutput,
    };
    #[cfg(all(feature = "dual-stage", feature = "emulator"))]
    use twinstack::dual_stage::ideal_axis::{AxisEncoder, AxisSteps, AxisSwitches, IdealAxis};
    use twinstack::hardware::control_timer::ControlTimer;
    use twinstack::hardware::dac::InternalDac;
    use twinstack::hardware::param_flash;
    use twinstack::hardware::{pins, profile};
    use twinstack::hardware::safe_state;
    use twinstack::hardware::tick::{ControlTick, LoopLock};
    #[cfg(not(feature = "emulator"))]
    use twinstack::hardware::usart::DmaTx;
    #[cfg(feature = "emulator")]
    use twinstack::hardware::usart::UsartTx;
    use twinstack::hardware::usart::{self, UsartRx};
    use twinstack::hardware::watchdog::Watchdog;
    #[cfg(feature = "emulator")]
    use twinstack::config::param_store::ReadOnlyStorage;
    use twinstack::config::param_store::{self, ParamSource};
    use twinstack::command_handler::{CommandHandler, MAX_RESPONSE};
    #[cfg(not(feature = "emulator"))]
    use twinstack::hardware::ccm;
    use twinstack::hardware::tick::SRAM_SLOTS;
    use twinstack::services::recorder::SplitStore;
    use twinstack::services::telemetry::{
        FrameLink, TelemetryQueue, TelemetrySample, TELEMETRY_QUEUE_LEN,
    };

    /// Received bytes waiting for the command handler: 2 047 bytes, 6.8 ms of the line at 3
    /// Mbaud: the largest frame (1 575 bytes with its delimiter) whole, with 472 bytes to
    /// spare, while the command task is kept from draining the queue (the receive interrupt
    /// outranks it; in QEMU a burst from the host starves it until the burst ends). The
    /// streaming chapter has the analysis.
    const RX_QUEUE: usize = 2048;

    /// The parameter storage: flash sector 11 on the board; read-only in the emulator (QEMU
    /// does not model the flash interface).
    #[cfg(not(feature = "emulator"))]
    type Storage = param_flash::FlashStorage;
    #[cfg(feature = "emulator")]
    type Storage = ReadOnlyStorage<'static>;

    /// Where outgoing frames go: USART1 TX by DMA, double-buffered, on the board; polled TX
    /// in the emulator (QEMU models no DMA). Responses and telemetry alike.
    #[cfg(not(feature = "emulator"))]
    type Uplink = DmaTx;
    #[cfg(feature = "emulator")]
    type Uplink = UsartTx;

    /// A response frame the uplink could not take yet (both transmit buffers on the line):
    /// the command task keeps it here and reads no further request until it has gone.
    type Outbox = heapless::Vec<u8, MAX_RESPONSE>;

    /// The receive side of USART1 and the handler's byte queue.
    pub struct Receiver {
        rx: UsartRx,
        bytes: Producer<'static, u8, RX_QUEUE>,
    }

    impl Receiver {
        fn drain(&mut self) {
            let bytes = &mut self.bytes;
            // A full queue drops the byte: the frame it belongs to fails its CRC and is
            // NACKed; the decoder resynchronises at the next delimiter.
            self.rx.drain(|b| {
                let _ = bytes.enqueue(b);
            });
            rtic::pend(Interrupt::EXTI0);
        }
    }

    /// The coarse stage's peripherals on the board: TIM1 step bursts, TIM8 / TIM4 encoders,
    /// GPIO switches.
    #[cfg(all(feature = "dual-stage", not(feature = "emulator")))]
    type CoarsePeripherals = (StepOutput, MotorEncoder, LinearEncoder, BoardSwitches);
    /// In the emulator (QEMU models neither TIM1, TIM8 nor the GPIOs): the library's model of
    /// them behind the same traits ([`IdealAxis`]).
    #[cfg(all(feature = "dual-stage", feature = "emulator"))]
    type CoarsePeripherals = (
        AxisSteps<'static>,
        AxisEncoder<'static>,
        AxisEncoder<'static>,
        AxisSwitches<'static>,
    );

    /// Every how many control ticks the emulator pends the coarse task (QEMU's TIM3 update
    /// interrupt is unreliable, so the SysTick tick paces it); 0: never.
    #[cfg(all(feature = "dual-stage", feature = "emulator"))]
    static COARSE_EVERY: core::sync::atomic::AtomicU32 = core::sync::atomic::AtomicU32::new(0);

    /// Everything the coarse-stage task owns.
    #[cfg(feature = "dual-stage")]
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

    #[cfg(feature = "dual-stage")]
    impl CoarseStage {
        /// One coarse tick: the handler's pending command and the piezo's last measurement are
        /// taken in one short lock of the control tick, the supervisor runs (a refused burst
        /// keeps its steps for the next tick), then, in a second short lock, its fine setpoints
        /// and status go to the tick's ramp.
        fn run(&mut self, tick: &mut impl rtic::Mutex<T = ControlTick>) {
            #[cfg(not(feature = "emulator"))]
            self.timer.acknowledge();
            let Some(axis) = self.axis.as_mut() else {
                return;
            };
            let (steps, motor, linear, switches) = &mut self.io;
            // The handler's command and the piezo's measurement of the last fine tick (the
            // carriage estimate subtracts it from the linear encoder's).
            let (command, measured) = tick.lock(|t| t.control.coarse().take());
            if let Some(command) = command {
                // Refused now (the state changed since the handler's check): the status says
                // what the axis does instead.
                let _ = axis.command(command);
            }
            // The emulator has no piezo (QEMU's ADC reads 0): no measurement; the model's
            // piezo sits where its setpoint is.
            #[cfg(feature = "emulator")]
            let measured = {
                let _ = measured;
                None
            };
            let fine = axis.tick(steps, motor, linear, switches, measured);
            #[cfg(feature = "emulator")]
            self.model.set_piezo_pm(axis.dual().fine_to_pm(fine.to));
            let status = axis.status();
            tick.lock(|t| t.control.post_coarse(&fine, status));
        }
    }

    /// Without the `dual-stage` feature there is no coarse stage (TIM3 never starts).
    #[cfg(not(feature = "dual-stage"))]
    pub struct CoarseStage;

    #[cfg(not(feature = "dual-stage"))]
    impl CoarseStage {
        fn run(&mut self, _tick: &mut impl rtic::Mutex<T = ControlTick>) {}
    }

    #[shared]
    struct Shared {
        /// Shared by the TIM2 (board) and SysTick (emulator) bindings (only one ever fires)
        /// and, through [`LoopLock`], the command handler.
        tick: ControlTick,
        /// Shared by the USART1 and DMA2 stream 2 interrupts (same priority).
        receiver: Receiver,
        /// Shared by the command task (frames in) and, on the board, the DMA2 stream 7
        /// interrupt (the next buffer on the line).
        uplink: Uplink,
        /// The coarse task's state: one task runs it (TIM3 on the board, EXTI1 in the
        /// emulator; both bindings exist for RTIC, only one ever fires), so no lock.
        #[lock_free]
        coarse: CoarseStage,
    }

    #[local]
    struct Local {
        handler: CommandHandler<Storage>,
        bytes_in: Consumer<'static, u8, RX_QUEUE>,
        setpoints_in: Producer<'static, i16, SETPOINT_QUEUE_LEN>,
        telemetry_out: Consumer<'static, TelemetrySample, TELEMETRY_QUEUE_LEN>,
    }

    #[init(local = [
        #[cfg(feature = "emulator")]
        setpoint_queue: SetpointQueue = Queue::new(),
        rx_queue: Queue<u8, RX_QUEUE> = Queue::new(),
        telemetry_queue: TelemetryQueue = Queue::new(),
        record_buffer: [i16; SRAM_SLOTS] = [0; SRAM_SLOTS],
    ])]
    fn init(cx: init::Context) -> (Shared, Local) {
        let dp: pac::Peripherals = cx.device;
        // Why the MCU started (read and cleared before anything can reset it again).
        let reset = twinstack::hardware::reset_cause::ResetCause::take(&dp.RCC);
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
        // The host link's USART and DMA controller.
        #[cfg(not(feature = "feather"))]
        let (link_usart, link_dma) = (dp.USART1, dp.DMA2);
        #[cfg(feature = "feather")]
        let (link_usart, link_dma) = (dp.USART3, dp.DMA1);

        // The timer's rate is fixed before the controller is built, so the drive's slew limit
        // per tick matches the real period.
        #[cfg(not(feature = "emulator"))]
        let timer = ControlTimer::start(dp.TIM2, &rcc, &bus, record.control_rate_hz);
        #[cfg(feature = "emulator")]
        let timer = ControlTimer::start(cx.core.SYST, &bus, record.control_rate_hz);
        let rate = timer.rate_hz();
        let hardware = Hardware::driver_board(rate as f64);

        // The stored settings if they hold at the rate the timer runs, else the compiled-in
        // ones (bypass, no model), which hold at every rate the board runs.
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
        // The capture buffer: 38 KiB of SRAM, then 24 KiB of CCM RAM (QEMU 7.2's
        // netduinoplus2 models no CCM: the emulator has the SRAM part only).
        #[cfg(not(feature = "emulator"))]
        let Some(second_half) = ccm::capture_half() else {
            panic!("CCM buffer already taken");
        };
        #[cfg(feature = "emulator")]
        let second_half: &'static mut [i16; 0] = &mut [];
        let capture_buffer = SplitStore::new(cx.local.record_buffer, second_half as &mut [i16]);
        let mut control = ControlLoop::new(active, spare, rate, capture_buffer);
        let mut handler = CommandHandler::new(
            hardware,
            settings,
            defaults,
            #[cfg(not(feature = "emulator"))]
            param_flash::FlashStorage::new(),
            #[cfg(feature = "emulator")]
            ReadOnlyStorage(param_flash::record_window()),
        );
        handler.set_watchdog_reset(reset.is_watchdog());
        // The stored analog setpoint input starts before the first tick: stand-alone, no host.
        if !defaults {
            if let Some(prepared) = handler.boot_analog(stored_analog, &config) {
                control.start_analog(prepared);
            }
        }
        let (safe_left, safe_right) = control.safe_codes();
        safe_state::arm(safe_left, safe_right);

        let dac = InternalDac::new(dp.DAC, &rcc, (safe_left, safe_right));
        let adc = SensorInput::new(dp.ADC1, &dp.ADC_COMMON, &rcc);
        #[cfg(feature = "emulator")]
        let _ = link_dma;
        let (tx, rx) = usart::configure(
            link_usart,
            #[cfg(not(feature = "emulator"))]
            link_dma,
            &rcc,
            &bus,
        );
        let watchdog = Watchdog::start(dp.IWDG, &dp.DBGMCU);
        #[cfg(not(feature = "emulator"))]
        let uplink = DmaTx::new(tx, &rcc);
        #[cfg(feature = "emulator")]
        let uplink = tx;

        // The coarse stage (feature `dual-stage`): settings refused for this tick rate leave it
        // idle, not the board.
        #[cfg(feature = "dual-stage")]
        let mut coarse = {
            let dual_settings = DualStageSettings {
                fine_rate_hz: rate as f64,
                ..DualStageSettings::paper_stage()
            };
            #[cfg(not(feature = "emulator"))]
            let (mut io, timer) = {
                let coarse_rate = dual_settings.coarse_rate_hz as u32;
                let switches = pins.coarse.switches;
                let steps = StepOutput::new(dp.TIM1, pins.coarse.dir, &rcc, &bus, coarse_rate);
                let motor = MotorEncoder::new(dp.TIM8, &rcc);
                let linear = LinearEncoder::new(dp.TIM4, &rcc);
                let timer = CoarseTimer::start(dp.TIM3, &rcc, &bus, coarse_rate);
                ((steps, motor, linear, switches), timer)
            };
            #[cfg(feature = "emulator")]
            let model: &'static IdealAxis;
            #[cfg(feature = "emulator")]
            let mut io = {
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
                model = axis;
                (axis.step_dir(), axis.motor(), axis.linear(), axis.switches())
            };
            let supervisor = match dual_settings.build() {
                Ok(config) => {
                    use twinstack::board::QuadratureEncoder;
                    let dual = DualStage::new(config, 0, io.1.count(), io.2.count());
                    match SupervisorSettings::paper_stage()
                        .build(dual.config(), dual_settings.coarse_rate_hz)
                    {
                        Ok(c) => Some(CoarseSupervisor::new(dual, c)),
                        Err(e) => {
                            defmt::warn!("coarse stage idle: settings refused ({=str})", e.as_str());
                            None
                        }
                    }
                }
                Err(e) => {
                    defmt::warn!("coarse stage idle: settings refused ({=str})", e.as_str());
                    None
                }
            };
            #[cfg(feature = "emulator")]
            if let Some(s) = &supervisor {
                COARSE_EVERY.store(
                    s.dual().config().fine_ticks,
                    core::sync::atomic::Ordering::Relaxed,
                );
            }
            CoarseStage {
                axis: supervisor,
                io,
                #[cfg(feature = "emulator")]
                model,
                #[cfg(not(feature = "emulator"))]
                timer,
            }
        };
        #[cfg(not(feature = "dual-stage"))]
        let coarse = CoarseStage;

        #[cfg(feature = "dual-stage")]
        if let Some(axis) = coarse.axis.as_mut() {
            control.coarse().attach(axis.limits(), axis.status());
        }
        #[cfg(feature = "dual-stage")]
        let coarse = coarse;
        // The analog setpoint input (ADC2: PC3, the Feather's A3), after every port's split.
        let adc = adc.with_setpoint_input(
            twinstack::hardware::setpoint_adc::SetpointChannel::new(dp.ADC2, &rcc),
        );
        // The setpoint queue: in CCM RAM on the board (only the core touches it), in SRAM in
        // the emulator (QEMU models no CCM).
        #[cfg(not(feature = "emulator"))]
        let Some(setpoint_queue) = ccm::setpoint_queue() else {
            panic!("setpoint queue already taken");
        };
        #[cfg(feature = "emulator")]
        let setpoint_queue = cx.local.setpoint_queue;
        let (setpoints_in, setpoints) = setpoint_queue.split();
        let (bytes, bytes_in) = cx.local.rx_queue.split();
        let (telemetry, telemetry_out) = cx.local.telemetry_queue.split();
        defmt::info!(
            "{=str} ({=str}) up: sysclk {=u32} Hz, tick {=u32} Hz",
            super::IMAGE_NAME,
            profile::NAME,
            bus.sysclk_hz,
            rate
        );
        #[cfg(not(feature = "emulator"))]
        {
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
        (
            Shared {
                tick: ControlTick {
                    control,
                    adc,
                    dac,
                    timer,
                    watchdog,
                    setpoints,
                    telemetry,
                    triggers,
                },
                receiver: Receiver { rx, bytes },
                uplink,
                coarse,
            },
            Local {
                handler,
                bytes_in,
                setpoints_in,
                telemetry_out,
            },
        )
    }

    /// Sleeps between interrupts. The command task is woken by what gives it work: received
    /// bytes, a transmit buffer freed, the tick (a learning period's end, or the telemetry
    /// queue at a frame's worth of samples) — never once per tick.
    #[idle]
    fn idle(_: idle::Context) -> ! {
        loop {
            cortex_m::asm::wfi();
        }
    }

    /// The control tick on the board: TIM2 update. (One tick handler per image, so the
    /// inlined tick is in flash once.)
    #[cfg(not(feature = "emulator"))]
    #[task(binds = TIM2, priority = 3, shared = [tick])]
    fn tim2_tick(mut cx: tim2_tick::Context) {
        if cx.shared.tick.lock(|t| t.run()) {
            // A learning period ended, or a telemetry frame's worth is queued.
            rtic::pend(Interrupt::EXTI0);
        }
    }

    /// The control tick in the emulator: SysTick. With the coarse axis, every `fine_ticks`
    /// ticks it also pends the coarse task (EXTI1).
    #[cfg(feature = "emulator")]
    #[task(binds = SysTick, priority = 3, shared = [tick], local = [since_coarse: u32 = 0])]
    fn systick_tick(mut cx: systick_tick::Context) {
        if cx.shared.tick.lock(|t| t.run()) {
            // A learning period ended, or a telemetry frame's worth is queued.
            rtic::pend(Interrupt::EXTI0);
        }
        #[cfg(feature = "dual-stage")]
        {
            let every = COARSE_EVERY.load(core::sync::atomic::Ordering::Relaxed);
            *cx.local.since_coarse += 1;
            if every != 0 && *cx.local.since_coarse >= every {
                *cx.local.since_coarse = 0;
                rtic::pend(Interrupt::EXTI1);
            }
        }
        #[cfg(not(feature = "dual-stage"))]
        let _ = cx.local.since_coarse;
    }

    /// The coarse stage's tick on the board: TIM3 update (started only with the `dual-stage`
    /// feature).
    #[cfg(not(feature = "emulator"))]
    #[task(binds = TIM3, priority = 2, shared = [coarse, tick])]
    fn coarse_tick(cx: coarse_tick::Context) {
        let shared = cx.shared;
        let mut tick = shared.tick;
        shared.coarse.run(&mut tick);
    }

    /// The coarse stage's tick in the emulator: EXTI1, pended by the SysTick tick.
    #[cfg(feature = "emulator")]
    #[task(binds = EXTI1, priority = 2, shared = [coarse, tick])]
    fn coarse_pended(cx: coarse_pended::Context) {
        let shared = cx.shared;
        let mut tick = shared.tick;
        shared.coarse.run(&mut tick);
    }

    // The host link's interrupts: one binding each per board profile (the driver board's
    // USART1 and DMA2 streams 2/7, the Feather's USART3 and DMA1 streams 1/3), the same body.

    /// USART1: idle line (board) or a received byte (emulator).
    #[cfg(not(feature = "feather"))]
    #[task(binds = USART1, priority = 2, shared = [receiver])]
    fn usart1_rx(mut cx: usart1_rx::Context) {
        cx.shared.receiver.lock(|r| r.drain());
    }

    /// USART3 (the Feather's TX/RX pins): idle line (board) or a received byte (emulator).
    #[cfg(feature = "feather")]
    #[task(binds = USART3, priority = 2, shared = [receiver])]
    fn usart3_rx(mut cx: usart3_rx::Context) {
        cx.shared.receiver.lock(|r| r.drain());
    }

    /// DMA2 stream 2 (USART1 RX): half or full ring.
    #[cfg(not(feature = "feather"))]
    #[task(binds = DMA2_STREAM2, priority = 2, shared = [receiver])]
    fn dma_rx(mut cx: dma_rx::Context) {
        cx.shared.receiver.lock(|r| r.drain());
    }

    /// DMA1 stream 1 (USART3 RX, the Feather): half or full ring.
    #[cfg(feature = "feather")]
    #[task(binds = DMA1_STREAM1, priority = 2, shared = [receiver])]
    fn dma1_rx(mut cx: dma1_rx::Context) {
        cx.shared.receiver.lock(|r| r.drain());
    }

    /// DMA2 stream 7 (USART1 TX): a frame has left; the waiting one goes on the line, and the
    /// command task may fill the free buffer.
    #[cfg(all(not(feature = "emulator"), not(feature = "feather")))]
    #[task(binds = DMA2_STREAM7, priority = 2, shared = [uplink])]
    fn dma_tx(mut cx: dma_tx::Context) {
        cx.shared.uplink.lock(|u| u.on_complete());
        rtic::pend(Interrupt::EXTI0);
    }

    /// DMA1 stream 3 (USART3 TX, the Feather): as the driver board's DMA2 stream 7.
    #[cfg(all(not(feature = "emulator"), feature = "feather"))]
    #[task(binds = DMA1_STREAM3, priority = 2, shared = [uplink])]
    fn dma1_tx(mut cx: dma1_tx::Context) {
        cx.shared.uplink.lock(|u| u.on_complete());
        rtic::pend(Interrupt::EXTI0);
    }

    /// The command handler: queued bytes → frames → one response frame per request; then,
    /// while a transmit buffer is free, the telemetry frames that are due.
    /// A response waiting in the outbox goes first; while it cannot, no request is read
    /// (the bytes stay queued) and the task returns: the transfer-complete interrupt wakes it
    /// again. No spinning on the uplink.
    #[task(binds = EXTI0, priority = 1, shared = [tick, uplink], local = [handler, bytes_in, setpoints_in, telemetry_out, outbox: Outbox = Outbox::new()])]
    fn command(cx: command::Context) {
        let mut control = LoopLock(cx.shared.tick);
        let mut uplink = cx.shared.uplink;
        let local = cx.local;
        let mut blocked = !send(&mut uplink, local.outbox);
        while !blocked {
            let Some(b) = local.bytes_in.dequeue() else {
                break;
            };
            let Some(frame) = local.handler.push_byte(b, local.setpoints_in, &mut control) else {
                continue;
            };
            // Frames are at most MAX_RESPONSE bytes: the outbox holds one.
            let _ = local.outbox.extend_from_slice(frame);
            blocked = !send(&mut uplink, local.outbox);
            let (left, right) = rtic::Mutex::lock(&mut control, |c| c.safe_codes());
            safe_state::arm(left, right);
        }
        // Telemetry fills the line between responses; at most one frame waits for it.
        while !blocked
            && local.handler.telemetry_due(local.telemetry_out)
            && uplink.lock(|u| u.ready())
        {
            let Some(frame) = local.handler.pack_telemetry(local.telemetry_out) else {
                break;
            };
            let _ = local.outbox.extend_from_slice(frame);
            blocked = !send(&mut uplink, local.outbox);
        }
        // The learning's work at a period boundary (returns at once when there is none).
        let _ = local.handler.service_learning(&mut control);
    }

    /// Hands the outbox's frame (if any) to the uplink in one short lock and empties it;
    /// `false`, the frame kept, while both transmit buffers are taken.
    fn send(uplink: &mut impl rtic::Mutex<T = Uplink>, outbox: &mut Outbox) -> bool {
        if outbox.is_empty() || uplink.lock(|u| u.send_frame(outbox)) {
            outbox.clear();
            true
        } else {
            false
        }
    }
}
