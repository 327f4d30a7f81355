//! The one training loop every torch operator runs ([`fit`]), and what it stands on: the device
//! a setting names, the finite-loss guard, and per-epoch checkpoints.
//!
//! An operator brings its model's variables, its training frames, the loss of one batch and an
//! evaluation after each epoch; `fit` owns the rest: the warmup-cosine schedule, AdamW, gradient
//! accumulation, gradient clipping, the epoch's frame order, progress, `epoch` and `resumed` events, and checkpoints.
//!
//! A checkpoint is the model's variables and the optimiser's moments in one safetensors file
//! plus the epochs' log lines in JSON; the log is renamed into place last, so the epochs it
//! lists are always the ones the state holds. Each epoch's draws (frame order, then whatever the
//! loss draws) come from a generator seeded by (seed, epoch) alone, so a killed run resumes at
//! the next epoch and ends with the weights of an uninterrupted one.
//!
//! Each step's loss, rate and figures and each epoch's log line also go to a TensorBoard event
//! file as they happen (`tensorboard.rs`), in the checkpoint directory, so a resumed run keeps
//! its curves; the finished file is copied into the artifact. Both hold it at their top, so
//! TensorBoard names a run by the folder a results link gives it (`pretrain/alpha4`).

use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;

use anyhow::{Context as _, bail};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use rlmflow_stages::numerics::{Precision, Target};
use rlmflow_stages::{Context, Device, SettingError, Training};
use serde_json::{Value, json};
use tch::{Tensor, nn};

use crate::cuda;
use crate::libtorch::{self, Autocast};
use crate::optim::{AdamW, warmup_cosine};
use crate::tensorboard::{self, EventWriter};

const STATE: &str = "state.safetensors";
const LOG: &str = "state.json";

/// The device a `device` setting computes on, given the engine's choice for the action
/// (`rlmflow_stages::numerics::Target::of`, the rule the action's key was planned by). On CUDA,
/// deterministic algorithms are on (an op without a deterministic kernel fails naming itself),
/// cuDNN's autotuner and TF32 off: two runs of a key give the same bytes. The CPU's matrix
/// products are first made what the numerics pins ask (`libtorch::pin_gemm`).
pub fn resolve_device(setting: Device, engine: Device) -> anyhow::Result<tch::Device> {
    libtorch::pin_gemm()?;
    match Target::of(setting, engine, cuda::available()) {
        Target::Cpu => Ok(tch::Device::Cpu),
        Target::Cuda(_) if !cuda::available() => {
            let why = cuda::status().why_not().unwrap_or_else(|| "libtorch reports no CUDA device".into());
            bail!(
                "device `{setting}`: libtorch cannot compute on CUDA here: {why}; or set the stage's `device = \"cpu\"` (`rlmflow-torch doctor` says more)"
            )
        }
        Target::Cuda(n) => {
            libtorch::set_deterministic(true)?;
            libtorch::set_tf32(false)?;
            tch::Cuda::cudnn_set_benchmark(false);
            Ok(tch::Device::Cuda(n))
        }
    }
}

/// Where a training stage computes, and in what arithmetic (`auto` resolved for the device).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Placement {
    pub device: tch::Device,
    pub precision: Precision,
}

impl Placement {
    /// For a training stage's settings, given the engine's device for the action.
    pub fn of(training: &Training, engine: Device) -> anyhow::Result<Placement> {
        let device = resolve_device(training.device, engine)?;
        let target = match device {
            tch::Device::Cuda(n) => Target::Cuda(n),
            _ => Target::Cpu,
        };
        let precision = training.precision.on(target);
        if device.is_cuda() && precision == Precision::Tf32 {
            libtorch::set_tf32(true)?;
        }
        Ok(Placement { device, precision })
    }

    /// Runs `f`, a forward pass (with its backward, where it takes one), in the placement's
    /// arithmetic: for `bf16` inside a bfloat16 autocast region of its own, so autocast's
    /// low-precision copies of the weights never outlive an optimiser step.
    pub fn forward<T>(&self, f: impl FnOnce() -> T) -> anyhow::Result<T> {
        let _region = match self.precision {
            Precision::Bf16 => Some(Autocast::enter(self.device)?),
            Precision::Auto | Precision::Fp32 | Precision::Tf32 => None,
        };
        Ok(f())
    }
}

