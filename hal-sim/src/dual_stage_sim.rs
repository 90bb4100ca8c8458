//! `DualStageSim`: the simulated piezo stage riding on the simulated ball-screw stage, run by
//! the library's two controllers exactly as the firmware runs them — the piezo's
//! [`Controller::tick`] every fine period on the emulated converters ([`ExternalBoard`]), the
//! [`DualStage::coarse_tick`] every coarse period on the emulated step/dir output and encoders.
//!
//! Sensors: the piezo's own sensor (ADS8689, ±45 µm, 2 nm rms) measures the piezo against the
//! carriage; a linear encoder (quadrature, 5 nm per count by default) measures the
//! total position `carriage + piezo`; the motor encoder measures the motor angle.
//!
//! Two scenarios give the dual stage's figures: [`five_mm_move`] and [`track_large_trajectory`].

use crate::coarse_stage::{EmulatedEncoder, EmulatedStepDir};
use crate::plant::ball_screw::{BallScrew, BallScrewError, BallScrewParams};
use crate::plant::{Configuration as PlantConfiguration, StageParams};
use crate::sim_board::{BoardConfig, BoardError, ExternalBoard};
use std::f64::consts::PI;
use twinstack::board::{DualDac, Hardware};
use twinstack::config::settings::{FeedbackSettings, Mode, Model, SensorSettings, Settings};
use twinstack::control::drive::{Configuration, DriveSettings, SafeState};
use twinstack::control::{Controller, TickFlags};
use twinstack::dual_stage::{DualMode, DualStage, DualStageError, DualStageSettings, PM_PER_UM};
use twinstack::refusal::Refusal;
use twinstack::{DuhemParams, Scaling};

/// The piezo controller's output range, µm (its Q2.30 ±1).
pub const FINE_RANGE_UM: (f64, f64) = (-40.0, 40.0);

/// Everything a dual-stage simulation is built from.
#[derive(Clone, Debug, PartialEq)]
pub struct DualStageSimConfig {
    /// The piezo stage and its converters.
    pub board: BoardConfig,
    /// The ball-screw stage.
    pub screw: BallScrewParams,
    /// The dual-stage controller.
    pub dual: DualStageSettings,
    /// Integral gain of the piezo's feedback, per second.
    pub fine_ki: f64,
}

impl DualStageSimConfig {
    /// The paper's differential piezo stage (SPI converters) on the precision ball screw, with
    /// [`DualStageSettings::paper_stage`] (its step, encoder and backlash taken from the screw).
    pub fn paper() -> Self {
        let screw = BallScrewParams::precision_stage();
        let mut dual = DualStageSettings::paper_stage();
        dual.step_um = screw.step_um();
        dual.motor_count_um = screw.encoder_count_um();
        dual.backlash_um = screw.backlash_m * 1e6;
        dual.fine_range_um = FINE_RANGE_UM;
        Self {
            board: BoardConfig::paper(PlantConfiguration::Differential),
            screw,
            dual,
            fine_ki: 500.0,
        }
    }
}

/// Why a simulation could not be built.
#[derive(Debug, thiserror::Error)]
pub enum DualStageSimError {
    /// The piezo board.
    #[error("piezo board: {0}")]
    Board(BoardError),
    /// The piezo controller's settings.
    #[error("piezo controller settings: {0}")]
    Settings(Refusal),
    /// The ball screw.
    #[error("{0}")]
    Screw(BallScrewError),
    /// The dual-stage settings.
    #[error("dual-stage settings: {0:?}")]
    Dual(DualStageError),
}

/// One fine period of a run.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    /// Time, s.
    pub t: f64,
    /// Total setpoint, µm.
    pub setpoint_um: f64,
    /// Total position (carriage + piezo), µm.
    pub total_um: f64,
    /// Carriage, µm.
    pub carriage_um: f64,
    /// Piezo against the carriage, µm.
    pub piezo_um: f64,
    /// The piezo's setpoint, µm.
    pub fine_setpoint_um: f64,
    /// The piezo's drive hit its range limit in this tick.
    pub fine_range_limited: bool,
}

