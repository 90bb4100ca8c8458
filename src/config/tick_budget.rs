//! The control pipeline's worst case per tick — the interrupt and what runs below it on its
//! snapshots — predicted from what a configuration runs, and the refusal of a configuration
//! that would not fit the control period.
//!
//! The interrupt's cost is set by what it runs ([`interrupt_cycles`]): the fixed part (RTIC's
//! entry and exit, the setpoint stream, the sensor, the feedback, the drive stage, the DAC
//! write, the watchdog) and the models, whose banks grow with their operators, dead zones and
//! creep modes (the compensator's). The observer and its drift check run below the tick
//! ([`observer_below_cycles`]).
//! Beside them, what the user turns on ([`Beside`]: the learning, a scan, the analog input,
//! the armed trigger input, and the services — the recorder and telemetry, which run below the
//! tick on its snapshots but take their share of its period while they listen).
//! [`pipeline_cycles`] and [`worst_case_cycles`] add these up from a built
//! [`ControlConfig`], asking each model for its own cost ([`Hysteresis::cycles`], declared
//! beside the model: [`crate::models::prandtl_ishlinskii::PI_PAIR_CYCLES`] and the like); [`Settings::build`](crate::config::settings::Settings::build) refuses
//! ([`Field::Workload`], [`Rule::TickOverrun`]) a configuration whose prediction exceeds
//! [`TICK_SHARE_PERCENT`] of the control period, so that no loaded configuration overruns the
//! interrupt at the board's rate, and the link, the command handler and the coarse axis keep the
//! rest of the CPU.
//!
//! The coefficients are **cycles at 5 flash wait states** (the ART cache assumed cold: every
//! taken branch waits the full 5), measured on the real image: the whole-interrupt bench
//! (`tests/irq_bench.rs`) traces every tick of each of its configurations in QEMU — no model,
//! the smallest and the largest of each model, every creep mode, the notch and the derivative —
//! and asserts, for each, that its worst tick stays under this prediction and that the
//! prediction is not loose by more than a stated factor. Between the measured sizes the prediction is linear in operators, dead
//! zones and modes, as the banks' loops are. A change that makes the tick dearer fails that
//! bench until the coefficients (here, and each model's beside it) are raised.
//!
//! ```
//! use twinstack::board::Hardware;
//! use twinstack::config::settings::{representative_gpi, Settings};
//! use twinstack::config::tick_budget::{available_cycles, worst_case_cycles};
//!
//! let s = Settings { compensator: Some(representative_gpi(16).unwrap()), ..Settings::default() };
//! let config = s.build(&Hardware::driver_board(50_000.0)).unwrap();
//! assert!(worst_case_cycles(&config) < available_cycles(50_000.0));
//! ```

use crate::control::{Compensator, ControlConfig, Observer};
use crate::models::Hysteresis;
use crate::refusal::{Field, Refusal, Rule};
use crate::sources::SetpointSource;

/// The core clock the board runs at, Hz.
pub const SYSCLK_HZ: u32 = 168_000_000;

/// The share of the control period the pipeline's predicted worst case (the interrupt and
/// the services below it) may take, percent. The prediction is cache-cold (5 wait states on
/// every taken branch), so no admitted tick overruns even then; the other 20 % of every
/// period are guaranteed to what runs below the pipeline — the link's DMA interrupts, the
/// command handler and the coarse axis — whatever configuration is loaded (on a warm cache
/// they get more: the whole-interrupt bench prints both, `cargo test --profile host-opt
/// --test irq_bench -- --nocapture`). At 100 kHz that leaves 1 344 cycles: what fits there
/// of each model, with or without its creep and its observer, `twinstack budget --rate
/// 100000` prints (with each one's highest admitted rate); `calibrate` and `identify
/// --tick-rate` size and pick only among what fits.
pub const TICK_SHARE_PERCENT: u32 = 80;

