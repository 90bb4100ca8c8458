//! A vector set's configuration: the board's [`Hardware`] and the one [`Settings`] type, in
//! physical units, encoded with `postcard` exactly as the wire and the flash record encode
//! settings. The host and the board decode the same bytes and build them with the same
//! library call ([`Settings::build`]), so both run the same tick.

use serde::{Deserialize, Serialize};

use twinstack::board::Hardware;
use twinstack::config::settings::{
    Settings, SettingsWithoutOutputMap, SettingsWithoutPreview, SettingsWithoutShaping,
};
use twinstack::control::ControlConfig;
use twinstack::refusal::Refusal;

/// Longest encoded recipe, bytes (two 32-operator P–I models and everything else fit).
pub const MAX_RECIPE: usize = 1536;

/// A vector set's configuration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Recipe {
    /// The board (amplifier, DAC, sensor ADC, control rate).
    pub hardware: Hardware,
    /// The settings, as a parameter load would carry them.
    pub settings: Settings,
}

/// Why a recipe could not be decoded or built.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RecipeError {
    /// The bytes are not a `postcard`-encoded recipe (or have bytes left over, or do not fit
    /// [`MAX_RECIPE`]).
    Malformed,
    /// The settings were refused on the recipe's hardware.
    Refused(Refusal),
    /// A record of a format before Bouc–Wen's `χ` holds a Bouc–Wen model, whose
    /// coefficients that format did not end with `χ`: write the file again.
    BoucWenWithoutChi,
}

