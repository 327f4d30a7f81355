//! What every training operator shares around its loop: the device a setting names, the
//! finite-loss guard, and per-epoch checkpoints.
//!
//! A checkpoint is the model's variables and the optimiser's moments in one safetensors file
//! plus the epochs' log lines in JSON; the log is renamed into place last, so the epochs it
//! lists are always the ones the state holds. An operator that seeds each epoch's draws by
//! (seed, epoch) needs nothing else to resume where it stopped and end with the same weights.

use std::collections::HashMap;
use std::path::Path;

use anyhow::{Context as _, bail};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde_json::Value;
use tch::{Tensor, nn};

use crate::optim::AdamW;

const STATE: &str = "state.safetensors";
const LOG: &str = "state.json";

/// The device a `device` setting (`auto`, `cpu`, `cuda`, `cuda:N`) names, given the engine's
/// choice for the action: `auto` takes the engine's GPU, else CUDA when libtorch has one.
pub fn resolve_device(setting: &str, engine: rlmflow_stages::Device) -> anyhow::Result<tch::Device> {
    let cuda = |n: usize| {
        if !tch::Cuda::is_available() {
            bail!("device `{setting}`: this machine has no CUDA device libtorch can use");
        }
        Ok(tch::Device::Cuda(n))
    };
    match setting {
        "cpu" => Ok(tch::Device::Cpu),
        "cuda" => cuda(0),
        "auto" => Ok(match engine {
            rlmflow_stages::Device::Cuda(n) => cuda(n)?,
            rlmflow_stages::Device::Cpu if tch::Cuda::is_available() => tch::Device::Cuda(0),
            rlmflow_stages::Device::Cpu => tch::Device::Cpu,
        }),
        other => cuda(other.trim_start_matches("cuda:").parse().with_context(|| format!("device `{other}`"))?),
    }
}

/// The generator of epoch `epoch`'s draws (frame order, captions): seeded by (seed, epoch) alone,
/// so the finished epochs are all the state a resumed run needs.
pub fn epoch_rng(seed: u64, epoch: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed ^ (epoch + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15))
}

/// The loss of `step` (1-based), or an error naming the step when it is not finite.
pub fn finite(loss: f64, step: u64, epoch: u64) -> anyhow::Result<f64> {
    if !loss.is_finite() {
        bail!("the loss is {loss} at step {step} (epoch {epoch}); lower `lr` or raise `batch`");
    }
    Ok(loss)
}

/// Variables sorted by name: files' bytes never depend on a hash order.
pub fn named_variables(vs: &nn::VarStore) -> Vec<(String, Tensor)> {
    let mut vars: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    vars
}

/// Writes `vs` to `path` on the CPU, sorted by name (an artifact's weights).
pub fn write_weights(vs: &nn::VarStore, path: &Path) -> anyhow::Result<()> {
    let cpu: Vec<(String, Tensor)> = named_variables(vs).into_iter().map(|(n, t)| (n, t.to_device(tch::Device::Cpu))).collect();
    Tensor::write_safetensors(&cpu, path).with_context(|| format!("writing {}", path.display()))
}

/// Saves the model, the optimiser and the finished epochs' log to `dir`.
pub fn save_checkpoint(vs: &nn::VarStore, opt: &AdamW, log: &[Value], dir: &Path) -> anyhow::Result<()> {
    let mut tensors = named_variables(vs);
    tensors.extend(opt.state());
    let tmp = dir.join(format!("{STATE}.tmp"));
    Tensor::write_safetensors(&tensors, &tmp)?;
    std::fs::write(dir.join(format!("{LOG}.tmp")), serde_json::to_vec(log)?)?;
    std::fs::rename(&tmp, dir.join(STATE))?;
    std::fs::rename(dir.join(format!("{LOG}.tmp")), dir.join(LOG))?;
    Ok(())
}

/// Restores the last checkpoint in `dir` into `vs` and `opt`; the finished epochs' log, empty
/// when there is none.
pub fn restore_checkpoint(vs: &nn::VarStore, opt: &mut AdamW, dir: &Path) -> anyhow::Result<Vec<Value>> {
    let path = dir.join(STATE);
    if !path.is_file() {
        return Ok(Vec::new());
    }
    let state: HashMap<String, Tensor> = Tensor::read_safetensors(&path)?.into_iter().collect();
    tch::no_grad(|| -> anyhow::Result<()> {
        for (name, mut var) in vs.variables() {
            var.copy_(state.get(&name).with_context(|| format!("the checkpoint has no `{name}`"))?);
        }
        Ok(())
    })?;
    opt.load_state(&state)?;
    let log = dir.join(LOG);
    serde_json::from_slice(&std::fs::read(&log)?).with_context(|| format!("reading {}", log.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_non_finite_loss_stops_training_naming_the_step() {
        assert_eq!(finite(2.5, 3, 1).unwrap(), 2.5);
        let err = finite(f64::NAN, 17, 2).unwrap_err().to_string();
        assert_eq!(err, "the loss is NaN at step 17 (epoch 2); lower `lr` or raise `batch`");
        assert!(finite(f64::INFINITY, 1, 1).unwrap_err().to_string().contains("the loss is inf at step 1"));
    }

    #[test]
    fn a_checkpoint_restores_weights_moments_and_log() {
        let dir = std::env::temp_dir().join(format!("rlmflow-nn-checkpoint-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let build = || {
            let vs = nn::VarStore::new(tch::Device::Cpu);
            let layer = nn::linear(vs.root() / "fc", 3, 2, Default::default());
            (vs, layer)
        };
        tch::manual_seed(1);
        let (vs, layer) = build();
        let mut opt = AdamW::new(&vs, (0.9, 0.999), 1e-8, 0.01);
        assert!(restore_checkpoint(&vs, &mut opt, &dir).unwrap().is_empty(), "no checkpoint yet");
        let loss = nn::Module::forward(&layer, &Tensor::ones([4, 3], (tch::Kind::Float, tch::Device::Cpu))).sum(tch::Kind::Float);
        opt.step(&opt.gradients(&loss), 0.1);
        save_checkpoint(&vs, &opt, &[serde_json::json!({"epoch": 1})], &dir).unwrap();

        tch::manual_seed(2);
        let (fresh, _) = build();
        let mut fresh_opt = AdamW::new(&fresh, (0.9, 0.999), 1e-8, 0.01);
        let log = restore_checkpoint(&fresh, &mut fresh_opt, &dir).unwrap();
        assert_eq!(log, vec![serde_json::json!({"epoch": 1})]);
        assert_eq!(fresh_opt.steps(), 1);
        let same = |a: &nn::VarStore, b: &nn::VarStore| named_variables(a).iter().zip(named_variables(b)).all(|((_, x), (_, y))| x.equal(&y));
        assert!(same(&vs, &fresh));
        let moments = |o: &AdamW| o.state().into_iter().map(|(_, t)| t).collect::<Vec<_>>();
        assert!(moments(&opt).iter().zip(moments(&fresh_opt)).all(|(a, b)| a.equal(&b)));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
