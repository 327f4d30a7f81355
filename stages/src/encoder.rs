//! The Encoder artifact: a pretrained radar-language model.
//!
//! ```text
//! model.safetensors  the weights, named as open_clip's CLIP where shapes allow
//!                    (visual.*, token_embedding, positional_embedding, transformer.*,
//!                    ln_final, text_projection, logit_scale)
//! config.json        the ModelConfig (towers, sizes) the weights belong to, and under
//!                    `open_clip` either the file below or why open_clip cannot build the model
//! open_clip.json     where open_clip can build it: its model config (`embed_dim`,
//!                    `quick_gelu`, `vision_cfg`, `text_cfg`), for `open_clip.CLIP(**config)`
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

use crate::memory::{Blocks, conv3x3_bn, linear};

pub const WEIGHTS: &str = "model.safetensors";
pub const CONFIG: &str = "config.json";
pub const LOG: &str = "train.jsonl";
pub const SUMMARY: &str = "encoder.json";
pub const TRAINED: &str = "trained_frames.txt";
pub const TOKENIZER_FRAMES: &str = "tokenizer_frames.txt";
pub const OPEN_CLIP: &str = "open_clip.json";
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

/// What maps a tower's pooled token (the radar CLS, the text end token) into the shared space.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Head {
    /// A matrix without bias (open_clip's `proj`, `text_projection`).
    #[default]
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
    /// The blocks' activation is QuickGELU (OpenAI's CLIP weights were trained with it), not
    /// GELU (configs written before it existed: GELU).
    #[serde(default)]
    pub quick_gelu: bool,
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
    /// Into the shared space (configs written before it existed: linear).
    #[serde(default)]
    pub head: Head,
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

impl VisionConfig {
    fn blocks(&self) -> Blocks {
        Blocks { width: self.width as u64, layers: self.layers as u64, mlp: self.mlp as u64, quick_gelu: self.quick_gelu }
    }

    /// Its parameters, projecting into `embed` dimensions.
    pub fn parameters(&self, embed: i64) -> u64 {
        let w = self.width as u64;
        let stem = match &self.stem {
            Stem::Patch { size } => (size * size) as u64 * w,
            Stem::Conv { channels } => channels.iter().fold((1, 0), |(input, n), &c| (c as u64, n + conv3x3_bn(input, c as u64))).1,
        };
        let tokens = (self.grid() * self.grid() + 1) as u64;
        stem + w + tokens * w + 4 * w + self.blocks().parameters() + head_parameters(self.head, w, embed as u64)
    }

    /// Floats a training step keeps per image: the stem's outputs, the tokens and the blocks.
    pub fn activations(&self) -> u64 {
        let stem = match &self.stem {
            Stem::Patch { .. } => 0,
            Stem::Conv { channels } => {
                let mut side = self.image as u64;
                channels
                    .iter()
                    .map(|&c| {
                        side = side.div_ceil(2);
                        3 * c as u64 * side * side
                    })
                    .sum()
            }
        };
        let tokens = (self.grid() * self.grid() + 1) as u64;
        (self.image * self.image) as u64 + stem + 3 * tokens * self.width as u64 + self.blocks().activations(tokens)
    }
}

impl TextConfig {
    fn positions(&self) -> u64 {
        (self.context / self.group) as u64
    }

    /// Its parameters, projecting into `embed` dimensions.
    pub fn parameters(&self, embed: i64) -> u64 {
        let (w, tw) = (self.width as u64, self.token_width as u64);
        let group = if self.group > 1 { linear(self.group as u64 * tw, w) } else { 0 };
        let blocks = Blocks { width: w, layers: self.layers as u64, mlp: self.mlp as u64, quick_gelu: true };
        self.vocab as u64 * tw + group + self.positions() * w + blocks.parameters() + 2 * w + head_parameters(self.head, w, embed as u64)
    }

    /// Floats a training step keeps per caption: the token embeddings and the blocks.
    pub fn activations(&self) -> u64 {
        let blocks = Blocks { width: self.width as u64, layers: self.layers as u64, mlp: self.mlp as u64, quick_gelu: true };
        (self.context * self.token_width) as u64 + 3 * self.positions() * self.width as u64 + blocks.activations(self.positions())
    }
}

fn head_parameters(head: Head, width: u64, embed: u64) -> u64 {
    match head {
        Head::Linear => width * embed,
        Head::Mlp => linear(width, width) + linear(width, embed),
    }
}

impl ModelConfig {
    /// Every parameter: both towers, the logit scale, the counts head.
    pub fn parameters(&self) -> u64 {
        let text = self.text.as_ref().map_or(0, |t| t.parameters(self.embed));
        let counts = if self.counts_head > 0 { linear(self.embed as u64, self.counts_head as u64) } else { 0 };
        self.vision.parameters(self.embed) + text + 1 + counts
    }

    /// Floats a training step keeps per frame (its image and, with a text tower, one caption).
    pub fn activations(&self) -> u64 {
        self.vision.activations() + self.text.as_ref().map_or(0, TextConfig::activations)
    }

