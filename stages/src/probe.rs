//! The ProbeReport artifact, and the one scoring rule every probe uses.
//!
//! ```text
//! probe.json         summary: the probe, its settings, one scored row per feature set
//!                    (e.g. `cls`, `mean-patch` and `patches`, or `pixels`), split sizes, and
//!                    the test frames' overlap with what the encoder and tokenizers learnt from
//! predictions.jsonl  per test frame and row: {"frame", "features", "grid"} (the predicted
//!                    grid in the paper's JSON; a caption probe adds "caption")
//! ```
//!
//! Scoring (the paper's): per test frame and cell (distance bin, sector), TP = min(pred, true),
//! FP = max(0, pred - true), FN = max(0, true - pred); summed over the test frames
//! (micro-averaged), then precision, recall and F1 per cell. A distance bin's scores are, as the
//! paper's table says, the cells' scores "averaged across angular sectors within each distance
//! bin": the mean over the bin's cells of each cell's precision, recall and F1. A cell with no
//! true and no predicted vehicle in any test frame has no score and is left out of its bin's
//! mean (a bin with no scored cell scores 0 over 0 cells); within a scored cell a ratio with
//! nothing to divide by is 0 (precision with nothing predicted, recall with nothing there).
//! Secondary figures: each bin pooled (its 12 cells' counts summed, then the ratios) and
//! overall pooled (all 48).

use serde::{Deserialize, Serialize};

use crate::grid::{CELLS, DISTANCE_BINS, SECTORS};

pub const SUMMARY: &str = "probe.json";
pub const PREDICTIONS: &str = "predictions.jsonl";
pub const FORMAT: u32 = 2;

/// Summed true positives, false positives and false negatives.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Counts {
    pub tp: u64,
    pub fp: u64,
    #[serde(rename = "fn")]
    pub fn_: u64,
}

impl Counts {
    fn add(&mut self, pred: u32, truth: u32) {
        self.tp += u64::from(pred.min(truth));
        self.fp += u64::from(pred.saturating_sub(truth));
        self.fn_ += u64::from(truth.saturating_sub(pred));
    }

    fn merge(&mut self, other: &Counts) {
        self.tp += other.tp;
        self.fp += other.fp;
        self.fn_ += other.fn_;
    }

    /// TP / (TP + FP); 0 when nothing was predicted.
    pub fn precision(&self) -> f64 {
        ratio(self.tp, self.tp + self.fp)
    }

    /// TP / (TP + FN); 0 when nothing was there.
    pub fn recall(&self) -> f64 {
        ratio(self.tp, self.tp + self.fn_)
    }

    pub fn f1(&self) -> f64 {
        ratio(2 * self.tp, 2 * self.tp + self.fp + self.fn_)
    }
}

fn ratio(a: u64, b: u64) -> f64 {
    if b == 0 { 0.0 } else { a as f64 / b as f64 }
}

/// Precision, recall and F1 of one group of cells.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Score {
    pub precision: f64,
    pub recall: f64,
    pub f1: f64,
    pub counts: Counts,
}

impl From<Counts> for Score {
    fn from(counts: Counts) -> Score {
        Score { precision: counts.precision(), recall: counts.recall(), f1: counts.f1(), counts }
    }
}

/// The mean of scored cells' precision, recall and F1 (see the module doc).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CellMean {
    pub precision: f64,
    pub recall: f64,
    pub f1: f64,
    /// Cells averaged (those with a true or predicted vehicle).
    pub cells: u64,
}

/// A probe's scores on the test split.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Scores {
    /// All 48 cells pooled.
    pub overall: Score,
    /// By distance bin, keyed as the paper (`0-10m`, ...): the paper's mean over the bin's cells.
    pub bins: std::collections::BTreeMap<String, CellMean>,
    /// By distance bin, the bin's cells pooled.
    pub bins_pooled: std::collections::BTreeMap<String, Score>,
    /// By cell, keyed `bin/sector`.
    pub cells: std::collections::BTreeMap<String, Score>,
}

