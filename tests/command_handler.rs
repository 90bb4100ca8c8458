//! The board's command handler against every request and every NACK reason, on the same
//! control loop the firmware runs (fake converters): each request gets one response; a
//! refused one applies nothing and loses nothing queued, and its NACK names the field and
//! the rule (with its limit) it broke; a load is prepared off the tick and swapped in between
//! two ticks; the board boots as the firmware does (`param_store::load_record` + `boot`).

use core::convert::Infallible;

use twinstack::board::{AdcCode, DacCode, DualDac, Hardware, SensorAdc};
use twinstack::command_handler::{start_services, CommandHandler, Parts};
use twinstack::config::param_store::{
    self, RamStorage, ReadOnlyStorage, RecordStorage, StorageError, StoredRecord, MAX_RECORD,
};
use twinstack::config::settings::{
    representative_bouc_wen, representative_duhem, representative_pi, FeedbackSettings, Mode,
    Model, NotchDesign, SensorSettings, Settings,
};
use twinstack::control::drive::SafeState;
use twinstack::control::Controller;
use twinstack::control_loop::{ControlLoop, SetpointQueue, SETPOINT_CAPACITY};
use twinstack::protocol::decoder::FrameDecoder;
use twinstack::protocol::frame::{self, FrameError, MAX_ENCODED, PROTOCOL_VERSION};
use twinstack::protocol::messages::*;
use twinstack::refusal::{Field, ModelField, Refusal, Rule};
use twinstack::services::consumer::Services;
use twinstack::services::recorder::Channel;
use twinstack::services::snapshot::SnapshotRing;
use twinstack::services::telemetry::TelemetryQueue;
use twinstack::sources::SetpointSource;

struct Dac(DacCode, DacCode);
impl DualDac for Dac {
    type Error = Infallible;
    fn full_scale(&self) -> DacCode {
        DacCode(4095)
    }
    fn write_both(&mut self, l: DacCode, r: DacCode) -> Result<(), Infallible> {
        (self.0, self.1) = (l, r);
        Ok(())
    }
}
struct Adc(u32);
impl SensorAdc for Adc {
    type Error = Infallible;
    fn full_scale(&self) -> AdcCode {
        AdcCode(4095)
    }
    fn read(&mut self) -> Result<AdcCode, Infallible> {
        Ok(AdcCode(self.0))
    }
}

/// Storage whose writes always fail (a flash that does not program).
struct BrokenFlash([u8; 16]);
impl RecordStorage for BrokenFlash {
    fn read(&self) -> &[u8] {
        &self.0
    }
    fn write(&mut self, _: &[u8]) -> Result<(), StorageError> {
        Err(StorageError::WriteFailed)
    }
}

const RATE: u32 = 50_000;
/// Values a v3 record holds (the buffer: two 16-bit slots each).
const RECORD_LEN: usize = 4096;

fn hardware() -> Hardware {
    Hardware::driver_board(RATE as f64)
}

/// A board: handler, control loop, queue, converters.
struct Board<S> {
    handler: CommandHandler<S>,
    control: ControlLoop<Box<Controller>>,
    services: Services<Vec<i16>>,
    queue: &'static mut SetpointQueue,
    snapshots: &'static mut SnapshotRing,
    telemetry: &'static mut TelemetryQueue,
    dac: Dac,
    adc: Adc,
    /// The loop's swap count before the last request.
    swaps_before: u32,
}

/// A board booted from `storage` on `hw` exactly as the firmware boots: the stored record if
/// it is sound and holds here, else the compiled-in defaults (bypass, no model).
fn board_on<S: RecordStorage>(storage: S, hw: Hardware) -> Board<S> {
    let (record, source) = param_store::load_record(storage.read(), &hw);
    let (settings, config, defaults) =
        param_store::boot(record, source, &hw).expect("the defaults hold on the driver board");
    let mut b = Board {
        handler: CommandHandler::new(hw, settings, defaults, storage),
        control: ControlLoop::new(
            Box::new(Controller::new(config)),
            Box::new(Controller::new(config)),
            hw.control_rate_hz.round() as u32,
        ),
        services: Services::new(vec![0i16; 2 * RECORD_LEN]),
        queue: Box::leak(Box::new(SetpointQueue::new())),
        snapshots: Box::leak(Box::new(SnapshotRing::new())),
        telemetry: Box::leak(Box::new(TelemetryQueue::new())),
        dac: Dac(DacCode(0), DacCode(0)),
        adc: Adc(2048),
        swaps_before: 0,
    };
    start_services(&config, &mut b.control, &mut b.services);
    b
}

fn board_with<S: RecordStorage>(storage: S) -> Board<S> {
    board_on(storage, hardware())
}

/// A fresh board: erased flash, so bypass on the defaults.
fn board() -> Board<RamStorage> {
    board_with(RamStorage::default())
}

/// A fresh board with [`closed`] loaded and swapped in.
fn closed_board() -> Board<RamStorage> {
    let mut b = board();
    assert!(matches!(
        b.handle(Request::LoadParams(closed())),
        Response::Ack { .. }
    ));
    b.ticks(1);
    b
}

/// Valid closed-loop settings with every optional float present: a 16-operator P–I
/// compensator, a Duhem observer, a drift limit, PID feedback with a notch.
fn closed() -> Settings {
    let mut s = Settings {
        compensator: Some(representative_pi(16).unwrap()),
        observer: Some(representative_duhem()),
        feedback: Some(FeedbackSettings {
            kd: 1e-6,
            derivative_cutoff_hz: 5_000.0,
            notch: Some(NotchDesign {
                frequency_hz: 2_000.0,
                q: 2.0,
                depth: 0.1,
            }),
            ..FeedbackSettings::pi(0.2, 500.0, 0.1)
        }),
        mode: Mode::ClosedLoop,
        ..Settings::default()
    };
    s.sensor = Some(SensorSettings {
        drift_limit: Some(0.2),
        ..s.sensor.unwrap()
    });
    s
}

impl<S: RecordStorage> Board<S> {
    fn handle(&mut self, request: Request) -> Response {
        self.swaps_before = self.control.swaps();
        let (mut p, _) = self.queue.split();
        let mut locks = Parts::new(
            &mut self.control,
            &mut self.services,
            self.snapshots,
            self.telemetry,
        );
        self.handler.handle(request, &mut p, &mut locks)
    }

    /// Bytes in, response frames out (decoded).
    fn bytes(&mut self, bytes: &[u8]) -> Vec<Response> {
        self.swaps_before = self.control.swaps();
        let (mut p, _) = self.queue.split();
        let mut frames = Vec::new();
        let mut locks = Parts::new(
            &mut self.control,
            &mut self.services,
            self.snapshots,
            self.telemetry,
        );
        self.handler
            .receive(bytes, &mut p, &mut locks, |f| frames.push(f.to_vec()));
        frames.iter().map(|f| decode_response(f)).collect()
    }

    fn ticks(&mut self, n: usize) {
        for _ in 0..n {
            self.tick();
        }
    }

    /// One tick, and the services' batch when it is due, as the board runs them; whether the
    /// services woke the telemetry packer.
    fn tick(&mut self) -> bool {
        let (_, mut c) = self.queue.split();
        let (mut snapshots, mut served) = self.snapshots.split();
        self.control
            .tick(&mut c, &mut snapshots, &mut self.adc, &mut self.dac);
        let (mut samples, _) = self.telemetry.split();
        self.control.services_due() && self.services.consume(&mut served, &mut samples)
    }

    fn status(&mut self) -> StatusReport {
        match self.handle(Request::Status) {
            Response::Status(s) => s,
            r => panic!("{r:?}"),
        }
    }

    fn read_params(&mut self) -> Settings {
        match self.handle(Request::ReadParams) {
            Response::Params(s) => s,
            r => panic!("{r:?}"),
        }
    }

    fn queued(&mut self) -> Vec<i16> {
        self.queue.iter().copied().collect()
    }

    fn outputs(&self) -> (DacCode, DacCode) {
        (self.dac.0, self.dac.1)
    }
}

fn decode_response(frame: &[u8]) -> Response {
    let mut d = FrameDecoder::new();
    let (&last, rest) = frame.split_last().unwrap();
    assert_eq!(last, 0, "a response frame ends with its delimiter");
    for &b in rest {
        assert!(d.push(b).is_none(), "one frame per response");
    }
    frame::decode_body(d.push(0).unwrap().unwrap()).unwrap()
}

fn encoded(r: &Request) -> Vec<u8> {
    let mut out = vec![0u8; MAX_ENCODED + 1];
    let n = frame::encode(r, &mut out).unwrap();
    out.truncate(n);
    out
}

fn batch(seq: u16, samples: &[i16]) -> Request {
    Request::Setpoints(SetpointBatch {
        seq,
        samples: heapless::Vec::from_slice(samples).unwrap(),
    })
}

fn nack(reason: NackReason) -> Response {
    Response::Nack { reason }
}

fn refused(field: Field, rule: Rule) -> Response {
    nack(NackReason::Refused(Refusal::new(field, rule)))
}

/// Refused requests leave everything as it was: the queue, the settings (as the handler holds
/// them and as `ReadParams` reports them), the sequence; nothing was posted to the tick.
fn assert_nothing_changed<S: RecordStorage>(b: &mut Board<S>, queued: &[i16], settings: &Settings) {
    assert_eq!(b.queued(), queued, "queued setpoints lost or added");
    assert_eq!(b.handler.settings(), settings, "settings changed");
    assert_eq!(&b.read_params(), settings, "settings read back changed");
    assert_eq!(
        b.control.swaps(),
        b.swaps_before,
        "a configuration was swapped in"
    );
}

#[test]
fn setpoint_batches_need_the_next_sequence_number_and_room() {
    let mut b = board();
    assert_eq!(
        b.handle(batch(0, &[1, 2, 3])),
        Response::Ack {
            credits: SETPOINT_CAPACITY as u16 - 3
        }
    );
    let params = b.handler.settings().clone();
    // Out of sequence: refused, nothing queued.
    assert_eq!(
        b.handle(batch(7, &[9; 10])),
        nack(NackReason::OutOfSequence { expected: 1 })
    );
    assert_nothing_changed(&mut b, &[1, 2, 3], &params);
    // Fill to the brim, then one over: refused whole.
    let mut seq = 1;
    let mut queued = vec![1, 2, 3];
    while queued.len() + MAX_BATCH <= SETPOINT_CAPACITY {
        assert!(matches!(
            b.handle(batch(seq, &[5; MAX_BATCH])),
            Response::Ack { .. }
        ));
        queued.extend([5; MAX_BATCH]);
        seq += 1;
    }
    let free = SETPOINT_CAPACITY - queued.len();
    assert_eq!(
        b.handle(batch(seq, &vec![6; free + 1])),
        nack(NackReason::QueueFull)
    );
    assert_nothing_changed(&mut b, &queued, &params);
    assert_eq!(
        b.handle(batch(seq, &vec![6; free])),
        Response::Ack { credits: 0 }
    );
    // The sequence number wraps.
    let mut b = board();
    for seq in 0..=u16::MAX {
        assert!(matches!(b.handle(batch(seq, &[])), Response::Ack { .. }));
    }
    assert!(matches!(b.handle(batch(0, &[])), Response::Ack { .. }));
}