    /// open_clip's model config for this model (3.3's `CLIP(**config)`), or why it has none.
    /// Two differences stay the loader's, and the README shows both lines: open_clip's patch
    /// embedding takes 3 channels (spread the one radar channel's kernel over them, divided by
    /// 3, and repeat the image), and it builds one activation for both towers (with
    /// `quick_gelu = false` the radar tower is GELU and the text tower QuickGELU, so the text
    /// blocks' `mlp.gelu` becomes `QuickGELU`).
    pub fn open_clip(&self) -> Result<serde_json::Value, String> {
        let v = &self.vision;
        let Stem::Patch { size } = v.stem else {
            return Err("the convolutional stem has no open_clip equivalent (open_clip's ViT embeds patches)".into());
        };
        let Some(t) = &self.text else {
            return Err("no text tower (a `counts` encoder)".into());
        };
        if v.head != Head::Linear || t.head != Head::Linear {
            return Err("open_clip's ViT and text tower project linearly; this model has an MLP head".into());
        }
        if t.group != 1 {
            return Err(format!("the text tower embeds {} tokens per position, which open_clip's does not", t.group));
        }
        if self.counts_head > 0 {
            return Err("a counts head, which open_clip's CLIP has not".into());
        }
        Ok(serde_json::json!({
            "embed_dim": self.embed,
            "quick_gelu": v.quick_gelu,
            "vision_cfg": {
                "image_size": v.image, "patch_size": size, "width": v.width, "layers": v.layers,
                "head_width": v.width / v.heads, "mlp_ratio": v.mlp as f64 / v.width as f64,
            },
            "text_cfg": {
                "context_length": t.context, "vocab_size": t.vocab, "width": t.width, "heads": t.heads,
                "layers": t.layers, "mlp_ratio": t.mlp as f64 / t.width as f64,
                "pool_type": "eos", "eos_id": t.end_token,
            },
        }))
    }
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

/// What an Encoder measures, by dotted path (claims name them): the last epoch's figures
/// (`last.loss`, `last.top1`, ... as its log line holds them) and the chance levels.
pub fn metrics(summary: &Summary) -> serde_json::Value {
    serde_json::json!({"last": summary.last, "chance_top1": summary.chance_top1, "chance_top5": summary.chance_top5})
}

/// The paths [`metrics`] gives for an encoder trained on the counts (its test MSE) or
/// contrastively (its test retrieval).
pub fn metric_names(counts: bool) -> Vec<String> {
    let mut names = vec!["last.loss", "last.lr", "last.tau", "last.off_diagonal", "chance_top1", "chance_top5"];
    names.extend(if counts { &["last.test_mse"][..] } else { &["last.top1", "last.top5"][..] });
    names.into_iter().map(str::to_owned).collect()
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
        let summary: Summary = crate::reading::read_summary(dir, SUMMARY, crate::artifact::ENCODER, "pretrain", FORMAT)?;
        let path = dir.join(CONFIG);
        let config = serde_json::from_slice(&std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?)
            .with_context(|| format!("{} is not a model config", path.display()))?;
        Ok(Encoder { config, summary, dir: dir.to_path_buf() })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The paper's towers with linear heads: ViT-B/16 at 224 px, the text tower at context 400.
    fn paper(head: Head) -> ModelConfig {
        let vision =
            VisionConfig { image: 224, stem: Stem::Patch { size: 16 }, width: 768, layers: 12, heads: 12, mlp: 3072, head, quick_gelu: true };
        let text =
            TextConfig { context: 400, vocab: 2048, group: 1, token_width: 512, width: 512, layers: 12, heads: 8, mlp: 2048, end_token: 1, head };
        ModelConfig { embed: 512, vision, text: Some(text), counts_head: 0 }
    }

    #[test]
    fn parameters_equal_open_clips_count_of_the_same_model() {
        // open_clip 3.3's CLIP(embed_dim=512, ViT-B/16, context 400, vocabulary 2048) holds
        // 86,192,640 vision parameters, 393,216 of them in the two extra colour channels of
        // conv1, and 39,345,153 others (text tower and logit scale).
        let config = paper(Head::Linear);
        assert_eq!(config.vision.parameters(config.embed), 86_192_640 - 2 * 16 * 16 * 768);
        assert_eq!(config.parameters(), 86_192_640 - 2 * 16 * 16 * 768 + 39_345_153);
        assert_eq!(paper(Head::Mlp).parameters() - config.parameters(), 768 * 768 + 768 + 512 + 512 * 512 + 512 + 512);
    }

    #[test]
    fn open_clip_expresses_patch_towers_with_linear_heads_and_says_why_not_otherwise() {
        let config = paper(Head::Linear).open_clip().unwrap();
        assert_eq!(config["vision_cfg"]["head_width"], 64);
        assert_eq!(config["text_cfg"]["pool_type"], "eos");
        assert_eq!(config["text_cfg"]["eos_id"], 1);
        assert_eq!(config["quick_gelu"], true);
        assert!(paper(Head::Mlp).open_clip().unwrap_err().contains("MLP head"));
        let mut conv = paper(Head::Linear);
        conv.vision.stem = Stem::Conv { channels: vec![32, 64, 128] };
        assert!(conv.open_clip().unwrap_err().contains("convolutional stem"));
    }
}
