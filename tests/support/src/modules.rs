//! A crate's modules form a DAG: the check behind "no module cycles".

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// Panics naming the cycle when a top-level module of the crate whose sources are under `src`
/// reaches back to one that uses it (each `crate::<module>` a file names is an arrow). Returns
/// how many modules it read, for the caller to check that it read them all.
pub fn assert_acyclic(src: &Path) -> usize {
    let mut arrows: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    let mut files = vec![src.to_path_buf()];
    while let Some(path) = files.pop() {
        if path.is_dir() {
            files.extend(std::fs::read_dir(&path).unwrap().map(|e| e.unwrap().path()));
            continue;
        }
        let module = path.strip_prefix(src).unwrap().components().next().unwrap().as_os_str().to_string_lossy().trim_end_matches(".rs").to_owned();
        if module == "lib" {
            continue;
        }
        let text = std::fs::read_to_string(&path).unwrap();
        let used =
            text.match_indices("crate::").map(|(i, _)| text[i + 7..].chars().take_while(|c| c.is_ascii_lowercase() || *c == '_').collect::<String>());
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
    arrows.len()
}

#[cfg(test)]
mod tests {
    #[test]
    #[should_panic(expected = "a module cycle: a -> b -> a")]
    fn a_module_that_reaches_back_is_a_cycle() {
        let src = std::env::temp_dir().join(format!("rlmflow-modules-{}", std::process::id()));
        std::fs::create_dir_all(&src).unwrap();
        std::fs::write(src.join("a.rs"), "use crate::b::B;").unwrap();
        std::fs::write(src.join("b.rs"), "fn f() -> crate::a::A {}").unwrap();
        std::fs::write(src.join("c.rs"), "use crate::a;").unwrap();
        let result = std::panic::catch_unwind(|| super::assert_acyclic(&src));
        std::fs::remove_dir_all(&src).unwrap();
        std::panic::resume_unwind(result.unwrap_err());
    }
}
