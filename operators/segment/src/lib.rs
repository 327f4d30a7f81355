//! The `segment` stage kind's operators as the planning binary sees them: settings, specs and
//! resources. They run in the `rlmflow-torch` worker (`operators/segment/torch`) and write the
//! SegReport artifact (`rlmflow_stages::segment`), scored by the same pixel metrics.
//!
//! `pup`: the paper's probe of spatial grounding at the patch level. The encoder stays frozen;
//! a progressive-upsampling decoder learns vehicle masks from its patch tokens after `ln_post`.
//! It also saves the CLS attention rollout of the encoder on the sample frames.
//! `unet`: the paper's baseline, a U-Net trained on the heatmap pixels with the same masks, loss
//! and metrics. It reads no encoder (its spec's inputs leave the slot out), so it runs once,
//! not per encoder variant.
//!
//! Training: AdamW, warmup then cosine, global-norm clipping, loss `dice_weight` * soft Dice +
//! (1 - `dice_weight`) * BCE against the labels' soft masks; one checkpoint per epoch.

use rlmflow_stages::memory::{FLOAT, LOWER_BY_ACCUMULATING, TRAINED, activation_bytes, conv3x3_bn};
use rlmflow_stages::numerics::Target;
use rlmflow_stages::{Footprint, InWorker, InputOutlines, OperatorSpec, Outline, Resources, SettingError, Settings, Training};

/// The most bytes of frozen-encoder tokens `pup` caches for every frame; beyond, it encodes each
/// batch's frames as it trains.
pub const TOKEN_CACHE_BYTES: u64 = 2 << 30;
use serde::{Deserialize, Serialize};

/// The binary the segmenters run in.
pub const WORKER: &str = "rlmflow-torch";

/// What both segmenters check alike: the kept sample frames and the loss's Dice share.
fn check_head(samples: usize, dice_weight: f64) -> Result<(), SettingError> {
    SettingError::check_range("dice_weight", dice_weight, 0.0..=1.0)?;
    SettingError::check_range("samples", samples, 0..=256)
}

fn check_widths(key: &str, widths: &[i64], allow_empty: bool) -> Result<(), SettingError> {
    if widths.is_empty() && !allow_empty {
        return Err(SettingError::new(key, "must list at least one width"));
    }
    SettingError::check_range(&format!("{key} (count)"), widths.len(), 0..=8)?;
    for (i, &w) in widths.iter().enumerate() {
        SettingError::check_range(&format!("{key}.{i}"), w, 1..=4096)?;
    }
    Ok(())
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default)]
pub struct PupSettings {
    /// Decoder widths, one conv + BN + ReLU + 2x upsampling stage each; empty: the paper's table
    /// (256, 256, 128, 64), one stage per doubling from the encoder's grid to the image side.
    pub channels: Vec<i64>,
    /// Attention rollout over the encoder's last this many blocks (the paper's figure: 3); 0: all.
    pub rollout_layers: usize,
    /// Test frames whose predicted masks and rollout maps the artifact keeps, 0..=256.
    pub samples: usize,
    /// The Dice share of the loss, the rest BCE (the paper: 0.6).
    pub dice_weight: f64,
    /// Run even when some test frames are among those the encoder trained on (a deliberate
    /// study; the report flags the row). Off: such an overlap stops the stage.
    pub allow_test_overlap: bool,
    /// The schedule, optimiser and device (`rlmflow_stages::training`).
    #[serde(flatten)]
    pub training: Training,
}

impl Default for PupSettings {
    fn default() -> Self {
        PupSettings {
            channels: Vec::new(),
            rollout_layers: 3,
            samples: 8,
            dice_weight: 0.6,
            allow_test_overlap: false,
            training: Training::default(),
        }
    }
}

impl Settings for PupSettings {
    fn check(&self) -> Result<(), SettingError> {
        check_widths("channels", &self.channels, true)?;
        SettingError::check_range("rollout_layers", self.rollout_layers, 0..=64)?;
        check_head(self.samples, self.dice_weight)?;
        self.training.check()
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default)]
pub struct UnetSettings {
    /// Widths per level, finest first (the original U-Net: 64, 128, 256, 512, 1024); the image
    /// side must divide by 2^(levels - 1).
    pub channels: Vec<i64>,
    pub samples: usize,
    pub dice_weight: f64,
    #[serde(flatten)]
    pub training: Training,
}