/// Everything in the interrupt that does not grow with a model: RTIC's entry and exit, the
/// stream, the trigger input and outputs, the sensor read, PI feedback,
/// the drive stage, the DAC write, the watchdog, the snapshot's push while the services
/// listen, the first tick after a reload or a mode
/// switch (its rebase, up to 50 instructions more), and the firmware's own binding of the
/// tick (`hardware::setup::tick`: the services' task pended once a batch, the command task
/// when the learning ends a period, which the whole-interrupt bench runs as the firmware
/// does). The recorder and telemetry are not in it: they run below the tick, charged as
/// [`ServicesLoad`] while they listen. What is off costs the tick no taken branch: the checks
/// that skip the learning, a scan, the other sources, the armed trigger input and the trigger
/// pulses fall through (`crate::rare` lays what they guard out of line), and what they guard
/// pays the two branches to it and back in its own charge.
pub const FIXED_CYCLES: u32 = 830;

/// What a Cortex-M4 pays, once per interrupt, to run floating-point code: the interrupted
/// code's floating-point registers (`S0`–`S15` and `FPSCR`, 17 words) saved when the handler
/// executes its first floating-point instruction (lazy stacking: the space is reserved on
/// entry) and restored by its return, about one cycle a word each way from SRAM. It is due
/// whenever the interrupted code has a floating-point context of its own — the services'
/// observer, the command task's settings — which the worst case assumes. The tick is charged
/// it where its compensator is a floating-point model
/// ([`crate::models::Hysteresis::uses_fpu`], [`interrupt_uses_fpu`]): the integer models and
/// the rest of the tick never touch the FPU. The services' task, which runs the observer's
/// models inline, pays it once a batch whatever the model, within its measured
/// [`SERVICES_BASE_CYCLES`] and [`SERVICES_EVERY_CYCLES`]. The whole-interrupt bench
/// (`tests/irq_bench.rs`) charges every invocation that executes a floating-point
/// instruction this much, and fails a tick that does in a configuration whose prediction does
/// not charge it.
pub const FP_CONTEXT_CYCLES: u32 = 34;

pub use crate::services::consumer::{
    ServicesLoad, CAPTURE_FRAME_CYCLES, FIRE_CYCLES, RELOAD_CYCLES, SERVE_CYCLES,
    SERVICES_BASE_CYCLES, SERVICES_EVERY_CYCLES, TELEMETRY_SAMPLE_CYCLES,
};
pub use crate::services::observer::OBSERVER_BELOW_CYCLES;

/// The feedback's derivative term.
pub const DERIVATIVE_CYCLES: u32 = 50;
/// The feedback's notch (one biquad); the feedforward's notch (input shaping,
/// [`ControlConfig::shaping`]) is charged the same.
pub const NOTCH_CYCLES: u32 = 95;
/// The preview ([`ControlConfig::preview`], [`crate::control::preview`]): the line's nine
/// setpoints moved along, eight multiply-adds, the rounding and the limits. Measured by the
/// whole-interrupt bench (`cargo test --profile host-opt --test irq_bench`, the dearest
/// configuration, which runs it): 87–88 cycles (5 WS) above the same configuration without
/// it, streamed and with every feature on; 95 keeps a margin.
pub const PREVIEW_CYCLES: u32 = 95;

/// The learning feedforward while it plays or learns ([`crate::services::learning`]): one table read,
/// one error store, the index flips at a period's end, and the branches out of the tick's
/// straight line to them and back (two places). Counted when the learning is switched on, and
/// at every load while it is on (the command handler checks both).
pub const LEARNING_CYCLES: u32 = 140;

/// A scan generated on the board while it runs ([`crate::sources::scan`]): the pattern's step, the
/// pixel, line and frame events, the trigger pulses, and the branches out of the tick's
/// straight line to them and back. Counted when a scan starts, and at every load while one
/// runs.
pub const SCAN_CYCLES: u32 = 165;

/// The analog setpoint input while it runs ([`crate::sources::analog_input`]): the second ADC's read,
/// the window's compares, the scaling's and the low-pass's multiplies, the walk. It replaces
/// the stream's step, which the fixed part already charges. Measured by the whole-interrupt
/// bench (`cargo test --profile host-opt --test irq_bench`, scenario `analog-input`: scaled,
/// filtered and walking on every tick): its worst tick is at most 14 cycles (5 WS) above the
/// configuration's worst streamed tick over the seven configurations; 32 keeps the fault
/// path's branches and a margin. Counted when the input starts, and at every load while it
/// runs.
pub const ANALOG_CYCLES: u32 = 32;