#[test]
fn stream_control_starts_stops_sets_the_rate_and_the_underrun_policy() {
    let mut b = board();
    assert!(matches!(
        b.handle(batch(0, &[1000, 2000])),
        Response::Ack { .. }
    ));
    assert_eq!(
        b.handle(Request::Stream(StreamControl::Rate { divider: 0 })),
        refused(Field::Divider, Rule::AtLeast(1.0))
    );
    assert!(matches!(
        b.handle(Request::Stream(StreamControl::Rate { divider: 2 })),
        Response::Ack { .. }
    ));
    b.ticks(3);
    assert_eq!(b.queued(), vec![1000, 2000], "stopped: nothing consumed");
    assert!(matches!(
        b.handle(Request::Stream(StreamControl::Start)),
        Response::Ack { .. }
    ));
    b.ticks(4);
    assert_eq!(b.control.controller().setpoint(), 2000 << 15);
    let s = b.status();
    assert!(s.has(StatusReport::STREAMING));
    assert_eq!((s.underruns, s.queue_fill), (0, 0));
    // Dry: hold counts underruns and keeps the last setpoint.
    b.ticks(5);
    assert_eq!(b.status().underruns, 5);
    assert_eq!(b.control.controller().setpoint(), 2000 << 15);
    // Ramp to the bias: walks towards the rest position and counts.
    assert!(matches!(
        b.handle(Request::Stream(StreamControl::Underrun(
            UnderrunPolicy::RampToBias
        ))),
        Response::Ack { .. }
    ));
    let rest = b.control.controller().rest_setpoint();
    b.ticks(10);
    assert_eq!(b.status().underruns, 15);
    let d = (b.control.controller().setpoint() as i64 - rest as i64).abs();
    assert!(
        d < ((2000i64 << 15) - rest as i64).abs(),
        "moved towards rest"
    );
    b.ticks(2000);
    assert_eq!(b.control.controller().setpoint(), rest);
    assert!(matches!(
        b.handle(Request::Stream(StreamControl::Stop)),
        Response::Ack { .. }
    ));
    assert!(!b.status().has(StatusReport::STREAMING));
}

#[test]
fn a_parameter_load_is_validated_whole_and_swapped_in_between_two_ticks() {
    let mut b = board();
    b.ticks(10);
    let mut p = closed();
    p.drive.safe_state = SafeState::Zero;
    p.mode = Mode::OpenLoop;
    assert!(matches!(
        b.handle(Request::LoadParams(p.clone())),
        Response::Ack { .. }
    ));
    // Prepared off the tick and swapped in, in O(1), when the load is acknowledged: the next
    // tick runs it.
    assert_eq!(b.control.swaps(), b.swaps_before + 1);
    assert_eq!(b.control.controller().mode(), Mode::OpenLoop);
    let s = b.status();
    assert_eq!(s.mode(), Mode::OpenLoop);
    assert!(
        !s.has(StatusReport::DEFAULTS),
        "loaded settings are not the defaults"
    );
    // The mode bits sit beside the image's: a host build of the handler is the simulator.
    assert_eq!(s.image(), Image::Simulator, "{s:?}");
    b.ticks(1);
    // Open loop now (the feedback stays configured, idle, so a later mode switch needs no
    // new settings).
    assert_eq!(b.control.controller().mode(), Mode::OpenLoop);
    assert!(b.control.controller().feedback_config().is_some());
    assert_eq!(
        b.control.safe_codes(),
        (DacCode(0), DacCode(0)),
        "safe state: zero"
    );
    assert_eq!(b.handler.settings(), &p);
    assert_eq!(b.read_params(), p, "ReadParams returns the settings loaded");
    assert!(matches!(
        b.handle(Request::Mode(Mode::ClosedLoop)),
        Response::Ack { .. }
    ));
    b.ticks(1);
    assert_eq!(b.control.controller().mode(), Mode::ClosedLoop);
}

/// A setter of one `f64` field of the settings, and the field a refusal of it must name.
type FloatField = (String, Field, Box<dyn Fn(&mut Settings, f64)>);

fn model_fields(which: &str, model: &Model, field: fn(ModelField) -> Field) -> Vec<FloatField> {
    fn model_of<'a>(s: &'a mut Settings, which: &str) -> &'a mut Model {
        match which {
            "compensator" => s.compensator.as_mut().unwrap(),
            _ => s.observer.as_mut().unwrap(),
        }
    }
    let w = which.to_string();
    let mut out: Vec<FloatField> = Vec::new();
    match model {
        Model::PrandtlIshlinskii(p) => {
            let m = w.clone();
            out.push((
                format!("{w}.a0"),
                field(ModelField::A0),
                Box::new(move |s, x| {
                    if let Model::PrandtlIshlinskii(p) = model_of(s, &m) {
                        p.a0 = x
                    }
                }),
            ));
            let m = w.clone();
            out.push((
                format!("{w}.offset"),
                field(ModelField::Offset),
                Box::new(move |s, x| {
                    if let Model::PrandtlIshlinskii(p) = model_of(s, &m) {
                        p.offset = x
                    }
                }),
            ));
            for i in 0..p.thresholds.len() {
                let m = w.clone();
                out.push((
                    format!("{w}.thresholds[{i}]"),
                    field(ModelField::Threshold(i as u8 + 1)),
                    Box::new(move |s, x| {
                        if let Model::PrandtlIshlinskii(p) = model_of(s, &m) {
                            p.thresholds[i] = x
                        }
                    }),
                ));
            }
            for i in 0..p.weights.len() {
                let m = w.clone();
                out.push((
                    format!("{w}.weights[{i}]"),
                    field(ModelField::Weight(i as u8 + 1)),
                    Box::new(move |s, x| {
                        if let Model::PrandtlIshlinskii(p) = model_of(s, &m) {
                            p.weights[i] = x
                        }
                    }),
                ));
            }
        }
        Model::Duhem(_) => {
            type Set = fn(&mut twinstack::DuhemParams, f64);
            let parts: [(&str, ModelField, Set); 4] = [
                ("alpha", ModelField::Alpha, |p, x| p.alpha = x),
                ("beta", ModelField::Beta, |p, x| p.beta = x),
                ("gamma", ModelField::Gamma, |p, x| p.gamma = x),
                ("offset", ModelField::Offset, |p, x| p.offset = x),
            ];
            for (name, f, set) in parts {
                let m = w.clone();
                out.push((
                    format!("{w}.{name}"),
                    field(f),
                    Box::new(move |s, x| {
                        if let Model::Duhem(p) = model_of(s, &m) {
                            set(p, x)
                        }
                    }),
                ));
            }
        }
        Model::GeneralisedPi(g) => {
            // The P–I part's fields keep the P–I's names; then the dead-zone map's.
            type Get = fn(&mut twinstack::models::generalised_pi::GpiParams, usize) -> &mut f64;
            let mut parts: Vec<(String, ModelField, Get, usize)> = vec![
                ("a0".into(), ModelField::A0, |p, _| &mut p.pi.a0, 0),
                (
                    "offset".into(),
                    ModelField::Offset,
                    |p, _| &mut p.pi.offset,
                    0,
                ),
                (
                    "dead_zones.centre".into(),
                    ModelField::DeadZoneCentre,
                    |p, _| &mut p.dead_zones.centre,
                    0,
                ),
                (
                    "dead_zones.linear".into(),
                    ModelField::DeadZoneLinear,
                    |p, _| &mut p.dead_zones.linear,
                    0,
                ),
            ];
            for i in 0..g.pi.thresholds.len() {
                parts.push((
                    format!("thresholds[{i}]"),
                    ModelField::Threshold(i as u8 + 1),
                    |p, i| &mut p.pi.thresholds[i],
                    i,
                ));
                parts.push((
                    format!("weights[{i}]"),
                    ModelField::Weight(i as u8 + 1),
                    |p, i| &mut p.pi.weights[i],
                    i,
                ));
            }
            for i in 0..g.dead_zones.thresholds.len() {
                parts.push((
                    format!("dead_zones.thresholds[{i}]"),
                    ModelField::DeadZoneThreshold(i as u8 + 1),
                    |p, i| &mut p.dead_zones.thresholds[i],
                    i,
                ));
                parts.push((
                    format!("dead_zones.weights[{i}]"),
                    ModelField::DeadZoneWeight(i as u8 + 1),
                    |p, i| &mut p.dead_zones.weights[i],
                    i,
                ));
            }
            for (name, f, get, i) in parts {
                let m = w.clone();
                out.push((
                    format!("{w}.{name}"),
                    field(f),
                    Box::new(move |s, x| {
                        if let Model::GeneralisedPi(p) = model_of(s, &m) {
                            *get(p, i) = x
                        }
                    }),
                ));
            }
        }
        Model::BoucWen(_) => {
            type Set = fn(&mut twinstack::BoucWenParams, f64);
            let parts: [(&str, ModelField, Set); 7] = [
                ("k", ModelField::K, |p, x| p.k = x),
                ("offset", ModelField::Offset, |p, x| p.offset = x),
                ("a", ModelField::A, |p, x| p.a = x),
                ("beta", ModelField::Beta, |p, x| p.beta = x),
                ("gamma", ModelField::Gamma, |p, x| p.gamma = x),
                ("psi", ModelField::Psi, |p, x| p.psi = x),
                ("chi", ModelField::Chi, |p, x| p.chi = x),
            ];
            for (name, f, set) in parts {
                let m = w.clone();
                out.push((
                    format!("{w}.{name}"),
                    field(f),
                    Box::new(move |s, x| {
                        if let Model::BoucWen(p) = model_of(s, &m) {
                            set(p, x)
                        }
                    }),
                ));
            }
        }
    }
    out
}