/// The generator an epoch's draws come from.
pub type EpochRng = ChaCha8Rng;

/// The generator of epoch `epoch`'s draws (frame order, captions): seeded by (seed, epoch) alone,
/// so the finished epochs are all the state a resumed run needs.
fn epoch_rng(seed: u64, epoch: u64) -> EpochRng {
    ChaCha8Rng::seed_from_u64(rlmflow_stages::item_seed(seed, epoch + 1))
}

/// The loss of `step` (1-based), or an error naming the step when it is not finite.
fn finite(loss: f64, step: u64, epoch: u64) -> anyhow::Result<f64> {
    if !loss.is_finite() {
        return Err(SettingError::new("lr", format!("the loss is {loss} at step {step} (epoch {epoch}); lower `lr` or raise `batch`")).into());
    }
    Ok(loss)
}

/// One batch's loss, and figures logged beside it (an epoch's line holds each one's mean).
pub struct Step {
    pub loss: Loss,
    pub figures: Vec<(&'static str, f64)>,
}

/// A batch's loss as [`fit`] receives it.
pub enum Loss {
    /// A tensor `fit` differentiates.
    Tensor(Tensor),
    /// Its value and the trained variables' gradients, which the operator computed itself with
    /// [`Backward`] (a batch embedded in chunks: `clip::cached_contrastive`).
    Computed { value: f64, gradients: Vec<Tensor> },
}

impl From<Tensor> for Step {
    fn from(loss: Tensor) -> Step {
        Step { loss: Loss::Tensor(loss), figures: Vec::new() }
    }
}

/// Gradients of a loss for an operator that computes a batch's gradients itself: those of every
/// trained variable, in the optimiser's order, and those of any `extra` inputs.
pub struct Backward<'a> {
    opt: &'a AdamW,
}

