//! Why a setting or a request was refused: the field and the rule (with its limit) it broke.
//!
//! A [`Refusal`] is what validation returns and what the wire carries in a NACK, so the host
//! can say "`feedback.ki` = 3e4: must be below 2.5e4" without knowing how the board validates.
//! [`Field`] and [`Rule`] are **wire-stable**: `postcard` encodes an enum by its variant index,
//! so variants are only ever appended, never reordered or removed (the protocol chapter of the
//! book lists their codes). Internal error types (the models' `ParamError`, the notch's
//! `NotchError`) never reach the wire; the builders map them onto a field here.

use serde::{Deserialize, Serialize};

/// A field of a hysteresis model (the compensator's or the observer's).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ModelField {
    /// The model as a whole (its kind, or a property of all its parameters together).
    Model,
    /// P–I linear term `a0`.
    A0,
    /// Output offset.
    Offset,
    /// P–I threshold of this operator (1-based).
    Threshold(u8),
    /// P–I weight of this operator (1-based).
    Weight(u8),
    /// The P–I operator list (count, lengths).
    Operators,
    /// Duhem `α`.
    Alpha,
    /// Duhem or Bouc–Wen `β`.
    Beta,
    /// Duhem or Bouc–Wen `γ`.
    Gamma,
    /// Generalised P–I: the dead-zone map's centre (`dead_zones.centre`).
    DeadZoneCentre,
    /// Generalised P–I: the dead-zone map's linear gain (`dead_zones.linear`).
    DeadZoneLinear,
    /// Generalised P–I: threshold of this dead zone (1-based).
    DeadZoneThreshold(u8),
    /// Generalised P–I: weight of this dead zone (1-based).
    DeadZoneWeight(u8),
    /// Generalised P–I: the dead-zone list (count, lengths, the sum of its weights).
    DeadZones,
    /// Bouc–Wen `k` (linear slope).
    K,
    /// Bouc–Wen `A` (the hysteretic state's gain).
    A,
    /// Bouc–Wen `ψ` (asymmetric term).
    Psi,
    /// Bouc–Wen `χ` (the term that depends on the state's sign).
    Chi,
}

/// A field of the creep operator (`creep`). Wire-stable: append only.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum CreepField {
    /// The mode list as a whole (count, lengths, the weights' sum).
    Modes,
    /// The time constant of this mode (1-based), `creep.time_constants_s`.
    TimeConstant(u8),
    /// The weight of this mode (1-based), `creep.weights`.
    Weight(u8),
}

