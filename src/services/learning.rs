//! Learning feedforward for periodic motion: iterative learning control (ILC) of a
//! phase-indexed correction table, played on top of the inverse-model feedforward.
//!
//! Scans repeat. Over the first periods the board learns, from the sensor, the drive
//! correction that cancels what the inverse model gets wrong (and the stage's own dynamics),
//! bin by bin of the period; then it can **freeze** the table and play it without updating,
//! with the sensor disconnected if need be.
//!
//! # Two halves
//!
//! * [`LearnTick`], owned by the control tick ([`crate::control_loop::ControlLoop`]): per tick
//!   it reads **one** entry of the active table (the correction, Q2.30 normalised drive, added
//!   to the feedforward before the range and slew limits: the table's output is limited like
//!   everything else) and stores **one** error (the target of the reading's instant minus
//!   the reading, Q2.30: the end of the hold of [`SENSOR_DELAY_TICKS`] ticks ago, between the
//!   targets of two ticks, as the feedback takes it: [`crate::control::instant`]) in the error
//!   buffer being filled. Constant time, no division, no loop. At the period's end it flips
//!   the error buffers and, if the task has posted a new table, flips the tables: a table
//!   always plays whole periods.
//! * [`LearnTask`], owned by the low-priority task (the command handler's context): at each
//!   period boundary [`service`] copies the completed period's errors out in short locked
//!   chunks, runs the ILC law below **off the tick**, writes the new table into the tick's
//!   inactive table in chunks and posts it (an O(1) flag; the tick swaps at the next boundary).
//!
//! # The law
//!
//! With `u_j` the table played in period `j`, `e_j` its error and `P` the period in ticks:
//!
//! ```text
//! u_{j+1}(n) = Q[ u_j(n) + L · e_j(n + d + λ) ]      n = 0 … P−1 (indices modulo P)
//! ```
//!
//! * `L` the learning gain (Q2.30);
//! * `λ` the phase lead in ticks, cancelling the drive-to-displacement delay beyond the
//!   sensor's own `d` ticks (DAC hold, amplifier, mechanics);
//! * `Q` the robustness filter ([`RobustnessFilter`]): a second-order Butterworth low pass
//!   run forward and then backward over the period (zero phase, `Q = 1 / (1 + (f/f_c)⁴)`),
//!   circular (the period's end continues into its start), so that noise and what the
//!   learning cannot follow (the resonance) do not build up from period to period, while in
//!   the pass band it leaves only `≈ (f/f_c)⁴ / (L·G)` of the error;
//! * the result limited to ±`limit` (saturating).
//!
//! The new table plays from the boundary after the one that completed `e_j` (the task needs
//! the period to compute it), so the update uses the error of the table before the one in
//! force: `u_{j+2} = Q[u_{j+1} + L e_j]`. For a plant gain `G` that converges when `L·G < 1`
//! (roots of `z² − z + L·G`), fastest at `L·G = 1/4` (a double root at 1/2 per period).
//!
//! # Formats
//!
//! Table, errors, limit: Q2.30 normalised (drive for the table, displacement for errors).
//! Gain `L`: Q2.30 (0 < L ≤ 1.5). Filter coefficients: Q2.30; its state: Q2.46 in an `i64`;
//! its products in `i128` (off the tick).

use crate::control::feedback::SENSOR_DELAY_TICKS;
use crate::control::instant::ReadingInstant;
use crate::fixed_point::{limit, saturate_i64, signal_from_f64};
use crate::refusal::{finite, Field, Refusal, Rule};
use serde::{Deserialize, Serialize};

/// Most bins (ticks) of a learning period: 512 (≥ 97.7 Hz at 50 kHz, ≥ 195.3 Hz at
/// 100 kHz, for one cycle; one bin per tick). Fixed at compile time: the tables take
/// `4 × MAX_BINS × 4` bytes on the tick's side and `2 × MAX_BINS × 4` on the task's (12 KiB
/// in all; with 1 024 bins the emulator image stopped answering: its 128 KiB of SRAM left
/// too little stack).
pub const MAX_BINS: usize = 512;

/// Words one locked copy moves between the task and the tick: a short critical section
/// (about 70 instructions; 64 words held a falling-due tick off for 265).
pub const CHUNK: usize = 16;

/// Largest learning gain.
pub const MAX_GAIN: f64 = 1.5;

/// Largest phase lead, ticks.
pub const MAX_LEAD: u16 = 64;

/// What the learning does.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum LearnState {
    /// No correction, no learning (the table is kept).
    #[default]
    Off,
    /// The table plays and is updated each period from the sensor's error.
    Learning,
    /// The table plays without updating (the sensor is not needed).
    Frozen,
}

/// The learning's parameters in physical terms (validated by [`LearnSettings::build`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LearnSettings {
    /// The motion's period in ticks (a whole number of the waveform's cycles: 200 for a
    /// 750 Hz sine at 50 kHz, which is 3 cycles), 2 … [`MAX_BINS`].
    pub period_ticks: u16,
    /// Learning gain `L` (normalised drive per normalised error), 0 < L ≤ [`MAX_GAIN`].
    pub gain: f64,
    /// Corner of the robustness filter, Hz, 0 < f_c < control rate / 2.
    pub cutoff_hz: f64,
    /// Phase lead, ticks, 0 … [`MAX_LEAD`] (and below the period).
    pub lead_ticks: u16,
    /// Largest correction, fraction of the drive range, (0, 1].
    pub limit: f64,
}

impl LearnSettings {
    /// The defaults for a period of `period_ticks`: gain 0.3, cutoff 3 kHz, lead 1 tick,
    /// correction within a quarter of the drive range.
    pub fn for_period(period_ticks: u16) -> Self {
        Self {
            period_ticks,
            gain: 0.3,
            cutoff_hz: 3000.0,
            lead_ticks: 1,
            limit: 0.25,
        }
    }

