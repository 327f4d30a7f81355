//! The Labels artifact: per frame of a Scenes artifact, the paper's grid, the train/test split and
//! the segmentation target.
//!
//! ```text
//! labels.json   summary: format, frames, train/test counts, the split rule and the test share
//!               it achieved per vehicle count, the grid rule and mask settings, vehicles per
//!               cell and per frame, and for sequences the nearest-neighbour pixel similarity
//!               from test to train against train to train
//! labels.jsonl  one line per frame, in frame order:
//!               {"frame": 0, "id": "...", "episode": "..." (sequences only), "split": "train",
//!                "counts": [48 numbers], "grid": {the paper's JSON}}
//!               counts[bin * 12 + sector], bins and sectors in the paper's order
//! masks.npy     uint8, (frames, size, size), the primary image's geometry; value / 255 is the
//!               target in [0, 1]
//! ```

use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use serde::{Deserialize, Serialize};

use crate::grid::{CELLS, Grid, GridRule};
use crate::identity::{FrameSet, Split, SplitBy};
use crate::npy::Npy;

pub const SUMMARY: &str = "labels.json";
pub const LINES: &str = "labels.jsonl";
pub const MASKS: &str = "masks.npy";
pub const FORMAT: u32 = 2;

/// The Gaussian blob drawn per vehicle, in pixels of the image it is drawn on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MaskGeometry {
    pub size: usize,
    pub radius_px: f64,
    pub sigma_px: f64,
}

/// Frames with one vehicle count, and how many of them the split holds out.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Stratum {
    pub vehicles: u32,
    pub frames: u64,
    pub test: u64,
}

/// How a Labels artifact split its frames (the rule is [`crate::identity`]'s).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SplitSummary {
    /// The rule, in words.
    pub rule: String,
    /// `episode` (a sequence's frames share a split) or `frame`.
    pub by: SplitBy,
    pub test_fraction: f64,
    pub seed: u64,
    /// Split groups (episodes, and frames without one) and those held out.
    pub groups: u64,
    pub test_groups: u64,
    /// Per vehicle count in the grid: frames and test frames (the achieved stratification).
    pub strata: Vec<Stratum>,
}

/// How alike test frames are to their nearest training frame, against training frames to their
/// nearest other training frame: the Pearson correlation of primary-image pixels, averaged, over
/// an evenly spaced sample of the frames that belong to a sequence.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NearestNeighbour {
    pub sample_train: u64,
    pub sample_test: u64,
    pub test_to_train: f64,
    pub train_to_train: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub format: u32,
    pub frames: u64,
    pub train: u64,
    pub test: u64,
    pub split: SplitSummary,
    /// For artifacts with sequences (and a sample size above 0).
    pub nearest_neighbour: Option<NearestNeighbour>,
    pub rule: GridRule,
    pub mask: MaskGeometry,
    /// Vehicles per cell over all frames, keyed `bin/sector`.
    pub cells: std::collections::BTreeMap<String, u64>,
    /// Entry n: frames with n vehicles in the grid.
    pub vehicles_per_frame: Vec<u64>,
}

/// One frame's labels.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameLabel {
    pub frame: u64,
    /// The frame's identity and episode, as its Scenes artifact has them.
    pub id: String,
    pub episode: Option<String>,
    pub split: Split,
    pub grid: Grid,
}

impl FrameLabel {
    /// The line `labels.jsonl` holds for this frame.
    pub fn to_line(&self) -> String {
        let episode = self.episode.as_ref().map_or(String::new(), |e| format!(",\"episode\":\"{e}\""));
        format!(
            "{{\"frame\":{},\"id\":\"{}\"{episode},\"split\":\"{}\",\"counts\":{},\"grid\":{}}}",
            self.frame,
            self.id,
            self.split.name(),
            serde_json::to_string(&self.grid.counts.as_slice()).expect("numbers"),
            self.grid.to_json()
        )
    }

