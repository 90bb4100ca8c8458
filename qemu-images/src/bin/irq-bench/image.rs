//! The image itself (built for the target only; see the crate docs in `main.rs`).

use cortex_m_semihosting::{debug, hprintln};
use defmt_rtt as _;

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    hprintln!("BENCH-PANIC {}", info);
    debug::exit(debug::EXIT_FAILURE);
    loop {
        cortex_m::asm::wfi();
    }
}

/// Called between scenarios: its name in QEMU's exec trace splits the trace.
#[inline(never)]
#[no_mangle]
pub extern "C" fn irq_bench_marker(n: u32) -> u32 {
    core::hint::black_box(n)
}

/// The control rate the bench runs at, Hz: 32 kHz, so that the tick budget admits the dearest
/// configuration with every feature beside it (about 3 800 cycles of its period's 5 250, with
/// room for a smaller share of the period). The cycles a tick takes do not depend on the rate.
pub const RATE_HZ: u32 = 32_000;

/// The scenarios' setpoints, Q1.15, one per tick (divider 1).
pub mod scenarios {
    use twinstack::protocol::messages::{WaveDecay, WaveShape, Waveform};
    use twinstack::sources::analog_input::{AnalogInputConfig, OnFault};
    use twinstack::sources::scan::{
        LissajousScan, RasterScan, ScanPattern, ScanRequest, SpiralScan, TriggerEdge,
    };
    use twinstack::sources::sequence::SequenceConfig;

    /// Ticks each scenario streams.
    pub const TICKS: u32 = 1500;

    /// A scenario: its name and the setpoint for tick `k`.
    pub struct Scenario {
        /// Printed before it runs.
        pub name: &'static str,
        /// Setpoint of tick `k`, Q1.15.
        pub setpoint: fn(u32) -> i16,
        /// Settings changes mid-stream: reload at tick 500, open loop at 800, closed loop at
        /// 1100.
        pub lifecycle: bool,
        /// The learning feedforward learns throughout (period 200 ticks, three cycles of the
        /// 750 Hz sine; the idle task runs its period-boundary service as the firmware's
        /// command task does): each tick reads a table entry and stores an error.
        pub learning: bool,
        /// Instead of streaming: a scan generated on the board with its pixel, line and frame
        /// outputs pulsing ([`RASTER`], [`LISSAJOUS`], [`SPIRAL`]), for `TICKS` ticks.
        pub scan: Option<ScanRequest>,
        /// Instead of streaming: the analog setpoint input as the source for `TICKS` ticks
        /// ([`ANALOG`]).
        pub analog: Option<AnalogInputConfig>,
        /// The external trigger input armed, and its rising edge driven by the image
        /// ([`twinstack::hardware::trigger_pins::EMULATED_INPUT`]) every [`TRIGGER_EVERY`]
        /// ticks (the input fires once per arming: it is armed again before each edge), with a
        /// capture armed on the first edge. With a scan, the scan waits for each edge (stopped
        /// and requested again between edges), so the edge's tick starts it (its approach
        /// from the setpoint in force); streamed, the edge (armed to start the stream) starts
        /// the running stream again.
        pub on_trigger: bool,
        /// Instead of streaming: the board's own waveform generator for `TICKS` ticks.
        pub waveform: Option<Waveform>,
        /// Instead of streaming: a TTL-stepped sequence over [`SEQUENCE_POSITIONS`] positions
        /// (the scenario's setpoints) queued before it is armed, advanced by the input's rising
        /// edge every [`SEQUENCE_EVERY`] ticks, for `TICKS` ticks: the edges come before the
        /// stage settles (counted early), and the last ones find the queue empty (missed).
        pub sequence: Option<SequenceConfig>,
        /// Instead of streaming: the coarse axis's ramp, as the dual-stage images' coarse task
        /// posts it (one ramp every [`COARSE_EVERY`] ticks, to the scenario's setpoint that
        /// many ticks on), for `TICKS` ticks; handed back to the stream at the end.
        pub coarse: bool,
    }

    /// The coarse scenario's axis: the paper stage's limits at its 5 kHz coarse rate (what the
    /// dual-stage images attach).
    pub const COARSE_LIMITS: twinstack::dual_stage::CoarseLimits =
        twinstack::dual_stage::CoarseLimits {
            travel_pm: (-1_000_000_000, 48_000_000_000),
            coarse: twinstack::dual_stage::MotionLimits {
                velocity: 6_000_000,
                acceleration: 60_000,
            },
            jog_acceleration: 60_000,
            coarse_rate_hz: 5_000.0,
        };

    /// Ticks between the coarse scenario's posts (the coarse task's period, 5 kHz, at a fine
    /// rate of 50 kHz).
    pub const COARSE_EVERY: u32 = 10;

    /// Ticks between the sequence scenario's edges.
    pub const SEQUENCE_EVERY: u32 = 30;

    /// Positions the sequence scenario queues: two fewer than its edges, so that the last
    /// edges find the queue empty and the next scenario finds it so too.
    pub const SEQUENCE_POSITIONS: u32 = TICKS / SEQUENCE_EVERY - 2;

    /// The sequence scenario's settings: a narrow window, settled after 5 ticks in it.
    pub const SEQUENCE: SequenceConfig = SequenceConfig {
        edge: TriggerEdge::Rising,
        window: 0.01,
        settle_ticks: 5,
    };

    /// Ticks between the trigger scenario's edges (the scan runs most of them).
    pub const TRIGGER_EVERY: u32 = 150;

    /// The analog scenario's input: scaled, low-pass filtered and walking to the input's
    /// value at 5 full scales a second, so every tick takes the valid path's dearest branch
    /// (scale, filter, the walk). QEMU's ADC2 converts nothing on the timer's trigger and
    /// reads 0, which the window (from 0) takes as valid.
    pub const ANALOG: AnalogInputConfig = AnalogInputConfig {
        gain: 2.0,
        offset: -1.0,
        corner_hz: Some(500.0),
        lost_below: 0.0,
        over_above: 1.0,
        on_fault: OnFault::Hold,
        rate: 5.0,
        start_at_boot: false,
    };

