//! A crate's modules form a DAG: the check behind "no module cycles", for every crate of the
//! workspace.
//!
//! Each file is a module (`a.rs` and `a/mod.rs` are `a`, `a/b.rs` is `a::b`, `lib.rs` and
//! `main.rs` the root). Each path a file names is an arrow to the deepest module of the path:
//! `crate::`, `super::` (also repeated), `self::` and a child's name, in `use` trees (grouped and
//! nested: `use super::{checker::Diagnostic, Stage}`) and inline (`crate::import::read_image(..)`).
//! Arrows between a module and its ancestors are left out (a parent declares and re-exports its
//! children; a child reads what its parent defines); comments and `#[cfg(test)] mod tests` are
//! not read.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// A module's path inside its crate, `["config", "checker"]` (the root is empty).
type Module = Vec<String>;

/// Panics naming the cycle when a module of the crate whose sources are under `src` reaches back
/// to one that reaches it. Returns how many modules it read, for the caller to check that it
/// read them all.
pub fn assert_acyclic(src: &Path) -> usize {
    let files = sources(src);
    let modules: BTreeSet<Module> = files.keys().cloned().collect();
    let mut arrows: BTreeMap<Module, BTreeSet<Module>> = BTreeMap::new();
    for (module, path) in &files {
        let text = readable(&std::fs::read_to_string(path).unwrap());
        let targets = arrows.entry(module.clone()).or_default();
        for named in paths(&text) {
            let Some(target) = resolve(&named, module, &modules) else { continue };
            if !target.starts_with(module) && !module.starts_with(&target) {
                targets.insert(target);
            }
        }
    }
    // Depth-first: a module met again while still on the path closes a cycle.
    fn visit(m: &Module, arrows: &BTreeMap<Module, BTreeSet<Module>>, path: &mut Vec<Module>, done: &mut BTreeSet<Module>) {
        if let Some(at) = path.iter().position(|p| p == m) {
            let names: Vec<String> = path[at..].iter().chain([m]).map(|p| p.join("::")).collect();
            panic!("a module cycle: {}", names.join(" -> "));
        }
        if !done.insert(m.clone()) {
            return;
        }
        path.push(m.clone());
        for next in arrows.get(m).into_iter().flatten() {
            visit(next, arrows, path, done);
        }
        path.pop();
    }
    let mut done = BTreeSet::new();
    for module in arrows.keys() {
        visit(module, &arrows, &mut Vec::new(), &mut done);
    }
    modules.len()
}

/// Every `.rs` file under `src` by the module it is.
fn sources(src: &Path) -> BTreeMap<Module, PathBuf> {
    let mut found = BTreeMap::new();
    let mut pending = vec![src.to_path_buf()];
    while let Some(path) = pending.pop() {
        if path.is_dir() {
            pending.extend(std::fs::read_dir(&path).unwrap().map(|e| e.unwrap().path()));
            continue;
        }
        if path.extension().is_none_or(|e| e != "rs") {
            continue;
        }
        let mut module: Module =
            path.strip_prefix(src).unwrap().with_extension("").components().map(|c| c.as_os_str().to_string_lossy().into_owned()).collect();
        if matches!(module.last().map(String::as_str), Some("mod")) || (module.len() == 1 && matches!(module[0].as_str(), "lib" | "main")) {
            module.pop();
        }
        found.insert(module, path);
    }
    found
}

/// The text a check reads: without comments, and cut where the file's unit tests begin.
fn readable(text: &str) -> String {
    let code: String = text.lines().map(|line| line.find("//").map_or(line, |at| &line[..at])).collect::<Vec<_>>().join("\n");
    match code.find("#[cfg(test)]\nmod tests") {
        Some(at) => code[..at].to_owned(),
        None => code,
    }
}

/// Every path the code names that may lead to a module of its own crate: each `use` tree
/// expanded, and each inline `crate::`, `super::` or `self::` path.
fn paths(code: &str) -> Vec<Vec<String>> {
    let is_word = |b: u8| b.is_ascii_alphanumeric() || b == b'_';
    let mut out = Vec::new();
    let mut inline = String::with_capacity(code.len());
    let mut at = 0;
    while let Some(found) = code[at..].find("use ").map(|i| at + i) {
        let before = code[..found].trim_end();
        let statement = (found == 0 || !is_word(code.as_bytes()[found - 1]))
            && (before.is_empty()
                || before.ends_with([';', '{', '}', ']'])
                || ["pub", "pub(crate)", "pub(super)"].iter().any(|v| before.ends_with(v)));
        match code[found..].find(';').map(|i| found + i) {
            Some(end) if statement => {
                inline.push_str(&code[at..found]);
                expand(&code[found + 4..end], Vec::new(), &mut out);
                at = end + 1;
            }
            _ => {
                inline.push_str(&code[at..found + 4]);
                at = found + 4;
            }
        }
    }
    inline.push_str(&code[at..]);
    for root in ["crate::", "super::", "self::"] {
        for (i, _) in inline.match_indices(root) {
            if i > 0 && (is_word(inline.as_bytes()[i - 1]) || matches!(inline.as_bytes()[i - 1], b'$' | b':')) {
                continue;
            }
            let tail: String = inline[i..].chars().take_while(|c| c.is_ascii_alphanumeric() || *c == '_' || *c == ':').collect();
            out.push(tail.split("::").filter(|s| !s.is_empty()).map(str::to_owned).collect());
        }
    }
    out
}

