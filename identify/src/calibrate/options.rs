//! What a calibration is asked to do: [`CalibrateOptions`], with the defaults `twinstack
//! calibrate` runs.

use super::*;
use crate::excitation::Excitation;
use crate::trajectory::MIN_SAMPLES_PER_CYCLE;

/// How a calibration runs. [`CalibrateOptions::default`] is what `twinstack calibrate` runs.
#[derive(Clone, Debug, PartialEq)]
pub struct CalibrateOptions {
    /// Base frequency of the excitation, Hz ([`Excitation::hz`]).
    pub excitation_hz: f64,
    /// Amplitude of the excitation, normalised (fraction of the half range about its middle):
    /// the full cycles sweep the middle ± this; the identified input range is the range swept
    /// (see [`crate::identification::INPUT_MARGIN`]).
    pub amplitude: f64,
    /// Cycles over the whole swept range ([`Excitation::full_cycles`]).
    pub full_cycles: u16,
    /// Cycles decaying about the middle after them ([`Excitation::decay_cycles`]).
    pub decay_cycles: u16,
    /// The decaying cycles' last amplitude, fraction of [`CalibrateOptions::amplitude`].
    pub final_amplitude: f64,
    /// Cycles' time of nested, off-centre minor loops after them ([`Excitation::loop_cycles`]).
    pub loop_cycles: u16,
    /// Cycles' time of a three-tone multisine last ([`Excitation::multisine_cycles`]). The
    /// excitation's last cycle, whichever part it is of, is held out of the fit and scores it.
    pub multisine_cycles: u16,
    /// The fastest motion the user will run, Hz: the excitation gains a sweep up to it before
    /// the multisine ([`Excitation::reaching`]), so that the fit sees the rates its
    /// compensator will be asked for. `None`: no sweep. The board must stream and record it
    /// with at least [`MIN_SAMPLES_PER_CYCLE`] samples a cycle, as a tracked triangle.
    pub fastest_hz: Option<f64>,
    /// Highest rate the excitation and the verification runs are recorded at, Hz (lower if
    /// the board's capture slots do not hold the run at this rate).
    pub sample_rate_hz: f64,
    /// The model to fit; `None`: every model of the family, the best kept (`--model auto`).
    pub model: Option<ModelKind>,
    /// Play operators of a P–I model; `None`: 17, or as many as the board runs at its rate
    /// where 17 are too many.
    pub operators: Option<usize>,
    /// Sensor lag, samples of the recorded excitation; `None`: estimated as `identify` does.
    pub lag: Option<usize>,
    /// Largest held-out max error of the identified model, % of span, before the calibration
    /// is refused as a fit that does not fit.
    pub max_held_out_pct: f64,
    /// Load a model whose input range the drive cannot reach in full (as `load --clamp`).
    pub clamp: bool,
    /// Store the settings to flash once verified, to boot in this mode; `None`: do not store.
    pub store: Option<Mode>,
    /// Ticks per streamed setpoint of the verification runs.
    pub stream_divider: u16,
    /// Unit of the sensor's displacement, written into the parameter file.
    pub output_unit: String,
    /// Load the model as the observer too (the estimate, and the drift check's reference),
    /// as well as the compensator; `false`: the compensator only, the observer's cost off the
    /// tick ([`crate::identification::IdentifyOptions::observer`]).
    pub observer: bool,
    /// Measure the stage's resonance after the excitation (the sweep and fit `twinstack
    /// tune` runs) and write it into the parameter file, for a planned trajectory's preview
    /// ([`crate::preview`]).
    pub resonance: bool,
}

impl Default for CalibrateOptions {
    /// The excitation [`Excitation::DEFAULT`] at 0.97 of the range (2 s at 10 Hz: 4 full
    /// cycles, 6 decaying to 30 %, 5 of nested loops, 5 of multisine), streamed and recorded at up to 10 kHz; the model picked
    /// by `auto`, refused above 5 % held-out max error, the resonance measured, stored to
    /// boot in bypass; verification streamed at 10 000 setpoints/s on a 50 kHz board.
    fn default() -> Self {
        Self {
            excitation_hz: Excitation::DEFAULT.hz,
            amplitude: 0.97,
            full_cycles: Excitation::DEFAULT.full_cycles,
            decay_cycles: Excitation::DEFAULT.decay_cycles,
            final_amplitude: Excitation::DEFAULT.final_amplitude,
            loop_cycles: Excitation::DEFAULT.loop_cycles,
            multisine_cycles: Excitation::DEFAULT.multisine_cycles,
            fastest_hz: None,
            sample_rate_hz: 10_000.0,
            model: None,
            operators: None,
            lag: Some(0),
            max_held_out_pct: 5.0,
            clamp: false,
            store: Some(Mode::Bypass),
            stream_divider: 5,
            output_unit: "um".into(),
            observer: true,
            resonance: true,
        }
    }
}

