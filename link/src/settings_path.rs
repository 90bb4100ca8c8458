//! Settings addressed by path: `/feedback/kp`, `/drive/slew_rate`, `/compensator`.
//!
//! A path is a JSON Pointer (RFC 6901) into the serde tree of the one settings type,
//! [`Settings`], as its JSON form writes it: struct fields by name, a model by its variant
//! (`/compensator/PrandtlIshlinskii/weights/3`), list entries by index. The same path reads
//! and writes the settings on a board (`twinstack get` / `twinstack set`, Python's
//! `Board.get` / `Board.set`) and in a parameter file's `settings` (`--file`).
//!
//! Nothing here knows any setting by name: the tree is the type's serde derive, and the
//! schema ([`schema`]) is traced from the same derive, so a setting added to `Settings` (or
//! to its part's own settings type) is addressable, listed and checked without a line here,
//! in the protocol, in the command-line tool or in Python. A write changes one value and
//! rebuilds the whole settings from the result, so a path that names nothing, a value of the
//! wrong type or a field the type does not have is refused here with the path; what the
//! values mean (ranges, limits, the tick budget) is checked by the board, which validates,
//! prepares and swaps the whole settings as for any load.

use serde_json::Value;
use serde_reflection::{
    ContainerFormat, Format, Registry, Samples, Tracer, TracerConfig, VariantFormat,
};
use twinstack::config::settings::{Model, Settings};

/// Why a path could not be read or written.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum PathError {
    /// The path does not start with `/` (a JSON Pointer's form).
    #[error("`{path}`: a settings path starts with `/` (for example /feedback/kp)")]
    NotAPath {
        /// The text given.
        path: String,
    },
    /// A segment of the path names nothing in the settings.
    #[error("`{path}`: `{at}` has no `{segment}`{choices}")]
    NoSuchSetting {
        /// The whole path.
        path: String,
        /// The part of the path that exists (`/` for the root).
        at: String,
        /// The segment that names nothing there.
        segment: String,
        /// What `at` does hold, to choose from (empty when it holds a single value).
        choices: String,
    },
    /// A part of the path is not set (`null`): its fields do not exist until it is.
    #[error(
        "`{path}`: `{at}` is not set; set it whole first (for example `set {at} '{{…}}'`, \
         the form `twinstack settings --schema` lists)"
    )]
    Absent {
        /// The whole path.
        path: String,
        /// The unset part.
        at: String,
    },
    /// The settings with the new value are not settings: a wrong type, a missing or an
    /// unknown field.
    #[error("`{path}` = {value}: {reason}")]
    Invalid {
        /// The path written.
        path: String,
        /// The value, as JSON.
        value: String,
        /// Why the result is not settings (serde's message).
        reason: String,
    },
}

/// The path's segments, unescaped (`~1` is `/`, `~0` is `~`); the root `""` or `/` has none.
fn segments(path: &str) -> Result<Vec<String>, PathError> {
    if path.is_empty() || path == "/" {
        return Ok(Vec::new());
    }
    let Some(rest) = path.strip_prefix('/') else {
        return Err(PathError::NotAPath {
            path: path.to_string(),
        });
    };
    Ok(rest
        .split('/')
        .map(|s| s.replace("~1", "/").replace("~0", "~"))
        .collect())
}

/// The value at `path` under `root`, or the error naming the first segment that is missing.
fn walk<'a>(root: &'a Value, path: &str) -> Result<&'a Value, PathError> {
    let mut here = root;
    let mut at = String::new();
    for segment in segments(path)? {
        let next = match here {
            Value::Object(map) => map.get(&segment),
            Value::Array(items) => segment.parse::<usize>().ok().and_then(|i| items.get(i)),
            Value::Null => {
                return Err(PathError::Absent {
                    path: path.to_string(),
                    at: if at.is_empty() { "/".into() } else { at },
                })
            }
            _ => None,
        };
        let Some(next) = next else {
            return Err(PathError::NoSuchSetting {
                path: path.to_string(),
                at: if at.is_empty() { "/".into() } else { at },
                segment,
                choices: choices(here),
            });
        };
        at.push('/');
        at.push_str(&segment.replace('~', "~0").replace('/', "~1"));
        here = next;
    }
    Ok(here)
}