/// Every `f64` of `s` (which has every optional part present), with the field it is.
fn float_fields(s: &Settings) -> Vec<FloatField> {
    type Set = fn(&mut Settings, f64);
    let plain: [(&str, Field, Set); 17] = [
        ("ranges.input_min", Field::InputRange, |s, x| {
            s.ranges.input_min = x
        }),
        ("ranges.input_max", Field::InputRange, |s, x| {
            s.ranges.input_max = x
        }),
        ("ranges.output_min", Field::OutputRange, |s, x| {
            s.ranges.output_min = x
        }),
        ("ranges.output_max", Field::OutputRange, |s, x| {
            s.ranges.output_max = x
        }),
        ("drive.bias", Field::Bias, |s, x| s.drive.bias = x),
        ("drive.min_voltage", Field::VoltageLimits, |s, x| {
            s.drive.min_voltage = x
        }),
        ("drive.max_voltage", Field::VoltageLimits, |s, x| {
            s.drive.max_voltage = x
        }),
        ("drive.slew_rate", Field::SlewRate, |s, x| {
            s.drive.slew_rate = x
        }),
        (
            "sensor.displacement_at_zero",
            Field::SensorCalibration,
            |s, x| s.sensor.as_mut().unwrap().displacement_at_zero = x,
        ),
        (
            "sensor.displacement_at_full_scale",
            Field::SensorCalibration,
            |s, x| s.sensor.as_mut().unwrap().displacement_at_full_scale = x,
        ),
        ("sensor.drift_limit", Field::DriftLimit, |s, x| {
            s.sensor.as_mut().unwrap().drift_limit = Some(x)
        }),
        ("feedback.kp", Field::Kp, |s, x| {
            s.feedback.as_mut().unwrap().kp = x
        }),
        ("feedback.ki", Field::Ki, |s, x| {
            s.feedback.as_mut().unwrap().ki = x
        }),
        ("feedback.kd", Field::Kd, |s, x| {
            s.feedback.as_mut().unwrap().kd = x
        }),
        (
            "feedback.derivative_cutoff_hz",
            Field::DerivativeCutoff,
            |s, x| s.feedback.as_mut().unwrap().derivative_cutoff_hz = x,
        ),
        ("feedback.limit", Field::FeedbackLimit, |s, x| {
            s.feedback.as_mut().unwrap().limit = x
        }),
        (
            "feedback.notch.frequency_hz",
            Field::NotchFrequency,
            |s, x| {
                s.feedback
                    .as_mut()
                    .unwrap()
                    .notch
                    .as_mut()
                    .unwrap()
                    .frequency_hz = x
            },
        ),
    ];
    let notch: [(&str, Field, Set); 2] = [
        ("feedback.notch.q", Field::NotchQ, |s, x| {
            s.feedback.as_mut().unwrap().notch.as_mut().unwrap().q = x
        }),
        ("feedback.notch.depth", Field::NotchDepth, |s, x| {
            s.feedback.as_mut().unwrap().notch.as_mut().unwrap().depth = x
        }),
    ];
    let mut out: Vec<FloatField> = plain
        .into_iter()
        .chain(notch)
        .map(|(name, field, set)| (name.to_string(), field, Box::new(set) as Box<_>))
        .collect();
    out.extend(model_fields(
        "compensator",
        s.compensator.as_ref().unwrap(),
        Field::Compensator,
    ));
    out.extend(model_fields(
        "observer",
        s.observer.as_ref().unwrap(),
        Field::Observer,
    ));
    out
}

#[test]
fn nan_or_infinity_in_any_float_of_a_load_is_refused_naming_that_field_and_changes_nothing() {
    let pi_duhem = closed();
    let duhem_pi = Settings {
        compensator: pi_duhem.observer.clone(),
        observer: pi_duhem.compensator.clone(),
        ..pi_duhem.clone()
    };
    let gpi_gpi = Settings {
        compensator: Some(twinstack::config::settings::representative_gpi(8).unwrap()),
        observer: Some(twinstack::config::settings::representative_gpi(4).unwrap()),
        ..pi_duhem.clone()
    };
    let bouc_wen = Settings {
        compensator: Some(representative_bouc_wen()),
        observer: Some(representative_bouc_wen()),
        ..pi_duhem.clone()
    };
    for base in [pi_duhem, duhem_pi, gpi_gpi, bouc_wen] {
        let hw = hardware();
        assert!(base.build(&hw).is_ok(), "the base settings are valid");
        // Two boards on the same settings, one refused everything, the other left alone:
        // after every refusal both must tick out the same codes and report the same status.
        let mut b = closed_board();
        let mut twin = closed_board();
        assert!(matches!(b.handle(base_load(&base)), Response::Ack { .. }));
        assert!(matches!(
            twin.handle(base_load(&base)),
            Response::Ack { .. }
        ));
        assert!(matches!(b.handle(batch(0, &[5; 12])), Response::Ack { .. }));
        assert!(matches!(
            twin.handle(batch(0, &[5; 12])),
            Response::Ack { .. }
        ));
        b.ticks(3);
        twin.ticks(3);
        let queued = b.queued();
        let fields = float_fields(&base);
        assert!(fields.len() >= 17 + 6, "{} fields", fields.len());
        let mut checked = 0;
        for (name, field, set) in &fields {
            for x in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
                let mut s = base.clone();
                set(&mut s, x);
                let want = refused(*field, Rule::NotFinite);
                let request = Request::LoadParams(s);
                assert_eq!(b.handle(request.clone()), want, "{name} = {x}");
                assert_nothing_changed(&mut b, &queued, &base);
                // The same through the wire: encoded, received byte by byte.
                assert_eq!(
                    b.bytes(&encoded(&request)),
                    vec![want],
                    "{name} = {x} (wire)"
                );
                assert_nothing_changed(&mut b, &queued, &base);
                b.ticks(2);
                twin.ticks(2);
                assert_eq!(b.outputs(), twin.outputs(), "{name} = {x}: outputs moved");
                assert_eq!(b.status(), twin.status(), "{name} = {x}: status differs");
                assert_eq!(
                    b.control.controller().setpoint(),
                    twin.control.controller().setpoint()
                );
                checked += 1;
            }
        }
        assert_eq!(checked, 3 * fields.len());
    }
}

fn base_load(s: &Settings) -> Request {
    Request::LoadParams(s.clone())
}

#[test]
fn every_refusal_names_its_field_and_its_limit() {
    let mut b = closed_board();
    assert!(matches!(b.handle(batch(0, &[7; 20])), Response::Ack { .. }));
    let queued = b.queued();
    let settings = b.handler.settings().clone();
    let load = |b: &mut Board<RamStorage>, edit: &dyn Fn(&mut Settings)| {
        let mut s = closed();
        edit(&mut s);
        b.handle(Request::LoadParams(s))
    };
    type Edit = Box<dyn Fn(&mut Settings)>;
    let cases: Vec<(&str, Edit, Response)> = vec![
        (
            "ki above rate/2",
            Box::new(|s| s.feedback.as_mut().unwrap().ki = 30_000.0),
            refused(Field::Ki, Rule::Below(25_000.0)),
        ),
        (
            "kp negative",
            Box::new(|s| s.feedback.as_mut().unwrap().kp = -0.1),
            refused(Field::Kp, Rule::AtLeast(0.0)),
        ),
        (
            "bias above the upper voltage limit",
            Box::new(|s| s.drive.bias = 145.0),
            refused(Field::Bias, Rule::AtMost(140.0)),
        ),
        (
            "closed loop without a sensor",
            Box::new(|s| s.sensor = None),
            refused(Field::Sensor, Rule::Required),
        ),
        (
            "closed loop without feedback",
            Box::new(|s| s.feedback = None),
            refused(Field::Feedback, Rule::Required),
        ),
        (
            "open loop without a compensator",
            Box::new(|s| {
                s.mode = Mode::OpenLoop;
                s.compensator = None
            }),
            refused(Field::Compensator(ModelField::Model), Rule::Required),
        ),
        (
            "a compensator that cannot be inverted",
            Box::new(|s| {
                if let Some(Model::PrandtlIshlinskii(p)) = &mut s.compensator {
                    p.weights[0] = -0.5;
                }
            }),
            refused(
                Field::Compensator(ModelField::Weight(1)),
                Rule::NotInvertible,
            ),
        ),
        (
            "an empty input range",
            Box::new(|s| s.ranges.input_max = s.ranges.input_min),
            refused(Field::InputRange, Rule::Empty),
        ),
        (
            "a drift limit above 1",
            Box::new(|s| s.sensor.as_mut().unwrap().drift_limit = Some(1.5)),
            refused(Field::DriftLimit, Rule::AtMost(1.0)),
        ),
    ];
    for (what, edit, want) in cases {
        assert_eq!(load(&mut b, &*edit), want, "{what}");
        assert_nothing_changed(&mut b, &queued, &settings);
    }
    assert_eq!(
        load(&mut b, &|s| {
            s.drive.min_voltage = 80.0;
        }),
        refused(Field::Bias, Rule::AtLeast(80.0)),
        "bias below the lower voltage limit"
    );
    assert_nothing_changed(&mut b, &queued, &settings);
    // Not settings, but refused the same way.
    assert_eq!(
        b.handle(Request::Stream(StreamControl::Rate { divider: 0 })),
        refused(Field::Divider, Rule::AtLeast(1.0))
    );
    assert_eq!(
        b.handle(Request::Record(RecordRequest {
            signal: Signal::Drive,
            count: RECORD_LEN as u32 + 1,
            decimation: 1,
        })),
        refused(Field::RecordCount, Rule::AtMost(RECORD_LEN as f64))
    );
    assert_eq!(
        b.handle(Request::Waveform(Waveform {
            shape: WaveShape::Sine,
            offset: 0,
            amplitude: 1000,
            frequency_mhz: 25_000_000, // exactly Nyquist at 50 kHz
            decay: None,
        })),
        refused(Field::WaveformFrequency, Rule::Below(25_000.0))
    );
    assert_nothing_changed(&mut b, &queued, &settings);
    assert!(!b.status().has(StatusReport::WAVEFORM));
    b.ticks(1);
    assert_eq!(
        b.queued().len(),
        queued.len(),
        "stopped stream: nothing consumed"
    );
}

#[test]
fn mode_changes_are_checked_against_the_settings_and_switch_between_two_ticks() {
    let mut b = closed_board();
    for mode in [Mode::Bypass, Mode::OpenLoop, Mode::ClosedLoop] {
        assert!(matches!(
            b.handle(Request::Mode(mode)),
            Response::Ack { .. }
        ));
        assert_eq!(b.status().mode(), mode);
        assert_eq!(b.handler.settings().mode, mode);
        assert_eq!(b.read_params().mode, mode);
        b.ticks(1);
        assert_eq!(b.control.controller().mode(), mode);
    }
    // The defaults have no model and no feedback: only bypass.
    let mut d = board();
    let defaults = d.handler.settings().clone();
    assert_eq!(
        d.handle(Request::Mode(Mode::OpenLoop)),
        refused(Field::Compensator(ModelField::Model), Rule::Required)
    );
    assert_eq!(
        d.handle(Request::Mode(Mode::ClosedLoop)),
        refused(Field::Feedback, Rule::Required)
    );
    assert_nothing_changed(&mut d, &[], &defaults);
    assert_eq!(d.control.controller().mode(), Mode::Bypass);
    // A board without a sensor input runs open loop and refuses closed loop.
    let hw = Hardware {
        sensor_adc_bits: None,
        ..hardware()
    };
    let open = Settings {
        sensor: None,
        mode: Mode::OpenLoop,
        ..closed()
    };
    let config = open.build(&hw).unwrap();
    let mut b = Board {
        handler: CommandHandler::new(hw, open.clone(), false, RamStorage::default()),
        control: ControlLoop::new(
            Box::new(Controller::new(config)),
            Box::new(Controller::new(config)),
            hw.control_rate_hz.round() as u32,
        ),
        services: Services::new(vec![0i16; 32]),
        queue: Box::leak(Box::new(SetpointQueue::new())),
        snapshots: Box::leak(Box::new(SnapshotRing::new())),
        telemetry: Box::leak(Box::new(TelemetryQueue::new())),
        dac: Dac(DacCode(0), DacCode(0)),
        adc: Adc(0),
        swaps_before: 0,
    };
    assert_eq!(
        b.handle(Request::Mode(Mode::ClosedLoop)),
        refused(Field::Sensor, Rule::Required)
    );
    assert_nothing_changed(&mut b, &[], &open);
    // Sensor settings on a board without the input: refused as such.
    assert_eq!(
        b.handle(Request::LoadParams(Settings {
            mode: Mode::OpenLoop,
            ..closed()
        })),
        refused(Field::Sensor, Rule::NoHardware)
    );
    assert_nothing_changed(&mut b, &[], &open);
}

