//! The image itself (built for the target only; see the crate docs in `main.rs`).

use core::hint::black_box;

use cortex_m_rt::entry;
use cortex_m_semihosting::{debug, hprintln};
use defmt_rtt as _;
use stm32f4xx_hal::pac;

use twinstack::board::{DacCode, DualDac, Hardware, QuadratureEncoder, SensorAdc};
use twinstack::board::{LimitSwitches, Switches};
use twinstack::config::settings::{
    representative_bouc_wen, representative_duhem, representative_gpi, representative_pi,
    FeedbackSettings, Mode, Model, SensorSettings, Settings,
};
use twinstack::control::drive::{DifferentialDrive, DriveOutput, StackVoltages};
use twinstack::control::notch::NotchDesign;
use twinstack::control::Controller;
use twinstack::control::{Compensator, ControlConfig, Observer, TickReport};
use twinstack::control_loop::ControlLoop;
use twinstack::dual_stage::ideal_axis::{AxisSteps, IdealAxis};
use twinstack::dual_stage::{
    CoarseCommand, CoarseState, CoarseStatus, CoarseSupervisor, CoarseTake, DualStage,
    DualStageSettings, FineSetpoints, LoopExchange, PreparedCoarse, SupervisorSettings,
};
use twinstack::fixed_point::SIGNAL_ONE;
use twinstack::hardware::adc::SensorInput;
use twinstack::hardware::dac::InternalDac;
use twinstack::models::duhem::{Duhem, DuhemState};
use twinstack::models::generalised_pi::{GeneralisedPi, InverseGeneralisedPi};
use twinstack::models::prandtl_ishlinskii::{InversePrandtlIshlinskii, PiState};
use twinstack::services::observer::Observed;

/// Ticks measured per configuration (after as many warm-up ticks).
const TICKS: u32 = 1000;
/// Ticks between setpoint reversals.
const HALF_PERIOD: i32 = 100;
/// Control rate the configurations are built for, Hz: the default rate, at which the tick
/// budget admits every row (at 100 kHz it refuses the largest, e.g. the inverse P–I N = 32
/// beside the Duhem observer; the rows' cost does not depend on the rate).
const RATE_HZ: f64 = 50_000.0;

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    hprintln!("BENCH-PANIC {}", info);
    debug::exit(debug::EXIT_FAILURE);
    loop {
        cortex_m::asm::wfi();
    }
}

/// TIM2's counter (1 GHz under `-icount shift=0`).
#[inline(always)]
fn now(tim: &pac::TIM2) -> u32 {
    tim.cnt().read().bits()
}

/// One tick and the observer's step on its report (which the board runs below the tick, in
/// its services: the control law's whole per-tick work), not inlined, so the measurement
/// brackets exactly one call.
#[inline(never)]
fn one_tick<D: DualDac, A: SensorAdc>(
    c: &mut Observed,
    setpoint: Option<i32>,
    adc: &mut A,
    dac: &mut D,
) -> TickReport {
    c.tick(setpoint, adc, dac)
}

/// [`DifferentialDrive::split`] alone.
#[inline(never)]
fn split_part(d: &DifferentialDrive, command: i32, previous: StackVoltages) -> DriveOutput {
    d.split(command, previous, d.slew())
}

/// [`Duhem::step`] alone.
#[inline(never)]
fn duhem_part(m: &Duhem, s: &mut DuhemState, u: i32) -> i32 {
    m.step(s, u)
}

/// [`InversePrandtlIshlinskii::step`] alone.
#[inline(never)]
fn pi_part(m: &InversePrandtlIshlinskii, s: &mut PiState, y: i32) -> i32 {
    m.step(s, y)
}

/// [`GeneralisedPi::step`] alone.
#[inline(never)]
fn gpi_part(m: &GeneralisedPi, s: &mut PiState, u: i32) -> i32 {
    m.step(s, u)
}

/// [`InverseGeneralisedPi::step`] alone.
#[inline(never)]
fn inverse_gpi_part(m: &InverseGeneralisedPi, s: &mut PiState, y: i32) -> i32 {
    m.step(s, y)
}

/// An encoder's counter as the board's timer holds it: a reading the model of the axis
/// latched before the tick, so that the tick is traced as the board runs it (one register
/// read), not with the model's arithmetic (a 64-bit division per count).
struct LatchedCount(u16);

impl QuadratureEncoder for LatchedCount {
    fn count(&mut self) -> u16 {
        self.0
    }
}

/// The switches as the board's GPIO input register holds them, latched from the model.
struct LatchedSwitches(Switches);