/// The paths of one `use` tree (`a::{b, c::{d, e}}`), each prefixed with `prefix`.
fn expand(tree: &str, prefix: Vec<String>, out: &mut Vec<Vec<String>>) {
    let tree = tree.trim();
    match tree.find('{') {
        None => {
            let mut path = prefix;
            let tree = tree.split(" as ").next().unwrap_or(tree);
            path.extend(tree.split("::").map(|s| s.trim().to_owned()).filter(|s| !s.is_empty() && s != "*"));
            out.push(path);
        }
        Some(open) => {
            let mut path = prefix;
            path.extend(tree[..open].split("::").map(|s| s.trim().to_owned()).filter(|s| !s.is_empty()));
            let inner = &tree[open + 1..tree.rfind('}').unwrap_or(tree.len())];
            // Split the group at its top-level commas.
            let (mut depth, mut from) = (0, 0);
            for (i, c) in inner.char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        expand(&inner[from..i], path.clone(), out);
                        from = i + 1;
                    }
                    _ => {}
                }
            }
            if !inner[from..].trim().is_empty() {
                expand(&inner[from..], path, out);
            }
        }
    }
}

/// The deepest module of the crate that `path`, named in `module`, leads to; `None` for a path
/// outside the crate (another crate's, or an item in scope).
fn resolve(path: &[String], module: &Module, modules: &BTreeSet<Module>) -> Option<Module> {
    let (first, mut rest) = path.split_first()?;
    let mut at = match first.as_str() {
        "crate" => Vec::new(),
        "self" => module.clone(),
        "super" => {
            let mut up = module.clone();
            up.pop();
            while rest.first().is_some_and(|s| s == "super") {
                up.pop();
                rest = &rest[1..];
            }
            up
        }
        // A child of this module named without `self::` (Rust 2018 paths); any other first
        // segment is another crate or an item in scope.
        child if modules.contains(&[module.as_slice(), &[child.to_owned()]].concat()) => {
            rest = path;
            module.clone()
        }
        _ => return None,
    };
    for segment in rest {
        let deeper = [at.as_slice(), std::slice::from_ref(segment)].concat();
        if !modules.contains(&deeper) {
            break;
        }
        at = deeper;
    }
    Some(at)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A crate of `files` (path, text) in a scratch folder; the check's panic message, if any.
    fn check(name: &str, files: &[(&str, &str)]) -> Result<usize, String> {
        let src = std::env::temp_dir().join(format!("rlmflow-modules-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&src);
        for (path, text) in files {
            std::fs::create_dir_all(src.join(path).parent().unwrap()).unwrap();
            std::fs::write(src.join(path), text).unwrap();
        }
        let result = std::panic::catch_unwind(|| assert_acyclic(&src));
        std::fs::remove_dir_all(&src).unwrap();
        result.map_err(|e| e.downcast_ref::<String>().cloned().unwrap_or_default())
    }

    #[test]
    fn a_module_that_reaches_back_is_a_cycle() {
        let err = check("plain", &[("a.rs", "use crate::b::B;"), ("b.rs", "fn f() -> crate::a::A {}"), ("c.rs", "use crate::a;")]).unwrap_err();
        assert_eq!(err, "a module cycle: a -> b -> a");
    }

    /// The engine's cycle before it was broken: siblings reaching each other through `super::`,
    /// one of them in a grouped import.
    #[test]
    fn siblings_through_super_and_grouped_imports_are_a_cycle() {
        let files = [
            ("lib.rs", "mod config;"),
            ("config/mod.rs", "mod checker;\nmod overrides;\npub struct Stage;"),
            ("config/checker.rs", "use super::overrides::Override;\nuse super::Stage;"),
            ("config/overrides.rs", "use super::{Stage, checker::{Diagnostic, too_deep}};"),
        ];
        assert_eq!(check("super", &files).unwrap_err(), "a module cycle: config::checker -> config::overrides -> config::checker");
    }

    /// The scenes crate's cycle before it was broken: a module and a sibling's children, through
    /// nested groups one way and inline paths the other.
    #[test]
    fn nested_groups_and_inline_paths_into_children_are_a_cycle() {
        let files = [
            ("lib.rs", "mod datasets;\nmod import;"),
            ("import.rs", "use crate::datasets::{Opened, radiate, cruw::{self}};"),
            ("datasets/mod.rs", "pub mod radiate;\npub mod cruw;\npub struct Opened;"),
            ("datasets/radiate.rs", "fn open() { let raw = crate::import::read_image(); }"),
            ("datasets/cruw.rs", ""),
        ];
        assert_eq!(check("nested", &files).unwrap_err(), "a module cycle: datasets::radiate -> import -> datasets::radiate");
    }

    /// A parent and its children use each other by design; comments and unit tests are not code
    /// paths; another crate's path of the same name is not this crate's.
    #[test]
    fn parents_children_comments_and_tests_are_no_cycle() {
        let files = [
            ("lib.rs", "mod a;\nmod b;\nuse a::A;"),
            ("a/mod.rs", "mod child;\npub use child::C;\npub struct A;"),
            ("a/child.rs", "use super::A;\nuse crate::b::B;"),
            ("b.rs", "// uses crate::a::A only in this comment\nuse other_crate::a::A;\n#[cfg(test)]\nmod tests {\n    use crate::a::A;\n}"),
        ];
        assert_eq!(check("fine", &files), Ok(4));
    }

    /// Every crate of the workspace: none has a module cycle.
    #[test]
    fn every_crate_in_the_workspace_has_its_modules_in_a_dag() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        let members = crate::layers::members(&root);
        assert!(members.len() >= 20, "{members:?}");
        let mut read = 0;
        for (_, dir, _) in members {
            let src = dir.join("src");
            if src.is_dir() {
                read += assert_acyclic(&src);
            }
        }
        assert!(read >= 140, "every crate's modules read: {read}");
    }
}