#[test]
fn a_mode_switch_right_after_a_load_is_checked_against_and_applied_to_the_load() {
    // The defaults run (no compensator, no feedback); the load brings both.
    let mut b = board();
    let p = Settings {
        mode: Mode::Bypass,
        ..closed()
    };
    assert!(matches!(
        b.handle(Request::LoadParams(p.clone())),
        Response::Ack { .. }
    ));
    // No tick between the load and the switch: the load is in force already.
    assert!(matches!(
        b.handle(Request::Mode(Mode::ClosedLoop)),
        Response::Ack { .. }
    ));
    assert_eq!(b.status().mode(), Mode::ClosedLoop);
    b.ticks(1);
    assert_eq!(b.control.controller().mode(), Mode::ClosedLoop);
    assert_eq!(
        b.read_params(),
        Settings {
            mode: Mode::ClosedLoop,
            ..p
        }
    );
    // A switch the waiting load cannot run is refused and leaves it as it was.
    let mut b = closed_board();
    let open = Settings {
        feedback: None,
        mode: Mode::OpenLoop,
        ..closed()
    };
    assert!(matches!(
        b.handle(Request::LoadParams(open.clone())),
        Response::Ack { .. }
    ));
    assert_eq!(
        b.handle(Request::Mode(Mode::ClosedLoop)),
        refused(Field::Feedback, Rule::Required)
    );
    b.ticks(1);
    assert_eq!(b.control.controller().mode(), Mode::OpenLoop);
    assert_eq!(b.read_params(), open);
}

#[test]
fn store_and_recall_round_trip_through_the_storage_and_refuse_when_they_cannot() {
    let mut b = board();
    assert_eq!(
        b.handle(Request::RecallParams),
        nack(NackReason::NothingStored)
    );
    let mut p = closed();
    p.drive.bias = 60.0;
    p.mode = Mode::Bypass;
    assert!(matches!(
        b.handle(Request::LoadParams(p.clone())),
        Response::Ack { .. }
    ));
    assert!(matches!(
        b.handle(Request::StoreParams {
            boot_mode: Mode::Bypass
        }),
        Response::Ack { .. }
    ));
    assert!(matches!(
        b.handle(Request::Mode(Mode::OpenLoop)),
        Response::Ack { .. }
    ));
    assert!(matches!(
        b.handle(Request::RecallParams),
        Response::Ack { .. }
    ));
    assert_eq!(b.handler.settings(), &p);
    assert_eq!(b.read_params(), p);
    // A board booting on that storage starts on the stored settings, not the defaults.
    let storage = b.handler.storage().clone();
    let mut again = board_with(storage);
    assert_eq!(again.handler.settings(), &p);
    assert!(!again.status().has(StatusReport::DEFAULTS));
    assert!(board().status().has(StatusReport::DEFAULTS));
    // Storing while the stream runs would stall the tick: refused.
    assert!(matches!(
        b.handle(Request::Stream(StreamControl::Start)),
        Response::Ack { .. }
    ));
    assert_eq!(
        b.handle(Request::StoreParams {
            boot_mode: Mode::Bypass
        }),
        nack(NackReason::Busy)
    );
    // Read-only and failing storage.
    let mut ro = board_with(ReadOnlyStorage(&[0xFF; 64]));
    assert_eq!(
        ro.handle(Request::StoreParams {
            boot_mode: Mode::Bypass
        }),
        nack(NackReason::NoStorage)
    );
    let mut broken = board_with(BrokenFlash([0xFF; 16]));
    assert_eq!(
        broken.handle(Request::StoreParams {
            boot_mode: Mode::Bypass
        }),
        nack(NackReason::StoreFailed)
    );
}

#[test]
fn a_board_on_erased_storage_boots_in_bypass_on_the_defaults_and_says_so() {
    let mut b = board();
    let s = b.status();
    assert_eq!(s.mode(), Mode::Bypass, "{s:?}");
    assert!(s.has(StatusReport::DEFAULTS), "{s:?}");
    assert_eq!(s.tick_rate_hz, RATE);
    assert_eq!(b.read_params(), Settings::default());
    assert_eq!(b.control.controller().mode(), Mode::Bypass);
    // The defaults start at their safe state (the bias) and hold it.
    b.ticks(5);
    assert_eq!(b.outputs(), b.control.safe_codes());
    // Damaged records boot the same way.
    let mut sector = [0u8; MAX_RECORD];
    let n = StoredRecord {
        control_rate_hz: RATE,
        settings: closed(),
        analog: None,
    }
    .encode(&mut sector)
    .unwrap();
    sector[param_store::HEADER_LEN + 3] ^= 0x10;
    let mut bad = board_with(ReadOnlyStorage(&sector[..n]));
    let s = bad.status();
    assert_eq!(s.mode(), Mode::Bypass, "{s:?}");
    assert!(s.has(StatusReport::DEFAULTS), "{s:?}");
}

#[test]
fn a_stored_record_boots_in_its_stored_mode() {
    for boot_mode in [Mode::Bypass, Mode::OpenLoop, Mode::ClosedLoop] {
        let mut b = closed_board();
        assert!(matches!(
            b.handle(Request::StoreParams { boot_mode }),
            Response::Ack { .. }
        ));
        // Storing does not switch the running board.
        assert_eq!(b.status().mode(), Mode::ClosedLoop);
        let mut again = board_with(b.handler.storage().clone());
        let s = again.status();
        assert_eq!(s.mode(), boot_mode, "{s:?}");
        assert!(!s.has(StatusReport::DEFAULTS), "{s:?}");
        assert_eq!(again.control.controller().mode(), boot_mode);
        assert_eq!(
            again.read_params(),
            Settings {
                mode: boot_mode,
                ..closed()
            }
        );
    }
}

#[test]
fn storing_a_boot_mode_the_settings_cannot_run_is_refused() {
    let mut p = closed();
    p.feedback = None;
    p.mode = Mode::OpenLoop;
    let mut b = board();
    assert!(matches!(
        b.handle(Request::LoadParams(p.clone())),
        Response::Ack { .. }
    ));
    assert_eq!(
        b.handle(Request::StoreParams {
            boot_mode: Mode::ClosedLoop
        }),
        refused(Field::Feedback, Rule::Required)
    );
    assert!(
        b.handler.storage().read().iter().all(|&x| x == 0xFF),
        "nothing was written"
    );
    assert_eq!(
        b.handle(Request::RecallParams),
        nack(NackReason::NothingStored)
    );
    // The defaults cannot boot open loop either (no compensator).
    let mut d = board();
    assert_eq!(
        d.handle(Request::StoreParams {
            boot_mode: Mode::OpenLoop
        }),
        refused(Field::Compensator(ModelField::Model), Rule::Required)
    );
}

#[test]
fn the_waveform_generator_runs_and_out_of_range_waveforms_are_refused() {
    let mut b = board();
    let w = |frequency_mhz, amplitude| {
        Request::Waveform(Waveform {
            shape: WaveShape::Triangle,
            offset: 0,
            amplitude,
            frequency_mhz,
            decay: None,
        })
    };
    // 30 kHz ≥ Nyquist.
    assert_eq!(
        b.handle(w(30_000_000, 1000)),
        refused(Field::WaveformFrequency, Rule::Below(25_000.0))
    );
    assert_eq!(
        b.handle(w(0, 1000)),
        refused(Field::WaveformFrequency, Rule::Above(0.0))
    );
    let beyond = Waveform {
        shape: WaveShape::Sine,
        offset: 20_000,
        amplitude: 20_000,
        frequency_mhz: 1_000,
        decay: None,
    };
    assert_eq!(
        b.handle(Request::Waveform(beyond)),
        refused(Field::WaveformAmplitude, Rule::AtMost(1.0))
    );
    assert!(!b.status().has(StatusReport::WAVEFORM));
    assert!(matches!(b.handle(w(750_000, 16384)), Response::Ack { .. }));
    assert!(b.status().has(StatusReport::WAVEFORM));
    // 750 Hz at 50 kHz: the triangle's crest (offset + amplitude) after a quarter period.
    let mut top = i32::MIN;
    for _ in 0..(50_000 / 750) {
        b.ticks(1);
        top = top.max(b.control.controller().setpoint());
    }
    assert!(
        (top - (16384 << 15)).abs() < (16384 << 15) / 50,
        "crest {top}"
    );
    assert!(matches!(
        b.handle(Request::Stream(StreamControl::Stop)),
        Response::Ack { .. }
    ));
    assert!(!b.status().has(StatusReport::WAVEFORM));
}

#[test]
fn the_recorder_captures_the_chosen_signal_and_reads_back_in_chunks() {
    let mut b = board();
    let arm = |signal, count, decimation| {
        Request::Record(RecordRequest {
            signal,
            count,
            decimation,
        })
    };
    assert_eq!(
        b.handle(arm(Signal::Drive, 0, 1)),
        refused(Field::RecordCount, Rule::AtLeast(1.0))
    );
    assert_eq!(
        b.handle(arm(Signal::Drive, 10, 0)),
        refused(Field::RecordDecimation, Rule::AtLeast(1.0))
    );
    assert_eq!(
        b.handle(arm(Signal::Drive, RECORD_LEN as u32 + 1, 1)),
        refused(Field::RecordCount, Rule::AtMost(RECORD_LEN as f64))
    );
    assert_eq!(
        b.handle(Request::ReadRecord { offset: 1 }),
        refused(Field::RecordOffset, Rule::AtMost(0.0))
    );
    // The board boots in bypass, so the sensor is read for the recorder only.
    assert_eq!(b.status().mode(), Mode::Bypass);
    assert!(matches!(
        b.handle(arm(Signal::Sensor, 100, 3)),
        Response::Ack { .. }
    ));
    // The status counts what the services have served (a batch of 8 ticks at a time):
    // after 144 ticks, every third of ticks 0–143.
    b.ticks(144);
    let s = b.status();
    assert_eq!(s.recorded, 48);
    assert!(s.has(StatusReport::RECORDING));
    b.ticks(200);
    assert_eq!(b.status().recorded, 100);
    let mut all = Vec::new();
    while all.len() < 100 {
        match b.handle(Request::ReadRecord {
            offset: all.len() as u32,
        }) {
            Response::RecordChunk { offset, values } => {
                assert_eq!(offset as usize, all.len());
                assert!(values.len() <= MAX_CHUNK);
                all.extend(values);
            }
            r => panic!("{r:?}"),
        }
    }
    // Code 2048 of 4096 over 0…70 µm is mid-stroke: normalised 0.
    assert!(all.iter().all(|&v| v == 0), "{all:?}");
    assert_eq!(
        b.handle(Request::ReadRecord { offset: 100 }),
        Response::RecordChunk {
            offset: 100,
            values: heapless::Vec::new()
        }
    );
    // Past the end: the limit is what the recorder holds.
    assert_eq!(
        b.handle(Request::ReadRecord { offset: 101 }),
        refused(Field::RecordOffset, Rule::AtMost(100.0))
    );
}

