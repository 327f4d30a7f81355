//! The contracts between rlmflow's engine and its operators.
//!
//! * [`kind`]: stage kinds and the artifact types they consume and produce, as data. The paper's
//!   pipeline is one [`Catalog`]; tests add their own kinds. [`artifact`] names the types once.
//! * [`operator`]: the [`Operator`] trait (one implementation of a stage kind), its typed
//!   [`Settings`], and the type-erased [`DynOperator`] the engine stores in its registry.
//! * [`context`]: what an operator is given when it runs: input paths, an output directory, a
//!   checkpoint directory that survives a crash, the seed, a thread budget and a progress handle.
//!
//! * [`grid`]: the paper's ego grid and its JSON; [`segment`]: the segmentation metrics;
//!   [`identity`]: frame identities, the split rule and the train/test overlap check.
//! * [`scenes`], [`labels`], [`captions`], [`tokens`], [`encoder`], [`embeddings`], [`probe`]: each artifact's directory layout, its
//!   writer-side line formats and its reader; [`npy`] for their dense arrays.
//! * [`claims`]: claims comparing two metrics paired by seed, and the rule deciding them as seeds
//!   are added; [`measure`]: what an artifact measures (metrics, per-frame differences).
//! * [`numerics`]: the numeric platform a model action's bytes depend on: its kernel pins and the
//!   class of machines that share its results.
//! * [`training`]: the settings every training operator shares; [`weights`]: the check of a
//!   weights file a setting names; [`memory`]: a training action's memory, estimated from shapes; [`item_seed`]: the seed rule of every per-item draw.
//!
//! Nothing here knows about scheduling, caching or processes, and nothing links a tensor
//! library: model shapes and training settings are plain data here, computed on elsewhere.

pub mod artifact;
pub mod captions;
pub mod claims;
pub mod context;
pub mod embeddings;
pub mod encoder;
pub mod grid;
pub mod identity;
pub mod kind;
pub mod labels;
pub mod measure;
pub mod memory;
pub mod npy;
pub mod numerics;
pub mod operator;
pub mod probe;
pub mod scenes;
pub mod segment;
pub mod tokens;
pub mod training;
pub mod weights;

pub use context::{Context, Device, Input, InstanceId, Progress, Reporter};
pub use kind::{Arity, Catalog, Need, Slot, StageKind};
pub use memory::Footprint;
pub use numerics::{Kernels, Numerics};
pub use operator::{
    DynOperator, FilePattern, InWorker, InputOutlines, ItemCount, Items, ModelOutline, Operator, OperatorSpec, Outcome, Outline, Part, Registry,
    Resources, SettingError, Settings, Sharding, Share,
};
pub use training::Training;

/// The seed of item `index` (a frame, an epoch) of a run seeded `seed`: each item's draws come
/// from its own generator, never from one shared across items, so an item's result does not
/// depend on which thread, batch, shard or resumed attempt computed it.
pub fn item_seed(seed: u64, index: u64) -> u64 {
    seed ^ index.wrapping_mul(0x9E37_79B9_7F4A_7C15)
}

/// `f` over `items` on up to `threads` scoped threads, results in order.
pub fn parallel_map<T: Sync, R: Send>(items: &[T], threads: usize, f: impl Fn(&T) -> R + Sync) -> Vec<R> {
    let chunk = items.len().div_ceil(threads.max(1)).max(1);
    std::thread::scope(|scope| {
        let f = &f;
        let handles: Vec<_> = items.chunks(chunk).map(|part| scope.spawn(move || part.iter().map(f).collect::<Vec<R>>())).collect();
        handles.into_iter().flat_map(|h| h.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic))).collect()
    })
}

/// Reads an artifact's summary (`dir/file`, JSON with a `format` field) and checks that this
/// build reads its format; `artifact` names the type (`Scenes`) and `stage` what to rerun.
pub(crate) fn read_summary<T: serde::de::DeserializeOwned>(
    dir: &std::path::Path,
    file: &str,
    artifact: &str,
    stage: &str,
    format: u32,
) -> anyhow::Result<T> {
    use anyhow::Context as _;
    let path = dir.join(file);
    let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
    let value: serde_json::Value = serde_json::from_slice(&bytes).with_context(|| format!("{} is not JSON", path.display()))?;
    let found = value.get("format").and_then(serde_json::Value::as_u64);
    if found != Some(u64::from(format)) {
        let found = found.map_or("without a version".to_string(), |f| f.to_string());
        anyhow::bail!("{}: {artifact} format {found} (this build reads {format}); rerun the {stage} stage", path.display());
    }
    serde_json::from_value(value).with_context(|| format!("{} is not a {artifact} summary", path.display()))
}

/// Reads a JSON Lines file, each line with `parse`; errors name the file and line.
pub(crate) fn read_lines<T>(path: &std::path::Path, parse: impl Fn(&str) -> Result<T, String>) -> anyhow::Result<Vec<T>> {
    use anyhow::Context as _;
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    text.lines().enumerate().map(|(i, l)| parse(l).map_err(|e| anyhow::anyhow!("{}:{}: {e}", path.display(), i + 1))).collect()
}

#[cfg(test)]
mod tests {
    #[test]
    fn summaries_of_another_format_and_bad_lines_are_named() {
        let dir = std::env::temp_dir().join(format!("rlmflow-stages-summary-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("labels.json"), r#"{"format": 0, "frames": 1}"#).unwrap();
        let e = crate::labels::Labels::open(&dir).err().unwrap().to_string();
        assert!(e.ends_with("labels.json: Labels format 0 (this build reads 2); rerun the labels stage"), "{e}");
        std::fs::write(dir.join("captions.json"), r#"{"format": 2, "frames": 1, "captions": 2, "generator": null}"#).unwrap();
        std::fs::write(
            dir.join("captions.jsonl"),
            "{\"frame\": 0, \"id\": \"a\", \"split\": \"train\", \"caption\": \"a\"}\n{\"frame\": 0, \"id\": \"a\", \"split\": \"dev\", \"caption\": \"b\"}\n",
        )
        .unwrap();
        let e = crate::captions::Captions::open(&dir).err().unwrap().to_string();
        assert!(e.contains("captions.jsonl:2: not a caption line: unknown variant `dev`, expected `train` or `test`"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
