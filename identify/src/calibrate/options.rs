//! What a calibration is asked to do: [`CalibrateOptions`], with the defaults `twinstack
//! calibrate` runs.

use super::*;

/// How a calibration runs. [`CalibrateOptions::default`] is what `twinstack calibrate` runs.
#[derive(Clone, Debug, PartialEq)]
pub struct CalibrateOptions {
    /// Frequency of the excitation, Hz.
    pub excitation_hz: f64,
    /// Amplitude of the full cycles, normalised (fraction of the half range about its middle);
    /// the identified input range is the range swept (see
    /// [`crate::identification::INPUT_MARGIN`]).
    pub amplitude: f64,
    /// Cycles at full amplitude.
    pub full_cycles: u16,
    /// Cycles decaying after them (the last one is held out of the fit and scores it).
    pub decay_cycles: u16,
    /// Amplitude of the last cycle, fraction of [`CalibrateOptions::amplitude`].
    pub final_amplitude: f64,
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
}

impl Default for CalibrateOptions {
    /// 10 Hz, 6 full cycles at 0.97 then 14 decaying to 15 %, recorded at up to 10 kHz, the
    /// model picked by `auto`, refused above 5 % held-out max error, stored to boot in
    /// bypass, verification streamed at 10 000 setpoints/s on a 50 kHz board.
    fn default() -> Self {
        Self {
            excitation_hz: 10.0,
            amplitude: 0.97,
            full_cycles: 6,
            decay_cycles: 14,
            final_amplitude: 0.15,
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
        }
    }
}

impl CalibrateOptions {
    /// Checks the options (every number finite and in its range), naming the first bad one.
    pub fn check(&self) -> Result<(), CalibrateError> {
        let bad = |field: &'static str, rule: &'static str, value: f64| {
            Err(CalibrateError::Option { field, rule, value })
        };
        if !(self.excitation_hz.is_finite() && self.excitation_hz > 0.0) {
            return bad(
                "excitation_hz",
                "a positive number of Hz",
                self.excitation_hz,
            );
        }
        if !(self.amplitude > 0.0 && self.amplitude <= 1.0) {
            return bad("amplitude", "in (0, 1]", self.amplitude);
        }
        if self.full_cycles == 0 {
            return bad("full_cycles", "at least 1", 0.0);
        }
        if self.decay_cycles < 2 {
            return bad("decay_cycles", "at least 2", self.decay_cycles as f64);
        }
        if !(self.final_amplitude > 0.0 && self.final_amplitude < 1.0) {
            return bad("final_amplitude", "in (0, 1)", self.final_amplitude);
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

    /// Cycles of the excitation in all.
    pub fn cycles(&self) -> u32 {
        self.full_cycles as u32 + self.decay_cycles as u32
    }

    /// Length of the excitation, seconds.
    pub fn excitation_s(&self) -> f64 {
        self.cycles() as f64 / self.excitation_hz
    }

    /// The waveform request: a sine about the middle, decaying per cycle after the full ones
    /// so that the last cycle's amplitude is [`CalibrateOptions::final_amplitude`] of the first.
    pub fn waveform(&self) -> Waveform {
        // Cycle `full_cycles + k` (k = 0 …) has `keep^(k + 1)`: the last, `keep^decay_cycles`.
        let keep = self.final_amplitude.powf(1.0 / self.decay_cycles as f64);
        Waveform {
            shape: WaveShape::Sine,
            offset: 0,
            amplitude: q1_15(self.amplitude),
            frequency_mhz: (self.excitation_hz * 1000.0).round().max(1.0) as u32,
            decay: Some(WaveDecay {
                hold_cycles: self.full_cycles,
                keep: (keep * 65536.0).round().min(65535.0) as u16,
            }),
        }
    }
}
