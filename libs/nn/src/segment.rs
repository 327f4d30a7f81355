//! Segmentation heads and their loss: the PUP decoder on a frozen radar tower's patch tokens,
//! the U-Net baseline on pixels, and the paper's Dice + BCE loss. Both heads give logits of
//! (batch, 1, side, side); a sigmoid makes them probabilities.

use tch::nn::{self, Module, ModuleT};
use tch::{Kind, Reduction, Tensor};

/// Conv 3x3 (no bias), BatchNorm, ReLU.
#[derive(Debug)]
struct ConvBnRelu {
    conv: nn::Conv2D,
    bn: nn::BatchNorm,
}

impl ConvBnRelu {
    fn new(p: &nn::Path, input: i64, output: i64) -> ConvBnRelu {
        let config = nn::ConvConfig { padding: 1, bias: false, ..Default::default() };
        ConvBnRelu { conv: nn::conv2d(p / "conv", input, output, 3, config), bn: nn::batch_norm2d(p / "bn", output, Default::default()) }
    }

    fn forward_t(&self, x: &Tensor, train: bool) -> Tensor {
        self.bn.forward_t(&self.conv.forward(x), train).relu()
    }
}

/// Bilinear interpolation from `from` points to `to` (`align_corners = false`, as libtorch's
/// `upsample_bilinear2d`): a (to, from) matrix, each row two weights summing to one.
fn interpolation(from: i64, to: i64, device: tch::Device) -> Tensor {
    let scale = from as f64 / to as f64;
    let mut weights = vec![0f32; (to * from) as usize];
    for i in 0..to {
        let source = ((i as f64 + 0.5) * scale - 0.5).max(0.0);
        let low = (source as i64).min(from - 1);
        let high = (low + 1).min(from - 1);
        let share = (source - low as f64) as f32;
        weights[(i * from + low) as usize] += 1.0 - share;
        weights[(i * from + high) as usize] += share;
    }
    Tensor::from_slice(&weights).view([to, from]).to_device(device)
}

/// Bilinear upsampling of (batch, channels, h, w) maps to `side` x `side`, as two matrix
/// products: libtorch's `upsample_bilinear2d` has no deterministic backward on CUDA (its
/// deterministic mode refuses it), a matmul's is; and the CPU computes what CUDA does.
fn upsample(x: &Tensor, side: i64) -> Tensor {
    let (h, w) = (x.size()[2], x.size()[3]);
    interpolation(h, side, x.device()).matmul(x).matmul(&interpolation(w, side, x.device()).tr())
}

/// Progressive upsampling (SETR's PUP, the paper's table, widths from
/// `rlmflow_segment::pup_widths`): the patch tokens after `ln_post`,
/// CLS dropped, as a (width, grid, grid) map; per stage a conv 3x3 + BN + ReLU and a bilinear
/// 2x upsampling; a final bilinear resize when the doublings do not land on `side`; a conv 1x1 to
/// one channel. Names: `stages.N.{conv,bn}`, `out`.
#[derive(Debug)]
pub struct Pup {
    stages: Vec<ConvBnRelu>,
    out: nn::Conv2D,
    side: i64,
}

impl Pup {
    pub fn new(p: &nn::Path, width: i64, widths: &[i64], side: i64) -> Pup {
        let mut input = width;
        let stages = widths
            .iter()
            .enumerate()
            .map(|(i, &w)| {
                let stage = ConvBnRelu::new(&(p / "stages" / i), input, w);
                input = w;
                stage
            })
            .collect();
        Pup { stages, out: nn::conv2d(p / "out", input, 1, 1, Default::default()), side }
    }

    /// `tokens`: (batch, 1 + grid², width), CLS first.
    pub fn forward_t(&self, tokens: &Tensor, train: bool) -> Tensor {
        let (b, t, w) = tokens.size3().expect("(batch, tokens, width)");
        let grid = ((t - 1) as f64).sqrt().round() as i64;
        assert_eq!(grid * grid, t - 1, "a square grid of patch tokens after the CLS token");
        let map = tokens.narrow(1, 1, t - 1).transpose(1, 2).contiguous().view([b, w, grid, grid]);
        let x = self.stages.iter().fold(map, |x, stage| {
            let x = stage.forward_t(&x, train);
            let side = x.size()[2] * 2;
            upsample(&x, side)
        });
        let x = if x.size()[2] == self.side { x } else { upsample(&x, self.side) };
        self.out.forward(&x)
    }
}

/// Two conv 3x3 + BN + ReLU.
#[derive(Debug)]
struct DoubleConv(ConvBnRelu, ConvBnRelu);

impl DoubleConv {
    fn new(p: &nn::Path, input: i64, output: i64) -> DoubleConv {
        DoubleConv(ConvBnRelu::new(&(p / "0"), input, output), ConvBnRelu::new(&(p / "1"), output, output))
    }

