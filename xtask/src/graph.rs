//! `cargo xtask graph`: each crate's module graph, printed, and a failure on any cycle.
//!
//! # What counts as a layer
//!
//! A module is a layer, and so is each module inside it: the modules of one parent (the
//! crate's top-level modules, or the files of one directory such as `protocol/`) must form a
//! one-way graph. A reference from module `a::x` to module `b::y` is an edge between the two
//! children of their deepest common parent that hold them (`a -> b`), so a submodule's imports
//! count for its top-level module, and two submodules of one parent are layered among
//! themselves. A reference to an enclosing module (a submodule using its parent's items) is no
//! edge: a parent is below the children it declares.
//!
//! A reference is a `use` of a `crate::`, `super::` or `self::` path, or of a child module by
//! name, and a `crate::` / `super::` path written in code. Comments (doc links included) and
//! `#[cfg(test)]` modules are left out: the graph is the product's. A path to an item the
//! parent re-exports (`crate::PiParams` for `pub use prandtl_ishlinskii::PiParams`) counts as
//! a reference to the module that defines it.
//!
//! No parser dependency: the module tree comes from the file layout (`foo.rs`, `foo/mod.rs`,
//! `foo/bar.rs`), and paths from the source text with comments, strings and test modules
//! stripped. Inline `mod x { … }` blocks other than tests count as their file's module.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The crates checked: name and source directory, relative to the workspace root. Each
/// library's binaries (`src/main.rs` beside a `lib.rs`, `src/bin/`) are thin shells over it
/// and are not read; the QEMU test images are binaries only.
pub const CRATES: &[(&str, &str)] = &[
    ("twinstack", "src"),
    ("twinstack-link", "link/src"),
    ("twinstack-identify", "identify/src"),
    ("hal-sim", "hal-sim/src"),
    ("twinstack-cli", "cli/src"),
    ("twinstack-golden", "golden/src"),
    ("xtask", "xtask/src"),
];

/// A module path inside its crate (`[]` is the crate root).
type ModPath = Vec<String>;

/// One crate's modules and the references between them.
pub struct CrateGraph {
    /// Every module, with the modules it refers to (each a full path).
    pub refs: BTreeMap<ModPath, BTreeSet<ModPath>>,
}

/// A cycle among the children of one parent.
#[derive(Debug, PartialEq, Eq)]
pub struct Cycle {
    /// The parent module (`crate` for the top level).
    pub parent: String,
    /// The children on the cycle, in order (the first repeated at the end).
    pub path: Vec<String>,
}

/// Reads the crate whose sources are under `src`.
pub fn read_crate(src: &Path) -> Result<CrateGraph, String> {
    let mut files = BTreeMap::new();
    collect(src, src, &mut files)?;
    let modules: BTreeSet<ModPath> = files.keys().cloned().collect();
    let mut texts = BTreeMap::new();
    for (module, file) in &files {
        let text = std::fs::read_to_string(file)
            .map_err(|e| format!("{}: cannot read: {e}", file.display()))?;
        texts.insert(
            module.clone(),
            strip_tests(&strip_comments_and_strings(&text)),
        );
    }
    // `pub use` re-exports: (module, name) -> the module the item comes from.
    let mut reexports: BTreeMap<(ModPath, String), ModPath> = BTreeMap::new();
    for (module, text) in &texts {
        for (is_pub, tree) in use_trees(text) {
            if !is_pub {
                continue;
            }
            for path in expand_use(&tree) {
                let Some(last) = path.last() else { continue };
                let name = if last == "self" {
                    path.get(path.len().wrapping_sub(2))
                        .cloned()
                        .unwrap_or_default()
                } else {
                    last.clone()
                };
                if let Some(target) = resolve(&path, module, &modules, &BTreeMap::new()) {
                    if &target != module {
                        reexports.insert((module.clone(), name), target);
                    }
                }
            }
        }
    }
    let mut refs = BTreeMap::new();
    for (module, text) in &texts {
        let mut to = BTreeSet::new();
        for (_, tree) in use_trees(text) {
            for path in expand_use(&tree) {
                to.extend(resolve(&path, module, &modules, &reexports));
            }
        }
        for path in code_paths(text) {
            to.extend(resolve(&path, module, &modules, &reexports));
        }
        to.remove(module);
        refs.insert(module.clone(), to);
    }
    Ok(CrateGraph { refs })
}

