//! The analog setpoint input on the in-process board (`SimDevice`: the library's command
//! handler and control loop, the simulated stage, a voltage on the input's pin): a step on the
//! input reaches the DAC within one tick and compensated exactly as the same setpoints
//! streamed; a lost or over-range input holds or ramps to rest and comes back without a jump,
//! never stepping the DAC beyond the slew limit; the other sources and the analog input
//! refuse each other; the status flags report it.

#[path = "support/virtual_board_process.rs"]
mod virtual_board_process;

use hal_sim::analog_source::AnalogSource;
use hal_sim::sim_device::{SimDevice, SimDeviceConfig};
use twinstack::board::DacCode;
use twinstack::fixed_point::SIGNAL_ONE;
use twinstack::protocol::messages::{
    Mode, NackReason, PackedBatch, Request, Response, StatusReport, StreamControl,
};
use twinstack::refusal::Field;
use twinstack::sources::analog_input::{AnalogInputConfig, AnalogRequest, AnalogStatus, OnFault};

const RATE: f64 = 50_000.0;

fn device(mode: Mode) -> SimDevice {
    let config = SimDeviceConfig {
        stored: Some(SimDeviceConfig::paper_settings(mode)),
        ..SimDeviceConfig::paper()
    };
    SimDevice::new(config).unwrap()
}

/// 0–3.3 V at the pin onto the whole stroke: −1 + 2 · reading. A 12-bit code `c` gives the
/// setpoint −1 + c / 2048, a whole Q1.15 wire sample (−32768 + 16 c): what a stream can send.
fn config(on_fault: OnFault) -> AnalogInputConfig {
    AnalogInputConfig {
        gain: 2.0,
        offset: -1.0,
        corner_hz: None,
        lost_below: 0.05,
        over_above: 0.95,
        on_fault,
        rate: 20.0,
        start_at_boot: false,
    }
}

fn ack(dev: &mut SimDevice, request: Request) {
    match dev.handle(&request) {
        Response::Ack { .. } => {}
        r => panic!("{request:?}: {r:?}"),
    }
}

fn analog_status(dev: &mut SimDevice) -> AnalogStatus {
    match dev.handle(&Request::Analog(AnalogRequest::Status)) {
        Response::Analog(s) => s,
        r => panic!("{r:?}"),
    }
}

fn status(dev: &mut SimDevice) -> StatusReport {
    match dev.handle(&Request::Status) {
        Response::Status(s) => s,
        r => panic!("{r:?}"),
    }
}

fn dac(dev: &SimDevice) -> (DacCode, DacCode) {
    let r = dev.last_report().unwrap();
    (r.left, r.right)
}

/// The 12-bit code the board's ADC gives for `volts` at the pin.
fn code(volts: f64) -> i32 {
    (volts / 3.3 * 4095.0).round() as i32
}

/// Largest DAC change one tick the drive's slew limit allows, codes (paper settings: 150 V
/// over 4095 codes).
fn slew_codes() -> i32 {
    let d = SimDeviceConfig::paper_settings(Mode::OpenLoop).drive;
    (d.slew_rate / RATE / 150.0 * 4095.0).ceil() as i32
}

fn step_of(a: (DacCode, DacCode), b: (DacCode, DacCode)) -> i32 {
    (a.0 .0 as i32 - b.0 .0 as i32)
        .abs()
        .max((a.1 .0 as i32 - b.1 .0 as i32).abs())
}