impl LimitSwitches for LatchedSwitches {
    fn read(&mut self) -> Switches {
        self.0
    }
}

/// The dual-stage images' coarse task's period, as the firmware's task runs it
/// ([`CoarseSupervisor::period`]: the handler's command and the piezo's position taken from
/// the control loop, the supervisor's tick, the fine setpoints and the status posted to the
/// loop), on the library's model of the axis (its step output, and its encoders and switches
/// latched before the period, as the board's peripherals hold them). The lock around each
/// exchange is the board's `BASEPRI` write, not run here.
#[inline(never)]
fn coarse_part(
    sup: &mut CoarseSupervisor,
    io: &mut (AxisSteps<'_>, LatchedCount, LatchedCount, LatchedSwitches),
    control: &mut ControlLoop<&mut Controller>,
) -> FineSetpoints {
    let (steps, motor, linear, switches) = io;
    // As the emulator image runs it: the model's piezo sits where its setpoint is, and the
    // task takes its own last fine setpoint for it.
    sup.period(
        (steps, motor, linear, switches),
        &mut Exchange(control),
        false,
    )
}

/// The coarse task's exchanges with the loop, each what the board runs under the tick's lock
/// (`hardware::setup`'s `TickLock`), in a call of its own so that the bench traces how long
/// each holds the tick off.
struct Exchange<'a, 'c>(&'a mut ControlLoop<&'c mut Controller>);

impl LoopExchange for Exchange<'_, '_> {
    fn take(&mut self) -> CoarseTake {
        coarse_take(self.0)
    }

    fn post(&mut self, fine: &FineSetpoints, status: CoarseStatus) {
        coarse_post(self.0, fine, status);
    }
}

/// The body of the coarse task's first lock of the tick.
#[inline(never)]
fn coarse_take(control: &mut ControlLoop<&mut Controller>) -> CoarseTake {
    control.take_coarse()
}

/// The body of the coarse task's second lock of the tick.
#[inline(never)]
fn coarse_post(
    control: &mut ControlLoop<&mut Controller>,
    fine: &FineSetpoints,
    status: CoarseStatus,
) {
    control.post_coarse(fine, status);
}

/// [`DualDac::write_both`] alone.
#[inline(never)]
fn dac_part(d: &mut InternalDac, l: DacCode, r: DacCode) {
    let _ = d.write_both(l, r);
}

/// The bench's settings: `compensator`, the Duhem observer, the sensor spanning the stroke
/// (drift limit 2 %), PI feedback, closed loop, over the defaults (ranges, drive).
fn closed(compensator: Option<Model>) -> Settings {
    Settings {
        compensator,
        observer: Some(representative_duhem()),
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

/// Triangle setpoint: ±0.95 of full scale (nearly the whole stroke, so that every play operator moves), reversing every [`HALF_PERIOD`] ticks.
fn setpoint(k: u32) -> i32 {
    let amplitude = (SIGNAL_ONE / 20) * 19;
    let step = 2 * amplitude / HALF_PERIOD;
    let phase = (k as i32) % (2 * HALF_PERIOD);
    if phase < HALF_PERIOD {
        -amplitude + step * phase
    } else {
        amplitude - step * (phase - HALF_PERIOD)
    }
}

#[entry]
fn main() -> ! {
    let dp = pac::Peripherals::take().unwrap();
    // Free-running 32-bit counter: PSC = 0, ARR = max.
    dp.RCC.apb1enr().modify(|_, w| w.tim2en().set_bit());
    let tim = dp.TIM2;
    tim.psc().write(|w| unsafe { w.bits(0) });
    tim.arr().write(|w| unsafe { w.bits(u32::MAX) });
    tim.egr().write(|w| w.ug().set_bit());
    tim.cr1().write(|w| w.cen().set_bit());

    let mut dac = InternalDac::new(dp.DAC, &dp.RCC, (Default::default(), Default::default()));
    let mut adc = SensorInput::new(dp.ADC1, &dp.ADC_COMMON, &dp.RCC);

    let hw = Hardware::driver_board(RATE_HZ);
    let build = |name: &str, s: Settings| -> ControlConfig {
        match s.build(&hw) {
            Ok(c) => c,
            Err(e) => panic!("configuration {} refused: {}", name, e),
        }
    };
    let pi = |n: usize| match representative_pi(n) {
        Ok(m) => Some(m),
        Err(_) => panic!("representative P–I N = {}", n),
    };
    let gpi = |n: usize| match representative_gpi(n) {
        Ok(m) => Some(m),
        Err(_) => panic!("representative generalised P–I N = {}", n),
    };
    let base = closed(None);
    // Four creep modes, 0.1 ms … 100 ms, 2 % each, in series with both models.
    let creep = match twinstack::models::creep::CreepParams::new(
        &[1e-4, 1e-3, 1e-2, 1e-1],
        &[0.02, 0.02, 0.02, 0.02],
    ) {
        Ok(c) => Some(c),
        Err(_) => panic!("creep parameters"),
    };
    let cases: [(&str, Settings); 13] = [
        // Breakdown of the fixed part: split + limits + DAC alone, then + the Duhem observer.
        (
            "bypass",
            Settings {
                sensor: None,
                ..Settings::default()
            },
        ),
        (
            "none-observer-only",
            Settings {
                observer: Some(representative_duhem()),
                sensor: None,
                ..Settings::default()
            },
        ),
        // The table: every compensator with the Duhem observer and sensor feedback on.
        ("none", base.clone()),
        ("inverse-pi-8", closed(pi(8))),
        ("inverse-pi-16", closed(pi(16))),
        ("inverse-pi-32", closed(pi(32))),
        ("inverse-duhem", closed(Some(representative_duhem()))),
        // Breakdown of the feedback: the sensor read and drift check alone (bypass), then
        // PID with the resonance notch (kd 0.05 per tick, low pass at a tenth of the rate).
        (
            "none-sensor-drift",
            Settings {
                feedback: None,
                mode: Mode::Bypass,
                ..base.clone()
            },
        ),
        (
            "none-pid-notch",
            Settings {
                feedback: Some(FeedbackSettings {
                    kd: 0.05 / RATE_HZ,
                    derivative_cutoff_hz: RATE_HZ / 10.0,
                    notch: Some(NotchDesign {
                        frequency_hz: 21_800.0,
                        q: 2.0,
                        depth: 0.0,
                    }),
                    ..FeedbackSettings::pi(0.2, 500.0, 0.1)
                }),
                ..base.clone()
            },
        ),
        // The generalised P–I (N = 16, 6 dead zones) as compensator, last so that the rows
        // above run the code they ran before it existed.
        ("inverse-gpi-16", closed(gpi(16))),
        // The inverse P–I N = 16 row with creep (inverse creep before the compensator,
        // creep after the observer).
        (
            "inverse-pi-16-creep-4",
            Settings {
                creep,
                ..closed(pi(16))
            },
        ),
        // Bouc–Wen: the compensator with the Duhem observer, then
        // with its own model as the observer.
        ("inverse-bouc-wen", closed(Some(representative_bouc_wen()))),
        (
            "inverse-bouc-wen-bouc-wen",
            Settings {
                observer: Some(representative_bouc_wen()),
                ..closed(Some(representative_bouc_wen()))
            },
        ),
    ];
    // The parts below run the inverse P–I N = 16 row's models and drive.
    let parts = build("inverse-pi-16", closed(pi(16)));
    for (name, settings) in cases {
        let mut c = Observed::new(build(name, settings));
        // Overhead: the bracket itself, two timer reads with nothing between. What is left of
        // a measured call is the tick's own instructions plus the call (`BL`) and its argument
        // moves, a few instructions the firmware, which inlines the tick, does not have: the
        // counts err high, never low.
        let mut overhead = u32::MAX;
        for _ in 0..16 {
            let t0 = now(&tim);
            let t1 = now(&tim);
            overhead = overhead.min(t1.wrapping_sub(t0));
        }
        for k in 0..TICKS {
            black_box(one_tick(&mut c, Some(setpoint(k)), &mut adc, &mut dac));
        }
        let (mut total, mut min, mut max) = (0u64, u32::MAX, 0u32);
        for k in TICKS..2 * TICKS {
            // Computed (and pinned by `black_box`) before the first timer read, so the bracket
            // holds the call alone.
            let sp = black_box(Some(setpoint(k)));
            let t0 = now(&tim);
            // The tick writes its report straight into `report`; it is looked at (by address,
            // no copy) only after the second timer read.
            let report = one_tick(&mut c, sp, &mut adc, &mut dac);
            let t1 = now(&tim);
            black_box(&report);
            let n = t1.wrapping_sub(t0).saturating_sub(overhead);
            total += n as u64;
            min = min.min(n);
            max = max.max(n);
        }
        hprintln!(
            "BENCH name={} ticks={} total={} min={} max={} overhead={}",
            name,
            TICKS,
            total,
            min,
            max,
            overhead
        );
    }
    // The tick's parts alone, on the same triangle: where the instructions go.
    let drive = parts.drive;
    let mut previous = drive.stacks_at(drive.rest_drive());
    let Observer::Duhem(duhem) = parts.observer else {
        panic!("the Duhem observer");
    };
    let mut duhem_state = duhem.state_at(0, 0);
    let Compensator::InversePi(inverse) = parts.compensator else {
        panic!("the inverse P–I");
    };
    let mut pi_state = inverse.state_at_rest(0);
    let (mut split_n, mut duhem_n, mut pi_n, mut dac_n) =
        ([0u64; 2], [0u64; 2], [0u64; 2], [0u64; 2]);
    for k in 0..2 * TICKS {
        let sp = setpoint(k);
        let t0 = now(&tim);
        let out = black_box(split_part(&drive, sp, previous));
        let t1 = now(&tim);
        black_box(duhem_part(&duhem, &mut duhem_state, out.applied));
        let t2 = now(&tim);
        black_box(pi_part(&inverse, &mut pi_state, sp));
        let t3 = now(&tim);
        dac_part(&mut dac, out.left, out.right);
        let t4 = now(&tim);
        previous = out.stacks;
        if k >= TICKS {
            for (acc, n) in [
                (&mut split_n, t1.wrapping_sub(t0)),
                (&mut duhem_n, t2.wrapping_sub(t1)),
                (&mut pi_n, t3.wrapping_sub(t2)),
                (&mut dac_n, t4.wrapping_sub(t3)),
            ] {
                acc[0] += n as u64;
                acc[1] = acc[1].max(n as u64);
            }
        }
    }
    // The inverse P–I's worst case: full-range steps (±0.95, alternating every tick), which
    // move every operator on every tick — the bound a setpoint jump can cost.
    let mut jump_n = [0u64; 2];
    for k in 0..2 * TICKS {
        let sp = if k % 2 == 0 {
            -setpoint(0)
        } else {
            setpoint(0)
        };
        let t0 = now(&tim);
        black_box(pi_part(&inverse, &mut pi_state, sp));
        let t1 = now(&tim);
        if k >= TICKS {
            jump_n[0] += t1.wrapping_sub(t0) as u64;
            jump_n[1] = jump_n[1].max(t1.wrapping_sub(t0) as u64);
        }
    }
    // The generalised P–I (N = 16, 6 dead zones) alone, forward on the triangle as a drive,
    // inverse on it as a setpoint.
    let gpi_parts = build("gpi-16", closed(gpi(16)));
    let Compensator::InverseGeneralisedPi(inverse_gpi) = gpi_parts.compensator else {
        panic!("the inverse generalised P–I");
    };
    let forward_gpi = match representative_gpi(16).map(|m| {
        let s = Settings {
            observer: Some(m),
            ..closed(None)
        };
        s.build(&hw).map(|c| c.observer)
    }) {
        Ok(Ok(Observer::GeneralisedPi(m))) => m,
        _ => panic!("the generalised P–I observer"),
    };
    let (mut fwd_state, mut inv_state) =
        (forward_gpi.state_at_rest(0), inverse_gpi.state_at_rest(0));
    let (mut gpi_fwd_n, mut gpi_inv_n) = ([0u64; 2], [0u64; 2]);
    for k in 0..2 * TICKS {
        let sp = setpoint(k);
        let t0 = now(&tim);
        black_box(gpi_part(&forward_gpi, &mut fwd_state, sp));
        let t1 = now(&tim);
        black_box(inverse_gpi_part(&inverse_gpi, &mut inv_state, sp));
        let t2 = now(&tim);
        if k >= TICKS {
            for (acc, n) in [
                (&mut gpi_fwd_n, t1.wrapping_sub(t0)),
                (&mut gpi_inv_n, t2.wrapping_sub(t1)),
            ] {
                acc[0] += n as u64;
                acc[1] = acc[1].max(n as u64);
            }
        }
    }
    // The coarse task's tick (the dual-stage images, once a coarse period): the paper stage's
    // axis on the library's model (the emulator image's), homed, then moved 10 mm at its
    // speed and acceleration limits and back, then stopped at full speed in a 20 mm move and
    // in a jog; every period measured, the commands left in the control loop as the command
    // handler leaves them.
    let coarse_n = {
        let settings = DualStageSettings {
            fine_rate_hz: RATE_HZ,
            ..DualStageSettings::paper_stage()
        };
        let axis = IdealAxis::new(
            312_500,
            250_000,
            5_000,
            (-2_000_000_000, -1_000_000_000, 49_000_000_000),
        );
        let latch = |axis: &IdealAxis| {
            (
                LatchedCount(axis.motor().count()),
                LatchedCount(axis.linear().count()),
                LatchedSwitches(axis.switches().read()),
            )
        };
        let (motor, linear, switches) = latch(&axis);
        let mut io = (axis.step_dir(), motor, linear, switches);
        let Ok(config) = settings.build() else {
            panic!("the paper stage's dual-stage settings");
        };
        let dual = DualStage::new(config, 0, io.1.count(), io.2.count());
        let Ok(supervision) =
            SupervisorSettings::paper_stage().build(dual.config(), settings.coarse_rate_hz)
        else {
            panic!("the paper stage's supervisor settings");
        };
        let mut sup = CoarseSupervisor::new(dual, supervision);
        // The control loop the task exchanges with, the axis attached as the firmware attaches
        // it; the handler's commands are left in it.
        let (mut active, mut spare) = (Controller::new(parts), Controller::new(parts));
        let mut control = ControlLoop::new(&mut active, &mut spare, RATE_HZ as u32);
        control.attach_coarse(&PreparedCoarse::new(
            sup.limits(),
            sup.status(),
            RATE_HZ as u32,
        ));
        let mut acc = [0u64; 3];
        // One command, then ticks until the axis is in `until` or `at_most` ticks have run.
        let mut run = |sup: &mut CoarseSupervisor,
                       command: CoarseCommand,
                       until: CoarseState,
                       at_most: u32| {
            control.coarse().request(command);
            for _ in 0..at_most {
                (io.1, io.2, io.3) = latch(&axis);
                let t0 = now(&tim);
                let fine = black_box(coarse_part(sup, &mut io, &mut control));
                let t1 = now(&tim);
                axis.set_piezo_pm(sup.dual().fine_to_pm(fine.to));
                let n = u64::from(t1.wrapping_sub(t0));
                acc[0] += n;
                acc[1] = acc[1].max(n);
                acc[2] += 1;
                if sup.status().state == until {
                    break;
                }
            }
        };
        run(&mut sup, CoarseCommand::Home, CoarseState::Idle, 50_000);
        if !sup.status().homed {
            panic!("the coarse axis did not home");
        }
        // Prepared where the firmware prepares them: the command handler, off the task.
        let limits = sup.limits().coarse.prepare();
        for target_pm in [10_000_000_000, 0] {
            run(
                &mut sup,
                CoarseCommand::MoveTo { target_pm, limits },
                CoarseState::Idle,
                50_000,
            );
            let s = sup.status();
            if s.state != CoarseState::Idle || (s.position_pm - target_pm).abs() > 1_000_000 {
                panic!("the coarse axis did not move to {} pm", target_pm);
            }
        }
        // A controlled stop at full speed, halfway through a move (the braking planned from
        // the speed), and a jog stopped: each comes to rest short of where it was going.
        for (what, command, ticks) in [
            (
                "move",
                CoarseCommand::MoveTo {
                    target_pm: 20_000_000_000,
                    limits,
                },
                3_000,
            ),
            (
                "jog",
                CoarseCommand::Jog {
                    forward: false,
                    limits,
                },
                1_000,
            ),
        ] {
            let from = sup.status().position_pm;
            run(&mut sup, command, CoarseState::Idle, ticks);
            if sup.status().state == CoarseState::Idle {
                panic!("the coarse axis ended its {} before its stop", what);
            }
            run(&mut sup, CoarseCommand::Stop, CoarseState::Idle, 50_000);
            let s = sup.status();
            if s.state != CoarseState::Idle || s.position_pm == from {
                panic!("the coarse axis did not stop its {}", what);
            }
        }
        acc
    };
    for (name, acc) in [
        ("drive-split", split_n),
        ("duhem-observer-step", duhem_n),
        ("inverse-pi-16-step", pi_n),
        ("inverse-pi-16-full-steps", jump_n),
        ("dac-write", dac_n),
        ("gpi-16-6-observer-step", gpi_fwd_n),
        ("inverse-gpi-16-6-step", gpi_inv_n),
    ] {
        hprintln!(
            "PART name={} ticks={} total={} max={}",
            name,
            TICKS,
            acc[0],
            acc[1]
        );
    }
    hprintln!(
        "PART name=coarse-tick ticks={} total={} max={}",
        coarse_n[2],
        coarse_n[0],
        coarse_n[1]
    );
    debug::exit(debug::EXIT_SUCCESS);
    loop {
        cortex_m::asm::wfi();
    }
}
