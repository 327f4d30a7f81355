//! The sample test frames and generated captions, read once for both the document and the
//! Rerun recording.

use std::collections::BTreeMap;

use anyhow::Context as _;
use rlmflow_stages::grid::Grid;
use rlmflow_stages::npy::Npy;
use rlmflow_stages::{probe, segment};
use serde_json::Value;

use crate::stats::rows;
use crate::study::{Instance, ProbeRun, Study};

/// One sample test frame with everything the report shows of it; each segmenter row by its
/// first seed.
pub struct Sample {
    pub frame: u64,
    pub side: usize,
    pub heatmap: Vec<u8>,
    pub truth: Vec<u8>,
    /// Each segmenter row that kept this frame: its position among the segmenter rows (which
    /// names its figures), the row, its predicted probability x 255.
    pub masks: Vec<(usize, Instance, Vec<u8>)>,
    /// The same for each encoder-reading segmenter row's CLS attention rollout: position, row,
    /// grid side, map.
    pub rollouts: Vec<(usize, Instance, usize, Vec<u8>)>,
    /// The vehicles the image shows, as (column, row) pixel centres (for the recording).
    #[cfg(feature = "rerun")]
    pub actors: Vec<[f64; 2]>,
}

/// The first `count` frames the segmenters kept, when the study has scenes, labels and a
/// segmenter with sample frames; none otherwise.
pub fn samples(study: &Study, count: usize) -> anyhow::Result<Vec<Sample>> {
    let (Some(scenes), Some(labels)) = (&study.scenes, &study.labels) else { return Ok(Vec::new()) };
    let Some(first) = study.segments.iter().find(|s| !s.summary.sample_frames.is_empty()) else { return Ok(Vec::new()) };
    let side = scenes.summary.images[0].size;
    // Each segmenter's arrays, opened once.
    let mut segmenters = Vec::new();
    for (row, group) in rows(&study.segments, |s| &s.instance) {
        let run = group[0];
        let masks = Npy::open(&run.dir.join(segment::SAMPLES))?;
        let rollout = if run.summary.rollout_blocks.is_empty() { None } else { Some(Npy::open(&run.dir.join(segment::ROLLOUT))?) };
        segmenters.push((row, &run.summary.sample_frames, masks, rollout));
    }
    let mut samples = Vec::new();
    for &frame in first.summary.sample_frames.iter().take(count) {
        let (mut masks, mut rollouts) = (Vec::new(), Vec::new());
        for (i, (row, frames, mask_rows, rollout)) in segmenters.iter().enumerate() {
            let Some(k) = frames.iter().position(|&f| f == frame) else { continue };
            masks.push((i, row.clone(), mask_rows.row_u8(k)?));
            if let Some(rollout) = rollout {
                rollouts.push((i, row.clone(), rollout.shape[1], rollout.row_u8(k)?));
            }
        }
        #[cfg(feature = "rerun")]
        let actors = {
            let inside = |v: f64| (0.0..side as f64).contains(&v);
            scenes.frame(frame)?.actors.iter().filter(|a| a.is_vehicle() && inside(a.col) && inside(a.row)).map(|a| [a.col, a.row]).collect()
        };
        samples.push(Sample {
            frame,
            side,
            heatmap: scenes.heatmap(frame)?,
            truth: labels.mask(frame)?,
            masks,
            rollouts,
            #[cfg(feature = "rerun")]
            actors,
        });
    }
    Ok(samples)
}

/// A caption probe row (first seed): per test frame its generated caption and parsed grid.
pub struct Captioner {
    pub row: Instance,
    pub generated: BTreeMap<u64, (String, Grid)>,
}

pub fn captioners(study: &Study) -> anyhow::Result<Vec<Captioner>> {
    rows(&study.probes, |p| &p.instance)
        .into_iter()
        .filter(|(_, g)| g[0].summary.probe == "clipcap")
        .map(|(row, g)| Ok(Captioner { row, generated: generated(g[0])? }))
        .collect()
}

fn generated(run: &ProbeRun) -> anyhow::Result<BTreeMap<u64, (String, Grid)>> {
    let path = run.dir.join(probe::PREDICTIONS);
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let mut out = BTreeMap::new();
    for (n, line) in text.lines().enumerate() {
        let bad = || format!("{}:{}: not a prediction line", path.display(), n + 1);
        let v: Value = serde_json::from_str(line).with_context(bad)?;
        let (Some(frame), Some(caption)) = (v["frame"].as_u64(), v["caption"].as_str()) else { anyhow::bail!(bad()) };
        let grid = Grid::from_json(&v["grid"]).map_err(|e| anyhow::anyhow!("{}: {e}", bad()))?;
        out.insert(frame, (caption.to_owned(), grid));
    }
    Ok(out)
}
