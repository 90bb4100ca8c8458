//! What a configuration costs the control tick, and the highest control rate the board admits
//! it at: the tick budget ([`twinstack::config::tick_budget`]) asked for each configuration
//! as loaded, without its observer, and with every feature a user may run beside it (the
//! learning feedforward, a scan, the trigger input armed, a capture and telemetry).
//!
//! ```
//! use twinstack_identify::budget::{family, BudgetRow};
//!
//! let rows: Vec<BudgetRow> = family().iter().map(|(name, s)| BudgetRow::of(name, s).unwrap()).collect();
//! // Every row's figures follow from its cycles; dropping the observer never costs more.
//! assert!(rows.iter().all(|r| r.without_observer.is_none_or(|w| w.cycles <= r.loaded.cycles)));
//! ```

use twinstack::board::Hardware;
use twinstack::config::settings::{
    representative_bouc_wen, representative_duhem, representative_pi, FeedbackSettings, Mode,
    Model, SensorSettings, Settings,
};
use twinstack::config::tick_budget::{
    available_cycles, coarse_task_share, highest_rate_hz, pipeline_cycles, worst_case_cycles,
    Beside,
};
use twinstack::models::creep::CreepParams;
use twinstack::models::generalised_pi::{DeadZoneParams, GpiParams};
use twinstack::refusal::Refusal;

/// One prediction: the tick's worst case and the highest rate it is admitted at.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Prediction {
    /// The pipeline's predicted worst case per tick (the interrupt and, with an observer below
    /// the tick or anything captured, the services' share), cycles at 5 flash wait states.
    pub cycles: u32,
    /// The highest control rate at which it is admitted, Hz.
    pub highest_rate_hz: f64,
    /// The rate of the coarse task a dual-stage image runs beside the pipeline, Hz (0: a
    /// piezo-only image): its share of each tick
    /// ([`twinstack::config::tick_budget::coarse_task_share`], which falls with the control
    /// rate) is charged beside `cycles` at every rate, as the board charges it.
    #[serde(skip_serializing_if = "is_zero")]
    pub coarse_rate_hz: u32,
}

fn is_zero(v: &u32) -> bool {
    *v == 0
}

impl Prediction {
    /// `cycles` on a board whose coarse task runs at `coarse_rate_hz` beside them (0: none).
    /// With a coarse task the highest rate is a whole number of hertz, as the board's rates
    /// are.
    ///
    /// ```
    /// use twinstack_identify::budget::Prediction;
    /// // 1 344 cycles fill 80 % of a 100 kHz period; beside a 5 kHz coarse task
    /// // (3 600 cycles a coarse period) they fit only up to about 86 kHz.
    /// let alone = Prediction::beside_coarse(1_344, 0);
    /// let dual = Prediction::beside_coarse(1_344, 5_000);
    /// assert!(alone.admitted_at(100_000.0) && !dual.admitted_at(100_000.0));
    /// assert!(dual.admitted_at(dual.highest_rate_hz));
    /// assert!(!dual.admitted_at(dual.highest_rate_hz + 1.0));
    /// assert!((86_000.0..87_000.0).contains(&dual.highest_rate_hz));
    /// ```
    pub fn beside_coarse(cycles: u32, coarse_rate_hz: u32) -> Self {
        let mut p = Self {
            cycles,
            highest_rate_hz: highest_rate_hz(cycles),
            coarse_rate_hz,
        };
        if coarse_rate_hz > 0 {
            p.highest_rate_hz = p.highest_with_coarse();
        }
        p
    }

    /// The cycles charged at `rate_hz`: the pipeline's and the coarse task's share.
    fn charged_at(&self, rate_hz: f64) -> u32 {
        if self.coarse_rate_hz == 0 {
            return self.cycles;
        }
        // The board's rate is a whole number of hertz (its `u32`).
        let share = coarse_task_share(self.coarse_rate_hz, rate_hz.max(1.0) as u32);
        self.cycles.saturating_add(share)
    }

    /// Whether the cycles (and the coarse task's share) fit the period at `rate_hz`.
    fn fits(&self, rate_hz: f64) -> bool {
        available_cycles(rate_hz) >= self.charged_at(rate_hz)
    }

