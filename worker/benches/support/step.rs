//! The training step the `step` and `numerics` benchmarks time: CLIP's two towers on synthetic
//! data (fixed pixels, seeded tokens and counts), SG-CLIP loss, clipping and AdamW, on the CPU.

use std::time::Instant;

use rlmflow_nn::clip::{Clip, images_from_u8, logits};
use rlmflow_nn::loss::{Distance, soft_clip_loss, soft_targets};
use rlmflow_nn::optim::AdamW;
use rlmflow_nn::tch::{self, Kind, Tensor, nn};

/// Runs `steps` training steps (after two warm-up steps) of a freshly seeded model of `config`
/// at `batch`: the median milliseconds of a step, and the trained weights.
pub fn train(config: &rlmflow_stages::encoder::ModelConfig, batch: i64, steps: usize) -> (f64, nn::VarStore) {
    tch::manual_seed(0);
    let vs = nn::VarStore::new(tch::Device::Cpu);
    let model = Clip::new(&vs.root(), config, 0.07, false);
    let mut opt = AdamW::new(&vs, (0.9, 0.98), 1e-8, 0.05);
    let side = config.vision.image;
    let text = config.text.as_ref().expect("a text tower");
    let pixels: Vec<u8> = (0..batch * side * side).map(|i| (i * 2_654_435_761 % 251) as u8).collect();
    let images = images_from_u8(&pixels, batch, side, tch::Device::Cpu);
    let tokens = Tensor::randint_low(3, text.vocab, [batch, text.context], (Kind::Int64, tch::Device::Cpu));
    let _ = tokens.narrow(1, text.context / 2, 1).fill_(text.end_token);
    let counts = Tensor::randint(3, [batch, 48], (Kind::Float, tch::Device::Cpu));
    let mut times = Vec::new();
    for _ in 0..steps + 2 {
        let t0 = Instant::now();
        let image = model.encode_image(&images, true).embedding;
        let l = logits(&image, &model.encode_text(&tokens), &model.scale());
        let loss = soft_clip_loss(&l, &soft_targets(&counts, 4.0, Distance::Raw));
        let grads = opt.gradients(&loss);
        AdamW::clip_grad_norm(&grads, 1.0);
        opt.step(&grads, 1e-4);
        times.push(t0.elapsed().as_secs_f64() * 1000.0);
    }
    (median(times.split_off(2)), vs)
}

pub fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}