fn choices(value: &Value) -> String {
    match value {
        Value::Object(map) => format!(
            " (it has: {})",
            map.keys()
                .map(String::as_str)
                .collect::<Vec<_>>()
                .join(", ")
        ),
        Value::Array(items) if items.is_empty() => " (it is an empty list)".to_string(),
        Value::Array(items) => format!(" (it is a list of {}: 0…{})", items.len(), items.len() - 1),
        _ => String::new(),
    }
}

/// The settings' value at `path`, as JSON (a number, a string, a list, an object, or `null`
/// for a part that is not set).
///
/// ```
/// use twinstack::config::settings::{Model, Settings};
/// use twinstack_link::settings_path;
///
/// let settings = Settings::default();
/// let slew = settings_path::get(&settings, "/drive/slew_rate").unwrap();
/// assert_eq!(slew, serde_json::json!(settings.drive.slew_rate));
/// assert!(settings_path::get(&settings, "/drive/slew").is_err());
/// ```
pub fn get(settings: &Settings, path: &str) -> Result<Value, PathError> {
    let tree = serde_json::to_value(settings).expect("settings serialize to JSON");
    walk(&tree, path).cloned()
}

/// `settings` with the value at `path` replaced by `value`: the whole settings rebuilt from
/// the result, so that a wrong type, or a field the type does not have, is refused here
/// (naming the path). The meaning of the values is the board's to check when it loads them.
///
/// ```
/// use twinstack::config::settings::{Model, Settings};
/// use twinstack_link::settings_path;
///
/// let settings = Settings::default();
/// let faster = settings_path::set(&settings, "/drive/slew_rate", serde_json::json!(2.5)).unwrap();
/// assert_eq!(faster.drive.slew_rate, 2.5);
/// assert!(settings_path::set(&settings, "/drive/slew_rate", serde_json::json!("fast")).is_err());
/// ```
pub fn set(settings: &Settings, path: &str, value: Value) -> Result<Settings, PathError> {
    let mut tree = serde_json::to_value(settings).expect("settings serialize to JSON");
    let segments = segments(path)?;
    let Some((last, parents)) = segments.split_last() else {
        return rebuild(value, path, None);
    };
    let parent_path: String = parents
        .iter()
        .map(|s| format!("/{}", s.replace('~', "~0").replace('/', "~1")))
        .collect();
    walk(&tree, &parent_path)?;
    let parent = tree
        .pointer_mut(&parent_path)
        .expect("walk found the parent");
    let shown = value.to_string();
    let text = value.as_str().map(str::to_string);
    match parent {
        Value::Object(map) => {
            if !map.contains_key(last) {
                return Err(PathError::NoSuchSetting {
                    path: path.to_string(),
                    at: if parent_path.is_empty() {
                        "/".into()
                    } else {
                        parent_path
                    },
                    segment: last.clone(),
                    choices: choices(&Value::Object(map.clone())),
                });
            }
            map.insert(last.clone(), value);
        }
        Value::Array(items) => match last.parse::<usize>() {
            Ok(i) if i < items.len() => items[i] = value,
            _ => {
                let choices = choices(&Value::Array(items.clone()));
                return Err(PathError::NoSuchSetting {
                    path: path.to_string(),
                    at: parent_path,
                    segment: last.clone(),
                    choices,
                });
            }
        },
        Value::Null => {
            return Err(PathError::Absent {
                path: path.to_string(),
                at: parent_path,
            })
        }
        _ => {
            return Err(PathError::NoSuchSetting {
                path: path.to_string(),
                at: parent_path,
                segment: last.clone(),
                choices: String::new(),
            })
        }
    }
    rebuild(tree, path, Some(shown)).map_err(|e| meant_as_json(e, text.as_deref()))
}

