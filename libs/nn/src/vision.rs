//! The radar tower: a ViT with a CLS token and pre-LN blocks (open_clip's `VisionTransformer`
//! names: `visual.conv1`, `class_embedding`, `positional_embedding`, `ln_pre`,
//! `transformer`, `ln_post`, `proj`), with either a patch embedding or a convolutional stem.

use rlmflow_stages::encoder::{Stem, VisionConfig};
use tch::Tensor;
use tch::nn::{self, Module, ModuleT};

use crate::projection::Projection;
use crate::transformer::{Activation, Transformer};

#[derive(Debug)]
enum Embedding {
    /// `conv1`: one convolution with kernel and stride `size`.
    Patch(nn::Conv2D),
    /// `stem.N.conv` and `stem.N.bn`.
    Conv(Vec<(nn::Conv2D, nn::BatchNorm)>),
}

#[derive(Debug)]
pub struct VisionTower {
    embedding: Embedding,
    class_embedding: Tensor,
    positional_embedding: Tensor,
    ln_pre: nn::LayerNorm,
    transformer: Transformer,
    ln_post: nn::LayerNorm,
    projection: Projection,
    pub config: VisionConfig,
}

/// What the tower gives for a batch of images.
pub struct VisionOutput {
    /// The CLS token projected into the shared space: (batch, embed).
    pub embedding: Tensor,
    /// Every token after `ln_post`, CLS first: (batch, 1 + grid², width).
    pub tokens: Tensor,
}

impl VisionTower {
    pub fn new(p: &nn::Path, c: &VisionConfig, embed: i64) -> VisionTower {
        let width = c.width;
        let embedding = match &c.stem {
            Stem::Patch { size } => {
                let conv = nn::ConvConfig { stride: *size, bias: false, ..Default::default() };
                Embedding::Patch(nn::conv2d(p / "conv1", 1, width, *size, conv))
            }
            Stem::Conv { channels } => {
                let mut layers = Vec::new();
                let mut input = 1;
                for (i, &output) in channels.iter().enumerate() {
                    let q = p / "stem" / i;
                    let conv = nn::ConvConfig { stride: 2, padding: 1, bias: false, ..Default::default() };
                    layers.push((nn::conv2d(&q / "conv", input, output, 3, conv), nn::batch_norm2d(&q / "bn", output, Default::default())));
                    input = output;
                }
                Embedding::Conv(layers)
            }
        };
        let tokens = c.grid() * c.grid() + 1;
        let scale = (width as f64).powf(-0.5);
        let activation = if c.quick_gelu { Activation::QuickGelu } else { Activation::Gelu };
        let projection = Projection::new(p, c.head, "proj", "head", width, embed);
        VisionTower {
            embedding,
            class_embedding: p.randn("class_embedding", &[width], 0.0, scale),
            positional_embedding: p.randn("positional_embedding", &[tokens, width], 0.0, scale),
            ln_pre: nn::layer_norm(p / "ln_pre", vec![width], Default::default()),
            transformer: Transformer::new(&(p / "transformer"), width, c.layers, c.heads, c.mlp, activation, false),
            ln_post: nn::layer_norm(p / "ln_post", vec![width], Default::default()),
            projection,
            config: c.clone(),
        }
    }

    /// `images`: (batch, 1, image, image), normalised.
    pub fn forward(&self, images: &Tensor, train: bool) -> VisionOutput {
        let x = self.transformer.forward(&self.embed(images, train));
        self.output(&x)
    }

    /// CLS attention rollout (Abnar and Zuidema, 2020) over the last `layers` blocks (0: all) of
    /// the frozen tower: per block the head-averaged attention plus the identity (the residual
    /// path), rows renormalised, multiplied through the blocks; the CLS row over the patches.
    /// (batch, grid, grid), each map summing to at most 1.
    pub fn attention_rollout(&self, images: &Tensor, layers: usize) -> Tensor {
        let (_, weights) = self.transformer.forward_with_weights(&self.embed(images, false));
        let grid = self.config.grid();
        rollout(&weights[weights.len() - if layers == 0 { weights.len() } else { layers.min(weights.len()) }..]).view([-1, grid, grid])
    }

    /// Tokens entering the transformer: the stem's grid flattened, CLS first, positions added,
    /// `ln_pre`.
    fn embed(&self, images: &Tensor, train: bool) -> Tensor {
        let grid = match &self.embedding {
            Embedding::Patch(conv) => conv.forward(images),
            Embedding::Conv(layers) => {
                layers.iter().fold(images.shallow_clone(), |x, (conv, bn)| bn.forward_t(&conv.forward(&x), train).gelu("none"))
            }
        };
        let (b, w) = (grid.size()[0], grid.size()[1]);
        let patches = grid.flatten(2, 3).transpose(1, 2);
        let cls = self.class_embedding.view([1, 1, w]).expand([b, 1, w], false);
        self.ln_pre.forward(&(Tensor::cat(&[cls, patches], 1) + &self.positional_embedding))
    }

    fn output(&self, x: &Tensor) -> VisionOutput {
        let tokens = self.ln_post.forward(x);
        let cls = tokens.select(1, 0);
        VisionOutput { embedding: self.projection.forward(&cls), tokens }
    }
}

/// The rollout of per-block attention probabilities (batch, tokens, tokens), first block
/// first: the CLS token's row of prod_l normalise(A_l + I), without its own column,
/// (batch, tokens - 1).
pub fn rollout(attentions: &[Tensor]) -> Tensor {
    let (b, t, _) = attentions[0].size3().expect("(batch, tokens, tokens)");
    let identity = Tensor::eye(t, (attentions[0].kind(), attentions[0].device()));
    let flow = attentions.iter().fold(identity.expand([b, t, t], false), |flow, a| {
        let a = a + &identity;
        let a = &a / a.sum_dim_intlist([-1].as_slice(), true, a.kind());
        a.matmul(&flow)
    });
    flow.select(1, 0).narrow(1, 1, t - 1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rollout_of_a_hand_computed_case() {
        let _generator = crate::generator();
        // Two tokens; CLS attends half to itself and half to the patch, the patch to itself.
        let a = Tensor::from_slice(&[0.5f32, 0.5, 0.0, 1.0]).view([1, 2, 2]);
        // (A + I) with rows renormalised: [[0.75, 0.25], [0, 1]]; CLS -> patch 0.25.
        assert!((rollout(&[a.shallow_clone()]).double_value(&[0, 0]) - 0.25).abs() < 1e-6);
        // Two such blocks: [[0.5625, 0.4375], [0, 1]].
        assert!((rollout(&[a.shallow_clone(), a]).double_value(&[0, 0]) - 0.4375).abs() < 1e-6);
    }
}
