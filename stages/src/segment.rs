//! The SegReport artifact, and the segmentation metrics every segment operator scores with.
//!
//! ```text
//! segment.json      summary: operator, split sizes, the test frames' overlap with what the
//!                   encoder trained on, metrics on the test split, the per-epoch
//!                   log (loss, test loss, IoU and AP at 0.5), the sample frames, the rollout's
//!                   blocks (pup), the settings
//! samples.npy       uint8 (samples, side, side): predicted probability x 255 on the sample frames
//! rollout.npy       uint8 (samples, grid, grid): the encoder's CLS attention rollout on the same
//!                   frames, each map scaled to its maximum (pup only)
//! head.safetensors  the trained head (PUP decoder or U-Net)
//! frames.jsonl      per test frame, in order: {"frame", "iou", "dice", "truth_pixels",
//!                   "predicted_pixels"} at threshold 0.5 (a frame with no vehicle pixel true
//!                   or predicted scores IoU and Dice 1: nothing to find, nothing found)
//! ```
//!
//! Ground truth is the labels' mask binarised at 0.3 (value / 255 >= 0.3). A prediction in
//! [0, 1] counts as positive at threshold t when it is >= t, for t = 0, 0.01, ..., 1; pixels of
//! all test frames are pooled (micro-averaged). At each threshold: precision TP / (TP + FP),
//! recall TP / (TP + FN), IoU TP / (TP + FP + FN), Dice 2TP / (2TP + FP + FN). Reported: the
//! four at 0.5, the IoU and Dice curves, Peak IoU (the curve's maximum) and AP, the area under
//! the precision-recall curve of the sweep taken stepwise:
//! AP = sum over ascending thresholds t_k of (R(t_k) - R(t_k+1)) * P(t_k), with R = 0 past the
//! last threshold. A perfect predictor scores AP 1; a constant one scores the positive rate.

use serde::{Deserialize, Serialize};

pub const SUMMARY: &str = "segment.json";
pub const SAMPLES: &str = "samples.npy";
pub const ROLLOUT: &str = "rollout.npy";
pub const WEIGHTS: &str = "head.safetensors";
pub const FRAMES: &str = "frames.jsonl";
pub const FORMAT: u32 = 2;

/// `segment.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub format: u32,
    /// `pup` or `unet`.
    pub operator: String,
    pub train_frames: u64,
    pub test_frames: u64,
    /// The test frames checked against every learnt set upstream (none for the U-Net).
    pub hygiene: Vec<crate::identity::Overlap>,
    pub epochs: u64,
    pub steps: u64,
    pub metrics: SegMetrics,
    /// One line per epoch.
    pub log: Vec<serde_json::Value>,
    /// The test frames `samples.npy` (and `rollout.npy`) hold, in order.
    pub sample_frames: Vec<u64>,
    /// The encoder blocks the rollout multiplies (0-based), empty without one.
    pub rollout_blocks: Vec<usize>,
    pub generator: serde_json::Value,
}

pub fn read_summary(dir: &std::path::Path) -> anyhow::Result<Summary> {
    crate::reading::read_summary(dir, SUMMARY, crate::artifact::SEG_REPORT, "segment", FORMAT)
}

/// What a SegReport measures, by dotted path (claims name them): its test-split figures at
/// threshold 0.5, Peak IoU, AP and the positive rate.
pub const METRICS: [&str; 7] = ["precision", "recall", "iou", "dice", "peak_iou", "ap", "positive_rate"];

/// [`METRICS`] of a summary.
pub fn metrics(summary: &Summary) -> serde_json::Value {
    let m = &summary.metrics;
    let values = [m.precision, m.recall, m.iou, m.dice, m.peak_iou, m.ap, m.positive_rate];
    serde_json::Value::Object(METRICS.iter().zip(values).map(|(k, v)| (k.to_string(), v.into())).collect())
}

/// One test frame's scores at threshold 0.5 (a line of [`FRAMES`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameScore {
    pub frame: u64,
    pub iou: f64,
    pub dice: f64,
    pub truth_pixels: u64,
    pub predicted_pixels: u64,
}