/// A text value that was meant as JSON (an object, a list, a number, NaN or infinity) but is
/// not JSON, and so was taken as a string the setting does not take: the error says what the
/// JSON reader found, where it said "invalid type: string".
fn meant_as_json(e: PathError, text: Option<&str>) -> PathError {
    let Some(text) = text else { return e };
    let t = text.trim();
    let meant = t.starts_with(['{', '[', '-', '+', '.'])
        || t.starts_with(|c: char| c.is_ascii_digit())
        || ["nan", "inf", "infinity", "-inf"].contains(&t.to_ascii_lowercase().as_str());
    match (e, serde_json::from_str::<Value>(t)) {
        (PathError::Invalid { path, reason, .. }, Err(json))
            if meant && reason.starts_with("invalid type: string") =>
        {
            PathError::Invalid {
                path,
                value: text.to_string(),
                reason: format!(
                    "not JSON ({json}): a setting takes a JSON value (a finite number, a list, an object; no NaN or infinity)"
                ),
            }
        }
        (e, _) => e,
    }
}

fn rebuild(tree: Value, path: &str, shown: Option<String>) -> Result<Settings, PathError> {
    let value = shown.unwrap_or_else(|| tree.to_string());
    serde_json::from_value(tree).map_err(|e| PathError::Invalid {
        path: path.to_string(),
        value,
        reason: e.to_string(),
    })
}

/// A value as a user types it on a command line: JSON (`0.1`, `true`, `null`, `"text"`,
/// `[1, 2]`, `{"kp": 0.1, …}`), or else the text itself as a string (`ClosedLoop`).
pub fn parse_value(text: &str) -> Value {
    serde_json::from_str(text).unwrap_or_else(|_| Value::String(text.to_string()))
}

/// Rounds of tracing the schema may take to learn the settings' enums (see [`schema`]);
/// passes of deserialization a round may take to trace every variant.
const TRACE_ROUNDS: usize = 8;
const TRACE_PASSES: usize = 64;

/// The settings' serde formats, or the enums left incomplete (to be named next round).
fn trace_settings(enums: &[String]) -> Result<Registry, Vec<String>> {
    let mut tracer = Tracer::new(TracerConfig::default());
    // The models are traced on their own first: the passes over the settings reach a
    // model's enum through a list and an option, and explore only its first variant there.
    if let Err(e) = tracer.trace_simple_type::<Model>() {
        panic!("the model type is plain serde, it traces: {e}");
    }
    let samples = Samples::new();
    for _ in 0..TRACE_PASSES {
        if tracer.trace_type_once::<Settings>(&samples).is_err() {
            break;
        }
        let mut incomplete = false;
        for name in enums {
            incomplete |= tracer.check_incomplete_enum(name).is_some();
        }
        if !incomplete {
            break;
        }
    }
    match tracer.registry() {
        Ok(registry) => Ok(registry),
        Err(serde_reflection::Error::MissingVariants(names)) => Err(names),
        Err(e) => panic!("the settings type is plain serde, it traces: {e}"),
    }
}

/// One line of the schema: a path and what it holds.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
pub struct SchemaEntry {
    /// The path, with `N` for a list index.
    pub path: String,
    /// What the value is: `f64`, `u32`, `bool`, `one of A, B`, `list of f64`, …; `optional`
    /// when `null` unsets it.
    pub kind: String,
}