/// A multi-signal capture through the handler: each bad field refused by name with its limit;
/// armed on the stream's start with pre-trigger frames, it holds the setpoints queued, the
/// DAC codes the tick wrote, and the frames from before the start.
#[test]
fn a_capture_triggered_by_the_stream_holds_its_setpoints_and_the_dac_codes() {
    let mut b = board();
    let capture = |signals, samples, pre_trigger, trigger, decimation| {
        Request::Capture(CaptureRequest {
            signals,
            samples,
            pre_trigger,
            trigger,
            decimation,
        })
    };
    let slots = 2 * RECORD_LEN as u32;
    for (request, field, rule) in [
        (
            capture(0, 10, 0, Trigger::Now, 1),
            Field::RecordSignals,
            Rule::AtLeast(1.0),
        ),
        (
            capture(0x81, 10, 0, Trigger::Now, 1),
            Field::RecordSignals,
            Rule::AtMost(127.0),
        ),
        (
            capture(1, 0, 0, Trigger::Now, 1),
            Field::RecordCount,
            Rule::AtLeast(1.0),
        ),
        (
            capture(0b111, slots / 3 + 1, 0, Trigger::Now, 1),
            Field::RecordCount,
            Rule::AtMost((slots / 3) as f64),
        ),
        (
            capture(1, 10, 1, Trigger::Now, 1),
            Field::RecordPreTrigger,
            Rule::AtMost(0.0),
        ),
        (
            capture(1, 10, 10, Trigger::StreamStart, 1),
            Field::RecordPreTrigger,
            Rule::Below(10.0),
        ),
        (
            capture(1, 10, 0, Trigger::Now, 0),
            Field::RecordDecimation,
            Rule::AtLeast(1.0),
        ),
    ] {
        assert_eq!(b.handle(request), refused(field, rule));
    }
    let status = |b: &mut Board<RamStorage>| match b.handle(Request::CaptureStatus) {
        Response::Capture(s) => s,
        r => panic!("{r:?}"),
    };
    assert_eq!(status(&mut b).state, CaptureState::Idle);
    // Reading before the capture is complete is refused as busy.
    assert_eq!(
        b.handle(Request::ReadCapture {
            offset: 0,
            count: 1
        }),
        nack(NackReason::Busy)
    );

    let samples: Vec<i16> = (0..40).map(|i| i * 500 - 10_000).collect();
    assert!(matches!(b.handle(batch(0, &samples)), Response::Ack { .. }));
    let mask = Channel::Setpoint.bit() | Channel::Left.bit() | Channel::Right.bit();
    assert!(matches!(
        b.handle(capture(mask, 50, 5, Trigger::StreamStart, 1)),
        Response::Ack { .. }
    ));
    b.ticks(20); // before the start: the ring keeps the latest 5
    let s = status(&mut b);
    assert_eq!((s.state, s.captured), (CaptureState::Armed, 5));
    assert!(b.status().has(StatusReport::RECORDING));
    let held = b.outputs();
    assert!(matches!(
        b.handle(Request::Stream(StreamControl::Start)),
        Response::Ack { .. }
    ));
    // The start reaches the recorder with the next tick's snapshot: the trigger frame is
    // that tick's.
    assert_eq!(status(&mut b).state, CaptureState::Armed);
    let mut codes = Vec::new();
    for k in 0..60 {
        b.ticks(1);
        codes.push(b.outputs());
        if k == 0 {
            assert_eq!(status(&mut b).state, CaptureState::Triggered);
        }
    }
    let s = status(&mut b);
    assert_eq!(
        (s.state, s.pre_available, s.captured, s.window_slots),
        (CaptureState::Done, 5, 50, 150)
    );
    assert_eq!((s.dac_full_scale, s.amplifier_full_scale), (4095, 150.0));
    let mut window = Vec::new();
    loop {
        match b.handle(Request::ReadCapture {
            offset: window.len() as u32,
            count: 64,
        }) {
            Response::CaptureChunk { offset, values } => {
                assert_eq!(offset as usize, window.len());
                assert!(values.len() <= 64);
                if values.is_empty() {
                    break;
                }
                window.extend(values);
            }
            r => panic!("{r:?}"),
        }
    }
    assert_eq!(window.len(), 150);
    let frames: Vec<&[i16]> = window.chunks(3).collect();
    // Five frames at the held output, then the 40 setpoints as queued, then the hold.
    for f in &frames[..5] {
        assert_eq!((f[1] as u16, f[2] as u16), (held.0 .0, held.1 .0));
    }
    let setpoints: Vec<i16> = frames[5..45].iter().map(|f| f[0]).collect();
    assert_eq!(setpoints, samples);
    for (f, (l, r)) in frames[5..].iter().zip(&codes) {
        assert_eq!((f[1] as u16, f[2] as u16), (l.0, r.0));
    }
    assert_eq!(
        b.handle(Request::ReadCapture {
            offset: 151,
            count: 1
        }),
        refused(Field::RecordOffset, Rule::AtMost(150.0))
    );
}

#[test]
fn every_frame_error_is_nacked_with_its_reason_and_counted() {
    let mut b = board();
    assert!(matches!(b.handle(batch(0, &[3; 4])), Response::Ack { .. }));
    let params = b.handler.settings().clone();
    let raw = |body: &[u8]| {
        let mut out = vec![0u8; MAX_ENCODED + 1];
        let n = twinstack::protocol::frame::encode_body_bytes(body, &mut out).unwrap();
        out.truncate(n);
        out
    };
    let mut corrupt = encoded(&batch(1, &[4; 8]));
    corrupt[5] ^= 0x22;
    let mut oversize = vec![0x41u8; MAX_ENCODED + 10];
    oversize.push(0);
    let cases: Vec<(Vec<u8>, FrameError)> = vec![
        (corrupt, FrameError::BadCrc),
        (oversize, FrameError::Oversize),
        (vec![0x02, 0x07, 0x00], FrameError::Truncated),
        (vec![0x09, 0x01, 0x00], FrameError::BadStuffing),
        (
            raw(&[PROTOCOL_VERSION + 1, 0]),
            FrameError::BadVersion {
                got: PROTOCOL_VERSION + 1,
            },
        ),
        (raw(&[PROTOCOL_VERSION, 99]), FrameError::UnknownType),
        (raw(&[PROTOCOL_VERSION, 0, 1]), FrameError::Malformed),
    ];
    for (bytes, reason) in cases {
        assert_eq!(b.bytes(&bytes), vec![nack(NackReason::Frame(reason))]);
        assert_nothing_changed(&mut b, &[3; 4], &params);
    }
    let s = b.status();
    assert_eq!((s.crc_errors, s.frame_errors, s.next_seq), (1, 6, 1));
    // Junk without a delimiter, then a good frame after one: resynchronised.
    let mut bytes = vec![0x13u8; 40];
    bytes.push(0);
    bytes.extend(encoded(&batch(1, &[4; 8])));
    assert_eq!(
        b.bytes(&bytes),
        vec![
            nack(NackReason::Frame(FrameError::BadStuffing)),
            Response::Ack {
                credits: SETPOINT_CAPACITY as u16 - 12
            }
        ]
    );
}

// ---- Fuzz: random bytes and mutated valid frames into the handler ----

use proptest::prelude::*;

fn any_request() -> impl Strategy<Value = Request> {
    let samples = prop::collection::vec(any::<i16>(), 0..=MAX_BATCH);
    prop_oneof![
        Just(Request::Status),
        (0u16..4, samples).prop_map(|(seq, s)| batch(seq, &s)),
        prop_oneof![
            Just(StreamControl::Start),
            Just(StreamControl::Stop),
            any::<u16>().prop_map(|divider| StreamControl::Rate { divider }),
            Just(StreamControl::Underrun(UnderrunPolicy::RampToBias)),
        ]
        .prop_map(Request::Stream),
        prop_oneof![
            Just(Mode::Bypass),
            Just(Mode::OpenLoop),
            Just(Mode::ClosedLoop)
        ]
        .prop_map(Request::Mode),
        (any::<i16>(), any::<i16>(), any::<u32>()).prop_map(|(offset, amplitude, f)| {
            Request::Waveform(Waveform {
                shape: WaveShape::Sine,
                offset,
                amplitude,
                frequency_mhz: f,
                decay: None,
            })
        }),
        (any::<u32>(), any::<u16>()).prop_map(|(count, decimation)| {
            Request::Record(RecordRequest {
                signal: Signal::Estimate,
                count: count % 5000,
                decimation: decimation % 4,
            })
        }),
        any::<u32>().prop_map(|o| Request::ReadRecord { offset: o % 200 }),
        (-10.0f64..160.0, -1.0f64..1.0).prop_map(|(bias, w)| {
            let mut p = closed();
            p.drive.bias = bias;
            if let Some(Model::PrandtlIshlinskii(m)) = &mut p.compensator {
                m.weights[1] = w;
            }
            Request::LoadParams(p)
        }),
        prop_oneof![
            Just(Mode::Bypass),
            Just(Mode::OpenLoop),
            Just(Mode::ClosedLoop)
        ]
        .prop_map(|boot_mode| Request::StoreParams { boot_mode }),
        Just(Request::ReadParams),
        Just(Request::RecallParams),
    ]
}

/// A piece of input: junk, a valid frame, or a valid frame with bytes changed or cut.
fn any_chunk() -> impl Strategy<Value = Vec<u8>> {
    prop_oneof![
        prop::collection::vec(any::<u8>(), 0..300),
        any_request().prop_map(|r| encoded(&r)),
        (any_request(), any::<prop::sample::Index>(), any::<u8>()).prop_map(|(r, at, x)| {
            let mut f = encoded(&r);
            let i = at.index(f.len());
            f[i] ^= x;
            f
        }),
        (any_request(), any::<prop::sample::Index>()).prop_map(|(r, at)| {
            let mut f = encoded(&r);
            f.truncate(at.index(f.len()));
            f
        }),
    ]
}

proptest! {
    // Bounded so CI spends seconds here; deterministic (work is counted, not timed).
    #![proptest_config(ProptestConfig { cases: 96, ..ProptestConfig::default() })]

    /// Whatever arrives: no panic, one well-formed response per frame, at most
    /// `2 × MAX_ENCODED + 1` decoder steps for any byte and three per byte on average, and the
    /// queue's fill and credits always add up to its capacity.
    #[test]
    fn fuzz_any_input_gets_one_response_per_frame_with_bounded_work(
        chunks in prop::collection::vec(any_chunk(), 1..24),
    ) {
        let mut b = board();
        let bytes: Vec<u8> = chunks.concat();
        let (mut frames, mut run) = (0usize, 0usize);
        let mut responses = 0usize;
        let mut worst = 0u32;
        let start = b.handler.decoder_steps();
        for (i, &byte) in bytes.iter().enumerate() {
            if byte == 0 {
                if run > 0 {
                    frames += 1;
                }
                run = 0;
            } else {
                run += 1;
            }
            let before = b.handler.decoder_steps();
            responses += b.bytes(&[byte]).len(); // each response decodes (or the test fails)
            worst = worst.max(b.handler.decoder_steps().wrapping_sub(before));
            if i % 50 == 0 {
                b.ticks(1);
            }
        }
        prop_assert_eq!(responses, frames);
        prop_assert!(worst as usize <= 2 * MAX_ENCODED + 1, "one byte cost {} steps", worst);
        let total = b.handler.decoder_steps().wrapping_sub(start) as usize;
        prop_assert!(total <= 3 * bytes.len(), "{} steps for {} bytes", total, bytes.len());
        let s = b.status();
        prop_assert_eq!(s.queue_fill as usize + s.credits as usize, SETPOINT_CAPACITY);
        prop_assert_eq!(s.queue_fill as usize, b.queued().len());
    }
}