    /// The highest whole rate at which the pipeline and the coarse task's share fit: the
    /// share is `COARSE_TASK_CYCLES · coarse / rate` rounded up, so the period's share left is
    /// `(available · rate − COARSE_TASK_CYCLES · coarse) / rate`, and the rate solves that
    /// for `cycles`; the roundings move it by a few hertz, which the steps down from above
    /// it find. 0 when the coarse task alone takes the period's share.
    fn highest_with_coarse(&self) -> f64 {
        let per_second = available_cycles(1.0) as f64;
        let coarse = f64::from(twinstack::config::tick_budget::COARSE_TASK_CYCLES)
            * f64::from(self.coarse_rate_hz);
        let estimate = (per_second - coarse) / f64::from(self.cycles.max(1));
        if estimate.is_nan() || estimate < 1.0 {
            return 0.0;
        }
        // A few hertz above the estimate; steps down to the first rate that fits (bounded:
        // the roundings are worth a few cycles, far fewer hertz than the steps allowed).
        let mut rate = estimate.floor() + 8.0;
        for _ in 0..4_096 {
            if rate < 1.0 {
                break;
            }
            if self.fits(rate) {
                return rate;
            }
            rate -= 1.0;
        }
        0.0
    }

    /// Whether the board runs it at `rate_hz` (within its range of rates and the budget,
    /// the coarse task's share beside it).
    pub fn admitted_at(&self, rate_hz: f64) -> bool {
        self.fits(rate_hz)
            && (Hardware::MIN_CONTROL_RATE_HZ as f64..=Hardware::MAX_CONTROL_RATE_HZ as f64)
                .contains(&rate_hz)
    }
}

/// A configuration's budget: as loaded, without its observer, and with every feature beside.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct BudgetRow {
    /// What it is.
    pub name: String,
    /// As loaded.
    pub loaded: Prediction,
    /// The same without its observer (`None`: it has none). With a sensor, the observer's
    /// estimate is telemetry only; the feedback runs on the sensor.
    pub without_observer: Option<Prediction>,
    /// As loaded, with the learning feedforward on, a scan running, the trigger input armed,
    /// a capture and telemetry running ([`BESIDE_EVERY_FEATURE`]).
    pub every_feature: Prediction,
}

/// What can run beside a configuration at once: the learning, a scan (the analog input is
/// the other board-side source, and cheaper), the armed trigger input, a capture and
/// telemetry (the services).
pub const BESIDE_EVERY_FEATURE: Beside = Beside::EVERY_FEATURE;

impl BudgetRow {
    /// The budget of `settings`, or the refusal the board would send for them at its slowest
    /// rate (a model out of range, a sensor without feedback, …).
    pub fn of(name: &str, settings: &Settings) -> Result<Self, Refusal> {
        Self::beside_coarse(name, settings, 0)
    }

    /// [`BudgetRow::of`] on a dual-stage image whose coarse task runs at `coarse_rate_hz`
    /// (0: a piezo-only image): its share of each tick is charged beside every prediction.
    pub fn beside_coarse(
        name: &str,
        settings: &Settings,
        coarse_rate_hz: u32,
    ) -> Result<Self, Refusal> {
        let hardware = Hardware::driver_board(f64::from(Hardware::MIN_CONTROL_RATE_HZ));
        let config = settings.build(&hardware)?;
        let predict = |cycles| Prediction::beside_coarse(cycles, coarse_rate_hz);
        let loaded = worst_case_cycles(&config);
        let without_observer = match settings.observer {
            Some(_) => {
                let bare = Settings {
                    observer: None,
                    ..settings.clone()
                };
                Some(predict(worst_case_cycles(&bare.build(&hardware)?)))
            }
            None => None,
        };
        Ok(Self {
            name: name.to_string(),
            loaded: predict(loaded),
            without_observer,
            every_feature: predict(pipeline_cycles(&config, BESIDE_EVERY_FEATURE)),
        })
    }
}

