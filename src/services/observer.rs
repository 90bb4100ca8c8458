//! The forward observer and its drift check, below the tick.
//!
//! Nothing in the tick needs the observer's estimate: the feedback acts on the measurement,
//! and the estimate is only reported (the recorder's and telemetry's `estimate` signal, the
//! status) and, with a sensor, compared with the measurement (the drift check: the model no
//! longer describes the stage). So the tick does not run the observer. It only has to see
//! every drive sample the stacks were given, in order, not at once: the services run it from
//! the tick's snapshots ([`crate::services::consumer::Services`]), each snapshot's applied
//! drive and measurement, in the same order and fixed point as the tick did — the same
//! estimates and drift flags, bit for bit, computed a batch later at a lower priority.
//!
//! A configuration's observer below the tick is prepared with it, off the tick, at the same
//! stacks' voltages: relaxed at the drive they hold, once — the controller's preparation
//! relaxes it to derive its compensator's state and hands it out ([`Controller::prepare`],
//! [`ObserverBelow::from_relaxed`]); [`ObserverBelow::prepare`] relaxes it on its own, for
//! what has no controller prepared beside it. A reload reaches the services in band: the command
//! handler stages the new configuration's observer ([`crate::services::consumer::Services::stage_observer`])
//! before it posts the controller, and the first snapshot of the new controller carries the
//! loop's new swap count ([`crate::services::snapshot::Snapshot::generation`]), at which the
//! services put the staged observer in force — the tick the new controller first ran.
//!
//! [`Observed`] runs a controller and its observer below the tick in one call, for what runs
//! the control law on its own (the golden vectors' replay, the closed-loop studies): the
//! report is the one the board's tick and services give together.

use crate::board::{DualDac, SensorAdc};
use crate::control::drive::StackVoltages;
use crate::control::feedback::DRIFT_FILTER_SHIFT;
use crate::control::instant::ReadingInstant;
use crate::control::{ControlConfig, Controller, Observer, RelaxedObserver, TickFlags, TickReport};
use crate::models::ObserverRun;

/// What the observer below the tick costs a snapshot beside its model's own cycles (which
/// each model declares, as in the tick) and the snapshot's full serve
/// (`services::consumer::SERVICES_EVERY_CYCLES`: with an observer the services serve every
/// snapshot in full): the dispatch, the drift check, the estimate's history, the report's
/// fields it reads and writes, at 5 flash wait states. Measured by the whole-interrupt bench
/// (`cargo test --profile host-opt --test irq_bench`), which traces the services' task
/// serving it beside a capture and telemetry and fails any scenario whose services' share
/// exceeds what the tick budget charges them (`config::tick_budget::observer_below_cycles`
/// with the services' own coefficients).
pub const OBSERVER_BELOW_CYCLES: u32 = 80;

/// The forward observer of a configuration with a sensor and its drift check, fed the tick's
/// applied drive and measurement from the snapshots.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ObserverBelow {
    observer: ObserverRun,
    /// Largest low-passed |measured − estimate| before the drift flag, Q2.30 (`u32::MAX`: no
    /// check).
    drift_limit: u32,
    /// Whether the stage has a sensor (no drift check without one).
    sensed: bool,
    /// The last estimates, each of the middle of its drive's hold, and from them the estimate
    /// of the instant of the present reading (the end of the hold [`SENSOR_DELAY_TICKS`](crate::control::feedback::SENSOR_DELAY_TICKS)
    /// ticks old: [`crate::control::instant`]).
    estimates: ReadingInstant,
    /// Low-passed measured − estimate, Q2.30.
    drift: i32,
    /// The last drift check's verdict.
    drifting: bool,
}