/// A field of the settings or of a request. Wire-stable: append only.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Field {
    /// `ranges.input_min` / `ranges.input_max` (volts).
    InputRange,
    /// `ranges.output_min` / `ranges.output_max` (output units).
    OutputRange,
    /// A field of the compensator's model.
    Compensator(ModelField),
    /// A field of the observer's model.
    Observer(ModelField),
    /// `drive.bias`.
    Bias,
    /// `drive.min_voltage` / `drive.max_voltage`.
    VoltageLimits,
    /// `drive.slew_rate`.
    SlewRate,
    /// The sensor's calibration (`sensor.displacement_at_zero` / `_at_full_scale`).
    SensorCalibration,
    /// `sensor.drift_limit`.
    DriftLimit,
    /// `feedback.kp`.
    Kp,
    /// `feedback.ki`.
    Ki,
    /// `feedback.kd`.
    Kd,
    /// `feedback.derivative_cutoff_hz`.
    DerivativeCutoff,
    /// `feedback.limit`.
    FeedbackLimit,
    /// `feedback.notch.frequency_hz`.
    NotchFrequency,
    /// `feedback.notch.q`.
    NotchQ,
    /// `feedback.notch.depth`.
    NotchDepth,
    /// `mode`.
    Mode,
    /// The sensor as a whole (present or not).
    Sensor,
    /// The feedback as a whole (present or not).
    Feedback,
    /// The stream's rate divider.
    Divider,
    /// The waveform's frequency.
    WaveformFrequency,
    /// The waveform's offset and amplitude.
    WaveformAmplitude,
    /// The recorder's sample count.
    RecordCount,
    /// The recorder's decimation.
    RecordDecimation,
    /// A record read's offset.
    RecordOffset,
    /// The recorder's signal list.
    RecordSignals,
    /// A field of the creep operator.
    Creep(CreepField),
    /// A capture's pre-trigger count.
    RecordPreTrigger,
    /// Telemetry's signal list (protocol v5).
    TelemetrySignals,
    /// Telemetry's decimation (protocol v5): at least 1, and at least what keeps the values
    /// per second within what the link carries.
    TelemetryDecimation,
    /// The coarse axis of the dual-actuated stage as a whole (absent, not homed, faulted).
    CoarseAxis,
    /// A coarse move's target position, mm.
    CoarseTarget,
    /// A coarse move's or jog's speed, mm/s.
    CoarseVelocity,
    /// A coarse move's acceleration, mm/s².
    CoarseAcceleration,
    /// `learning.period_ticks`.
    LearnPeriod,
    /// `learning.gain`.
    LearnGain,
    /// `learning.cutoff_hz`.
    LearnCutoff,
    /// `learning.lead_ticks`.
    LearnLead,
    /// `learning.limit`.
    LearnLimit,
    /// The tick's work as a whole at the board's control rate: the models, their creep and
    /// the feedback together ([`crate::config::tick_budget`]).
    Workload,
    /// A scan's lines per frame (raster) or turns (spiral), protocol v6.
    ScanLines,
    /// A raster's pixels per line.
    ScanPixels,
    /// A scan's ticks per pixel (the pixel clock's period; longer than the trigger pulse).
    ScanTicksPerPixel,
    /// A raster's turnaround ticks (its overshoot must stay within the range).
    ScanTurnaround,
    /// A scan's rate: the raster's line rate, the Lissajous frame rate, the spiral's turn
    /// rate (Nyquist and the slew limit).
    ScanFrequency,
    /// A Lissajous figure's x or y cycles per frame.
    ScanCycles,
    /// A scan's amplitude (offset ± amplitude within −1…1).
    ScanAmplitude,
    /// A scan's offset (centre).
    ScanOffset,
    /// The trigger outputs' pulse width, ticks.
    TriggerPulse,
    /// `shaping.frequency_hz`: the feedforward notch's centre (protocol v7).
    ShapingFrequency,
    /// `shaping.q`: the feedforward notch's quality factor.
    ShapingQ,
    /// `shaping.depth`: the feedforward notch's gain at its centre.
    ShapingDepth,
    /// A sequence's trigger edge (rising or falling; off is refused).
    SequenceEdge,
    /// A sequence's settle window, normalised displacement.
    SequenceWindow,
    /// A sequence's settle time, ticks.
    SequenceSettle,
    /// The analog input's gain, normalised displacement per input span.
    AnalogGain,
    /// The analog input's offset, normalised displacement.
    AnalogOffset,
    /// The analog input's low-pass corner, Hz.
    AnalogCorner,
    /// The analog input's valid window, lower bound (fraction of the span).
    AnalogLostBelow,
    /// The analog input's valid window, upper bound (fraction of the span).
    AnalogOverAbove,
    /// The analog input's ramp rate (faults and recovery), normalised displacement per second.
    AnalogRate,
    /// `preview.frequency_hz`: the resonance the preview shapes for (protocol v11).
    PreviewFrequency,
    /// `preview.damping`: its damping ratio.
    PreviewDamping,
    /// A field of the static output map after the model (`output_map`, protocol v12): the
    /// dead-zone fields of [`ModelField`], named as the map's own (`output_map.centre`,
    /// `output_map.thresholds[0]`, …).
    OutputMap(ModelField),
}

/// The rule a field broke, with its limit where it has one (in the field's own units).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Rule {
    /// NaN or infinite.
    NotFinite,
    /// Must be at least this.
    AtLeast(f64),
    /// Must be above this.
    Above(f64),
    /// Must be at most this.
    AtMost(f64),
    /// Must be below this.
    Below(f64),
    /// The range is empty (`max ≤ min`).
    Empty,
    /// Must exceed the value before it (thresholds).
    NotIncreasing,
    /// The model has no inverse (a weight sum that does not rise).
    NotInvertible,
    /// More than this many items.
    TooMany(u32),
    /// Two lists that go together differ in length.
    LengthMismatch,
    /// Needed by another setting (closed loop needs the sensor and the feedback, open loop a
    /// compensator) and absent.
    Required,
    /// The board has no hardware for it (a sensor setting on a board without a sensor ADC).
    NoHardware,
    /// Outside what the fixed-point formats hold, once normalised.
    BeyondFixedPoint,
    /// The voltage limits and the model's input range leave no drive, or the codes would
    /// leave the DAC's range.
    Unreachable,
    /// The model's state could grow without bound (Bouc–Wen: `|γ| < β`, `|ψ| < β − |γ|`).
    Unbounded,
    /// The coarse axis must be homed first (after power-up or a fault).
    NotHomed,
    /// The move runs into a limit switch that is active.
    LimitSwitch,
    /// The tick would need more cycles than the control period leaves it
    /// ([`crate::config::tick_budget`]): its predicted worst case and the cycles available, both at 5
    /// flash wait states.
    TickOverrun {
        /// Predicted worst case of the whole interrupt, cycles.
        needs: u32,
        /// Cycles the control rate leaves the tick.
        available: u32,
    },
    /// Takes no output map (protocol v12): a model other than Bouc–Wen with `output_map` set.
    NoOutputMap,
}

