//! The CLIP model: radar tower (`visual.*`), text tower and `logit_scale` at the root, as
//! open_clip's `CLIP`; or a radar tower with a counts head (`counts_head`) for the `counts`
//! objective.

use rlmflow_stages::encoder::ModelConfig;
use tch::nn::{self, Module};
use tch::{Kind, Tensor};

use crate::text::TextTower;
use crate::vision::{VisionOutput, VisionTower};

#[derive(Debug)]
pub struct Clip {
    pub visual: VisionTower,
    pub text: Option<TextTower>,
    /// ln(1 / tau).
    pub logit_scale: Tensor,
    pub counts_head: Option<nn::Linear>,
    pub config: ModelConfig,
}

impl Clip {
    /// A model with fresh weights (drawn from torch's generator: seed it first). `tau` is the
    /// initial temperature, learnt when `learn_tau`.
    pub fn new(root: &nn::Path, config: &ModelConfig, tau: f64, learn_tau: bool) -> Clip {
        let logit_scale = root.add("logit_scale", Tensor::from((1.0 / tau).ln() as f32), learn_tau);
        Clip {
            visual: VisionTower::new(&(root / "visual"), &config.vision, config.embed),
            text: config.text.as_ref().map(|t| TextTower::new(root, t, config.embed)),
            logit_scale,
            counts_head: (config.counts_head > 0).then(|| nn::linear(root / "counts_head", config.embed, config.counts_head, Default::default())),
            config: config.clone(),
        }
    }

    pub fn encode_image(&self, images: &Tensor, train: bool) -> VisionOutput {
        self.visual.forward(images, train)
    }

    pub fn encode_text(&self, tokens: &Tensor) -> Tensor {
        self.text.as_ref().expect("a model with a text tower").forward(tokens)
    }

    /// Predicted counts from radar embeddings (`counts` objective).
    pub fn counts(&self, embedding: &Tensor) -> Tensor {
        self.counts_head.as_ref().expect("a model with a counts head").forward(embedding)
    }

    /// The learnt scale, clamped as open_clip does (at most 100).
    pub fn scale(&self) -> Tensor {
        self.logit_scale.exp().clamp_max(100.0)
    }
}

/// Cosine similarities times `scale`: rows are radar embeddings, columns texts.
pub fn logits(image: &Tensor, text: &Tensor, scale: &Tensor) -> Tensor {
    let unit = |x: &Tensor| x / x.norm_scalaropt_dim(2, [-1].as_slice(), true).clamp_min(1e-12);
    scale * unit(image).matmul(&unit(text).tr())
}

/// Images as the towers take them: one channel, u8 pixels scaled to [-1, 1].
pub fn images_from_u8(pixels: &[u8], batch: i64, side: i64, device: tch::Device) -> Tensor {
    Tensor::from_slice(pixels).view([batch, 1, side, side]).to_device(device).to_kind(Kind::Float) / 127.5 - 1.0
}

/// A trained model read back from an Encoder artifact, frozen (no gradients), with its weights,
/// for images of `side` pixels (an error names both sizes when the encoder was trained on others).
pub fn load(dir: &std::path::Path, device: tch::Device, side: i64) -> anyhow::Result<(nn::VarStore, Clip)> {
    use anyhow::Context as _;
    let encoder = rlmflow_stages::encoder::Encoder::open(dir).with_context(|| format!("reading the encoder at {}", dir.display()))?;
    if encoder.config.vision.image != side {
        anyhow::bail!("the encoder was trained on {} px images, the scenes have {side} px", encoder.config.vision.image);
    }
    let mut vs = nn::VarStore::new(device);
    let model = Clip::new(&vs.root(), &encoder.config, 0.07, false);
    let weights = dir.join(rlmflow_stages::encoder::WEIGHTS);
    vs.freeze();
    vs.read_safetensors(&weights).with_context(|| format!("loading {}", weights.display()))?;
    Ok((vs, model))
}