impl ObserverBelow {
    /// The observer below the tick for `config` with the stacks at `stacks` (board units; the
    /// voltages the controller is prepared at, [`Controller::prepare`]): `None` where it has
    /// none. Relaxes the model itself, off the tick: where a controller is prepared beside it,
    /// [`ObserverBelow::from_relaxed`] takes the observer that preparation relaxed instead.
    ///
    /// ```
    /// use twinstack::board::Hardware;
    /// use twinstack::config::settings::{representative_pi, SensorSettings, Settings};
    /// use twinstack::services::observer::ObserverBelow;
    ///
    /// let hardware = Hardware::driver_board(50_000.0);
    /// let config = Settings::default().build(&hardware).unwrap();
    /// assert!(ObserverBelow::prepare(&config, config.drive.safe_stacks()).is_none());
    /// let observed = Settings { observer: Some(representative_pi(8).unwrap()), ..Settings::default() };
    /// let config = observed.build(&hardware).unwrap();
    /// let o = ObserverBelow::prepare(&config, config.drive.safe_stacks()).unwrap();
    /// assert!(!o.is_drifting());
    /// ```
    pub fn prepare(config: &ControlConfig, stacks: StackVoltages) -> Option<Self> {
        if matches!(config.observer, Observer::None) {
            return None;
        }
        let drive = config.drive.drive_of(stacks.left);
        let (run, output) = config
            .observer
            .prepare(config.creep, drive, config.drive.rest());
        Self::from_relaxed(config, RelaxedObserver { run, output })
    }

    /// The observer below the tick for `config` from the observer its controller's
    /// preparation relaxed ([`Controller::prepare`] on `config`, which hands it out): the same
    /// as [`ObserverBelow::prepare`] at the same stacks, bit for bit, without relaxing the
    /// model again. `None` where `config` has no observer.
    ///
    /// ```
    /// use twinstack::board::Hardware;
    /// use twinstack::config::settings::{representative_pi, Settings};
    /// use twinstack::control::Controller;
    /// use twinstack::services::observer::ObserverBelow;
    ///
    /// let hardware = Hardware::driver_board(50_000.0);
    /// let observed = Settings { observer: Some(representative_pi(8).unwrap()), ..Settings::default() };
    /// let config = observed.build(&hardware).unwrap();
    /// let mut c = Controller::new(config);
    /// let stacks = c.stacks();
    /// let relaxed = c.prepare(config, stacks);
    /// let o = ObserverBelow::from_relaxed(&config, relaxed).unwrap();
    /// assert_eq!(o.estimate(), ObserverBelow::prepare(&config, stacks).unwrap().estimate());
    /// ```
    pub fn from_relaxed(config: &ControlConfig, relaxed: RelaxedObserver) -> Option<Self> {
        if matches!(config.observer, Observer::None) {
            return None;
        }
        Some(Self {
            observer: relaxed.run,
            drift_limit: config.sensor.map_or(u32::MAX, |s| s.drift_limit),
            sensed: config.sensor.is_some(),
            estimates: ReadingInstant::at(relaxed.output),
            drift: 0,
            drifting: false,
        })
    }

    /// One tick, after it: the observer on its applied drive, then the drift check of its
    /// measurement against the estimate of the reading's instant (with a sensor; skipped on a
    /// failed reading). Fills the report's `estimate` and sets its `DRIFT` flag as the tick
    /// would have. No division, no loop, no panic.
    #[inline(always)]
    pub fn observe(&mut self, report: &mut TickReport) {
        let estimate = self.observer.step(report.drive);
        let at_reading = self.estimates.push(estimate);
        report.estimate = estimate;
        if self.sensed && !report.flags.contains(TickFlags::ADC_ERROR) {
            let difference = report.measured.saturating_sub(at_reading);
            let step = difference.saturating_sub(self.drift) >> DRIFT_FILTER_SHIFT;
            self.drift = self.drift.saturating_add(step);
            self.drifting = self.drift.unsigned_abs() > self.drift_limit;
            if self.drifting {
                report.flags.0 |= TickFlags::DRIFT;
            }
        }
    }

    /// The last estimate, Q2.30 normalised displacement.
    pub fn estimate(&self) -> i32 {
        self.estimates.newest()
    }

    /// The low-passed difference measured − estimate, Q2.30 normalised displacement.
    pub fn drift(&self) -> i32 {
        self.drift
    }

    /// Whether the last drift check found the model drifted from the stage.
    pub fn is_drifting(&self) -> bool {
        self.drifting
    }
}

