//! The dual-stage board in simulation: [`CoarseRig`] is the coarse axis of a [`SimDevice`] —
//! the library's [`CoarseSupervisor`] (the firmware's coarse task) on the simulated ball screw
//! with its emulated step/dir output, encoders and switches, and fault injection — so that
//! `twinstack coarse … --port sim` and the virtual board drive the same code as the board, over
//! the same command handler.
//!
//! Each control tick the device runs [`CoarseRig::before_tick`] (every `fine_ticks` ticks: the
//! coarse tick, meeting the control loop as the firmware's coarse task does: the handler's
//! command and the piezo's last measurement in, the period's fine setpoints and the status
//! out), then the piezo tick, then [`CoarseRig::after_tick`] (the pulses due in the
//! tick reach the screw; the encoders see the carriage and the total position).

use crate::coarse_stage::{EmulatedEncoder, EmulatedStepDir};
use crate::dual_stage_sim::{piezo_hardware, piezo_settings, DualStageSimConfig};
use crate::plant::ball_screw::BallScrew;
use crate::sim_board::{ExternalBoard, SimBoard};
use crate::sim_device::{CoarseAxisSim, SimDevice, SimDeviceError};
use twinstack::board::{LimitSwitches, QuadratureEncoder, Switches};
use twinstack::control::{Controller, TickFlags, TickReport};
use twinstack::control_loop::ControlLoop;
use twinstack::dual_stage::{
    CoarseLimits, CoarseStatus, CoarseSupervisor, DualStage, DualStageSettings, SupervisorSettings,
    PM_PER_UM,
};

impl CoarseAxisSim for CoarseRig {
    fn limits(&self) -> CoarseLimits {
        CoarseRig::limits(self)
    }
    fn status(&self) -> CoarseStatus {
        CoarseRig::status(self)
    }
    fn before_tick(&mut self, control: &mut ControlLoop<Box<Controller>>) {
        CoarseRig::before_tick(self, control)
    }
    fn after_tick(&mut self, piezo_um: f64, report: &TickReport) {
        CoarseRig::after_tick(self, piezo_um, report)
    }
    fn as_any(&self) -> &dyn std::any::Any {
        self
    }
    fn as_any_mut(&mut self) -> &mut dyn std::any::Any {
        self
    }
}

impl<D: crate::converters::AnalogDualDac, A: crate::converters::AnalogSensorAdc> SimDevice<D, A> {
    /// The coarse axis (dual-stage board).
    pub fn coarse_rig(&self) -> Option<&CoarseRig> {
        self.coarse_axis()?.as_any().downcast_ref()
    }

    /// The coarse axis, to inject faults (dual-stage board).
    pub fn coarse_rig_mut(&mut self) -> Option<&mut CoarseRig> {
        self.coarse_axis_mut()?.as_any_mut().downcast_mut()
    }
}

/// The external converters' device: what [`SimDevice::dual_stage`] builds.
pub type DualStageDevice = SimDevice<
    twinstack::converters::Dac856x<crate::converters::EmulatedDac856x>,
    twinstack::converters::Ads8689<crate::converters::EmulatedAds8689>,
>;

/// Where the switches are, carriage µm from its power-up position.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SwitchPositions {
    /// The lower limit switch is active at or below this.
    pub lower_um: f64,
    /// The home switch is active at or below this.
    pub home_um: f64,
    /// The upper limit switch is active at or above this.
    pub upper_um: f64,
}

impl SwitchPositions {
    /// Home 1 mm below the power-up position, the limits 2 mm below and 49 mm above (with
    /// [`SupervisorSettings::paper_stage`]'s home at −24 mm, the ±25 mm travel lies inside).
    pub fn paper() -> Self {
        Self {
            lower_um: -2_000.0,
            home_um: -1_000.0,
            upper_um: 49_000.0,
        }
    }
}

/// Faults the rig can inject.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct InjectedFaults {
    /// The motor stalls: the driver's pulses no longer turn it.
    pub stall: bool,
    /// The linear encoder's signal is lost: its counter stops.
    pub linear_lost: bool,
    /// The upper limit switch reads active.
    pub upper_limit: bool,
    /// The lower limit switch reads active.
    pub lower_limit: bool,
}

/// Switch readings for one coarse tick.
struct Read(Switches);

impl LimitSwitches for Read {
    fn read(&mut self) -> Switches {
        self.0
    }
}