/// The modules under `dir` (`src` is the crate's root directory), each with its file.
fn collect(src: &Path, dir: &Path, files: &mut BTreeMap<ModPath, PathBuf>) -> Result<(), String> {
    let entries =
        std::fs::read_dir(dir).map_err(|e| format!("{}: cannot list: {e}", dir.display()))?;
    for entry in entries {
        let path = entry
            .map_err(|e| format!("{}: cannot list: {e}", dir.display()))?
            .path();
        if path.is_dir() {
            // `src/bin/` holds binaries: separate crates, each its own root.
            if path.strip_prefix(src).map(|p| p == Path::new("bin")) == Ok(true) {
                continue;
            }
            collect(src, &path, files)?;
        } else if path.extension().is_some_and(|e| e == "rs") {
            let rel = path.strip_prefix(src).unwrap_or(&path).with_extension("");
            let mut module: ModPath = rel
                .components()
                .map(|c| c.as_os_str().to_string_lossy().into_owned())
                .collect();
            match module.last().map(String::as_str) {
                Some("mod") => {
                    module.pop();
                }
                Some("lib") if module.len() == 1 => module.clear(),
                Some("main") if module.len() == 1 => {
                    if src.join("lib.rs").is_file() {
                        continue;
                    }
                    module.clear();
                }
                _ => {}
            }
            files.insert(module, path);
        }
    }
    Ok(())
}

/// `text` with comments, string and character literals blanked (their line breaks kept).
fn strip_comments_and_strings(text: &str) -> String {
    let b: Vec<char> = text.chars().collect();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    while i < b.len() {
        let c = b[i];
        let next = b.get(i + 1).copied();
        if c == '/' && next == Some('/') {
            while i < b.len() && b[i] != '\n' {
                i += 1;
            }
        } else if c == '/' && next == Some('*') {
            let mut depth = 0;
            while i < b.len() {
                if b[i] == '/' && b.get(i + 1) == Some(&'*') {
                    depth += 1;
                    i += 2;
                } else if b[i] == '*' && b.get(i + 1) == Some(&'/') {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    if b[i] == '\n' {
                        out.push('\n');
                    }
                    i += 1;
                }
            }
        } else if c == 'r' && (next == Some('"') || next == Some('#')) && !ident_before(&b, i) {
            // A raw string: r"…", r#"…"#, …
            let mut j = i + 1;
            let mut hashes = 0;
            while b.get(j) == Some(&'#') {
                hashes += 1;
                j += 1;
            }
            if b.get(j) != Some(&'"') {
                out.push(c);
                i += 1;
                continue;
            }
            j += 1;
            loop {
                match b.get(j) {
                    None => break,
                    Some('"') if (0..hashes).all(|k| b.get(j + 1 + k) == Some(&'#')) => {
                        j += 1 + hashes;
                        break;
                    }
                    Some('\n') => out.push('\n'),
                    _ => {}
                }
                j += 1;
            }
            out.push_str("\"\"");
            i = j;
        } else if c == '"' {
            i += 1;
            while i < b.len() && b[i] != '"' {
                if b[i] == '\\' {
                    i += 1;
                } else if b[i] == '\n' {
                    out.push('\n');
                }
                i += 1;
            }
            i += 1;
            out.push_str("\"\"");
        } else if c == '\'' {
            // A character literal ('x', '\n', '\u{..}'), or a lifetime ('a), left as it is.
            if next == Some('\\') {
                let mut j = i + 2;
                while j < b.len() && b[j] != '\'' {
                    j += 1;
                }
                i = j + 1;
                out.push_str("' '");
            } else if b.get(i + 2) == Some(&'\'') {
                i += 3;
                out.push_str("' '");
            } else {
                out.push(c);
                i += 1;
            }
        } else {
            out.push(c);
            i += 1;
        }
    }
    out
}