    /// Validates at `control_rate` (Hz) and builds the fixed-point configuration.
    ///
    /// ```
    /// use twinstack::services::learning::LearnSettings;
    /// let c = LearnSettings::for_period(200).build(50_000.0).unwrap();
    /// assert_eq!(c.period(), 200);
    /// let mut s = LearnSettings::for_period(200);
    /// s.cutoff_hz = 30_000.0; // above Nyquist
    /// assert_eq!(s.build(50_000.0).unwrap_err().to_string(),
    ///            "learning.cutoff_hz must be below 25000");
    /// ```
    pub fn build(&self, control_rate: f64) -> Result<LearnConfig, Refusal> {
        finite(Field::LearnGain, self.gain)?;
        finite(Field::LearnCutoff, self.cutoff_hz)?;
        finite(Field::LearnLimit, self.limit)?;
        let p = self.period_ticks;
        if p < 2 {
            return Err(Refusal::new(Field::LearnPeriod, Rule::AtLeast(2.0)));
        }
        if p as usize > MAX_BINS {
            return Err(Refusal::new(
                Field::LearnPeriod,
                Rule::AtMost(MAX_BINS as f64),
            ));
        }
        if self.gain <= 0.0 {
            return Err(Refusal::new(Field::LearnGain, Rule::Above(0.0)));
        }
        if self.gain > MAX_GAIN {
            return Err(Refusal::new(Field::LearnGain, Rule::AtMost(MAX_GAIN)));
        }
        if self.cutoff_hz <= 0.0 {
            return Err(Refusal::new(Field::LearnCutoff, Rule::Above(0.0)));
        }
        if control_rate.is_nan() || control_rate <= 0.0 || self.cutoff_hz >= control_rate / 2.0 {
            return Err(Refusal::new(
                Field::LearnCutoff,
                Rule::Below(control_rate / 2.0),
            ));
        }
        let lead_max = MAX_LEAD.min(p - 1);
        if self.lead_ticks > lead_max {
            return Err(Refusal::new(
                Field::LearnLead,
                Rule::AtMost(lead_max as f64),
            ));
        }
        if self.limit <= 0.0 {
            return Err(Refusal::new(Field::LearnLimit, Rule::Above(0.0)));
        }
        if self.limit > 1.0 {
            return Err(Refusal::new(Field::LearnLimit, Rule::AtMost(1.0)));
        }
        Ok(LearnConfig {
            period: p,
            gain: signal_from_f64(self.gain),
            filter: RobustnessFilter::new(self.cutoff_hz, control_rate, p as usize),
            lead: self.lead_ticks,
            limit: signal_from_f64(2.0 * self.limit),
        })
    }
}

/// The learning's configuration in fixed point (from [`LearnSettings::build`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LearnConfig {
    /// Period, ticks (2 … [`MAX_BINS`]).
    period: u16,
    /// Learning gain, Q2.30.
    gain: i32,
    /// The robustness filter.
    filter: RobustnessFilter,
    /// Phase lead, ticks.
    lead: u16,
    /// Largest correction, Q2.30 normalised drive.
    limit: i32,
}

impl LearnConfig {
    /// Period, ticks.
    pub fn period(&self) -> usize {
        self.period as usize
    }
}

/// The tick's half: the tables it plays, the errors it stores (see the module doc).
///
/// `repr(C)`, the small fields first and the tables last, so that the tick reaches the
/// former with one-instruction offsets.
#[derive(Clone, Debug)]
#[repr(C)]
pub struct LearnTick {
    state: LearnState,
    /// The task has written `tables[1 − active]`: swap at the next boundary.
    posted: bool,
    /// Period, ticks (1 … [`MAX_BINS`]).
    period: usize,
    /// This tick's bin, `0 … period − 1`.
    bin: usize,
    active: usize,
    fill: usize,
    /// The last targets, and from them the target of the present reading's instant (the
    /// sensor is `SENSOR_DELAY_TICKS` late: [`crate::control::instant`]).
    targets: ReadingInstant,
    /// Periods completed (wrapping): the task's cue.
    periods: u32,
    /// Ticks whose error could not be measured (ADC error or no sensor) while storing.
    missing: u32,
    /// [`LearnTick::periods`] at the last restart of the period (a motion started, or the
    /// period set): the task's cue that the errors before are another motion's.
    restarted_at: u32,
    /// The two tables, Q2.30 normalised drive: `tables[active]` plays.
    tables: [[i32; MAX_BINS]; 2],
    /// The two error buffers, Q2.30: the tick fills `errors[fill]`.
    errors: [[i32; MAX_BINS]; 2],
}

impl Default for LearnTick {
    fn default() -> Self {
        Self::new()
    }
}

impl LearnTick {
    /// Off, empty tables, period [`MAX_BINS`].
    ///
    /// ```
    /// use twinstack::services::learning::{LearnState, LearnTick};
    /// let t = LearnTick::new();
    /// assert_eq!(t.state(), LearnState::Off);
    /// assert_eq!(t.correction(), 0);
    /// ```
    pub const fn new() -> Self {
        Self {
            state: LearnState::Off,
            period: MAX_BINS,
            bin: 0,
            tables: [[0; MAX_BINS]; 2],
            active: 0,
            posted: false,
            errors: [[0; MAX_BINS]; 2],
            fill: 0,
            targets: ReadingInstant::at(0),
            periods: 0,
            missing: 0,
            restarted_at: 0,
        }
    }

    /// This tick's correction, Q2.30 normalised drive (0 when off): one read.
    #[inline(always)]
    pub fn correction(&self) -> i32 {
        if self.state == LearnState::Off {
            return 0;
        }
        self.tables
            .get(self.active)
            .and_then(|t| t.get(self.bin))
            .copied()
            .unwrap_or(0)
    }

    /// After the tick: stores this tick's error (the target of the reading's instant, the end
    /// of the hold of [`SENSOR_DELAY_TICKS`] ticks ago, minus `measured`, Q2.30; `None`: no
    /// reading, stored as 0, which leaves that bin as it is) and advances one bin; at the
    /// period's end flips the error buffers and, if a table was posted, the tables. Returns
    /// whether a period ended. Constant time.
    #[inline(always)]
    pub fn observe(&mut self, target: i32, measured: Option<i32>) -> bool {
        if self.state == LearnState::Off {
            return false;
        }
        // The target of the reading's instant, as the feedback takes it.
        let reference = self.targets.push(target);
        let error = match measured {
            Some(m) => reference.saturating_sub(m),
            None => {
                self.missing = self.missing.wrapping_add(1);
                0
            }
        };
        if let Some(slot) = self
            .errors
            .get_mut(self.fill)
            .and_then(|e| e.get_mut(self.bin))
        {
            *slot = error;
        }
        self.bin += 1;
        if self.bin < self.period {
            return false;
        }
        self.bin = 0;
        self.fill ^= 1;
        self.periods = self.periods.wrapping_add(1);
        if self.posted {
            self.active ^= 1;
            self.posted = false;
        }
        true
    }

    /// Whether the table plays (learning or frozen).
    #[inline(always)]
    pub fn is_on(&self) -> bool {
        self.state != LearnState::Off
    }

    /// The state.
    pub fn state(&self) -> LearnState {
        self.state
    }

    /// Sets the state (O(1)). Turning it on restarts the target history at `target` (the
    /// setpoint in force).
    pub fn set_state(&mut self, state: LearnState, target: i32) {
        if self.state == LearnState::Off && state != LearnState::Off {
            self.targets = ReadingInstant::at(target);
        }
        self.state = state;
    }

