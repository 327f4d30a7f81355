//! TensorBoard's own event reader, installed from PyPI into a scratch environment the first time
//! a test needs it (never into the product): what the training stages' curves are checked with.

use std::path::{Path, PathBuf};
use std::process::Command;

/// A venv holding the `tensorboard` package (installed on first use, about 30 s: a test may
/// start it on a thread of its own while it trains).
pub fn install() -> PathBuf {
    crate::venv::scratch_venv("rlmflow-test-tensorboard-v1", &["tensorboard"], &["tensorboard==2.21.0"])
}

const READ: &str = r#"
import json, sys
from tensorboard.backend.event_processing.event_file_loader import EventFileLoader
from tensorboard.util import tensor_util
out = []
# The loader TensorBoard serves from: it migrates each simple value to a scalar tensor.
for event in EventFileLoader(sys.argv[1]).Load():
    if event.HasField("file_version"):
        out.append({"file_version": event.file_version})
    for value in event.summary.value:
        assert value.metadata.plugin_data.plugin_name == "scalars", value
        out.append({"step": event.step, "tag": value.tag, "value": float(tensor_util.make_ndarray(value.tensor).item())})
print(json.dumps(out))
"#;

/// Every scalar of event file `file` as TensorBoard reads it: (step, tag, value), in order, after
/// checking the file declares its format version.
pub fn scalars(file: &Path) -> Vec<(u64, String, f64)> {
    let out = Command::new(install().join("bin/python")).args(["-c", READ]).arg(file).output().unwrap();
    assert!(out.status.success(), "reading {}: {}", file.display(), String::from_utf8_lossy(&out.stderr));
    let events: Vec<serde_json::Value> = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(events.first().and_then(|e| e["file_version"].as_str()), Some("brain.Event:2"), "{}", file.display());
    events[1..].iter().map(|e| (e["step"].as_u64().unwrap(), e["tag"].as_str().unwrap().to_owned(), e["value"].as_f64().unwrap())).collect()
}

const RUNS: &str = r#"
import json, sys
from tensorboard.backend.event_processing.plugin_event_multiplexer import EventMultiplexer
# How `tensorboard --logdir` finds and names runs: each folder holding an event file.
runs = EventMultiplexer()
runs.AddRunsFromDirectory(sys.argv[1])
print(json.dumps(sorted(runs.Runs())))
"#;

/// The runs `tensorboard --logdir LOGDIR` shows, by name, sorted.
pub fn runs(logdir: &Path) -> Vec<String> {
    let out = Command::new(install().join("bin/python")).args(["-c", RUNS]).arg(logdir).output().unwrap();
    assert!(out.status.success(), "listing the runs under {}: {}", logdir.display(), String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).unwrap()
}
