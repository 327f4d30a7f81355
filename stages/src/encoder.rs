//! The Encoder artifact: a pretrained radar-language model.
//!
//! ```text
//! model.safetensors  the weights, named as open_clip's CLIP where shapes allow
//!                    (visual.*, token_embedding, positional_embedding, transformer.*,
//!                    ln_final, text_projection, logit_scale)
//! config.json        the ModelConfig (towers, sizes) the weights belong to
//! train.jsonl        one line per epoch: loss, lr, tau, soft-target mass off the diagonal,
//!                    test-split radar->text retrieval top-1 / top-5, and per batch the loss
//!                    and the off-diagonal mass (`batch_loss`, `batch_off_diagonal`)
//! encoder.json       summary: objective, steps, samples, final metrics, chance levels
//! trained_frames.txt the identities of the frames the radar tower trained on (none for an
//!                    untrained encoder), one per line, sorted
//! tokenizer_frames.txt  with a text tower: the identities of the frames whose captions its
//!                    tokenizer learnt from (the tokens artifact's `learnt_frames.txt`)
//! ```
//!
//! The model shapes are plain structs here, so light crates (settings, the report) read them
//! without libtorch.

use serde::{Deserialize, Serialize};

pub const WEIGHTS: &str = "model.safetensors";
pub const CONFIG: &str = "config.json";
pub const LOG: &str = "train.jsonl";
pub const SUMMARY: &str = "encoder.json";
pub const TRAINED: &str = "trained_frames.txt";
pub const TOKENIZER_FRAMES: &str = "tokenizer_frames.txt";
pub const FORMAT: u32 = 2;

/// How the radar image becomes a sequence of tokens.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", tag = "type")]
pub enum Stem {
    /// Non-overlapping `size` x `size` patches, linearly embedded (ViT; open_clip's `conv1`).
    Patch { size: i64 },
    /// 3x3 stride-2 convolutions, each with BatchNorm and GELU, `channels` wide in turn; the
    /// last is the width. Learns on small data where a patch embedding does not.
    Conv { channels: Vec<i64> },
}

/// What maps the radar tower's CLS token into the shared space.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Head {
    /// A matrix without bias (open_clip's `proj`).
    Linear,
    /// Linear, GELU, linear.
    Mlp,
}

/// How SG-CLIP measures d_ij, the distance between two frames' 48-cell count vectors.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Distance {
    /// The L1 count difference (the paper).
    Raw,
    /// The difference divided by the pair's total count (at least 1): a difference of one
    /// vehicle weighs less between busy scenes, so near-identical scenes exist even where exact
    /// ones are rare.
    PairTotal,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VisionConfig {
    /// Image side in pixels; one input channel.
    pub image: i64,
    pub stem: Stem,
    pub width: i64,
    pub layers: i64,
    pub heads: i64,
    pub mlp: i64,
    pub head: Head,
}

impl VisionConfig {
    /// Tokens per side of the grid the stem produces.
    pub fn grid(&self) -> i64 {
        match &self.stem {
            Stem::Patch { size } => self.image / size,
            Stem::Conv { channels } => (0..channels.len()).fold(self.image, |side, _| (side + 1) / 2),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TextConfig {
    /// Token positions (the tokens stage's context).
    pub context: i64,
    pub vocab: i64,
    /// Tokens embedded `group` at a time: each group's `token_width`-wide embeddings are
    /// concatenated and projected to `width`, so the transformer sees context / group positions.
    /// 1 is the paper's tower (token_width = width).
    pub group: i64,
    pub token_width: i64,
    pub width: i64,
    pub layers: i64,
    pub heads: i64,
    pub mlp: i64,
    /// The id whose first position is pooled (the end token).
    pub end_token: i64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelConfig {
    /// The shared space's width.
    pub embed: i64,
    pub vision: VisionConfig,
    /// None for a radar tower trained on the counts alone (`counts` objective).
    pub text: Option<TextConfig>,
    /// Outputs of the counts head (48) when trained on the counts; 0 otherwise.
    pub counts_head: i64,
}

/// `encoder.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub format: u32,
    pub objective: String,
    pub epochs: u64,
    pub steps: u64,
    pub train_frames: u64,
    pub test_frames: u64,
    /// The last epoch's log line.
    pub last: serde_json::Value,
    /// Retrieval top-k of a random ranking on the test split.
    pub chance_top1: f64,
    pub chance_top5: f64,
    /// The operator's settings.
    pub generator: serde_json::Value,
}

/// An Encoder artifact's config and summary, read (the weights are the worker's to load).
pub struct Encoder {
    pub config: ModelConfig,
    pub summary: Summary,
    pub dir: std::path::PathBuf,
}

impl Encoder {
    pub fn open(dir: &std::path::Path) -> anyhow::Result<Encoder> {
        use anyhow::Context as _;
        let summary: Summary = crate::read_summary(dir, SUMMARY, "Encoder", "pretrain", FORMAT)?;
        let path = dir.join(CONFIG);
        let config = serde_json::from_slice(&std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?)
            .with_context(|| format!("{} is not a model config", path.display()))?;
        Ok(Encoder { config, summary, dir: dir.to_path_buf() })
    }
}
