//! What maps a tower's pooled token into the shared space, for both towers: a matrix without
//! bias (open_clip's `proj` and `text_projection`), or an MLP (linear, GELU, linear), which the
//! paper's section 3.1 describes.

use rlmflow_stages::encoder::Head;
use tch::Tensor;
use tch::nn::{self, Module};

#[derive(Debug)]
pub enum Projection {
    /// (width, embed), applied as x @ matrix.
    Linear(Tensor),
    /// `fc1` (width to width) and `fc2` (width to embed).
    Mlp(nn::Linear, nn::Linear),
}

impl Projection {
    /// The matrix is `p / linear`, the MLP lives under `p / mlp`.
    pub fn new(p: &nn::Path, head: Head, linear: &str, mlp: &str, width: i64, embed: i64) -> Projection {
        match head {
            Head::Linear => Projection::Linear(p.randn(linear, &[width, embed], 0.0, (width as f64).powf(-0.5))),
            Head::Mlp => Projection::Mlp(
                nn::linear(p / mlp / "fc1", width, width, Default::default()),
                nn::linear(p / mlp / "fc2", width, embed, Default::default()),
            ),
        }
    }

    pub fn forward(&self, x: &Tensor) -> Tensor {
        match self {
            Projection::Linear(matrix) => x.matmul(matrix),
            Projection::Mlp(fc1, fc2) => fc2.forward(&fc1.forward(x).gelu("none")),
        }
    }
}
