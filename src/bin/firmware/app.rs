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
    use stm32f4xx_hal::gpio::GpioExt;
    use stm32f4xx_hal::pac::{self, Interrupt};

    use twinstack::board::Hardware;
    use twinstack::control::Controller;
    use twinstack::control_loop::{ControlLoop, SetpointQueue, SETPOINT_QUEUE_LEN};
    #[cfg(feature = "dual-stage")]
    use twinstack::dual_stage::{DualStage, DualStageSettings};
    use twinstack::hardware::adc::SensorInput;
    use twinstack::hardware::clocks;
    #[cfg(feature = "dual-stage")]
    use twinstack::hardware::coarse_stage::{CoarseTimer, LinearEncoder, MotorEncoder, StepOutput};
    use twinstack::hardware::control_timer::ControlTimer;
    use twinstack::hardware::dac::InternalDac;
    use twinstack::hardware::param_flash;
    use twinstack::hardware::safe_state;
    use twinstack::hardware::tick::{ControlTick, LoopLock};
    use twinstack::hardware::usart::{self, UsartRx, UsartTx};
    use twinstack::hardware::watchdog::Watchdog;
    #[cfg(feature = "emulator")]
    use twinstack::param_store::ReadOnlyStorage;
    use twinstack::param_store::{self, ParamSource};
    use twinstack::protocol::handler::CommandHandler;
    #[cfg(not(feature = "emulator"))]
    use twinstack::hardware::ccm;
    use twinstack::hardware::tick::HALF_SLOTS;
    use twinstack::recorder::SplitStore;

    /// Received bytes waiting for the command handler: 5 ms at 2 Mbaud, more than the longest
    /// response the handler sends (blocking) while bytes keep arriving.
    const RX_QUEUE: usize = 1024;

    /// The parameter storage: flash sector 11 on the board; read-only in the emulator (QEMU
    /// does not model the flash interface).
    #[cfg(not(feature = "emulator"))]
    type Storage = param_flash::FlashStorage;
    #[cfg(feature = "emulator")]
    type Storage = ReadOnlyStorage<'static>;

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

    /// Everything the coarse-stage task owns.
    #[cfg(feature = "dual-stage")]
    pub struct CoarseStage {
        /// `None` when the dual-stage settings are refused for this tick rate (logged at boot).
        dual: Option<DualStage>,
        steps: StepOutput,
        motor: MotorEncoder,
        linear: LinearEncoder,
        timer: CoarseTimer,
    }

    #[cfg(feature = "dual-stage")]
    impl CoarseStage {
        /// One coarse tick. A refused burst (the last one still running) keeps its steps for
        /// the next tick.
        fn run(&mut self) {
            self.timer.acknowledge();
            if let Some(dual) = self.dual.as_mut() {
                let _report =
                    dual.coarse_tick(&mut self.steps, &mut self.motor, &mut self.linear, None);
            }
        }
    }

    /// Without the `dual-stage` feature there is no coarse stage (TIM3 never starts).
    #[cfg(not(feature = "dual-stage"))]
    pub struct CoarseStage;

    #[cfg(not(feature = "dual-stage"))]
    impl CoarseStage {
        fn run(&mut self) {}
    }

    #[shared]
    struct Shared {
        /// Shared by the TIM2 (board) and SysTick (emulator) bindings (only one ever fires)
        /// and, through [`LoopLock`], the command handler.
        tick: ControlTick,
        /// Shared by the USART1 and DMA2 stream 2 interrupts (same priority).
        receiver: Receiver,
    }

    #[local]
    struct Local {
        handler: CommandHandler<Storage>,
        bytes_in: Consumer<'static, u8, RX_QUEUE>,
        setpoints_in: Producer<'static, i16, SETPOINT_QUEUE_LEN>,
        tx: UsartTx,
        coarse: CoarseStage,
    }

    #[init(local = [
        setpoint_queue: SetpointQueue = Queue::new(),
        rx_queue: Queue<u8, RX_QUEUE> = Queue::new(),
        record_buffer: [i16; HALF_SLOTS] = [0; HALF_SLOTS],
    ])]
    fn init(cx: init::Context) -> (Shared, Local) {
        let dp: pac::Peripherals = cx.device;
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
        let gpioa = dp.GPIOA.split(&mut rcc);
        let _dac_left = gpioa.pa4.into_analog();
        let _dac_right = gpioa.pa5.into_analog();
        let _sensor = gpioa.pa0.into_analog();
        let _tx_pin = gpioa.pa9.into_alternate::<7>();
        let _rx_pin = gpioa.pa10.into_alternate::<7>();

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
        let Ok((settings, config, defaults)) = param_store::boot(record, source, &hardware) else {
            panic!("compiled-in settings refused");
        };
        let (Some(active), Some(spare)) = (
            cortex_m::singleton!(ACTIVE: Controller = Controller::new(config)),
            cortex_m::singleton!(SPARE: Controller = Controller::new(config)),
        ) else {
            panic!("controllers already taken");
        };
        // The capture buffer: 64 KiB of SRAM, then the 64 KiB of CCM RAM (QEMU 7.2's
        // netduinoplus2 models no CCM: the emulator has the SRAM half only).
        #[cfg(not(feature = "emulator"))]
        let Some(second_half) = ccm::capture_half() else {
            panic!("CCM buffer already taken");
        };
        #[cfg(feature = "emulator")]
        let second_half: &'static mut [i16; 0] = &mut [];
        let capture_buffer = SplitStore::new(cx.local.record_buffer, second_half as &mut [i16]);
        let control = ControlLoop::new(active, spare, rate, capture_buffer);
        let handler = CommandHandler::new(
            hardware,
            settings,
            defaults,
            #[cfg(not(feature = "emulator"))]
            param_flash::FlashStorage::new(),
            #[cfg(feature = "emulator")]
            ReadOnlyStorage(param_flash::record_window()),
        );
        let (safe_left, safe_right) = control.safe_codes();
        safe_state::arm(safe_left, safe_right);

        let dac = InternalDac::new(dp.DAC, &rcc, (safe_left, safe_right));
        let adc = SensorInput::new(dp.ADC1, &dp.ADC_COMMON, &rcc);
        let (tx, rx) = usart::configure(
            dp.USART1,
            #[cfg(not(feature = "emulator"))]
            dp.DMA2,
            &rcc,
            &bus,
        );
        let watchdog = Watchdog::start(dp.IWDG, &dp.DBGMCU);

        // The coarse stage (feature `dual-stage`): settings refused for this tick rate leave it
        // idle, not the board.
        #[cfg(feature = "dual-stage")]
        let coarse = {
            let gpiob = dp.GPIOB.split(&mut rcc);
            let gpioc = dp.GPIOC.split(&mut rcc);
            let _step_pin = gpioa.pa8.into_alternate::<1>();
            let dir_pin = gpiob.pb0.into_push_pull_output();
            let _linear_a = gpiob.pb6.into_alternate::<2>();
            let _linear_b = gpiob.pb7.into_alternate::<2>();
            let _motor_a = gpioc.pc6.into_alternate::<3>();
            let _motor_b = gpioc.pc7.into_alternate::<3>();
            let dual_settings = DualStageSettings {
                fine_rate_hz: rate as f64,
                ..DualStageSettings::paper_stage()
            };
            let coarse_rate = dual_settings.coarse_rate_hz as u32;
            let steps = StepOutput::new(dp.TIM1, dir_pin, &rcc, &bus, coarse_rate);
            let mut motor = MotorEncoder::new(dp.TIM8, &rcc);
            let mut linear = LinearEncoder::new(dp.TIM4, &rcc);
            let dual = match dual_settings.build() {
                Ok(config) => {
                    use twinstack::board::QuadratureEncoder;
                    Some(DualStage::new(config, 0, motor.count(), linear.count()))
                }
                Err(e) => {
                    defmt::warn!("coarse stage idle: settings refused ({=str})", e.as_str());
                    None
                }
            };
            CoarseStage {
                dual,
                steps,
                motor,
                linear,
                timer: CoarseTimer::start(dp.TIM3, &rcc, &bus, coarse_rate),
            }
        };
        #[cfg(not(feature = "dual-stage"))]
        let coarse = CoarseStage;

        let (setpoints_in, setpoints) = cx.local.setpoint_queue.split();
        let (bytes, bytes_in) = cx.local.rx_queue.split();
        defmt::info!(
            "{=str} up: sysclk {=u32} Hz, tick {=u32} Hz",
            super::IMAGE_NAME,
            bus.sysclk_hz,
            rate
        );
        (
            Shared {
                tick: ControlTick {
                    control,
                    adc,
                    dac,
                    timer,
                    watchdog,
                    setpoints,
                },
                receiver: Receiver { rx, bytes },
            },
            Local {
                handler,
                bytes_in,
                setpoints_in,
                tx,
                coarse,
            },
        )
    }

    /// Sleeps between interrupts.
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
            // A learning period ended: the command task takes its errors.
            rtic::pend(Interrupt::EXTI0);
        }
    }

    /// The control tick in the emulator: SysTick.
    #[cfg(feature = "emulator")]
    #[task(binds = SysTick, priority = 3, shared = [tick])]
    fn systick_tick(mut cx: systick_tick::Context) {
        if cx.shared.tick.lock(|t| t.run()) {
            // A learning period ended: the command task takes its errors.
            rtic::pend(Interrupt::EXTI0);
        }
    }

    /// The coarse stage's tick: TIM3 update (started only with the `dual-stage` feature).
    #[task(binds = TIM3, priority = 2, local = [coarse])]
    fn coarse_tick(cx: coarse_tick::Context) {
        cx.local.coarse.run();
    }

    /// USART1: idle line (board) or a received byte (emulator).
    #[task(binds = USART1, priority = 2, shared = [receiver])]
    fn usart1_rx(mut cx: usart1_rx::Context) {
        cx.shared.receiver.lock(|r| r.drain());
    }

    /// DMA2 stream 2 (USART1 RX): half or full ring.
    #[task(binds = DMA2_STREAM2, priority = 2, shared = [receiver])]
    fn dma_rx(mut cx: dma_rx::Context) {
        cx.shared.receiver.lock(|r| r.drain());
    }

    /// The command handler: queued bytes → frames → one response frame per request.
    #[task(binds = EXTI0, priority = 1, shared = [tick], local = [handler, bytes_in, setpoints_in, tx])]
    fn command(cx: command::Context) {
        let mut control = LoopLock(cx.shared.tick);
        let local = cx.local;
        while let Some(b) = local.bytes_in.dequeue() {
            let Some(frame) = local.handler.push_byte(b, local.setpoints_in, &mut control) else {
                continue;
            };
            if local.tx.write_all(frame).is_err() {
                defmt::warn!("USART1 transmit timed out");
            }
            let (left, right) = rtic::Mutex::lock(&mut control, |c| c.safe_codes());
            safe_state::arm(left, right);
        }
        // The learning's work at a period boundary (returns at once when there is none).
        let _ = local.handler.service_learning(&mut control);
    }
}
