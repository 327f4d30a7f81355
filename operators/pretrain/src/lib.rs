//! The `pretrain` stage kind's `clip` operator, as the planning binary sees it: its settings,
//! the named model sizes, its spec and resources. The training itself runs in the
//! `rlmflow-torch` worker (`operators/pretrain/torch`), which links libtorch; this crate does
//! not, so `rlmflow run --dry-run` validates every setting without it.
//!
//! Objectives: `clip` (symmetric cross-entropy against the identity), `sg-clip` (the paper's
//! soft targets from the frames' 48-cell count vectors, `alpha`, `distance`), and `counts` (the
//! radar tower regressed on the counts directly, no text: an upper reference for the probes).
//! `epochs = 0` writes the model untrained: the random-init sanity row.
//!
//! Choices the paper leaves open, all settings: the laptop towers (`conv-tiny`: a stem of three
//! 3x3 stride-2 convolutions before two transformer blocks; `tiny` text: eight 64-wide token
//! embeddings per position), `distance = "pair-total"` (scaled SG-CLIP distance), a fixed or
//! learnt temperature, and `device = "auto"` (CUDA when present; the result then depends on the
//! machine's device, so a pipeline that must reproduce bit for bit everywhere names `cpu`). The
//! schedule and optimiser settings are the shared `Training` group.

use rlmflow_stages::encoder::{Distance, Head, ModelConfig, Stem, TextConfig, VisionConfig};
use rlmflow_stages::grid::CELLS;
use rlmflow_stages::memory::{FLOAT, LOWER_BY_ACCUMULATING, TRAINED, activation_bytes};
use rlmflow_stages::numerics::{Precision, Target};
use rlmflow_stages::weights::{Expected, check_init};
use rlmflow_stages::{
    Device, Footprint, InWorker, InputOutlines, ModelOutline, Numerics, OperatorSpec, Outline, Resources, SettingError, Settings, Training,
};
use serde::{Deserialize, Serialize};

/// The binary the torch operators run in.
pub const WORKER: &str = "rlmflow-torch";

pub const ENCODERS: [&str; 3] = ["conv-tiny", "conv-small", "vit-b16"];
pub const TEXTS: [&str; 2] = ["tiny", "paper"];

/// What an `init` file must hold: a CLIP ViT-B/16 vision tower, by open_clip's or Hugging
/// Face's names.
const CLIP_WEIGHTS: Expected = Expected {
    model: "CLIP ViT-B/16 (open_clip `visual.*` or Hugging Face `vision_model.*` names)",
    names: &["visual.conv1.weight", "vision_model.embeddings.patch_embedding.weight"],
    source: "docs/guide/paper-scale.md (\"Pretrained weights\") converts OpenAI's in a few lines of Python",
};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Objective {
    Clip,
    SgClip,
    Counts,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default)]
pub struct ClipSettings {
    /// Radar tower: `conv-tiny` (laptop), `conv-small`, `vit-b16` (the paper's ViT-B/16).
    pub encoder: String,
    /// Text tower: `tiny` (laptop) or `paper` (width 512, 12 layers, 8 heads).
    pub text: String,
    /// Radar projection into the shared space: `linear` or `mlp`.
    pub head: Head,
    /// Text projection into the shared space: `linear` or `mlp`.
    pub text_head: Head,
    /// QuickGELU in the radar tower's blocks (open_clip's `quick_gelu`), as OpenAI's CLIP
    /// weights need; GELU otherwise. The text tower always uses QuickGELU (the paper's table).
    pub quick_gelu: bool,
    pub objective: Objective,
    /// SG-CLIP sharpness, 0..=1000.
    pub alpha: f64,
    pub distance: Distance,
    /// Temperature (initial, when learnt), 0.001..=1.
    pub tau: f64,
    /// Learn the temperature (open_clip's logit scale, clamped at 100).
    pub learn_tau: bool,
    /// A CLIP ViT-B/16 safetensors file (open_clip or Hugging Face names) to start the radar
    /// tower from; empty: random. Only for `encoder = "vit-b16"`.
    pub init: String,
    /// Frames embedded at a time in a contrastive batch (gradient caching): the loss and
    /// gradients of the whole `batch` at the memory of `chunk` frames, so one GPU runs the
    /// paper's batch of 640 exactly. 0: the whole batch at once. Only for towers without
    /// BatchNorm (`vit-b16`: a conv stem's batch statistics would differ per chunk).
    pub chunk: u64,
    /// The schedule, optimiser and device (`rlmflow_stages::training`).
    #[serde(flatten)]
    pub training: Training,
}