    /// The board's generator at its dearest: a table sine at 750 Hz, ±0.95, its amplitude
    /// decaying after the first cycle (nested minor loops, so the P–I memory moves on every
    /// reversal).
    pub const SINE_DECAYING: Waveform = Waveform {
        shape: WaveShape::Sine,
        offset: 0,
        amplitude: 31_129,
        frequency_mhz: 750_000,
        decay: Some(WaveDecay {
            hold_cycles: 1,
            keep: 62_259,
        }),
    };

    /// The board's generator beside the learning: a 200 Hz sine, ±0.95 (one learning period
    /// of 200 ticks a cycle at the bench's 40 kHz).
    pub const SINE_200HZ: Waveform = Waveform {
        shape: WaveShape::Sine,
        offset: 0,
        amplitude: 31_129,
        frequency_mhz: 200_000,
        decay: None,
    };

    /// `pattern` scanned until stopped, 4 ticks a pixel, started at once.
    const fn endless(pattern: ScanPattern) -> ScanRequest {
        ScanRequest {
            pattern,
            ticks_per_pixel: 4,
            frames: 0,
            on_trigger: false,
        }
    }

    /// The scan scenario's raster: 8 lines of 30 pixels, 4 ticks each, 40-tick turnarounds
    /// (160 ticks a line), ±0.8, until stopped.
    pub const RASTER: ScanRequest = endless(ScanPattern::Raster(RasterScan {
        lines: 8,
        pixels: 30,
        turn_ticks: 40,
        offset: 0.0,
        amplitude: 0.8,
        y_offset: 0.0,
        y_amplitude: 0.5,
    }));

    /// A Lissajous figure, 8 periods of x (200 Hz at the bench's 40 kHz) against 7 of y per
    /// frame, ±0.8: its two phases and a table sine a tick.
    pub const LISSAJOUS: ScanRequest = endless(ScanPattern::Lissajous(LissajousScan {
        frame_hz: 25.0,
        x_cycles: 8,
        y_cycles: 7,
        y_phase_deg: 30.0,
        offset: 0.0,
        amplitude: 0.8,
        y_offset: 0.0,
        y_amplitude: 0.5,
    }));

    /// A spiral out and in over 3 turns each way at 200 Hz, radius 0.8: its envelope, its
    /// phase and a table sine a tick.
    pub const SPIRAL: ScanRequest = endless(ScanPattern::Spiral(SpiralScan {
        turn_hz: 200.0,
        turns: 3,
        offset: 0.0,
        amplitude: 0.8,
        y_offset: 0.0,
    }));

    const FULL: i32 = 32767;

    fn triangle(k: u32) -> i16 {
        // ±0.95, reversing every 100 ticks.
        let a = (FULL * 95 / 100) as i64;
        let phase = (k % 200) as i64;
        let v = if phase < 100 {
            -a + 2 * a * phase / 100
        } else {
            a - 2 * a * (phase - 100) / 100
        };
        v as i16
    }

    fn sine_750hz(k: u32) -> i16 {
        // 750 Hz at the bench's rate (53.3 ticks a period); a parabolic sine (no libm needed).
        let period = super::RATE_HZ as f32 / 750.0;
        let x = (k as f32 / period) % 1.0; // 0…1
        let s = if x < 0.5 {
            16.0 * x * (0.5 - x)
        } else {
            -16.0 * (x - 0.5) * (1.0 - x)
        };
        (s * 0.95 * FULL as f32) as i16
    }

    fn steps(k: u32) -> i16 {
        if k % 2 == 0 {
            FULL as i16
        } else {
            -(FULL as i16)
        }
    }

    fn random(k: u32) -> i16 {
        let mut x = k.wrapping_mul(2_654_435_761).wrapping_add(0x9E37_79B9);
        x ^= x >> 15;
        x = x.wrapping_mul(0x2C1B_3C6D);
        x ^= x >> 12;
        (x >> 16) as i16
    }

    fn nested_loops(k: u32) -> i16 {
        // Reversals of shrinking amplitude about 0 (20 ticks apart), every 200 ticks ended by
        // a full-range jump: the P–I memory fills up and is wiped out at once.
        let cycle = k % 200;
        if cycle == 199 {
            return if (k / 200) % 2 == 0 {
                FULL as i16
            } else {
                -(FULL as i16)
            };
        }
        let level = (cycle / 20) as i32;
        let amplitude = FULL - level * (FULL / 10);
        if level % 2 == 0 {
            amplitude as i16
        } else {
            -amplitude as i16
        }
    }

    /// A streamed scenario.
    const fn streamed(
        name: &'static str,
        setpoint: fn(u32) -> i16,
        lifecycle: bool,
        learning: bool,
    ) -> Scenario {
        Scenario {
            name,
            setpoint,
            lifecycle,
            learning,
            scan: None,
            analog: None,
            on_trigger: false,
            waveform: None,
            sequence: None,
            coarse: false,
        }
    }

    /// A streamed scenario whose trigger input's edges start the (running) stream again.
    const fn streamed_on_trigger(name: &'static str, setpoint: fn(u32) -> i16) -> Scenario {
        Scenario {
            on_trigger: true,
            ..streamed(name, setpoint, false, false)
        }
    }

    /// A scan scenario (the stream's setpoint function unused).
    const fn scanned(name: &'static str, scan: ScanRequest, learning: bool) -> Scenario {
        Scenario {
            name,
            setpoint: triangle,
            lifecycle: false,
            learning,
            scan: Some(scan),
            analog: None,
            on_trigger: false,
            waveform: None,
            sequence: None,
            coarse: false,
        }
    }

    /// A scan started by the external trigger's edges, again and again (the stream's setpoint
    /// function unused).
    const fn on_trigger(name: &'static str, scan: ScanRequest, learning: bool) -> Scenario {
        Scenario {
            on_trigger: true,
            ..scanned(name, scan, learning)
        }
    }

