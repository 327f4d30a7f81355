//! The radar tower: a ViT with a CLS token and pre-LN blocks (open_clip's `VisionTransformer`
//! names: `visual.conv1`, `class_embedding`, `positional_embedding`, `ln_pre`,
//! `transformer`, `ln_post`, `proj`), with either a patch embedding or a convolutional stem.

use rlmflow_stages::encoder::{Head, Stem, VisionConfig};
use tch::Tensor;
use tch::nn::{self, Module, ModuleT};

use crate::transformer::{Activation, Transformer};

#[derive(Debug)]
enum Embedding {
    /// `conv1`: one convolution with kernel and stride `size`.
    Patch(nn::Conv2D),
    /// `stem.N.conv` and `stem.N.bn`.
    Conv(Vec<(nn::Conv2D, nn::BatchNorm)>),
}

#[derive(Debug)]
enum Projection {
    /// `proj`: (width, embed), applied as x @ proj.
    Linear(Tensor),
    /// `head.fc1`, `head.fc2`.
    Mlp(nn::Linear, nn::Linear),
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
        let projection = match c.head {
            Head::Linear => Projection::Linear(p.randn("proj", &[width, embed], 0.0, scale)),
            Head::Mlp => Projection::Mlp(
                nn::linear(p / "head" / "fc1", width, width, Default::default()),
                nn::linear(p / "head" / "fc2", width, embed, Default::default()),
            ),
        };
        VisionTower {
            embedding,
            class_embedding: p.randn("class_embedding", &[width], 0.0, scale),
            positional_embedding: p.randn("positional_embedding", &[tokens, width], 0.0, scale),
            ln_pre: nn::layer_norm(p / "ln_pre", vec![width], Default::default()),
            transformer: Transformer::new(&(p / "transformer"), width, c.layers, c.heads, c.mlp, Activation::Gelu, false),
            ln_post: nn::layer_norm(p / "ln_post", vec![width], Default::default()),
            projection,
            config: c.clone(),
        }
    }

    /// `images`: (batch, 1, image, image), normalised.
    pub fn forward(&self, images: &Tensor, train: bool) -> VisionOutput {
        let grid = match &self.embedding {
            Embedding::Patch(conv) => conv.forward(images),
            Embedding::Conv(layers) => {
                layers.iter().fold(images.shallow_clone(), |x, (conv, bn)| bn.forward_t(&conv.forward(&x), train).gelu("none"))
            }
        };
        let (b, w) = (grid.size()[0], grid.size()[1]);
        let patches = grid.flatten(2, 3).transpose(1, 2);
        let cls = self.class_embedding.view([1, 1, w]).expand([b, 1, w], false);
        let x = Tensor::cat(&[cls, patches], 1) + &self.positional_embedding;
        let x = self.transformer.forward(&self.ln_pre.forward(&x));
        let tokens = self.ln_post.forward(&x);
        let cls = tokens.select(1, 0);
        let embedding = match &self.projection {
            Projection::Linear(proj) => cls.matmul(proj),
            Projection::Mlp(fc1, fc2) => fc2.forward(&fc1.forward(&cls).gelu("none")),
        };
        VisionOutput { embedding, tokens }
    }
}
