//! The rlmflow engine: pipeline files ([`config`]), plans and freshness ([`plan`]), the executor
//! ([`run`]), the memory check before it ([`footprint`]), the numeric platform class a model
//! action's key carries ([`platform`]), how it starts actions ([`dispatch`]: child processes or HyperQueue tasks), the
//! child-process entry point ([`exec`]), the determinism check ([`determinism`]) and the command
//! line ([`cli`]).
//! It knows no machine learning and depends on no operator: operators come from the registry a
//! binary passes to [`cli::main`] (`rlmflow` registers the shipped ones, `rlmflow-torch` the
//! libtorch ones, the end-to-end tests their own).

pub mod cli;
pub mod config;
pub mod determinism;
pub mod dispatch;
pub mod exec;
pub mod footprint;
pub mod plan;
pub mod platform;
pub mod protocol;
pub mod run;
mod ui;

#[cfg(test)]
mod tests {
    use std::collections::{BTreeMap, BTreeSet};

    /// The engine's modules form a DAG: no module reaches back to one that uses it (each
    /// `crate::<module>` a file names is an arrow).
    #[test]
    fn the_engines_modules_import_one_another_without_a_cycle() {
        let src = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
        let mut arrows: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
        let mut files = vec![src.clone()];
        while let Some(path) = files.pop() {
            if path.is_dir() {
                files.extend(std::fs::read_dir(&path).unwrap().map(|e| e.unwrap().path()));
                continue;
            }
            let module =
                path.strip_prefix(&src).unwrap().components().next().unwrap().as_os_str().to_string_lossy().trim_end_matches(".rs").to_owned();
            if module == "lib" {
                continue;
            }
            let text = std::fs::read_to_string(&path).unwrap();
            let used = text
                .match_indices("crate::")
                .map(|(i, _)| text[i + 7..].chars().take_while(|c| c.is_ascii_lowercase() || *c == '_').collect::<String>());
            arrows.entry(module.clone()).or_default().extend(used.filter(|m| !m.is_empty() && *m != module));
        }
        // Depth-first: a module met again while still on the path closes a cycle.
        fn visit(m: &str, arrows: &BTreeMap<String, BTreeSet<String>>, path: &mut Vec<String>, done: &mut BTreeSet<String>) {
            if let Some(at) = path.iter().position(|p| p == m) {
                panic!("a module cycle: {} -> {m}", path[at..].join(" -> "));
            }
            if !done.insert(m.to_owned()) {
                return;
            }
            path.push(m.to_owned());
            for next in arrows.get(m).into_iter().flatten() {
                visit(next, arrows, path, done);
            }
            path.pop();
        }
        let mut done = BTreeSet::new();
        for module in arrows.keys() {
            visit(module, &arrows, &mut Vec::new(), &mut done);
        }
        assert!(arrows.len() >= 10, "every module read: {arrows:?}");
    }
}
