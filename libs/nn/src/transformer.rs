//! The residual attention blocks both towers share, named as open_clip's `transformer.py`
//! (`resblocks.N.ln_1`, `attn.in_proj_weight`, `attn.out_proj`, `ln_2`, `mlp.c_fc`, `mlp.c_proj`).

use rlmflow_stages::numerics::{ATTENTION_BY_PRODUCTS, ATTENTION_VARIABLE};
use tch::nn::{self, Module};
use tch::{Device, Kind, Tensor};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Activation {
    Gelu,
    /// x * sigmoid(1.702 x), as OpenAI's CLIP text tower.
    QuickGelu,
    /// GELU's tanh approximation, as GPT-2.
    GeluTanh,
}

impl Activation {
    fn apply(self, x: &Tensor) -> Tensor {
        match self {
            Activation::Gelu => x.gelu("none"),
            Activation::QuickGelu => x * (x * 1.702).sigmoid(),
            Activation::GeluTanh => x.gelu("tanh"),
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

    /// Queries, keys and values of `x` (batch, tokens, width), each (batch, heads, tokens, head width).
    fn qkv(&self, x: &Tensor) -> [Tensor; 3] {
        let (b, t, w) = x.size3().expect("(batch, tokens, width)");
        let qkv = x.linear(&self.in_proj_weight, Some(&self.in_proj_bias));
        std::array::from_fn(|i| qkv.narrow(2, i as i64 * w, w).view([b, t, self.heads, w / self.heads]).transpose(1, 2))
    }

    /// Heads (batch, heads, tokens, head width) joined and projected back to (batch, tokens, width).
    fn join(&self, heads: &Tensor) -> Tensor {
        let (b, h, t, d) = heads.size4().expect("(batch, heads, tokens, head width)");
        self.out_proj.forward(&heads.transpose(1, 2).contiguous().view([b, t, h * d]))
    }

    fn forward(&self, x: &Tensor, causal: bool) -> Tensor {
        let [q, k, v] = self.qkv(x);
        self.join(&attend(&q, &k, &v, causal))
    }

    /// Causal attention that remembers keys and values: the first call (no `past`) attends
    /// causally over its tokens; each later call gives one new token, which attends to every
    /// earlier one. Returns the output and the keys and values so far.
    fn forward_cached(&self, x: &Tensor, past: Option<&(Tensor, Tensor)>) -> (Tensor, (Tensor, Tensor)) {
        let [q, k, v] = self.qkv(x);
        let (k, v, causal) = match past {
            None => (k, v, true),
            Some((pk, pv)) => {
                assert_eq!(q.size()[2], 1, "one new token per cached step");
                (Tensor::cat(&[pk, &k], 2), Tensor::cat(&[pv, &v], 2), false)
            }
        };
        let out = attend(&q, &k, &v, causal);
        (self.join(&out), (k, v))
    }

    /// The same attention computed step by step, so its probabilities come out as well (the
    /// fused kernel does not return them): (output, probabilities averaged over the heads,
    /// (batch, tokens, tokens)). Not causal: for the radar tower's attention maps.
    fn forward_with_weights(&self, x: &Tensor) -> (Tensor, Tensor) {
        let [q, k, v] = self.qkv(x);
        let scale = (q.size()[3] as f64).powf(-0.5);
        let weights = (q.matmul(&k.transpose(-2, -1)) * scale).softmax(-1, q.kind());
        (self.join(&weights.matmul(&v)), weights.mean_dim([1].as_slice(), false, weights.kind()))
    }
}

/// softmax(q k^T / sqrt(d)) v over (batch, heads, tokens, head width), causal or not: ATen's fused
/// kernel, or on the CPU under the portable pins that ask for it (`RLMFLOW_ATTENTION=products`)
/// its two products and a softmax, so the products are the chain GEMM's rather than MKL's.
pub fn attend(q: &Tensor, k: &Tensor, v: &Tensor, causal: bool) -> Tensor {
    let by_products = q.device() == Device::Cpu && std::env::var(ATTENTION_VARIABLE).is_ok_and(|v| v == ATTENTION_BY_PRODUCTS);
    attend_by(q, k, v, causal, by_products)
}

fn attend_by(q: &Tensor, k: &Tensor, v: &Tensor, causal: bool, by_products: bool) -> Tensor {
    if !by_products {
        return Tensor::scaled_dot_product_attention::<Tensor>(q, k, v, None, 0.0, causal, None, false);
    }
    let (queries, keys) = (q.size()[2], k.size()[2]);
    let scores = q.matmul(&k.transpose(-2, -1)) * (q.size()[3] as f64).powf(-0.5);
    // As the fused kernel's `is_causal`: query i sees keys 0..=i.
    let scores = if causal {
        let future = Tensor::ones([queries, keys], (Kind::Bool, q.device())).triu(1);
        scores.masked_fill(&future, f64::NEG_INFINITY)
    } else {
        scores
    };
    // exp(log_softmax): ATen's CPU softmax backward gives other bits on other thread counts
    // (measured; its log_softmax backward does not), and a key's bytes must not depend on them.
    scores.log_softmax(-1, q.kind()).exp().matmul(v)
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
        self.mlp(&(x + self.attn.forward(&self.ln_1.forward(x), causal)))
    }

    fn mlp(&self, x: &Tensor) -> Tensor {
        let h = self.activation.apply(&self.c_fc.forward(&self.ln_2.forward(x)));
        x + self.c_proj.forward(&h)
    }

    fn forward_cached(&self, x: &Tensor, past: Option<&(Tensor, Tensor)>) -> (Tensor, (Tensor, Tensor)) {
        let (attended, kv) = self.attn.forward_cached(&self.ln_1.forward(x), past);
        (self.mlp(&(x + attended)), kv)
    }

    /// `forward` without a causal mask, with the block's attention probabilities.
    fn forward_with_weights(&self, x: &Tensor) -> (Tensor, Tensor) {
        let (attended, weights) = self.attn.forward_with_weights(&self.ln_1.forward(x));
        (self.mlp(&(x + attended)), weights)
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

    /// `forward` of a causal stack one step at a time: the first call with the prompt, then one
    /// token per call; `cache` keeps every block's keys and values between calls.
    pub fn forward_cached(&self, x: &Tensor, cache: &mut KvCache) -> Tensor {
        assert!(self.causal, "cached decoding is for causal stacks");
        let first = cache.layers.is_empty();
        let mut x = x.shallow_clone();
        for (i, block) in self.blocks.iter().enumerate() {
            let (out, kv) = block.forward_cached(&x, if first { None } else { Some(&cache.layers[i]) });
            if first {
                cache.layers.push(kv);
            } else {
                cache.layers[i] = kv;
            }
            x = out;
        }
        x
    }

    /// `forward` of a non-causal stack, with each block's attention probabilities averaged over
    /// the heads, (batch, tokens, tokens), first block first.
    pub fn forward_with_weights(&self, x: &Tensor) -> (Tensor, Vec<Tensor>) {
        assert!(!self.causal, "attention maps are for the radar tower");
        let mut weights = Vec::with_capacity(self.blocks.len());
        let out = self.blocks.iter().fold(x.shallow_clone(), |x, block| {
            let (out, w) = block.forward_with_weights(&x);
            weights.push(w);
            out
        });
        (out, weights)
    }
}

/// Every block's keys and values of the positions decoded so far, (batch, heads, tokens, head
/// width) each.
#[derive(Default)]
pub struct KvCache {
    layers: Vec<(Tensor, Tensor)>,
}

impl KvCache {
    /// Keeps the rows `index` names, in its order (beam search reorders and repeats rows).
    pub fn select(&mut self, index: &Tensor) {
        for (k, v) in &mut self.layers {
            *k = k.index_select(0, index);
            *v = v.index_select(0, index);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_step_by_step_attention_matches_the_fused_kernel_and_its_rows_sum_to_one() {
        let _generator = crate::generator();
        tch::manual_seed(3);
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let transformer = Transformer::new(&vs.root(), 16, 2, 4, 32, Activation::Gelu, false);
        let x = Tensor::randn([3, 5, 16], (tch::Kind::Float, tch::Device::Cpu));
        let (out, weights) = transformer.forward_with_weights(&x);
        let fused = transformer.forward(&x);
        assert!((out - fused).abs().max().double_value(&[]) < 1e-5);
        assert_eq!(weights.len(), 2);
        for w in &weights {
            assert_eq!(w.size(), [3, 5, 5]);
            let rows = w.sum_dim_intlist([-1].as_slice(), false, tch::Kind::Float);
            assert!((rows - 1.0).abs().max().double_value(&[]) < 1e-5);
        }
    }

    #[test]
    fn attention_by_products_computes_what_the_fused_kernel_does_with_its_gradients() {
        let _generator = crate::generator();
        tch::manual_seed(5);
        let r = |shape: [i64; 4]| Tensor::randn(shape, (Kind::Float, Device::Cpu)).set_requires_grad(true);
        // Self-attention, causal or not, and one cached decoding step (a query over every key).
        for (queries, keys, causal) in [(7, 7, false), (7, 7, true), (1, 9, false)] {
            let (mut q, mut k, mut v) = (r([2, 3, queries, 8]), r([2, 3, keys, 8]), r([2, 3, keys, 8]));
            let weight = Tensor::randn([2, 3, queries, 8], (Kind::Float, Device::Cpu));
            let mut run = |by_products: bool| {
                for t in [&mut q, &mut k, &mut v] {
                    t.zero_grad();
                }
                let out = attend_by(&q, &k, &v, causal, by_products);
                (&out * &weight).sum(Kind::Float).backward();
                [out.detach(), q.grad().detach().copy(), k.grad().detach().copy(), v.grad().detach().copy()]
            };
            let (fused, products) = (run(false), run(true));
            for (name, (a, b)) in ["output", "dq", "dk", "dv"].iter().zip(fused.iter().zip(&products)) {
                let gap = (a - b).abs().max().double_value(&[]);
                assert!(gap < 1e-5, "{queries}x{keys} causal {causal}: {name} differs by {gap}");
            }
        }
    }

    #[test]
    fn decoding_with_the_cache_matches_the_full_causal_pass() {
        let _generator = crate::generator();
        tch::manual_seed(4);
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let transformer = Transformer::new(&vs.root(), 16, 2, 4, 32, Activation::GeluTanh, true);
        let x = Tensor::randn([2, 6, 16], (tch::Kind::Float, tch::Device::Cpu));
        let full = transformer.forward(&x);
        let mut cache = KvCache::default();
        let mut steps = vec![transformer.forward_cached(&x.narrow(1, 0, 3), &mut cache)];
        for t in 3..6 {
            steps.push(transformer.forward_cached(&x.narrow(1, t, 1), &mut cache));
        }
        assert!((Tensor::cat(&steps, 1) - full).abs().max().double_value(&[]) < 1e-5);
    }
}