/// A TTL-stepped sequence while it is armed ([`crate::sources::sequence`]): the settle
/// window's compares, the edge, the queue's pop on it, the walk to the new position. It
/// replaces the stream's step, which the fixed part already charges; its edge's tick, a
/// full-range step away, also takes each model's dearest path on the walk's first ticks.
/// Measured by the whole-interrupt bench (`cargo test --profile host-opt --test irq_bench`,
/// scenario `sequence-on-edges`: full-range steps, a rising edge every 30 ticks, before the
/// stage settles, the last edges finding the queue empty) as the worst tick above the
/// configuration's prediction: 64 cycles (5 WS) for the Duhem configuration with its observer,
/// 33 for the P–I ones; 80 keeps a margin. Counted when a sequence is armed, and at every
/// load, trigger or learning start while it is.
pub const SEQUENCE_CYCLES: u32 = 80;

/// The coarse axis's ramp as the setpoint source (the dual-stage images,
/// [`crate::dual_stage::link`]): an add and a compare a tick, and the branches out of the
/// tick's straight line to them and back, in place of the stream's step, which the fixed part
/// charges. Measured by the whole-interrupt bench (`cargo test --profile host-opt --test
/// irq_bench`, scenario `coarse-ramp`: a ramp posted every 10 ticks, as the coarse task posts
/// one a coarse period): its worst tick is 29–66 cycles (5 WS) below the configuration's
/// worst streamed tick, and 70–170 below its prediction, over the ten configurations; that
/// also covers the emulator's pacing of the coarse task from the tick
/// (`hardware::setup::CoarsePacer`, a count and a compare). So nothing is charged above the
/// stream. Counted at every load, trigger or learning start
/// once the coarse axis owns the setpoint.
pub const COARSE_CYCLES: u32 = 0;

/// The dual-stage images' coarse task, one coarse period's tick as the firmware's task runs it
/// (the command the handler passed, then [`crate::dual_stage::CoarseSupervisor::tick`]: the
/// encoders, the trajectory's step, the centring, the step burst's plan, the supervision),
/// cycles at 5 flash wait states. It runs at priority 2, below the control interrupt, once a
/// coarse period (5 kHz on the paper stage), so the pipeline's share of the period pays it in
/// fine ticks' shares ([`coarse_task_share`]). The tick bench runs it on the library's model
/// of the axis (its encoders and switches latched before the tick, as the board's timers and
/// GPIOs hold them), homing and moving 10 mm and back at the stage's limits, and traces every
/// tick instruction by instruction, costed as the whole-interrupt bench costs the control tick
/// (`cargo test --profile host-opt --test tick_bench`, part `coarse-tick`; the tick-cost
/// chapter has the figures): it fails if the dearest tick, with the exception's entry and
/// return, exceeds this charge. The tick's arithmetic is 64-bit and saturating, but it calls
/// no library division: its divisors are settings, prepared with them
/// ([`crate::divisor::Divisor`], [`crate::dual_stage::PreparedLimits`]; a move's or a jog's
/// own limits are prepared by the command handler). The charge stays above the dearest traced
/// tick by up to half of it (the bench fails a looser one), for the paths the bench does not
/// run (a streamed reference's split filter, a fault's stop).
pub const COARSE_TASK_CYCLES: u32 = 3_600;

/// The coarse task's share of each fine tick, cycles at 5 WS: [`COARSE_TASK_CYCLES`] once
/// every `control_rate_hz / coarse_rate_hz` ticks, rounded up (0 for a coarse rate of 0).
///
/// ```
/// use twinstack::config::tick_budget::coarse_task_share;
/// // The paper stage's 5 kHz coarse task at 50 kHz and at 100 kHz.
/// assert_eq!(coarse_task_share(5_000, 50_000), 360);
/// assert_eq!(coarse_task_share(5_000, 100_000), 180);
/// ```
pub const fn coarse_task_share(coarse_rate_hz: u32, control_rate_hz: u32) -> u32 {
    if control_rate_hz == 0 {
        return COARSE_TASK_CYCLES;
    }
    // Saturating: an absurd coarse rate is charged the most, and refused.
    COARSE_TASK_CYCLES
        .saturating_mul(coarse_rate_hz)
        .div_ceil(control_rate_hz)
}