#[test]
fn a_learning_table_write_near_two_to_the_32_is_refused_not_wrapped() {
    // The bound is checked in u32 with `checked_add`: an offset near 2^32 cannot wrap past it
    // on the 32-bit board, and the host and the board give the same refusal (the emulator's
    // test sends the fuzzer's frame itself).
    let mut b = board();
    let learn = twinstack::services::learning::LearnSettings::for_period(200);
    assert!(matches!(
        b.handle(Request::Learn(LearnRequest::Configure(learn))),
        Response::Ack { .. }
    ));
    let last = (twinstack::services::learning::MAX_BINS - 2) as f64;
    for offset in [u32::MAX, u32::MAX - 1, 1 << 31, 511] {
        let values = heapless::Vec::from_slice(&[1, 2]).unwrap();
        assert_eq!(
            b.handle(Request::Learn(LearnRequest::WriteTable { offset, values })),
            Response::Nack {
                reason: NackReason::Refused(Refusal::new(Field::RecordOffset, Rule::AtMost(last)))
            },
            "offset {offset}"
        );
    }
    let values = heapless::Vec::from_slice(&[1, 2]).unwrap();
    assert!(matches!(
        b.handle(Request::Learn(LearnRequest::WriteTable {
            offset: 510,
            values
        })),
        Response::Ack { .. }
    ));
}

#[test]
fn telemetry_at_decimation_zero_is_refused_with_the_least_decimation_that_fits() {
    let mut b = board();
    // Six signals at 50 kHz: 300 000 values/s, 6 the least decimation under 50 000.
    assert_eq!(
        b.handle(Request::Telemetry(TelemetryRequest::Start {
            signals: 0b11_1111,
            decimation: 0
        })),
        Response::Nack {
            reason: NackReason::Refused(Refusal::new(
                Field::TelemetryDecimation,
                Rule::AtLeast(6.0)
            ))
        }
    );
}

#[test]
fn two_loads_between_two_ticks_swap_twice_and_the_newer_runs_from_the_drive_held() {
    let mut b = closed_board();
    b.ticks(200);
    let held = b.outputs();
    let swaps = b.control.swaps();
    let mut first = closed();
    first.mode = Mode::OpenLoop;
    let mut newer = closed();
    newer.mode = Mode::Bypass;
    for s in [first, newer.clone()] {
        assert!(matches!(
            b.handle(Request::LoadParams(s)),
            Response::Ack { .. }
        ));
    }
    // Each load is swapped in when it is acknowledged (under the handler's lock, between two
    // ticks): two swaps, the newer in force, the stacks untouched until the next tick.
    assert_eq!(b.control.swaps(), swaps + 2);
    assert_eq!(b.control.controller().mode(), Mode::Bypass);
    assert_eq!(b.handler.settings(), &newer);
    assert_eq!(b.outputs(), held);
    // The next tick starts the fade from the drive the stacks hold: no step.
    b.ticks(1);
    let (l, r) = b.outputs();
    let step = |a: DacCode, b: DacCode| (a.0 as i32 - b.0 as i32).abs();
    assert!(
        step(l, held.0) <= 2 && step(r, held.1) <= 2,
        "{held:?} → {:?}",
        (l, r)
    );
}

/// A board at a rate whose period holds the closed-loop configuration (loaded) but not
/// `charge` more cycles beside it: halfway between the two. Returns it, the rate and the
/// configuration's predicted cycles there.
fn closed_loop_board_short_of(charge: u32) -> (Board<RamStorage>, f64, u32) {
    use twinstack::config::tick_budget::{available_cycles, highest_rate_hz, worst_case_cycles};
    let worst = worst_case_cycles(&closed().build(&hardware()).unwrap());
    let rate = highest_rate_hz(worst + charge / 2);
    let hw = Hardware::driver_board(rate);
    let fits = worst_case_cycles(&closed().build(&hw).unwrap());
    assert!(fits <= available_cycles(rate) && fits + charge > available_cycles(rate));
    let mut b = board_on(RamStorage::default(), hw);
    assert!(matches!(
        b.handle(Request::LoadParams(closed())),
        Response::Ack { .. }
    ));
    (b, rate, fits)
}

/// `response` is the refusal of a request that would overrun the tick: the workload, needing
/// `needs` cycles of what `rate` leaves.
fn refused_as_overrun(response: Response, needs: u32, rate: f64) {
    match response {
        Response::Nack {
            reason: NackReason::Refused(r),
        } => {
            assert_eq!(r.field, Field::Workload, "{r:?}");
            assert_eq!(
                r.rule,
                Rule::TickOverrun {
                    needs,
                    available: twinstack::config::tick_budget::available_cycles(rate)
                }
            );
        }
        r => panic!("not refused as an overrun: {r:?}"),
    }
}

/// The analog input is charged beside the configuration's tick
/// ([`twinstack::config::tick_budget::ANALOG_CYCLES`]): at a rate whose period holds the closed-loop
/// configuration but not the input beside it, the load is taken and the start refused with
/// the cycles it needs and has; nothing starts.
#[test]
fn an_analog_start_that_would_overrun_the_tick_is_refused_with_its_cycles() {
    use twinstack::config::tick_budget::ANALOG_CYCLES;
    use twinstack::sources::analog_input::{AnalogInputConfig, AnalogRequest, OnFault};
    let (mut b, rate, fits) = closed_loop_board_short_of(ANALOG_CYCLES);
    let input = AnalogInputConfig {
        gain: 2.0,
        offset: -1.0,
        corner_hz: None,
        lost_below: 0.0,
        over_above: 1.0,
        on_fault: OnFault::Hold,
        rate: 10.0,
        start_at_boot: false,
    };
    refused_as_overrun(
        b.handle(Request::Analog(AnalogRequest::Start(input))),
        fits + ANALOG_CYCLES,
        rate,
    );
    assert!(!b.control.analog_status().running);
}

/// A TTL-stepped sequence is charged beside the configuration's tick
/// ([`twinstack::config::tick_budget::SEQUENCE_CYCLES`]: its edge's tick pops a position and
/// starts the walk to it): at a rate whose period holds the closed-loop configuration but not
/// the sequence beside it, arming is refused with the cycles it needs and has, and nothing is
/// armed.
#[test]
fn arming_a_sequence_that_would_overrun_the_tick_is_refused_with_its_cycles() {
    use twinstack::config::tick_budget::SEQUENCE_CYCLES;
    use twinstack::sources::scan::TriggerEdge;
    use twinstack::sources::sequence::{SequenceConfig, SequenceRequest};
    let (mut b, rate, fits) = closed_loop_board_short_of(SEQUENCE_CYCLES);
    let config = SequenceConfig {
        edge: TriggerEdge::Rising,
        window: 0.01,
        settle_ticks: 5,
    };
    refused_as_overrun(
        b.handle(Request::Sequence(SequenceRequest::Arm(config))),
        fits + SEQUENCE_CYCLES,
        rate,
    );
    assert!(!b.control.sequence_status().armed);
}

/// The armed trigger input is charged beside the configuration's tick
/// ([`twinstack::config::tick_budget::TRIGGER_CYCLES`]: its edge's tick starts a scan or the
/// stream and fires a capture, and the edge may come on any tick): at a rate whose period
/// holds the configuration but not the edge's tick beside it, arming is refused with the
/// cycles it needs and has, and nothing is armed; trigger outputs alone (input off) are taken.
#[test]
fn arming_the_trigger_input_where_its_edge_would_overrun_the_tick_is_refused() {
    use twinstack::config::tick_budget::TRIGGER_CYCLES;
    use twinstack::sources::scan::{TriggerConfig, TriggerEdge};
    let (mut b, rate, fits) = closed_loop_board_short_of(TRIGGER_CYCLES);
    let armed = TriggerConfig {
        pulse_ticks: 2,
        input: TriggerEdge::Rising,
        start_stream: true,
    };
    refused_as_overrun(
        b.handle(Request::Trigger(armed)),
        fits + TRIGGER_CYCLES,
        rate,
    );
    assert!(!b.control.beside().trigger, "nothing armed");
    let outputs_only = TriggerConfig {
        input: TriggerEdge::Off,
        ..armed
    };
    assert!(matches!(
        b.handle(Request::Trigger(outputs_only)),
        Response::Ack { .. }
    ));
    // At the test's own rate the same arming fits, and the tick budget then charges it.
    let mut b = board();
    assert!(matches!(
        b.handle(Request::Trigger(armed)),
        Response::Ack { .. }
    ));
    assert!(b.control.beside().trigger);
    // A scan waiting for the edge is charged as a scan (the edge starts it): a load meanwhile
    // is checked with it.
    let waiting = small_raster(1, true);
    assert!(matches!(
        b.handle(Request::Scan(waiting)),
        Response::Ack { .. }
    ));
    assert!(!b.control.is_scanning() && b.control.beside().source == SetpointSource::Scan);
}

/// While telemetry runs, the tick wakes the command task (the packer) when the queue holds a
/// frame's worth of samples, never once per tick: the wake level the handler gives the tap is
/// the packer's own frame target, and at every wake a frame is due and packed.
#[test]
fn the_telemetry_packer_is_woken_by_the_queue_s_fill_level_not_per_tick() {
    use twinstack::services::telemetry::frame_target;
    let mut b = board();
    let (signals, decimation) = (0b11, 2);
    assert!(matches!(
        b.handle(Request::Telemetry(TelemetryRequest::Start {
            signals,
            decimation
        })),
        Response::Ack { .. }
    ));
    let target = frame_target(signals, decimation, RATE);
    assert!(target > 1, "a frame's worth of {target} samples");
    let ticks = 4_000;
    let (mut wakes, mut frames) = (0, 0);
    for _ in 0..ticks {
        if !b.tick() {
            continue;
        }
        wakes += 1;
        let (_, mut packer) = b.telemetry.split();
        assert!(
            packer.len() >= target,
            "woken at {} queued samples, a frame is {target}",
            packer.len()
        );
        assert!(b.handler.telemetry_due(&packer));
        while b.handler.telemetry_due(&packer) {
            assert!(b.handler.pack_telemetry(&mut packer).is_some());
            frames += 1;
        }
    }
    let samples = ticks / decimation as usize;
    assert_eq!(
        wakes,
        samples / target,
        "{samples} samples, {target} a frame"
    );
    assert!(frames >= wakes);
    assert_eq!(b.services.telemetry().overflows(), 0);
}