impl FrameScore {
    /// Frame `frame`'s predictions in [0, 1] against its mask bytes, with [`PixelCounts`]' rule
    /// for what is positive.
    pub fn of(frame: u64, predicted: &[f32], mask: &[u8]) -> FrameScore {
        let (mut tp, mut fp, mut fn_) = (0u64, 0u64, 0u64);
        for (&p, &m) in predicted.iter().zip(mask) {
            let positive = bin(p) >= THRESHOLDS / 2;
            match (positive, f32::from(m) / 255.0 >= TRUTH_THRESHOLD) {
                (true, true) => tp += 1,
                (true, false) => fp += 1,
                (false, true) => fn_ += 1,
                (false, false) => {}
            }
        }
        let ratio = |a: u64, b: u64| if b == 0 { 1.0 } else { a as f64 / b as f64 };
        FrameScore { frame, iou: ratio(tp, tp + fp + fn_), dice: ratio(2 * tp, 2 * tp + fp + fn_), truth_pixels: tp + fn_, predicted_pixels: tp + fp }
    }
}

/// [`FRAMES`] of a SegReport.
pub fn read_frames(dir: &std::path::Path) -> anyhow::Result<Vec<FrameScore>> {
    use anyhow::Context as _;
    let path = dir.join(FRAMES);
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(n, l)| serde_json::from_str(l).with_context(|| format!("{}:{}: not a frame score", path.display(), n + 1)))
        .collect()
}

/// Where two SegReports of the same test frames differ: each frame's IoU at 0.5 on either
/// side, the largest difference first.
pub fn frame_differences(a: &std::path::Path, b: &std::path::Path) -> anyhow::Result<crate::measure::FrameDifferences> {
    let (fa, fb) = (read_frames(a)?, read_frames(b)?);
    if fa.iter().map(|f| f.frame).ne(fb.iter().map(|f| f.frame)) {
        anyhow::bail!("{} and {} score other test frames: they did not read the same test split", a.display(), b.display());
    }
    let describe = |f: &FrameScore| format!("IoU {:.3} ({} px predicted, {} true)", f.iou, f.predicted_pixels, f.truth_pixels);
    let frames = fa
        .iter()
        .zip(&fb)
        .map(|(x, y)| crate::measure::FrameDifference {
            frame: x.frame,
            row: String::new(),
            differ: (x.iou - y.iou).abs(),
            a: describe(x),
            b: describe(y),
        })
        .collect();
    Ok(crate::measure::FrameDifferences::ranked("IoU difference at 0.5", frames))
}

/// Thresholds 0, 0.01, ..., 1.
pub const THRESHOLDS: usize = 101;
/// Ground truth is a mask value of at least this share of 255.
pub const TRUTH_THRESHOLD: f32 = 0.3;

/// The highest threshold k / 100 that a prediction `p` reaches.
fn bin(p: f32) -> usize {
    ((p.clamp(0.0, 1.0) as f64 * 100.0 + 1e-9).floor() as usize).min(THRESHOLDS - 1)
}

/// Pixels of the test frames by predicted-score bin, split by ground truth.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PixelCounts {
    positive: Vec<u64>,
    negative: Vec<u64>,
}

/// The metrics of one segmenter on the test split.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SegMetrics {
    pub precision: f64,
    pub recall: f64,
    pub iou: f64,
    pub dice: f64,
    pub peak_iou: f64,
    pub peak_threshold: f64,
    pub ap: f64,
    pub positive_rate: f64,
    /// IoU and Dice at each threshold.
    pub iou_curve: Vec<f64>,
    pub dice_curve: Vec<f64>,
}

impl PixelCounts {
    pub fn new() -> PixelCounts {
        PixelCounts { positive: vec![0; THRESHOLDS], negative: vec![0; THRESHOLDS] }
    }

    /// Adds one frame: predictions in [0, 1] (clamped) and its mask bytes, pixel for pixel.
    pub fn add(&mut self, predicted: &[f32], mask: &[u8]) {
        assert_eq!(predicted.len(), mask.len(), "one prediction per mask pixel");
        for (&p, &m) in predicted.iter().zip(mask) {
            if f32::from(m) / 255.0 >= TRUTH_THRESHOLD {
                self.positive[bin(p)] += 1;
            } else {
                self.negative[bin(p)] += 1;
            }
        }
    }