/// The closed loop as `calibrate` loads it: `model` as compensator and observer, a sensor with
/// its drift check, PI feedback, closed loop.
fn closed(model: Model) -> Settings {
    Settings {
        compensator: Some(model.clone()),
        observer: Some(model),
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

/// A generalised P–I of `n` operators with all 8 dead zones (four a side), the shape
/// `calibrate` fits by default.
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

/// Every model `calibrate` (and `identify --model auto`) can pick, at its default size, without
/// and with four creep modes, each loaded as `calibrate` loads it (compensator and observer, a
/// sensor with its drift check, PI feedback): the names say what runs.
pub fn family() -> Vec<(String, Settings)> {
    let mut out = Vec::new();
    let creep = CreepParams::new(&[0.01, 0.1, 1.0, 10.0], &[0.02; 4]).ok();
    let models = [
        ("P–I 17", representative_pi(17).ok()),
        ("generalised P–I 17 × 8", gpi_with_eight_dead_zones(17)),
        ("Bouc–Wen", Some(representative_bouc_wen())),
        ("Duhem", Some(representative_duhem())),
    ];
    for (name, model) in models {
        let Some(model) = model else { continue };
        out.push((format!("{name} + PI"), closed(model.clone())));
        if let Some(creep) = &creep {
            out.push((
                format!("{name} + creep 4 + PI"),
                Settings {
                    creep: Some(creep.clone()),
                    ..closed(model)
                },
            ));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use twinstack::config::tick_budget::{check, check_with};

    #[test]
    fn the_highest_rate_is_where_the_board_starts_to_refuse() {
        for (name, settings) in family() {
            let row = BudgetRow::of(&name, &settings).unwrap();
            let hardware = Hardware::driver_board(10_000.0);
            let config = settings.build(&hardware).unwrap();
            let at = row.loaded.highest_rate_hz;
            assert!(check(&config, at).is_ok(), "{name} refused at {at}");
            assert!(
                check(&config, at * 1.000_001).is_err(),
                "{name} admitted above {at}"
            );
            let all = row.every_feature.highest_rate_hz;
            assert!(check_with(&config, all, BESIDE_EVERY_FEATURE).is_ok());
            assert!(check_with(&config, all * 1.000_001, BESIDE_EVERY_FEATURE).is_err());
            assert!(available_cycles(all) >= row.every_feature.cycles);
            let without = row
                .without_observer
                .expect("every family member has an observer");
            assert!(without.cycles < row.loaded.cycles, "{name}");
        }
    }

    #[test]
    fn beside_a_coarse_task_the_highest_rate_is_where_the_dual_stage_board_starts_to_refuse() {
        use twinstack::config::tick_budget::Beside;
        // The board's own check, at a whole rate, with the coarse task's share as the
        // dual-stage image charges it (`PreparedCoarse`).
        let board_admits = |config: &twinstack::control::ControlConfig, rate: f64, coarse| {
            let beside = Beside {
                coarse_task: coarse_task_share(coarse, rate as u32),
                ..Beside::default()
            };
            check_with(config, rate, beside).is_ok()
        };
        for (name, settings) in family() {
            let config = settings.build(&Hardware::driver_board(10_000.0)).unwrap();
            let alone = BudgetRow::of(&name, &settings).unwrap();
            for coarse in [1_000, 5_000, 10_000] {
                let row = BudgetRow::beside_coarse(&name, &settings, coarse).unwrap();
                let at = row.loaded.highest_rate_hz;
                assert_eq!(at, at.floor(), "{name}: a whole rate");
                assert!(at < alone.loaded.highest_rate_hz, "{name}: the task costs");
                assert!(board_admits(&config, at, coarse), "{name} refused at {at}");
                // Every whole rate above it up to 10 Hz higher is refused.
                for up in 1..=10 {
                    let above = at + f64::from(up);
                    assert!(!board_admits(&config, above, coarse), "{name} at {above}");
                    assert!(!row.loaded.admitted_at(above));
                }
                assert_eq!(row.loaded.coarse_rate_hz, coarse);
                assert_eq!(row.loaded.cycles, alone.loaded.cycles);
            }
        }
        // A coarse task that takes the whole share leaves no rate: at this coarse rate its
        // charges alone fill the pipeline's share of every second.
        use twinstack::config::tick_budget::{COARSE_TASK_CYCLES, SYSCLK_HZ, TICK_SHARE_PERCENT};
        let whole = (SYSCLK_HZ / 100 * TICK_SHARE_PERCENT).div_ceil(COARSE_TASK_CYCLES);
        assert_eq!(Prediction::beside_coarse(100, whole).highest_rate_hz, 0.0);
        assert!(Prediction::beside_coarse(100, whole / 2).highest_rate_hz > 0.0);
    }

    #[test]
    fn the_family_is_every_model_with_and_without_creep() {
        let names: Vec<String> = family().into_iter().map(|(n, _)| n).collect();
        assert_eq!(names.len(), 8);
        assert!(names.iter().filter(|n| n.contains("creep")).count() == 4);
    }

    #[test]
    fn admitted_is_within_the_boards_rates_and_the_budget() {
        // The share of the period a 100 kHz board leaves the pipeline (80 % of 1 680 cycles).
        let p = Prediction::beside_coarse(1_344, 0);
        assert!(p.admitted_at(100_000.0) && p.admitted_at(10_000.0));
        assert!(!p.admitted_at(100_001.0) && !p.admitted_at(9_999.0));
        assert!(!Prediction::beside_coarse(1_345, 0).admitted_at(100_000.0));
        let dear = Prediction::beside_coarse(2_688, 0);
        assert!(dear.admitted_at(50_000.0) && !dear.admitted_at(50_001.0));
    }
}
