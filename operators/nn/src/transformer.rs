//! The residual attention blocks both towers share, named as open_clip's `transformer.py`
//! (`resblocks.N.ln_1`, `attn.in_proj_weight`, `attn.out_proj`, `ln_2`, `mlp.c_fc`, `mlp.c_proj`).

use tch::Tensor;
use tch::nn::{self, Module};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Activation {
    Gelu,
    /// x * sigmoid(1.702 x), as OpenAI's CLIP text tower.
    QuickGelu,
}

impl Activation {
    fn apply(self, x: &Tensor) -> Tensor {
        match self {
            Activation::Gelu => x.gelu("none"),
            Activation::QuickGelu => x * (x * 1.702).sigmoid(),
        }
    }
}

/// Multi-head self-attention with PyTorch's `nn.MultiheadAttention` parameter layout.
#[derive(Debug)]
struct Attention {
    in_proj_weight: Tensor,
    in_proj_bias: Tensor,
    out_proj: nn::Linear,
    heads: i64,
}

impl Attention {
    fn new(p: &nn::Path, width: i64, heads: i64) -> Attention {
        let bound = (6.0 / (2.0 * width as f64)).sqrt();
        Attention {
            in_proj_weight: p.var("in_proj_weight", &[3 * width, width], nn::Init::Uniform { lo: -bound, up: bound }),
            in_proj_bias: p.zeros("in_proj_bias", &[3 * width]),
            out_proj: nn::linear(p / "out_proj", width, width, Default::default()),
            heads,
        }
    }

    /// `x`: (batch, tokens, width).
    fn forward(&self, x: &Tensor, causal: bool) -> Tensor {
        let (b, t, w) = x.size3().expect("(batch, tokens, width)");
        let qkv = x.linear(&self.in_proj_weight, Some(&self.in_proj_bias));
        let split = |i: i64| qkv.narrow(2, i * w, w).view([b, t, self.heads, w / self.heads]).transpose(1, 2);
        let out = Tensor::scaled_dot_product_attention::<Tensor>(&split(0), &split(1), &split(2), None, 0.0, causal, None, false);
        self.out_proj.forward(&out.transpose(1, 2).contiguous().view([b, t, w]))
    }
}

/// A pre-LN residual block: x + attn(ln_1(x)), then x + mlp(ln_2(x)).
#[derive(Debug)]
struct ResidualBlock {
    ln_1: nn::LayerNorm,
    attn: Attention,
    ln_2: nn::LayerNorm,
    c_fc: nn::Linear,
    c_proj: nn::Linear,
    activation: Activation,
}

impl ResidualBlock {
    fn new(p: &nn::Path, width: i64, heads: i64, mlp: i64, activation: Activation) -> ResidualBlock {
        ResidualBlock {
            ln_1: nn::layer_norm(p / "ln_1", vec![width], Default::default()),
            attn: Attention::new(&(p / "attn"), width, heads),
            ln_2: nn::layer_norm(p / "ln_2", vec![width], Default::default()),
            c_fc: nn::linear(p / "mlp" / "c_fc", width, mlp, Default::default()),
            c_proj: nn::linear(p / "mlp" / "c_proj", mlp, width, Default::default()),
            activation,
        }
    }

    fn forward(&self, x: &Tensor, causal: bool) -> Tensor {
        let x = x + self.attn.forward(&self.ln_1.forward(x), causal);
        let h = self.activation.apply(&self.c_fc.forward(&self.ln_2.forward(&x)));
        &x + self.c_proj.forward(&h)
    }
}

/// `layers` residual blocks (`resblocks.N`).
#[derive(Debug)]
pub struct Transformer {
    blocks: Vec<ResidualBlock>,
    causal: bool,
}

impl Transformer {
    pub fn new(p: &nn::Path, width: i64, layers: i64, heads: i64, mlp: i64, activation: Activation, causal: bool) -> Transformer {
        let blocks = (0..layers).map(|i| ResidualBlock::new(&(p / "resblocks" / i), width, heads, mlp, activation)).collect();
        Transformer { blocks, causal }
    }

    pub fn forward(&self, x: &Tensor) -> Tensor {
        self.blocks.iter().fold(x.shallow_clone(), |x, block| block.forward(&x, self.causal))
    }
}
