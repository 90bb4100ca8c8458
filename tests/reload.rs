//! Reloads and mode switches while the board runs, driven as a host drives the board (requests
//! through the command handler, the tick as the firmware runs it): over random pairs of
//! accepted settings and random running states — a setpoint stream of jumps and ramps, random
//! sensor readings and failed reads, mode switches — no DAC step ever exceeds the slew limit in
//! volts (the stricter of the old and the new one while a reload or switch settles), and each
//! stack moves only towards the new voltage limits until it is inside them, then stays there;
//! and where the settings have a sensor, the observer the services run below the tick gives,
//! tick for tick, the estimate and drift flags of one prepared with each load and run on the
//! tick's report from the tick its controller took over (the reload's hand-over in band).

use proptest::prelude::*;
use twinstack::board::fakes::{FixedAdc, RecordingDac};
use twinstack::board::{AdcCode, DacCode, Hardware};
use twinstack::command_handler::{start_services, CommandHandler, Parts};
use twinstack::config::param_store::RamStorage;
use twinstack::config::settings::{
    pi_model, FeedbackSettings, Mode, Model, SensorSettings, Settings,
};
use twinstack::control::drive::{Configuration, DriveSettings, SafeState};
use twinstack::control::{Controller, TickFlags};
use twinstack::control_loop::{ControlLoop, SetpointQueue};
use twinstack::models::generalised_pi::{DeadZoneParams, GpiParams};
use twinstack::models::params::{BoucWenParams, DuhemParams};
use twinstack::protocol::messages::{Request, Response, SetpointBatch, StreamControl};
use twinstack::services::consumer::Services;
use twinstack::services::observer::ObserverBelow;
use twinstack::services::snapshot::SnapshotRing;
use twinstack::services::telemetry::TelemetryQueue;
use twinstack::Scaling;

const RATE: f64 = 50_000.0;
const HW: Hardware = Hardware::driver_board(RATE);
const VOLTS_PER_CODE: f64 = 150.0 / 4095.0;

/// A P–I model spread over `span` volts: `n` operators, weights decaying from `w1`.
fn pi_over(span: f64, n: usize, w1: f64, offset: f64) -> Model {
    let thresholds: Vec<f64> = (0..n).map(|i| span * i as f64 / n as f64).collect();
    let weights: Vec<f64> = (0..n)
        .map(|i| {
            if i == 0 {
                w1
            } else {
                w1 * 0.3 * 0.8f64.powi(i as i32)
            }
        })
        .collect();
    pi_model(0.0, offset, &thresholds, &weights).unwrap()
}

/// A generalised P–I: [`pi_over`] through a map of four dead zones centred on the output
/// range (at ±0.15 and ±0.3 of its span), each slope `slopes[j]`.
fn gpi_over(
    span: f64,
    n: usize,
    w1: f64,
    offset: f64,
    centre: f64,
    out_span: f64,
    slopes: [f64; 4],
) -> Model {
    let Model::PrandtlIshlinskii(pi) = pi_over(span, n, w1, offset) else {
        unreachable!("pi_over builds a P–I")
    };
    // Slopes outward: below the centre slopes[1] then slopes[0], above slopes[2] then slopes[3].
    let weights = [
        slopes[0] - slopes[1],
        slopes[1] - 1.0,
        slopes[2] - 1.0,
        slopes[3] - slopes[2],
    ];
    let dead_zones = DeadZoneParams::new(
        centre,
        1.0,
        &[-0.3, -0.15, 0.15, 0.3].map(|f| f * out_span),
        &weights,
    )
    .unwrap();
    Model::GeneralisedPi(GpiParams { pi, dead_zones })
}

prop_compose! {
    fn any_model(span: f64, out_lo: f64, out_span: f64)(kind in 0..5u8, n in 1..=32usize, w in 0.2f64..1.5, alpha in 0.001f64..0.1, gamma in 0.2f64..0.9, off in -0.3f64..0.3, slopes in proptest::array::uniform4(0.4f64..1.8)) -> Option<Model> {
        let slope = out_span / span;
        match kind {
            0 => None,
            1 => Some(pi_over(span, n, w * slope, off * out_span)),
            2 => Some(Model::Duhem(DuhemParams { alpha, beta: w * slope, gamma: gamma * w * slope, offset: off * out_span })),
            // Bouc–Wen, the only model that takes an output map: Duhem's in its form.
            3 => Some(Model::BoucWen(BoucWenParams::from_duhem(&DuhemParams { alpha, beta: w * slope, gamma: gamma * w * slope, offset: off * out_span }))),
            _ => Some(gpi_over(span, n, w * slope, off * out_span, out_lo + 0.5 * out_span, out_span, slopes)),
        }
    }
}