#[test]
fn a_step_on_the_input_reaches_the_dac_within_one_tick_compensated_as_a_stream() {
    for mode in [Mode::OpenLoop, Mode::ClosedLoop] {
        let mut analog = device(mode);
        let mut stream = device(mode);
        // Two identical boards (same stage, same noise seeds): one fed by the analog input,
        // one by the stream, with the same setpoint every tick.
        let at = analog.ticks() + 200;
        let (v0, v1) = (1.2, 2.6);
        analog.set_analog_input(AnalogSource::Step {
            before: v0,
            after: v1,
            at_tick: at,
        });
        // A rate of the whole range in one tick: the input's first reading is taken at once.
        let c = AnalogInputConfig {
            rate: 2.0 * RATE as f32,
            ..config(OnFault::Hold)
        };
        ack(&mut analog, Request::Analog(AnalogRequest::Start(c)));
        let wire = |v: f64| (-32768 + 16 * code(v)) as i16;
        let mut samples: Vec<i16> = vec![wire(v0); (at - stream.ticks()) as usize];
        samples.extend(std::iter::repeat_n(wire(v1), 400));
        for (seq, chunk) in samples.chunks(64).enumerate() {
            ack(
                &mut stream,
                Request::PackedSetpoints(PackedBatch {
                    seq: seq as u16,
                    samples: heapless::Vec::from_slice(chunk).unwrap(),
                }),
            );
        }
        ack(&mut stream, Request::Stream(StreamControl::Start));
        assert_eq!(analog.ticks(), stream.ticks());
        let mut before = None;
        let mut moved_at = None;
        for _ in 0..500 {
            let tick = analog.ticks();
            analog.tick();
            stream.tick();
            let (a, s) = (dac(&analog), dac(&stream));
            assert_eq!(a, s, "{mode:?}: tick {tick}: analog {a:?}, streamed {s:?}");
            if tick > at - 50 && tick < at && before.is_none() {
                before = Some(a);
            }
            if tick >= at - 40 && moved_at.is_none() && before.is_some_and(|b| b != a) {
                moved_at = Some(tick);
            }
        }
        // The tick that converts the step writes the first moved DAC sample (in closed loop
        // the sensor's noise moves the DAC every tick: there the equality above holds it).
        if mode == Mode::OpenLoop {
            assert_eq!(moved_at, Some(at), "{mode:?}");
        }
        let s = analog_status(&mut analog);
        assert!(
            s.running && !s.lost && !s.over_range && s.faults == 0,
            "{s:?}"
        );
        assert_eq!(s.setpoint, (wire(v1) as i32) << 15);
        assert!(status(&mut analog).has(StatusReport::ANALOG));
    }
}

/// Runs `ticks` ticks, asserting no DAC step beyond the slew limit and no setpoint step
/// beyond the input's rate (`limit`, Q2.30); returns the analog status after.
fn run_checked(dev: &mut SimDevice, ticks: usize, limit: i32) -> AnalogStatus {
    if dev.last_report().is_none() {
        dev.tick();
    }
    let mut last_dac = dac(dev);
    let mut last = dev.control().analog_status().setpoint;
    for _ in 0..ticks {
        dev.tick();
        let now = dac(dev);
        assert!(
            step_of(now, last_dac) <= slew_codes(),
            "{now:?} after {last_dac:?}"
        );
        last_dac = now;
        let s = dev.control().analog_status().setpoint;
        assert!((s - last).abs() <= limit, "setpoint {s} after {last}");
        last = s;
    }
    dev.control().analog_status()
}

/// The setpoint's largest step a tick at `config`'s rate, Q2.30 (and one LSB of rounding).
fn rate_step(c: &AnalogInputConfig) -> i32 {
    (c.rate as f64 / RATE * SIGNAL_ONE as f64).round() as i32 + 1
}

#[test]
fn a_lost_input_holds_and_an_over_range_one_ramps_to_rest_and_both_come_back_without_a_jump() {
    for on_fault in [OnFault::Hold, OnFault::RampToRest] {
        for fault in [
            AnalogSource::Disconnected,
            AnalogSource::Constant(3.25),
            AnalogSource::NoConversion,
        ] {
            let mut dev = device(Mode::OpenLoop);
            let c = config(on_fault);
            let limit = rate_step(&c);
            dev.set_analog_input(AnalogSource::Constant(2.4));
            ack(&mut dev, Request::Analog(AnalogRequest::Start(c)));
            // From rest to the input's value at 20 /s: under 0.1 s.
            let s = run_checked(&mut dev, 5_000, limit);
            let live = (-32768 + 16 * code(2.4)) << 15;
            assert_eq!(s.setpoint, live, "{on_fault:?}");
            dev.set_analog_input(fault);
            let s = run_checked(&mut dev, 10_000, limit);
            let over = matches!(fault, AnalogSource::Constant(_));
            assert_eq!(
                (s.lost, s.over_range, s.faults),
                (!over, over, 1),
                "{fault:?}"
            );
            let st = status(&mut dev);
            assert!(st.has(StatusReport::ANALOG) && st.has(StatusReport::ANALOG_FAULT));
            let rest = dev.control().controller().rest_setpoint();
            match on_fault {
                OnFault::Hold => assert_eq!(s.setpoint, live),
                OnFault::RampToRest => assert_eq!(s.setpoint, rest),
            }
            // Back, somewhere else: walks there at the rate, no jump, then tracks.
            dev.set_analog_input(AnalogSource::Constant(0.9));
            let s = run_checked(&mut dev, 10_000, limit);
            assert_eq!(s.setpoint, (-32768 + 16 * code(0.9)) << 15);
            assert!(!s.lost && !s.over_range && s.faults == 1);
            assert!(!status(&mut dev).has(StatusReport::ANALOG_FAULT));
        }
    }
}