/// Scores predicted count grids against the true ones (same frames, same order).
pub fn score(predicted: &[[u32; CELLS]], truth: &[[u32; CELLS]]) -> Scores {
    assert_eq!(predicted.len(), truth.len(), "one prediction per frame");
    let mut cells = [Counts::default(); CELLS];
    for (p, t) in predicted.iter().zip(truth) {
        for c in 0..CELLS {
            cells[c].add(p[c], t[c]);
        }
    }
    let mut overall = Counts::default();
    let (mut bins, mut bins_pooled) = (std::collections::BTreeMap::new(), std::collections::BTreeMap::new());
    for (b, bin) in DISTANCE_BINS.iter().enumerate() {
        let mut sum = Counts::default();
        let mut mean = CellMean { precision: 0.0, recall: 0.0, f1: 0.0, cells: 0 };
        for c in &cells[b * SECTORS.len()..(b + 1) * SECTORS.len()] {
            sum.merge(c);
            if c.tp + c.fp + c.fn_ > 0 {
                mean.precision += c.precision();
                mean.recall += c.recall();
                mean.f1 += c.f1();
                mean.cells += 1;
            }
        }
        if mean.cells > 0 {
            let n = mean.cells as f64;
            (mean.precision, mean.recall, mean.f1) = (mean.precision / n, mean.recall / n, mean.f1 / n);
        }
        overall.merge(&sum);
        bins.insert(bin.to_string(), mean);
        bins_pooled.insert(bin.to_string(), Score::from(sum));
    }
    let cells = (0..CELLS).map(|c| (format!("{}/{}", DISTANCE_BINS[c / SECTORS.len()], SECTORS[c % SECTORS.len()]), Score::from(cells[c]))).collect();
    Scores { overall: Score::from(overall), bins, bins_pooled, cells }
}

/// One scored row of a probe: which features it read and how it did.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Row {
    /// `cls`, `mean-patch`, `pixels`, or `caption` for a caption probe.
    pub features: String,
    /// Probe-specific facts (a ridge's chosen strength, a decoder's beam).
    pub details: serde_json::Value,
    pub scores: Scores,
}

/// `probe.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub format: u32,
    pub probe: String,
    pub train_frames: u64,
    pub test_frames: u64,
    /// The test frames checked against every learnt set upstream.
    pub hygiene: Vec<crate::identity::Overlap>,
    pub rows: Vec<Row>,
    /// The probe's settings.
    pub generator: serde_json::Value,
}

pub fn read_summary(dir: &std::path::Path) -> anyhow::Result<Summary> {
    crate::reading::read_summary(dir, SUMMARY, crate::artifact::PROBE_REPORT, "probe", FORMAT)
}

/// The figures a row's metrics hold, each as `ROW.FIGURE`, `ROW.bins.BIN.FIGURE` (the paper's
/// per-bin mean) and `ROW.bins_mean.FIGURE` (the four bins' means averaged).
pub const FIGURES: [&str; 3] = ["f1", "precision", "recall"];

/// What a ProbeReport measures, by dotted path (claims name them): per row (`cls`,
/// `mean-patch`, `pixels`, ...) its pooled figures, each distance bin's and the bins' mean.
pub fn metrics(summary: &Summary) -> serde_json::Value {
    let figures = |p: f64, r: f64, f: f64| serde_json::json!({"f1": f, "precision": p, "recall": r});
    let rows = summary.rows.iter().map(|row| {
        let s = &row.scores;
        let bins: serde_json::Map<String, serde_json::Value> =
            s.bins.iter().map(|(bin, m)| (bin.clone(), figures(m.precision, m.recall, m.f1))).collect();
        let n = s.bins.len().max(1) as f64;
        let mean = |f: fn(&CellMean) -> f64| s.bins.values().map(f).sum::<f64>() / n;
        let mut row_metrics = figures(s.overall.precision, s.overall.recall, s.overall.f1);
        row_metrics["bins"] = bins.into();
        row_metrics["bins_mean"] = figures(mean(|m| m.precision), mean(|m| m.recall), mean(|m| m.f1));
        (row.features.clone(), row_metrics)
    });
    serde_json::Value::Object(rows.collect())
}