impl Default for ClipSettings {
    fn default() -> Self {
        ClipSettings {
            encoder: "conv-tiny".into(),
            text: "tiny".into(),
            head: Head::Linear,
            text_head: Head::Linear,
            quick_gelu: false,
            objective: Objective::Clip,
            alpha: 1.0,
            distance: Distance::Raw,
            tau: 0.07,
            learn_tau: false,
            init: String::new(),
            chunk: 0,
            training: Training {
                epochs: 10,
                batch: 128,
                accumulate: 1,
                lr: 1e-3,
                warmup_epochs: 1.0,
                warmup_lr: 1e-6,
                min_lr: 1e-5,
                betas: [0.9, 0.98],
                eps: 1e-8,
                weight_decay: 0.05,
                clip_norm: 1.0,
                device: Device::Auto,
                threads: 2,
                numerics: Numerics::Portable,
                precision: Precision::Auto,
            },
        }
    }
}

impl Settings for ClipSettings {
    const TRACKED: &'static [&'static str] = &["init"];

    fn check_tracked(&self, key: &str, path: &std::path::Path) -> Result<(), SettingError> {
        check_init(key, path, &CLIP_WEIGHTS)
    }

    fn check(&self) -> Result<(), SettingError> {
        let one_of = |key: &str, value: &str, valid: &[&str]| {
            if valid.contains(&value) {
                return Ok(());
            }
            let mut e = SettingError::new(key, format!("unknown {key} `{value}`; valid: {}", valid.join(", ")));
            e.valid = Vec::new();
            Err(e)
        };
        one_of("encoder", &self.encoder, &ENCODERS)?;
        one_of("text", &self.text, &TEXTS)?;
        SettingError::check_range("alpha", self.alpha, 0.0..=1000.0)?;
        SettingError::check_range("tau", self.tau, 0.001..=1.0)?;
        self.training.check()?;
        if self.objective != Objective::Counts && self.training.batch < 2 {
            return Err(SettingError::new("batch", "a contrastive batch needs at least 2 frames"));
        }
        if !self.init.is_empty() && self.encoder != "vit-b16" {
            return Err(SettingError::new("init", "CLIP weights fit only encoder = \"vit-b16\""));
        }
        if self.text_head != Head::Linear && self.objective == Objective::Counts {
            return Err(SettingError::new("text_head", "the `counts` objective trains no text tower"));
        }
        SettingError::check_range("chunk", self.chunk, 0..=65_536)?;
        if self.training.accumulate > 1 && self.objective != Objective::Counts {
            return Err(SettingError::new(
                "accumulate",
                "a contrastive loss over a batch is not the mean of its parts' losses; set `chunk` to embed the batch a chunk at a time (the same loss)",
            ));
        }
        if self.chunk > 0 && self.objective == Objective::Counts {
            return Err(SettingError::new("chunk", "embeds a contrastive batch in chunks; the `counts` objective has none"));
        }
        if self.chunk > 0 && self.encoder != "vit-b16" {
            return Err(SettingError::new(
                "chunk",
                format!(
                    "needs a tower without BatchNorm (encoder = \"vit-b16\"): `{}`'s conv stem normalises by batch, which chunks would change",
                    self.encoder
                ),
            ));
        }
        Ok(())
    }
}

fn spec() -> OperatorSpec {
    OperatorSpec {
        name: "clip",
        kind: "pretrain",
        version: 8,
        inputs: None,
        summary: "radar and text towers trained with CLIP, SG-CLIP (alpha) or on the counts (libtorch, in rlmflow-torch)",
    }
}

fn resources(s: &ClipSettings) -> Resources {
    s.training.resources()
}

/// The settings against the scenes and tokens: the batch fits their frames, the encoder's patch
/// divides their image and the text tower's grouping their context. The outline passes on the
/// scenes' and describes the model.
fn outline(s: &ClipSettings, inputs: &InputOutlines) -> Result<Outline, SettingError> {
    let outline = s.training.outline(inputs)?;
    let Some(config) = configured(s, inputs)? else { return Ok(outline) };
    let v = &config.vision;
    let model = ModelOutline { parameters: config.parameters(), width: v.width as u64, grid: v.grid() as u64, embed: config.embed as u64 };
    Ok(Outline { model: Some(model), ..outline })
}