impl Sample {
    /// Tracking error (total − setpoint), µm.
    pub fn error_um(&self) -> f64 {
        self.total_um - self.setpoint_um
    }
}

/// The piezo stage on the ball screw, with both controllers and all the emulated peripherals.
pub struct DualStageSim {
    board: ExternalBoard,
    controller: Controller,
    dual: DualStage,
    screw: BallScrew,
    step_dir: EmulatedStepDir,
    motor_encoder: EmulatedEncoder,
    linear_encoder: EmulatedEncoder,
    linear_count_um: f64,
    last_measured: Option<i32>,
    setpoint_pm: i64,
    dt: f64,
    periods: u64,
}

/// The piezo board at `rate`: 150 V amplifiers on the board's DAC, the sensor on the 16-bit
/// ADS8689.
pub(crate) fn piezo_hardware(board: &ExternalBoard, rate: f64) -> Hardware {
    Hardware {
        amplifier_full_scale: 150.0,
        dac_full_scale: DualDac::full_scale(board).0,
        sensor_adc_bits: Some(16),
        control_rate_hz: rate,
    }
}

/// The piezo controller: inverse Duhem (and the Duhem observer) with PI feedback on the piezo
/// sensor (as in `tests/closed_loop.rs`), output range [`FINE_RANGE_UM`].
pub(crate) fn piezo_settings(board: &ExternalBoard, ki: f64) -> Settings {
    let gain = StageParams::paper()
        .second_order(PlantConfiguration::Differential)
        .a0_um_per_volt;
    let sensor = board.sensor();
    let um_at = |volts: f64| (volts - sensor.offset_volts()) / sensor.volts_per_um();
    let model = Model::Duhem(DuhemParams {
        alpha: 0.03,
        beta: gain,
        gamma: 0.75 * gain,
        offset: -70.0 * gain,
    });
    Settings {
        ranges: Scaling {
            input_min: 0.0,
            input_max: 140.0,
            output_min: FINE_RANGE_UM.0,
            output_max: FINE_RANGE_UM.1,
        },
        compensator: Some(model.clone()),
        observer: Some(model),
        drive: DriveSettings {
            configuration: Configuration::Differential,
            bias: 70.0,
            min_voltage: 0.0,
            max_voltage: 140.0,
            slew_rate: 1.0e6,
            safe_state: SafeState::Bias,
        },
        sensor: Some(SensorSettings {
            displacement_at_zero: um_at(-10.24),
            displacement_at_full_scale: um_at(10.24),
            drift_limit: None,
        }),
        feedback: Some(FeedbackSettings::pi(0.0, ki, 1.0)),
        mode: Mode::ClosedLoop,
        creep: None,
        shaping: None,
        preview: None,
        output_map: None,
    }
}

impl DualStageSim {
    /// Everything at rest at total position 0, mode coarse only.
    pub fn new(config: &DualStageSimConfig) -> Result<Self, DualStageSimError> {
        let board = ExternalBoard::external(&config.board).map_err(DualStageSimError::Board)?;
        let dt = config.board.plant.dt;
        let piezo = piezo_settings(&board, config.fine_ki)
            .build(&piezo_hardware(&board, 1.0 / dt))
            .map_err(DualStageSimError::Settings)?;
        let dual_settings = DualStageSettings {
            fine_rate_hz: 1.0 / dt,
            ..config.dual
        };
        let dual_config = dual_settings.build().map_err(DualStageSimError::Dual)?;
        let screw = BallScrew::new(&config.screw, dt).map_err(DualStageSimError::Screw)?;
        let linear_count_um = config.dual.linear_count_um;
        let total = screw.carriage_um() + board.plant().stage_um();
        let mut motor_encoder = EmulatedEncoder::new(1.0, screw.encoder_counts() as f64);
        let mut linear_encoder = EmulatedEncoder::new(linear_count_um, total);
        // What the controller knows: the count, read as the middle of its interval.
        let known = ((total / linear_count_um).floor() + 0.5) * linear_count_um;
        use twinstack::board::QuadratureEncoder;
        let dual = DualStage::new(
            dual_config,
            (known * PM_PER_UM).round() as i64,
            motor_encoder.count(),
            linear_encoder.count(),
        );
        Ok(Self {
            board,
            controller: Controller::new(piezo),
            step_dir: EmulatedStepDir::new(dual_config.fine_ticks, dual_config.max_steps_per_burst),
            setpoint_pm: (known * PM_PER_UM).round() as i64,
            dual,
            screw,
            motor_encoder,
            linear_encoder,
            linear_count_um,
            last_measured: None,
            dt,
            periods: 0,
        })
    }

