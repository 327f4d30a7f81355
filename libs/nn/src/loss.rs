//! Contrastive objectives over a batch's cosine logits (rows radar, columns text).
//!
//! * CLIP: symmetric cross-entropy against the identity.
//! * SG-CLIP (the paper's): soft targets from scene similarity. d_ij is the L1 distance of the
//!   two frames' 48-cell count vectors, s_ij = exp(-alpha d_ij^2), T = s with rows normalised;
//!   the loss is the mean of the two soft cross-entropies. When every pair of frames differs
//!   and alpha is large, T is the identity and SG-CLIP is CLIP.

pub use rlmflow_stages::encoder::Distance;
use tch::{Kind, Reduction, Tensor};

/// Symmetric cross-entropy against the identity.
pub fn clip_loss(logits: &Tensor) -> Tensor {
    let n = logits.size()[0];
    let labels = Tensor::arange(n, (Kind::Int64, logits.device()));
    let ce = |l: &Tensor| l.cross_entropy_loss::<Tensor>(&labels, None, Reduction::Mean, -100, 0.0);
    (ce(logits) + ce(&logits.tr())) / 2.0
}

/// Row-normalised similarity targets from (batch, 48) counts.
pub fn soft_targets(counts: &Tensor, alpha: f64, distance: Distance) -> Tensor {
    let kind = if counts.is_floating_point() { counts.kind() } else { Kind::Float };
    let counts = counts.to_kind(kind);
    let d = (counts.unsqueeze(1) - counts.unsqueeze(0)).abs().sum_dim_intlist([-1].as_slice(), false, kind);
    let d = match distance {
        Distance::Raw => d,
        Distance::PairTotal => {
            let totals = counts.sum_dim_intlist([-1].as_slice(), false, kind);
            d / (totals.unsqueeze(1) + totals.unsqueeze(0)).clamp_min(1.0)
        }
    };
    let s = (-(d.square()) * alpha).exp();
    &s / s.sum_dim_intlist([1].as_slice(), true, kind)
}

/// The mean of the two soft cross-entropies (radar->text against `targets`, text->radar
/// against its transpose, rows normalised).
pub fn soft_clip_loss(logits: &Tensor, targets: &Tensor) -> Tensor {
    let kind = logits.kind();
    let ce = |l: &Tensor, t: &Tensor| -(t * l.log_softmax(1, kind)).sum_dim_intlist([1].as_slice(), false, kind).mean(kind);
    let transposed = targets.tr();
    let transposed = &transposed / transposed.sum_dim_intlist([1].as_slice(), true, kind);
    (ce(logits, targets) + ce(&logits.tr(), &transposed)) / 2.0
}

/// The share of target mass off the diagonal, averaged over rows: 0 for CLIP.
pub fn off_diagonal_mass(targets: &Tensor) -> f64 {
    1.0 - targets.diagonal(0, 0, 1).mean(targets.kind()).double_value(&[])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sg_clip_is_clip_when_every_pair_differs_and_alpha_is_large() {
        let counts = Tensor::from_slice(&[0f32, 1., 2., 3., 2., 0., 1., 5., 4., 4., 0., 0.]).view([3, 4]);
        let targets = soft_targets(&counts, 50.0, Distance::Raw);
        assert!(off_diagonal_mass(&targets) < 1e-9);
        let logits = Tensor::from_slice(&[3f32, 0.5, -1., 0.2, 2., 0.1, -0.3, 0.4, 1.5]).view([3, 3]);
        let (soft, hard) = (soft_clip_loss(&logits, &targets).double_value(&[]), clip_loss(&logits).double_value(&[]));
        assert!((soft - hard).abs() < 1e-6, "{soft} vs {hard}");
        // Identical scenes share their mass.
        let same = Tensor::from_slice(&[1f32, 2., 1., 2., 0., 9.]).view([3, 2]);
        let t = soft_targets(&same, 1.0, Distance::Raw);
        assert!((t.double_value(&[0, 1]) - 0.5).abs() < 1e-6 && (off_diagonal_mass(&t) - 1.0 / 3.0).abs() < 1e-6);
    }
}