fn ident_before(b: &[char], i: usize) -> bool {
    i > 0 && (b[i - 1].is_alphanumeric() || b[i - 1] == '_')
}

/// `text` without its `#[cfg(test)]` modules (`#[cfg(test)] mod name { … }`).
fn strip_tests(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while let Some(at) = rest.find("#[cfg(test)]") {
        out.push_str(&rest[..at]);
        let after = &rest[at + "#[cfg(test)]".len()..];
        let trimmed = after.trim_start();
        let is_mod = trimmed.starts_with("mod ") || trimmed.starts_with("pub mod ");
        let open = trimmed.find(['{', ';']);
        match (is_mod, open) {
            (true, Some(o)) if trimmed.as_bytes()[o] == b'{' => {
                let body = &trimmed[o..];
                let mut depth = 0usize;
                let mut end = body.len();
                for (k, ch) in body.char_indices() {
                    match ch {
                        '{' => depth += 1,
                        '}' => {
                            depth -= 1;
                            if depth == 0 {
                                end = k + 1;
                                break;
                            }
                        }
                        _ => {}
                    }
                }
                rest = &body[end..];
            }
            _ => {
                // A test-only item other than a module: its `use`s are test-only too.
                rest = after;
                if let Some(semi) = trimmed.strip_prefix("use ").and_then(|u| u.find(';')) {
                    rest = &trimmed["use ".len() + semi + 1..];
                }
            }
        }
    }
    out.push_str(rest);
    out
}

/// The `use` trees of `text` (the text between `use` and `;`), each with whether it is `pub`.
fn use_trees(text: &str) -> Vec<(bool, String)> {
    let mut trees = Vec::new();
    let bytes = text.as_bytes();
    let mut from = 0;
    while let Some(at) = text[from..].find("use ") {
        let at = from + at;
        from = at + 4;
        let starts_word =
            at == 0 || !(bytes[at - 1].is_ascii_alphanumeric() || bytes[at - 1] == b'_');
        if !starts_word {
            continue;
        }
        let Some(end) = text[from..].find(';') else {
            break;
        };
        let before = text[..at].trim_end();
        let is_pub = before.ends_with("pub") || before.ends_with(')') && before.contains("pub(");
        let tree: Vec<&str> = text[from..from + end].split_whitespace().collect();
        trees.push((is_pub, tree.join(" ")));
        from += end + 1;
    }
    trees
}

/// The paths a use tree names: `a::{b, c::{d, e}}` -> `a::b`, `a::c::d`, `a::c::e`.
fn expand_use(tree: &str) -> Vec<Vec<String>> {
    fn go(prefix: &[String], tree: &str, out: &mut Vec<Vec<String>>) {
        let tree = tree.trim();
        if let Some(open) = tree.find('{') {
            let head: Vec<String> = split_path(&tree[..open]);
            let mut base = prefix.to_vec();
            base.extend(head);
            let inner = tree[open + 1..]
                .strip_suffix('}')
                .unwrap_or(&tree[open + 1..]);
            let mut depth = 0;
            let mut start = 0;
            for (k, ch) in inner.char_indices() {
                match ch {
                    '{' => depth += 1,
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        go(&base, &inner[start..k], out);
                        start = k + 1;
                    }
                    _ => {}
                }
            }
            go(&base, &inner[start..], out);
        } else {
            let tree = tree.split(" as ").next().unwrap_or(tree);
            let mut path = prefix.to_vec();
            path.extend(split_path(tree));
            if !path.is_empty() {
                out.push(path);
            }
        }
    }
    let mut out = Vec::new();
    go(&[], tree, &mut out);
    out
}

fn split_path(s: &str) -> Vec<String> {
    s.split("::")
        .map(|p| p.trim().trim_start_matches("r#").to_string())
        .filter(|p| !p.is_empty())
        .collect()
}