    fn from_line(line: &str) -> Result<FrameLabel, String> {
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct Line {
            frame: u64,
            id: String,
            #[serde(default)]
            episode: Option<String>,
            split: Split,
            counts: Vec<u32>,
            grid: serde_json::Value,
        }
        let line: Line = serde_json::from_str(line).map_err(|e| e.to_string())?;
        let grid = Grid::from_json(&line.grid)?;
        if line.counts.len() != CELLS || line.counts != grid.counts {
            return Err("`counts` does not match `grid`".into());
        }
        Ok(FrameLabel { frame: line.frame, id: line.id, episode: line.episode, split: line.split, grid })
    }
}

/// A Labels artifact, read.
pub struct Labels {
    pub summary: Summary,
    pub frames: Vec<FrameLabel>,
    masks: Npy,
    dir: PathBuf,
}

impl Labels {
    pub fn open(dir: &Path) -> anyhow::Result<Labels> {
        let summary: Summary = crate::reading::read_summary(dir, SUMMARY, crate::artifact::LABELS, "labels", FORMAT)?;
        let path = dir.join(LINES);
        let frames = crate::reading::read_lines(&path, FrameLabel::from_line)?;
        if frames.len() as u64 != summary.frames || frames.iter().enumerate().any(|(i, f)| f.frame != i as u64) {
            bail!("{}: expected frames 0..{} in order", path.display(), summary.frames);
        }
        let masks = Npy::open(&dir.join(MASKS))?;
        let size = summary.mask.size;
        if masks.shape != [frames.len(), size, size] {
            bail!("{}: shape {:?}, expected [{}, {size}, {size}]", dir.join(MASKS).display(), masks.shape, frames.len());
        }
        Ok(Labels { summary, frames, masks, dir: dir.to_owned() })
    }

    /// Frame `frame`'s mask, size x size bytes, row-major.
    pub fn mask(&self, frame: u64) -> anyhow::Result<Vec<u8>> {
        self.masks.row_u8(frame as usize).with_context(|| format!("labels in {}", self.dir.display()))
    }

    /// Checks that these labels describe a Scenes artifact of `frames` frames: a stage that reads
    /// both must be given the scenes that were labelled.
    pub fn check_scenes(&self, frames: u64) -> anyhow::Result<()> {
        if self.frames.len() as u64 != frames {
            bail!("the labels have {} frames but the scenes {frames}: give the stage the scenes that were labelled", self.frames.len());
        }
        Ok(())
    }

    pub fn split(&self, split: Split) -> impl Iterator<Item = &FrameLabel> {
        self.frames.iter().filter(move |f| f.split == split)
    }

    /// The identities of the frames in `split`.
    pub fn ids(&self, split: Split) -> FrameSet {
        self.split(split).map(|f| f.id.clone()).collect()
    }

    /// The training split cut into the frames to fit on and a validation slice of about `share`
    /// of its split groups (at least one): the groups whose split position lies highest, so an
    /// episode is never cut and the slice depends on the frames alone, not their order.
    pub fn train_validation<'a>(&'a self, share: f64) -> (Vec<&'a FrameLabel>, Vec<&'a FrameLabel>) {
        let group = |f: &'a FrameLabel| self.summary.split.by.group(&f.id, f.episode.as_deref());
        let groups: std::collections::BTreeSet<&str> = self.split(Split::Train).map(group).collect();
        let mut ranked: Vec<(f64, &str)> = groups.iter().map(|g| (crate::identity::split_position(g, self.summary.split.seed), *g)).collect();
        ranked.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(b.1)));
        let take = ((groups.len() as f64 * share).round() as usize).clamp(usize::from(!groups.is_empty()), groups.len().saturating_sub(1).max(1));
        let held: std::collections::BTreeSet<&str> = ranked.iter().take(take).map(|(_, g)| *g).collect();
        self.split(Split::Train).partition(|f| !held.contains(group(f)))
    }
}
