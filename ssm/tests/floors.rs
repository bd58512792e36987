//! The crate's floors, checked on its sources: every module of `ssm/src` imports
//! only from its own top-level module or from the floors below it (the order of
//! `ssm/src/lib.rs`'s docs), and no two files import each other, directly or
//! round a circle, beyond the few circles named in [`KNOWN_CIRCLE_EDGES`].
//!
//! An import is any `crate::` path in the code (a `use`, a path written inline,
//! a serde attribute's function path) and any `super::` path that climbs out of
//! a file's module. Comments and `#[cfg(test)]` modules (from their attribute to
//! the end of the file) are not read: a unit test may drive its module with
//! the floors above it.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// The top-level modules of `ssm`, bottom floor first. Modules on one floor may
/// not import each other.
const FLOORS: &[&[&str]] = &[
    &["util", "stats"],
    &["data"],
    &["models"],
    &["simulation"],
    &["filter"],
    &["estimators"],
    &["training"],
    &["evaluation"],
    &["criticism"],
];

/// Imports between files that close a circle and are known: `(from, to)` by
/// module path. The graph is checked for circles without them.
const KNOWN_CIRCLE_EDGES: &[(&str, &str)] = &[
    // A model error names the catalogue's extension; the catalogue (`Extension`)
    // lives with the extended model, which returns model errors.
    ("models::error", "models::extended"),
    // The diagnosis's rules, screen, judgement and report read each other's
    // types.
    ("criticism::diagnose::report", "criticism::diagnose::rules"),
    ("criticism::diagnose::report", "criticism::diagnose::judge"),
    ("criticism::diagnose::report", "criticism::diagnose::screen"),
    ("criticism::diagnose::rules", "criticism::diagnose::screen"),
    ("criticism::diagnose::unmeasured", "criticism::diagnose::pipeline"),
];

/// A module path (`["models", "extended"]`; the crate root is empty).
type Module = Vec<String>;

/// Every source file of `ssm/src`, by module path, with its code (comments and
/// test modules dropped).
fn sources() -> BTreeMap<Module, String> {
    fn walk(dir: &Path, root: &Path, out: &mut BTreeMap<Module, String>) {
        for entry in std::fs::read_dir(dir).expect("read ssm/src") {
            let path = entry.expect("a directory entry").path();
            if path.is_dir() {
                walk(&path, root, out);
            } else if path.extension().is_some_and(|e| e == "rs") {
                let rel = path.strip_prefix(root).expect("under src").with_extension("");
                let mut module: Module = rel.iter().map(|c| c.to_string_lossy().into_owned()).collect();
                if module.last().is_some_and(|l| l == "mod" || l == "lib") {
                    module.pop();
                }
                out.insert(module, code_of(&std::fs::read_to_string(&path).expect("read a source file")));
            }
        }
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut out = BTreeMap::new();
    walk(&root, &root, &mut out);
    out
}

/// The code of a source file: comment lines dropped, and everything from the
/// first `#[cfg(test)]` on.
fn code_of(text: &str) -> String {
    let mut code = String::new();
    for line in text.lines() {
        if line.starts_with("#[cfg(test)]") {
            break;
        }
        let line = match line.find("// ") {
            Some(k) if !line[..k].contains('"') => &line[..k],
            _ => line,
        };
        if !line.trim_start().starts_with("//") {
            code.push_str(line);
            code.push('\n');
        }
    }
    code
}

/// The identifier paths that follow each occurrence of `prefix` in `code`:
/// `crate::a::b::{c, d::e}` gives `a::b::c` and `a::b::d::e`.
fn paths_after(code: &str, prefix: &str) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let bytes = code.as_bytes();
    let mut from = 0;
    while let Some(k) = code[from..].find(prefix) {
        let start = from + k;
        from = start + prefix.len();
        if start > 0
            && (bytes[start - 1].is_ascii_alphanumeric() || bytes[start - 1] == b'_' || bytes[start - 1] == b':')
        {
            continue;
        }
        let rest = &code[from..];
        let mut segments = Vec::new();
        let mut i = 0;
        loop {
            let len = rest[i..].find(|c: char| !(c.is_ascii_alphanumeric() || c == '_')).unwrap_or(rest.len() - i);
            if len == 0 {
                break;
            }
            segments.push(rest[i..i + len].to_string());
            i += len;
            if rest[i..].starts_with("::{") {
                let close = rest[i..].find('}').map_or(rest.len(), |c| i + c);
                for item in rest[i + 3..close].split(',') {
                    let item: Vec<String> = item
                        .split("::")
                        .map(|s| s.trim().split_whitespace().next().unwrap_or("").to_string())
                        .filter(|s| !s.is_empty())
                        .collect();
                    out.push(segments.iter().cloned().chain(item).collect());
                }
                segments.clear();
                break;
            }
            if rest[i..].starts_with("::") {
                i += 2;
            } else {
                break;
            }
        }
        if !segments.is_empty() {
            out.push(segments);
        }
    }
    out
}

