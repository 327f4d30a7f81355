//! What a training action will hold in memory at its peak, estimated from model shapes alone
//! before it runs: `rlmflow run --dry-run` and `status` show it, and a run refuses a stage whose
//! estimate exceeds its device's memory.
//!
//! The estimate counts what dominates, in float32: every weight (4 bytes); for trained weights
//! also the gradient and AdamW's two moments (16 bytes a parameter in all); and the activations
//! a training step keeps for its backward pass, per sample, times the samples a step holds at
//! once (the batch, or the chunk under gradient caching), in float32 or, under bf16 autocast,
//! at [`activation_bytes`]' measured share. Transient buffers, the allocator's
//! slack and the CUDA context are not counted: the refusal leaves [`HEADROOM`] of the device
//! for them.

use serde::Serialize;

use crate::numerics::Precision;

pub const FLOAT: u64 = 4;
/// Bytes per trained parameter: the weight, its gradient and AdamW's two moments.
pub const TRAINED: u64 = 4 * FLOAT;
/// The share of a device's memory an estimate may fill.
pub const HEADROOM: f64 = 0.9;

/// An action's estimate, as `--dry-run` shows it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Footprint {
    /// Parameters of every model the action holds, trained or frozen.
    pub parameters: u64,
    /// Estimated peak bytes on the device it trains on.
    pub peak_bytes: u64,
    /// The settings that lower the estimate, for the refusal: "`chunk` or `batch`".
    pub lower_with: &'static str,
}

/// Bytes `floats` kept activations take under `precision`. Under bf16 autocast the matmuls keep
/// bfloat16 inputs while norms, softmax and the loss keep float32: on an H100 the paper model's
/// activations took 52-59 % of their float32 bytes (three batch and chunk sizes, `cargo xtask
/// device-check`; docs/guide/paper-scale.md), and 55 % puts all three peaks within 6 %.
pub fn activation_bytes(floats: u64, precision: Precision) -> u64 {
    match precision {
        Precision::Bf16 => floats * FLOAT * 55 / 100,
        Precision::Auto | Precision::Fp32 | Precision::Tf32 => floats * FLOAT,
    }
}

/// A stack of pre-LN residual blocks (attention and an MLP of `mlp` units), as `rlmflow-nn`
/// builds them.
pub struct Blocks {
    pub width: u64,
    pub layers: u64,
    pub mlp: u64,
    /// QuickGELU keeps two more tensors of the MLP's width than GELU.
    pub quick_gelu: bool,
}

impl Blocks {
    pub fn parameters(&self) -> u64 {
        let (w, m) = (self.width, self.mlp);
        let attention = 3 * w * w + 3 * w + w * w + w;
        let mlp = w * m + m + m * w + w;
        let norms = 4 * w;
        self.layers * (attention + mlp + norms)
    }

    /// Floats a training step keeps per sample of `tokens` tokens: per block and token the two
    /// LayerNorms' inputs and outputs, the queries, keys and values, the attention output and
    /// the MLP's hidden units before and after the activation (fused attention keeps no tokens x
    /// tokens map).
    pub fn activations(&self, tokens: u64) -> u64 {
        let hidden = if self.quick_gelu { 4 } else { 2 };
        self.layers * tokens * (8 * self.width + hidden * self.mlp)
    }
}

/// The parameters of a linear layer with bias.
pub fn linear(input: u64, output: u64) -> u64 {
    input * output + output
}

/// The parameters of a 3x3 convolution without bias and its BatchNorm's scale and shift.
pub fn conv3x3_bn(input: u64, output: u64) -> u64 {
    9 * input * output + 2 * output
}

/// What a refusal suggests for a loss that averages over frames.
pub const LOWER_BY_ACCUMULATING: &str = "`accumulate` (the same gradient) or `batch`";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn block_parameters_match_a_hand_count_of_vit_b16() {
        // ViT-B/16's 12 blocks hold 85.05 M parameters (open_clip: 85,054,464).
        let blocks = Blocks { width: 768, layers: 12, mlp: 3072, quick_gelu: false };
        assert_eq!(blocks.parameters(), 85_054_464);
    }
}