/// What `source` costs the tick above the stream's step, which the fixed part charges: the
/// scan's, the sequence's, the analog input's or the coarse ramp's charge; 0 for the stream.
pub const fn source_cycles(source: SetpointSource) -> u32 {
    match source {
        SetpointSource::Stream => 0,
        SetpointSource::Scan => SCAN_CYCLES,
        SetpointSource::Sequence => SEQUENCE_CYCLES,
        SetpointSource::Analog => ANALOG_CYCLES,
        SetpointSource::Coarse => COARSE_CYCLES,
    }
}

/// The tick on which the external trigger input's armed edge comes
/// ([`crate::sources::scan::TriggerConfig`]): the scan waiting for it starts from the setpoint
/// in force (its approach computed), or the stream starts, and a capture armed on it fires.
/// Charged while the input is armed, since an edge may come on any tick: measured by the
/// whole-interrupt bench (`cargo test --profile host-opt --test irq_bench`, scenarios
/// `scan-spiral-on-trigger-learning` and `triangle-on-trigger`, whose image drives the input so
/// that its edges start a spiral beside the learning, or the running stream, again and again,
/// a capture armed on the first) as the
/// worst such tick above the configuration's prediction: the stream started again beside it
/// (`triangle-on-trigger`) is the dearest, 147 cycles above it for the P–I 16 and P–I 17
/// configurations (5 WS), the spiral started by the edge is within the scan's charge; 170
/// keeps a margin. Counted when the input is armed, and at every load, scan, analog input or
/// learning start while it is.
pub const TRIGGER_CYCLES: u32 = 170;
/// Cycles the tick may take at `control_rate_hz`: [`TICK_SHARE_PERCENT`] of the period.
/// A rate that is not positive and finite leaves none.
pub fn available_cycles(control_rate_hz: f64) -> u32 {
    if !(control_rate_hz.is_finite() && control_rate_hz > 0.0) {
        return 0;
    }
    let period = SYSCLK_HZ as f64 / control_rate_hz;
    (period * TICK_SHARE_PERCENT as f64 / 100.0) as u32
}

/// The highest control rate at which a tick predicted to take `cycles` is admitted, Hz: the
/// rate whose [`available_cycles`] are `cycles` (at most; a hair below the exact quotient, so
/// that the rate returned is admitted). Zero cycles: infinite.
///
/// ```
/// use twinstack::config::tick_budget::{available_cycles, highest_rate_hz};
///
/// // 80 % of a 100 kHz period.
/// let rate = highest_rate_hz(1_344);
/// assert!((rate - 100_000.0).abs() < 0.01 && available_cycles(rate) >= 1_344);
/// assert!(available_cycles(rate * 1.000_01) < 1_344);
/// ```
pub fn highest_rate_hz(cycles: u32) -> f64 {
    if cycles == 0 {
        return f64::INFINITY;
    }
    let exact = SYSCLK_HZ as f64 * TICK_SHARE_PERCENT as f64 / 100.0 / cycles as f64;
    exact * (1.0 - 1e-12)
}