/// The file a path names: the longest prefix that is a module, followed into a
/// child module when the module re-exports the next name from it
/// (`pub use error::ModelError` in `models/mod.rs` sends `models::ModelError` to
/// `models::error`).
fn resolve(path: &[String], files: &BTreeMap<Module, String>) -> Module {
    let mut module: Module = Vec::new();
    for segment in path {
        let mut next = module.clone();
        next.push(segment.clone());
        if files.contains_key(&next) {
            module = next;
        } else {
            break;
        }
    }
    if let Some(name) = path.get(module.len()) {
        for statement in files[&module].split(';') {
            let Some(k) = statement.find("pub use ") else { continue };
            let used = &statement[k + "pub use ".len()..];
            let used = used.strip_prefix("self::").unwrap_or(used);
            let Some((child, items)) = used.split_once("::") else { continue };
            let names_it = items.split(|c: char| !(c.is_ascii_alphanumeric() || c == '_')).any(|w| w == name);
            let mut target = module.clone();
            target.push(child.to_string());
            if names_it && files.contains_key(&target) {
                return target;
            }
        }
    }
    module
}

/// Each file's imports of other files.
fn imports(files: &BTreeMap<Module, String>) -> BTreeMap<Module, BTreeSet<Module>> {
    let mut graph = BTreeMap::new();
    for (module, code) in files {
        let mut targets = BTreeSet::new();
        for path in paths_after(code, "crate::") {
            targets.insert(resolve(&path, files));
        }
        for path in paths_after(code, "super::") {
            // `super::super::x` arrives here as `super::x`: count the climbs.
            let ups = 1 + path.iter().take_while(|s| *s == "super").count();
            let rest: Vec<String> = path.iter().skip(ups - 1).cloned().collect();
            let base = &module[..module.len().saturating_sub(ups)];
            let full: Vec<String> = base.iter().cloned().chain(rest).collect();
            targets.insert(resolve(&full, files));
        }
        targets.remove(module);
        targets.remove(&Vec::new());
        graph.insert(module.clone(), targets);
    }
    graph
}

fn floor_of(top: &str) -> usize {
    FLOORS
        .iter()
        .position(|floor| floor.contains(&top))
        .unwrap_or_else(|| panic!("`{top}` is a top-level module of ssm missing from FLOORS (ssm/tests/floors.rs)"))
}

/// The imports that run back up or sideways between floors.
fn floor_violations(graph: &BTreeMap<Module, BTreeSet<Module>>) -> Vec<String> {
    let mut bad = Vec::new();
    for (from, targets) in graph {
        let Some(top) = from.first() else { continue };
        for to in targets {
            let to_top = &to[0];
            if to_top != top && floor_of(to_top) >= floor_of(top) {
                bad.push(format!("{} imports {}", from.join("::"), to.join("::")));
            }
        }
    }
    bad
}

