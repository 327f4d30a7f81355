//! The settings every training operator shares, typed and checked once.
//!
//! [`Training`] is flattened into each torch operator's settings struct (`#[serde(flatten)]`),
//! so `pipeline.toml` keeps flat keys (`epochs`, `lr`, `device`, ...) with the same meaning and
//! bounds everywhere; each operator's `Default` picks its own values. The loop that reads them
//! is `rlmflow_nn::train::fit`.

use serde::{Deserialize, Serialize};

use crate::context::Device;
use crate::numerics::Precision;
use crate::numerics::{Kernels, Numerics};
use crate::operator::Resources;
use crate::outline::{InputOutlines, Outline};
use crate::settings::SettingError;

/// One training run's schedule, optimiser and placement.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Training {
    /// 0..=10,000; 0 leaves the model untrained (a random-init sanity row).
    pub epochs: u64,
    /// Frames per step, 1..=65,536.
    pub batch: u64,
    /// Micro-batches a step's batch is split into, 1..=batch, dividing it: their gradients are
    /// averaged before the one step, so a batch larger than memory allows trains at the memory of
    /// `batch / accumulate` frames with the gradient of the whole batch (exact for a loss that
    /// averages over frames; BatchNorm normalises each micro-batch, as data-parallel training
    /// normalises each GPU's share). A contrastive loss is not such a mean: `clip` embeds in
    /// chunks instead (`chunk`).
    pub accumulate: u64,
    /// Peak learning rate, (0, 1].
    pub lr: f64,
    /// Linear warmup from `warmup_lr` to `lr`, in epochs (fractions allowed), 0..=epochs.
    pub warmup_epochs: f64,
    /// The warmup's first rate, [0, lr].
    pub warmup_lr: f64,
    /// The cosine schedule ends here, [0, lr].
    pub min_lr: f64,
    /// AdamW's moment decay rates, each in [0, 1).
    pub betas: [f64; 2],
    /// AdamW's denominator term, (0, 1].
    pub eps: f64,
    /// AdamW decay on matrices and kernels only, 0..=1.
    pub weight_decay: f64,
    /// Global gradient-norm clip, (0, 1e6].
    pub clip_norm: f64,
    /// `auto` (CUDA when present), `cpu`, `cuda` or `cuda:N`. With `auto` the result depends on
    /// the machine's device, so a pipeline that must reproduce bit for bit everywhere names `cpu`.
    pub device: Device,
    /// CPU threads libtorch uses, 1..=256. Part of the result: libtorch's parallel reductions
    /// add in an order that depends on the thread count, so the same key must mean the same
    /// count, whatever the scheduler grants.
    pub threads: usize,
    /// `portable` (one kernel path on every machine of a class, so results are shared across
    /// CPU models) or `native` (the fastest kernels this machine has; results shared only with
    /// machines of the same CPU model). See `rlmflow_stages::numerics`.
    pub numerics: Numerics,
    /// `auto` (bf16 on CUDA, fp32 on the CPU), `fp32`, `tf32` (CUDA only) or `bf16`: the
    /// arithmetic of the forward passes; see [`Precision`].
    pub precision: Precision,
}

impl Default for Training {
    fn default() -> Self {
        Training {
            epochs: 6,
            batch: 64,
            accumulate: 1,
            lr: 1e-3,
            warmup_epochs: 0.5,
            warmup_lr: 1e-6,
            min_lr: 1e-5,
            betas: [0.9, 0.999],
            eps: 1e-8,
            weight_decay: 0.01,
            clip_norm: 4.0,
            device: Device::Auto,
            threads: 2,
            numerics: Numerics::Portable,
            precision: Precision::Auto,
        }
    }
}

impl Training {
    /// The bounds in the field docs; errors name the key.
    pub fn check(&self) -> Result<(), SettingError> {
        SettingError::check_range("epochs", self.epochs, 0..=10_000)?;
        if self.epochs == 0 && self.warmup_epochs > 0.0 {
            let message =
                format!("0 leaves the model untrained, with no room for the {} warmup epochs; set `warmup_epochs = 0.0` too", self.warmup_epochs);
            return Err(SettingError::new("epochs", message));
        }
        SettingError::check_range("batch", self.batch, 1..=65_536)?;
        SettingError::check_range("accumulate", self.accumulate, 1..=self.batch)?;
        if !self.batch.is_multiple_of(self.accumulate) {
            return Err(SettingError::new(
                "accumulate",
                format!("must divide `batch` ({}) into equal micro-batches; {} does not", self.batch, self.accumulate),
            ));
        }
        SettingError::check_positive("lr", self.lr, 1.0)?;
        SettingError::check_range("warmup_epochs", self.warmup_epochs, 0.0..=self.epochs as f64)?;
        SettingError::check_range("warmup_lr", self.warmup_lr, 0.0..=self.lr)?;
        SettingError::check_range("min_lr", self.min_lr, 0.0..=self.lr)?;
        for (i, b) in self.betas.iter().enumerate() {
            if !(0.0..1.0).contains(b) {
                return Err(SettingError::new(format!("betas.{i}"), format!("must be in [0, 1), not {b}")));
            }
        }
        SettingError::check_positive("eps", self.eps, 1.0)?;
        SettingError::check_range("weight_decay", self.weight_decay, 0.0..=1.0)?;
        SettingError::check_positive("clip_norm", self.clip_norm, 1e6)?;
        if self.precision == Precision::Tf32 && self.device == Device::Cpu {
            return Err(SettingError::new("precision", "`tf32` is a CUDA matmul mode; on the CPU use `fp32` or `bf16`"));
        }
        SettingError::check_range("threads", self.threads, 1..=256)
    }