/// The services (recorder, telemetry) are charged beside the configuration while they listen,
/// by what they run ([`twinstack::config::tick_budget::ServicesLoad`]): at a rate whose period
/// holds the closed-loop configuration but not a capture (or telemetry) beside it, the arming
/// is refused with the cycles it needs and has, and the tick hands the services nothing more.
/// Without an observer below the tick, at the test's own rate a capture makes the tick push its
/// snapshots until it completes, and the next request that looks stops them; telemetry keeps
/// them until it stops.
#[test]
fn the_services_are_charged_while_they_listen_and_refused_where_they_would_overrun() {
    use twinstack::config::tick_budget::{
        available_cycles, pipeline_cycles, worst_case_cycles, Beside, ServicesLoad,
    };
    use twinstack::services::recorder::Trigger;
    let capture = CaptureRequest {
        signals: Channel::Left.bit() | Channel::Sensor.bit(),
        samples: 8,
        pre_trigger: 0,
        trigger: Trigger::Now,
        decimation: 1,
    };
    let telemetry = Request::Telemetry(TelemetryRequest::Start {
        signals: Channel::Left.bit(),
        decimation: 10,
    });
    let capture_load = ServicesLoad {
        capture_decimation: Some(1),
        ..ServicesLoad::default()
    };
    let telemetry_load = ServicesLoad {
        telemetry_decimation: Some(10),
        ..ServicesLoad::default()
    };
    // What each adds to the configuration's pipeline (its observer below the tick already
    // has the services listening: their base share is charged once).
    let config = closed().build(&hardware()).unwrap();
    let adds = |load: ServicesLoad| {
        let beside = Beside {
            services: load,
            ..Beside::default()
        };
        pipeline_cycles(&config, beside) - worst_case_cycles(&config)
    };
    for (request, load) in [
        (Request::Capture(capture), capture_load),
        (telemetry.clone(), telemetry_load),
    ] {
        let (mut b, rate, fits) = closed_loop_board_short_of(adds(load));
        match b.handle(request.clone()) {
            Response::Nack {
                reason: NackReason::Refused(r),
            } => assert_eq!(
                (r.field, r.rule),
                (
                    Field::Workload,
                    Rule::TickOverrun {
                        needs: fits + adds(load),
                        available: available_cycles(rate)
                    }
                ),
                "{request:?}"
            ),
            r => panic!("{request:?} was not refused: {r:?}"),
        }
        assert!(!b.services.recorder().is_capturing());
        assert!(!b.services.telemetry().is_running());
        // A request the checks refuse first (no signal) is refused for that, not the budget.
        match b.handle(Request::Capture(CaptureRequest {
            signals: 0,
            ..capture
        })) {
            Response::Nack {
                reason: NackReason::Refused(r),
            } => assert_eq!(r.field, Field::RecordSignals, "{r:?}"),
            r => panic!("{r:?}"),
        }
    }

    // The closed loop without an observer: nothing below the tick until a capture is armed.
    let mut b = board();
    let blind = Settings {
        observer: None,
        ..closed()
    };
    assert!(matches!(
        b.handle(Request::LoadParams(blind)),
        Response::Ack { .. }
    ));
    b.ticks(1);
    let _ = b.status();
    assert!(!b.control.is_listening(), "nothing listens");
    b.ticks(16);
    assert!(b.snapshots.is_empty(), "no snapshot while nothing listens");
    assert!(matches!(
        b.handle(Request::Capture(capture)),
        Response::Ack { .. }
    ));
    assert!(b.control.is_listening());
    b.ticks(8 + 8);
    // The capture completed; a status read sees it and the tick stops pushing.
    let _ = b.status();
    assert!(!b.control.is_listening());
    match b.handle(Request::CaptureStatus) {
        Response::Capture(c) => assert_eq!(c.captured, 8, "{c:?}"),
        r => panic!("{r:?}"),
    }
    // Telemetry listens until it stops.
    assert!(matches!(b.handle(telemetry), Response::Ack { .. }));
    b.ticks(40);
    let _ = b.status();
    assert!(b.control.is_listening());
    assert!(matches!(
        b.handle(Request::Telemetry(TelemetryRequest::Stop)),
        Response::Ack { .. }
    ));
    assert!(!b.control.is_listening());
}

/// The observer runs below the tick: the services listen from the load that brings one in
/// force on, the estimate the status reports is theirs (the tick's report carries none), and a
/// load without an observer stops them once its first tick has been served.
#[test]
fn the_observer_below_the_tick_listens_from_its_load_until_a_load_without_one() {
    let mut b = board();
    assert!(!b.control.is_listening(), "the defaults have no observer");
    assert!(matches!(
        b.handle(Request::LoadParams(closed())),
        Response::Ack { .. }
    ));
    assert!(b.control.is_listening(), "listening before the swap's tick");
    b.adc = Adc(40_000);
    b.ticks(64);
    let _ = b.status();
    assert!(b.control.is_listening());
    let below = b
        .services
        .observer()
        .expect("the observer is below the tick")
        .estimate();
    assert_ne!(below, 0);
    assert_eq!(b.status().estimate, below);
    // The same settings without the observer: nothing below the tick any more.
    let bare = Settings {
        observer: None,
        ..closed()
    };
    assert!(matches!(
        b.handle(Request::LoadParams(bare)),
        Response::Ack { .. }
    ));
    b.ticks(8);
    let s = b.status();
    assert!(b.services.observer().is_none());
    assert!(!b.control.is_listening());
    assert_eq!(s.estimate, 0);
}

/// The drift check is reported: with an observer and a sensor with a drift limit, a sensor
/// reading far from the observer's estimate is counted in the status's `drifts`, one a tick
/// the services have checked, as a host decodes it from the status frame; the count is since
/// start-up (a load does not reset it) and stands still without an observer.
#[test]
fn the_status_counts_the_ticks_the_drift_check_flagged_since_start_up() {
    // The status as a host reads it: a `Status` frame in, the response frame decoded.
    fn wire_status<S: RecordStorage>(b: &mut Board<S>) -> StatusReport {
        match b.bytes(&encoded(&Request::Status)).as_slice() {
            [Response::Status(s)] => *s,
            r => panic!("{r:?}"),
        }
    }
    let mut b = board();
    // The defaults have no observer: a reading anywhere is no drift.
    b.adc = Adc(4095);
    b.ticks(64);
    assert_eq!(wire_status(&mut b).drifts, 0);
    // An observer and a drift limit of 2 % of the range; open loop, the setpoint held.
    let mut observed = Settings {
        compensator: Some(representative_pi(16).unwrap()),
        observer: Some(representative_duhem()),
        mode: Mode::OpenLoop,
        ..Settings::default()
    };
    observed.sensor = Some(SensorSettings {
        drift_limit: Some(0.02),
        ..observed.sensor.unwrap()
    });
    assert!(matches!(
        b.handle(Request::LoadParams(observed.clone())),
        Response::Ack { .. }
    ));
    b.ticks(8);
    let estimate = wire_status(&mut b).estimate;
    // The sensor at the end of its span farther from the estimate: half the range away or more.
    b.adc = Adc(if estimate > 0 { 0 } else { 4095 });
    b.ticks(64);
    let first = wire_status(&mut b);
    assert!(first.drifts > 0, "the drift check fired: {first:?}");
    assert_eq!(first.drifts, b.services.drifts());
    // Every tick from now on is flagged and counted, a batch of 8 at a time.
    b.ticks(64);
    let later = wire_status(&mut b);
    assert_eq!(later.drifts, first.drifts + 64);
    // A load does not reset the count, and its observer goes on flagging the stage.
    assert!(matches!(
        b.handle(Request::LoadParams(observed.clone())),
        Response::Ack { .. }
    ));
    b.ticks(64);
    let reloaded = wire_status(&mut b);
    assert!(reloaded.drifts > later.drifts, "{reloaded:?}");
    // Without an observer nothing is checked: the count stands.
    assert!(matches!(
        b.handle(Request::LoadParams(Settings {
            observer: None,
            ..observed
        })),
        Response::Ack { .. }
    ));
    b.ticks(8);
    let bare = wire_status(&mut b).drifts;
    b.ticks(64);
    assert_eq!(wire_status(&mut b).drifts, bare);
    assert!(bare >= reloaded.drifts);
}

/// Once the coarse axis owns the piezo's setpoint (a dual-stage image's coarse task has posted
/// a ramp), every other source is refused as something this image cannot do, setpoints too
/// (no stream would ever play them): nothing is accepted to be dropped, nor a scan's trigger
/// pulses sent with the stage not scanning. The tick follows the ramp to its end; handed
/// back, the stream holds there and takes setpoints again.
#[test]
fn once_the_coarse_axis_owns_the_setpoint_no_other_source_is_accepted() {
    use twinstack::dual_stage::{CoarseTake, FineSetpoints, PreparedCoarse};
    use twinstack::sources::analog_input::{AnalogInputConfig, AnalogRequest, OnFault};
    use twinstack::sources::scan::TriggerEdge;
    use twinstack::sources::sequence::{SequenceConfig, SequenceRequest};
    let mut b = board();
    assert!(matches!(
        b.handle(batch(0, &[1000, 2000])),
        Response::Ack { .. }
    ));
    assert!(!b.control.coarse_owns_setpoint());
    // A post without an attached coarse task is ignored.
    let status = b.control.coarse().status();
    b.control.post_coarse(
        &FineSetpoints {
            from: 0,
            to: 1 << 20,
            ticks: 4,
        },
        status,
    );
    assert!(!b.control.coarse_owns_setpoint());
    b.control.attach_coarse(&PreparedCoarse::new(
        paper_stage_coarse_limits(),
        status,
        RATE,
    ));
    // A scan running when the coarse task first posts stops: the ramp takes over.
    let scan = small_raster(0, false);
    assert!(matches!(
        b.handle(Request::Scan(scan)),
        Response::Ack { .. }
    ));
    b.ticks(3);
    assert!(b.control.is_scanning());
    let end = 1 << 28;
    let status = b.control.coarse().status();
    b.control.post_coarse(
        &FineSetpoints {
            from: 0,
            to: end,
            ticks: 4,
        },
        status,
    );
    assert!(b.control.coarse_owns_setpoint() && !b.control.is_scanning());
    let refused = [
        batch(1, &[3000]),
        Request::Stream(StreamControl::Start),
        Request::Waveform(Waveform {
            shape: WaveShape::Triangle,
            offset: 0,
            amplitude: 1000,
            frequency_mhz: 10_000,
            decay: None,
        }),
        Request::Scan(scan),
        Request::Sequence(SequenceRequest::Arm(SequenceConfig {
            edge: TriggerEdge::Rising,
            window: 0.01,
            settle_ticks: 5,
        })),
        Request::Analog(AnalogRequest::Start(AnalogInputConfig {
            gain: 2.0,
            offset: -1.0,
            corner_hz: None,
            lost_below: 0.0,
            over_above: 1.0,
            on_fault: OnFault::Hold,
            rate: 10.0,
            start_at_boot: false,
        })),
        Request::Trigger(TriggerConfig {
            pulse_ticks: 2,
            input: TriggerEdge::Rising,
            start_stream: true,
        }),
    ];
    for request in refused {
        let what = format!("{request:?}");
        assert_eq!(
            b.handle(request),
            nack(NackReason::Unsupported),
            "{what} while the coarse axis owns the setpoint"
        );
    }
    assert_eq!(b.queued(), vec![1000, 2000], "the queue is as it was");
    // The coarse task's exchange: the command the handler left, and the piezo's position as
    // the sensor last read it; none without a sensor.
    let reading = b.control.controller().position();
    let take = |measured| CoarseTake {
        command: None,
        measured,
        resume_fine: None,
    };
    assert_eq!(b.control.take_coarse(), take(Some(reading)));
    let mut blind = board();
    blind.control.attach_coarse(&PreparedCoarse::new(
        paper_stage_coarse_limits(),
        status,
        RATE,
    ));
    let no_sensor = Settings {
        sensor: None,
        ..blind.read_params()
    };
    assert!(matches!(
        blind.handle(Request::LoadParams(no_sensor)),
        Response::Ack { .. }
    ));
    blind.ticks(1);
    assert_eq!(blind.control.take_coarse(), take(None));
    // What does not start a source still works: the trigger outputs alone.
    assert!(matches!(
        b.handle(Request::Trigger(TriggerConfig {
            pulse_ticks: 2,
            input: TriggerEdge::Off,
            start_stream: false,
        })),
        Response::Ack { .. }
    ));
    b.ticks(4);
    assert_eq!(
        b.control.controller().setpoint(),
        end,
        "the ramp lands on its end"
    );
    assert!(!b.control.is_scanning(), "the scan stopped for good");
    // Handed back: the stream holds where the ramp left the setpoint, and takes setpoints;
    // the task's posts are ignored until it is attached again.
    b.control.release_coarse();
    assert!(!b.control.coarse_owns_setpoint());
    b.control.post_coarse(
        &FineSetpoints {
            from: 0,
            to: 0,
            ticks: 4,
        },
        status,
    );
    assert!(!b.control.coarse_owns_setpoint());
    b.ticks(2);
    assert_eq!(b.control.controller().setpoint(), end);
    assert!(matches!(b.handle(batch(1, &[3000])), Response::Ack { .. }));
}

