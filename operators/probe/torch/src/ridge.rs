//! Closed-form ridge regression on libtorch, in double precision: features standardised by their
//! training mean and standard deviation, targets centred, then (XᵀX + λ n I) W = Xᵀ Y solved by
//! Cholesky, or with more features than rows its dual, W = Xᵀ (XXᵀ + λ n I)⁻¹ Y (the same W, a
//! smaller system). A `RidgeProblem` holds one training set's Gram matrix, so the strengths
//! tried on it cost a factorisation each, not another product. The products and the
//! factorisation run in MKL under the action's kernel pins (`rlmflow_stages::numerics`) with the
//! action's thread count, so the weights are the same bytes on every machine of its class; a Rust
//! linear-algebra crate picks AVX-512 or AVX2 code by the CPU it finds, which no setting pins.

use anyhow::Context as _;
use rlmflow_nn::tch::{Device, Kind, Tensor};

pub struct Ridge {
    mean: Tensor,
    scale: Tensor,
    target_mean: Tensor,
    /// features x targets.
    weights: Tensor,
}

/// One training set standardised, with its Gram matrix computed once for every strength tried
/// on it: the products are the fit's cost (for every patch token, a few thousand rows by 8,192
/// features), the factorisation per strength a small part of it.
pub struct RidgeProblem {
    mean: Tensor,
    scale: Tensor,
    target_mean: Tensor,
    /// The standardised features (rows x features).
    xs: Tensor,
    /// XᵀX (primal) or XXᵀ (dual, more features than rows).
    gram: Tensor,
    /// XᵀY (primal) or the centred targets Y (dual).
    right: Tensor,
    dual: bool,
    rows: usize,
}

/// `rows` x `width` values as a double tensor on the CPU.
fn matrix(values: &[f64], width: usize) -> Tensor {
    Tensor::from_slice(values).view([(values.len() / width) as i64, width as i64]) // host: ridge solves on the CPU, in MKL under the pins
}

impl RidgeProblem {
    /// `x` (rows of `features` values) to be fitted to `y` (rows of `targets` values).
    pub fn new(x: &[f64], features: usize, y: &[f64], targets: usize) -> RidgeProblem {
        let rows = x.len() / features;
        assert_eq!(y.len(), rows * targets, "one target row per feature row");
        let (x, y) = (matrix(x, features), matrix(y, targets));
        let mean = x.mean_dim(0, true, Kind::Double);
        let var = (&x - &mean).square().mean_dim(0, true, Kind::Double);
        // A constant feature keeps its scale (it standardises to 0 either way).
        let scale = var.sqrt().where_self(&var.gt(1e-12), &var.ones_like());
        let target_mean = y.mean_dim(0, true, Kind::Double);
        let xs = (x - &mean) / &scale;
        let yc = y - &target_mean;
        let dual = features > rows;
        let (gram, right) =
            if dual { (xs.matmul(&xs.transpose(0, 1)), yc) } else { (xs.transpose(0, 1).matmul(&xs), xs.transpose(0, 1).matmul(&yc)) };
        RidgeProblem { mean, scale, target_mean, xs, gram, right, dual, rows }
    }

    /// The fit with strength `lambda` per training row.
    pub fn solve(&self, lambda: f64) -> anyhow::Result<Ridge> {
        let shift = lambda * self.rows as f64;
        let weights = if self.dual {
            // Dual, for more features than rows (every patch token): W = Xᵀ (XXᵀ + λ n I)⁻¹ Y,
            // the same solution through an n x n system.
            self.xs.transpose(0, 1).matmul(&solve_regularised(&self.gram, shift, &self.right)?)
        } else {
            // Primal: (XᵀX + λ n I) W = Xᵀ Y, a features x features system.
            solve_regularised(&self.gram, shift, &self.right)?
        };
        Ok(Ridge { mean: self.mean.shallow_clone(), scale: self.scale.shallow_clone(), target_mean: self.target_mean.shallow_clone(), weights })
    }
}

