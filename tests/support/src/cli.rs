//! Running the real binaries as a user would, and finding what a run stored.

use std::path::{Path, PathBuf};
use std::process::Command;

/// The binary `name` built beside `exe` (a test's `CARGO_BIN_EXE_*`): `rlmflow` beside the
/// worker, say.
pub fn beside(exe: &str, name: &str) -> PathBuf {
    let path = Path::new(exe).with_file_name(name);
    assert!(path.is_file(), "{} is missing: build the workspace (`cargo xtask test` does)", path.display());
    path
}

/// Runs `exe ARGS` in `dir`: whether it succeeded, and everything it printed (stdout, then
/// stderr).
pub fn run(exe: &Path, dir: &Path, args: &[&str]) -> (bool, String) {
    let out = Command::new(exe).current_dir(dir).args(args).output().unwrap_or_else(|e| panic!("running {}: {e}", exe.display()));
    (out.status.success(), format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
}

/// The key each instance of `pipeline` had in its latest run, by the label the run printed:
/// the store's refs (which name instances as data) read through the runs' plans, which give
/// each instance's label.
pub fn last_keys(store: &rlmflow_cache::Store, pipeline: &str) -> std::collections::BTreeMap<String, rlmflow_cache::Digest> {
    let refs = store.last_keys(pipeline).unwrap();
    let mut labels = std::collections::BTreeMap::new();
    for run in store.runs().unwrap() {
        let Some(plan) = store.plan(&run).unwrap().filter(|p| p.pipeline == pipeline) else { continue };
        labels.extend(plan.instances.into_iter().map(|e| (e.instance, e.label)));
    }
    let named = refs.instances.iter().map(|(instance, key)| (labels.get(instance).unwrap_or_else(|| panic!("no run printed {instance:?}")).clone(), *key));
    named.chain(refs.labels.clone()).collect()
}

/// The output digest of stage instance `label` of pipeline `pipeline` in the store at `store`,
/// through the store's refs to its last run.
pub fn output_digest(store: &Path, pipeline: &str, label: &str) -> rlmflow_cache::Digest {
    let store = open(store);
    let key = last_keys(&store, pipeline)[label];
    store.record(&key).unwrap().unwrap().output
}

/// The output directory of stage instance `label` of pipeline `pipeline` in the store at
/// `store` (see [`output_digest`]).
pub fn output_dir(store: &Path, pipeline: &str, label: &str) -> PathBuf {
    open(store).object_dir(&output_digest(store, pipeline, label))
}

fn open(store: &Path) -> rlmflow_cache::Store {
    rlmflow_cache::Store::open_existing(store).unwrap().unwrap_or_else(|| panic!("no store at {}", store.display()))
}
