// The firmware's RTIC shell, shared by every image: each binary (`src/bin/twinstack-*.rs`)
// `include!`s this file and calls `firmware_app!` with its interrupt bindings, the only thing
// RTIC needs to know at compile time that differs between images. Everything the tasks do is
// in the library: [`twinstack::hardware::setup::setup`] brings the board up (one function per
// target, chosen by the library's features, one `Board` type), and each task's body is one
// library function. Not a crate of its own: no `main.rs` here, so cargo makes no binary of
// this directory.
//
// Bindings: `tick` (TIM2 on a board, SysTick in QEMU), `coarse` (TIM3 on a board, EXTI1 —
// pended by the tick — in QEMU; it never fires without `dual-stage`), `rx` and `rx_dma` (the
// link's USART and receive DMA stream), and, on a board, `uplink_done` (the transmit DMA
// stream). The command task is EXTI0 in every image (`setup::COMMAND_IRQ`), the services'
// task EXTI2 (`setup::SERVICES_IRQ`, pended by the tick once a batch of snapshots).

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

/// The RTIC application with this image's interrupt bindings.
#[cfg(target_os = "none")]
macro_rules! firmware_app {
    (
        tick = $tick:ident,
        coarse = $coarse:ident,
        rx = $rx:ident,
        rx_dma = $rx_dma:ident
        $(, uplink_done = $uplink_done:ident)? $(,)?
    ) => {
        #[rtic::app(device = stm32f4xx_hal::pac, peripherals = true)]
        mod app {
            use heapless::spsc::Queue;
            use twinstack::hardware::setup::{
                self, Board, CoarsePacer, CoarseStage, CommandSide, Outbox, Receiver, Statics,
                Uplink, RX_QUEUE,
            };
            use twinstack::hardware::tick::{ControlTick, ServiceSide, SRAM_SLOTS};
            use twinstack::services::telemetry::TelemetryQueue;

            #[shared]
            struct Shared {
                /// The control tick's resources; the command task reaches the loop through a
                /// short lock.
                tick: ControlTick,
                /// The services (recorder, telemetry's tap): their task and the command task
                /// share them; neither lock masks the tick.
                services: ServiceSide,
                /// Shared by the link's receive interrupts (same priority).
                receiver: Receiver,
                /// Shared by the command task (frames in) and, on a board, the transmit DMA
                /// stream's interrupt (the next buffer on the line).
                uplink: Uplink,
                /// The coarse task's state: one task runs it, so no lock.
                #[lock_free]
                coarse: CoarseStage,
            }

            #[local]
            struct Local {
                command: CommandSide,
                pacer: CoarsePacer,
            }

            #[init(local = [
                rx_queue: Queue<u8, RX_QUEUE> = Queue::new(),
                telemetry_queue: TelemetryQueue = Queue::new(),
                record_buffer: [i16; SRAM_SLOTS] = [0; SRAM_SLOTS],
            ])]
            fn init(cx: init::Context) -> (Shared, Local) {
                let statics = Statics {
                    rx_queue: cx.local.rx_queue,
                    telemetry_queue: cx.local.telemetry_queue,
                    record_buffer: cx.local.record_buffer,
                };
                let Board {
                    tick,
                    services,
                    receiver,
                    uplink,
                    coarse,
                    pacer,
                    command,
                } = setup::setup(cx.device, cx.core.SYST, statics, super::IMAGE_NAME);
                (
                    Shared {
                        tick,
                        services,
                        receiver,
                        uplink,
                        coarse,
                    },
                    Local { command, pacer },
                )
            }

            /// Sleeps between interrupts. The command task is woken by what gives it work:
            /// received bytes, a transmit buffer freed, the tick (a learning period's end),
            /// the services (the telemetry queue at a frame's worth of samples) — never once
            /// per tick.
            #[idle]
            fn idle(_: idle::Context) -> ! {
                loop {
                    cortex_m::asm::wfi();
                }
            }

            /// The control tick (one handler per image, so the inlined tick is in flash once).
            #[task(binds = $tick, priority = 3, shared = [tick], local = [pacer])]
            fn control_tick(mut cx: control_tick::Context) {
                setup::tick(&mut cx.shared.tick, cx.local.pacer);
            }

            /// The services below the tick: the snapshots of a batch of ticks served (the
            /// recorder, telemetry's tap). EXTI2, pended by the tick (`setup::SERVICES_IRQ`).
            #[task(binds = EXTI2, priority = 2, shared = [services])]
            fn services(mut cx: services::Context) {
                setup::services(&mut cx.shared.services);
            }

            /// The coarse stage's tick (`dual-stage`; never raised without it).
            #[task(binds = $coarse, priority = 2, shared = [coarse, tick])]
            fn coarse_tick(cx: coarse_tick::Context) {
                let shared = cx.shared;
                let mut tick = shared.tick;
                shared.coarse.run(&mut tick);
            }

            /// The link's USART: idle line (board) or a received byte (emulator).
            #[task(binds = $rx, priority = 2, shared = [receiver])]
            fn link_rx(mut cx: link_rx::Context) {
                cx.shared.receiver.lock(|r| r.drain());
            }

            /// The link's receive DMA stream: half or full ring.
            #[task(binds = $rx_dma, priority = 2, shared = [receiver])]
            fn link_rx_dma(mut cx: link_rx_dma::Context) {
                cx.shared.receiver.lock(|r| r.drain());
            }

            $(
                /// The link's transmit DMA stream: a frame has left; the waiting one goes on
                /// the line, and the command task may fill the free buffer.
                #[task(binds = $uplink_done, priority = 2, shared = [uplink])]
                fn uplink_done(mut cx: uplink_done::Context) {
                    setup::uplink_done(&mut cx.shared.uplink);
                }
            )?

            /// The command handler (EXTI0, a software interrupt: `setup::COMMAND_IRQ`).
            #[task(binds = EXTI0, priority = 1, shared = [tick, services, uplink], local = [command, outbox: Outbox = Outbox::new()])]
            fn command(mut cx: command::Context) {
                setup::command(
                    cx.shared.tick,
                    cx.shared.services,
                    &mut cx.shared.uplink,
                    cx.local.command,
                    cx.local.outbox,
                );
            }
        }
    };
}