/// A controller and its observer, run one after the other: the report the board's tick and
/// its services give together, for what runs the control law without the board's two
/// priorities (replays, studies, tests).
#[derive(Clone, Debug)]
pub struct Observed {
    /// The controller (the tick).
    pub controller: Controller,
    /// Its observer, if its configuration has one.
    pub observer: Option<ObserverBelow>,
}

impl Observed {
    /// A controller on `config` ([`Controller::new`]) and its observer below the tick,
    /// prepared at the same stacks.
    ///
    /// ```
    /// use twinstack::board::Hardware;
    /// use twinstack::config::settings::Settings;
    /// use twinstack::services::observer::Observed;
    /// let config = Settings::default().build(&Hardware::driver_board(50_000.0)).unwrap();
    /// let o = Observed::new(config);
    /// assert!(o.observer.is_none()); // the defaults have no model
    /// ```
    pub fn new(config: ControlConfig) -> Self {
        let controller = Controller::new(config);
        let observer = ObserverBelow::prepare(&config, controller.stacks());
        Self {
            controller,
            observer,
        }
    }

    /// Reloads `config` as the board does: the controller prepared at the stacks' present
    /// voltages ([`Controller::prepare`]) takes over from the running one
    /// ([`Controller::take_over`]), and the observer below the tick starts from the observer
    /// that preparation relaxed ([`ObserverBelow::from_relaxed`]), in force from the next tick.
    pub fn reload(&mut self, config: ControlConfig) {
        let stacks = self.controller.stacks();
        let mut next = self.controller.clone();
        let relaxed = next.prepare(config, stacks);
        next.take_over(&self.controller);
        self.controller = next;
        self.observer = ObserverBelow::from_relaxed(&config, relaxed);
    }

    /// One tick ([`Controller::tick`]) and the observer below it on the tick's report.
    #[inline]
    pub fn tick<D: DualDac, A: SensorAdc>(
        &mut self,
        setpoint: Option<i32>,
        adc: &mut A,
        dac: &mut D,
    ) -> TickReport {
        let report = self.controller.tick(setpoint, adc, dac);
        self.observed(report)
    }

    /// [`Observed::tick`] for a board that is both the DAC and the ADC.
    #[inline]
    pub fn tick_board<B: DualDac + SensorAdc>(
        &mut self,
        setpoint: Option<i32>,
        board: &mut B,
    ) -> TickReport {
        let report = self.controller.tick_board(setpoint, board);
        self.observed(report)
    }