impl Default for UnetSettings {
    fn default() -> Self {
        let pup = PupSettings::default();
        UnetSettings { channels: vec![16, 32, 64, 128], samples: pup.samples, dice_weight: pup.dice_weight, training: pup.training }
    }
}

impl Settings for UnetSettings {
    fn check(&self) -> Result<(), SettingError> {
        check_widths("channels", &self.channels, false)?;
        check_head(self.samples, self.dice_weight)?;
        self.training.check()
    }
}

fn pup_spec() -> OperatorSpec {
    OperatorSpec {
        name: "pup",
        kind: "segment",
        version: 9,
        inputs: Some(&["encoder", "scenes", "labels"]),
        summary: "progressive-upsampling decoder on the frozen encoder's patch tokens, with its attention rollout (libtorch, in rlmflow-torch)",
    }
}

fn unet_spec() -> OperatorSpec {
    OperatorSpec {
        name: "unet",
        kind: "segment",
        version: 8,
        // No encoder: the baseline must not fan out over the encoder's variants.
        inputs: Some(&["scenes", "labels"]),
        summary: "U-Net on the heatmap pixels, the segmentation baseline (libtorch, in rlmflow-torch)",
    }
}

fn pup_resources(s: &PupSettings) -> Resources {
    s.training.resources()
}

fn unet_resources(s: &UnetSettings) -> Resources {
    s.training.resources()
}

/// The U-Net against its scenes: the batch fits their frames and its levels halve their image
/// evenly.
fn unet_outline(s: &UnetSettings, inputs: &InputOutlines) -> Result<Outline, SettingError> {
    let outline = s.training.outline(inputs)?;
    if let Some(image) = outline.image {
        s.check_depth(image)?;
    }
    Ok(outline)
}

impl UnetSettings {
    /// Whether its levels halve an image of `image` pixels evenly: checked when the pipeline is
    /// validated, and again by the worker on the scenes it reads.
    pub fn check_depth(&self, image: u64) -> Result<(), SettingError> {
        let divisor = 1u64 << (self.channels.len() - 1);
        if !image.is_multiple_of(divisor) {
            return Err(SettingError::new(
                "channels",
                format!("{} levels need an image side divisible by {divisor}; the scenes have {image}", self.channels.len()),
            ));
        }
        Ok(())
    }
}

/// The decoder widths of the paper's PUP table (768 -> 256 -> 256 -> 128 -> 64), one stage per
/// doubling of `grid` up to `side`: the table's last stages when fewer are needed, 256 wide
/// stages first when more are.
pub fn pup_widths(grid: i64, side: i64) -> Vec<i64> {
    let mut stages = 0usize;
    while grid << stages < side {
        stages += 1;
    }
    let paper = [256, 256, 128, 64];
    let extra = stages.saturating_sub(paper.len());
    std::iter::repeat_n(256, extra).chain(paper[paper.len() - (stages - extra)..].iter().copied()).collect()
}

/// The frozen encoder held once (its tokens cached for every frame up to the worker's 2 GiB, else
/// encoded per batch), and the decoder trained on `batch` frames: per frame the token map, each
/// stage's convolution, BatchNorm and ReLU outputs and its upsampling, the full-size logits.
fn pup_footprint(s: &PupSettings, inputs: &InputOutlines, target: Target) -> Option<Footprint> {
    let scenes = Outline::passed_on(inputs);
    let (side, model) = (scenes.image?, Outline::of(inputs, "encoder")?.model?);
    let widths = if s.channels.is_empty() { pup_widths(model.grid as i64, side as i64) } else { s.channels.clone() };
    let (mut input, mut grid, mut decoder, mut per_frame) = (model.width, model.grid, 0, (model.grid * model.grid + 1) * model.width);
    for &w in &widths {
        let w = w as u64;
        decoder += conv3x3_bn(input, w);
        per_frame += 3 * w * grid * grid + w * 4 * grid * grid;
        (input, grid) = (w, 2 * grid);
    }
    decoder += input + 1;
    per_frame += 4 * side * side;
    let tokens = scenes.frames.unwrap_or(0) * (model.grid * model.grid + 1) * model.width * FLOAT;
    // Beyond the cache each micro-batch is encoded without gradients: one block's tokens and
    // MLP units (4 x width) at a time.
    let encoded = (model.grid * model.grid + 1) * 12 * model.width;
    let cached = if tokens <= TOKEN_CACHE_BYTES { tokens } else { s.training.micro_batch() * encoded * FLOAT };
    let peak_bytes = model.parameters * FLOAT
        + decoder * TRAINED
        + cached
        + activation_bytes(per_frame * s.training.micro_batch(), s.training.precision.on(target));
    Some(Footprint { parameters: model.parameters + decoder, peak_bytes, lower_with: LOWER_BY_ACCUMULATING })
}