/// Every path [`metrics`] gives for rows of these features.
pub fn metric_names(rows: &[&str]) -> Vec<String> {
    let mut names = Vec::new();
    for row in rows {
        for figure in FIGURES {
            names.push(format!("{row}.{figure}"));
            names.extend(DISTANCE_BINS.iter().map(|bin| format!("{row}.bins.{bin}.{figure}")));
            names.push(format!("{row}.bins_mean.{figure}"));
        }
    }
    names
}

/// `predictions.jsonl`: each test frame's predicted counts, per row, in the file's order. A line
/// gives its grid in the paper's JSON (`grid`, as the probes write it) or as the 48 counts in
/// the cells' order (`counts`, as a script may).
pub fn read_predictions(dir: &std::path::Path) -> anyhow::Result<Vec<(u64, String, [u32; CELLS])>> {
    use anyhow::Context as _;
    use serde_json::Value;
    let path = dir.join(PREDICTIONS);
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let line = |(n, l): (usize, &str)| -> anyhow::Result<(u64, String, [u32; CELLS])> {
        let bad = |what: String| anyhow::anyhow!("{}:{}: {what}", path.display(), n + 1);
        let v: Value = serde_json::from_str(l).map_err(|e| bad(format!("not JSON: {e}")))?;
        let frame = v["frame"].as_u64().ok_or_else(|| bad("`frame` must be a frame's index (a whole number)".into()))?;
        let features = v["features"].as_str().filter(|f| !f.is_empty()).ok_or_else(|| bad("`features` must name the row (a string)".into()))?;
        let counts = match (&v["grid"], &v["counts"]) {
            (Value::Null, Value::Array(items)) if items.len() == CELLS => {
                let mut counts = [0u32; CELLS];
                for (c, item) in items.iter().enumerate() {
                    counts[c] =
                        item.as_u64().and_then(|n| u32::try_from(n).ok()).ok_or_else(|| bad(format!("`counts.{c}` must be a count, not {item}")))?;
                }
                counts
            }
            (Value::Null, Value::Array(items)) => return Err(bad(format!("`counts` holds {} numbers; it holds the {CELLS} cells'", items.len()))),
            (grid, Value::Null) if !grid.is_null() => crate::grid::Grid::from_json(grid).map_err(|e| bad(format!("`grid`: {e}")))?.counts,
            (Value::Null, Value::Null) => return Err(bad("give the prediction as `grid` (the paper's JSON) or `counts` (48 counts)".into())),
            _ => return Err(bad("give `grid` or `counts` (a list), not both".into())),
        };
        Ok((frame, features.to_owned(), counts))
    };
    text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()).map(line).collect()
}

