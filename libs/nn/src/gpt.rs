//! ClipCap's two parts (Mokady et al., 2021): a transformer mapper from a frozen encoder's
//! embedding to `prefix` embeddings, and a GPT-2-style causal decoder that continues them with
//! caption tokens. The decoder's tensors are named as Hugging Face's `GPT2Model` at the ends
//! (`wte`, `wpe`, `ln_f`; the head is tied to `wte`) and as open_clip's blocks in between
//! (`transformer.resblocks.N`); [`crate::start::GPT2`] maps GPT-2 weights onto them.

use tch::nn::{self, Module};
use tch::{Kind, Tensor};

use crate::decode::StepModel;
use crate::transformer::{Activation, KvCache, Transformer};

/// A decoder's shape.
#[derive(Clone, Debug, PartialEq)]
pub struct GptConfig {
    pub vocab: i64,
    /// Positions: the prefix plus the longest caption.
    pub positions: i64,
    pub width: i64,
    pub layers: i64,
    pub heads: i64,
    pub mlp: i64,
}

#[derive(Debug)]
pub struct Gpt {
    wte: Tensor,
    wpe: Tensor,
    transformer: Transformer,
    ln_f: nn::LayerNorm,
    pub config: GptConfig,
}

impl Gpt {
    pub fn new(p: &nn::Path, c: &GptConfig) -> Gpt {
        let init = nn::Init::Randn { mean: 0.0, stdev: 0.02 };
        Gpt {
            wte: (p / "wte").var("weight", &[c.vocab, c.width], init),
            wpe: (p / "wpe").var("weight", &[c.positions, c.width], nn::Init::Randn { mean: 0.0, stdev: 0.01 }),
            transformer: Transformer::new(&(p / "transformer"), c.width, c.layers, c.heads, c.mlp, Activation::GeluTanh, true),
            ln_f: nn::layer_norm(p / "ln_f", vec![c.width], Default::default()),
            config: c.clone(),
        }
    }

    /// Token embeddings of ids (batch, tokens).
    pub fn embed(&self, ids: &Tensor) -> Tensor {
        Tensor::embedding(&self.wte, ids, -1, false, false)
    }

    /// Next-token logits at every position of embeddings `x` (batch, tokens, width), which start
    /// at position 0: (batch, tokens, vocab).
    pub fn forward(&self, x: &Tensor) -> Tensor {
        let t = x.size()[1];
        self.head(&self.transformer.forward(&(x + self.wpe.narrow(0, 0, t))))
    }

    /// The same one step at a time: `x` holds the positions from `start` on (the prompt first,
    /// then one token per call); logits of those positions.
    pub fn forward_cached(&self, x: &Tensor, start: i64, cache: &mut KvCache) -> Tensor {
        let t = x.size()[1];
        self.head(&self.transformer.forward_cached(&(x + self.wpe.narrow(0, start, t)), cache))
    }

    fn head(&self, x: &Tensor) -> Tensor {
        self.ln_f.forward(x).matmul(&self.wte.tr())
    }
}

/// ClipCap's transformer mapper: the embedding linearly mapped to `prefix` tokens, followed by
/// `prefix` learnt constants; after the transformer the constants' positions are the prefix.
/// Names: `linear`, `prefix_const`, `transformer`.
#[derive(Debug)]
pub struct Mapper {
    linear: nn::Linear,
    prefix_const: Tensor,
    transformer: Transformer,
    prefix: i64,
}

impl Mapper {
    pub fn new(p: &nn::Path, embed: i64, width: i64, prefix: i64, layers: i64, heads: i64) -> Mapper {
        Mapper {
            linear: nn::linear(p / "linear", embed, prefix * width, Default::default()),
            prefix_const: p.randn_standard("prefix_const", &[prefix, width]),
            transformer: Transformer::new(&(p / "transformer"), width, layers, heads, 4 * width, Activation::Gelu, false),
            prefix,
        }
    }

    /// (batch, embed) -> (batch, prefix, width).
    pub fn forward(&self, embedding: &Tensor) -> Tensor {
        let b = embedding.size()[0];
        let mapped = self.linear.forward(embedding).view([b, self.prefix, -1]);
        let constants = self.prefix_const.unsqueeze(0).expand([b, -1, -1], false);
        self.transformer.forward(&Tensor::cat(&[mapped, constants], 1)).narrow(1, self.prefix, self.prefix)
    }
}