prop_compose! {
    fn any_settings()(
        lo in 0.0f64..60.0, span in 20.0f64..150.0,
        out_lo in -50.0f64..10.0, out_span in 5.0f64..100.0,
    )(
        ranges in Just((lo, (lo + span).min(150.0), out_lo, out_lo + out_span)),
        compensator in any_model((lo + span).min(150.0) - lo, out_lo, out_span),
        observer in any_model((lo + span).min(150.0) - lo, out_lo, out_span),
        differential in any::<bool>(),
        vmin in 0.0f64..40.0, vspan in 20.0f64..150.0, bias_frac in 0.0f64..=1.0,
        slew in 1.0e4f64..5.0e6,
        zero_safe in any::<bool>(),
        sensor in any::<bool>(),
        drift in proptest::option::of(0.01f64..0.5),
        feedback in proptest::option::of((0.0f64..1.0, 0.0f64..5000.0, 0.01f64..0.5)),
        mode in 0..3u8,
        shaping_preview_map in (
            proptest::option::of((500.0f64..20_000.0, 0.3f64..5.0, 0.0f64..1.0)),
            proptest::option::of((300.0f64..40_000.0, 0.005f64..0.5)),
            proptest::option::weighted(0.25, (-0.2f64..0.2, -0.2f64..0.2)),
        ),
    ) -> Settings {
        let (shaping, preview, map) = shaping_preview_map;
        // A map over the output range: one dead zone a side, a third of the half span out.
        let (out_mid, out_half) = ((ranges.2 + ranges.3) / 2.0, (ranges.3 - ranges.2) / 2.0);
        let output_map = map.map(|(below, above)| {
            twinstack::config::settings::DeadZoneParams::new(
                out_mid,
                1.0,
                &[-out_half / 3.0, out_half / 3.0],
                &[below, above],
            )
            .unwrap()
        });
        let vmax = (vmin + vspan).min(150.0);
        Settings {
            ranges: Scaling::new(ranges.0, ranges.1, ranges.2, ranges.3).unwrap(),
            compensator,
            observer,
            drive: DriveSettings {
                configuration: if differential { Configuration::Differential } else { Configuration::Unidirectional },
                bias: vmin + (vmax - vmin) * bias_frac,
                min_voltage: vmin,
                max_voltage: vmax,
                slew_rate: slew,
                safe_state: if zero_safe { SafeState::Zero } else { SafeState::Bias },
            },
            sensor: sensor.then_some(SensorSettings {
                displacement_at_zero: ranges.2,
                displacement_at_full_scale: ranges.3,
                drift_limit: drift,
            }),
            feedback: feedback.map(|(kp, ki, limit)| FeedbackSettings::pi(kp, ki, limit)),
            mode: [Mode::Bypass, Mode::OpenLoop, Mode::ClosedLoop][mode as usize],
            creep: None,
            shaping: shaping.map(|(frequency_hz, q, depth)| twinstack::control::notch::NotchDesign {
                frequency_hz,
                q,
                depth,
            }),
            // Above half the rate, refused (and skipped below).
            preview: preview.map(|(frequency_hz, damping)| twinstack::control::preview::PreviewDesign {
                frequency_hz,
                damping,
            }),
            output_map,
        }
    }
}

/// Settings the board accepts (the generator's rejects are skipped, not tested).
fn accepted() -> impl Strategy<Value = Settings> {
    any_settings().prop_filter("accepted by the board", |s| s.build(&HW).is_ok())
}

/// What happens between two checks.
#[derive(Clone, Debug)]
enum Event {
    /// Ticks with the sensor at this code (None: reads fail), streaming setpoints.
    Run { ticks: u16, adc: Option<u16> },
    /// A batch of setpoints: jumps or a ramp.
    Batch { samples: Vec<i16> },
    /// A parameter load.
    Load(Box<Settings>),
    /// A mode switch (refused when the settings lack what it needs: nothing changes).
    Mode(u8),
    /// Start or stop the stream.
    Stream(bool),
}

fn any_event() -> impl Strategy<Value = Event> {
    prop_oneof![
        4 => (1..400u16, proptest::option::of(0..4096u16)).prop_map(|(ticks, adc)| Event::Run { ticks, adc }),
        2 => prop_oneof![
            proptest::collection::vec(any::<i16>(), 1..96),
            (any::<i16>(), -800i16..800, 1..96usize).prop_map(|(a, d, n)| (0..n).map(|k| a.saturating_add(d.saturating_mul(k as i16))).collect()),
        ].prop_map(|samples| Event::Batch { samples }),
        2 => accepted().prop_map(|s| Event::Load(Box::new(s))),
        1 => (0..3u8).prop_map(Event::Mode),
        1 => any::<bool>().prop_map(Event::Stream),
    ]
}