    pub fn metrics(&self) -> SegMetrics {
        let total_positive: u64 = self.positive.iter().sum();
        let total: u64 = total_positive + self.negative.iter().sum::<u64>();
        let ratio = |a: u64, b: u64| if b == 0 { 0.0 } else { a as f64 / b as f64 };
        // Counts at threshold k: every bin at or above it is predicted positive.
        let (mut tp, mut fp) = (vec![0u64; THRESHOLDS], vec![0u64; THRESHOLDS]);
        let (mut run_tp, mut run_fp) = (0, 0);
        for k in (0..THRESHOLDS).rev() {
            run_tp += self.positive[k];
            run_fp += self.negative[k];
            tp[k] = run_tp;
            fp[k] = run_fp;
        }
        let fn_ = |k: usize| total_positive - tp[k];
        let iou_curve: Vec<f64> = (0..THRESHOLDS).map(|k| ratio(tp[k], tp[k] + fp[k] + fn_(k))).collect();
        let dice_curve: Vec<f64> = (0..THRESHOLDS).map(|k| ratio(2 * tp[k], 2 * tp[k] + fp[k] + fn_(k))).collect();
        let precision = |k: usize| if tp[k] + fp[k] == 0 { 1.0 } else { ratio(tp[k], tp[k] + fp[k]) };
        let recall = |k: usize| ratio(tp[k], total_positive);
        let ap = (0..THRESHOLDS).map(|k| (recall(k) - if k + 1 < THRESHOLDS { recall(k + 1) } else { 0.0 }) * precision(k)).sum();
        let (peak, peak_iou) = iou_curve.iter().enumerate().fold((0, f64::MIN), |best, (k, &v)| if v > best.1 { (k, v) } else { best });
        let half = 50;
        SegMetrics {
            precision: ratio(tp[half], tp[half] + fp[half]),
            recall: recall(half),
            iou: iou_curve[half],
            dice: dice_curve[half],
            peak_iou,
            peak_threshold: peak as f64 / 100.0,
            ap,
            positive_rate: ratio(total_positive, total),
            iou_curve,
            dice_curve,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 10-pixel frame: the first 3 pixels are vehicles.
    const MASK: [u8; 10] = [255, 200, 80, 60, 0, 0, 0, 0, 0, 0];

    fn metrics(predicted: &[f32]) -> SegMetrics {
        let mut counts = PixelCounts::new();
        counts.add(predicted, &MASK);
        counts.metrics()
    }

    #[test]
    fn a_hand_computed_case() {
        // At 0.5: predicted positive pixels 0, 1, 3 -> TP 2, FP 1, FN 1.
        let m = metrics(&[0.9, 0.6, 0.2, 0.7, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0]);
        assert_eq!((m.precision, m.recall), (2.0 / 3.0, 2.0 / 3.0));
        assert!((m.iou - 0.5).abs() < 1e-12 && (m.dice - 2.0 / 3.0).abs() < 1e-12);
        // At 0.2 and below 0.2: TP 3, FP 1 -> IoU 0.75, the peak.
        assert!((m.peak_iou - 0.75).abs() < 1e-12 && m.peak_iou >= m.iou);
        assert_eq!(m.positive_rate, 0.3);
    }

    #[test]
    fn ap_is_one_for_a_perfect_predictor_and_the_positive_rate_for_a_constant_one() {
        let truth: Vec<f32> = MASK.iter().map(|&m| if f32::from(m) / 255.0 >= TRUTH_THRESHOLD { 1.0 } else { 0.0 }).collect();
        let perfect = metrics(&truth);
        assert!((perfect.ap - 1.0).abs() < 1e-12, "{}", perfect.ap);
        assert_eq!((perfect.iou, perfect.peak_iou), (1.0, 1.0));
        for c in [0.0, 0.37, 0.5, 1.0] {
            let constant = metrics(&[c; 10]);
            assert!((constant.ap - 0.3).abs() < 1e-12, "constant {c}: AP {}", constant.ap);
            assert!(constant.peak_iou >= constant.iou);
        }
    }
}