impl Ridge {
    /// Predictions for the rows of `x`.
    pub fn predict(&self, x: &[f64]) -> Vec<f64> {
        let xs = (matrix(x, self.weights.size()[0] as usize) - &self.mean) / &self.scale;
        let out = xs.matmul(&self.weights) + &self.target_mean;
        Vec::<f64>::try_from(out.flatten(0, -1)).expect("double predictions")
    }
}

/// Solves (A + shift I) X = B for a symmetric positive semi-definite A by Cholesky.
fn solve_regularised(a: &Tensor, shift: f64, b: &Tensor) -> anyhow::Result<Tensor> {
    let a = a + Tensor::eye(b.size()[0], (Kind::Double, Device::Cpu)) * shift;
    let lower = a.f_linalg_cholesky(false).ok().context("the regularised Gram matrix is not positive definite; raise `lambdas`")?;
    Ok(b.cholesky_solve(&lower, false))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn it_solves_a_small_system_as_by_hand() {
        // x = [-1, 0, 1] (mean 0, sd sqrt(2/3)), y = 2x + 5. Standardised z = x / sd, so
        // sum z^2 = 3 and sum z (y - 5) = 2 * sum x^2 / sd = 4 / sd. With lambda = 1/3 per row
        // (lambda n = 1): w = (4 / sd) / (3 + 1), and the prediction at x is 5 + w x / sd
        // = 5 + x / sd^2 = 5 + 1.5 x.
        let ridge = RidgeProblem::new(&[-1.0, 0.0, 1.0], 1, &[3.0, 5.0, 7.0], 1).solve(1.0 / 3.0).unwrap();
        let p = ridge.predict(&[-1.0, 2.0]);
        assert!((p[0] - 3.5).abs() < 1e-12 && (p[1] - 8.0).abs() < 1e-12, "{p:?}");
        // Without regularisation it recovers the line exactly, for two targets at once.
        let ridge = RidgeProblem::new(&[-1.0, 0.0, 1.0], 1, &[3.0, 1.0, 5.0, 1.0, 7.0, 1.0], 2).solve(1e-15).unwrap();
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
        let primal = RidgeProblem::new(&x, 4, &y, 2).solve(0.05).unwrap();
        let dual = RidgeProblem::new(&wide, 8, &y, 2).solve(0.1).unwrap();
        let query = [0.3, -1.0, 2.0, 0.5];
        let wide_query: Vec<f64> = query.iter().chain(&query).copied().collect();
        let (p, d) = (primal.predict(&query), dual.predict(&wide_query));
        for (a, b) in p.iter().zip(&d) {
            assert!((a - b).abs() < 1e-9, "{p:?} {d:?}");
        }
    }

    #[test]
    fn one_problem_solved_at_several_strengths_gives_each_fresh_fit_exactly() {
        let x: Vec<f64> = (0..60).map(|i| ((i * 7 % 13) as f64 - 6.0) * 0.2 + (i / 5) as f64 * 0.05).collect();
        let y: Vec<f64> = (0..24).map(|i| ((i * 5 % 9) as f64) - 3.0).collect();
        let query: Vec<f64> = (0..10).map(|i| i as f64 * 0.3 - 1.0).collect();
        // 12 rows of 5 features (primal) and 6 rows of 10 (dual).
        for (features, targets) in [(5, 2), (10, 4)] {
            let problem = RidgeProblem::new(&x, features, &y, targets);
            for lambda in [1e-3, 0.1, 10.0] {
                let fresh = RidgeProblem::new(&x, features, &y, targets).solve(lambda).unwrap();
                let reused = problem.solve(lambda).unwrap();
                assert_eq!(reused.predict(&query[..features]), fresh.predict(&query[..features]), "lambda {lambda}");
            }
        }
    }

    #[test]
    fn an_indefinite_system_says_which_setting_helps() {
        let err = solve_regularised(&Tensor::from_slice(&[-1.0f64]).view([1, 1]), 0.0, &Tensor::from_slice(&[1.0f64]).view([1, 1])).err().unwrap();
        assert!(err.to_string().contains("raise `lambdas`"), "{err}");
    }
}
