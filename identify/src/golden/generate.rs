//! Generating the vectors: the library's tick in closed loop on a sensor model, recorded.
//!
//! Each tick reads the sensor ADC code of the stage as the drive of two ticks ago left it
//! ([`twinstack::control::feedback::SENSOR_DELAY_TICKS`]: the conversion starts at the tick's trigger,
//! before the tick writes, and the ADC returns the previous conversion — the board's one
//! sample of latency), so the feedback and the observer see a stage that responds. The
//! stage is the set's [`Truth`] model (the `f64` reference, in physical units) on the left
//! stack's voltage as the DAC code puts it out, its displacement mapped onto the ADC's codes
//! by the set's sensor calibration, plus a deterministic ±2-code dither. Those codes are then
//! just recorded inputs: the replay on the board does not need the stage. The stage starts at
//! rest where the controller starts the stacks: the safe state's left-stack voltage.

use super::scenario;
use super::sets::{SetDefinition, Truth};
use crate::reference;
use anyhow::{anyhow, Context};
use twinstack::Scaling;
use twinstack_golden::{
    config_fingerprint, format::encode_record, run_tick, Recipe, TickInput, TickOutput, MAX_RECIPE,
};

/// One generated set.
#[derive(Clone, Debug)]
pub struct GeneratedSet {
    /// The definition it came from.
    pub name: &'static str,
    /// Inputs per tick (ADC codes filled in).
    pub inputs: Vec<TickInput>,
    /// Outputs per tick.
    pub outputs: Vec<TickOutput>,
    /// The encoded record.
    pub record: Vec<u8>,
}

/// The stage as the sensor sees it.
enum Stage {
    Pi(Box<reference::PrandtlIshlinskii>),
    Duhem(reference::Duhem),
}

impl Stage {
    fn at_rest(truth: &Truth, scaling: &Scaling, volts: f64) -> anyhow::Result<Self> {
        Ok(match truth {
            Truth::Pi(p) => Stage::Pi(Box::new(reference::PrandtlIshlinskii::new(
                p, scaling, volts,
            )?)),
            Truth::Duhem(d) => Stage::Duhem(reference::Duhem::new(
                d,
                scaling,
                volts,
                d.beta * volts + d.offset,
            )?),
        })
    }
    fn step(&mut self, volts: f64) -> f64 {
        match self {
            Stage::Pi(m) => m.step(volts),
            Stage::Duhem(m) => m.step(volts),
        }
    }
}

/// The sensor ADC: displacement → code, clamped to the converter's range.
fn adc_code(recipe: &Recipe, displacement: f64, dither: i64) -> u16 {
    let (Some(s), Some(bits)) = (&recipe.settings.sensor, recipe.hardware.sensor_adc_bits) else {
        // Without a sensor the tick never reads the ADC; record a steady mid-scale code.
        return 0x8000;
    };
    let full = (1u64 << bits) as f64;
    let fraction = (displacement - s.displacement_at_zero)
        / (s.displacement_at_full_scale - s.displacement_at_zero);
    let code = (fraction * full).round() as i64 + dither;
    code.clamp(0, (full as i64 - 1).min(u16::MAX as i64)) as u16
}

/// A small deterministic generator (SplitMix64) for the ADC dither.
struct Dither(u64);
impl Dither {
    fn next(&mut self) -> i64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z % 5) as i64 - 2
    }
}

/// Runs the scenario on `def` in closed loop and encodes the record.
pub fn generate(def: &SetDefinition) -> anyhow::Result<GeneratedSet> {
    let recipe = &def.recipe;
    let config = recipe
        .build()
        .map_err(|e| anyhow!("set {}: configuration refused: {e:?}", def.name))?;
    let mut controller = twinstack::services::observer::Observed::new(config);
    let hw = &recipe.hardware;
    let volts_per_code = hw.amplifier_full_scale / hw.dac_full_scale as f64;
    // The controller starts with the stacks in the safe state, where the DAC starts: the stage
    // rests at the left stack's voltage there.
    let (left, _) = controller.controller.safe_codes();
    let start = left.0 as f64 * volts_per_code;
    let mut stage = Stage::at_rest(&def.truth, &recipe.settings.ranges, start)
        .with_context(|| format!("set {}: stage model", def.name))?;
    let mut displacement = stage.step(start);
    // The conversion in the ADC's pipeline: a read returns the one started at the previous
    // tick's trigger, i.e. the stage after the write of two ticks ago.
    let mut converting = displacement;
    let mut dither = Dither(0x0060_1DE2);
    let mut inputs = scenario::timeline();
    let mut outputs = Vec::with_capacity(inputs.len());
    for input in inputs.iter_mut() {
        input.adc_code = adc_code(recipe, converting, dither.next());
        // This tick's trigger starts converting the stage as the last write left it.
        converting = displacement;
        let out = run_tick(&mut controller, input);
        displacement = stage.step(out.left as f64 * volts_per_code);
        outputs.push(out);
    }
    let mut buf = [0u8; MAX_RECIPE];
    let recipe_bytes = recipe
        .encode(&mut buf)
        .map_err(|e| anyhow!("set {}: {e:?}", def.name))?;
    let mut record = Vec::new();
    encode_record(
        def.name,
        config_fingerprint(&config),
        recipe_bytes,
        &inputs,
        &outputs,
        &mut record,
    )
    .ok_or_else(|| anyhow!("set {}: does not fit the vector format", def.name))?;
    Ok(GeneratedSet {
        name: def.name,
        inputs,
        outputs,
        record,
    })
}

/// Every set, generated, and the file that holds them all.
pub fn generate_all(defs: &[SetDefinition]) -> anyhow::Result<(Vec<GeneratedSet>, Vec<u8>)> {
    let sets = defs
        .iter()
        .map(generate)
        .collect::<anyhow::Result<Vec<_>>>()?;
    let file = sets.iter().flat_map(|s| s.record.iter().copied()).collect();
    Ok((sets, file))
}