/// The simulated coarse axis (see the module doc).
pub struct CoarseRig {
    supervisor: CoarseSupervisor,
    screw: BallScrew,
    step_dir: EmulatedStepDir,
    motor: EmulatedEncoder,
    linear: EmulatedEncoder,
    switches: SwitchPositions,
    faults: InjectedFaults,
    /// Microstep position the stalled motor holds.
    stalled_at: Option<i64>,
    fine_ticks: u32,
    phase: u32,
    piezo_um: f64,
    /// Largest |piezo| since [`CoarseRig::reset_stats`], µm.
    peak_piezo_um: f64,
    /// Ticks whose drive hit the range limit since the reset.
    range_limited: u64,
    /// Largest change of either DAC code from one tick to the next since the reset.
    largest_dac_step: u16,
    last_codes: Option<(u16, u16)>,
}

impl CoarseRig {
    /// The rig at rest at carriage 0 around `dual` settings (their fine rate the control
    /// rate) and `supervisor` settings, the piezo at `piezo_um` (the board's plant).
    pub fn new(
        config: &DualStageSimConfig,
        supervisor: &SupervisorSettings,
        switches: SwitchPositions,
        piezo_um: f64,
    ) -> Result<Self, SimDeviceError> {
        let dt = config.board.plant.dt;
        let dual_settings = DualStageSettings {
            fine_rate_hz: (1.0 / dt).round(),
            ..config.dual
        };
        let bad = |what: &str| SimDeviceError::Coarse(what.to_string());
        let dual_config = dual_settings
            .build()
            .map_err(|e| bad(&format!("dual-stage settings: {}", e.as_str())))?;
        let screw = BallScrew::new(&config.screw, dt).map_err(|e| bad(&e.to_string()))?;
        let linear_count_um = dual_settings.linear_count_um;
        let total = screw.carriage_um() + piezo_um;
        let mut motor = EmulatedEncoder::new(1.0, screw.encoder_counts() as f64);
        let mut linear = EmulatedEncoder::new(linear_count_um, total);
        let known = ((total / linear_count_um).floor() + 0.5) * linear_count_um;
        let dual = DualStage::new(
            dual_config,
            (known * PM_PER_UM).round() as i64,
            motor.count(),
            linear.count(),
        );
        let supervisor_config = supervisor
            .build(dual.config(), dual_settings.coarse_rate_hz)
            .map_err(|e| bad(&format!("supervisor settings: {}", e.as_str())))?;
        Ok(Self {
            supervisor: CoarseSupervisor::new(dual, supervisor_config),
            screw,
            step_dir: EmulatedStepDir::new(dual_config.fine_ticks, dual_config.max_steps_per_burst),
            motor,
            linear,
            switches,
            faults: InjectedFaults::default(),
            stalled_at: None,
            fine_ticks: dual_config.fine_ticks,
            phase: 0,
            piezo_um,
            peak_piezo_um: 0.0,
            range_limited: 0,
            largest_dac_step: 0,
            last_codes: None,
        })
    }

    /// The limits the handler validates against.
    pub fn limits(&self) -> CoarseLimits {
        self.supervisor.limits()
    }

    /// The supervisor's status.
    pub fn status(&self) -> CoarseStatus {
        self.supervisor.status()
    }

    /// The supervisor.
    pub fn supervisor(&self) -> &CoarseSupervisor {
        &self.supervisor
    }

    /// The ball screw.
    pub fn screw(&self) -> &BallScrew {
        &self.screw
    }

    /// Total position now (carriage + piezo), µm, in the simulation's frame (the board's
    /// frame is this plus the home offset: [`CoarseRig::offset_um`]).
    pub fn total_um(&self) -> f64 {
        self.screw.carriage_um() + self.piezo_um
    }

    /// The board's position − the simulation's, µm (fixed by homing; 0 before).
    pub fn offset_um(&self) -> f64 {
        let s = self.supervisor.status();
        let raw = self.supervisor.dual().setpoint_pm();
        (s.setpoint_pm - raw) as f64 / PM_PER_UM
    }

    /// The piezo, µm.
    pub fn piezo_um(&self) -> f64 {
        self.piezo_um
    }

    /// Injects (or clears) faults.
    pub fn inject(&mut self, faults: InjectedFaults) {
        self.faults = faults;
        if !faults.stall {
            self.stalled_at = None;
        }
    }

    /// Restarts the statistics (peak piezo, range-limit ticks, largest DAC step).
    pub fn reset_stats(&mut self) {
        self.peak_piezo_um = 0.0;
        self.range_limited = 0;
        self.largest_dac_step = 0;
    }

    /// Largest |piezo| since the reset, µm.
    pub fn peak_piezo_um(&self) -> f64 {
        self.peak_piezo_um
    }

    /// Ticks whose drive hit the piezo's range limit since the reset.
    pub fn range_limited_ticks(&self) -> u64 {
        self.range_limited
    }