/// Teacher-forced cross-entropy of captions after their prefixes: `ids` (batch, tokens) start
/// with the start token and end in padding (`pad`, not scored); position k + j predicts token
/// j + 1. The mean over every scored token of the batch, computed in `groups` groups of rows of
/// similar length, each cut to its own longest caption: one long caption would otherwise pad
/// every row to its length, and with template captions (131 tokens on average, 217 at most)
/// that padding is a third of the work. The groups change only the order of the sums, not the
/// loss or its gradient.
pub fn caption_loss(gpt: &Gpt, prefix: &Tensor, ids: &Tensor, pad: i64, groups: usize) -> Tensor {
    let lengths = Vec::<i64>::try_from(ids.ne(pad).sum_dim_intlist([1].as_slice(), false, Kind::Int64).to_device(tch::Device::Cpu)).expect("lengths");
    let mut rows: Vec<usize> = (0..lengths.len()).collect();
    rows.sort_by_key(|&r| (lengths[r], r));
    let per_group = rows.len().div_ceil(groups.max(1)).max(1);
    let k = prefix.size()[1];
    let mut total = Tensor::zeros([], (Kind::Float, prefix.device()));
    for group in rows.chunks(per_group) {
        let t = group.iter().map(|&r| lengths[r]).max().unwrap_or(0).max(2);
        let index = Tensor::from_slice(&group.iter().map(|&r| r as i64).collect::<Vec<_>>()).to_device(ids.device());
        let ids = ids.index_select(0, &index).narrow(1, 0, t);
        let inputs = gpt.embed(&ids.narrow(1, 0, t - 1));
        let logits = gpt.forward(&Tensor::cat(&[prefix.index_select(0, &index), inputs], 1));
        let predicted = logits.narrow(1, k, t - 1).flatten(0, 1);
        let summed = predicted.cross_entropy_loss::<Tensor>(&ids.narrow(1, 1, t - 1).flatten(0, 1), None, tch::Reduction::Sum, pad, 0.0);
        total += summed.to_kind(Kind::Float);
    }
    let scored: i64 = lengths.iter().map(|&l| (l - 1).max(0)).sum();
    total / scored.max(1) as f64
}

/// A decoder stepped over cached keys and values from each row's prefix and the start token.
pub struct Steps<'a> {
    gpt: &'a Gpt,
    prompt: Option<Tensor>,
    cache: KvCache,
    position: i64,
}

impl<'a> Steps<'a> {
    /// `prefix` (rows, k, width) is followed by `start_token`.
    pub fn new(gpt: &'a Gpt, prefix: &Tensor, start_token: i64) -> Steps<'a> {
        let rows = prefix.size()[0];
        let start = Tensor::full([rows, 1], start_token, (Kind::Int64, prefix.device()));
        Steps { gpt, prompt: Some(Tensor::cat(&[prefix.shallow_clone(), gpt.embed(&start)], 1)), cache: KvCache::default(), position: 0 }
    }

    fn last_log_probs(&mut self, x: &Tensor) -> Tensor {
        let logits = self.gpt.forward_cached(x, self.position, &mut self.cache);
        self.position += x.size()[1];
        logits.select(1, -1).log_softmax(-1, Kind::Float)
    }
}

impl StepModel for Steps<'_> {
    fn device(&self) -> tch::Device {
        self.gpt.wte.device()
    }

    fn start(&mut self) -> Tensor {
        let prompt = self.prompt.take().expect("start is called once");
        self.last_log_probs(&prompt)
    }