impl CalibrateOptions {
    /// Checks the options (every number finite and in its range), naming the first bad one.
    pub fn check(&self) -> Result<(), CalibrateError> {
        let bad = |field: &'static str, rule: &'static str, value: f64| {
            Err(CalibrateError::Option { field, rule, value })
        };
        if let Err((field, rule, value)) = self.excitation().check() {
            // The sweep's top is checked last: the excitation's frequency it is held against
            // is good by then, and the message names both.
            return match (field, self.fastest_hz) {
                ("fastest_hz", Some(fastest_hz)) => Err(CalibrateError::FastestOutOfRange {
                    fastest_hz,
                    excitation_hz: self.excitation_hz,
                }),
                _ => bad(field, rule, value),
            };
        }
        if !(self.amplitude > 0.0 && self.amplitude <= 1.0) {
            return bad("amplitude", "in (0, 1]", self.amplitude);
        }
        if !(self.sample_rate_hz.is_finite() && self.sample_rate_hz > 0.0) {
            return bad(
                "sample_rate_hz",
                "a positive number of Hz",
                self.sample_rate_hz,
            );
        }
        if !(self.max_held_out_pct.is_finite() && self.max_held_out_pct > 0.0) {
            return bad("max_held_out_pct", "a positive %", self.max_held_out_pct);
        }
        if self.stream_divider == 0 {
            return bad("stream_divider", "at least 1", 0.0);
        }
        Ok(())
    }

    /// The excitation's shape.
    pub fn excitation(&self) -> Excitation {
        let shape = Excitation {
            hz: self.excitation_hz,
            full_cycles: self.full_cycles,
            decay_cycles: self.decay_cycles,
            final_amplitude: self.final_amplitude,
            loop_cycles: self.loop_cycles,
            multisine_cycles: self.multisine_cycles,
            ..Excitation::DEFAULT
        };
        match self.fastest_hz {
            Some(hz) => shape.reaching(hz),
            None => shape,
        }
    }

    /// Checks that the excitation's fastest motion is resolved where it is streamed and
    /// recorded, at `stream_hz` setpoints and `recorded_hz` frames a second: at least
    /// [`MIN_SAMPLES_PER_CYCLE`] of each a cycle, as a tracked triangle.
    pub fn check_resolved(&self, stream_hz: f64, recorded_hz: f64) -> Result<(), CalibrateError> {
        let fastest = self.excitation().fastest_hz();
        let slowest = stream_hz.min(recorded_hz);
        let needed = fastest * MIN_SAMPLES_PER_CYCLE;
        if needed > slowest {
            return Err(CalibrateError::FastestUnresolved {
                fastest_hz: fastest,
                stream_hz,
                recorded_hz,
                // The stream's rate is the board's tick rate over the stream divider, and the
                // recorder's at most `sample_rate_hz`; below that, it falls as the excitation
                // lengthens (the board's slots hold the whole run).
                remedy: if stream_hz.min(self.sample_rate_hz) < needed {
                    "name a slower motion (the board streams and records no faster)"
                } else {
                    "name a slower motion, or shorten the excitation (fewer cycles of its parts: `--full-cycles`, `--decay-cycles`, `--loop-cycles`, `--multisine-cycles`) so that the recorder holds it at a higher rate"
                },
            });
        }
        Ok(())
    }

    /// How calibrate streams (the excitation, the verification runs) to a board ticking at
    /// `tick_rate_hz`: one setpoint every [`CalibrateOptions::stream_divider`] ticks, holding
    /// on an empty queue, drained before the capture is read.
    pub fn stream_options(&self, tick_rate_hz: f64) -> StreamOptions {
        StreamOptions {
            divider: self.stream_divider,
            underrun: Some(UnderrunPolicy::Hold),
            tick_rate_hz,
            drain: true,
            ..StreamOptions::default()
        }
    }

    /// The lead-in before the excitation, seconds: a quarter cycle from the middle of the
    /// range down to the bottom of the swept range, where the excitation starts.
    pub fn lead_in_s(&self) -> f64 {
        0.25 / self.excitation_hz
    }

    /// Length of what is streamed and recorded (the lead-in, then the excitation), seconds.
    pub fn excitation_s(&self) -> f64 {
        self.lead_in_s() + self.excitation().duration_s()
    }

    /// The setpoints streamed at `rate` per second, Q1.15 normalised (the middle of the range
    /// ± [`CalibrateOptions::amplitude`]); in bypass, the drive: the lead-in from the middle
    /// (`−sin`, ending on the excitation's first value with its slope, 0), then the
    /// excitation.
    pub fn excitation_setpoints(&self, rate: f64) -> Vec<i16> {
        let lead = (self.lead_in_s() * rate).round() as usize;
        let w = std::f64::consts::TAU * self.excitation_hz;
        (0..lead)
            .map(|k| -(w * k as f64 / rate).sin())
            .chain(self.excitation().sampled(rate))
            .map(|x| q1_15(self.amplitude * x))
            .collect()
    }
}