    /// Largest change of a DAC code from one tick to the next since the reset (LSB).
    pub fn largest_dac_step(&self) -> u16 {
        self.largest_dac_step
    }

    /// Pulses the step output has emitted.
    pub fn pulses(&self) -> u64 {
        self.step_dir.pulses()
    }

    /// Before a control tick: every `fine_ticks` ticks, the coarse tick and the exchange.
    pub fn before_tick(&mut self, control: &mut ControlLoop<Box<Controller>>) {
        if self.phase == 0 {
            let carriage = self.screw.carriage_um();
            let at = |um: f64| carriage <= um;
            let mut switches = Read(Switches {
                lower: at(self.switches.lower_um) || self.faults.lower_limit,
                upper: carriage >= self.switches.upper_um || self.faults.upper_limit,
                home: at(self.switches.home_um),
            });
            self.supervisor.period(
                (
                    &mut self.step_dir,
                    &mut self.motor,
                    &mut self.linear,
                    &mut switches,
                ),
                control,
                true,
            );
        }
        self.phase = (self.phase + 1) % self.fine_ticks.max(1);
    }

    /// After a control tick (`piezo_um`: the piezo's displacement now, `report`: the tick's):
    /// the pulses due reach the screw, the encoders follow.
    pub fn after_tick(&mut self, piezo_um: f64, report: &TickReport) {
        let microsteps = self.step_dir.advance();
        let input = if self.faults.stall {
            *self
                .stalled_at
                .get_or_insert(self.screw.commanded_microsteps())
        } else {
            microsteps
        };
        let carriage = self.screw.step(input);
        self.piezo_um = piezo_um;
        self.motor.move_to(self.screw.encoder_counts() as f64);
        if !self.faults.linear_lost {
            self.linear.move_to(carriage + piezo_um);
        }
        self.peak_piezo_um = self.peak_piezo_um.max(piezo_um.abs());
        if report.flags.contains(TickFlags::RANGE_LIMIT) {
            self.range_limited += 1;
        }
        let codes = (report.left.0, report.right.0);
        if let Some((l, r)) = self.last_codes {
            let step = l.abs_diff(codes.0).max(r.abs_diff(codes.1));
            self.largest_dac_step = self.largest_dac_step.max(step);
        }
        self.last_codes = Some(codes);
    }
}

/// Everything the dual-stage board is built from.
#[derive(Clone, Debug, PartialEq)]
pub struct DualStageDeviceConfig {
    /// The piezo board, the screw and the dual-stage controller.
    pub sim: DualStageSimConfig,
    /// The supervisor.
    pub supervisor: SupervisorSettings,
    /// Where the switches are.
    pub switches: SwitchPositions,
    /// UART baud rate.
    pub baud: u32,
    /// The USB–serial adapter's delay each way.
    pub link: crate::sim_device::LinkDelay,
}

impl DualStageDeviceConfig {
    /// The paper's stage ([`DualStageSimConfig::paper`]), the supervisor's and the switches'
    /// defaults, 3 Mbaud, an ideal link.
    pub fn paper() -> Self {
        Self {
            sim: DualStageSimConfig::paper(),
            supervisor: SupervisorSettings::paper_stage(),
            switches: SwitchPositions::paper(),
            baud: twinstack::protocol::LINK_BAUD,
            link: crate::sim_device::LinkDelay::IDEAL,
        }
    }
}

impl DualStageDevice {
    /// The dual-stage board: the piezo stage on the external converters with its closed-loop
    /// settings stored (inverse Duhem + PI on its sensor, range ±40 µm), carried by the ball
    /// screw whose coarse axis the supervisor runs ([`CoarseRig`]), unhomed at power-up.
    ///
    /// ```
    /// use hal_sim::coarse_rig::{DualStageDevice, DualStageDeviceConfig};
    /// let dev = DualStageDevice::dual_stage(&DualStageDeviceConfig::paper()).unwrap();
    /// assert!(!dev.coarse_rig().unwrap().status().homed);
    /// ```
    pub fn dual_stage(config: &DualStageDeviceConfig) -> Result<Self, SimDeviceError> {
        let board: ExternalBoard =
            SimBoard::external(&config.sim.board).map_err(SimDeviceError::Board)?;
        let rate = (1.0 / config.sim.board.plant.dt).round();
        let hw = piezo_hardware(&board, rate);
        let settings = piezo_settings(&board, config.sim.fine_ki);
        let rig = CoarseRig::new(
            &config.sim,
            &config.supervisor,
            config.switches,
            board.plant().stage_um(),
        )?;
        SimDevice::build(
            board,
            hw,
            Some((settings, None)),
            config.baud,
            config.link,
            Some(Box::new(rig) as Box<dyn CoarseAxisSim>),
        )
    }
}