/// The piezo handed back from the coarse axis (`ControlLoop::release_piezo`): the coarse task
/// stays attached and charged, its posts carry only its status, and the piezo's own sources
/// start again; a motion command left for the task takes the piezo back from the handler's
/// acknowledgement on (the sources are refused again), and the task is told where the
/// piezo's setpoint is, so that its ramp leaves from there.
#[test]
fn the_piezo_handed_back_from_the_coarse_axis_plays_its_own_sources_until_the_next_motion() {
    use twinstack::dual_stage::{CoarseCommand, FineSetpoints, MotionLimits, PreparedCoarse};
    let mut b = board();
    let status = b.control.coarse().status();
    let task = PreparedCoarse::new(paper_stage_coarse_limits(), status, RATE);
    b.control.attach_coarse(&task);
    let ramp = |to| FineSetpoints {
        from: 0,
        to,
        ticks: 4,
    };
    b.control.post_coarse(&ramp(1 << 28), status);
    b.ticks(4);
    assert!(b.control.coarse_owns_setpoint());
    assert!(!b.control.piezo_source_busy());
    b.control.release_piezo();
    assert!(!b.control.coarse_owns_setpoint());
    assert_eq!(
        b.control.beside().coarse_task,
        task.share(),
        "still charged"
    );
    // A scan plays; the task's posts update the status and move nothing.
    assert!(matches!(
        b.handle(Request::Scan(small_raster(0, false))),
        Response::Ack { .. }
    ));
    assert!(b.control.piezo_source_busy());
    b.ticks(30);
    let moved = CoarseStatus {
        ticks: status.ticks + 7,
        ..status
    };
    b.control.post_coarse(&ramp(0), moved);
    assert_eq!(b.control.coarse().status(), moved);
    b.ticks(3);
    assert!(b.control.is_scanning() && !b.control.coarse_owns_setpoint());
    let take = b.control.take_coarse();
    assert_eq!((take.command, take.resume_fine), (None, None));
    assert!(take.measured.is_some(), "the sensor's reading");
    // Stopped, the piezo holds; a move left for the task takes it back at once.
    assert!(matches!(
        b.handle(Request::Stream(StreamControl::Stop)),
        Response::Ack { .. }
    ));
    let held = b.control.controller().setpoint();
    let limits = MotionLimits {
        velocity: 1000,
        acceleration: 10,
    };
    b.control.coarse().request(CoarseCommand::MoveTo {
        target_pm: 1_000_000,
        limits: limits.prepare(),
    });
    assert!(b.control.coarse_owns_setpoint());
    assert_eq!(
        b.handle(Request::Stream(StreamControl::Start)),
        nack(NackReason::Unsupported)
    );
    let take = b.control.take_coarse();
    assert!(matches!(take.command, Some(CoarseCommand::MoveTo { .. })));
    assert_eq!(
        take.resume_fine,
        Some(held),
        "the ramp leaves from the piezo"
    );
    b.control.post_coarse(&ramp(held + 400), status);
    b.tick();
    assert_eq!(b.control.controller().setpoint(), held + 100, "no jump");
    assert!(b.control.coarse_owns_setpoint());
    // A stop taken while handed back engages nothing.
    b.control.release_piezo();
    b.control.coarse().request(CoarseCommand::Stop);
    assert!(!b.control.coarse_owns_setpoint());
    let take = b.control.take_coarse();
    assert_eq!(take.resume_fine, None);
    b.control.post_coarse(&ramp(0), status);
    assert!(!b.control.coarse_owns_setpoint());
}

/// The coarse axis's limits of the paper stage's supervisor, at its 5 kHz coarse rate (what the
/// dual-stage images attach).
fn paper_stage_coarse_limits() -> twinstack::dual_stage::CoarseLimits {
    use twinstack::dual_stage::{
        CoarseSupervisor, DualStage, DualStageSettings, SupervisorSettings,
    };
    let settings = DualStageSettings::paper_stage();
    let dual = DualStage::new(settings.build().unwrap(), 0, 0, 0);
    let supervision = SupervisorSettings::paper_stage()
        .build(dual.config(), settings.coarse_rate_hz)
        .unwrap();
    CoarseSupervisor::new(dual, supervision).limits()
}

/// The dual-stage images' coarse task runs below the tick once a coarse period: attached, it
/// is charged its share of every tick (`tick_budget::coarse_task_share`), so a load that fits
/// the period alone but not beside the task is refused with the cycles it needs, and the
/// configuration in force stays; detached, the same load is taken.
#[test]
fn a_load_that_leaves_the_coarse_task_no_time_is_refused_with_its_cycles() {
    use twinstack::config::tick_budget::{
        available_cycles, coarse_task_share, pipeline_cycles, Beside,
    };
    use twinstack::dual_stage::PreparedCoarse;
    let rate = 100_000.0;
    let hw = Hardware::driver_board(rate);
    let mut b = board_on(RamStorage::default(), hw);
    let limits = paper_stage_coarse_limits();
    let share = coarse_task_share(limits.coarse_rate_hz as u32, rate as u32);
    assert_eq!(share, 180);
    let status = b.control.coarse().status();
    let task = PreparedCoarse::new(limits, status, rate as u32);
    assert_eq!(task.share(), share);
    b.control.attach_coarse(&task);
    assert_eq!(b.control.beside().coarse_task, share);
    // Duhem as the compensator fits 100 kHz alone, not beside the task.
    let dear = Settings {
        compensator: Some(representative_duhem()),
        mode: Mode::OpenLoop,
        ..b.read_params()
    };
    let config = dear.build(&hw).unwrap();
    let alone = pipeline_cycles(&config, Beside::default());
    assert!(alone <= available_cycles(rate) && alone + share > available_cycles(rate));
    let before = b.read_params();
    refused_as_overrun(
        b.handle(Request::LoadParams(dear.clone())),
        alone + share,
        rate,
    );
    assert_eq!(b.read_params(), before, "the configuration in force stays");
    b.control.release_coarse();
    assert_eq!(b.control.beside().coarse_task, 0);
    assert!(matches!(
        b.handle(Request::LoadParams(dear)),
        Response::Ack { .. }
    ));
}

/// A raster of 3 lines of 40 pixels, ±0.5, 3 ticks a pixel: `frames` of them (0: until
/// stopped), started now or by the trigger input's edge.
fn small_raster(frames: u16, on_trigger: bool) -> twinstack::sources::scan::ScanRequest {
    use twinstack::sources::scan::{RasterScan, ScanPattern, ScanRequest};
    ScanRequest {
        pattern: ScanPattern::Raster(RasterScan {
            lines: 3,
            pixels: 40,
            turn_ticks: 20,
            offset: 0.0,
            amplitude: 0.5,
            y_offset: 0.0,
            y_amplitude: 0.5,
        }),
        ticks_per_pixel: 3,
        frames,
        on_trigger,
    }
}

/// A scan's start restarts the learning's period at bin 0, as a waveform's or a stream's
/// does, whether the request starts it or the trigger input's edge: a table learned on a scan
/// is aligned with the scan's start, and plays again aligned on the same scan started again.
#[test]
fn a_scan_s_start_restarts_the_learning_s_period_now_or_on_the_input_s_edge() {
    use twinstack::services::learning::{LearnSettings, LearnState};
    use twinstack::sources::scan::{TriggerConfig, TriggerEdge};
    let mut b = board();
    for request in [
        Request::Learn(LearnRequest::Configure(LearnSettings::for_period(200))),
        Request::Learn(LearnRequest::State(LearnState::Frozen)),
    ] {
        assert!(matches!(b.handle(request), Response::Ack { .. }));
    }
    b.ticks(37);
    assert_eq!(b.control.learning().bin(), 37, "the period runs");
    // Started by the request: at bin 0 from the next tick.
    assert!(matches!(
        b.handle(Request::Scan(small_raster(1, false))),
        Response::Ack { .. }
    ));
    assert_eq!(b.control.learning().bin(), 0);
    b.ticks(37);
    assert_eq!(b.control.learning().bin(), 37);
    // Waiting for the input's edge: the period runs on until the edge starts the scan.
    assert!(matches!(
        b.handle(Request::Trigger(TriggerConfig {
            pulse_ticks: 2,
            input: TriggerEdge::Rising,
            start_stream: false,
        })),
        Response::Ack { .. }
    ));
    assert!(matches!(
        b.handle(Request::Scan(small_raster(1, true))),
        Response::Ack { .. }
    ));
    assert_eq!(
        b.control.learning().bin(),
        37,
        "a waiting scan restarts nothing"
    );
    b.ticks(5);
    assert_eq!(b.control.learning().bin(), 42);
    b.control.set_trigger_input(true);
    b.tick();
    assert!(b.control.is_scanning(), "the edge started the scan");
    // The edge's tick ran bin 0.
    assert_eq!(b.control.learning().bin(), 1);
}