    /// The dual-stage controller (to move, stream, switch modes).
    pub fn dual(&mut self) -> &mut DualStage {
        &mut self.dual
    }

    /// The ball screw.
    pub fn screw(&self) -> &BallScrew {
        &self.screw
    }

    /// The step/dir output.
    pub fn step_dir(&self) -> &EmulatedStepDir {
        &self.step_dir
    }

    /// The piezo controller.
    pub fn controller(&self) -> &Controller {
        &self.controller
    }

    /// Total position now, µm.
    pub fn total_um(&self) -> f64 {
        self.screw.carriage_um() + self.board.plant().stage_um()
    }

    /// Linear-encoder resolution, µm.
    pub fn linear_count_um(&self) -> f64 {
        self.linear_count_um
    }

    /// Simulated time, s.
    pub fn time(&self) -> f64 {
        self.periods as f64 * self.dt
    }

    /// One coarse period: the coarse tick, then its fine ticks; appends a [`Sample`] per fine
    /// tick to `out`.
    pub fn coarse_period(&mut self, out: &mut Vec<Sample>) {
        let report = self.dual.coarse_tick(
            &mut self.step_dir,
            &mut self.motor_encoder,
            &mut self.linear_encoder,
            self.last_measured,
        );
        let from = self.setpoint_pm;
        let to = report.setpoint_pm;
        self.setpoint_pm = to;
        let n = report.fine.ticks;
        for j in 1..=n {
            let fine = report.fine.at(j);
            let tick = {
                let (mut dac, mut adc) = self.board.split();
                self.controller.tick(Some(fine), &mut adc, &mut dac)
            };
            self.last_measured = Some(tick.measured);
            let microsteps = self.step_dir.advance();
            let carriage = self.screw.step(microsteps);
            let piezo = self.board.plant().stage_um();
            self.motor_encoder
                .move_to(self.screw.encoder_counts() as f64);
            self.linear_encoder.move_to(carriage + piezo);
            self.periods += 1;
            let setpoint = (from as f64 + (to - from) as f64 * j as f64 / n as f64) / PM_PER_UM;
            out.push(Sample {
                t: self.time(),
                setpoint_um: setpoint,
                total_um: carriage + piezo,
                carriage_um: carriage,
                piezo_um: piezo,
                fine_setpoint_um: self.dual.fine_to_pm(fine) as f64 / PM_PER_UM,
                fine_range_limited: tick.flags.contains(TickFlags::RANGE_LIMIT),
            });
        }
    }

    /// Runs coarse periods for `seconds`, calling `before` ahead of each with the dual-stage
    /// controller and the time at the end of the coming period (to move or stream).
    pub fn run(
        &mut self,
        seconds: f64,
        mut before: impl FnMut(&mut DualStage, f64),
        out: &mut Vec<Sample>,
    ) {
        let n = self.dual.config().fine_ticks as f64;
        let periods = (seconds / (self.dt * n)).round().max(0.0) as u64;
        for _ in 0..periods {
            let t_end = self.time() + self.dt * n;
            before(&mut self.dual, t_end);
            self.coarse_period(out);
        }
    }
}

/// Largest change of the tracking error from one fine tick to the next, nm: a jump in the
/// output that the setpoint does not explain.
pub fn largest_jump_nm(samples: &[Sample]) -> f64 {
    largest_jump(samples).0
}

/// [`largest_jump_nm`] and the time it happened, s.
pub fn largest_jump(samples: &[Sample]) -> (f64, f64) {
    samples
        .windows(2)
        .map(|w| ((w[1].error_um() - w[0].error_um()).abs() * 1e3, w[1].t))
        .fold((0.0, 0.0), |a, b| if b.0 > a.0 { b } else { a })
}