    fn next(&mut self, parents: Option<&Tensor>, tokens: &Tensor) -> Tensor {
        if let Some(parents) = parents {
            self.cache.select(parents);
        }
        let x = self.gpt.embed(tokens);
        self.last_log_probs(&x)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(shape: &[i64], offset: f64) -> Tensor {
        let n: i64 = shape.iter().product();
        (Tensor::arange(n, (Kind::Float, tch::Device::Cpu)) / n as f64 + offset).view(shape)
    }

    #[test]
    fn gpt2_weights_load_transposed_and_a_foreign_vocabulary_is_skipped() {
        let _generator = crate::generator();
        let config = GptConfig { vocab: 11, positions: 9, width: 8, layers: 2, heads: 2, mlp: 32 };
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let _gpt = Gpt::new(&(vs.root() / "gpt"), &config);
        // Hugging Face GPT2LMHeadModel names: Conv1D kernels are (in, out); vocabulary 50 != 11.
        let mut tensors = vec![
            ("transformer.wte.weight".to_owned(), ramp(&[50, 8], 0.0)),
            ("transformer.wpe.weight".to_owned(), ramp(&[9, 8], 1.0)),
            ("transformer.ln_f.weight".to_owned(), ramp(&[8], 2.0)),
            ("transformer.ln_f.bias".to_owned(), ramp(&[8], 3.0)),
        ];
        for i in 0..2 {
            let h = |k: &str| format!("transformer.h.{i}.{k}");
            for (k, shape) in [
                ("attn.c_attn.weight", vec![8, 24]),
                ("attn.c_attn.bias", vec![24]),
                ("attn.c_proj.weight", vec![8, 8]),
                ("attn.c_proj.bias", vec![8]),
                ("mlp.c_fc.weight", vec![8, 32]),
                ("mlp.c_fc.bias", vec![32]),
                ("mlp.c_proj.weight", vec![32, 8]),
                ("mlp.c_proj.bias", vec![8]),
                ("ln_1.weight", vec![8]),
                ("ln_1.bias", vec![8]),
                ("ln_2.weight", vec![8]),
                ("ln_2.bias", vec![8]),
            ] {
                tensors.push((h(k), ramp(&shape, 10.0 + i as f64)));
            }
        }
        let dir = std::env::temp_dir().join(format!("rlmflow-gpt2-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("gpt2.safetensors");
        Tensor::write_safetensors(&tensors, &file).unwrap();
        let total = vs.variables().len();
        assert_eq!(crate::start::load(&vs, "gpt.", &file, &crate::start::GPT2).unwrap(), total - 1, "everything but the foreign token table");
        let source: std::collections::HashMap<String, Tensor> = tensors.into_iter().collect();
        let ours = vs.variables();
        assert!(ours["gpt.transformer.resblocks.1.attn.in_proj_weight"].equal(&source["transformer.h.1.attn.c_attn.weight"].tr()));
        assert!(ours["gpt.transformer.resblocks.0.mlp.c_proj.weight"].equal(&source["transformer.h.0.mlp.c_proj.weight"].tr()));
        assert!(ours["gpt.wpe.weight"].equal(&source["transformer.wpe.weight"]));
        assert!(!ours["gpt.wte.weight"].equal(&source["transformer.wte.weight"].narrow(0, 0, 11)));

        let wrong = vec![("h.0.ln_1.weight".to_owned(), ramp(&[768], 0.0))];
        Tensor::write_safetensors(&wrong, &file).unwrap();
        let err = crate::start::load(&vs, "gpt.", &file, &crate::start::GPT2).unwrap_err().to_string();
        assert!(err.contains("`gpt.transformer.resblocks.0.ln_1.weight` has shape [768], the model needs [8]"), "{err}");
        Tensor::write_safetensors(&[("unrelated".to_owned(), ramp(&[2], 0.0))], &file).unwrap();
        assert!(crate::start::load(&vs, "gpt.", &file, &crate::start::GPT2).unwrap_err().to_string().contains("no tensor with GPT-2 names"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn grouping_rows_by_length_keeps_the_loss_and_its_gradient() {
        let _generator = crate::generator();
        tch::manual_seed(3);
        let config = GptConfig { vocab: 13, positions: 12, width: 16, layers: 2, heads: 2, mlp: 32 };
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let gpt = Gpt::new(&vs.root(), &config);
        let prefix = Tensor::randn([5, 3, 16], (Kind::Float, tch::Device::Cpu));
        // Five captions of 2 to 8 tokens, padded with 0.
        let rows: [&[i64]; 5] = [&[1, 4, 7, 9, 2, 5, 6, 3], &[1, 2], &[1, 8, 3, 4, 10], &[1, 11, 12], &[1, 5, 5, 5, 5, 5, 9]];
        let ids: Vec<i64> = rows.iter().flat_map(|r| r.iter().copied().chain(std::iter::repeat(0)).take(8)).collect();
        let ids = Tensor::from_slice(&ids).view([5, 8]);
        let weights: Vec<Tensor> = vs.trainable_variables();
        let mut losses = Vec::new();
        for groups in [1, 2, 5] {
            let loss = caption_loss(&gpt, &prefix, &ids, 0, groups);
            let grads = Tensor::run_backward(&[&loss], &weights.iter().collect::<Vec<_>>(), false, false);
            losses.push((loss.double_value(&[]), grads));
        }
        // The unpadded reference: every scored token's cross-entropy, averaged.
        let mut sum = 0.0;
        for (r, caption) in rows.iter().enumerate() {
            let t = caption.len() as i64;
            let x = Tensor::cat(&[prefix.narrow(0, r as i64, 1), gpt.embed(&ids.narrow(0, r as i64, 1).narrow(1, 0, t - 1))], 1);
            let logits = gpt.forward(&x).narrow(1, 3, t - 1).squeeze_dim(0);
            sum += logits.cross_entropy_loss::<Tensor>(&ids.get(r as i64).narrow(0, 1, t - 1), None, tch::Reduction::Sum, 0, 0.0).double_value(&[]);
        }
        let reference = sum / rows.iter().map(|r| r.len() - 1).sum::<usize>() as f64;
        for (loss, grads) in &losses {
            assert!((loss - reference).abs() < 1e-5, "{loss} != {reference}");
            for (g, g1) in grads.iter().zip(&losses[0].1) {
                assert!((g - g1).abs().max().double_value(&[]) < 1e-5);
            }
        }
    }

    #[test]
    fn cached_decoding_gives_the_full_pass_logits() {
        let _generator = crate::generator();
        tch::manual_seed(5);
        let config = GptConfig { vocab: 13, positions: 12, width: 16, layers: 2, heads: 2, mlp: 32 };
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let gpt = Gpt::new(&vs.root(), &config);
        let prefix = Tensor::randn([2, 3, 16], (Kind::Float, tch::Device::Cpu));
        let ids = Tensor::from_slice(&[1i64, 4, 7, 1, 9, 2]).view([2, 3]);
        let full = gpt.forward(&Tensor::cat(&[prefix.shallow_clone(), gpt.embed(&ids)], 1)).log_softmax(-1, Kind::Float);
        let mut steps = Steps::new(&gpt, &prefix, 1);
        let first = steps.start();
        assert!((first - full.select(1, 3)).abs().max().double_value(&[]) < 1e-5);
        let next = steps.next(None, &ids.narrow(1, 1, 1));
        assert!((next - full.select(1, 4)).abs().max().double_value(&[]) < 1e-5);
    }
}
