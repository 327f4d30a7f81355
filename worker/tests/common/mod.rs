//! What the worker's end-to-end tests share: the real `rlmflow` beside this package's worker, a
//! scratch pipeline directory, and the stored output of a stage instance.

use std::path::{Path, PathBuf};
use std::process::Command;

/// `rlmflow`, built beside this package's worker.
pub fn rlmflow_exe() -> PathBuf {
    let exe = Path::new(env!("CARGO_BIN_EXE_rlmflow-torch")).with_file_name("rlmflow");
    assert!(exe.is_file(), "{} is missing: build the workspace (`cargo xtask test` does)", exe.display());
    exe
}

/// Runs `rlmflow ARGS` in `dir`: success and everything it printed.
pub fn rlmflow(dir: &Path, args: &[&str]) -> (bool, String) {
    let out = Command::new(rlmflow_exe()).current_dir(dir).args(args).output().unwrap();
    (out.status.success(), format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
}

/// A fresh directory holding `p.toml`.
pub fn scratch(name: &str, pipeline: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("rlmflow-worker-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("p.toml"), pipeline).unwrap();
    dir
}

/// The output directory of stage instance `label` of pipeline `name` run in `dir`.
pub fn output(dir: &Path, name: &str, label: &str) -> PathBuf {
    let store = rlmflow_cache::Store::open_existing(&dir.join(".rlmflow")).unwrap().unwrap();
    let record = store.record(&store.last_keys(name).unwrap()[label]).unwrap().unwrap();
    store.object_dir(&record.output)
}

/// Procedural scenes at 32 px, labels, template captions and tokens: what the model stages read.
pub fn data_stages(name: &str, seed: u64, frames: u32, per_frame: u32) -> String {
    format!(
        r#"[pipeline]
name = "{name}"
seed = {seed}

[stages.scenes]
operator = "procedural"
frames = {frames}
radar = {{ image = 32 }}

[stages.labels]
operator = "ego-grid"

[stages.captions]
operator = "template"
per_frame = {per_frame}

[stages.tokens]
operator = "bpe"
vocab = 400
context = 128
"#
    )
}