/// The predicted worst case of the control interrupt itself running `config`, cycles at 5
/// flash wait states: the fixed part, the compensator (each model declares its own cost)
/// with its creep in series, the feedback's derivative and notch, input shaping, the preview. The observer
/// runs below the tick ([`observer_below_cycles`]).
pub fn interrupt_cycles(config: &ControlConfig) -> u32 {
    let mut cycles = FIXED_CYCLES + config.compensator.cycles();
    if interrupt_uses_fpu(config) {
        cycles += FP_CONTEXT_CYCLES;
    }
    if let (Some(creep), false) = (
        &config.creep,
        matches!(config.compensator, Compensator::None),
    ) {
        cycles += creep.cycles();
    }
    if let Some(feedback) = &config.feedback {
        if feedback.derivative.is_some() {
            cycles += DERIVATIVE_CYCLES;
        }
        if feedback.notch.is_some() {
            cycles += NOTCH_CYCLES;
        }
    }
    // The feedforward's notch (input shaping) is the same biquad as the feedback's.
    if config.shaping.is_some() {
        cycles += NOTCH_CYCLES;
    }
    if config.preview.is_some() {
        cycles += PREVIEW_CYCLES;
    }
    cycles
}

/// Whether the control interrupt running `config` executes floating-point instructions: its
/// compensator is a floating-point model ([`crate::models::Hysteresis::uses_fpu`]). Nothing
/// else in the tick does.
pub fn interrupt_uses_fpu(config: &ControlConfig) -> bool {
    config.compensator.uses_fpu()
}

/// What `config`'s observer costs the services a snapshot below the tick: its model, its
/// creep and the drift check ([`OBSERVER_BELOW_CYCLES`]); 0 where it has none.
pub fn observer_below_cycles(config: &ControlConfig) -> u32 {
    if matches!(config.observer, Observer::None) {
        return 0;
    }
    config.observer.cycles()
        + config.creep.as_ref().map_or(0, |c| c.cycles())
        + OBSERVER_BELOW_CYCLES
}

/// The whole pipeline's predicted worst case per tick running `config` with `beside`, cycles
/// at 5 flash wait states: the interrupt ([`interrupt_cycles`]) and what runs beside it
/// ([`Beside::cycles`]), the services charged with the configuration's observer (and their
/// base share once, whatever makes them listen).
pub fn pipeline_cycles(config: &ControlConfig, beside: Beside) -> u32 {
    let beside = Beside {
        services: beside.services.observing(observer_below_cycles(config)),
        ..beside
    };
    interrupt_cycles(config) + beside.cycles()
}

/// The predicted worst case per tick of `config` alone, cycles at 5 flash wait states: the
/// interrupt and, where it has an observer, the services' share serving it
/// ([`pipeline_cycles`] with nothing beside).
pub fn worst_case_cycles(config: &ControlConfig) -> u32 {
    pipeline_cycles(config, Beside::default())
}

/// `Ok(())` if `config` fits the tick at `control_rate_hz`, else a [`Rule::TickOverrun`]
/// refusal of [`Field::Workload`] with the cycles it needs and the cycles the rate leaves.
pub fn check(config: &ControlConfig, control_rate_hz: f64) -> Result<(), Refusal> {
    check_with(config, control_rate_hz, Beside::default())
}

/// What runs beside the configuration and costs the tick: the learning feedforward, the
/// setpoint source (a scan, a sequence, the analog input, the coarse ramp), the armed trigger
/// input, the services (recorder, telemetry).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Beside {
    /// The learning feedforward plays (learning or frozen).
    pub learning: bool,
    /// The setpoint source in force ([`source_cycles`]; a scan waiting for its trigger counts
    /// as running).
    pub source: SetpointSource,
    /// The coarse task's share of each tick (the dual-stage images, while the coarse axis is
    /// attached: [`coarse_task_share`]), cycles; 0 elsewhere.
    pub coarse_task: u32,
    /// The external trigger input is armed: its edge's tick may come on any tick.
    pub trigger: bool,
    /// What the services run (a capture or a record, telemetry): while anything does, the
    /// tick pushes its snapshot and the services' task serves it.
    pub services: ServicesLoad,
}

impl Beside {
    /// Everything that can run beside a configuration at once: the learning, a scan (the
    /// dearest source: [`source_cycles`]), the armed trigger input, a capture and telemetry
    /// on every tick (in an image without a coarse axis: the dual-stage images add the coarse
    /// task's share, [`coarse_task_share`]).
    pub const EVERY_FEATURE: Self = Self {
        learning: true,
        source: SetpointSource::Scan,
        coarse_task: 0,
        trigger: true,
        services: ServicesLoad::WORST,
    };

