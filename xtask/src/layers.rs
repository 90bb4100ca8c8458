//! The host crates' layering, read from their manifests: each crate depends only on crates
//! below it (`cargo xtask graph` checks it beside the module graph, so `cargo xtask test`
//! does).
//!
//! From the bottom: the `no_std` library and its golden vectors; the board link and the
//! host's files; identification, calibration and tuning with the `f64` reference; the
//! simulated board and stage; the Python package; the command-line tool. A crate that reached
//! up (identification into the simulator, the simulator into the CLI, the Python package into
//! the CLI) would pull the layer above, and its dependencies, into everything under it.

use std::path::Path;

/// The layers, bottom first: package name, manifest (relative to the workspace root) and
/// layer. A crate may depend (normal, build or dev) on the crates of lower layers only; the
/// library and its golden vectors are one layer (the vectors' crate is written against the
/// library, whose tests replay them).
pub const LAYERS: &[(&str, &str, usize)] = &[
    ("twinstack", "Cargo.toml", 0),
    ("twinstack-golden", "golden/Cargo.toml", 0),
    ("twinstack-link", "link/Cargo.toml", 1),
    ("twinstack-identify", "identify/Cargo.toml", 2),
    ("hal-sim", "hal-sim/Cargo.toml", 3),
    ("twinstack-python", "python/Cargo.toml", 4),
    ("twinstack-cli", "cli/Cargo.toml", 5),
];

/// The packages a manifest's dependency tables name by `path` (the workspace's own crates),
/// by package name (`package = "…"` when the key renames it). Read line by line: inline
/// tables (`name = { path = "…" }`) and `[dependencies.name]` tables with a `path` key.
pub fn path_dependencies(manifest: &str) -> Vec<String> {
    let mut deps = Vec::new();
    let mut in_deps = false;
    // A `[…dependencies.NAME]` table being read: its key, and its `package` if given.
    let mut table: Option<(String, Option<String>, bool)> = None;
    let flush = |table: &mut Option<(String, Option<String>, bool)>, deps: &mut Vec<String>| {
        if let Some((key, package, has_path)) = table.take() {
            if has_path {
                deps.push(package.unwrap_or(key));
            }
        }
    };
    for line in manifest.lines() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.starts_with('[') {
            flush(&mut table, &mut deps);
            let header = line.trim_matches(|c| c == '[' || c == ']');
            let parts: Vec<&str> = header.split('.').collect();
            match parts.iter().position(|p| p.ends_with("dependencies")) {
                Some(i) if i + 1 == parts.len() => in_deps = true,
                Some(i) => {
                    in_deps = false;
                    table = Some((parts[i + 1..].join("."), None, false));
                }
                None => in_deps = false,
            }
            continue;
        }
        let Some((key, value)) = line.split_once('=') else {
            continue;
        };
        let (key, value) = (key.trim(), value.trim());
        if let Some((_, package, has_path)) = table.as_mut() {
            match key {
                "path" => *has_path = true,
                "package" => *package = Some(value.trim_matches('"').to_string()),
                _ => {}
            }
        } else if in_deps && value.starts_with('{') && inline_key(value, "path").is_some() {
            deps.push(inline_key(value, "package").unwrap_or_else(|| key.to_string()));
        }
    }
    flush(&mut table, &mut deps);
    deps
}

/// The string value of `key` in an inline table `{ … }`.
fn inline_key(table: &str, key: &str) -> Option<String> {
    table
        .trim_matches(|c| c == '{' || c == '}')
        .split(',')
        .filter_map(|kv| kv.split_once('='))
        .find(|(k, _)| k.trim() == key)
        .map(|(_, v)| v.trim().trim_matches('"').to_string())
}

/// Every dependency of a layer on a crate of its own layer or above, or on a workspace crate
/// outside [`LAYERS`]: `crate -> dependency` with why. `manifests` gives each layer's text.
pub fn violations(manifests: &[(&str, String)]) -> Vec<String> {
    let rank = |name: &str| LAYERS.iter().find(|(n, ..)| *n == name).map(|l| l.2);
    let mut out = Vec::new();
    for (name, text) in manifests {
        let Some(own) = rank(name) else {
            out.push(format!(
                "{name}: not a layer (add it to xtask's layers::LAYERS)"
            ));
            continue;
        };
        for dep in path_dependencies(text) {
            if dep == *name {
                continue; // the crate itself with test features, as a dev-dependency
            }
            match rank(&dep) {
                Some(r) if r < own || (r == 0 && own == 0) => {}
                Some(_) => out.push(format!("{name} -> {dep}: depends on a layer above it")),
                None => out.push(format!("{name} -> {dep}: not a layer")),
            }
        }
    }
    out
}

/// Reads the layers' manifests under `root` and checks them.
pub fn check(root: &Path) -> Result<(), String> {
    let mut manifests = Vec::new();
    for (name, manifest, _) in LAYERS {
        let path = root.join(manifest);
        let text = std::fs::read_to_string(&path)
            .map_err(|e| format!("{}: cannot read: {e}", path.display()))?;
        manifests.push((*name, text));
    }
    let problems = violations(&manifests);
    if problems.is_empty() {
        let mut layers: Vec<String> = Vec::new();
        for (i, (name, _, layer)) in LAYERS.iter().enumerate() {
            match layers.last_mut() {
                Some(last) if i > 0 && LAYERS[i - 1].2 == *layer => {
                    last.push_str(" + ");
                    last.push_str(name);
                }
                _ => layers.push((*name).to_string()),
            }
        }
        println!(
            "crate layers: each depends only on those below it ({})",
            layers.join(" < ")
        );
        Ok(())
    } else {
        Err(format!(
            "{} dependency(ies) against the crate layering (move what the lower crate needs \
             down into it):\n  {}",
            problems.len(),
            problems.join("\n  ")
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn path_dependencies_of_every_table_kind_are_read() {
        let manifest = r#"
[package]
name = "x"
[dependencies]
twinstack = { path = "..", features = ["dual-stage"] } # comment
serde = { version = "1" }
link = { path = "../link", package = "twinstack-link" }
[target.'cfg(unix)'.dependencies]
libc = "0.2"
[dev-dependencies]
hal-sim = { path = "../hal-sim" }
[dev-dependencies.twinstack-cli]
path = "../cli"
[build-dependencies.cc]
version = "1"
"#;
        assert_eq!(
            path_dependencies(manifest),
            ["twinstack", "twinstack-link", "hal-sim", "twinstack-cli"]
        );
    }

    #[test]
    fn a_dependency_on_a_layer_above_is_refused() {
        let manifests = [
            (
                "twinstack-identify",
                "[dependencies]\nhal-sim = { path = \"../hal-sim\" }\n".to_string(),
            ),
            (
                "twinstack-python",
                "[dependencies]\ntwinstack-cli = { path = \"../cli\" }\n\
                 twinstack-link = { path = \"../link\" }\n"
                    .to_string(),
            ),
            (
                "hal-sim",
                "[dev-dependencies]\nhal-sim = { path = \".\" }\nx = { path = \"../x\" }\n"
                    .to_string(),
            ),
        ];
        assert_eq!(
            violations(&manifests),
            [
                "twinstack-identify -> hal-sim: depends on a layer above it",
                "twinstack-python -> twinstack-cli: depends on a layer above it",
                "hal-sim -> x: not a layer",
            ]
        );
    }

    #[test]
    fn the_workspace_is_layered() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        check(&root).unwrap();
    }
}