impl<'a> Backward<'a> {
    pub fn new(opt: &'a AdamW) -> Backward<'a> {
        Backward { opt }
    }

    /// The gradients of `loss` for the trained variables (undefined where it does not reach one)
    /// and for `extra`.
    pub fn gradients(&self, loss: &Tensor, extra: &[&Tensor]) -> (Vec<Tensor>, Vec<Tensor>) {
        let mut grads = self.opt.gradients_with(loss, extra);
        let extra = grads.split_off(grads.len() - extra.len());
        (grads, extra)
    }
}

/// Figures an evaluation adds to an epoch's log line.
pub type Figures = Vec<(&'static str, f64)>;

/// What [`fit`] trains on.
pub struct Fit<'a> {
    pub training: &'a Training,
    /// Where it computes, and in what arithmetic: each batch's loss and each evaluation run in it.
    pub placement: Placement,
    /// The training frames (indices into the operator's data); each epoch visits them once in a
    /// seeded order, in batches of `training.batch`, the remainder dropped.
    pub frames: &'a [usize],
    /// Keep each batch's loss and figures in the epoch's log line (`batch_loss`, `batch_<name>`).
    pub per_batch: bool,
}

/// The finished training: one log line per epoch (one line of evaluation for 0 epochs) and the
/// optimiser steps taken.
pub struct Fitted {
    pub log: Vec<Value>,
    pub steps: u64,
}

/// Trains `vs`'s variables: for each epoch not already in the checkpoint, the frames in the
/// epoch's order, `loss` per batch (per micro-batch under `accumulate`, their gradients
/// averaged; given the epoch's generator after the order was drawn), an AdamW step at the
/// schedule's rate after clipping, then `evaluate` and a checkpoint.
pub fn fit(
    vs: &nn::VarStore,
    fit: Fit,
    ctx: &mut Context,
    mut loss: impl FnMut(&[usize], &mut EpochRng, &Backward) -> anyhow::Result<Step>,
    mut evaluate: impl FnMut() -> anyhow::Result<Figures>,
) -> anyhow::Result<Fitted> {
    let t = fit.training;
    let batch = t.batch as usize;
    let micro_batches = t.accumulate as usize;
    let steps_per_epoch = (fit.frames.len() / batch) as u64;
    if steps_per_epoch == 0 && t.epochs > 0 {
        let message = format!(
            "{batch} is larger than the {} frames this stage trains on (the labels' training split, less any validation slice); lower it",
            fit.frames.len()
        );
        return Err(SettingError::new("batch", message).into());
    }
    let total = t.epochs * steps_per_epoch;
    let warmup = (t.warmup_epochs * steps_per_epoch as f64).round() as u64;
    let lr = |step: u64| warmup_cosine(step, total, warmup, t.warmup_lr, t.lr, t.min_lr);
    let mut opt = AdamW::new(vs, (t.betas[0], t.betas[1]), t.eps, t.weight_decay);
    let mut log = checkpoint_log(&ctx.checkpoint_dir)?;
    let curves = &ctx.checkpoint_dir;
    let checkpointed = log.last().and_then(|line| line["step"].as_u64()).unwrap_or(0);
    let mut tensorboard = match EventWriter::resume(curves, checkpointed)? {
        Some(writer) => writer,
        None => {
            // A checkpoint whose curves were not kept with it: start over, so the artifact's
            // curves are whole.
            log.clear();
            EventWriter::resume(curves, 0)?.expect("a new event file")
        }
    };
    if !log.is_empty() {
        restore_state(vs, &mut opt, &ctx.checkpoint_dir)?;
        ctx.event("resumed", json!({"epoch": log.len()}));
    }
    // Where the curves grow while it trains.
    ctx.live(&ctx.checkpoint_dir);
    let progress = ctx.progress(total, "steps");
    progress.set_position(opt.steps() as u64);
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    for epoch in log.len() as u64..t.epochs {
        let clock = Instant::now();
        let mut rng = epoch_rng(ctx.seed, epoch);
        let mut order = fit.frames.to_vec();
        order.shuffle(&mut rng);
        let mut losses = Vec::with_capacity(steps_per_epoch as usize);
        let mut figures: Vec<(&'static str, Vec<f64>)> = Vec::new();
        for (step, frames) in order.chunks_exact(batch).enumerate() {
            let global = epoch * steps_per_epoch + step as u64;
            // The micro-batches' losses, figures and gradients, averaged.
            let (mut value, mut grads, mut batch_figures) = (0.0, Vec::<Tensor>::new(), Vec::new());
            for (m, micro) in frames.chunks_exact(batch / micro_batches).enumerate() {
                let Step { loss: micro_loss, figures: micro_figures } = fit.placement.forward(|| loss(micro, &mut rng, &Backward::new(&opt)))??;
                let (micro_value, micro_grads) = match micro_loss {
                    Loss::Tensor(loss) => (finite(loss.double_value(&[]), global + 1, epoch + 1)?, opt.gradients(&loss)),
                    Loss::Computed { value, gradients } => (finite(value, global + 1, epoch + 1)?, gradients),
                };
                value += micro_value / micro_batches as f64;
                if m == 0 {
                    batch_figures = micro_figures.into_iter().map(|(name, f)| (name, f / micro_batches as f64)).collect();
                    grads = micro_grads;
                } else {
                    batch_figures.iter_mut().zip(micro_figures).for_each(|((_, sum), (_, f))| *sum += f / micro_batches as f64);
                    tch::no_grad(|| grads.iter_mut().zip(&micro_grads).filter(|(g, _)| g.defined()).for_each(|(g, add)| *g += add));
                }
            }
            if micro_batches > 1 {
                tch::no_grad(|| grads.iter_mut().filter(|g| g.defined()).for_each(|g| *g /= micro_batches as f64));
            }
            losses.push(value);
            for (i, (name, figure)) in batch_figures.into_iter().enumerate() {
                match figures.get_mut(i) {
                    Some((_, series)) => series.push(figure),
                    None => figures.push((name, vec![figure])),
                }
            }
            opt.clip_grad_norm(&grads, t.clip_norm)?;
            opt.step(&grads, lr(global))?;
            let mut scalars = vec![("train/loss".to_owned(), value), ("train/lr".to_owned(), lr(global))];
            scalars.extend(figures.iter().map(|(name, series)| (format!("train/{name}"), series[series.len() - 1])));
            tensorboard.scalars(global + 1, &scalars)?;
            progress.set_position(global + 1);
            progress.set_message(format!("epoch {}/{} loss {:.3}", epoch + 1, t.epochs, losses[losses.len() - 1]));
        }
        let step = (epoch + 1) * steps_per_epoch;
        let mut line = json!({"epoch": epoch + 1, "step": step, "loss": mean(&losses), "lr": lr(step - 1)});
        figures.iter().for_each(|(name, series)| line[*name] = mean(series).into());
        fit.placement.forward(&mut evaluate)??.into_iter().for_each(|(name, figure)| line[name] = figure.into());
        tensorboard.scalars(step, &epoch_scalars(&line))?;
        // Times go to the event log only: the artifact holds what the key determines.
        let mut event = line.clone();
        event["seconds"] = clock.elapsed().as_secs_f64().into();
        ctx.event("epoch", event);
        if fit.per_batch {
            line["batch_loss"] = losses.into();
            figures.into_iter().for_each(|(name, series)| line[format!("batch_{name}")] = series.into());
        }
        log.push(line);
        save_checkpoint(vs, &opt, &log, &ctx.checkpoint_dir)?;
    }
    progress.finish();
    if t.epochs == 0 {
        let mut line = json!({"epoch": 0, "step": 0});
        fit.placement.forward(&mut evaluate)??.into_iter().for_each(|(name, figure)| line[name] = figure.into());
        tensorboard.scalars(0, &epoch_scalars(&line))?;
        log.push(line);
    }
    let into = ctx.output_dir.join(tensorboard::FILE);
    std::fs::copy(tensorboard.path(), &into).with_context(|| format!("copying the curves to {}", into.display()))?;
    Ok(Fitted { log, steps: total })
}

/// An epoch's log line as TensorBoard scalars: `epoch/<name>` for each of its numbers.
fn epoch_scalars(line: &Value) -> Vec<(String, f64)> {
    let numbers = line.as_object().into_iter().flatten().filter(|(name, _)| *name != "epoch" && *name != "step");
    numbers.filter_map(|(name, v)| Some((format!("epoch/{name}"), v.as_f64()?))).collect()
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
fn save_checkpoint(vs: &nn::VarStore, opt: &AdamW, log: &[Value], dir: &Path) -> anyhow::Result<()> {
    let mut tensors = named_variables(vs);
    tensors.extend(opt.state());
    let tmp = dir.join(format!("{STATE}.tmp"));
    Tensor::write_safetensors(&tensors, &tmp)?;
    std::fs::write(dir.join(format!("{LOG}.tmp")), serde_json::to_vec(log)?)?;
    std::fs::rename(&tmp, dir.join(STATE))?;
    std::fs::rename(dir.join(format!("{LOG}.tmp")), dir.join(LOG))?;
    Ok(())
}

/// The finished epochs' log lines of the last checkpoint in `dir`, empty when there is none.
fn checkpoint_log(dir: &Path) -> anyhow::Result<Vec<Value>> {
    if !dir.join(STATE).is_file() {
        return Ok(Vec::new());
    }
    let log = dir.join(LOG);
    serde_json::from_slice(&std::fs::read(&log)?).with_context(|| format!("reading {}", log.display()))
}

/// Restores the last checkpoint in `dir` into `vs` and `opt`.
fn restore_state(vs: &nn::VarStore, opt: &mut AdamW, dir: &Path) -> anyhow::Result<()> {
    let state: HashMap<String, Tensor> = Tensor::read_safetensors(dir.join(STATE))?.into_iter().collect();
    tch::no_grad(|| -> anyhow::Result<()> {
        for (name, mut var) in vs.variables() {
            var.copy_(state.get(&name).with_context(|| format!("the checkpoint has no `{name}`"))?);
        }
        Ok(())
    })?;
    opt.load_state(&state)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_non_finite_loss_stops_training_naming_the_step() {
        let _generator = crate::generator();
        assert_eq!(finite(2.5, 3, 1).unwrap(), 2.5);
        let err = finite(f64::NAN, 17, 2).unwrap_err().to_string();
        assert_eq!(err, "lr: the loss is NaN at step 17 (epoch 2); lower `lr` or raise `batch`");
        assert!(finite(f64::INFINITY, 1, 1).unwrap_err().to_string().contains("the loss is inf at step 1"));
    }

    /// A context for `fit` with its output and checkpoint directories under `dir`.
    fn fit_context(dir: &Path, seed: u64) -> Context {
        let (out, ckpt) = (dir.join("out"), dir.join("ckpt"));
        std::fs::create_dir_all(&out).unwrap();
        std::fs::create_dir_all(&ckpt).unwrap();
        Context::standalone("fit", &[], &out, &ckpt, seed, 1)
    }

    /// One step of `fit` on a linear model under a mean squared error over 8 frames, with the
    /// batch split into `accumulate` micro-batches: the trained weights. AdamW's `eps` is large
    /// so the step depends on the gradient's scale, not only its sign.
    fn one_step(accumulate: u64) -> Tensor {
        let dir = std::env::temp_dir().join(format!("rlmflow-nn-accumulate-{}-{accumulate}", std::process::id()));
        let mut ctx = fit_context(&dir, 5);
        tch::manual_seed(3);
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let layer = nn::linear(vs.root() / "fc", 3, 2, Default::default());
        let inputs = Tensor::randn([8, 3], (tch::Kind::Float, tch::Device::Cpu));
        let targets = Tensor::randn([8, 2], (tch::Kind::Float, tch::Device::Cpu));
        let training = Training { epochs: 1, batch: 8, accumulate, warmup_epochs: 0.0, lr: 0.1, eps: 1.0, clip_norm: 1e6, ..Training::default() };
        let frames: Vec<usize> = (0..8).collect();
        let placement = Placement { device: tch::Device::Cpu, precision: Precision::Fp32 };
        let fit_on = Fit { training: &training, placement, frames: &frames, per_batch: false };
        fit(
            &vs,
            fit_on,
            &mut ctx,
            |batch, _, _| {
                let index = Tensor::from_slice(&batch.iter().map(|&i| i as i64).collect::<Vec<_>>());
                let predicted = nn::Module::forward(&layer, &inputs.index_select(0, &index));
                Ok(Step::from((predicted - targets.index_select(0, &index)).square().mean(tch::Kind::Float)))
            },
            || Ok(Vec::new()),
        )
        .unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        layer.ws.detach()
    }

    #[test]
    fn accumulated_micro_batches_take_the_step_of_the_whole_batch() {
        let _generator = crate::generator();
        let whole = one_step(1);
        for accumulate in [2, 4, 8] {
            let accumulated = one_step(accumulate);
            assert!(accumulated.allclose(&whole, 1e-5, 1e-6, false), "accumulate = {accumulate}: {accumulated} against {whole}");
        }
    }

    /// `epochs` epochs of a two-layer model in bfloat16 autocast on the CPU, in `dir`'s
    /// checkpoint; the loss fails at the first step of epoch `fail_at` (a killed run), if given.
    /// The trained weights, or the error.
    fn bf16_run(dir: &Path, epochs: u64, fail_at: Option<u64>) -> anyhow::Result<Vec<(String, Tensor)>> {
        let mut ctx = fit_context(dir, 11);
        tch::manual_seed(4);
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let hidden = nn::linear(vs.root() / "hidden", 6, 16, Default::default());
        let head = nn::linear(vs.root() / "head", 16, 2, Default::default());
        let inputs = Tensor::randn([32, 6], (tch::Kind::Float, tch::Device::Cpu));
        let targets = Tensor::randn([32, 2], (tch::Kind::Float, tch::Device::Cpu));
        let training =
            Training { epochs, batch: 8, warmup_epochs: 0.0, lr: 0.01, precision: Precision::Bf16, device: Device::Cpu, ..Training::default() };
        let placement = Placement::of(&training, Device::Cpu)?;
        assert_eq!(placement, Placement { device: tch::Device::Cpu, precision: Precision::Bf16 });
        let frames: Vec<usize> = (0..32).collect();
        let steps = std::cell::Cell::new(0u64);
        fit(
            &vs,
            Fit { training: &training, placement, frames: &frames, per_batch: false },
            &mut ctx,
            |batch, _, _| {
                steps.set(steps.get() + 1);
                if fail_at.is_some_and(|epoch| steps.get() > (epoch - 1) * 4) {
                    anyhow::bail!("killed");
                }
                let index = Tensor::from_slice(&batch.iter().map(|&i| i as i64).collect::<Vec<_>>());
                let h = nn::Module::forward(&hidden, &inputs.index_select(0, &index)).relu();
                assert_eq!(h.kind(), tch::Kind::BFloat16, "the forward pass computes in bfloat16");
                let predicted = nn::Module::forward(&head, &h).to_kind(tch::Kind::Float);
                Ok(Step::from((predicted - targets.index_select(0, &index)).square().mean(tch::Kind::Float)))
            },
            || Ok(Vec::new()),
        )?;
        Ok(named_variables(&vs).into_iter().map(|(name, t)| (name, t.detach().copy())).collect())
    }

    #[test]
    fn bfloat16_training_keeps_float_weights_and_resumes_to_the_same_bytes() {
        let _generator = crate::generator();
        let dir = std::env::temp_dir().join(format!("rlmflow-nn-bf16-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let whole = bf16_run(&dir.join("whole"), 3, None).unwrap();
        assert!(whole.iter().all(|(_, t)| t.kind() == tch::Kind::Float), "weights stay float32");
        assert!(bf16_run(&dir.join("resumed"), 3, Some(3)).is_err(), "killed in epoch 3");
        let resumed = bf16_run(&dir.join("resumed"), 3, None).unwrap();
        for ((name, a), (_, b)) in whole.iter().zip(&resumed) {
            assert!(a.equal(b), "{name}: a resumed bfloat16 run ends with other weights");
        }
        let again = bf16_run(&dir.join("again"), 3, None).unwrap();
        assert!(whole.iter().zip(&again).all(|((_, a), (_, b))| a.equal(b)), "two runs of one key, other bytes");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_checkpoint_restores_weights_moments_and_log() {
        let _generator = crate::generator();
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
        assert!(checkpoint_log(&dir).unwrap().is_empty(), "no checkpoint yet");
        let loss = nn::Module::forward(&layer, &Tensor::ones([4, 3], (tch::Kind::Float, tch::Device::Cpu))).sum(tch::Kind::Float);
        opt.step(&opt.gradients(&loss), 0.1).unwrap();
        save_checkpoint(&vs, &opt, &[serde_json::json!({"epoch": 1})], &dir).unwrap();

        tch::manual_seed(2);
        let (fresh, _) = build();
        let mut fresh_opt = AdamW::new(&fresh, (0.9, 0.999), 1e-8, 0.01);
        restore_state(&fresh, &mut fresh_opt, &dir).unwrap();
        assert_eq!(checkpoint_log(&dir).unwrap(), vec![serde_json::json!({"epoch": 1})]);
        assert_eq!(fresh_opt.steps(), 1);
        let same = |a: &nn::VarStore, b: &nn::VarStore| named_variables(a).iter().zip(named_variables(b)).all(|((_, x), (_, y))| x.equal(&y));
        assert!(same(&vs, &fresh));
        let moments = |o: &AdamW| o.state().into_iter().map(|(_, t)| t).collect::<Vec<_>>();
        assert!(moments(&opt).iter().zip(moments(&fresh_opt)).all(|(a, b)| a.equal(&b)));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