/// The 5 mm move's figures.
#[derive(Clone, Debug, PartialEq)]
pub struct MoveResult {
    /// Length of the move, µm.
    pub distance_um: f64,
    /// Duration of the planned move, s.
    pub move_time_s: f64,
    /// Time from the end of the planned move until the error, averaged over 1 ms, stays within
    /// the linear encoder's resolution, s.
    pub settling_time_s: f64,
    /// Whether it did settle (stayed within for at least the last 50 ms of the run).
    pub settled: bool,
    /// Mean error over the last 20 ms, nm.
    pub final_error_nm: f64,
    /// RMS deviation from that mean over the last 20 ms (noise), nm.
    pub final_jitter_nm: f64,
    /// Largest |error| over the last 20 ms, nm.
    pub final_error_max_nm: f64,
    /// The linear encoder's resolution, nm.
    pub resolution_nm: f64,
    /// Largest |piezo − mid-stroke| during the run, µm.
    pub peak_piezo_um: f64,
    /// The piezo's usable window, ± µm.
    pub window_um: f64,
    /// Fine ticks whose drive hit the piezo's range limit.
    pub range_limited_ticks: usize,
    /// Coarse ticks whose residual exceeded the window.
    pub fine_clamps: u32,
    /// Largest per-tick change of the error during the whole run (hand-over included), nm.
    pub largest_jump_nm: f64,
    /// When it happened, s after the move started.
    pub largest_jump_at_s: f64,
    /// Largest tracking error during the move, µm.
    pub max_error_during_move_um: f64,
    /// The samples.
    pub samples: Vec<Sample>,
}

/// Hand-over to dual mode at rest, then a planned move of `distance_um` (trapezoidal profile of
/// the settings), then 0.4 s at the target.
pub fn five_mm_move(
    config: &DualStageSimConfig,
    distance_um: f64,
) -> Result<MoveResult, DualStageSimError> {
    let mut sim = DualStageSim::new(config)?;
    let mut samples = Vec::new();
    sim.dual().set_mode(DualMode::Dual);
    sim.run(0.1, |_, _| {}, &mut samples);
    let start = sim.time();
    let start_um = sim.total_um();
    let target = start_um + distance_um;
    sim.dual().move_to((target * PM_PER_UM).round() as i64);
    let mut done_at = None;
    while done_at.is_none() && sim.time() < start + 60.0 {
        sim.coarse_period(&mut samples);
        if sim.dual().move_done() {
            done_at = Some(sim.time());
        }
    }
    let done_at = done_at.unwrap_or(sim.time());
    let moving_until = samples.len();
    sim.run(0.4, |_, _| {}, &mut samples);

    let resolution_nm = sim.linear_count_um() * 1e3;
    // Settled: the error averaged over 1 ms (the amplifier's and sensors' white noise, which
    // no 5 nm sensor resolves, averaged out) stays within the linear encoder's resolution.
    let per_ms = ((1e-3 / sim.dt).round() as usize).max(1);
    let averaged: Vec<(f64, f64)> = samples
        .windows(per_ms)
        .map(|w| {
            let e = w.iter().map(|s| s.total_um - target).sum::<f64>() / per_ms as f64;
            (w[per_ms - 1].t, e * 1e3)
        })
        .collect();
    let last_outside = averaged
        .iter()
        .rposition(|&(_, e)| e.abs() > resolution_nm)
        .map_or(0.0, |i| averaged[i].0);
    let tail: Vec<f64> = samples
        .iter()
        .rev()
        .take((0.02 / sim.dt) as usize)
        .map(|s| (s.total_um - target) * 1e3)
        .collect();
    let tail_mean = tail.iter().sum::<f64>() / tail.len().max(1) as f64;
    let window_um = config.dual.fine_window_um;
    let centre = config.dual.fine_centre_um;
    Ok(MoveResult {
        distance_um,
        move_time_s: done_at - start,
        settling_time_s: (last_outside - done_at).max(0.0),
        final_error_nm: tail_mean,
        final_jitter_nm: (tail.iter().map(|e| (e - tail_mean).powi(2)).sum::<f64>()
            / tail.len().max(1) as f64)
            .sqrt(),
        final_error_max_nm: tail.iter().fold(0.0, |m: f64, e| m.max(e.abs())),
        settled: last_outside < averaged.last().map_or(0.0, |a| a.0) - 0.05,
        resolution_nm,
        peak_piezo_um: samples
            .iter()
            .fold(0.0, |m: f64, s| m.max((s.piezo_um - centre).abs())),
        window_um,
        range_limited_ticks: samples.iter().filter(|s| s.fine_range_limited).count(),
        fine_clamps: sim.dual().counters().fine_clamps,
        largest_jump_nm: largest_jump(&samples).0,
        largest_jump_at_s: largest_jump(&samples).1 - start,
        max_error_during_move_um: samples[..moving_until]
            .iter()
            .filter(|s| s.t > start)
            .fold(0.0, |m: f64, s| m.max(s.error_um().abs())),
        samples,
    })
}