/// The circles of the graph (strongly connected sets of more than one file).
fn circles(graph: &BTreeMap<Module, BTreeSet<Module>>) -> Vec<Vec<String>> {
    // Tarjan's algorithm.
    struct State<'g> {
        graph: &'g BTreeMap<Module, BTreeSet<Module>>,
        index: BTreeMap<&'g Module, usize>,
        low: BTreeMap<&'g Module, usize>,
        stack: Vec<&'g Module>,
        on_stack: BTreeSet<&'g Module>,
        found: Vec<Vec<String>>,
    }
    fn visit<'g>(s: &mut State<'g>, v: &'g Module) {
        let n = s.index.len();
        s.index.insert(v, n);
        s.low.insert(v, n);
        s.stack.push(v);
        s.on_stack.insert(v);
        for w in &s.graph[v] {
            let Some((w, _)) = s.graph.get_key_value(w) else { continue };
            if !s.index.contains_key(w) {
                visit(s, w);
                let low = s.low[v].min(s.low[w]);
                s.low.insert(v, low);
            } else if s.on_stack.contains(w) {
                let low = s.low[v].min(s.index[w]);
                s.low.insert(v, low);
            }
        }
        if s.low[v] == s.index[v] {
            let mut component = Vec::new();
            loop {
                let w = s.stack.pop().expect("v is on the stack");
                s.on_stack.remove(w);
                component.push(w.join("::"));
                if w == v {
                    break;
                }
            }
            if component.len() > 1 {
                component.sort();
                s.found.push(component);
            }
        }
    }
    let mut s = State {
        graph,
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        on_stack: BTreeSet::new(),
        found: Vec::new(),
    };
    for v in graph.keys() {
        if !s.index.contains_key(v) {
            visit(&mut s, v);
        }
    }
    s.found
}

fn module(path: &str) -> Module {
    path.split("::").map(String::from).collect()
}

#[test]
fn every_import_runs_down_the_floors() {
    let graph = imports(&sources());
    let bad = floor_violations(&graph);
    assert!(bad.is_empty(), "imports against the floors of ssm/src/lib.rs:\n{}", bad.join("\n"));
}

#[test]
fn no_circles_between_files_beyond_the_known_ones() {
    let mut graph = imports(&sources());
    for (from, to) in KNOWN_CIRCLE_EDGES {
        if let Some(targets) = graph.get_mut(&module(from)) {
            targets.remove(&module(to));
        }
    }
    let found = circles(&graph);
    assert!(found.is_empty(), "files that import each other (round a circle): {found:?}");
}

#[test]
fn the_floors_name_every_top_level_module() {
    let files = sources();
    let tops: BTreeSet<&str> = files.keys().filter_map(|m| m.first()).map(String::as_str).collect();
    for top in &tops {
        floor_of(top);
    }
    let listed: BTreeSet<&str> = FLOORS.iter().flat_map(|f| f.iter().copied()).collect();
    assert_eq!(listed, tops, "FLOORS lists exactly the top-level modules");
}

/// The check itself: an import of the metrics from the data, a circle of two
/// files and a re-export followed to its file are all seen.
#[test]
fn the_check_sees_what_it_must() {
    let mut files: BTreeMap<Module, String> = BTreeMap::new();
    files.insert(vec![], "pub mod data;\npub mod evaluation;\npub mod models;\n".into());
    files.insert(module("data"), "pub mod kitti;\n".into());
    files.insert(module("data::kitti"), code_of("// use crate::evaluation::metrics::x;\nuse crate::evaluation::metrics::{heading_reversals, HeadingReversals};\n"));
    files.insert(module("evaluation"), "pub mod metrics;\n".into());
    files.insert(module("evaluation::metrics"), "use crate::data::Dataset;\n".into());
    files.insert(module("models"), "mod error;\npub mod extended;\npub use error::ModelError;\n".into());
    files.insert(module("models::error"), "use crate::models::extended::Extension;\n".into());
    files.insert(module("models::extended"), "fn f() -> Result<(), crate::models::ModelError> { Ok(()) }\n".into());
    let graph = imports(&files);
    assert_eq!(graph[&module("data::kitti")], BTreeSet::from([module("evaluation::metrics")]));
    assert_eq!(graph[&module("models::extended")], BTreeSet::from([module("models::error")]));
    let bad = floor_violations(&graph);
    assert_eq!(bad, vec!["data::kitti imports evaluation::metrics".to_string()]);
    assert_eq!(circles(&graph), vec![vec!["models::error".to_string(), "models::extended".to_string()]]);
    // Test modules are not read.
    assert!(code_of("use crate::a;\n#[cfg(test)]\nmod tests {\n    use crate::b;\n}\n").contains("crate::a"));
    assert!(!code_of("use crate::a;\n#[cfg(test)]\nmod tests {\n    use crate::b;\n}\n").contains("crate::b"));
    // `super::` climbs out of a file's module.
    let mut files = files.clone();
    files.insert(module("data::kitti"), "use super::super::evaluation::metrics::x;\n".into());
    assert_eq!(imports(&files)[&module("data::kitti")], BTreeSet::from([module("evaluation::metrics")]));
}