/// A refusal: the field and the rule it broke. Nothing was applied.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Refusal {
    /// What was refused.
    pub field: Field,
    /// Why.
    pub rule: Rule,
}

impl Refusal {
    /// A refusal of `field` for `rule`.
    pub const fn new(field: Field, rule: Rule) -> Self {
        Self { field, rule }
    }
}

/// `Ok(())` if `x` is finite, else a [`Rule::NotFinite`] refusal of `field`.
pub fn finite(field: Field, x: f64) -> Result<(), Refusal> {
    if x.is_finite() {
        Ok(())
    } else {
        Err(Refusal::new(field, Rule::NotFinite))
    }
}

/// `Ok(())` if `lo ≤ x ≤ hi` (`x` finite), else the bound it broke.
pub fn within(field: Field, x: f64, lo: f64, hi: f64) -> Result<(), Refusal> {
    finite(field, x)?;
    if x < lo {
        return Err(Refusal::new(field, Rule::AtLeast(lo)));
    }
    if x > hi {
        return Err(Refusal::new(field, Rule::AtMost(hi)));
    }
    Ok(())
}

impl core::fmt::Display for ModelField {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            ModelField::Model => write!(f, "model"),
            ModelField::A0 => write!(f, "a0"),
            ModelField::Offset => write!(f, "offset"),
            ModelField::Threshold(i) => write!(f, "thresholds[{}]", *i as usize - 1),
            ModelField::Weight(i) => write!(f, "weights[{}]", *i as usize - 1),
            ModelField::Operators => write!(f, "operators"),
            ModelField::Alpha => write!(f, "alpha"),
            ModelField::Beta => write!(f, "beta"),
            ModelField::Gamma => write!(f, "gamma"),
            ModelField::DeadZoneCentre => write!(f, "dead_zones.centre"),
            ModelField::DeadZoneLinear => write!(f, "dead_zones.linear"),
            ModelField::DeadZoneThreshold(i) => {
                write!(
                    f,
                    "dead_zones.thresholds[{}]",
                    (*i as usize).saturating_sub(1)
                )
            }
            ModelField::DeadZoneWeight(i) => {
                write!(f, "dead_zones.weights[{}]", (*i as usize).saturating_sub(1))
            }
            ModelField::DeadZones => write!(f, "dead_zones"),
            ModelField::K => write!(f, "k"),
            ModelField::A => write!(f, "a"),
            ModelField::Psi => write!(f, "psi"),
            ModelField::Chi => write!(f, "chi"),
        }
    }
}

impl core::fmt::Display for CreepField {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            CreepField::Modes => write!(f, "creep"),
            CreepField::TimeConstant(i) => {
                write!(f, "creep.time_constants_s[{}]", (*i as usize).max(1) - 1)
            }
            CreepField::Weight(i) => write!(f, "creep.weights[{}]", (*i as usize).max(1) - 1),
        }
    }
}