    /// Sets the period (1 … [`MAX_BINS`] ticks; clamped) and restarts at bin 0
    /// ([`LearnTick::restart`]).
    pub fn set_period(&mut self, period: usize) {
        self.period = period.clamp(1, MAX_BINS);
        self.restart();
    }

    /// Restarts the period at bin 0 (the motion starts: a waveform, a stream or a scan, now or
    /// on the trigger input's edge), so that a
    /// table is aligned with the motion's start and plays again on the same motion started
    /// again. The error buffer being filled is abandoned (its period is not counted), and the
    /// task's divergence guard starts again from the next period ([`LearnTick::restarted_at`]):
    /// the errors before were another motion's (a stage at rest before the waveform), so a
    /// period completed before the restart that the task has not taken yet is dropped (its
    /// [`LearnTick::periods`] still equals [`LearnTick::restarted_at`]). O(1): two stores,
    /// for it runs under the tick's lock.
    pub fn restart(&mut self) {
        self.bin = 0;
        self.restarted_at = self.periods;
    }

    /// [`LearnTick::periods`] at the last restart: it moves when a motion starts after a
    /// period has completed. Two restarts with no period completed between them leave it
    /// where it was, and the task has taken no period between them to forget. (After 2³²
    /// periods without a restart the count comes round to it again: the task then passes
    /// over one period, and a restart exactly there is not seen.)
    pub fn restarted_at(&self) -> u32 {
        self.restarted_at
    }

    /// Period, ticks.
    pub fn period(&self) -> usize {
        self.period
    }

    /// This tick's bin.
    pub fn bin(&self) -> usize {
        self.bin
    }

    /// Periods completed since start-up (wrapping).
    pub fn periods(&self) -> u32 {
        self.periods
    }

    /// Ticks without a reading while storing errors.
    pub fn missing(&self) -> u32 {
        self.missing
    }

    /// The table playing now.
    pub fn table(&self) -> &[i32; MAX_BINS] {
        &self.tables[self.active & 1]
    }

    /// Copies `out.len()` errors of the last **completed** period from bin `offset` (for the
    /// task, in short locked chunks). Returns the count copied.
    pub fn copy_errors(&self, offset: usize, out: &mut [i32]) -> usize {
        let done = &self.errors[(self.fill ^ 1) & 1];
        let from = done.get(offset..).unwrap_or(&[]);
        let n = out.len().min(from.len());
        out[..n].copy_from_slice(&from[..n]);
        n
    }

    /// Writes `values` into the inactive table from bin `offset` (for the task, in short locked
    /// chunks; the tick does not read it). Returns the count written.
    pub fn write_spare(&mut self, offset: usize, values: &[i32]) -> usize {
        let spare = &mut self.tables[(self.active ^ 1) & 1];
        let to = spare.get_mut(offset..).unwrap_or(&mut []);
        let n = values.len().min(to.len());
        to[..n].copy_from_slice(&values[..n]);
        n
    }

    /// Posts the inactive table: it plays from the next period boundary (at once when off,
    /// when no boundary comes). O(1).
    pub fn post(&mut self) {
        if self.state == LearnState::Off {
            self.active ^= 1;
            self.posted = false;
        } else {
            self.posted = true;
        }
    }

    /// Whether a posted table waits for the boundary.
    pub fn is_posted(&self) -> bool {
        self.posted
    }
}

/// One period's error, as the task saw it (Q2.30 normalised displacement).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct PeriodError {
    /// Largest |error|.
    pub max: i32,
    /// Root mean square.
    pub rms: i32,
}

/// The task's half: the table being learned and the ILC law (see the module doc).
#[derive(Clone, Debug)]
pub struct LearnTask {
    config: Option<LearnConfig>,
    /// The table, Q2.30: the last one posted.
    table: [i32; MAX_BINS],
    /// Working buffer: the completed period's errors, then the update before filtering.
    work: [i32; MAX_BINS],
    /// The tick's period count at the last period taken.
    seen: u32,
    /// The tick's [`LearnTick::restarted_at`] the guard last started from.
    restart_seen: u32,
    /// Periods learned from (updates posted).
    updates: u32,
    /// Periods missed (the tick completed another before the copy ended).
    missed: u32,
    last: PeriodError,
    /// The lowest period RMS since the learning last started (`i32::MAX`: none yet), for the
    /// divergence guard.
    best: i32,
    /// The first period's RMS since the learning last started: what the stage did before the
    /// learning had acted, the level the guard's stop returns it to.
    start: i32,
    /// The guard's allowance over twice the best, Q2.30: [`DIVERGENCE_FLOOR`] or the
    /// sensor's resolution ([`LearnTask::set_resolution`]), whichever is larger.
    floor: i32,
    /// Whether the last period tripped the divergence guard.
    diverged: bool,
    /// Times the divergence guard stopped the learning.
    stops: u32,
}

/// The divergence guard: the learning is switched off (the feedforward alone plays; the
/// table is kept, as [`LearnState::Off`] keeps it) when a period's RMS error exceeds this many
/// times the lowest since it started, plus [`DIVERGENCE_FLOOR`], **and** the first period's
/// since it started (the error before the learning had acted).
///
/// A learning that converges brings its error down period after period, to the sensor's
/// noise; one that diverges (a robustness filter too wide for the stage: a resonance moved, a
/// shaping notch off the resonance, a gain too high) grows it geometrically, and the ringing
/// it has excited keeps growing for a few periods whatever table plays next (freezing the
/// table measured 5× the best error on the simulated stage). Off, the stage is back to the
/// feedforward alone: never worse than without learning. A learning still below its first
/// period's error is not stopped however far it has risen from its best: off would take the
/// stage back to that first error, worse than it is (a stage held at rest in open loop, its
/// static error learned down to the sensor's noise, creeps back up to several times that:
/// far over twice the best, far below where it started). A motion started (a waveform or a
/// stream: [`LearnTick::restart`]) starts the guard again, so a learning switched on over a
/// stage at rest is not stopped when the motion begins; a motion changed within a running
/// source (the stream's setpoints) trips it: configure the learning again (or recall a
/// table) to relearn.
pub const DIVERGENCE_FACTOR: i32 = 2;

/// The guard's least allowance over [`DIVERGENCE_FACTOR`] × the best, Q2.30 normalised
/// displacement (2⁻¹⁶ of full scale); a coarser sensor's resolution raises it to one ADC
/// code ([`LearnTask::set_resolution`]): a period's RMS error at the resolution takes a few
/// values (most errors 0, some one code) that differ by more than twice from period to
/// period, and an error within one code in every bin has an RMS within it.
pub const DIVERGENCE_FLOOR: i32 = 1 << 14;

