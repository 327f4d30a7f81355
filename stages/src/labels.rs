//! The Labels artifact: per frame of a Scenes artifact, the paper's grid, the train/test split and
//! the segmentation target.
//!
//! ```text
//! labels.json   summary: format, frames, train/test counts, the rule and mask settings,
//!               vehicles per cell and per frame
//! labels.jsonl  one line per frame, in frame order:
//!               {"frame": 0, "split": "train", "counts": [48 numbers], "grid": {the paper's JSON}}
//!               counts[bin * 12 + sector], bins and sectors in the paper's order
//! masks.npy     uint8, (frames, size, size), the primary image's geometry; value / 255 is the
//!               target in [0, 1]
//! ```

use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use serde::{Deserialize, Serialize};

use crate::grid::{CELLS, Grid, GridRule};
use crate::npy::Npy;

pub const SUMMARY: &str = "labels.json";
pub const LINES: &str = "labels.jsonl";
pub const MASKS: &str = "masks.npy";
pub const FORMAT: u32 = 1;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    Train,
    Test,
}

impl Split {
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Test => "test",
        }
    }
}

/// The Gaussian blob drawn per vehicle, in pixels of the image it is drawn on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MaskGeometry {
    pub size: usize,
    pub radius_px: f64,
    pub sigma_px: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub format: u32,
    pub frames: u64,
    pub train: u64,
    pub test: u64,
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
    pub split: Split,
    pub grid: Grid,
}

impl FrameLabel {
    /// The line `labels.jsonl` holds for this frame.
    pub fn to_line(&self) -> String {
        format!(
            "{{\"frame\":{},\"split\":\"{}\",\"counts\":{},\"grid\":{}}}",
            self.frame,
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
            split: Split,
            counts: Vec<u32>,
            grid: serde_json::Value,
        }
        let line: Line = serde_json::from_str(line).map_err(|e| e.to_string())?;
        let grid = Grid::from_json(&line.grid)?;
        if line.counts.len() != CELLS || line.counts != grid.counts {
            return Err("`counts` does not match `grid`".into());
        }
        Ok(FrameLabel { frame: line.frame, split: line.split, grid })
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
        let summary: Summary = crate::read_summary(dir, SUMMARY, "Labels", "labels", FORMAT)?;
        let path = dir.join(LINES);
        let frames = crate::read_lines(&path, FrameLabel::from_line)?;
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
}