/// The `crate::…`, `super::…` and `self::…` paths written in code (outside `use`).
fn code_paths(text: &str) -> Vec<Vec<String>> {
    let mut paths = Vec::new();
    let chars: Vec<char> = text.chars().collect();
    let mut i = 0;
    while i < chars.len() {
        let starts_word = i == 0
            || !(chars[i - 1].is_alphanumeric() || chars[i - 1] == '_' || chars[i - 1] == ':');
        if starts_word && chars[i].is_alphabetic() {
            let mut j = i;
            let mut path = String::new();
            while j < chars.len()
                && (chars[j].is_alphanumeric() || chars[j] == '_' || chars[j] == ':')
            {
                path.push(chars[j]);
                j += 1;
            }
            let parts = split_path(&path);
            if parts.len() > 1 && matches!(parts[0].as_str(), "crate" | "super") {
                paths.push(parts);
            }
            i = j;
        } else {
            i += 1;
        }
    }
    paths
}

/// The module `path` (as written in `from`) refers to, if it is one of this crate's: the
/// deepest module it names, or the module an item it names is re-exported from.
fn resolve(
    path: &[String],
    from: &ModPath,
    modules: &BTreeSet<ModPath>,
    reexports: &BTreeMap<(ModPath, String), ModPath>,
) -> Option<ModPath> {
    let mut at: ModPath;
    let mut rest = path;
    match path.first().map(String::as_str) {
        Some("crate") => {
            at = Vec::new();
            rest = &path[1..];
        }
        Some("self") => {
            at = from.clone();
            rest = &path[1..];
        }
        Some("super") => {
            at = from.clone();
            while rest.first().map(String::as_str) == Some("super") {
                at.pop()?;
                rest = &rest[1..];
            }
        }
        Some(first) => {
            // A child module of `from`, named without `self::` (2018 paths).
            let mut child = from.clone();
            child.push(first.to_string());
            if !modules.contains(&child) {
                return None;
            }
            at = from.clone();
        }
        None => return None,
    }
    for (k, seg) in rest.iter().enumerate() {
        let mut next = at.clone();
        next.push(seg.clone());
        if modules.contains(&next) {
            at = next;
        } else if let Some(target) = reexports.get(&(at.clone(), seg.clone())) {
            // Followed once: a re-export of a re-export resolves to the first one's module.
            let _ = k;
            return Some(target.clone());
        } else {
            break;
        }
    }
    Some(at)
}

/// The edges among the children of each parent: `parent -> {child -> {sibling it uses}}`.
pub fn layered_edges(g: &CrateGraph) -> BTreeMap<ModPath, BTreeMap<String, BTreeSet<String>>> {
    let mut layers: BTreeMap<ModPath, BTreeMap<String, BTreeSet<String>>> = BTreeMap::new();
    for (from, tos) in &g.refs {
        for to in tos {
            let common = from.iter().zip(to).take_while(|(a, b)| a == b).count();
            // `to` encloses `from` (a parent's items), or the other way: no sibling edge.
            if common == from.len() || common == to.len() {
                continue;
            }
            let parent = from[..common].to_vec();
            layers
                .entry(parent)
                .or_default()
                .entry(from[common].clone())
                .or_default()
                .insert(to[common].clone());
        }
    }
    layers
}

/// Every cycle among siblings (one per strongly connected group, as a path through it).
pub fn cycles(g: &CrateGraph) -> Vec<Cycle> {
    let mut found = Vec::new();
    for (parent, edges) in layered_edges(g) {
        let mut reported: BTreeSet<String> = BTreeSet::new();
        for start in edges.keys() {
            if reported.contains(start) {
                continue;
            }
            if let Some(path) = cycle_from(start, &edges) {
                reported.extend(path.iter().cloned());
                found.push(Cycle {
                    parent: if parent.is_empty() {
                        "crate".into()
                    } else {
                        parent.join("::")
                    },
                    path,
                });
            }
        }
    }
    found
}

/// A shortest cycle back to `start`, if there is one (breadth-first).
fn cycle_from(start: &str, edges: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    let mut came_from: BTreeMap<String, String> = BTreeMap::new();
    let mut queue = std::collections::VecDeque::from([start.to_string()]);
    while let Some(at) = queue.pop_front() {
        for next in edges.get(&at).into_iter().flatten() {
            if next == start {
                let mut path = vec![start.to_string()];
                let mut back = at.clone();
                let mut rev = Vec::new();
                while back != start {
                    rev.push(back.clone());
                    back = came_from.get(&back)?.clone();
                }
                path.extend(rev.into_iter().rev());
                path.push(start.to_string());
                return Some(path);
            }
            if next != start && !came_from.contains_key(next) {
                came_from.insert(next.clone(), at.clone());
                queue.push_back(next.clone());
            }
        }
    }
    None
}

