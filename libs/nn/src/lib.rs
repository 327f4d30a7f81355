//! Shared model code on tch for the torch operators (pretraining, probes, segmentation), short
//! and flat in open_clip's manner and configured by the plain structs of
//! `rlmflow_stages::encoder`: [`transformer`] (pre-LN residual attention blocks), [`vision`]
//! (the radar ViT, patch or convolutional stem), [`text`] (the causal text tower), [`clip`]
//! (both towers and the logit scale), [`projection`] (either tower's head into the shared space), [`loss`] (CLIP and SG-CLIP), [`optim`] (AdamW with saveable
//! state, clipping, the learning-rate schedule), [`segment`] (the PUP decoder, the U-Net, Dice +
//! BCE), [`data`] (the frames every operator trains on, in memory), [`train`] (the one training
//! loop, `fit`: schedule, clipping, resume, checkpoints, device choice), [`tensorboard`] (its curves
//! as TensorBoard event files), [`gpt`] and [`decode`]
//! (ClipCap's mapper and decoder, greedy and beam search), [`start`] (published start weights, CLIP's vision tower and GPT-2, onto them). Tensor names follow open_clip's CLIP layout, so
//! a Python user can map the weights onto it.

pub mod clip;
pub mod cuda;
pub mod data;
pub mod decode;
pub mod failure;
pub mod gpt;
pub mod libtorch;
pub mod loss;
pub mod optim;
pub mod projection;
pub mod segment;
pub mod start;
pub mod tensorboard;
pub mod text;
pub mod train;
pub mod transformer;
pub mod vision;

pub use tch;

/// Held for its whole body by every unit test that draws from libtorch's one global generator
/// (or sets a global switch): the harness runs tests on threads, and another test's draws between
/// a test's `manual_seed` and its own draws would change what it computes.
#[cfg(test)]
pub(crate) fn generator() -> std::sync::MutexGuard<'static, ()> {
    static GENERATOR: std::sync::Mutex<()> = std::sync::Mutex::new(());
    GENERATOR.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}
