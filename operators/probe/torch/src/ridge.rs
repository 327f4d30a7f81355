//! Closed-form ridge regression on faer: features standardised by their training mean and
//! standard deviation, targets centred, then (XᵀX + λ n I) W = Xᵀ Y solved by Cholesky, or with
//! more features than rows its dual, W = Xᵀ (XXᵀ + λ n I)⁻¹ Y (the same W, a smaller system). Every
//! product runs sequentially, so the result does not depend on a thread count.

use anyhow::Context as _;
use faer::linalg::matmul::matmul;
use faer::linalg::solvers::Solve;
use faer::{Accum, Mat, Par, Side};

pub struct Ridge {
    mean: Vec<f64>,
    scale: Vec<f64>,
    target_mean: Vec<f64>,
    /// features x targets.
    weights: Mat<f64>,
}

impl Ridge {
    /// Fits `x` (rows of `features` values) to `y` (rows of `targets` values) with strength
    /// `lambda` per training row.
    pub fn fit(x: &[f64], features: usize, y: &[f64], targets: usize, lambda: f64) -> anyhow::Result<Ridge> {
        let n = x.len() / features;
        assert_eq!(y.len(), n * targets, "one target row per feature row");
        let column_mean =
            |data: &[f64], width: usize| -> Vec<f64> { (0..width).map(|j| (0..n).map(|i| data[i * width + j]).sum::<f64>() / n as f64).collect() };
        let mean = column_mean(x, features);
        let scale: Vec<f64> = (0..features)
            .map(|j| {
                let var = (0..n).map(|i| (x[i * features + j] - mean[j]).powi(2)).sum::<f64>() / n as f64;
                if var > 1e-12 { var.sqrt() } else { 1.0 }
            })
            .collect();
        let target_mean = column_mean(y, targets);
        let xs = Mat::from_fn(n, features, |i, j| (x[i * features + j] - mean[j]) / scale[j]);
        let yc = Mat::from_fn(n, targets, |i, j| y[i * targets + j] - target_mean[j]);
        let weights = if features <= n {
            // Primal: (XᵀX + λ n I) W = Xᵀ Y, a features x features system.
            let mut gram = Mat::<f64>::zeros(features, features);
            matmul(gram.as_mut(), Accum::Replace, xs.transpose(), xs.as_ref(), 1.0, Par::Seq);
            let mut weights = Mat::<f64>::zeros(features, targets);
            matmul(weights.as_mut(), Accum::Replace, xs.transpose(), yc.as_ref(), 1.0, Par::Seq);
            solve_regularised(gram, lambda * n as f64, weights)?
        } else {
            // Dual, for more features than rows (every patch token): W = Xᵀ (XXᵀ + λ n I)⁻¹ Y,
            // the same solution through an n x n system.
            let mut kernel = Mat::<f64>::zeros(n, n);
            matmul(kernel.as_mut(), Accum::Replace, xs.as_ref(), xs.transpose(), 1.0, Par::Seq);
            let alpha = solve_regularised(kernel, lambda * n as f64, yc)?;
            let mut weights = Mat::<f64>::zeros(features, targets);
            matmul(weights.as_mut(), Accum::Replace, xs.transpose(), alpha.as_ref(), 1.0, Par::Seq);
            weights
        };
        Ok(Ridge { mean, scale, target_mean, weights })
    }

    /// Predictions for the rows of `x`.
    pub fn predict(&self, x: &[f64]) -> Vec<f64> {
        let (features, targets) = (self.weights.nrows(), self.weights.ncols());
        let n = x.len() / features;
        let xs = Mat::from_fn(n, features, |i, j| (x[i * features + j] - self.mean[j]) / self.scale[j]);
        let mut out = Mat::<f64>::zeros(n, targets);
        matmul(out.as_mut(), Accum::Replace, xs.as_ref(), self.weights.as_ref(), 1.0, Par::Seq);
        (0..n).flat_map(|i| (0..targets).map(move |j| (i, j))).map(|(i, j)| out[(i, j)] + self.target_mean[j]).collect()
    }
}

/// Solves (A + shift I) X = B for a symmetric positive semi-definite A by Cholesky.
fn solve_regularised(mut a: Mat<f64>, shift: f64, mut b: Mat<f64>) -> anyhow::Result<Mat<f64>> {
    for j in 0..a.nrows() {
        a[(j, j)] += shift;
    }
    let llt = a.llt(Side::Lower).ok().context("the regularised Gram matrix is not positive definite; raise `lambdas`")?;
    llt.solve_in_place(b.as_mut());
    Ok(b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn faer_solves_a_small_system_as_by_hand() {
        // x = [-1, 0, 1] (mean 0, sd sqrt(2/3)), y = 2x + 5. Standardised z = x / sd, so
        // sum z^2 = 3 and sum z (y - 5) = 2 * sum x^2 / sd = 4 / sd. With lambda = 1/3 per row
        // (lambda n = 1): w = (4 / sd) / (3 + 1), and the prediction at x is 5 + w x / sd
        // = 5 + x / sd^2 = 5 + 1.5 x.
        let ridge = Ridge::fit(&[-1.0, 0.0, 1.0], 1, &[3.0, 5.0, 7.0], 1, 1.0 / 3.0).unwrap();
        let p = ridge.predict(&[-1.0, 2.0]);
        assert!((p[0] - 3.5).abs() < 1e-12 && (p[1] - 8.0).abs() < 1e-12, "{p:?}");
        // Without regularisation it recovers the line exactly, for two targets at once.
        let ridge = Ridge::fit(&[-1.0, 0.0, 1.0], 1, &[3.0, 1.0, 5.0, 1.0, 7.0, 1.0], 2, 1e-15).unwrap();
        let p = ridge.predict(&[4.0]);
        assert!((p[0] - 13.0).abs() < 1e-9 && (p[1] - 1.0).abs() < 1e-9, "{p:?}");
    }

    #[test]
    fn the_dual_form_gives_the_primal_solution() {
        // 6 rows: with 4 features the primal solves, with the same 4 features repeated to 8 the
        // dual does; the duplicated columns share the weight, so predictions agree.
        let x: Vec<f64> = (0..24).map(|i| ((i * 7 % 11) as f64 - 5.0) * 0.3 + (i / 4) as f64 * 0.1).collect();
        let y: Vec<f64> = (0..12).map(|i| ((i * 5 % 7) as f64) - 2.0).collect();
        let wide: Vec<f64> = x.chunks(4).flat_map(|row| row.iter().chain(row).copied().collect::<Vec<_>>()).collect();
        let primal = Ridge::fit(&x, 4, &y, 2, 0.05).unwrap();
        let dual = Ridge::fit(&wide, 8, &y, 2, 0.1).unwrap();
        let query = [0.3, -1.0, 2.0, 0.5];
        let wide_query: Vec<f64> = query.iter().chain(&query).copied().collect();
        let (p, d) = (primal.predict(&query), dual.predict(&wide_query));
        for (a, b) in p.iter().zip(&d) {
            assert!((a - b).abs() < 1e-9, "{p:?} {d:?}");
        }
    }
}