/// `cargo xtask graph`: prints each crate's layered graph and fails on any cycle.
pub fn run(root: &Path, quiet: bool) -> Result<(), String> {
    let mut problems = Vec::new();
    for (name, dir) in CRATES {
        let g = read_crate(&root.join(dir))?;
        if !quiet {
            println!("{name}:");
            for (parent, edges) in layered_edges(&g) {
                let parent = if parent.is_empty() {
                    "crate".to_string()
                } else {
                    parent.join("::")
                };
                for (from, tos) in edges {
                    let tos: Vec<&str> = tos.iter().map(String::as_str).collect();
                    println!("  {parent}: {from} -> {}", tos.join(", "));
                }
            }
        }
        for c in cycles(&g) {
            problems.push(format!(
                "{name}: a cycle among the modules of {}: {}",
                c.parent,
                c.path.join(" -> ")
            ));
        }
    }
    if problems.is_empty() {
        println!("module graph: no cycles in {} crates", CRATES.len());
        Ok(())
    } else {
        Err(format!(
            "{} module cycle(s) (break each by moving what both sides use into the lower \
             module):\n  {}",
            problems.len(),
            problems.join("\n  ")
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn graph(files: &[(&str, &str)]) -> CrateGraph {
        let dir = std::env::temp_dir().join(format!(
            "xtask-graph-{}-{}",
            std::process::id(),
            files.len() * 31 + files.iter().map(|f| f.1.len()).sum::<usize>()
        ));
        let _ = std::fs::remove_dir_all(&dir);
        for (path, text) in files {
            let p = dir.join(path);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(p, text).unwrap();
        }
        let g = read_crate(&dir).unwrap();
        let _ = std::fs::remove_dir_all(&dir);
        g
    }

    #[test]
    fn a_cycle_through_a_submodule_and_a_reexport_is_found() {
        let g = graph(&[
            ("lib.rs", "pub mod a;\npub mod b;\npub use a::Thing;\n"),
            (
                "a.rs",
                "pub struct Thing;\nfn f() { crate::b::inner::g(); }\n",
            ),
            ("b/mod.rs", "pub mod inner;\n"),
            // Comments and strings do not count; the re-exported name does.
            (
                "b/inner.rs",
                "// use crate::a;\nconst S: &str = \"crate::a\";\nuse crate::{Thing as T};\n",
            ),
        ]);
        assert_eq!(
            cycles(&g),
            vec![Cycle {
                parent: "crate".into(),
                path: vec!["a".into(), "b".into(), "a".into()],
            }]
        );
    }

    #[test]
    fn a_one_way_graph_parents_and_test_modules_make_no_cycle() {
        let g = graph(&[
            ("lib.rs", "pub mod a;\npub mod b;\n"),
            ("a.rs", "use crate::b::{self, B};\n"),
            // A child using its parent's items, and a test module using anything.
            ("b/mod.rs", "pub mod c;\npub struct B;\n"),
            ("b/c.rs", "use super::B;\n#[cfg(test)]\nmod tests {\n    use crate::a;\n    fn f() { let _ = '{'; }\n}\n"),
        ]);
        assert_eq!(cycles(&g), vec![]);
        let layers = layered_edges(&g);
        assert_eq!(layers[&vec![]]["a"], BTreeSet::from(["b".to_string()]));
    }

    #[test]
    fn siblings_inside_a_directory_are_layered_too() {
        let g = graph(&[
            ("lib.rs", "mod p;\n"),
            ("p/mod.rs", "mod x;\nmod y;\n"),
            ("p/x.rs", "use super::y::Y;\npub struct X;\n"),
            ("p/y.rs", "pub struct Y(super::x::X);\n"),
        ]);
        let c = cycles(&g);
        assert_eq!(c.len(), 1);
        assert_eq!(c[0].parent, "p");
    }
}
