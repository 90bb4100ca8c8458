//! A static output map after a hysteresis model: the generalised P–I's monotone dead-zone map
//! ([`crate::models::generalised_pi`]) after the Bouc–Wen model
//! ([`crate::models::bouc_wen::BoucWen::with_output_map`]), before the creep.
//!
//! A stage's displacement is rarely the hysteresis alone: the flexure that guides it
//! stiffens at large deflection, a lever amplifies unevenly, a capacitive sensor reads
//! nonlinearly near its ends. Such a static curve after the hysteresis bends every branch
//! the same way, which a Duhem or Bouc–Wen model, whose output is linear in its state
//! (`k·u + δ + h`), describes only by distorting its loop. The map `S` takes it out:
//!
//! * forward (the observer): `drive → H → S → creep → displacement`;
//! * inverse (the compensator): `setpoint → creep⁻¹ → S⁻¹ → H⁻¹ → drive`,
//!
//! `S` between the model and the creep, where the generalised P–I has its own map (a P–I
//! with an output map *is* the generalised P–I). The model holds it (the observer applies `S`
//! to the model's output, the compensator `S⁻¹` to the desired displacement), not a wrapper
//! around every model: a map field beside the creep in the tick's dispatch made every
//! configuration's tick dearer, with a map or not (12 cycles at 5 WS in the P–I's, and the
//! services' reload, which moves the observer, over 100 a tick more in Duhem's), so only the
//! model that takes one pays for it. `S` and `S⁻¹` are [`DeadZoneBank`]s, the
//! inverse in closed form ([`DeadZoneParams::inverse`]), both built off the tick; each costs
//! one segment search and one multiply-accumulate a tick ([`DEAD_ZONE_MAP_CYCLES`]),
//! whatever the number of dead zones.
//!
//! Formats: the map's input and output are the model's signals, Q2.30 normalised by the
//! output range; its parameters are in output units ([`DeadZoneParams`]: the centre, and
//! the thresholds relative to it), normalised by the same ranges as the model's.

use crate::fixed_point::clamp_full_scale;
pub use crate::models::generalised_pi::{DeadZoneBank, DeadZoneParams, DEAD_ZONE_MAP_CYCLES};
use crate::models::params::ParamError;
use crate::scaling::Scaling;

/// A static output map `S` and its inverse, in fixed point (see the module doc).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct OutputMap {
    /// `S`: the model's output → the displacement (before the creep).
    forward: DeadZoneBank,
    /// `S⁻¹`, in closed form.
    inverse: DeadZoneBank,
}

impl OutputMap {
    /// Validates `params` (output units) and builds the map and its inverse, normalised by
    /// `scaling`'s output range. Refuses a map that is not increasing, or whose map or
    /// inverse does not fit the fixed-point formats, naming the dead zone.
    ///
    /// ```
    /// use twinstack::models::output_map::{DeadZoneParams, OutputMap};
    /// use twinstack::fixed_point::{signal_from_f64, signal_to_f64};
    /// use twinstack::Scaling;
    /// // Over 0…70 µm (centre 35 µm): 10 % flatter beyond 20 µm above the centre.
    /// let params = DeadZoneParams::new(35.0, 1.0, &[20.0], &[-0.1]).unwrap();
    /// let map = OutputMap::new(&params, &Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap()).unwrap();
    /// // 65 µm from the model: 35 + 20 + 0.9·10 = 64 µm.
    /// let y = map.forward(signal_from_f64(30.0 / 35.0));
    /// assert!((signal_to_f64(y) * 35.0 - 29.0).abs() < 1e-6);
    /// // The inverse undoes it.
    /// assert!((signal_to_f64(map.inverse(y)) * 35.0 - 30.0).abs() < 1e-6);
    /// // A map that falls is refused.
    /// let falling = DeadZoneParams::new(35.0, 1.0, &[20.0], &[-1.5]).unwrap();
    /// assert!(OutputMap::new(&falling, &Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap()).is_err());
    /// ```
    #[inline(never)] // configuration, off the tick path: one copy in flash
    pub fn new(params: &DeadZoneParams, scaling: &Scaling) -> Result<Self, ParamError> {
        let forward = params.normalized(scaling)?;
        Ok(Self {
            forward: DeadZoneBank::from_normalized(&forward)?,
            inverse: DeadZoneBank::from_normalized(&forward.inverse()?)?,
        })
    }