impl Default for LearnTask {
    fn default() -> Self {
        Self::new()
    }
}

impl LearnTask {
    /// No configuration, empty table.
    ///
    /// ```
    /// use twinstack::services::learning::LearnTask;
    /// let t = LearnTask::new();
    /// assert!(t.table().iter().all(|&u| u == 0));
    /// ```
    pub const fn new() -> Self {
        Self {
            config: None,
            table: [0; MAX_BINS],
            work: [0; MAX_BINS],
            seen: 0,
            restart_seen: 0,
            updates: 0,
            missed: 0,
            last: PeriodError { max: 0, rms: 0 },
            best: i32::MAX,
            start: i32::MAX,
            floor: DIVERGENCE_FLOOR,
            diverged: false,
            stops: 0,
        }
    }

    /// Sets the configuration (the tick's period is set separately, see [`configure`]).
    pub fn set_config(&mut self, config: LearnConfig) {
        self.config = Some(config);
    }

    /// The configuration, if one was set.
    pub fn config(&self) -> Option<&LearnConfig> {
        self.config.as_ref()
    }

    /// The table (Q2.30 normalised drive), [`MAX_BINS`] entries of which the period's are used.
    pub fn table(&self) -> &[i32; MAX_BINS] {
        &self.table
    }

    /// Replaces the table (a recalled one; entries beyond `values` are zeroed, each limited
    /// to the configured limit when there is one). Post it with [`post_table`].
    pub fn set_table(&mut self, values: &[i32]) {
        let lim = self.config.map(|c| c.limit).unwrap_or(i32::MAX);
        for (i, u) in self.table.iter_mut().enumerate() {
            *u = limit(values.get(i).copied().unwrap_or(0), -lim, lim);
        }
    }

    /// Writes `values` into the table from bin `offset` (each limited to the configured limit
    /// when there is one); what does not fit is dropped. Returns the count written.
    pub fn write_entries(&mut self, offset: usize, values: &[i32]) -> usize {
        let lim = self.config.map(|c| c.limit).unwrap_or(i32::MAX);
        let to = self.table.get_mut(offset..).unwrap_or(&mut []);
        let n = values.len().min(to.len());
        for (u, &v) in to.iter_mut().zip(&values[..n]) {
            *u = limit(v, -lim, lim);
        }
        n
    }

    /// Whether the last [`LearnTask::update`] tripped the divergence guard.
    pub fn diverged(&self) -> bool {
        self.diverged
    }

    /// Updates posted.
    pub fn updates(&self) -> u32 {
        self.updates
    }

    /// Periods the task could not copy in time.
    pub fn missed(&self) -> u32 {
        self.missed
    }

    /// The last period's error.
    pub fn last_error(&self) -> PeriodError {
        self.last
    }

    /// Times the divergence guard stopped the learning ([`DIVERGENCE_FACTOR`]).
    pub fn guard_stops(&self) -> u32 {
        self.stops
    }

    /// Sets the sensor's resolution (one ADC code, Q2.30 normalised displacement:
    /// [`crate::control::sensor::Sensor::quantum`]; `None`: no sensor): the divergence
    /// guard's allowance is at least that ([`DIVERGENCE_FLOOR`]).
    pub fn set_resolution(&mut self, quantum: Option<i32>) {
        self.floor = quantum.unwrap_or(0).max(DIVERGENCE_FLOOR);
    }

    /// Forgets the best period (the learning starts again: the guard measures from there).
    pub fn restart_guard(&mut self) {
        self.best = i32::MAX;
        self.start = i32::MAX;
    }

    /// Takes the error of a completed period (in `errors`, `period` bins: its max and RMS
    /// become [`LearnTask::last_error`]) and, when `learn`, computes the next table by the ILC
    /// law — unless the period's RMS trips the divergence guard ([`DIVERGENCE_FACTOR`]): then
    /// the table is left as it is and [`LearnTask::diverged`] says so. Off the tick:
    /// `O(period)`, one 64-bit division for the RMS and two for the circular filter's start.
    pub fn update(&mut self, period: usize, learn: bool) {
        self.diverged = false;
        let p = period.min(MAX_BINS);
        let Some(c) = self.config else {
            return;
        };
        let e = &mut self.work[..p];
        let (mut max, mut sq) = (0i32, 0u128);
        for &x in e.iter() {
            max = max.max(x.saturating_abs());
            sq += (x as i128 * x as i128) as u128;
        }
        let mean = if p > 0 { sq / p as u128 } else { 0 };
        self.last = PeriodError {
            max,
            rms: isqrt(mean).min(i32::MAX as u128) as i32,
        };
        if !learn || p < 2 {
            return;
        }
        let rms = self.last.rms;
        if self.start == i32::MAX {
            self.start = rms;
        }
        let grown = self
            .best
            .saturating_mul(DIVERGENCE_FACTOR)
            .saturating_add(self.floor);
        if rms < self.best {
            self.best = rms;
        } else if rms > grown && rms > self.start {
            self.diverged = true;
            self.stops = self.stops.wrapping_add(1);
            self.restart_guard();
            return;
        }
        // e(n + d + λ) onto bin n.
        let shift = (SENSOR_DELAY_TICKS + c.lead as usize) % p;
        e.rotate_left(shift);
        // u + L·e, saturating (Q2.30 × Q2.30 >> 30).
        for (v, &u) in e.iter_mut().zip(self.table.iter()) {
            let le = saturate_i64((c.gain as i64 * *v as i64) >> 30);
            *v = u.saturating_add(le);
        }
        c.filter.run(e);
        for (u, &v) in self.table.iter_mut().zip(e.iter()) {
            *u = limit(v, -c.limit, c.limit);
        }
        self.updates = self.updates.wrapping_add(1);
    }
}

/// `⌊√x⌋`.
fn isqrt(x: u128) -> u128 {
    if x < 2 {
        return x;
    }
    // Newton from above: at most ~70 iterations for 128 bits.
    let mut r = 1u128 << ((128 - x.leading_zeros()).div_ceil(2));
    loop {
        let next = (r + x / r) / 2;
        if next >= r {
            return r;
        }
        r = next;
    }
}

/// Extra fractional bits of the filter's state over Q2.30 (the state is Q2.46 in an `i64`).
const STATE_BITS: u32 = 16;

/// Most warm-up passes of the circular filter (each one period).
pub const MAX_WARMUP: u8 = 16;

