//! The CLIP model: radar tower (`visual.*`), text tower and `logit_scale` at the root, as
//! open_clip's `CLIP`; or a radar tower with a counts head (`counts_head`) for the `counts`
//! objective.

use rlmflow_stages::encoder::ModelConfig;
use tch::nn::{self, Module};
use tch::{Kind, Tensor};

use crate::text::TextTower;
use crate::train::Backward;
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
        let logit_scale = root.add("logit_scale", Tensor::from((1.0 / tau).ln() as f32).to_device(root.device()), learn_tau);
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

/// A contrastive batch's loss and the gradients of every trained variable, embedded `chunk`
/// frames at a time (gradient caching, Gao et al. 2021): both towers embed the whole batch in
/// chunks without autograd; `loss_of` (of the radar and text embeddings, reading the live logit
/// scale) and its gradient with respect to the embeddings are taken over the full batch; then
/// each chunk is embedded again with autograd and back-propagates its share of those gradients.
/// The same loss and gradients as the whole batch at once, up to float rounding, at the memory of
/// one chunk, for towers without batch statistics (no BatchNorm: the patch stem).
pub fn cached_contrastive(
    model: &Clip,
    images: &Tensor,
    tokens: &Tensor,
    chunk: i64,
    loss_of: impl Fn(&Tensor, &Tensor) -> Tensor,
    backward: &Backward,
) -> (f64, Vec<Tensor>) {
    let n = images.size()[0];
    let chunks: Vec<(i64, i64)> = (0..n).step_by(chunk as usize).map(|start| (start, chunk.min(n - start))).collect();
    let embed = |(start, len): (i64, i64)| {
        (model.encode_image(&images.narrow(0, start, len), true).embedding, model.encode_text(&tokens.narrow(0, start, len)))
    };
    let (images_cut, texts_cut): (Vec<Tensor>, Vec<Tensor>) = tch::no_grad(|| chunks.iter().map(|&c| embed(c)).unzip());
    let image = Tensor::cat(&images_cut, 0).set_requires_grad(true);
    let text = Tensor::cat(&texts_cut, 0).set_requires_grad(true);
    let loss = loss_of(&image, &text);
    let value = loss.double_value(&[]);
    let (mut gradients, cached) = backward.gradients(&loss, &[&image, &text]);
    for &(start, len) in &chunks {
        let (image, text) = embed((start, len));
        let share = (image * cached[0].narrow(0, start, len)).sum(Kind::Float) + (text * cached[1].narrow(0, start, len)).sum(Kind::Float);
        for (total, part) in gradients.iter_mut().zip(backward.gradients(&share, &[]).0) {
            if part.defined() {
                *total = if total.defined() { &*total + part } else { part };
            }
        }
    }
    (value, gradients)
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

#[cfg(test)]
mod tests {
    use rlmflow_stages::encoder::{Head, Stem, TextConfig, VisionConfig};

    use super::*;
    use crate::loss::{Distance, clip_loss, soft_clip_loss, soft_targets};
    use crate::optim::AdamW;

    #[test]
    fn a_batch_embedded_in_chunks_has_the_whole_batchs_loss_and_gradients() {
        let _generator = crate::generator();
        tch::manual_seed(7);
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let vision =
            VisionConfig { image: 16, stem: Stem::Patch { size: 8 }, width: 32, layers: 2, heads: 2, mlp: 64, head: Head::Mlp, quick_gelu: false };
        let text =
            TextConfig { context: 8, vocab: 40, group: 1, token_width: 32, width: 32, layers: 2, heads: 2, mlp: 64, end_token: 1, head: Head::Mlp };
        let config = ModelConfig { embed: 16, vision, text: Some(text), counts_head: 0 };
        let model = Clip::new(&vs.root(), &config, 0.07, true);
        let opt = AdamW::new(&vs, (0.9, 0.98), 1e-8, 0.0);
        let backward = Backward::new(&opt);
        let batch = 10;
        let images = Tensor::randn([batch, 1, 16, 16], (Kind::Float, tch::Device::Cpu));
        let tokens = Tensor::randint_low(2, 40, [batch, 8], (Kind::Int64, tch::Device::Cpu));
        let counts = Tensor::randint(3, [batch, 48], (Kind::Float, tch::Device::Cpu));
        let targets = soft_targets(&counts, 1.0, Distance::Raw);
        type Loss<'a> = Box<dyn Fn(&Tensor, &Tensor) -> Tensor + 'a>;
        let objectives: [(&str, Loss); 2] = [
            ("clip", Box::new(|image: &Tensor, text: &Tensor| clip_loss(&logits(image, text, &model.scale())))),
            ("sg-clip", Box::new(|image: &Tensor, text: &Tensor| soft_clip_loss(&logits(image, text, &model.scale()), &targets))),
        ];
        for (name, loss_of) in objectives {
            let whole = loss_of(&model.encode_image(&images, true).embedding, &model.encode_text(&tokens));
            let expected = backward.gradients(&whole, &[]).0;
            for chunk in [3, 4] {
                let (value, gradients) = cached_contrastive(&model, &images, &tokens, chunk, &loss_of, &backward);
                assert!((value - whole.double_value(&[])).abs() < 1e-5, "{name}, chunks of {chunk}: loss {value} vs {}", whole.double_value(&[]));
                assert_eq!(gradients.len(), expected.len());
                for (got, want) in gradients.iter().zip(&expected) {
                    assert_eq!(got.defined(), want.defined(), "{name}: the same variables get gradients");
                    if want.defined() {
                        // Float rounding, relative to the gradient's own scale.
                        let (gap, scale) = ((got - want).abs().max().double_value(&[]), want.abs().max().double_value(&[]));
                        assert!(gap <= 1e-4 * scale + 1e-7, "{name}, chunks of {chunk}: gradients differ by {gap} at scale {scale}");
                    }
                }
            }
        }
    }
}