impl Recipe {
    /// Encodes the recipe into `out`; returns the bytes used.
    pub fn encode<'a>(&self, out: &'a mut [u8]) -> Result<&'a [u8], RecipeError> {
        postcard::to_slice(self, out)
            .map(|b| &*b)
            .map_err(|_| RecipeError::Malformed)
    }

    /// Decodes a recipe; the whole of `bytes` must be one.
    pub fn decode(bytes: &[u8]) -> Result<Self, RecipeError> {
        match postcard::take_from_bytes::<Recipe>(bytes) {
            Ok((r, [])) => Ok(r),
            _ => Err(RecipeError::Malformed),
        }
    }

    /// Decodes a recipe of format 3, whose settings end before `shaping` (read as none).
    pub fn decode_without_shaping(bytes: &[u8]) -> Result<Self, RecipeError> {
        #[derive(Deserialize)]
        struct Old {
            hardware: Hardware,
            settings: SettingsWithoutShaping,
        }
        match postcard::take_from_bytes::<Old>(bytes) {
            Ok((r, [])) => Ok(Self {
                hardware: r.hardware,
                settings: r.settings.into(),
            }),
            _ => Err(RecipeError::Malformed),
        }
    }

    /// Decodes a recipe of formats 4 and 5, whose settings end before `preview` (read as
    /// none).
    pub fn decode_without_preview(bytes: &[u8]) -> Result<Self, RecipeError> {
        #[derive(Deserialize)]
        struct Old {
            hardware: Hardware,
            settings: SettingsWithoutPreview,
        }
        match postcard::take_from_bytes::<Old>(bytes) {
            Ok((r, [])) => Ok(Self {
                hardware: r.hardware,
                settings: r.settings.into(),
            }),
            _ => Err(RecipeError::Malformed),
        }
    }

    /// Decodes a recipe of format 6, whose settings end before `output_map` (read as none).
    pub fn decode_without_output_map(bytes: &[u8]) -> Result<Self, RecipeError> {
        #[derive(Deserialize)]
        struct Old {
            hardware: Hardware,
            settings: SettingsWithoutOutputMap,
        }
        match postcard::take_from_bytes::<Old>(bytes) {
            Ok((r, [])) => Ok(Self {
                hardware: r.hardware,
                settings: r.settings.into(),
            }),
            _ => Err(RecipeError::Malformed),
        }
    }

    /// Validates and builds the tick's configuration.
    pub fn build(&self) -> Result<ControlConfig, RecipeError> {
        self.settings
            .build(&self.hardware)
            .map_err(RecipeError::Refused)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_recipe_round_trips_and_trailing_bytes_are_refused() {
        let r = Recipe {
            hardware: Hardware::driver_board(50_000.0),
            settings: Settings::default(),
        };
        let mut buf = [0u8; MAX_RECIPE];
        let n = r.encode(&mut buf).unwrap().len();
        assert_eq!(Recipe::decode(&buf[..n]), Ok(r.clone()));
        assert_eq!(Recipe::decode(&buf[..n + 1]), Err(RecipeError::Malformed));
        assert_eq!(Recipe::decode(&buf[..n - 1]), Err(RecipeError::Malformed));
        assert!(r.build().is_ok());
        // Format 6's recipe is the same without the trailing `output_map: None` byte, format
        // 5's without `preview: None` too, format 3's without `shaping: None` too.
        assert_eq!(buf[n - 3..n], [0, 0, 0]);
        assert_eq!(
            Recipe::decode_without_output_map(&buf[..n - 1]),
            Ok(r.clone())
        );
        assert_eq!(
            Recipe::decode_without_output_map(&buf[..n]),
            Err(RecipeError::Malformed)
        );
        assert_eq!(Recipe::decode_without_preview(&buf[..n - 2]), Ok(r.clone()));
        assert_eq!(
            Recipe::decode_without_preview(&buf[..n - 1]),
            Err(RecipeError::Malformed)
        );
        assert_eq!(Recipe::decode_without_shaping(&buf[..n - 3]), Ok(r.clone()));
        assert_eq!(
            Recipe::decode_without_shaping(&buf[..n - 2]),
            Err(RecipeError::Malformed)
        );
    }

    /// A recipe with an output map round-trips and builds it; the format before the map
    /// cannot read it.
    #[test]
    fn a_recipe_with_an_output_map_round_trips() {
        use twinstack::config::settings::{representative_bouc_wen, representative_output_map};
        let r = Recipe {
            hardware: Hardware::driver_board(50_000.0),
            settings: Settings {
                compensator: Some(representative_bouc_wen()),
                observer: Some(representative_bouc_wen()),
                output_map: Some(representative_output_map()),
                ..Settings::default()
            },
        };
        let mut buf = [0u8; MAX_RECIPE];
        let n = r.encode(&mut buf).unwrap().len();
        assert_eq!(Recipe::decode(&buf[..n]), Ok(r.clone()));
        let config = r.build().unwrap();
        assert!(
            matches!(config.observer, twinstack::control::Observer::BoucWen(m) if m.has_output_map())
        );
        assert!(matches!(
            config.compensator,
            twinstack::control::Compensator::InverseBoucWen(m) if m.model().has_output_map()
        ));
        assert_eq!(
            Recipe::decode_without_output_map(&buf[..n]),
            Err(RecipeError::Malformed)
        );
    }

    /// The largest recipe fits [`MAX_RECIPE`]: two 32-operator P–I models, six creep modes,
    /// both notches, the preview and an output map of eight dead zones.
    #[test]
    fn the_largest_recipe_fits() {
        use twinstack::config::settings::{
            representative_pi, CreepParams, FeedbackSettings, Mode, SensorSettings,
        };
        use twinstack::control::notch::NotchDesign;
        use twinstack::control::preview::PreviewDesign;
        let notch = NotchDesign {
            frequency_hz: 1000.0,
            q: 2.0,
            depth: 0.1,
        };
        let mut feedback = FeedbackSettings::pi(0.1, 1000.0, 0.1);
        feedback.kd = 1e-6;
        feedback.notch = Some(notch);
        let r = Recipe {
            hardware: Hardware::driver_board(50_000.0),
            settings: Settings {
                compensator: Some(representative_pi(32).unwrap()),
                observer: Some(representative_pi(32).unwrap()),
                sensor: Some(SensorSettings {
                    displacement_at_zero: -1.5,
                    displacement_at_full_scale: 71.5,
                    drift_limit: Some(0.02),
                }),
                feedback: Some(feedback),
                mode: Mode::ClosedLoop,
                creep: Some(
                    CreepParams::new(
                        &[1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0],
                        &[0.01, 0.01, 0.01, 0.01, 0.01, 0.01],
                    )
                    .unwrap(),
                ),
                shaping: Some(notch),
                preview: Some(PreviewDesign {
                    frequency_hz: 3000.0,
                    damping: 0.05,
                }),
                output_map: Some(twinstack::config::settings::widest_output_map()),
                ..Settings::default()
            },
        };
        let mut buf = [0u8; 4096];
        let n = r.encode(&mut buf).unwrap().len();
        assert!(n <= MAX_RECIPE, "{n} bytes");
    }
}