    /// Their cost, cycles.
    pub fn cycles(&self) -> u32 {
        u32::from(self.learning) * LEARNING_CYCLES
            + source_cycles(self.source)
            + self.coarse_task
            + u32::from(self.trigger) * TRIGGER_CYCLES
            + self.services.cycles()
    }
}

/// [`check`], with what runs beside the configuration added.
pub fn check_with(
    config: &ControlConfig,
    control_rate_hz: f64,
    beside: Beside,
) -> Result<(), Refusal> {
    let needs = pipeline_cycles(config, beside);
    let available = available_cycles(control_rate_hz);
    if needs > available {
        return Err(Refusal::new(
            Field::Workload,
            Rule::TickOverrun { needs, available },
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::board::Hardware;
    use crate::config::settings::{representative_gpi, representative_pi, Settings};
    use crate::models::creep::{
        Creep, CreepParams, CREEP_BASE_CYCLES, CREEP_MODE_CYCLES, CREEP_TURN_CYCLES,
    };
    use crate::models::generalised_pi::DEAD_ZONE_MAP_CYCLES;

    fn build(s: &Settings) -> ControlConfig {
        s.build(&Hardware::driver_board(10_000.0)).unwrap()
    }

    #[test]
    fn a_floating_point_model_is_charged_the_fpu_context_and_an_integer_one_is_not() {
        use crate::config::settings::{representative_bouc_wen, representative_duhem};
        let pair = |m: crate::config::settings::Model| Settings {
            compensator: Some(m.clone()),
            observer: Some(m),
            ..Settings::default()
        };
        for (model, fpu) in [
            (representative_pi(16).unwrap(), false),
            (representative_gpi(16).unwrap(), false),
            (representative_duhem(), true),
            (representative_bouc_wen(), true),
        ] {
            let config = build(&pair(model));
            assert_eq!(interrupt_uses_fpu(&config), fpu);
            // The interrupt: the fixed part, the model, and the context once.
            assert_eq!(
                interrupt_cycles(&config),
                FIXED_CYCLES + config.compensator.cycles() + u32::from(fpu) * FP_CONTEXT_CYCLES
            );
        }
        // No model: nothing of the FPU.
        let bare = build(&Settings::default());
        assert!(!interrupt_uses_fpu(&bare));
        assert_eq!(interrupt_cycles(&bare), FIXED_CYCLES);
    }

    #[test]
    fn each_source_beside_the_stream_is_charged_and_the_dearest_makes_every_feature() {
        let only = |source| {
            Beside {
                source,
                ..Beside::default()
            }
            .cycles()
        };
        assert_eq!(Beside::default().cycles(), 0);
        assert_eq!(only(SetpointSource::Stream), 0);
        assert_eq!(only(SetpointSource::Sequence), SEQUENCE_CYCLES);
        assert_eq!(only(SetpointSource::Analog), ANALOG_CYCLES);
        assert_eq!(only(SetpointSource::Scan), SCAN_CYCLES);
        assert_eq!(only(SetpointSource::Coarse), COARSE_CYCLES);
        // One source at a time: every feature counts the dearest of them, the scan.
        let sources = [
            SetpointSource::Stream,
            SetpointSource::Scan,
            SetpointSource::Sequence,
            SetpointSource::Analog,
            SetpointSource::Coarse,
        ];
        assert!(sources.iter().all(|s| source_cycles(*s) <= SCAN_CYCLES));
        assert_eq!(Beside::EVERY_FEATURE.source, SetpointSource::Scan);
    }

    #[test]
    fn the_highest_rate_is_admitted_and_a_faster_one_is_not() {
        for cycles in [1, 346, 1_130, 1_679, 1_680, 1_681, 3_250, 16_800] {
            let rate = highest_rate_hz(cycles);
            assert!(available_cycles(rate) >= cycles, "{cycles} at {rate}");
            assert!(
                available_cycles(rate * (1.0 + 1e-9)) < cycles,
                "{cycles} above {rate}"
            );
        }
        assert_eq!(highest_rate_hz(0), f64::INFINITY);
    }

    #[test]
    fn the_services_cost_nothing_idle_and_less_the_coarser_they_take_the_ticks() {
        let load = |c: Option<u16>, t: Option<u16>| ServicesLoad {
            capture_decimation: c,
            telemetry_decimation: t,
            capture_pre_trigger: false,
            observer_cycles: 0,
        };
        assert_eq!(load(None, None).cycles(), 0);
        assert_eq!(Beside::default().cycles(), 0);
        let batch = crate::services::snapshot::BATCH as u16;
        for side in [0, 1] {
            let at = |d: u16| {
                if side == 0 {
                    load(Some(d), None)
                } else {
                    load(None, Some(d))
                }
                .cycles()
            };
            // Every tick: every snapshot served in full, a frame (a sample) on each; every
            // `batch` ticks or coarser: the others passed over, one served a batch.
            let per = if side == 0 {
                CAPTURE_FRAME_CYCLES
            } else {
                TELEMETRY_SAMPLE_CYCLES
            };
            assert_eq!(at(1), SERVICES_EVERY_CYCLES + per);
            assert_eq!(at(batch), at(u16::MAX));
            // A capture's batch also serves the event it waits for in full.
            let served = if side == 0 { 2 } else { 1 };
            assert_eq!(
                at(batch),
                SERVICES_BASE_CYCLES + (served * SERVE_CYCLES + per).div_ceil(u32::from(batch))
            );
            // With a pre-trigger window, the batch it fires in costs more.
            if side == 0 {
                let windowed = ServicesLoad {
                    capture_pre_trigger: true,
                    ..load(Some(batch), None)
                };
                assert_eq!(
                    windowed.cycles(),
                    SERVICES_BASE_CYCLES
                        + (2 * SERVE_CYCLES + FIRE_CYCLES + per).div_ceil(u32::from(batch))
                );
            }
            for d in 1..3 * batch {
                assert!(at(d + 1) <= at(d), "{side}: {d}");
            }
        }
        let both = load(Some(1), Some(1));
        assert_eq!(
            ServicesLoad {
                capture_pre_trigger: true,
                ..both
            },
            ServicesLoad::WORST
        );
        // Every snapshot served in full (a pre-trigger window of every tick adds nothing).
        assert_eq!(both.cycles(), ServicesLoad::WORST.cycles());
        assert_eq!(
            both.cycles(),
            SERVICES_EVERY_CYCLES + CAPTURE_FRAME_CYCLES + TELEMETRY_SAMPLE_CYCLES
        );
        // A frame and a sample every other tick: four of each a batch (and the capture's
        // event), each of the eight snapshots served in full at most once.
        assert_eq!(
            load(Some(2), Some(2)).cycles(),
            SERVICES_BASE_CYCLES
                + SERVE_CYCLES
                + (CAPTURE_FRAME_CYCLES + TELEMETRY_SAMPLE_CYCLES).div_ceil(2)
        );
        let beside = Beside {
            services: both,
            ..Beside::default()
        };
        assert_eq!(beside.cycles(), both.cycles());
    }

    #[test]
    fn the_prediction_grows_with_every_part_a_configuration_runs() {
        let bare = worst_case_cycles(&build(&Settings::default()));
        assert_eq!(bare, FIXED_CYCLES);
        let pi8 = Settings {
            compensator: Some(representative_pi(8).unwrap()),
            ..Settings::default()
        };
        let pi32 = Settings {
            compensator: Some(representative_pi(32).unwrap()),
            ..Settings::default()
        };
        let (c8, c32) = (
            worst_case_cycles(&build(&pi8)),
            worst_case_cycles(&build(&pi32)),
        );
        assert!(bare < c8 && c8 < c32, "{bare} {c8} {c32}");
        let with_observer = Settings {
            observer: Some(representative_pi(32).unwrap()),
            ..pi32.clone()
        };
        // The observer runs below the tick: the interrupt is the compensator's, the pipeline
        // adds the observer's bank, its drift check and the services' base share.
        let both = worst_case_cycles(&build(&with_observer));
        assert_eq!(interrupt_cycles(&build(&with_observer)), c32);
        assert_eq!(
            both - c32,
            c32 - bare
                + OBSERVER_BELOW_CYCLES
                + SERVICES_EVERY_CYCLES
                + RELOAD_CYCLES.div_ceil(crate::services::snapshot::BATCH),
            "the observer's bank costs what the inverse's does"
        );
        // With an observer every snapshot is served in full already: a capture beside it adds
        // its frames only.
        let capturing = Beside {
            services: ServicesLoad {
                capture_decimation: Some(1),
                ..ServicesLoad::default()
            },
            ..Beside::default()
        };
        assert_eq!(
            pipeline_cycles(&build(&with_observer), capturing) - both,
            CAPTURE_FRAME_CYCLES
        );
        // At 10 kHz modes of 2 ms and 10 ms update every tick (2 ms is 20 ticks, less than
        // 20 updates of 2 ticks); modes of 10 ms and 100 ms take turns, at one cost.
        for (taus, cost) in [
            ([0.002, 0.01], CREEP_BASE_CYCLES + 2 * CREEP_MODE_CYCLES),
            ([0.01, 0.1], CREEP_TURN_CYCLES),
        ] {
            let crept = Settings {
                creep: Some(CreepParams::new(&taus, &[0.02, 0.02]).unwrap()),
                ..with_observer.clone()
            };
            assert_eq!(
                worst_case_cycles(&build(&crept)) - both,
                2 * cost,
                "creep runs on both sides"
            );
        }
        let gpi = Settings {
            compensator: Some(representative_gpi(32).unwrap()),
            ..pi32
        };
        assert_eq!(worst_case_cycles(&build(&gpi)) - c32, DEAD_ZONE_MAP_CYCLES);
        // The feedforward's notch is charged as the feedback's (the same biquad).
        let shaped = Settings {
            shaping: Some(crate::control::notch::NotchDesign {
                frequency_hz: 2_000.0,
                q: 0.5,
                depth: 0.02,
            }),
            ..gpi.clone()
        };
        assert_eq!(
            worst_case_cycles(&build(&shaped)) - worst_case_cycles(&build(&gpi)),
            NOTCH_CYCLES
        );
        let previewed = Settings {
            preview: Some(crate::control::preview::PreviewDesign {
                frequency_hz: 2_000.0,
                damping: 0.02,
            }),
            ..gpi.clone()
        };
        assert_eq!(
            worst_case_cycles(&build(&previewed)) - worst_case_cycles(&build(&gpi)),
            PREVIEW_CYCLES
        );
    }

    #[test]
    fn a_configuration_too_dear_for_the_rate_is_refused_with_what_it_needs() {
        let creep = CreepParams::new(&[0.01, 0.1, 1.0, 10.0, 30.0, 100.0], &[0.01; 6]).unwrap();
        let dear = Settings {
            compensator: Some(representative_gpi(32).unwrap()),
            observer: Some(representative_gpi(32).unwrap()),
            creep: Some(creep),
            ..Settings::default()
        };
        assert!(check(&build(&dear), 10_000.0).is_ok());
        // The creep's modes take turns at 100 kHz (not at 10 kHz): the cost is the 100 kHz one.
        let config = dear.build(&Hardware::driver_board(1_000.0)).unwrap();
        let config = ControlConfig {
            creep: Creep::new(dear.creep.as_ref().unwrap(), 100_000.0).ok(),
            ..config
        };
        let needs = worst_case_cycles(&config);
        let refusal = check(&config, 100_000.0).unwrap_err();
        assert_eq!(
            refusal,
            Refusal::new(
                Field::Workload,
                Rule::TickOverrun {
                    needs,
                    // 80 % of the 1 680 cycles of a 100 kHz period.
                    available: 1344
                }
            )
        );
        // The settings' own validation refuses it the same way.
        assert_eq!(
            dear.build(&Hardware::driver_board(100_000.0)).unwrap_err(),
            refusal
        );
        assert_eq!(available_cycles(f64::NAN), 0);
        assert_eq!(available_cycles(-1.0), 0);
    }
}