/// The U-Net trained on `batch` frames: per frame each level's two convolutions with their
/// BatchNorm and ReLU outputs going down, pooled, and coming back up with the skip joined.
fn unet_footprint(s: &UnetSettings, inputs: &InputOutlines, target: Target) -> Option<Footprint> {
    let side = Outline::passed_on(inputs).image?;
    let widths: Vec<u64> = s.channels.iter().map(|&w| w as u64).collect();
    let (mut parameters, mut per_frame, mut input) = (0, side * side, 1);
    for (level, &w) in widths.iter().enumerate() {
        let area = (side >> level) * (side >> level);
        parameters += conv3x3_bn(input, w) + conv3x3_bn(w, w);
        per_frame += 6 * w * area + w * area / 4;
        if let Some(&below) = widths.get(level + 1) {
            parameters += conv3x3_bn(w + below, w) + conv3x3_bn(w, w);
            per_frame += (below + w + below) * area + 6 * w * area;
        }
        input = w;
    }
    parameters += widths[0] + 1;
    per_frame += 4 * side * side;
    Some(Footprint {
        parameters,
        peak_bytes: parameters * TRAINED + activation_bytes(per_frame * s.training.micro_batch(), s.training.precision.on(target)),
        lower_with: LOWER_BY_ACCUMULATING,
    })
}

/// `pup` as `rlmflow` registers it: validated and planned here, run by the worker.
pub fn pup() -> InWorker<PupSettings> {
    InWorker {
        spec: pup_spec(),
        worker: WORKER,
        resources: pup_resources,
        outline: |s, inputs| s.training.outline(inputs),
        footprint: pup_footprint,
        metrics: segment_metrics,
        run: None,
    }
}

/// `unet` as `rlmflow` registers it.
pub fn unet() -> InWorker<UnetSettings> {
    InWorker {
        spec: unet_spec(),
        worker: WORKER,
        resources: unet_resources,
        outline: unet_outline,
        footprint: unet_footprint,
        metrics: segment_metrics,
        run: None,
    }
}

/// Every segmenter measures the same figures.
fn segment_metrics<S>(_: &S) -> Vec<String> {
    rlmflow_stages::segment::METRICS.iter().map(|m| m.to_string()).collect()
}

#[cfg(test)]
mod tests {
    use rlmflow_stages::DynOperator;

    use super::*;

    #[test]
    fn pup_widths_follow_the_paper_table() {
        assert_eq!(pup_widths(14, 224), [256, 256, 128, 64], "vit-b16: 14 -> 224, four doublings");
        assert_eq!(pup_widths(8, 64), [256, 128, 64]);
        assert_eq!(pup_widths(4, 32), [256, 128, 64]);
        assert_eq!(pup_widths(2, 64), [256, 256, 256, 128, 64]);
        assert_eq!(pup_widths(7, 50), [256, 128, 64], "7 -> 56, resized to 50");
    }

    #[test]
    fn impossible_settings_name_their_key() {
        let pup_key = |v: serde_json::Value| pup().settings(v).unwrap_err().key;
        assert_eq!(pup_key(serde_json::json!({"channels": [64, 0]})), "channels.1");
        assert_eq!(pup_key(serde_json::json!({"dice_weight": 1.5})), "dice_weight");
        assert_eq!(pup_key(serde_json::json!({"device": "tpu"})), "device");
        assert_eq!(pup_key(serde_json::json!({"epochs": 0})), "epochs");
        let unet_key = |v: serde_json::Value| unet().settings(v).unwrap_err().key;
        assert_eq!(unet_key(serde_json::json!({"channels": []})), "channels");
        assert_eq!(unet_key(serde_json::json!({"min_lr": 1.0, "lr": 0.1})), "min_lr");
        assert_eq!(unet_key(serde_json::json!({"rollout_layers": 3})), "rollout_layers", "the U-Net has no attention");
        assert!(pup().settings(serde_json::json!({})).is_ok() && unet().settings(serde_json::json!({})).is_ok());
    }
}