/// The large trajectory: `amplitude_um · sin(2π·slow_hz·t) + ripple_um · sin(2π·fast_hz·t)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Trajectory {
    /// Slow amplitude, µm.
    pub amplitude_um: f64,
    /// Slow frequency, Hz.
    pub slow_hz: f64,
    /// Fast amplitude, µm.
    pub ripple_um: f64,
    /// Fast frequency, Hz.
    pub fast_hz: f64,
}

impl Trajectory {
    /// 400 µm at 1 Hz (eleven times the piezo's ±37 µm stroke) plus 5 µm at 40 Hz (more
    /// acceleration than the coarse stage's limit).
    pub fn larger_than_the_stroke() -> Self {
        Self {
            amplitude_um: 400.0,
            slow_hz: 1.0,
            ripple_um: 5.0,
            fast_hz: 40.0,
        }
    }

    /// Setpoint at `t`, µm.
    pub fn at(&self, t: f64) -> f64 {
        self.amplitude_um * (2.0 * PI * self.slow_hz * t).sin()
            + self.ripple_um * (2.0 * PI * self.fast_hz * t).sin()
    }
}

/// Tracking figures of one mode.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackingResult {
    /// Largest |error|, µm.
    pub max_um: f64,
    /// RMS error, µm.
    pub rms_um: f64,
    /// Largest |piezo − mid-stroke|, µm.
    pub peak_piezo_um: f64,
    /// Fine ticks whose drive hit the piezo's range limit.
    pub range_limited_ticks: usize,
}

/// Streams `trajectory` for `seconds` in `mode` (after 0.1 s of hand-over at rest) and scores
/// the error after the first `skip_s` seconds of the trajectory.
pub fn track_large_trajectory(
    config: &DualStageSimConfig,
    mode: DualMode,
    trajectory: Trajectory,
    seconds: f64,
    skip_s: f64,
) -> Result<TrackingResult, DualStageSimError> {
    let mut sim = DualStageSim::new(config)?;
    let mut samples = Vec::new();
    sim.dual().set_mode(mode);
    sim.run(0.1, |_, _| {}, &mut samples);
    let start = sim.time();
    let origin = sim.total_um();
    samples.clear();
    sim.run(
        seconds,
        |dual, t_end| {
            dual.follow(((origin + trajectory.at(t_end - start)) * PM_PER_UM).round() as i64)
        },
        &mut samples,
    );
    let scored: Vec<&Sample> = samples.iter().filter(|s| s.t - start >= skip_s).collect();
    let n = scored.len().max(1) as f64;
    let centre = config.dual.fine_centre_um;
    Ok(TrackingResult {
        max_um: scored
            .iter()
            .fold(0.0, |m: f64, s| m.max(s.error_um().abs())),
        rms_um: (scored.iter().map(|s| s.error_um().powi(2)).sum::<f64>() / n).sqrt(),
        peak_piezo_um: samples
            .iter()
            .fold(0.0, |m: f64, s| m.max((s.piezo_um - centre).abs())),
        range_limited_ticks: samples.iter().filter(|s| s.fine_range_limited).count(),
    })
}
