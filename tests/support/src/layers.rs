//! The crates' layers, as cargo resolves them: what each binary and crate may depend on
//! (ARCHITECTURE.md's invariants on the engine, the operator families and the two binaries).

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;

fn cargo(root: &Path, args: &[&str]) -> String {
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let out = Command::new(cargo).current_dir(root).args(args).output().expect("running cargo");
    assert!(out.status.success(), "cargo {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap()
}

/// The names of the packages `package` is built from (normal dependencies, features resolved
/// as `cargo build -p PACKAGE` resolves them).
pub fn built_from(root: &Path, package: &str) -> BTreeSet<String> {
    let tree = cargo(root, &["tree", "--locked", "-p", package, "-e", "normal", "--prefix", "none", "-f", "{p}"]);
    tree.lines().filter_map(|l| l.split_whitespace().next()).map(str::to_owned).collect()
}

/// Each workspace member: its name, its manifest's directory and its workspace dependencies
/// (normal ones).
pub fn members(root: &Path) -> Vec<(String, PathBuf, Vec<String>)> {
    let metadata: serde_json::Value = serde_json::from_str(&cargo(root, &["metadata", "--format-version", "1", "--no-deps"])).unwrap();
    let packages = metadata["packages"].as_array().unwrap();
    let names: BTreeSet<&str> = packages.iter().map(|p| p["name"].as_str().unwrap()).collect();
    packages
        .iter()
        .map(|p| {
            let dir = Path::new(p["manifest_path"].as_str().unwrap()).parent().unwrap().to_path_buf();
            let deps = p["dependencies"].as_array().unwrap().iter();
            let normal = deps.filter(|d| d["kind"].is_null()).map(|d| d["name"].as_str().unwrap()).filter(|n| names.contains(n));
            (p["name"].as_str().unwrap().to_owned(), dir, normal.map(str::to_owned).collect())
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The operator family a crate belongs to (`operators/<family>/...`), `None` for a crate outside
    /// `operators/` (the shared libraries are all under `libs/`).
    fn family(operators: &Path, dir: &Path) -> Option<String> {
        Some(dir.strip_prefix(operators).ok()?.components().next()?.as_os_str().to_str()?.to_owned())
    }

    /// `rlmflow` never links libtorch and `rlmflow-torch` never embeds Python; the engine depends
    /// on no operator crate; an operator family depends on `stages` and the shared libraries
    /// (`libs/`), never on another family, and a shared library on no family; the store depends on no other crate of the workspace and never
    /// prints.
    #[test]
    fn each_binary_and_crate_depends_only_on_its_layers() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..").canonicalize().unwrap();
        let rlmflow = built_from(&root, "rlmflow");
        assert!(rlmflow.contains("rlmflow-engine") && rlmflow.contains("pyo3"), "the tree is read: {rlmflow:?}");
        for torch in ["tch", "torch-sys", "rlmflow-libtorch", "rlmflow-nn"] {
            assert!(!rlmflow.contains(torch), "rlmflow is built from {torch}");
        }
        let stages = built_from(&root, "rlmflow-stages");
        assert!(!stages.contains("tch"), "the contracts crate is built from a tensor library");
        let worker = built_from(&root, "rlmflow-torch");
        assert!(worker.contains("tch"), "the tree is read: {worker:?}");
        assert!(!worker.contains("pyo3"), "rlmflow-torch embeds Python");

        let operators = root.join("operators");
        let members = members(&root);
        let family_of: std::collections::BTreeMap<&str, Option<String>> =
            members.iter().map(|(name, dir, _)| (name.as_str(), dir.starts_with(&operators).then(|| family(&operators, dir)).flatten())).collect();
        let (_, _, engine) = members.iter().find(|(name, ..)| name == "rlmflow-engine").unwrap();
        let engine_reaches: Vec<&String> =
            engine.iter().filter(|d| members.iter().any(|(n, dir, _)| n == *d && dir.starts_with(&operators))).collect();
        assert!(engine_reaches.is_empty(), "the engine depends on operator crates {engine_reaches:?}");
        let mut families = 0;
        for (name, _, deps) in &members {
            let Some(Some(own)) = family_of.get(name.as_str()) else { continue };
            families += 1;
            for dep in deps {
                if let Some(Some(other)) = family_of.get(dep.as_str()) {
                    assert_eq!(other, own, "{name} (family {own}) depends on {dep} (family {other})");
                }
            }
        }
        assert!(families >= 11, "every family crate checked: {families}");
        // A shared library serves the families and depends on none.
        let libs = root.join("libs");
        for (name, dir, deps) in members.iter().filter(|(_, dir, _)| dir.starts_with(&libs)) {
            let reaches: Vec<&String> = deps.iter().filter(|d| family_of.get(d.as_str()).is_some_and(Option::is_some)).collect();
            assert!(reaches.is_empty(), "{name} ({}) depends on operator families {reaches:?}", dir.display());
        }

        // The store knows no stage or operator and never prints: its warnings are data.
        let (_, cache_dir, cache) = members.iter().find(|(name, ..)| name == "rlmflow-cache").unwrap();
        assert!(cache.is_empty(), "the store depends on {cache:?}");
        for file in std::fs::read_dir(cache_dir.join("src")).unwrap().flatten() {
            let text = std::fs::read_to_string(file.path()).unwrap();
            let code = text.split("#[cfg(test)]").next().unwrap();
            assert!(!code.contains("println!(") && !code.contains("eprintln!("), "{} prints", file.path().display());
        }
    }
}