/// The robustness filter `Q`: a second-order Butterworth low pass (bilinear, prewarped at the
/// corner), run forward and then backward over one period, circularly: zero phase, magnitude
/// `1 / (1 + (f/f_c)⁴)`, so that `1 − Q ≈ (f/f_c)⁴` well inside the pass band (what the
/// learning leaves of the error there) and noise above the corner is not accumulated.
///
/// Coefficients Q2.30 (`b0 b1 b2 a1 a2`, `a0 = 1`); state Q2.46 in `i64`, products in `i128`.
/// Each direction starts from the periodic steady state: `warmup` passes over the period
/// (enough for the poles to forget their start to 2⁻³², at most [`MAX_WARMUP`]) before the
/// pass that writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RobustnessFilter {
    /// `b0, b1, b2, a1, a2`, Q2.30.
    coefficients: [i32; 5],
    /// Warm-up passes per direction.
    warmup: u8,
}

impl RobustnessFilter {
    /// The filter for `cutoff_hz` at `rate_hz` over a period of `period` samples (`0 <
    /// cutoff < rate / 2`, checked by [`LearnSettings::build`]).
    ///
    /// ```
    /// use twinstack::services::learning::RobustnessFilter;
    /// use twinstack::fixed_point::signal_from_f64;
    /// let q = RobustnessFilter::new(3000.0, 50_000.0, 200);
    /// let mut dc = [signal_from_f64(0.25); 200];
    /// q.run(&mut dc);
    /// assert!(dc.iter().all(|&x| (x - signal_from_f64(0.25)).abs() < 64));
    /// ```
    pub fn new(cutoff_hz: f64, rate_hz: f64, period: usize) -> Self {
        let [b0, b1, b2, a1, a2] = butterworth(cutoff_hz, rate_hz);
        // Pole radius √a2; samples for r^n < 2^-32.
        let r = libm::sqrt(a2.clamp(0.0, 1.0 - 1e-12));
        let settle = 32.0 * core::f64::consts::LN_2 / -libm::log(r).max(1e-12);
        let passes = libm::ceil(settle / period.max(1) as f64).clamp(1.0, MAX_WARMUP as f64);
        Self {
            coefficients: [b0, b1, b2, a1, a2].map(signal_from_f64),
            warmup: passes as u8,
        }
    }

    /// Filters one period in place (zero phase, circular).
    pub fn run(&self, xs: &mut [i32]) {
        if xs.is_empty() {
            return;
        }
        self.pass(xs, false);
        self.pass(xs, true);
    }

    fn pass(&self, xs: &mut [i32], reverse: bool) {
        let [b0, b1, b2, a1, a2] = self.coefficients.map(|c| c as i128);
        // x[n−1], x[n−2] (Q2.30) and y[n−1], y[n−2] (Q2.46).
        let mut s = ([0i32; 2], [0i64; 2]);
        let step = |s: &mut ([i32; 2], [i64; 2]), x: i32| -> i64 {
            let (xh, yh) = s;
            let acc = ((b0 * x as i128 + b1 * xh[0] as i128 + b2 * xh[1] as i128) << STATE_BITS)
                - a1 * yh[0] as i128
                - a2 * yh[1] as i128;
            let y = (acc >> 30).clamp(i64::MIN as i128, i64::MAX as i128) as i64;
            *xh = [x, xh[0]];
            *yh = [y, yh[0]];
            y
        };
        let len = xs.len();
        let at = |n: usize| if reverse { len - 1 - n } else { n };
        for _ in 0..self.warmup {
            for n in 0..len {
                step(&mut s, xs[at(n)]);
            }
        }
        for n in 0..len {
            let i = at(n);
            let y = step(&mut s, xs[i]);
            xs[i] = saturate_i64((y + (1 << (STATE_BITS - 1))) >> STATE_BITS);
        }
    }
}

/// A second-order Butterworth low pass at `fc` for rate `fs` (bilinear, prewarped):
/// `[b0, b1, b2, a1, a2]` of `y = b0 x + b1 x₁ + b2 x₂ − a1 y₁ − a2 y₂`.
pub fn butterworth(fc: f64, fs: f64) -> [f64; 5] {
    let k = libm::tan(core::f64::consts::PI * fc / fs);
    let q = core::f64::consts::SQRT_2;
    let norm = 1.0 / (1.0 + q * k + k * k);
    let b0 = k * k * norm;
    [
        b0,
        2.0 * b0,
        b0,
        2.0 * (k * k - 1.0) * norm,
        (1.0 - q * k + k * k) * norm,
    ]
}

/// What the task's side needs of the tick's owner (the control loop, which holds the
/// [`LearnTick`]): the locked calls below go through it, so this module sits below the loop.
pub trait LearnHost {
    /// The learning's tick half.
    fn learning(&self) -> &LearnTick;
    /// The learning's tick half, to configure it or move a table in or errors out.
    fn learning_mut(&mut self) -> &mut LearnTick;
    /// Sets the learning's state between two ticks.
    fn set_learning(&mut self, state: LearnState);
}

/// Configures the learning on both halves: the task's gain, filter and limit, the tick's period
/// (restarting at bin 0). O(1) under the lock.
pub fn configure<H, L>(task: &mut LearnTask, config: LearnConfig, control: &mut L)
where
    H: LearnHost,
    L: rtic_core::Mutex<T = H>,
{
    task.set_config(config);
    let period = config.period();
    control.lock(|c| c.learning_mut().set_period(period));
    task.seen = control.lock(|c| c.learning().periods());
}

/// Writes the task's table into the tick's inactive table in [`CHUNK`]-word locked copies
/// and posts it (it plays from the next period boundary).
pub fn post_table<H, L>(task: &LearnTask, control: &mut L)
where
    H: LearnHost,
    L: rtic_core::Mutex<T = H>,
{
    for (i, chunk) in task.table.chunks(CHUNK).enumerate() {
        control.lock(|c| c.learning_mut().write_spare(i * CHUNK, chunk));
    }
    control.lock(|c| c.learning_mut().post());
}

/// What [`service`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Service {
    /// No period completed since the last call (or learning off).
    Idle,
    /// A period's error was taken (and, learning, a new table posted).
    Took(PeriodError),
    /// The tick completed another period while the errors were copied: that one is skipped.
    Missed,
    /// The period's error tripped the divergence guard ([`DIVERGENCE_FACTOR`]): the learning
    /// is off, the feedforward alone plays.
    Stopped(PeriodError),
}