impl core::fmt::Display for Field {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        let name = match self {
            Field::Compensator(m) => return write!(f, "compensator.{m}"),
            Field::Observer(m) => return write!(f, "observer.{m}"),
            Field::Creep(c) => return write!(f, "{c}"),
            Field::OutputMap(m) => {
                return match m {
                    ModelField::DeadZoneCentre => write!(f, "output_map.centre"),
                    ModelField::DeadZoneLinear => write!(f, "output_map.linear"),
                    ModelField::DeadZoneThreshold(i) => write!(
                        f,
                        "output_map.thresholds[{}]",
                        (*i as usize).saturating_sub(1)
                    ),
                    ModelField::DeadZoneWeight(i) => {
                        write!(f, "output_map.weights[{}]", (*i as usize).saturating_sub(1))
                    }
                    _ => write!(f, "output_map"),
                };
            }
            Field::InputRange => "ranges.input",
            Field::OutputRange => "ranges.output",
            Field::Bias => "drive.bias",
            Field::VoltageLimits => "drive.min_voltage/max_voltage",
            Field::SlewRate => "drive.slew_rate",
            Field::SensorCalibration => "sensor.displacement_at_zero/at_full_scale",
            Field::DriftLimit => "sensor.drift_limit",
            Field::Kp => "feedback.kp",
            Field::Ki => "feedback.ki",
            Field::Kd => "feedback.kd",
            Field::DerivativeCutoff => "feedback.derivative_cutoff_hz",
            Field::FeedbackLimit => "feedback.limit",
            Field::NotchFrequency => "feedback.notch.frequency_hz",
            Field::NotchQ => "feedback.notch.q",
            Field::NotchDepth => "feedback.notch.depth",
            Field::Mode => "mode",
            Field::Sensor => "sensor",
            Field::Feedback => "feedback",
            Field::Divider => "stream divider",
            Field::WaveformFrequency => "waveform frequency",
            Field::WaveformAmplitude => "waveform offset/amplitude",
            Field::RecordCount => "record count",
            Field::RecordDecimation => "record decimation",
            Field::RecordOffset => "record offset",
            Field::RecordSignals => "record signals",
            Field::RecordPreTrigger => "record pre-trigger",
            Field::TelemetrySignals => "telemetry signals",
            Field::TelemetryDecimation => "telemetry decimation",
            Field::CoarseAxis => "coarse axis",
            Field::CoarseTarget => "coarse target (mm)",
            Field::CoarseVelocity => "coarse speed (mm/s)",
            Field::CoarseAcceleration => "coarse acceleration (mm/s²)",
            Field::LearnPeriod => "learning.period_ticks",
            Field::LearnGain => "learning.gain",
            Field::LearnCutoff => "learning.cutoff_hz",
            Field::LearnLead => "learning.lead_ticks",
            Field::LearnLimit => "learning.limit",
            Field::Workload => "the models, creep and feedback together",
            Field::ScanLines => "scan lines (raster) / turns (spiral)",
            Field::ScanPixels => "scan pixels per line",
            Field::ScanTicksPerPixel => "scan ticks per pixel",
            Field::ScanTurnaround => "scan turnaround ticks",
            Field::ScanFrequency => "scan rate (Hz: line, frame or turn rate)",
            Field::ScanCycles => "scan Lissajous cycles",
            Field::ScanAmplitude => "scan amplitude",
            Field::ScanOffset => "scan offset",
            Field::TriggerPulse => "trigger pulse ticks",
            Field::ShapingFrequency => "shaping.frequency_hz",
            Field::ShapingQ => "shaping.q",
            Field::ShapingDepth => "shaping.depth",
            Field::SequenceEdge => "sequence edge",
            Field::SequenceWindow => "sequence window",
            Field::SequenceSettle => "sequence settle ticks",
            Field::AnalogGain => "analog gain",
            Field::AnalogOffset => "analog offset",
            Field::AnalogCorner => "analog corner_hz",
            Field::AnalogLostBelow => "analog lost_below",
            Field::AnalogOverAbove => "analog over_above",
            Field::AnalogRate => "analog rate",
            Field::PreviewFrequency => "preview.frequency_hz",
            Field::PreviewDamping => "preview.damping",
        };
        f.write_str(name)
    }
}

impl core::fmt::Display for Rule {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Rule::NotFinite => write!(f, "is NaN or infinite"),
            Rule::AtLeast(x) => write!(f, "must be at least {x}"),
            Rule::Above(x) => write!(f, "must be above {x}"),
            Rule::AtMost(x) => write!(f, "must be at most {x}"),
            Rule::Below(x) => write!(f, "must be below {x}"),
            Rule::Empty => write!(f, "is empty (max must exceed min)"),
            Rule::NotIncreasing => write!(f, "must exceed the value before it"),
            Rule::NotInvertible => write!(f, "makes the model non-invertible"),
            Rule::TooMany(n) => write!(f, "has more than {n} items"),
            Rule::LengthMismatch => write!(f, "lists differ in length"),
            Rule::Required => write!(f, "is required by the mode or another setting"),
            Rule::NoHardware => write!(f, "needs hardware this board lacks"),
            Rule::BeyondFixedPoint => write!(f, "does not fit the fixed-point format"),
            Rule::Unreachable => write!(f, "leaves no drive the stacks and DAC can reach"),
            Rule::Unbounded => write!(f, "lets the model's state grow without bound"),
            Rule::NotHomed => write!(
                f,
                "is not homed (home it first: power-up and faults unhome it)"
            ),
            Rule::LimitSwitch => write!(f, "would run into an active limit switch"),
            Rule::NoOutputMap => write!(
                f,
                "takes no output_map (Bouc–Wen does; the generalised P–I is the P–I with one)"
            ),
            Rule::TickOverrun { needs, available } => write!(
                f,
                "need {needs} cycles per tick, more than the {available} the control rate leaves \
                 (use fewer operators, dead zones or creep modes, or a lower rate)"
            ),
        }
    }
}

impl core::fmt::Display for Refusal {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "{} {}", self.field, self.rule)
    }
}

impl core::error::Error for Refusal {}