#[test]
fn the_analog_input_and_the_other_sources_refuse_each_other() {
    let mut dev = device(Mode::OpenLoop);
    ack(&mut dev, Request::Stream(StreamControl::Start));
    let start = Request::Analog(AnalogRequest::Start(config(OnFault::Hold)));
    assert_eq!(
        dev.handle(&start),
        Response::Nack {
            reason: NackReason::Busy
        }
    );
    assert!(!analog_status(&mut dev).running);
    ack(&mut dev, Request::Stream(StreamControl::Stop));
    ack(&mut dev, start);
    for other in [
        Request::Stream(StreamControl::Start),
        Request::Sequence(twinstack::sources::sequence::SequenceRequest::Arm(
            twinstack::sources::sequence::SequenceConfig {
                edge: twinstack::sources::scan::TriggerEdge::Rising,
                window: 0.01,
                settle_ticks: 1,
            },
        )),
    ] {
        assert_eq!(
            dev.handle(&other),
            Response::Nack {
                reason: NackReason::Busy
            },
            "{other:?}"
        );
    }
    assert!(analog_status(&mut dev).running);
    // Stop (the analog request's or the stream's) ends it; the setpoint holds.
    ack(&mut dev, Request::Analog(AnalogRequest::Stop));
    assert!(!analog_status(&mut dev).running);
    assert!(!status(&mut dev).has(StatusReport::ANALOG));
    ack(&mut dev, Request::Stream(StreamControl::Start));
}

#[test]
fn hostile_settings_are_refused_with_the_field() {
    let mut dev = device(Mode::OpenLoop);
    let ok = config(OnFault::RampToRest);
    for (c, field) in [
        (
            AnalogInputConfig {
                gain: f32::NAN,
                ..ok
            },
            Field::AnalogGain,
        ),
        (
            AnalogInputConfig {
                lost_below: 0.7,
                over_above: 0.3,
                ..ok
            },
            Field::AnalogOverAbove,
        ),
        (AnalogInputConfig { rate: 0.0, ..ok }, Field::AnalogRate),
        (AnalogInputConfig { rate: -5.0, ..ok }, Field::AnalogRate),
        (
            AnalogInputConfig {
                corner_hz: Some(f32::INFINITY),
                ..ok
            },
            Field::AnalogCorner,
        ),
    ] {
        match dev.handle(&Request::Analog(AnalogRequest::Start(c))) {
            Response::Nack {
                reason: NackReason::Refused(r),
            } => assert_eq!(r.field, field, "{c:?}"),
            r => panic!("{c:?}: {r:?}"),
        }
        assert!(!analog_status(&mut dev).running);
    }
}

#[test]
fn a_stored_input_with_start_at_boot_runs_from_power_up_without_a_host() {
    for start_at_boot in [true, false] {
        let c = AnalogInputConfig {
            start_at_boot,
            ..config(OnFault::RampToRest)
        };
        let mut dev = SimDevice::new(SimDeviceConfig {
            stored: Some(SimDeviceConfig::paper_settings(Mode::OpenLoop)),
            stored_analog: Some(c),
            ..SimDeviceConfig::paper()
        })
        .unwrap();
        dev.set_analog_input(AnalogSource::Constant(2.4));
        // No request at all: the board's own boot.
        let s = run_checked(&mut dev, 5_000, rate_step(&c));
        assert_eq!(s.running, start_at_boot);
        if start_at_boot {
            assert_eq!(s.setpoint, (-32768 + 16 * code(2.4)) << 15);
        } else {
            assert_eq!(s.setpoint, 0);
        }
    }
    // A board on its defaults (nothing stored) never starts a stored input.
    let mut dev = SimDevice::new(SimDeviceConfig {
        stored: None,
        stored_analog: Some(AnalogInputConfig {
            start_at_boot: true,
            ..config(OnFault::Hold)
        }),
        ..SimDeviceConfig::paper()
    })
    .unwrap();
    dev.tick();
    assert!(!dev.control().analog_status().running);
}