/// The distance of `v` from `[lo, hi]`, volts.
fn outside(v: f64, lo: f64, hi: f64) -> f64 {
    (lo - v).max(v - hi).max(0.0)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, ..ProptestConfig::default() })]

    #[test]
    fn reloads_and_mode_switches_never_step_the_stacks_past_the_slew_limit(
        boot in accepted(),
        events in proptest::collection::vec(any_event(), 1..40),
    ) {
        let config = boot.build(&HW).unwrap();
        let mut control = ControlLoop::new(
            Box::new(Controller::new(config)),
            Box::new(Controller::new(config)),
            RATE as u32,
        );
        let mut services = Services::new(vec![0i16; 2048]);
        // At power-up, as the firmware starts: the observer below the tick in force at once.
        start_services(&config, &mut control, &mut services);
        // The reference: each load's observer, prepared at the stacks of its load, run on the
        // tick's report from the tick its controller takes over.
        let mut shadow = ObserverBelow::prepare(&config, config.drive.safe_stacks());
        let mut shadow_pending: Option<Option<ObserverBelow>> = None;
        let mut shadow_drifts = 0u32;
        let snapshots: &'static mut SnapshotRing = Box::leak(Box::new(SnapshotRing::new()));
        let telemetry: &'static mut TelemetryQueue = Box::leak(Box::new(TelemetryQueue::new()));
        // The handler's two locks: the loop, and the services (the snapshots served first).
        macro_rules! locks {
            () => {
                &mut Parts::new(&mut control, &mut services, snapshots, telemetry)
            };
        }
        let mut handler = CommandHandler::new(HW, boot.clone(), false, RamStorage::default());
        let queue: &'static mut SetpointQueue = Box::leak(Box::new(SetpointQueue::new()));
        let (mut producer, mut consumer) = queue.split();
        let mut dac = RecordingDac::default();
        let (l0, r0) = config.drive.safe_codes();
        let mut last = (l0.0 as f64 * VOLTS_PER_CODE, r0.0 as f64 * VOLTS_PER_CODE);
        let mut seq = 0u16;
        // The settings in force, the ones before the last swap (for the stricter slew limit
        // while a reload settles), and a load waiting for the next tick (a newer load
        // replaces it).
        let mut now = boot;
        let mut before = now.clone();
        let mut pending: Option<Settings> = None;
        let mut adc = FixedAdc(Some(AdcCode(2048)));
        let mut settled_inside = [false, false];
        for event in events {
            match event {
                Event::Run { ticks, adc: code } => {
                    adc.0 = code.map(|c| AdcCode(c as u32));
                    for _ in 0..ticks {
                        if let Some(next) = pending.take() {
                            before = core::mem::replace(&mut now, next);
                            settled_inside = [false, false];
                        }
                        if let Some(next) = shadow_pending.take() {
                            shadow = next;
                        }
                        let report = control.tick(&mut consumer, &mut snapshots.split().0, &mut adc, &mut dac);
                        let mut expected = report;
                        if let Some(o) = shadow.as_mut() {
                            o.observe(&mut expected);
                            shadow_drifts += u32::from(expected.flags.contains(TickFlags::DRIFT));
                        }
                        services.consume(&mut snapshots.split().1, &mut telemetry.split().0);
                        prop_assert_eq!(
                            services.observer().map(|o| (o.estimate(), o.drift())),
                            shadow.as_ref().map(|o| (o.estimate(), o.drift())),
                            "the observer below the tick"
                        );
                        prop_assert_eq!(services.drifts(), shadow_drifts);
                        let volts = (dac.left.0 as f64 * VOLTS_PER_CODE, dac.right.0 as f64 * VOLTS_PER_CODE);
                        let slew = |s: &Settings| s.drive.slew_rate / RATE;
                        let allowed = if report.flags.contains(TickFlags::SETTLING) {
                            slew(&now).min(slew(&before))
                        } else {
                            slew(&now)
                        } + VOLTS_PER_CODE + 1e-9;
                        prop_assert!((volts.0 - last.0).abs() <= allowed,
                            "left stack stepped {:.3} V (allowed {allowed:.3}): {:.3} → {:.3}", volts.0 - last.0, last.0, volts.0);
                        prop_assert!((volts.1 - last.1).abs() <= allowed,
                            "right stack stepped {:.3} V (allowed {allowed:.3}): {:.3} → {:.3}", volts.1 - last.1, last.1, volts.1);
                        let (lo, hi) = (now.drive.min_voltage, now.drive.max_voltage);
                        for (i, (v, was)) in [(volts.0, last.0), (volts.1, last.1)].into_iter().enumerate() {
                            let d = outside(v, lo, hi);
                            prop_assert!(d <= outside(was, lo, hi) + VOLTS_PER_CODE,
                                "stack {i} moved away from the limits {lo}…{hi} V: {was:.3} → {v:.3}");
                            if settled_inside[i] {
                                prop_assert!(d <= VOLTS_PER_CODE, "stack {i} left the limits {lo}…{hi} V: {v:.3}");
                            }
                            settled_inside[i] |= d <= VOLTS_PER_CODE / 2.0;
                        }
                        last = volts;
                    }
                }
                Event::Batch { samples } => {
                    let batch = SetpointBatch { seq, samples: samples.into_iter().take(96).collect() };
                    let r = handler.handle(Request::Setpoints(batch), &mut producer, locks!());
                    if matches!(r, Response::Ack { .. }) {
                        seq = seq.wrapping_add(1);
                    }
                }
                Event::Load(s) => {
                    let stacks = control.stacks();
                    shadow_pending = Some(ObserverBelow::prepare(&s.build(&HW).unwrap(), stacks));
                    let r = handler.handle(Request::LoadParams((*s).clone()), &mut producer, locks!());
                    prop_assert!(matches!(r, Response::Ack { .. }), "an accepted settings set is acked: {r:?}");
                    pending = Some(*s);
                }
                Event::Mode(m) => {
                    let mode = [Mode::Bypass, Mode::OpenLoop, Mode::ClosedLoop][m as usize];
                    let r = handler.handle(Request::Mode(mode), &mut producer, locks!());
                    let newest = pending.as_ref().unwrap_or(&now);
                    prop_assert_eq!(matches!(r, Response::Ack { .. }), newest.check_mode(mode).is_ok(), "{:?}", r);
                    if matches!(r, Response::Ack { .. }) {
                        now.mode = mode;
                        if let Some(p) = pending.as_mut() {
                            p.mode = mode;
                        }
                    }
                }
                Event::Stream(on) => {
                    let c = if on { StreamControl::Start } else { StreamControl::Stop };
                    handler.handle(Request::Stream(c), &mut producer, locks!());
                }
            }
        }
    }
}