    /// The board's waveform generator (the stream's setpoint function unused).
    const fn generated(name: &'static str, waveform: Waveform, learning: bool) -> Scenario {
        Scenario {
            name,
            setpoint: triangle,
            lifecycle: false,
            learning,
            scan: None,
            analog: None,
            on_trigger: false,
            waveform: Some(waveform),
            sequence: None,
            coarse: false,
        }
    }

    /// The analog input scenario (the stream's setpoint function unused).
    const fn analog(name: &'static str, input: AnalogInputConfig) -> Scenario {
        Scenario {
            name,
            setpoint: triangle,
            lifecycle: false,
            learning: false,
            scan: None,
            analog: Some(input),
            on_trigger: false,
            waveform: None,
            sequence: None,
            coarse: false,
        }
    }

    /// The TTL-stepped sequence scenario (the setpoints are its positions).
    const fn sequenced(name: &'static str, setpoint: fn(u32) -> i16) -> Scenario {
        Scenario {
            sequence: Some(SEQUENCE),
            ..streamed(name, setpoint, false, false)
        }
    }

    /// The coarse axis's ramp scenario (its ends are the setpoints').
    const fn coarse_ramp(name: &'static str, setpoint: fn(u32) -> i16) -> Scenario {
        Scenario {
            coarse: true,
            ..streamed(name, setpoint, false, false)
        }
    }

    /// Every scenario, in the order they run.
    pub const ALL: [Scenario; 19] = [
        streamed("triangle", triangle, false, false),
        streamed("sine-750Hz", sine_750hz, false, false),
        streamed("full-range-steps", steps, false, false),
        streamed("random", random, false, false),
        streamed("nested-loops", nested_loops, false, false),
        streamed("sine-750Hz-learning", sine_750hz, false, true),
        scanned("scan-raster-triggers", RASTER, false),
        scanned("scan-lissajous-triggers", LISSAJOUS, false),
        scanned("scan-spiral-triggers", SPIRAL, false),
        // The learning's use case: a periodic scan with the learned feedforward on.
        scanned("scan-raster-learning", RASTER, true),
        scanned("scan-spiral-learning", SPIRAL, true),
        // Every path: the tick on which the armed input's edge starts the spiral and fires a
        // capture, beside the learning.
        on_trigger("scan-spiral-on-trigger-learning", SPIRAL, true),
        analog("analog-input", ANALOG),
        // A camera stepping the stage: full-range steps, one a rising edge.
        sequenced("sequence-on-edges", steps),
        // The dual-stage images' source: the coarse task's ramp, a triangle's.
        coarse_ramp("coarse-ramp", triangle),
        // The board's own generator, as `twinstack waveform` plays it.
        generated("waveform-sine-decaying", SINE_DECAYING, false),
        generated("waveform-sine-learning", SINE_200HZ, true),
        // The edge's tick beside a stream: the stream started again, a capture fired.
        streamed_on_trigger("triangle-on-trigger", triangle),
        streamed("reload-and-mode-switches", triangle, true, false),
    ];
}

/// The configurations a user can load, as the bench measures them: the shipped sizes of each
/// model, and the largest of every part the tick budget ([`twinstack::config::tick_budget`]) counts, so
/// that its prediction is checked at both ends of each size.
pub mod configs {
    use twinstack::config::settings::{
        representative_bouc_wen, representative_duhem, representative_output_map,
        representative_pi, FeedbackSettings, Mode, Model, NotchDesign, PreviewDesign,
        SensorSettings, Settings,
    };
    use twinstack::models::creep::CreepParams;
    use twinstack::models::generalised_pi::{DeadZoneParams, GpiParams};

    /// How many configurations run.
    pub const COUNT: usize = 11;

    /// A named configuration.
    pub struct Config {
        /// Printed with the scenario.
        pub name: &'static str,
        /// The settings.
        pub settings: Settings,
    }

    fn closed(compensator: Model, observer: Model) -> Settings {
        Settings {
            compensator: Some(compensator),
            observer: Some(observer),
            sensor: Some(SensorSettings {
                displacement_at_zero: 0.0,
                displacement_at_full_scale: 70.0,
                drift_limit: Some(0.02),
            }),
            feedback: Some(FeedbackSettings::pi(0.2, 500.0, 0.1)),
            mode: Mode::ClosedLoop,
            ..Settings::default()
        }
    }

    /// `compensator` with the sensor and PI feedback and no observer (so no drift check: it
    /// compares the sensor with the observer's estimate), as `twinstack calibrate` loads a
    /// model at 100 kHz.
    fn compensator_only(compensator: Model) -> Settings {
        let mut settings = closed(compensator.clone(), compensator);
        settings.observer = None;
        if let Some(sensor) = settings.sensor.as_mut() {
            sensor.drift_limit = None;
        }
        settings
    }

    /// A generalised P–I of `n` operators with all 8 dead zones: with 17, the shape
    /// `twinstack calibrate` (and `identify --model auto`) fits by default (17 operators, four
    /// dead zones a side); with 32, the largest.
    fn gpi_with_eight_dead_zones(n: usize) -> Option<Model> {
        let Model::PrandtlIshlinskii(pi) = representative_pi(n).ok()? else {
            return None;
        };
        let dead_zones = DeadZoneParams::new(
            35.0,
            1.0,
            &[-28.0, -21.0, -14.0, -7.0, 7.0, 14.0, 21.0, 28.0],
            &[-0.05, -0.05, -0.05, -0.05, 0.05, 0.05, 0.1, 0.1],
        )
        .ok()?;
        Some(Model::GeneralisedPi(GpiParams { pi, dead_zones }))
    }