    fn forward_t(&self, x: &Tensor, train: bool) -> Tensor {
        self.1.forward_t(&self.0.forward_t(x, train), train)
    }
}

/// U-Net (Ronneberger et al., 2015) on one-channel images: per level of `widths` a double
/// conv, max-pooled 2x between levels; back up by bilinear 2x upsampling, concatenation with the
/// level's features and a double conv; a conv 1x1 to one channel. The image side must divide
/// by 2^(levels - 1). Names: `down.N`, `up.N`, `out`.
#[derive(Debug)]
pub struct UNet {
    down: Vec<DoubleConv>,
    up: Vec<DoubleConv>,
    out: nn::Conv2D,
}

impl UNet {
    pub fn new(p: &nn::Path, widths: &[i64]) -> UNet {
        let mut input = 1;
        let down = widths
            .iter()
            .enumerate()
            .map(|(i, &w)| {
                let level = DoubleConv::new(&(p / "down" / i), input, w);
                input = w;
                level
            })
            .collect();
        let up = (0..widths.len() - 1).rev().map(|i| DoubleConv::new(&(p / "up" / i), widths[i + 1] + widths[i], widths[i])).collect();
        UNet { down, up, out: nn::conv2d(p / "out", widths[0], 1, 1, Default::default()) }
    }

    /// `images`: (batch, 1, side, side), normalised.
    pub fn forward_t(&self, images: &Tensor, train: bool) -> Tensor {
        let mut skips = Vec::with_capacity(self.down.len());
        let mut x = images.shallow_clone();
        for (i, level) in self.down.iter().enumerate() {
            if i > 0 {
                x = x.max_pool2d([2, 2], [2, 2], [0, 0], [1, 1], false);
            }
            x = level.forward_t(&x, train);
            skips.push(x.shallow_clone());
        }
        skips.pop();
        for level in &self.up {
            let skip = skips.pop().expect("one skip per level going up");
            x = level.forward_t(&Tensor::cat(&[upsample(&x, skip.size()[2]), skip], 1), train);
        }
        self.out.forward(&x)
    }
}

/// The paper's segmentation loss: `dice_weight` * soft Dice (per frame, eps 1e-8, averaged) +
/// (1 - `dice_weight`) * binary cross-entropy, from logits against targets in [0, 1].
pub fn dice_bce_loss(logits: &Tensor, target: &Tensor, dice_weight: f64) -> Tensor {
    let p = logits.sigmoid().flatten(1, -1);
    let t = target.flatten(1, -1);
    let sum = |x: &Tensor| x.sum_dim_intlist([1].as_slice(), false, Kind::Float);
    let overlap: Tensor = (sum(&(&p * &t)) * 2.0 + 1e-8) / (sum(&p) + sum(&t) + 1e-8);
    let dice = overlap.neg() + 1.0;
    let bce = logits.binary_cross_entropy_with_logits::<Tensor>(target, None, None, Reduction::Mean);
    dice.mean(Kind::Float) * dice_weight + bce * (1.0 - dice_weight)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn upsampling_by_matrices_is_libtorchs_bilinear_upsampling() {
        let _generator = crate::generator();
        for (from, to) in [(2, 4), (7, 14), (14, 224), (5, 12), (28, 32)] {
            let x = Tensor::randn([2, 3, from, from], (tch::Kind::Float, tch::Device::Cpu));
            let ours = upsample(&x, to);
            let theirs = x.upsample_bilinear2d([to, to], false, None, None);
            assert!(ours.allclose(&theirs, 1e-5, 1e-5, false), "{from} -> {to}: {}", (ours - theirs).abs().max());
        }
    }

    #[test]
    fn dice_bce_is_small_for_a_confident_right_answer_and_large_for_a_wrong_one() {
        let _generator = crate::generator();
        let target = Tensor::from_slice(&[1.0f32, 0.0, 0.0, 0.0]).view([1, 1, 2, 2]);
        let right = &target * 20.0 - 10.0;
        let wrong = -&right;
        let loss = |l: &Tensor| dice_bce_loss(l, &target, 0.6).double_value(&[]);
        assert!(loss(&right) < 0.01, "{}", loss(&right));
        assert!(loss(&wrong) > 0.6 + 0.4 * 9.0, "{}", loss(&wrong));
        // Pure Dice of a half-right prediction by hand: p = (1, 1, 0, 0) -> 1 - 2 / 3.
        let half = Tensor::from_slice(&[100.0f32, 100.0, -100.0, -100.0]).view([1, 1, 2, 2]);
        assert!((dice_bce_loss(&half, &target, 1.0).double_value(&[]) - 1.0 / 3.0).abs() < 1e-5);
    }
}