    /// `S` as the models hold it.
    pub(crate) fn forward_bank(&self) -> &DeadZoneBank {
        &self.forward
    }

    /// `S⁻¹` as the compensators hold it.
    pub(crate) fn inverse_bank(&self) -> &DeadZoneBank {
        &self.inverse
    }

    /// Dead zones besides the linear gain.
    pub fn dead_zones(&self) -> usize {
        self.forward.dead_zones()
    }

    /// `S`: the model's output `z` (Q2.30 normalised) → the displacement it stands for
    /// (Q2.30, rounded toward −∞ and saturated).
    #[inline(always)]
    pub fn forward(&self, z: i32) -> i32 {
        self.forward.apply(z)
    }

    /// `S⁻¹`: a desired displacement `y` (Q2.30 normalised, clamped to full scale) → what
    /// the model is to give (Q2.30, rounded toward −∞ and saturated).
    #[inline(always)]
    pub fn inverse(&self, y: i32) -> i32 {
        self.inverse.apply(clamp_full_scale(y))
    }

    /// Its cost in the tick, cycles at 5 wait states: the forward map in the observer, or
    /// the inverse in the compensator, cost the same ([`DEAD_ZONE_MAP_CYCLES`]).
    pub fn cycles(&self) -> u32 {
        DEAD_ZONE_MAP_CYCLES
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed_point::{signal_from_f64 as q, signal_to_f64 as f};

    fn scaling() -> Scaling {
        Scaling::new(0.0, 150.0, -2.0, 82.0).unwrap()
    }

    /// A flexure's stiffening: three dead zones a side, flatter toward both ends.
    fn flexure() -> DeadZoneParams {
        DeadZoneParams::new(
            40.0,
            1.03,
            &[-30.0, -20.0, -10.0, 10.0, 20.0, 30.0],
            &[-0.02, -0.02, -0.01, -0.01, -0.02, -0.03],
        )
        .unwrap()
    }

    /// The fixed-point map is the `f64` map within its gains' Q8.24 rounding, and the
    /// inverse undoes it over the whole output range within the same.
    #[test]
    fn the_map_is_its_f64_reference_and_the_inverse_undoes_it() {
        let s = scaling();
        let p = flexure();
        let map = OutputMap::new(&p, &s).unwrap();
        assert_eq!(map.dead_zones(), 6);
        let (mid, half) = (s.output_mid(), s.output_half_span());
        for k in 0..=2000 {
            let z = -1.0 + k as f64 / 1000.0;
            let y = map.forward(q(z));
            let reference = (p.apply(mid + z * half) - mid) / half;
            assert!(
                (f(y) - reference).abs() < 1e-7,
                "S({z}): {} vs {reference}",
                f(y)
            );
            // The inverse takes desired outputs within the range.
            if f(y).abs() > 1.0 {
                continue;
            }
            let back = map.inverse(y);
            assert!((f(back) - z).abs() < 2e-7, "S⁻¹(S({z})) = {}", f(back));
        }
    }

    /// A map that is not invertible, or whose inverse leaves the fixed point, is refused.
    #[test]
    fn a_map_without_a_monotone_inverse_is_refused() {
        let s = scaling();
        let falls = DeadZoneParams::new(40.0, 1.0, &[10.0], &[-1.0]).unwrap();
        assert_eq!(
            OutputMap::new(&falls, &s),
            Err(ParamError::DeadZoneSlopeNotPositive { dead_zone: 1 })
        );
        let flat = DeadZoneParams::new(40.0, 1e-3, &[], &[]).unwrap();
        assert!(
            OutputMap::new(&flat, &s).is_err(),
            "its inverse's gain is 1000"
        );
    }
}