#[test]
fn store_params_keeps_the_input_last_started_for_the_next_power_up() {
    let mut dev = device(Mode::OpenLoop);
    let c = AnalogInputConfig {
        start_at_boot: true,
        ..config(OnFault::Hold)
    };
    ack(&mut dev, Request::Analog(AnalogRequest::Start(c)));
    // Storing stalls the tick: refused while the input runs, as while a stream runs.
    assert_eq!(
        dev.handle(&Request::StoreParams {
            boot_mode: Mode::OpenLoop
        }),
        Response::Nack {
            reason: NackReason::Busy
        }
    );
    ack(&mut dev, Request::Analog(AnalogRequest::Stop));
    ack(
        &mut dev,
        Request::StoreParams {
            boot_mode: Mode::OpenLoop,
        },
    );
    let record = twinstack::config::param_store::StoredRecord::decode(
        twinstack::config::param_store::RecordStorage::read(dev.handler().storage()),
        &hal_sim::sim_device::hardware(RATE),
    )
    .unwrap();
    assert_eq!(record.analog, Some(c));
}

#[test]
fn the_command_refuses_hostile_settings_by_name_and_starts_and_reads_the_input() {
    let run = |args: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
            .args(args)
            .output()
            .unwrap()
    };
    for (flag, value, field) in [
        ("--rate", "0", "analog rate"),
        ("--gain", "NaN", "analog gain"),
        ("--over-above", "0.01", "analog over_above"),
    ] {
        let out = run(&[
            "analog",
            "start",
            "--port",
            "sim",
            "--lost-below",
            "0.02",
            flag,
            value,
        ]);
        assert!(!out.status.success(), "{flag} {value}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            err.contains(field) && err.contains("nothing was sent"),
            "{err}"
        );
    }
    let out = run(&["analog", "start", "--port", "sim"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = run(&["analog", "status", "--port", "sim", "--json"]);
    assert!(out.status.success());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["running"], false, "a fresh simulated board per command");
    // --start-at-boot is a stored setting.
    let out = run(&["analog", "start", "--port", "sim", "--start-at-boot"]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("--store"));
}

/// A virtual board with a voltage on its analog input (`--analog-input`): `twinstack analog
/// start` makes it the setpoint source, the status reads the pin as the ADC converts it and
/// names the flag, and the output walks to the input's value; a bad spec is one line naming
/// it, nothing served.
#[test]
fn a_virtual_board_s_analog_input_is_driven_from_the_command_line() {
    let run = |args: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
            .args(args)
            .output()
            .unwrap()
    };
    // Three quarters of 3.3 V: gain 2, offset −1 maps it onto +0.5 of the output range.
    let (_board, port) = virtual_board_process::start(&["--speed", "0", "--analog-input", "2.475"]);
    let out = run(&["analog", "start", "--port", &port, "--rate", "50"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = run(&["status", "--port", &port, "--json"]);
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let flags: Vec<&str> = v["flags"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_str().unwrap())
        .collect();
    assert!(
        flags.contains(&"analog") && !flags.contains(&"analog-fault"),
        "{v}"
    );
    let status = || {
        let out = run(&["analog", "status", "--port", &port, "--json"]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        serde_json::from_slice::<serde_json::Value>(&out.stdout).unwrap()
    };
    let start = std::time::Instant::now();
    let a = loop {
        let a = status();
        assert_eq!(a["running"], true, "{a}");
        assert!((a["reading"].as_f64().unwrap() - 0.75).abs() < 1e-3, "{a}");
        if (a["setpoint"].as_f64().unwrap() - 0.5).abs() < 1e-3 {
            break a;
        }
        assert!(
            start.elapsed() < std::time::Duration::from_secs(30),
            "never reached: {a}"
        );
    };
    assert_eq!(a["faults"], 0, "{a}");
    for (spec, needle) in [
        ("sine:1,2", "sine:MEAN,AMPLITUDE,HZ"),
        ("volts", "the voltage"),
        ("nan", "not a finite number"),
    ] {
        let out = run(&[
            "virtual-board",
            "--listen",
            "tcp:127.0.0.1:0",
            "--analog-input",
            spec,
        ]);
        assert_eq!(out.status.code(), Some(2), "{spec}");
        assert!(out.stdout.is_empty(), "{spec} served");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(needle), "{spec}: {err}");
    }
}
