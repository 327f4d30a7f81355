//! Shared model code on tch for the torch operators (pretraining, probes, segmentation), short
//! and flat in open_clip's manner and configured by the plain structs of
//! `rlmflow_stages::encoder`: [`transformer`] (pre-LN residual attention blocks), [`vision`]
//! (the radar ViT, patch or convolutional stem), [`text`] (the causal text tower), [`clip`]
//! (both towers and the logit scale), [`loss`] (CLIP and SG-CLIP), [`optim`] (AdamW with saveable
//! state, clipping, the learning-rate schedule), [`segment`] (the PUP decoder, the U-Net, Dice +
//! BCE), [`train`] (device choice, checkpoints), [`gpt`] and [`decode`] (ClipCap's
//! mapper and decoder, greedy and beam search). Tensor names follow open_clip's CLIP layout, so
//! a Python user can map the weights onto it.

pub mod clip;
pub mod decode;
pub mod gpt;
pub mod loss;
pub mod optim;
pub mod segment;
pub mod text;
pub mod train;
pub mod transformer;
pub mod vision;

pub use tch;

/// The device an operator asked for, as tch names it.
pub fn device(device: rlmflow_stages::Device) -> tch::Device {
    match device {
        rlmflow_stages::Device::Cpu => tch::Device::Cpu,
        rlmflow_stages::Device::Cuda(n) => tch::Device::Cuda(n),
    }
}