    /// Configuration `i` (`0 … COUNT`), built when it is needed (one at a time on the
    /// stack). `None` past the end or if a model is refused (it is not: the tests check the
    /// representative models).
    pub fn get(i: usize) -> Option<Config> {
        // Identified creep (from 10 ms): its modes take turns at the bench's rate, one a tick.
        let creep4 = || CreepParams::new(&[0.01, 0.1, 1.0, 10.0], &[0.02; 4]).ok();
        // Six modes from 1 ms (32 ticks, less than 20 updates of 6 ticks): every mode every
        // tick, the creep's dearest form.
        let creep6 = || CreepParams::new(&[0.001, 0.01, 0.1, 1.0, 10.0, 100.0], &[0.01; 6]).ok();
        Some(match i {
            0 => {
                let pi = representative_pi(16).ok()?;
                Config {
                    name: "inverse-pi16+pi16-observer+pi+drift",
                    settings: closed(pi.clone(), pi),
                }
            }
            1 => Config {
                name: "inverse-duhem+duhem-observer+pi+drift",
                settings: closed(representative_duhem(), representative_duhem()),
            },
            // What `twinstack calibrate` loads by default where the model family's generalised
            // P–I wins (as on the simulated lab stage): 17 operators, 8 dead zones, four creep
            // modes in series, as compensator and observer.
            2 => {
                let gpi = gpi_with_eight_dead_zones(17)?;
                Config {
                    name: "inverse-gpi17x8+creep4+gpi17x8-observer+pi+drift",
                    settings: Settings {
                        creep: Some(creep4()?),
                        ..closed(gpi.clone(), gpi)
                    },
                }
            }
            3 => Config {
                name: "inverse-bouc-wen+bouc-wen-observer+pi+drift",
                settings: closed(representative_bouc_wen(), representative_bouc_wen()),
            },
            // The largest P–I with the most creep modes.
            4 => {
                let pi = representative_pi(32).ok()?;
                Config {
                    name: "inverse-pi32+creep6+pi32-observer+pi+drift",
                    settings: Settings {
                        creep: Some(creep6()?),
                        ..closed(pi.clone(), pi)
                    },
                }
            }
            // The dearest configuration a user can load: the largest generalised P–I both
            // ways, six creep modes, PID feedback with the notch, input shaping, the preview.
            6 => {
                let gpi = gpi_with_eight_dead_zones(32)?;
                let mut settings = Settings {
                    creep: Some(creep6()?),
                    ..closed(gpi.clone(), gpi)
                };
                settings.feedback = Some(FeedbackSettings {
                    kd: 1e-5,
                    derivative_cutoff_hz: 5_000.0,
                    notch: Some(NotchDesign {
                        frequency_hz: 8_000.0,
                        q: 2.0,
                        depth: 0.05,
                    }),
                    ..FeedbackSettings::pi(0.2, 500.0, 0.1)
                });
                // And input shaping: the notch on the feedforward too.
                settings.shaping = Some(NotchDesign {
                    frequency_hz: 12_000.0,
                    q: 0.5,
                    depth: 0.02,
                });
                // And the preview: every setpoint shaped for the resonance.
                settings.preview = Some(PreviewDesign {
                    frequency_hz: 12_000.0,
                    damping: 0.02,
                });
                Config {
                    name: "inverse-gpi32x8+creep6+gpi32x8-observer+pid+notch+shaping+preview+drift",
                    settings,
                }
            }
            // What `twinstack calibrate --model pi` loads by default at 100 kHz (with telemetry
            // every eighth tick, as odd configurations run it): 17 operators,
            // the compensator only (the feedback acts on the sensor; no observer below the
            // tick, so the services serve their snapshots with nothing but the capture and
            // telemetry: their own base cost).
            5 => {
                let settings = compensator_only(representative_pi(17).ok()?);
                Config {
                    name: "inverse-pi17+pi",
                    settings,
                }
            }
            // What `twinstack calibrate` loads at 100 kHz where the model family's generalised
            // P–I + creep wins: the compensator only, as above.
            7 => {
                let gpi = gpi_with_eight_dead_zones(17)?;
                Config {
                    name: "inverse-gpi17x8+creep4+pi",
                    settings: Settings {
                        creep: Some(creep4()?),
                        ..compensator_only(gpi)
                    },
                }
            }
            // And Duhem + creep as the compensator only: the smallest floating-point
            // configuration with creep (the budget refuses it at 100 kHz; measured, to show how
            // far from the period).
            8 => Config {
                name: "inverse-duhem+creep4+pi",
                settings: Settings {
                    creep: Some(creep4()?),
                    ..compensator_only(representative_duhem())
                },
            },
            // And Bouc–Wen with an output map and creep as the compensator only, as
            // `calibrate` loads it where it wins: the budget refuses it at 100 kHz; measured,
            // to show how far from the period.
            9 => Config {
                name: "inverse-bouc-wen+map6+creep4+pi",
                settings: Settings {
                    creep: Some(creep4()?),
                    output_map: Some(representative_output_map()),
                    ..compensator_only(representative_bouc_wen())
                },
            },
            // The board's defaults (bypass, no model, the sensor the learning needs) through
            // every scenario: the interrupt's fixed part with each feature beside it — the
            // scans, the learning, the trigger input's edges, the capture and telemetry.
            10 => Config {
                name: "bypass-no-model",
                settings: Settings::default(),
            },
            _ => return None,
        })
    }
}

#[rtic::app(device = stm32f4xx_hal::pac, peripherals = true)]
mod app {
    use heapless::spsc::{Producer, Queue};
    use stm32f4xx_hal::gpio::GpioExt;

    use core::sync::atomic::Ordering;
    use twinstack::board::Hardware;
    use twinstack::command_handler::MAX_RESPONSE;
    use twinstack::command_handler::{CommandHandler, Locks};
    use twinstack::config::param_store::ReadOnlyStorage;
    use twinstack::config::settings::{Mode, Settings};
    use twinstack::config::tick_budget::{
        interrupt_cycles, interrupt_uses_fpu, observer_below_cycles, pipeline_cycles, Beside,
    };
    use twinstack::control::Controller;
    use twinstack::control_loop::{SetpointQueue, SETPOINT_QUEUE_LEN};
    use twinstack::dual_stage::{FineSetpoints, PreparedCoarse};
    use twinstack::hardware::adc::SensorInput;
    use twinstack::hardware::clocks;
    use twinstack::hardware::control_timer::ControlTimer;
    use twinstack::hardware::dac::InternalDac;
    use twinstack::hardware::setup::{self, CoarsePacer};
    use twinstack::hardware::tick::SRAM_SLOTS;
    use twinstack::hardware::tick::{BoardLocks, ControlTick, ServiceSide};
    use twinstack::hardware::trigger_pins::EMULATED_INPUT;
    use twinstack::hardware::watchdog::Watchdog;
    use twinstack::protocol::messages::{
        AnalogRequest, CaptureRequest, CaptureState, LearnRequest, RecordRequest, Request,
        Response, SequenceRequest, SetpointBatch, Signal, StreamControl, Trigger, MAX_BATCH,
        MAX_CAPTURE_CHUNK,
    };
    use twinstack::services::consumer::Services;
    use twinstack::services::learning::{LearnSettings, LearnState};
    use twinstack::services::recorder::SplitStore;
    use twinstack::services::snapshot::SnapshotRing;
    use twinstack::services::telemetry::{
        TelemetryPacker, TelemetryQueue, TelemetrySample, TELEMETRY_QUEUE_LEN,
    };
    use twinstack::sources::scan::ScanRequest;