/// The model for the inputs' outlines, where they tell the image side (a stand-in context and
/// vocabulary where they do not tell the tokens').
fn configured(s: &ClipSettings, inputs: &InputOutlines) -> Result<Option<ModelConfig>, SettingError> {
    let Some(image) = Outline::passed_on(inputs).image else { return Ok(None) };
    let tokens = Outline::of(inputs, "tokens");
    let context = tokens.and_then(|t| t.context).unwrap_or(8);
    let vocab = tokens.and_then(|t| t.vocab).unwrap_or(259);
    model_config(s, image as i64, context as i64, vocab as i64, 1).map(Some)
}

/// Every weight with its gradient and AdamW's moments, and the activations of the frames a step
/// embeds at once (the chunk under gradient caching, else the batch), with the batch's logits.
fn footprint(s: &ClipSettings, inputs: &InputOutlines, target: Target) -> Option<Footprint> {
    let config = configured(s, inputs).ok()??;
    let parameters = config.parameters();
    if s.training.epochs == 0 {
        return Some(Footprint { parameters, peak_bytes: parameters * FLOAT, lower_with: "nothing (untrained)" });
    }
    let batch = s.training.batch;
    let at_once = if s.chunk > 0 { s.chunk.min(batch) } else { s.training.micro_batch() };
    let activations = config.activations() * at_once + 6 * batch * batch;
    let lower_with = match (s.objective, s.encoder.as_str()) {
        (Objective::Counts, _) => LOWER_BY_ACCUMULATING,
        (_, "vit-b16") => "`chunk` (gradient caching, the same loss) or `batch`",
        _ => "`batch`",
    };
    Some(Footprint { parameters, peak_bytes: parameters * TRAINED + activation_bytes(activations, s.training.precision.on(target)), lower_with })
}

/// The operator as `rlmflow` registers it: validated and planned here, run by the worker.
pub fn operator() -> InWorker<ClipSettings> {
    InWorker {
        spec: spec(),
        worker: WORKER,
        resources,
        outline,
        footprint,
        metrics: |s| rlmflow_stages::encoder::metric_names(s.objective == Objective::Counts),
        run: None,
    }
}