/// Every path the settings have, traced from the settings type's serde derive: struct
/// fields by name, each variant of a model under its name, `N` for a list index. A part that
/// may be unset (`null`) is listed with `optional`, then its fields below it.
pub fn schema() -> Vec<SchemaEntry> {
    // The tracer explores an enum one variant per pass of deserialization, once told that
    // the enum is incomplete; it names the enums it left incomplete when the registry is
    // taken. So: trace with the enums known so far, learn the missing ones, start again
    // with them — found without naming any here.
    let mut enums: Vec<String> = Vec::new();
    let registry = (0..TRACE_ROUNDS)
        .find_map(|_| match trace_settings(&enums) {
            Ok(registry) => Some(registry),
            Err(missing) => {
                enums.extend(missing);
                None
            }
        })
        .expect("every variant of the settings' enums traced");
    let mut out = Vec::new();
    walk_format(
        &registry,
        &Format::TypeName("Settings".into()),
        String::new(),
        &mut out,
    );
    out
}

fn walk_format(registry: &Registry, format: &Format, path: String, out: &mut Vec<SchemaEntry>) {
    let leaf = |kind: &str, out: &mut Vec<SchemaEntry>| {
        out.push(SchemaEntry {
            path: if path.is_empty() {
                "/".into()
            } else {
                path.clone()
            },
            kind: kind.to_string(),
        })
    };
    match format {
        Format::TypeName(name) => match registry.get(name) {
            Some(ContainerFormat::Struct(fields)) => {
                for field in fields {
                    walk_format(
                        registry,
                        &field.value,
                        format!("{path}/{}", field.name),
                        out,
                    );
                }
            }
            Some(ContainerFormat::NewTypeStruct(inner)) => walk_format(registry, inner, path, out),
            Some(ContainerFormat::Enum(variants)) => {
                let unit: Vec<&str> = variants
                    .values()
                    .filter(|v| matches!(v.value, VariantFormat::Unit))
                    .map(|v| v.name.as_str())
                    .collect();
                if unit.len() == variants.len() {
                    leaf(&format!("one of {}", unit.join(", ")), out);
                } else {
                    leaf(
                        &format!(
                            "one of {}",
                            variants
                                .values()
                                .map(|v| v.name.as_str())
                                .collect::<Vec<_>>()
                                .join(", ")
                        ),
                        out,
                    );
                    for v in variants.values() {
                        let here = format!("{path}/{}", v.name);
                        match &v.value {
                            VariantFormat::NewType(inner) => {
                                walk_format(registry, inner, here, out)
                            }
                            VariantFormat::Struct(fields) => {
                                for field in fields {
                                    walk_format(
                                        registry,
                                        &field.value,
                                        format!("{here}/{}", field.name),
                                        out,
                                    );
                                }
                            }
                            _ => {}
                        }
                    }
                }
            }
            _ => leaf(name, out),
        },
        Format::Option(inner) => {
            let mut below = Vec::new();
            walk_format(registry, inner, path.clone(), &mut below);
            match below.first_mut() {
                Some(first) if first.path == path => {
                    first.kind = format!("{}, optional", first.kind)
                }
                _ => leaf("optional", out),
            }
            out.extend(below);
        }
        Format::Seq(inner) => {
            leaf(&format!("list of {}", kind_of(registry, inner)), out);
            let mut below = Vec::new();
            walk_format(registry, inner, format!("{path}/N"), &mut below);
            // A list of plain values is described by its own line.
            if below.len() > 1 || below.first().is_some_and(|e| e.path != format!("{path}/N")) {
                out.extend(below);
            }
        }
        other => leaf(&kind_of(registry, other), out),
    }
}

