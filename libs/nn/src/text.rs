//! The text tower: a GPT-style causal transformer pooled at the end token (open_clip's text
//! names: `token_embedding`, `positional_embedding`, `transformer`, `ln_final`,
//! `text_projection`, or an MLP `text_head`). With `group` > 1, `group` narrow token embeddings are concatenated and
//! projected (`token_group`) before the transformer, which then sees context / group positions:
//! the tower costs a fraction of the paper's at laptop scale.

use rlmflow_stages::encoder::TextConfig;
use tch::nn::{self, Module};
use tch::{Kind, Tensor};

use crate::projection::Projection;
use crate::transformer::{Activation, Transformer};

#[derive(Debug)]
pub struct TextTower {
    token_embedding: nn::Embedding,
    token_group: Option<nn::Linear>,
    positional_embedding: Tensor,
    transformer: Transformer,
    ln_final: nn::LayerNorm,
    projection: Projection,
    pub config: TextConfig,
}

impl TextTower {
    pub fn new(root: &nn::Path, c: &TextConfig, embed: i64) -> TextTower {
        let positions = c.context / c.group;
        let embedding = nn::EmbeddingConfig { ws_init: nn::Init::Randn { mean: 0.0, stdev: 0.02 }, ..Default::default() };
        TextTower {
            token_embedding: nn::embedding(root / "token_embedding", c.vocab, c.token_width, embedding),
            token_group: (c.group > 1).then(|| nn::linear(root / "token_group", c.group * c.token_width, c.width, Default::default())),
            positional_embedding: root.randn("positional_embedding", &[positions, c.width], 0.0, 0.01),
            transformer: Transformer::new(&(root / "transformer"), c.width, c.layers, c.heads, c.mlp, Activation::QuickGelu, true),
            ln_final: nn::layer_norm(root / "ln_final", vec![c.width], Default::default()),
            projection: Projection::new(root, c.head, "text_projection", "text_head", c.width, embed),
            config: c.clone(),
        }
    }

    /// `tokens`: (batch, context) int64 ids; returns (batch, embed).
    pub fn forward(&self, tokens: &Tensor) -> Tensor {
        let c = &self.config;
        let (b, t) = tokens.size2().expect("(batch, context)");
        let x = self.token_embedding.forward(tokens);
        let x = match &self.token_group {
            Some(group) => group.forward(&x.view([b, t / c.group, c.group * c.token_width])),
            None => x,
        };
        let x = self.ln_final.forward(&self.transformer.forward(&(x + &self.positional_embedding)));
        // The first end token's position (the last position if a row has none), in groups.
        let is_end = tokens.eq(c.end_token).to_kind(Kind::Int64);
        let first_end = is_end.argmax(1, false);
        let has_end = is_end.amax([1].as_slice(), false).to_kind(Kind::Bool);
        let position = first_end.where_self(&has_end, &Tensor::full([b], t - 1, (Kind::Int64, tokens.device()))).divide_scalar_mode(c.group, "floor");
        let pooled = x.gather(1, &position.view([b, 1, 1]).expand([b, 1, c.width], false), false).squeeze_dim(1);
        self.projection.forward(&pooled)
    }
}