/// The model the settings name, for images of `image` pixels and the tokens stage's `context`,
/// `vocab` and end token. Errors name the setting that does not fit.
pub fn model_config(s: &ClipSettings, image: i64, context: i64, vocab: i64, end_token: i64) -> Result<ModelConfig, SettingError> {
    let (stem, width, layers, heads, mlp, embed) = match s.encoder.as_str() {
        "conv-tiny" => (Stem::Conv { channels: vec![32, 64, 128] }, 128, 2, 4, 512, 128),
        "conv-small" => (Stem::Conv { channels: vec![32, 96, 192] }, 192, 4, 6, 768, 256),
        _ => (Stem::Patch { size: 16 }, 768, 12, 12, 3072, 512),
    };
    if let Stem::Patch { size } = stem
        && image % size != 0
    {
        return Err(SettingError::new("encoder", format!("`{}` needs an image side divisible by {size}; the scenes have {image}", s.encoder)));
    }
    let vision = VisionConfig { image, stem, width, layers, heads, mlp, head: s.head, quick_gelu: s.quick_gelu };
    let text = match (s.objective, s.text.as_str()) {
        (Objective::Counts, _) => None,
        (_, "tiny") => {
            Some(TextConfig { context, vocab, group: 8, token_width: 64, width: 128, layers: 2, heads: 4, mlp: 512, end_token, head: s.text_head })
        }
        _ => {
            Some(TextConfig { context, vocab, group: 1, token_width: 512, width: 512, layers: 12, heads: 8, mlp: 2048, end_token, head: s.text_head })
        }
    };
    if let Some(t) = &text
        && context % t.group != 0
    {
        return Err(SettingError::new(
            "text",
            format!("`{}` groups {} tokens; the tokens stage's context {context} is not a multiple", s.text, t.group),
        ));
    }
    let counts_head = if s.objective == Objective::Counts { CELLS as i64 } else { 0 };
    Ok(ModelConfig { embed, vision, text, counts_head })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rlmflow_stages::DynOperator;

    #[test]
    fn sizes_fit_their_inputs_or_name_the_setting() {
        let s = ClipSettings::default();
        let c = model_config(&s, 64, 256, 2048, 1).unwrap();
        assert_eq!(c.vision.grid(), 8);
        assert_eq!(c.text.as_ref().unwrap().context / c.text.as_ref().unwrap().group, 32);
        let b16 = ClipSettings { encoder: "vit-b16".into(), text: "paper".into(), ..s.clone() };
        let c = model_config(&b16, 224, 400, 2048, 1).unwrap();
        assert_eq!((c.vision.grid(), c.vision.width, c.embed), (14, 768, 512));
        assert_eq!(model_config(&b16, 64 + 8, 400, 2048, 1).unwrap_err().key, "encoder");
        assert_eq!(model_config(&s, 64, 250, 2048, 1).unwrap_err().key, "text");
        let counts = ClipSettings { objective: Objective::Counts, ..s };
        assert!(model_config(&counts, 64, 250, 2048, 1).unwrap().text.is_none());
    }

    /// The H100's peaks (nvidia-smi, CUDA context included; docs/guide/paper-scale.md) for the
    /// paper model at three batch and chunk sizes in float32 and under bf16 autocast: the
    /// estimate is within 11 % of each. `auto` is bf16 on CUDA and float32 on the CPU.
    #[test]
    fn the_estimate_follows_the_precision_a_stage_computes_in() {
        let scenes = Outline { image: Some(224), frames: Some(400), ..Outline::default() };
        let tokens = Outline { context: Some(400), vocab: Some(2048), ..Outline::default() };
        let inputs: InputOutlines = [("scenes", vec![scenes]), ("tokens", vec![tokens])].into_iter().collect();
        let paper = ClipSettings {
            encoder: "vit-b16".into(),
            quick_gelu: true,
            text: "paper".into(),
            head: Head::Mlp,
            text_head: Head::Mlp,
            ..ClipSettings::default()
        };
        let mib = |precision, batch, chunk, target| {
            let s = ClipSettings { chunk, training: Training { precision, batch, ..paper.training.clone() }, ..paper.clone() };
            footprint(&s, &inputs, target).unwrap().peak_bytes as f64 / 2f64.powi(20)
        };
        let measured = [
            (Precision::Fp32, 160, 80, 30_397.0),
            (Precision::Fp32, 64, 64, 25_505.0),
            (Precision::Fp32, 160, 40, 18_769.0),
            (Precision::Bf16, 160, 80, 18_509.0),
            (Precision::Bf16, 64, 64, 15_227.0),
            (Precision::Bf16, 160, 40, 11_271.0),
        ];
        for (precision, batch, chunk, peak) in measured {
            let estimate = mib(precision, batch, chunk, Target::Cuda(0));
            assert!((estimate / peak - 1.0).abs() < 0.11, "{precision} batch {batch} chunk {chunk}: {estimate:.0} MiB estimated, {peak} measured");
        }
        assert_eq!(mib(Precision::Auto, 160, 80, Target::Cuda(0)), mib(Precision::Bf16, 160, 80, Target::Cuda(0)));
        assert_eq!(mib(Precision::Auto, 160, 80, Target::Cpu), mib(Precision::Fp32, 160, 80, Target::Cpu));
    }

    #[test]
    fn impossible_settings_name_their_key() {
        let op = operator();
        let key = |v: serde_json::Value| op.settings(v).unwrap_err().key;
        assert_eq!(key(serde_json::json!({"encoder": "vit-h14"})), "encoder");
        assert_eq!(key(serde_json::json!({"objective": "sgclip"})), "objective");
        assert_eq!(key(serde_json::json!({"epochs": 5, "warmup_epochs": 6.0})), "warmup_epochs");
        assert_eq!(key(serde_json::json!({"device": "tpu"})), "device");
        assert_eq!(key(serde_json::json!({"init": "/clip.safetensors"})), "init");
        assert_eq!(key(serde_json::json!({"batch": 1})), "batch");
        assert_eq!(key(serde_json::json!({"objective": "counts", "text_head": "mlp"})), "text_head");
        assert_eq!(key(serde_json::json!({"chunk": 40})), "chunk", "conv-tiny has BatchNorm");
        assert_eq!(key(serde_json::json!({"encoder": "vit-b16", "chunk": 40, "objective": "counts"})), "chunk");
        assert!(op.settings(serde_json::json!({"encoder": "vit-b16", "chunk": 40, "batch": 640})).is_ok());
        // The file `init` names is checked once the engine has resolved it (a tracked path).
        let settings = op.settings(serde_json::json!({"encoder": "vit-b16", "init": "/nowhere/clip.safetensors"})).unwrap();
        let e = op.check_tracked(&settings, "init", std::path::Path::new("/nowhere/clip.safetensors")).unwrap_err();
        assert_eq!(e.key, "init");
        assert!(e.message.contains("`/nowhere/clip.safetensors` is not a file") && e.message.contains("CLIP ViT-B/16"), "{}", e.message);
    }
}
