//! What the worker's end-to-end tests share: the real `rlmflow` beside this package's worker, a
//! scratch pipeline directory over one store for the whole test binary, and the stored output of
//! a stage instance.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use rlmflow_test_support::Scratch;

/// `rlmflow`, built beside this package's worker.
pub fn rlmflow_exe() -> PathBuf {
    rlmflow_test_support::cli::beside(env!("CARGO_BIN_EXE_rlmflow-torch"), "rlmflow")
}

/// Runs `rlmflow ARGS` in `dir`: success and everything it printed.
pub fn rlmflow(dir: &Path, args: &[&str]) -> (bool, String) {
    rlmflow_test_support::cli::run(&rlmflow_exe(), dir, args)
}

/// The store every test of this process shares, under the build's scratch space
/// (`CARGO_TARGET_TMPDIR`): the one an earlier test process left is removed when the next starts.
fn shared_store() -> &'static Path {
    static STORE: OnceLock<PathBuf> = OnceLock::new();
    STORE.get_or_init(|| rlmflow_test_support::scratch::shared_dir(Path::new(env!("CARGO_TARGET_TMPDIR")), "worker-store"))
}

/// A fresh directory holding `p.toml`, whose store (`.rlmflow`, a link) is the one every test of
/// this process shares: stages that several tests run with the same settings and inputs (the
/// data stages, an encoder) are computed once, by whichever run gets to them first, while the
/// store's locks make the others wait and reuse them. Tests give their pipelines distinct names,
/// so each finds its own run's outputs.
pub fn scratch(name: &str, pipeline: &str) -> Scratch {
    let dir = scratch_alone(name, pipeline);
    std::os::unix::fs::symlink(shared_store(), dir.join(".rlmflow")).unwrap();
    dir
}

/// A fresh directory holding `p.toml`, with a store of its own.
pub fn scratch_alone(name: &str, pipeline: &str) -> Scratch {
    Scratch::with_pipeline(&format!("worker-{name}"), pipeline)
}

/// The output directory of stage instance `label` of pipeline `name` run in `dir`.
pub fn output(dir: &Path, name: &str, label: &str) -> PathBuf {
    rlmflow_test_support::cli::output_dir(&dir.join(".rlmflow"), name, label)
}

/// Pipeline `name`'s data stages, the same in every test so the shared store computes them once:
/// 1,000 procedural scenes at 32 px, labels with masks drawn twice the paper's relative size
/// (blobs of a few pixels at 32 px), two template captions per frame and tokens.
pub fn data_stages(name: &str) -> String {
    format!(
        r#"[pipeline]
name = "{name}"
seed = 5

[stages.scenes]
operator = "procedural"
frames = 1000
radar = {{ image = 32 }}

[stages.labels]
operator = "ego-grid"
mask = {{ reference_size = 64 }}

[stages.captions]
operator = "template"
per_frame = 2

[stages.tokens]
operator = "bpe"
vocab = 400
context = 128
"#
    )
}

/// The encoder the probe and segmenter tests read (`clip`, four epochs at batch 64 on the CPU),
/// with its untrained twin as a second variant when `random`: the same stage in every test, so
/// the shared store trains it once.
pub fn encoders(random: bool) -> String {
    let variants = if random { "[stages.pretrain.variants]\nclip = {}\nrandom = { epochs = 0, warmup_epochs = 0.0 }\n" } else { "" };
    format!("\n[stages.pretrain]\noperator = \"clip\"\ndevice = \"cpu\"\n{NATIVE}\nbatch = 64\nepochs = 4\n{variants}")
}

/// The fastest kernels (`numerics = "native"`) for the stages of tests that check what a model
/// learns or keeps, not its kernels: MKL's portable branch halves their speed, and `numerics.rs`
/// checks the portable path of every operator.
pub const NATIVE: &str = "numerics = \"native\"";

/// Held by each test while it runs: every model test keeps both cores busy (its stages take two
/// threads), so they take turns rather than oversubscribe the machine and wait on each other's
/// locks in the shared store.
pub fn one_at_a_time() -> std::sync::MutexGuard<'static, ()> {
    static TURN: std::sync::Mutex<()> = std::sync::Mutex::new(());
    TURN.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// A training stage's TensorBoard curves in its output `object`, as TensorBoard's own reader
/// reads them, hold each number of each epoch's `log` line at the epoch's last step, and a loss
/// and a learning rate for every step.
pub fn assert_curves_hold(object: &Path, log: &[serde_json::Value]) {
    let scalars = rlmflow_test_support::tensorboard::scalars(&object.join("events.out.tfevents.rlmflow"));
    for line in log {
        let step = line["step"].as_u64().unwrap();
        for (name, value) in line.as_object().unwrap() {
            let Some(value) = value.as_f64().filter(|_| name != "epoch" && name != "step") else { continue };
            let tag = format!("epoch/{name}");
            let found: Vec<f64> = scalars.iter().filter(|(s, t, _)| *s == step && *t == tag).map(|(_, _, v)| *v).collect();
            assert_eq!(found, [f64::from(value as f32)], "{}: {tag} at step {step}", object.display());
        }
    }
    let steps = log.last().unwrap()["step"].as_u64().unwrap();
    for tag in ["train/loss", "train/lr"] {
        let at: Vec<u64> = scalars.iter().filter(|(_, t, _)| t == tag).map(|(s, _, _)| *s).collect();
        assert_eq!(at, (1..=steps).collect::<Vec<_>>(), "{}: {tag}", object.display());
    }
}
