//! The Embeddings artifact: a frozen encoder's features of every frame of its scenes, as `.npy`
//! arrays a program reads with numpy alone (a `script` probe).
//!
//! ```text
//! embed.json            summary: frames, the arrays' shapes, the split's sizes, the settings
//! cls.npy               float32 (frames, embed): the projected CLS embedding
//! mean_patch.npy        float32 (frames, width): the mean of the radar tower's patch tokens
//! patches.npy           float32 (frames, tokens, width): every patch token (with `patches`)
//! frames.jsonl          per frame, in order: {"frame", "id", "split"} (the labels' split)
//! trained_frames.txt    the encoder's, copied: what it trained on and its tokenizer learnt
//! tokenizer_frames.txt  from, so a probe on these features checks its test frames as one on
//!                       the encoder does
//! ```

use std::path::Path;

use serde::{Deserialize, Serialize};

pub const SUMMARY: &str = "embed.json";
pub const CLS: &str = "cls.npy";
pub const MEAN_PATCH: &str = "mean_patch.npy";
pub const PATCHES: &str = "patches.npy";
pub const FRAMES: &str = "frames.jsonl";
pub const FORMAT: u32 = 1;

/// `embed.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub format: u32,
    pub frames: u64,
    pub train_frames: u64,
    pub test_frames: u64,
    /// Each array's file and shape.
    pub arrays: std::collections::BTreeMap<String, Vec<usize>>,
    pub generator: serde_json::Value,
}

pub fn read_summary(dir: &Path) -> anyhow::Result<Summary> {
    crate::reading::read_summary(dir, SUMMARY, crate::artifact::EMBEDDINGS, "embed", FORMAT)
}

/// One line of [`FRAMES`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Frame {
    pub frame: u64,
    pub id: String,
    pub split: crate::identity::Split,
}