/// A reload across input ranges, as a user meets it: the board on a 0…140 V model, then a
/// load whose input range is ±156 V. The outputs must not move in the swap tick (re-deriving
/// the drive from the new model's input range would step them by up to 140 V).
#[test]
fn a_load_with_another_input_range_does_not_step_the_outputs() {
    let first = Settings {
        compensator: Some(pi_over(140.0, 16, 0.2, 0.0)),
        mode: Mode::OpenLoop,
        ..Settings::default()
    };
    let mut second = first.clone();
    second.ranges = Scaling::new(-156.0, 156.0, -20.0, 21.0).unwrap();
    second.compensator = Some(pi_over(312.0, 16, 0.05, 0.0));
    let config = first.build(&HW).unwrap();
    let mut control = ControlLoop::new(
        Box::new(Controller::new(config)),
        Box::new(Controller::new(config)),
        RATE as u32,
    );
    let mut services = Services::new(vec![0i16; 32]);
    let snapshots: &'static mut SnapshotRing = Box::leak(Box::new(SnapshotRing::new()));
    let telemetry: &'static mut TelemetryQueue = Box::leak(Box::new(TelemetryQueue::new()));
    macro_rules! locks {
        () => {
            &mut Parts::new(&mut control, &mut services, snapshots, telemetry)
        };
    }
    let mut handler = CommandHandler::new(HW, first, false, RamStorage::default());
    let queue: &'static mut SetpointQueue = Box::leak(Box::new(SetpointQueue::new()));
    let (mut producer, mut consumer) = queue.split();
    let mut dac = RecordingDac::default();
    let mut adc = FixedAdc(Some(AdcCode(2048)));
    // Somewhere off-centre: stream a held setpoint of 0.3.
    handler.handle(
        Request::Setpoints(SetpointBatch {
            seq: 0,
            samples: [9830i16; 8].into_iter().collect(),
        }),
        &mut producer,
        locks!(),
    );
    handler.handle(
        Request::Stream(StreamControl::Start),
        &mut producer,
        locks!(),
    );
    for _ in 0..100 {
        control.tick(&mut consumer, &mut snapshots.split().0, &mut adc, &mut dac);
    }
    let held = (dac.left, dac.right);
    let r = handler.handle(Request::LoadParams(second), &mut producer, locks!());
    assert!(matches!(r, Response::Ack { .. }), "{r:?}");
    control.tick(&mut consumer, &mut snapshots.split().0, &mut adc, &mut dac);
    let step = |a: DacCode, b: DacCode| (a.0 as i32 - b.0 as i32).abs();
    assert!(
        step(held.0, dac.left) <= 1 && step(held.1, dac.right) <= 1,
        "swap tick moved the outputs: {held:?} → {:?}",
        (dac.left, dac.right)
    );
    assert_eq!(
        control.telemetry().ticks,
        101,
        "the tick count goes on across the swap"
    );
    let _spare = control.spare();
    assert_eq!(
        control.telemetry().ticks,
        101,
        "and when the handler takes the spare back"
    );
}