    use cortex_m_semihosting::{debug, hprintln};

    use super::{configs, irq_bench_marker, scenarios, RATE_HZ};

    #[shared]
    struct Shared {
        tick: ControlTick,
        services: ServiceSide,
    }

    #[local]
    struct Local {
        handler: CommandHandler<ReadOnlyStorage<'static>>,
        setpoints_in: Producer<'static, i16, SETPOINT_QUEUE_LEN>,
        telemetry_out: heapless::spsc::Consumer<'static, TelemetrySample, TELEMETRY_QUEUE_LEN>,
    }

    #[init(local = [
        setpoint_queue: SetpointQueue = Queue::new(),
        telemetry_queue: TelemetryQueue = Queue::new(),
        snapshot_ring: SnapshotRing = Queue::new(),
        record_buffer: [i16; SRAM_SLOTS] = [0; SRAM_SLOTS],
    ])]
    fn init(cx: init::Context) -> (Shared, Local) {
        let dp = cx.device;
        let (mut rcc, bus) = clocks::configure(dp.RCC);
        let gpioa = dp.GPIOA.split(&mut rcc);
        let _dac_left = gpioa.pa4.into_analog();
        let _dac_right = gpioa.pa5.into_analog();
        let _sensor = gpioa.pa0.into_analog();
        let triggers = twinstack::hardware::trigger_pins::TriggerPins::new(
            gpioa.pa1.into_push_pull_output(),
            gpioa.pa2.into_push_pull_output(),
            gpioa.pa3.into_push_pull_output(),
            gpioa.pa6.into_pull_down_input(),
            gpioa.pa7.into_push_pull_output(),
        );
        let timer = ControlTimer::start(cx.core.SYST, &bus, RATE_HZ);
        let hardware = Hardware::driver_board(timer.rate_hz() as f64);
        let settings = Settings::default();
        let Ok(config) = settings.build(&hardware) else {
            panic!("defaults refused");
        };
        let (Some(active), Some(spare)) = (
            cortex_m::singleton!(ACTIVE: Controller = Controller::new(config)),
            cortex_m::singleton!(SPARE: Controller = Controller::new(config)),
        ) else {
            panic!("controllers already taken");
        };
        // QEMU 7.2's netduinoplus2 models no CCM RAM: the SRAM half only (the same code on
        // the tick: a split store whose second half is empty).
        let record = SplitStore::new(cx.local.record_buffer, &mut [] as &mut [i16]);
        // In its static, as the firmware's.
        let Some(control) = twinstack::hardware::tick::control_loop(active, spare, timer.rate_hz())
        else {
            panic!("control loop already taken");
        };
        let (safe_left, safe_right) = control.safe_codes();
        let dac = InternalDac::new(dp.DAC, &rcc, (safe_left, safe_right));
        // The analog setpoint input on ADC2, as the firmware's.
        let adc = SensorInput::new(dp.ADC1, &dp.ADC_COMMON, &rcc).with_setpoint_input(
            twinstack::hardware::setpoint_adc::SetpointChannel::new(dp.ADC2, &rcc),
        );
        let watchdog = Watchdog::start(dp.IWDG, &dp.DBGMCU);
        let handler = CommandHandler::new(hardware, settings, true, ReadOnlyStorage(&[]));
        let (setpoints_in, setpoints) = cx.local.setpoint_queue.split();
        let (telemetry, telemetry_out) = cx.local.telemetry_queue.split();
        let (snapshots, snapshots_out) = cx.local.snapshot_ring.split();
        (
            Shared {
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
                    services: Services::new(record),
                    snapshots: snapshots_out,
                    telemetry,
                },
            },
            Local {
                handler,
                setpoints_in,
                telemetry_out,
            },
        )
    }

    /// The control tick: the firmware's own body ([`setup::tick`]: the tick, then the command
    /// task pended when it has work, then the coarse stage's pacer), bound as the firmware's
    /// emulator image binds it.
    #[task(binds = SysTick, priority = 3, shared = [tick], local = [pacer: CoarsePacer = CoarsePacer])]
    fn systick_tick(mut cx: systick_tick::Context) {
        setup::tick(&mut cx.shared.tick, cx.local.pacer);
    }

    /// The services below the tick: the firmware's own body ([`setup::services`]), bound as
    /// the firmware binds it ([`setup::SERVICES_IRQ`], priority 2).
    #[task(binds = EXTI2, priority = 2, shared = [services])]
    fn services(mut cx: services::Context) {
        setup::services(&mut cx.shared.services);
    }

    /// What the tick pends ([`setup::COMMAND_IRQ`]): the firmware's command task. Here the
    /// idle task plays the host and the command task in turn, so the wake-up finds no work.
    #[task(binds = EXTI0, priority = 1)]
    fn command_woken(_: command_woken::Context) {}

    /// The capture's and telemetry's decimations the scenarios alternate: every tick (the
    /// dearest batch) and every eighth (a batch with one frame or sample and seven countdowns).
    /// The services' cost is affine in the frames and samples a batch holds, so these two
    /// bound every decimation between.
    const DECIMATIONS: [u16; 2] = [1, 8];

    /// The trigger I/O settings with the input armed for its rising edge (pulses of 2 ticks);
    /// the edge starts the stream if `start_stream`.
    fn arm_input(start_stream: bool) -> twinstack::sources::scan::TriggerConfig {
        twinstack::sources::scan::TriggerConfig {
            pulse_ticks: 2,
            input: twinstack::sources::scan::TriggerEdge::Rising,
            start_stream,
        }
    }

    /// The trigger I/O settings with the input disarmed (pulses of 2 ticks).
    fn disarm_input() -> twinstack::sources::scan::TriggerConfig {
        twinstack::sources::scan::TriggerConfig {
            input: twinstack::sources::scan::TriggerEdge::Off,
            ..arm_input(false)
        }
    }

    /// The host: requests through the command handler, one scenario after another.
    #[idle(shared = [tick, services], local = [handler, setpoints_in, telemetry_out, frame: [u8; MAX_RESPONSE] = [0; MAX_RESPONSE]])]
    fn idle(cx: idle::Context) -> ! {
        let handler = cx.local.handler;
        let producer = cx.local.setpoints_in;
        let samples = cx.local.telemetry_out;
        let frame = cx.local.frame;
        let mut lock = BoardLocks {
            tick: cx.shared.tick,
            services: cx.shared.services,
        };
        // Telemetry of all seven signals (the tap queues all seven whatever the mask), packed
        // into frames here between ticks; started again at each configuration, on every tick
        // (the tap's dearest; the handler would refuse this rate for the 2 Mbaud line, but
        // the services' cost per sample is what is measured) or every eighth (the most
        // snapshots a batch serves without a sample).
        let mut packer = TelemetryPacker::new();
        // The tick hands the services its snapshots from here on (as the handler has it do
        // before it starts telemetry).
        lock.lock(|c| c.listen(true));
        // A macro, not a closure: the learning's service borrows the handler and the lock too.
        macro_rules! ask {
            ($request:expr) => {
                handler.handle($request, producer, &mut lock)
            };
        }
        let hardware = Hardware::driver_board(RATE_HZ as f64);
        let mut seq = 0u16;
        let mut marker = 0u32;
        for i in 0..configs::COUNT {
            let Some(config) = configs::get(i) else {
                panic!("configuration refused");
            };
            // The budget's prediction for it, computed by the library on the target.
            match config.settings.build(&hardware) {
                Ok(c) => hprintln!(
                    "BUDGET {} {} {} {} {}",
                    config.name,
                    interrupt_cycles(&c),
                    observer_below_cycles(&c),
                    pipeline_cycles(&c, Beside::EVERY_FEATURE),
                    u8::from(interrupt_uses_fpu(&c))
                ),
                Err(e) => hprintln!("BUDGET-REFUSED {} {}", config.name, e),
            }
            // The load's own row: the ticks between it and the first scenario (the previous
            // configuration's last ticks, then this one's, the stream stopped).
            marker += 1;
            irq_bench_marker(marker);
            hprintln!("SCENARIO {}/load", config.name);
            // Telemetry started again at this configuration's decimation, inside the load's
            // row (charged at the services' worst), so that no scenario's row holds ticks of
            // another decimation.
            let telemetry_decimation = DECIMATIONS[i % 2];
            let Some(first) =
                lock.lock_services(|s| s.start_telemetry(0b111_1111, telemetry_decimation, 1))
            else {
                panic!("telemetry refused");
            };
            packer.start(0b111_1111, telemetry_decimation, first, RATE_HZ);
            expect_ack(ask!(Request::LoadParams(config.settings.clone())), "load");
            for (j, scenario) in scenarios::ALL.iter().enumerate() {
                // A fresh capture per scenario, of all seven signals (seven stores a frame, the
                // recorder's dearest), on every tick or every eighth in every other scenario.
                // Armed after the scenario's marker, and done within its first half, so that
                // no row holds ticks of another scenario's capture: the row is charged the
                // services as its `SERVICES` line says.
                let capture_decimation = DECIMATIONS[j % 2];
                let frames = scenarios::TICKS / 2 / u32::from(capture_decimation);
                // (In the trigger scenario, armed on the input's edge with a pre-trigger window:
                // the edge's tick fires it.)
                let (trigger, pre_trigger) = if scenario.on_trigger {
                    (Trigger::External, frames / 2)
                } else {
                    (Trigger::Now, 0)
                };
                marker += 1;
                irq_bench_marker(marker);
                hprintln!("SCENARIO {}/{}", config.name, scenario.name);
                hprintln!(
                    "SERVICES {} {} {}",
                    capture_decimation,
                    telemetry_decimation,
                    u8::from(pre_trigger > 0)
                );
                expect_ack(
                    ask!(Request::Capture(CaptureRequest {
                        signals: 0b111_1111,
                        samples: frames,
                        pre_trigger,
                        trigger,
                        decimation: capture_decimation,
                    })),
                    "capture",
                );
                if scenario.learning {
                    let learn = LearnSettings::for_period(200);
                    expect_ack(
                        ask!(Request::Learn(LearnRequest::Configure(learn))),
                        "learn configure",
                    );
                    expect_ack(
                        ask!(Request::Learn(LearnRequest::State(LearnState::Learning))),
                        "learn on",
                    );
                }
                let mut k = 0u32;
                let mut started = false;
                let mut changed = 0u8;
                // The trigger scenarios' cycle: the input armed (low), raised a few ticks later.
                let mut cycle = 0u32;
                let mut armed_at: Option<u32> = None;
                let mut next_post = 0u32;
                // The coarse scenario's task, prepared off the tick's lock.
                let coarse_task =
                    PreparedCoarse::new(scenarios::COARSE_LIMITS, Default::default(), RATE_HZ);
                if scenario.scan.is_some()
                    || scenario.analog.is_some()
                    || scenario.waveform.is_some()
                    || scenario.sequence.is_some()
                    || scenario.coarse
                {
                    // A source on the board (a scan, the analog input, the generator) runs
                    // TICKS ticks
                    // (counted by the status).
                    let t0 = match ask!(Request::Status) {
                        Response::Status(s) => s.ticks,
                        _ => 0,
                    };
                    if let Some(scan) = scenario.scan {
                        // Pulses of 2 ticks; the input disarmed (the trigger scenario arms it
                        // before each edge).
                        expect_ack(ask!(Request::Trigger(disarm_input())), "trigger");
                        if !scenario.on_trigger {
                            expect_ack(ask!(Request::Scan(scan)), "scan");
                        }
                    }
                    if let Some(input) = scenario.analog {
                        expect_ack(ask!(Request::Analog(AnalogRequest::Start(input))), "analog");
                    }
                    if let Some(waveform) = scenario.waveform {
                        expect_ack(ask!(Request::Waveform(waveform)), "waveform");
                    }
                    if let Some(sequence) = scenario.sequence {
                        // The positions queued (the stream stopped), then the sequence armed,
                        // the input low.
                        EMULATED_INPUT.store(false, Ordering::Relaxed);
                        let samples = (0..scenarios::SEQUENCE_POSITIONS)
                            .map(scenario.setpoint)
                            .collect();
                        expect_ack(
                            ask!(Request::Setpoints(SetpointBatch { seq, samples })),
                            "positions",
                        );
                        seq = seq.wrapping_add(1);
                        expect_ack(
                            ask!(Request::Sequence(SequenceRequest::Arm(sequence))),
                            "sequence",
                        );
                    }
                    loop {
                        let now = match ask!(Request::Status) {
                            Response::Status(s) => s.ticks,
                            _ => 0,
                        };
                        let elapsed = now.wrapping_sub(t0);
                        if elapsed >= scenarios::TICKS {
                            break;
                        }
                        if scenario.coarse && elapsed >= next_post {
                            // The coarse task's post: the period's ramp, to where the
                            // triangle is a period on (Q1.15 → Q2.30), with the status.
                            next_post = elapsed - elapsed % scenarios::COARSE_EVERY
                                + scenarios::COARSE_EVERY;
                            let fine = FineSetpoints {
                                from: 0,
                                to: i32::from((scenario.setpoint)(next_post)) << 15,
                                ticks: scenarios::COARSE_EVERY,
                            };
                            lock.lock(|c| {
                                // Attached at the first post (after the scenario's capture
                                // was armed: the handler charges the task from then on).
                                if !c.coarse().is_attached() {
                                    c.attach_coarse(&coarse_task);
                                }
                                let status = c.coarse().status();
                                c.post_coarse(&fine, status);
                            });
                        }
                        if scenario.sequence.is_some() {
                            // A rising edge every SEQUENCE_EVERY ticks.
                            let half = scenarios::SEQUENCE_EVERY / 2;
                            EMULATED_INPUT.store((elapsed / half) % 2 == 1, Ordering::Relaxed);
                        }
                        if let (true, Some(scan)) = (scenario.on_trigger, scenario.scan) {
                            if elapsed / scenarios::TRIGGER_EVERY >= cycle {
                                cycle = elapsed / scenarios::TRIGGER_EVERY + 1;
                                EMULATED_INPUT.store(false, Ordering::Relaxed);
                                expect_ack(ask!(Request::Stream(StreamControl::Stop)), "stop");
                                expect_ack(ask!(Request::Trigger(arm_input(false))), "arm");
                                let armed = ScanRequest {
                                    on_trigger: true,
                                    ..scan
                                };
                                expect_ack(ask!(Request::Scan(armed)), "scan on the trigger");
                                armed_at = Some(now);
                            } else if armed_at.is_some_and(|t| now.wrapping_sub(t) >= 4) {
                                EMULATED_INPUT.store(true, Ordering::Relaxed);
                                armed_at = None;
                            }
                        }
                        cortex_m::asm::wfi();
                        if scenario.learning {
                            let _ = handler.service_learning(&mut lock);
                        }
                        while packer.due(samples) {
                            if twinstack::protocol::messages::encode_telemetry(
                                &mut packer,
                                samples,
                                frame,
                            )
                            .is_none()
                            {
                                break;
                            }
                        }
                    }
                    if scenario.coarse {
                        lock.lock(|c| c.release_coarse());
                    }
                    expect_ack(ask!(Request::Stream(StreamControl::Stop)), "stop");
                    if scenario.on_trigger {
                        EMULATED_INPUT.store(false, Ordering::Relaxed);
                        expect_ack(ask!(Request::Trigger(disarm_input())), "trigger off");
                    }
                    if scenario.sequence.is_some() {
                        // Every position stepped to, and the edges after them missed: the
                        // scenario ran the sequence's every path (the bench reads the line).
                        if let Response::Sequence(st) =
                            ask!(Request::Sequence(SequenceRequest::Status))
                        {
                            hprintln!("SEQUENCE {} {} {}", st.steps, st.early, st.missed);
                            if st.steps != scenarios::SEQUENCE_POSITIONS || st.missed == 0 {
                                panic!("sequence: {} steps, {} missed", st.steps, st.missed);
                            }
                        }
                        EMULATED_INPUT.store(false, Ordering::Relaxed);
                        expect_ack(
                            ask!(Request::Sequence(SequenceRequest::Stop)),
                            "sequence stop",
                        );
                    }
                    if scenario.learning {
                        expect_ack(
                            ask!(Request::Learn(LearnRequest::State(LearnState::Off))),
                            "learn off",
                        );
                    }
                    continue;
                }
                loop {
                    // Fill the queue as far as the credits go.
                    if k < scenarios::TICKS {
                        let credits = match ask!(Request::Status) {
                            Response::Status(s) => s.credits as u32,
                            _ => 0,
                        };
                        let n = credits.min(MAX_BATCH as u32).min(scenarios::TICKS - k);
                        if n >= 32 || (n > 0 && k + n == scenarios::TICKS) {
                            let samples = (k..k + n).map(scenario.setpoint).collect();
                            expect_ack(
                                ask!(Request::Setpoints(SetpointBatch { seq, samples })),
                                "setpoints",
                            );
                            seq = seq.wrapping_add(1);
                            k += n;
                        }
                    }
                    if !started {
                        expect_ack(ask!(Request::Stream(StreamControl::Start)), "start");
                        started = true;
                    }
                    let (fill, ticks_played) = match ask!(Request::Status) {
                        Response::Status(s) => (s.queue_fill as u32, k - s.queue_fill as u32),
                        _ => (0, 0),
                    };
                    if scenario.on_trigger && started {
                        if ticks_played / scenarios::TRIGGER_EVERY >= cycle {
                            cycle = ticks_played / scenarios::TRIGGER_EVERY + 1;
                            EMULATED_INPUT.store(false, Ordering::Relaxed);
                            expect_ack(ask!(Request::Trigger(arm_input(true))), "arm");
                            armed_at = Some(ticks_played);
                        } else if armed_at.is_some_and(|t| ticks_played >= t + 4) {
                            EMULATED_INPUT.store(true, Ordering::Relaxed);
                            armed_at = None;
                        }
                    }
                    if scenario.lifecycle {
                        // The reload loads the first other configuration (the P–I and the
                        // Duhem ones reload each other; the rest reload the P–I one), so a
                        // lifecycle row holds ticks of two configurations.
                        if changed == 0 && ticks_played >= 500 {
                            if let Some(other) = configs::get(usize::from(i == 0)) {
                                expect_ack(ask!(Request::LoadParams(other.settings)), "reload");
                            }
                            changed = 1;
                        } else if changed == 1 && ticks_played >= 800 {
                            expect_ack(ask!(Request::Mode(Mode::OpenLoop)), "open loop");
                            changed = 2;
                        } else if changed == 2 && ticks_played >= 1100 {
                            expect_ack(ask!(Request::Mode(Mode::ClosedLoop)), "closed loop");
                            changed = 3;
                        }
                    }
                    if k >= scenarios::TICKS && fill == 0 {
                        break;
                    }
                    cortex_m::asm::wfi();
                    if scenario.learning {
                        let _ = handler.service_learning(&mut lock);
                    }
                    while packer.due(samples) {
                        if twinstack::protocol::messages::encode_telemetry(
                            &mut packer,
                            samples,
                            frame,
                        )
                        .is_none()
                        {
                            break;
                        }
                    }
                }
                // (The lifecycle scenario is each configuration's last; the next configuration
                // starts with its own load.)
                expect_ack(ask!(Request::Stream(StreamControl::Stop)), "stop");
                if scenario.on_trigger {
                    EMULATED_INPUT.store(false, Ordering::Relaxed);
                    expect_ack(ask!(Request::Trigger(disarm_input())), "trigger off");
                }
                if scenario.learning {
                    expect_ack(
                        ask!(Request::Learn(LearnRequest::State(LearnState::Off))),
                        "learn off",
                    );
                }
            }
        }
        // The host reading back what the board took, while the tick runs: a capture of all
        // seven signals at the largest chunk, then a v3 record. The bench measures every
        // critical section that holds the tick off; these copies are the handler's longest.
        hprintln!("READBACK");
        expect_ack(
            ask!(Request::Capture(CaptureRequest {
                signals: 0b111_1111,
                samples: 300,
                pre_trigger: 0,
                trigger: Trigger::Now,
                decimation: 1,
            })),
            "readback capture",
        );
        let window = loop {
            match ask!(Request::CaptureStatus) {
                Response::Capture(c) if c.state == CaptureState::Done => break c.window_slots,
                _ => cortex_m::asm::wfi(),
            }
        };
        let mut offset = 0;
        while offset < window {
            match ask!(Request::ReadCapture {
                offset,
                count: MAX_CAPTURE_CHUNK as u16,
            }) {
                Response::CaptureChunk { values, .. } if !values.is_empty() => {
                    offset += values.len() as u32;
                }
                r => {
                    hprintln!("BENCH-REFUSED read capture {:?}", r);
                    debug::exit(debug::EXIT_FAILURE);
                }
            }
        }
        expect_ack(
            ask!(Request::Record(RecordRequest {
                signal: Signal::Drive,
                count: 256,
                decimation: 1,
            })),
            "readback record",
        );
        // Read slower than the tick (every 24 ticks), as a host on a slow link does: each
        // chunk then copies full pieces, the record's longest sections.
        let mut offset = 0;
        while offset < 256 {
            match ask!(Request::ReadRecord { offset }) {
                Response::RecordChunk { values, .. } => offset += values.len() as u32,
                r => {
                    hprintln!("BENCH-REFUSED read record {:?}", r);
                    debug::exit(debug::EXIT_FAILURE);
                }
            }
            for _ in 0..24 {
                cortex_m::asm::wfi();
            }
        }
        hprintln!("READBACK done");
        irq_bench_marker(u32::MAX);
        let (used, room) = super::stack_high_water();
        hprintln!("STACK used {} room {}", used, room);
        hprintln!("DONE");
        debug::exit(debug::EXIT_SUCCESS);
        loop {
            cortex_m::asm::wfi();
        }
    }

    fn expect_ack(r: Response, what: &str) {
        if !matches!(r, Response::Ack { .. }) {
            hprintln!("BENCH-REFUSED {} {:?}", what, r);
            debug::exit(debug::EXIT_FAILURE);
        }
    }
}

/// The stack this run used and the room the static RAM leaves it, bytes: cortex-m-rt's
/// `paint-stack` filled `_stack_end .. _stack_start` with `0xCCCC_CCCC` at reset; the lowest
/// word changed since is the high-water mark.
#[cfg(target_os = "none")]
fn stack_high_water() -> (u32, u32) {
    extern "C" {
        static _stack_start: u32;
        static _stack_end: u32;
    }
    let top = core::ptr::addr_of!(_stack_start) as usize;
    let bottom = core::ptr::addr_of!(_stack_end) as usize;
    let mut low = top;
    let mut a = bottom;
    while a < top {
        // SAFETY: `_stack_end .. _stack_start` is RAM the linker gave the stack; reading a
        // word of it (volatile: below the stack pointer, the compiler knows nothing of it)
        // is sound.
        if unsafe { core::ptr::read_volatile(a as *const u32) } != 0xCCCC_CCCC {
            low = a;
            break;
        }
        a += 4;
    }
    ((top - low) as u32, (top - bottom) as u32)
}