    /// The frames one forward and backward pass holds.
    pub fn micro_batch(&self) -> u64 {
        self.batch / self.accumulate
    }

    /// A training stage's outline check: a batch no larger than the frames its scenes hold (it
    /// trains on a share of them), which it passes on.
    pub fn outline(&self, inputs: &InputOutlines) -> Result<Outline, SettingError> {
        let outline = Outline::passed_on(inputs);
        if let Some(frames) = outline.frames
            && self.batch > frames
        {
            return Err(SettingError::new(
                "batch",
                format!("{} is more than the {frames} frames its scenes hold (it trains on a share of them)", self.batch),
            ));
        }
        // The labels' training split, in expectation.
        if let Some(train) = inputs.values().flatten().find_map(|o| o.train_frames)
            && self.batch > train
        {
            return Err(SettingError::new(
                "batch",
                format!(
                    "{} is more than the about {train} frames of the labels' training split (the scenes' frames less its test_fraction)",
                    self.batch
                ),
            ));
        }
        Ok(outline)
    }

    /// What a training stage asks of the machine: its threads, a GPU unless it names the CPU,
    /// and a CUDA device when it names one.
    pub fn resources(&self) -> Resources {
        Resources {
            threads: self.threads,
            gpu: self.device != Device::Cpu,
            needs_cuda: matches!(self.device, Device::Cuda(_)),
            kernels: Some(Kernels { numerics: self.numerics, device: self.device }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounds_name_their_key() {
        let key = |t: Training| t.check().unwrap_err().key;
        assert!(Training::default().check().is_ok());
        assert!(Training { epochs: 0, warmup_epochs: 0.0, ..Training::default() }.check().is_ok(), "0 epochs: untrained");
        assert_eq!(key(Training { epochs: 0, ..Training::default() }), "epochs", "an untrained model with a warmup");
        assert_eq!(key(Training { batch: 0, ..Training::default() }), "batch");
        assert_eq!(key(Training { lr: f64::NAN, ..Training::default() }), "lr");
        assert_eq!(key(Training { epochs: 2, warmup_epochs: 3.0, ..Training::default() }), "warmup_epochs");
        assert_eq!(key(Training { min_lr: 1.0, ..Training::default() }), "min_lr");
        assert_eq!(key(Training { betas: [0.9, 1.0], ..Training::default() }), "betas.1");
        assert_eq!(key(Training { eps: 0.0, ..Training::default() }), "eps");
        assert_eq!(key(Training { threads: 0, ..Training::default() }), "threads");
        assert_eq!(key(Training { precision: Precision::Tf32, device: Device::Cpu, ..Training::default() }), "precision");
        assert!(Training { precision: Precision::Tf32, device: Device::Cuda(0), ..Training::default() }.check().is_ok());
    }

    #[test]
    fn a_batch_larger_than_the_scenes_is_refused_by_its_key() {
        let inputs: InputOutlines = [("scenes", vec![Outline { image: Some(32), frames: Some(100), ..Outline::default() }])].into_iter().collect();
        let t = Training { batch: 128, ..Training::default() };
        let e = t.outline(&inputs).unwrap_err();
        assert_eq!((e.key.as_str(), e.message.as_str()), ("batch", "128 is more than the 100 frames its scenes hold (it trains on a share of them)"));
        assert_eq!(Training::default().outline(&inputs).unwrap(), inputs["scenes"][0]);
        assert!(t.outline(&InputOutlines::new()).is_ok(), "unknown frames: nothing to check");
    }

    #[test]
    fn accumulate_must_divide_the_batch() {
        let key = |batch, accumulate| Training { batch, accumulate, ..Training::default() }.check().err().map(|e| e.key);
        assert_eq!(key(64, 4), None);
        assert_eq!(Training { batch: 64, accumulate: 4, ..Training::default() }.micro_batch(), 16);
        assert_eq!(key(64, 5).as_deref(), Some("accumulate"));
        assert_eq!(key(64, 0).as_deref(), Some("accumulate"));
        assert_eq!(key(4, 8).as_deref(), Some("accumulate"));
    }

    #[test]
    fn a_device_is_a_string_in_settings() {
        let t: Training = serde_json::from_value(serde_json::json!({
            "epochs": 1, "batch": 2, "accumulate": 1, "lr": 0.1, "warmup_epochs": 0.0, "warmup_lr": 0.0, "min_lr": 0.0, "betas": [0.9, 0.99],
            "eps": 1e-8, "weight_decay": 0.0, "clip_norm": 1.0, "device": "cuda:1", "threads": 1, "numerics": "native",
            "precision": "bf16"
        }))
        .unwrap();
        assert_eq!(t.device, Device::Cuda(1));
        assert_eq!(serde_json::to_value(&t).unwrap()["device"], "cuda:1");
        let kernels = Some(Kernels { numerics: Numerics::Native, device: Device::Cuda(1) });
        assert_eq!(t.resources(), Resources { threads: 1, gpu: true, needs_cuda: true, kernels });
    }
}