    /// The tick's `report` with the observer's estimate and drift flag filled in.
    #[inline(always)]
    fn observed(&mut self, mut report: TickReport) -> TickReport {
        if let Some(o) = &mut self.observer {
            o.observe(&mut report);
        }
        report
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::board::DacCode;
    use crate::fixed_point::signal_from_f64;

    /// An observer whose estimate reads 0 (no model), with a sensor and a 1 % drift limit:
    /// the drift check alone.
    fn check_alone() -> ObserverBelow {
        ObserverBelow {
            observer: ObserverRun::NONE,
            drift_limit: signal_from_f64(0.01) as u32,
            sensed: true,
            estimates: ReadingInstant::at(0),
            drift: 0,
            drifting: false,
        }
    }

    fn report(measured: i32, flags: u8) -> TickReport {
        TickReport {
            left: DacCode(0),
            right: DacCode(0),
            estimate: 0,
            measured,
            drive: 0,
            flags: TickFlags(flags),
            triggers: 0,
        }
    }

    fn drifted(o: &mut ObserverBelow, measured: i32) -> bool {
        let mut r = report(measured, 0);
        o.observe(&mut r);
        r.flags.contains(TickFlags::DRIFT)
    }

    /// The observer a controller's preparation hands out (what a load stages below the tick)
    /// is the one [`ObserverBelow::prepare`] relaxes on its own at the same stacks, bit for
    /// bit: every model, with and without creep, with and without a drift check, wherever
    /// the stacks stand.
    #[test]
    fn the_observer_a_preparation_hands_out_is_the_one_prepared_on_its_own() {
        use crate::board::Hardware;
        use crate::config::settings::{
            representative_bouc_wen, representative_duhem, representative_gpi, representative_pi,
            Settings,
        };
        use crate::models::creep::CreepParams;
        // 40 kHz: Bouc–Wen with creep and its observer beside it needs more than 80 % of 50 kHz.
        let hardware = Hardware::driver_board(40_000.0);
        let models = [
            None,
            Some(representative_pi(16).unwrap()),
            Some(representative_gpi(8).unwrap()),
            Some(representative_duhem()),
            Some(representative_bouc_wen()),
        ];
        let mut compared = 0;
        for model in models {
            for creep in [false, true] {
                for drift_limit in [None, Some(0.02)] {
                    let mut s = Settings {
                        compensator: model.clone(),
                        observer: model.clone(),
                        creep: creep
                            .then(|| CreepParams::new(&[1e-3, 1e-2], &[0.05, 0.05]).unwrap()),
                        ..Settings::default()
                    };
                    if let Some(sensor) = &mut s.sensor {
                        sensor.drift_limit = drift_limit;
                    }
                    let config = s.build(&hardware).unwrap();
                    let safe = config.drive.safe_stacks();
                    for step in [-20_000i32, 0, 12_000, 30_000] {
                        let stacks = StackVoltages {
                            left: safe.left.saturating_add(step << 15),
                            right: safe.right.saturating_sub(step << 15),
                        };
                        let mut c = Controller::new(config);
                        let relaxed = c.prepare(config, stacks);
                        let handed = ObserverBelow::from_relaxed(&config, relaxed);
                        let own = ObserverBelow::prepare(&config, stacks);
                        assert_eq!(handed, own, "{model:?}, creep {creep}, stacks {stacks:?}");
                        assert_eq!(handed.is_some(), model.is_some());
                        compared += usize::from(handed.is_some());
                    }
                }
            }
        }
        assert_eq!(compared, 4 * 2 * 2 * 4);
    }

    #[test]
    fn drift_is_flagged_when_the_sensor_leaves_the_estimate_and_cleared_when_it_returns() {
        let mut o = check_alone();
        // The estimate and the (delayed) measurement agree, with sensor noise: no flag.
        let mut seed = 3u32;
        for _ in 0..500 {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let noise = ((seed >> 16) as i32 - 32768) * 256; // ±0.8 % of full scale
            assert!(!drifted(&mut o, noise));
        }
        // The stage sits 2 % away from the model: flagged within a few filter time constants.
        let flagged = (0..100).position(|_| drifted(&mut o, signal_from_f64(0.02)));
        assert!(matches!(flagged, Some(k) if k < 40), "{flagged:?}");
        assert!(o.is_drifting());
        // Back in agreement: the flag clears.
        let cleared = (0..200).position(|_| !drifted(&mut o, 0));
        assert!(cleared.is_some());
        assert!(!o.is_drifting());
    }

    #[test]
    fn the_reading_is_compared_with_the_estimate_of_its_instant_and_skipped_when_it_failed() {
        // The estimates were 0.5 until this tick's, 0: a reading of 0 is below the estimate of
        // its instant, SENSOR_DELAY_TICKS ticks back (the present estimate would see no drift).
        let mut o = check_alone();
        o.estimates = ReadingInstant::at(signal_from_f64(0.5));
        let mut r = report(0, 0);
        o.observe(&mut r);
        assert!(
            o.drift() < 0,
            "the old estimate (0.5) is what the reading is compared to"
        );
        // A failed reading leaves the check as it was; no sensor, no check at all.
        let mut o = check_alone();
        let mut r = report(signal_from_f64(0.5), TickFlags::ADC_ERROR);
        o.observe(&mut r);
        assert_eq!(o.drift(), 0);
        let mut o = ObserverBelow {
            sensed: false,
            ..check_alone()
        };
        for _ in 0..100 {
            assert!(!drifted(&mut o, signal_from_f64(0.5)));
        }
        assert_eq!(o.drift(), 0);
    }
}