/// Where two ProbeReports of the same test frames differ, per frame and row: the cells whose
/// predicted counts differ, most first (frames in file order among equals).
pub fn frame_differences(a: &std::path::Path, b: &std::path::Path) -> anyhow::Result<crate::measure::FrameDifferences> {
    let (pa, pb) = (read_predictions(a)?, read_predictions(b)?);
    let keys = |p: &[(u64, String, [u32; CELLS])]| p.iter().map(|(f, r, _)| (*f, r.clone())).collect::<Vec<_>>();
    if keys(&pa) != keys(&pb) {
        anyhow::bail!(
            "{} and {} predict other frames or rows ({} and {} predictions): they did not read the same test split",
            a.display(),
            b.display(),
            pa.len(),
            pb.len()
        );
    }
    let describe = |counts: &[u32; CELLS]| {
        let cells: Vec<String> = (0..CELLS)
            .filter(|&c| counts[c] > 0)
            .map(|c| format!("{}/{} {}", DISTANCE_BINS[c / SECTORS.len()], SECTORS[c % SECTORS.len()], counts[c]))
            .collect();
        format!("{} vehicles{}{}", counts.iter().sum::<u32>(), if cells.is_empty() { "" } else { ": " }, cells.join(", "))
    };
    let frames = pa
        .iter()
        .zip(&pb)
        .map(|((frame, row, x), (_, _, y))| crate::measure::FrameDifference {
            frame: *frame,
            row: row.clone(),
            differ: (0..CELLS).filter(|&c| x[c] != y[c]).count() as f64,
            a: describe(x),
            b: describe(y),
        })
        .collect();
    Ok(crate::measure::FrameDifferences::ranked("cells predicted differently", frames))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scores_follow_the_papers_rule_on_a_hand_computed_case() {
        let mut truth = [[0u32; CELLS]; 2];
        let mut pred = [[0u32; CELLS]; 2];
        // Frame 0: cell 0 true 3, predicted 1 (tp 1, fn 2); cell 13 (bin 1) true 0, predicted 2 (fp 2).
        truth[0][0] = 3;
        pred[0][0] = 1;
        pred[0][13] = 2;
        // Frame 1: cell 0 true 1, predicted 1 (tp 1); cell 47 (bin 3) true 4, predicted 4 (tp 4).
        truth[1][0] = 1;
        pred[1][0] = 1;
        truth[1][47] = 4;
        pred[1][47] = 4;
        let s = score(&pred, &truth);
        assert_eq!(s.cells["0-10m/left_lane_front_side"].counts, Counts { tp: 2, fp: 0, fn_: 2 });
        assert_eq!(s.bins_pooled["0-10m"].precision, 1.0);
        assert_eq!(s.bins_pooled["0-10m"].recall, 0.5);
        assert!((s.bins_pooled["0-10m"].f1 - 2.0 / 3.0).abs() < 1e-12);
        assert_eq!(s.bins_pooled["10-20m"].counts, Counts { tp: 0, fp: 2, fn_: 0 });
        assert_eq!((s.bins_pooled["10-20m"].precision, s.bins_pooled["10-20m"].recall, s.bins_pooled["10-20m"].f1), (0.0, 0.0, 0.0));
        assert_eq!(s.bins_pooled["30-40m"].f1, 1.0);
        // Overall: tp 6, fp 2, fn 2.
        assert_eq!(s.overall.counts, Counts { tp: 6, fp: 2, fn_: 2 });
        assert!((s.overall.f1 - 0.75).abs() < 1e-12);
        // Perfect predictions score 1.
        assert_eq!(score(&truth, &truth).overall.f1, 1.0);
    }

    #[test]
    fn a_bins_scores_are_the_mean_of_its_scored_cells_leaving_out_empty_ones() {
        // Bin 0-10m over two frames. Cell 0: true 3 + 1, predicted 1 + 1 (tp 2, fn 2): P 1, R 0.5,
        // F1 2/3. Cell 1: true 1, predicted 3 (tp 1, fp 2): P 1/3, R 1, F1 1/2. Cell 2: only a
        // false positive (fp 1): P 0, R 0, F1 0. Cells 3-11: nothing true or predicted, left out.
        let mut truth = [[0u32; CELLS]; 2];
        let mut pred = [[0u32; CELLS]; 2];
        (truth[0][0], pred[0][0], truth[1][0], pred[1][0]) = (3, 1, 1, 1);
        (truth[0][1], pred[0][1]) = (1, 3);
        pred[1][2] = 1;
        let s = score(&pred, &truth);
        let bin = &s.bins["0-10m"];
        assert_eq!(bin.cells, 3);
        assert!((bin.precision - (1.0 + 1.0 / 3.0 + 0.0) / 3.0).abs() < 1e-12, "{bin:?}");
        assert!((bin.recall - (0.5 + 1.0 + 0.0) / 3.0).abs() < 1e-12, "{bin:?}");
        assert!((bin.f1 - (2.0 / 3.0 + 0.5 + 0.0) / 3.0).abs() < 1e-12, "{bin:?}");
        // Pooled, the same bin is tp 3, fp 3, fn 2.
        assert_eq!(s.bins_pooled["0-10m"].counts, Counts { tp: 3, fp: 3, fn_: 2 });
        assert!((s.bins_pooled["0-10m"].f1 - 6.0 / 11.0).abs() < 1e-12);
        // A bin without a true or predicted vehicle scores 0 over 0 cells.
        assert_eq!(s.bins["30-40m"], CellMean { precision: 0.0, recall: 0.0, f1: 0.0, cells: 0 });
    }
}