fn kind_of(registry: &Registry, format: &Format) -> String {
    match format {
        Format::Bool => "bool".into(),
        Format::I8 => "i8".into(),
        Format::I16 => "i16".into(),
        Format::I32 => "i32".into(),
        Format::I64 => "i64".into(),
        Format::U8 => "u8".into(),
        Format::U16 => "u16".into(),
        Format::U32 => "u32".into(),
        Format::U64 => "u64".into(),
        Format::F32 => "f32".into(),
        Format::F64 => "f64".into(),
        Format::Str => "string".into(),
        Format::Option(inner) => format!("{}, optional", kind_of(registry, inner)),
        Format::Seq(inner) => format!("list of {}", kind_of(registry, inner)),
        Format::TypeName(name) => match registry.get(name) {
            Some(ContainerFormat::Enum(v))
                if v.values().all(|v| matches!(v.value, VariantFormat::Unit)) =>
            {
                format!(
                    "one of {}",
                    v.values()
                        .map(|v| v.name.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                )
            }
            _ => name.clone(),
        },
        other => format!("{other:?}").to_lowercase(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;
    use twinstack::config::settings::{FeedbackSettings, Mode};

    fn closed_loop() -> Settings {
        Settings {
            feedback: Some(FeedbackSettings::DEFAULT),
            ..Settings::default()
        }
    }

    #[test]
    fn a_path_reads_and_writes_one_value_and_leaves_the_rest() {
        let s = closed_loop();
        assert_eq!(
            get(&s, "/feedback/kp").unwrap(),
            json!(s.feedback.unwrap().kp)
        );
        let t = set(&s, "/feedback/kp", json!(0.125)).unwrap();
        assert_eq!(t.feedback.unwrap().kp, 0.125);
        let mut back = t.clone();
        back.feedback = s.feedback;
        assert_eq!(back, s, "only kp changed");
        let m = set(&s, "/mode", parse_value("ClosedLoop")).unwrap();
        assert_eq!(m.mode, Mode::ClosedLoop);
    }

    #[test]
    fn a_wrong_path_or_value_is_refused_with_the_path() {
        let s = closed_loop();
        let e = get(&s, "/feedback/kq").unwrap_err();
        assert!(
            matches!(&e, PathError::NoSuchSetting { at, segment, choices, .. }
                if at == "/feedback" && segment == "kq" && choices.contains("kp")),
            "{e}"
        );
        assert!(matches!(
            set(&s, "/feedback/kq", json!(1.0)),
            Err(PathError::NoSuchSetting { .. })
        ));
        assert!(matches!(
            get(&s, "feedback/kp"),
            Err(PathError::NotAPath { .. })
        ));
        let e = set(&s, "/feedback/kp", json!("fast")).unwrap_err();
        assert!(e.to_string().contains("/feedback/kp"), "{e}");
        assert!(matches!(e, PathError::Invalid { .. }));
        // A value meant as JSON that is not: what the JSON reader found, not "a string".
        for text in ["NaN", "1e400", "{\"kp\": NaN}", "[1, 2"] {
            let e = set(&s, "/drive/slew_rate", parse_value(text)).unwrap_err();
            assert!(e.to_string().contains("not JSON ("), "{text}: {e}");
        }
        let e = set(&s, "/mode", parse_value("Sideways")).unwrap_err();
        assert!(matches!(e, PathError::Invalid { .. }), "{e}");
    }

    #[test]
    fn an_unset_part_is_named_before_its_fields() {
        let s = Settings::default();
        assert_eq!(s.feedback, None);
        assert_eq!(get(&s, "/feedback").unwrap(), Value::Null);
        let e = set(&s, "/feedback/kp", json!(0.1)).unwrap_err();
        assert!(
            matches!(&e, PathError::Absent { at, .. } if at == "/feedback"),
            "{e}"
        );
        // Set whole, then by field.
        let whole = serde_json::to_value(FeedbackSettings::DEFAULT).unwrap();
        let t = set(&s, "/feedback", whole).unwrap();
        let t = set(&t, "/feedback/ki", json!(0.5)).unwrap();
        assert_eq!(t.feedback.unwrap().ki, 0.5);
        // And unset again.
        assert_eq!(set(&t, "/feedback", Value::Null).unwrap().feedback, None);
    }

    /// The output map is addressed as any part: its fields once it is set, `Absent` before.
    #[test]
    fn the_output_map_is_addressed_by_its_paths() {
        use twinstack::config::settings::{representative_bouc_wen, representative_output_map};
        let unset = Settings {
            compensator: Some(representative_bouc_wen()),
            ..Settings::default()
        };
        assert_eq!(get(&unset, "/output_map").unwrap(), Value::Null);
        let e = set(&unset, "/output_map/linear", json!(1.01)).unwrap_err();
        assert!(
            matches!(&e, PathError::Absent { at, .. } if at == "/output_map"),
            "{e}"
        );
        let mapped = Settings {
            output_map: Some(representative_output_map()),
            ..unset.clone()
        };
        assert_eq!(get(&mapped, "/output_map/linear").unwrap(), json!(1.0));
        let t = set(&mapped, "/output_map/linear", json!(1.01)).unwrap();
        assert_eq!(t.output_map.as_ref().unwrap().linear, 1.01);
        let t = set(&t, "/output_map/weights/5", json!(-0.04)).unwrap();
        assert_eq!(t.output_map.as_ref().unwrap().weights[5], -0.04);
        let mut back = t.clone();
        back.output_map = mapped.output_map.clone();
        assert_eq!(back, mapped, "only the map changed");
        // Set whole from unset, and unset again.
        let whole = serde_json::to_value(representative_output_map()).unwrap();
        assert_eq!(set(&unset, "/output_map", whole).unwrap(), mapped);
        assert_eq!(
            set(&mapped, "/output_map", Value::Null).unwrap().output_map,
            None
        );
        // A field the map does not have is named.
        let e = set(&mapped, "/output_map/gain", json!(1.0)).unwrap_err();
        assert!(
            matches!(&e, PathError::NoSuchSetting { at, segment, .. }
                if at == "/output_map" && segment == "gain"),
            "{e}"
        );
        let schema = schema();
        let find = |p: &str| schema.iter().find(|e| e.path == p).map(|e| e.kind.as_str());
        assert!(find("/output_map").unwrap().contains("optional"));
        assert_eq!(find("/output_map/centre"), Some("f64"));
        assert_eq!(find("/output_map/linear"), Some("f64"));
        assert_eq!(find("/output_map/thresholds"), Some("list of f64"));
        assert_eq!(find("/output_map/weights"), Some("list of f64"));
    }

    #[test]
    fn the_schema_lists_every_path_the_settings_have() {
        let schema = schema();
        let find = |p: &str| schema.iter().find(|e| e.path == p).map(|e| e.kind.as_str());
        assert_eq!(find("/feedback/kp"), Some("f64"));
        assert_eq!(find("/drive/slew_rate"), Some("f64"));
        assert!(find("/feedback").unwrap().contains("optional"));
        assert!(find("/mode").unwrap().contains("ClosedLoop"));
        for model in ["PrandtlIshlinskii", "Duhem", "GeneralisedPi", "BoucWen"] {
            assert!(find("/compensator").unwrap().contains(model), "{model}");
            assert!(
                find(&format!("/observer/{model}")).is_some()
                    || schema
                        .iter()
                        .any(|e| e.path.starts_with(&format!("/observer/{model}/"))),
                "{model}"
            );
        }
        // Every leaf of a fully set settings tree is in the schema (list indices as N).
        let full = closed_loop();
        let tree = serde_json::to_value(&full).unwrap();
        let mut leaves = Vec::new();
        fn leaves_of(v: &Value, path: String, out: &mut Vec<String>) {
            match v {
                Value::Object(m) => m
                    .iter()
                    .for_each(|(k, v)| leaves_of(v, format!("{path}/{k}"), out)),
                Value::Array(_) => out.push(path),
                _ => out.push(path),
            }
        }
        leaves_of(&tree, String::new(), &mut leaves);
        for leaf in leaves {
            assert!(find(&leaf).is_some(), "{leaf} is not in the schema");
        }
    }
}