/// The low-priority task's work at a period boundary (call it whenever the task runs; it
/// returns at once when no period has completed): copies the completed period's errors out
/// in [`CHUNK`]-word locked copies, runs the ILC law outside any lock ([`LearnTask::update`])
/// and, learning, posts the new table ([`post_table`]).
pub fn service<H, L>(task: &mut LearnTask, control: &mut L) -> Service
where
    H: LearnHost,
    L: rtic_core::Mutex<T = H>,
{
    let (periods, state, period, posted, restarted_at) = control.lock(|c| {
        let l = c.learning();
        (
            l.periods(),
            l.state(),
            l.period(),
            l.is_posted(),
            l.restarted_at(),
        )
    });
    // Not learning, or a motion started since: the guard measures from the next period.
    if state != LearnState::Learning || restarted_at != task.restart_seen {
        task.restart_guard();
        task.restart_seen = restarted_at;
    }
    // A period not yet taken when the motion started (the task ran late) is the previous
    // motion's: neither the guard's nor the law's.
    let stale = periods == restarted_at;
    if periods == task.seen || stale || state == LearnState::Off || task.config.is_none() {
        task.seen = periods;
        return Service::Idle;
    }
    let p = period.min(MAX_BINS);
    let mut offset = 0;
    while offset < p {
        let end = (offset + CHUNK).min(p);
        let out = &mut task.work[offset..end];
        control.lock(|c| c.learning().copy_errors(offset, out));
        offset = end;
    }
    let (now, restarted) = control.lock(|c| {
        let l = c.learning();
        (l.periods(), l.restarted_at())
    });
    if now != periods {
        task.seen = now;
        task.missed = task.missed.wrapping_add(1);
        return Service::Missed;
    }
    task.seen = periods;
    // A motion started during the copy (it marks `periods`, which the copied period is not
    // stale against): the period copied was the previous motion's.
    if restarted != restarted_at {
        return Service::Idle;
    }
    // A table posted but not yet swapped in: the period just completed played the one before
    // it, as the law expects (see the module doc); a second post would only overwrite it.
    let learn = state == LearnState::Learning && !posted;
    task.update(p, learn);
    if task.diverged() {
        control.lock(|c| c.set_learning(LearnState::Off));
        return Service::Stopped(task.last);
    }
    if learn {
        post_table(task, control);
    }
    Service::Took(task.last)
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::fixed_point::signal_to_f64;
    use std::vec::Vec;

    /// The f64 reference of the robustness filter: the same biquad, forward then backward,
    /// each direction after the same warm-up passes.
    fn reference_filter(xs: &[f64], c: [f64; 5], warmup: u8) -> Vec<f64> {
        let pass = |xs: &[f64]| -> Vec<f64> {
            let [b0, b1, b2, a1, a2] = c;
            let (mut x1, mut x2, mut y1, mut y2) = (0.0, 0.0, 0.0, 0.0);
            let mut out = Vec::new();
            for round in 0..=warmup {
                for &x in xs {
                    let y = b0 * x + b1 * x1 + b2 * x2 - a1 * y1 - a2 * y2;
                    (x2, x1, y2, y1) = (x1, x, y1, y);
                    if round == warmup {
                        out.push(y);
                    }
                }
            }
            out
        };
        let fwd = pass(xs);
        let rev: Vec<f64> = fwd.iter().rev().copied().collect();
        pass(&rev).into_iter().rev().collect()
    }

    #[test]
    fn the_filter_matches_its_f64_reference() {
        let mut seed = 99u32;
        for &(p, fc) in &[
            (200usize, 3000.0),
            (250, 500.0),
            (1024, 50.0),
            (7, 20_000.0),
        ] {
            let xs: Vec<f64> = (0..p)
                .map(|n| {
                    seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                    0.3 * libm::sin(n as f64 * 0.1)
                        + 0.05 * ((seed >> 8) as f64 / 16_777_216.0 - 0.5)
                })
                .collect();
            let f = RobustnessFilter::new(fc, 50_000.0, p);
            let c = f.coefficients.map(signal_to_f64);
            let want = reference_filter(&xs, c, f.warmup);
            let mut q: Vec<i32> = xs.iter().map(|&x| signal_from_f64(x)).collect();
            f.run(&mut q);
            let worst = q
                .iter()
                .zip(&want)
                .map(|(&g, &w)| (signal_to_f64(g) - w).abs())
                .fold(0.0, f64::max);
            assert!(worst < 1e-7, "P = {p}, fc = {fc}: {worst}");
        }
    }

    #[test]
    fn the_filter_is_zero_phase_flat_in_band_and_cuts_above() {
        // Cosines centred on bin 0 stay centred (no lag): one in the pass band passes within
        // (f/fc)^4, one an octave above the corner is cut to 1/17.
        let p = 200;
        let f = RobustnessFilter::new(5000.0, 50_000.0, p);
        let cosine = |cycles: f64| -> Vec<i32> {
            (0..p)
                .map(|n| {
                    signal_from_f64(
                        0.5 * libm::cos(2.0 * core::f64::consts::PI * cycles * n as f64 / p as f64),
                    )
                })
                .collect()
        };
        // 5 cycles per 200 ticks at 50 kHz: 1250 Hz, (1/4)^4 = 0.004.
        let mut low = cosine(5.0);
        f.run(&mut low);
        let peak = (0..p).max_by_key(|&n| low[n]).unwrap();
        assert_eq!(peak % 40, 0, "peak at {peak}");
        let gain = signal_to_f64(low[0]) / 0.5;
        assert!(
            (gain - 1.0 / (1.0 + 0.25f64.powi(4))).abs() < 0.01,
            "{gain}"
        );
        // 40 cycles: 10 kHz, an octave above.
        let mut high = cosine(40.0);
        f.run(&mut high);
        let gain = signal_to_f64(high[0]) / 0.5;
        assert!(gain < 0.1, "{gain}");
    }

    #[test]
    fn refusals_name_the_field_and_the_limit() {
        let s = LearnSettings::for_period(200);
        let r = |f: fn(&mut LearnSettings)| {
            let mut t = s;
            f(&mut t);
            t.build(50_000.0).unwrap_err()
        };
        assert_eq!(
            r(|t| t.period_ticks = 1),
            Refusal::new(Field::LearnPeriod, Rule::AtLeast(2.0))
        );
        assert_eq!(
            r(|t| t.period_ticks = 600),
            Refusal::new(Field::LearnPeriod, Rule::AtMost(512.0))
        );
        assert_eq!(
            r(|t| t.gain = f64::NAN),
            Refusal::new(Field::LearnGain, Rule::NotFinite)
        );
        assert_eq!(
            r(|t| t.gain = 0.0),
            Refusal::new(Field::LearnGain, Rule::Above(0.0))
        );
        assert_eq!(
            r(|t| t.gain = 2.0),
            Refusal::new(Field::LearnGain, Rule::AtMost(1.5))
        );
        assert_eq!(
            r(|t| t.cutoff_hz = -1.0),
            Refusal::new(Field::LearnCutoff, Rule::Above(0.0))
        );
        assert_eq!(
            r(|t| t.lead_ticks = 65),
            Refusal::new(Field::LearnLead, Rule::AtMost(64.0))
        );
        assert_eq!(
            r(|t| t.limit = 1.5),
            Refusal::new(Field::LearnLimit, Rule::AtMost(1.0))
        );
        let mut short = LearnSettings::for_period(5);
        short.lead_ticks = 5;
        assert_eq!(
            short.build(50_000.0).unwrap_err(),
            Refusal::new(Field::LearnLead, Rule::AtMost(4.0))
        );
    }

    #[test]
    fn the_tick_plays_whole_periods_and_swaps_at_the_boundary() {
        let mut t = LearnTick::new();
        t.set_period(4);
        t.set_state(LearnState::Frozen, 0);
        t.write_spare(0, &[10, 11, 12, 13]);
        t.post();
        // Mid-period: the old (empty) table until the boundary.
        let mut played = Vec::new();
        for k in 0..12 {
            played.push(t.correction());
            let ended = t.observe(0, Some(0));
            assert_eq!(ended, k % 4 == 3);
        }
        assert_eq!(played, [0, 0, 0, 0, 10, 11, 12, 13, 10, 11, 12, 13]);
        assert_eq!(t.periods(), 3);
    }

    #[test]
    fn errors_meet_the_target_of_their_instant_and_flip_each_period() {
        let mut t = LearnTick::new();
        t.set_period(5);
        t.set_state(LearnState::Learning, 0);
        // The stage follows the target exactly, read at the end of the hold of
        // SENSOR_DELAY_TICKS ago, between that target's instant and the next's: no error.
        let target = |k: i32| 1000 * k;
        let d = SENSOR_DELAY_TICKS as i32;
        // Along the ramp, half a step past the target of SENSOR_DELAY_TICKS ago (from the
        // third tick on: the cubic sees the ramp's start before).
        let instant = |k: i32| {
            let r = |j: i32| target(j.max(0));
            crate::control::instant::between_holds([
                r(k - d - 1),
                r(k - d),
                r(k - d + 1),
                r(k - d + 2),
            ])
        };
        assert_eq!(instant(9), target(9 - d) + 500);
        for k in 0..5 {
            t.observe(target(k), Some(instant(k)));
        }
        let mut e = [7; 5];
        assert_eq!(t.copy_errors(0, &mut e), 5);
        assert_eq!(e, [0; 5]);
        // A constant shortfall of 3 appears in every bin; a failed read stores 0.
        for k in 5..10 {
            let measured = instant(k) - 3;
            t.observe(target(k), (k != 7).then_some(measured));
        }
        t.copy_errors(0, &mut e);
        assert_eq!(e, [3, 3, 0, 3, 3]);
        assert_eq!(t.missing(), 1);
    }

    /// The ILC law on a plant it can learn: `x(k) = g · u(k − 1)` (a gain and one tick of
    /// delay) behind the sensor's delay; the error shrinks period after period.
    #[test]
    fn the_guard_stops_a_learning_whose_error_grows_past_twice_its_best() {
        let mut t = LearnTask::new();
        t.set_config(LearnSettings::for_period(40).build(50_000.0).unwrap());
        let period = |t: &mut LearnTask, e: i32| {
            t.work[..40].fill(e);
            t.update(40, true);
            t.diverged()
        };
        // Falling, then a rise within twice the best (plus the floor): learning goes on.
        for e in [1 << 24, 1 << 22, 1 << 20, (1 << 21) + DIVERGENCE_FLOOR] {
            assert!(!period(&mut t, e), "{e}");
        }
        // Far past twice the best, but below the first period's error: off would be worse.
        for e in [1 << 22, 1 << 23, 1 << 24] {
            assert!(!period(&mut t, e), "{e}");
        }
        let updates = t.updates();
        let table = *t.table();
        // Past twice the best and the first period's: stopped, the table as it was, counted.
        assert!(period(&mut t, (1 << 24) + 1));
        assert_eq!((t.updates(), t.guard_stops()), (updates, 1));
        assert_eq!(*t.table(), table);
        // The guard starts again from the next period (as after a restart): this one is its
        // first, and a learning that starts at its floor is stopped past twice its best.
        assert!(!period(&mut t, 1 << 20));
        assert!(!period(&mut t, (1 << 21) + DIVERGENCE_FLOOR));
        assert!(period(&mut t, (1 << 21) + DIVERGENCE_FLOOR + 1));
        assert!(!period(&mut t, 1 << 24));
        // Not learning (frozen): measured, never stopped.
        t.work[..40].fill(i32::MAX);
        t.update(40, false);
        assert!(!t.diverged());
    }

    /// A stage at rest under a 12-bit sensor: most errors 0, some one code (2^19 in Q2.30).
    /// From period to period the RMS takes values more than twice apart; at the sensor's
    /// resolution that is not a divergence, and the guard, given it, does not take it for one.
    #[test]
    fn errors_at_the_sensor_s_resolution_do_not_trip_the_guard() {
        let code = 1 << 19;
        // Codes in 40 bins: RMS = code · √(n / 40).
        let rest = |ones: usize| {
            let mut e = [0i32; 40];
            e[..ones].fill(code);
            e
        };
        let run = |resolution: Option<i32>| {
            let mut t = LearnTask::new();
            t.set_config(LearnSettings::for_period(40).build(50_000.0).unwrap());
            t.set_resolution(resolution);
            [12, 3, 12, 40].iter().any(|&ones| {
                t.work[..40].copy_from_slice(&rest(ones));
                t.update(40, true);
                t.diverged()
            })
        };
        assert!(run(None), "without the resolution the noise trips it");
        assert!(!run(Some(code)));
        // A growth past one code above twice the best still does.
        let mut t = LearnTask::new();
        t.set_config(LearnSettings::for_period(40).build(50_000.0).unwrap());
        t.set_resolution(Some(code));
        for (e, tripped) in [(code, false), (code / 2, false), (2 * code + 1, true)] {
            t.work[..40].fill(e);
            t.update(40, true);
            assert_eq!(t.diverged(), tripped, "{e}");
        }
    }

    /// The tick's half as its own host, behind a lock that just lends it (one thread).
    struct Host(LearnTick);

    /// A host whose tick restarts the period (a motion starts) just before the task's
    /// `restart_on`-th lock: what the tick's interrupt may do between any two of them.
    struct Racing {
        host: Host,
        locks: usize,
        restart_on: usize,
    }

    impl rtic_core::Mutex for Racing {
        type T = Host;
        fn lock<R>(&mut self, f: impl FnOnce(&mut Host) -> R) -> R {
            self.locks += 1;
            if self.locks == self.restart_on {
                self.host.0.restart();
            }
            f(&mut self.host)
        }
    }

    impl LearnHost for Host {
        fn learning(&self) -> &LearnTick {
            &self.0
        }
        fn learning_mut(&mut self) -> &mut LearnTick {
            &mut self.0
        }
        fn set_learning(&mut self, state: LearnState) {
            self.0.set_state(state, 0);
        }
    }

    impl rtic_core::Mutex for Host {
        type T = Host;
        fn lock<R>(&mut self, f: impl FnOnce(&mut Host) -> R) -> R {
            f(self)
        }
    }

    /// Learning switched on over a stage at rest, then the motion starts: the errors of the
    /// motion's first periods are far above those at rest, and the guard, started again with
    /// the motion, does not take them for a divergence.
    #[test]
    fn a_motion_started_after_the_learning_starts_the_guard_again() {
        let p = 40;
        let mut host = Host(LearnTick::new());
        let mut task = LearnTask::new();
        configure(
            &mut task,
            LearnSettings::for_period(p as u16).build(50_000.0).unwrap(),
            &mut host,
        );
        host.0.set_state(LearnState::Learning, 0);
        let periods = |host: &mut Host, task: &mut LearnTask, error: i32, n: usize| {
            let mut last = Service::Idle;
            for _ in 0..n * p {
                if host.0.observe(error, Some(0)) {
                    last = service(task, host);
                }
            }
            last
        };
        // At rest: the error is the sensor's noise.
        assert!(matches!(
            periods(&mut host, &mut task, 1 << 10, 3),
            Service::Took(_)
        ));
        // The waveform starts (the loop restarts the period): errors 2^12 times larger.
        host.0.restart();
        let moving = periods(&mut host, &mut task, 1 << 22, 2);
        assert!(matches!(moving, Service::Took(_)), "{moving:?}");
        assert_eq!(host.0.state(), LearnState::Learning);
        assert_eq!(task.guard_stops(), 0);
        // A motion that changes within the running source still trips it.
        let changed = periods(&mut host, &mut task, 1 << 26, 1);
        assert!(matches!(changed, Service::Stopped(_)), "{changed:?}");
        assert_eq!(host.0.state(), LearnState::Off);
    }

    /// The task runs late: a period at rest completes, the motion starts before the task has
    /// taken it, and the task takes it only then. Whichever of the task's locks the start
    /// falls before, the period at rest is neither learned from nor made the guard's best, so
    /// the motion's far larger errors do not trip the guard.
    #[test]
    fn a_period_completed_before_the_motion_and_taken_after_it_is_not_learned_from() {
        let p: usize = 40;
        // The task's locks for one period: the state, the chunks' copies, the check.
        let locks = 1 + p.div_ceil(CHUNK) + 1;
        for restart_on in 1..=locks + 1 {
            let mut racing = Racing {
                host: Host(LearnTick::new()),
                locks: 0,
                restart_on: usize::MAX,
            };
            let mut task = LearnTask::new();
            configure(
                &mut task,
                LearnSettings::for_period(p as u16).build(50_000.0).unwrap(),
                &mut racing.host,
            );
            racing.host.0.set_state(LearnState::Learning, 0);
            // At rest, taken in time: the sensor's noise.
            for _ in 0..2 * p {
                if racing.host.0.observe(1 << 10, Some(0)) {
                    service(&mut task, &mut racing.host);
                }
            }
            // One more period at rest that the task does not take in time.
            for _ in 0..p {
                racing.host.0.observe(1 << 10, Some(0));
            }
            let updates = task.updates();
            // The motion starts before, or while, the task takes it.
            racing.locks = 0;
            racing.restart_on = restart_on;
            let late = service(&mut task, &mut racing);
            if restart_on <= locks {
                assert!(matches!(late, Service::Idle), "{restart_on}: {late:?}");
                assert_eq!(task.updates(), updates, "{restart_on}");
            } else {
                // The motion started after the task's last lock: that period was the rest's.
                racing.host.0.restart();
            }
            racing.restart_on = usize::MAX;
            // The motion: errors 2^12 times larger, the same period after period.
            for _ in 0..3 * p {
                if racing.host.0.observe(1 << 22, Some(0)) {
                    let s = service(&mut task, &mut racing);
                    assert!(matches!(s, Service::Took(_)), "{restart_on}: {s:?}");
                }
            }
            assert_eq!(racing.host.0.state(), LearnState::Learning, "{restart_on}");
            assert_eq!(task.guard_stops(), 0, "{restart_on}");
        }
    }

    #[test]
    fn the_law_converges_on_a_delayed_gain() {
        let p = 100;
        let mut tick = LearnTick::new();
        let mut task = LearnTask::new();
        let mut s = LearnSettings::for_period(p as u16);
        s.lead_ticks = 1;
        s.cutoff_hz = 5000.0;
        let config = s.build(50_000.0).unwrap();
        task.set_config(config);
        tick.set_period(p);
        tick.set_state(LearnState::Learning, 0);
        let r = |k: usize| {
            signal_from_f64(0.4 * libm::sin(2.0 * core::f64::consts::PI * k as f64 / p as f64))
        };
        let g = 0.8;
        let mut drive_hist = [0i32; 2];
        let mut x_hist = [0i32; 3];
        let mut errs = Vec::new();
        for k in 0..40 * p {
            // Feedforward = a model that is 30 % off (0.7 r), plus the table.
            let u = (0.7 * r(k) as f64) as i32 + tick.correction();
            // x(k) = g · u(k − 1); the sensor reads x two ticks late.
            let x = (g * drive_hist[0] as f64) as i32;
            drive_hist = [u, drive_hist[0]];
            x_hist = [x, x_hist[0], x_hist[1]];
            if tick.observe(r(k), Some(x_hist[SENSOR_DELAY_TICKS])) {
                let n = tick.periods();
                let mut buf = [0i32; MAX_BINS];
                tick.copy_errors(0, &mut buf[..p]);
                task.work[..p].copy_from_slice(&buf[..p]);
                let learn = !tick.is_posted();
                task.update(p, learn);
                if learn {
                    tick.write_spare(0, &task.table[..p]);
                    tick.post();
                }
                errs.push((n, signal_to_f64(task.last_error().max)));
            }
        }
        let first = errs[1].1;
        let last = errs.last().unwrap().1;
        assert!(first > 0.05, "{errs:?}");
        assert!(last < first / 100.0, "{first} → {last}");
    }
}
