//! What an artifact measures, read from its own files: its metrics by dotted path (what claims
//! compare) and, between two artifacts of one type, the frames where they differ (what
//! `rlmflow compare` lists). An artifact type says how in its [`Measures`]; the engine calls
//! them through the [`crate::Catalog`] without knowing what they read.

use std::path::Path;

use serde::Serialize;
use serde_json::Value;

/// How to measure the artifacts of one type.
#[derive(Clone, Copy, Debug)]
pub struct Measures {
    pub artifact: &'static str,
    /// The artifact's metrics, a JSON object whose numeric leaves claims name by dotted path.
    pub metrics: fn(&Path) -> anyhow::Result<Value>,
    /// Two artifacts' per-frame differences, where the type keeps per-frame outputs.
    pub frames: Option<fn(&Path, &Path) -> anyhow::Result<FrameDifferences>>,
}

/// One test frame where two artifacts' outputs differ.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FrameDifference {
    /// Its index in the scenes both read.
    pub frame: u64,
    /// The row of a probe with several (`cls`, `patches`); empty for one.
    pub row: String,
    /// How much they differ, in [`FrameDifferences::unit`].
    pub differ: f64,
    /// Each side's output for the frame, in words.
    pub a: String,
    pub b: String,
}

/// Two artifacts' frames, the most different first.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FrameDifferences {
    /// What [`FrameDifference::differ`] counts: `cells predicted differently`.
    pub unit: &'static str,
    /// How many frames (and rows) were compared.
    pub compared: usize,
    /// Every frame where they differ at all, most first; frames in order among equals.
    pub frames: Vec<FrameDifference>,
}

impl FrameDifferences {
    /// `frames` (every compared one) ranked, those that do not differ left out.
    pub fn ranked(unit: &'static str, mut frames: Vec<FrameDifference>) -> FrameDifferences {
        let compared = frames.len();
        frames.retain(|f| f.differ > 0.0);
        frames.sort_by(|x, y| y.differ.total_cmp(&x.differ));
        FrameDifferences { unit, compared, frames }
    }
}

/// The value at `path` (dotted) of a metrics object, where it is a number.
pub fn lookup(metrics: &Value, path: &str) -> Option<f64> {
    path.split('.').try_fold(metrics, |v, key| v.get(key))?.as_f64()
}

/// Every numeric leaf's dotted path of a metrics object, sorted.
pub fn paths(metrics: &Value) -> Vec<String> {
    fn walk(prefix: &str, v: &Value, out: &mut Vec<String>) {
        match v {
            Value::Object(map) => map.iter().for_each(|(k, v)| walk(&if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") }, v, out)),
            Value::Number(_) => out.push(prefix.to_owned()),
            _ => {}
        }
    }
    let mut out = Vec::new();
    walk("", metrics, &mut out);
    out.sort();
    out
}
