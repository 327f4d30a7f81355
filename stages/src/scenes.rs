//! The Scenes artifact: per frame, a 360-degree radar range-azimuth heatmap, every actor's
//! state, and each actor's pixel position in the heatmap.
//!
//! ```text
//! scenes.json     summary: format, frame count, image size, radar settings, dataset statistics
//! frames.jsonl    one Frame per line, in frame order
//! heatmaps.u8     frames x image x image bytes, row-major (rows: range from the ego outwards;
//!                 columns: azimuth, straight behind at 0, ahead at the centre, the ego's left
//!                 left of centre); value / 255 is the normalised log power
//! ```
//!
//! Actor positions are in the ego frame (x forward, y left, metres; headings relative to the
//! ego's, radians, counter-clockwise).

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufRead, BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use serde::{Deserialize, Serialize};

pub const SUMMARY: &str = "scenes.json";
pub const FRAMES: &str = "frames.jsonl";
pub const HEATMAPS: &str = "heatmaps.u8";
pub const FORMAT: u32 = 1;

/// One actor in one frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Actor {
    pub id: u32,
    /// `car`, `truck`, `walker` or `sign`.
    pub class: String,
    pub x: f64,
    pub y: f64,
    pub heading: f64,
    pub length: f64,
    pub width: f64,
    pub speed: f64,
    /// Pixel coordinates of its centre in the heatmap (pixel centres at integer + 0.5).
    pub row: f64,
    pub col: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Frame {
    pub index: u64,
    pub scenario: String,
    pub actors: Vec<Actor>,
}

/// `scenes.json`: what a reader needs, and the dataset statistics the report shows.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub format: u32,
    pub frames: u64,
    pub image: usize,
    pub range_max_m: f64,
    /// The generator's settings (operator-specific).
    pub generator: serde_json::Value,
    pub frames_per_scenario: BTreeMap<String, u64>,
    /// Entry n: frames with n vehicles.
    pub vehicles_per_scene: Vec<u64>,
    /// Vehicles per grid cell under the default rule, keyed `bin/sector`.
    pub cells: BTreeMap<String, u64>,
}

/// Reads a Scenes artifact directory.
pub struct Scenes {
    dir: PathBuf,
    pub summary: Summary,
}

impl Scenes {
    pub fn open(dir: &Path) -> anyhow::Result<Scenes> {
        let path = dir.join(SUMMARY);
        let summary: Summary = serde_json::from_slice(&std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?)
            .with_context(|| format!("{} is not a Scenes summary", path.display()))?;
        if summary.format != FORMAT {
            bail!("{}: Scenes format {} (this build reads {FORMAT})", path.display(), summary.format);
        }
        Ok(Scenes { dir: dir.to_path_buf(), summary })
    }

    pub fn frames(&self) -> anyhow::Result<Vec<Frame>> {
        let path = self.dir.join(FRAMES);
        let file = File::open(&path).with_context(|| format!("reading {}", path.display()))?;
        BufReader::new(file)
            .lines()
            .enumerate()
            .map(|(i, line)| serde_json::from_str(&line?).with_context(|| format!("{}:{}: not a frame", path.display(), i + 1)))
            .collect()
    }

    /// The heatmap of frame `index` (image x image bytes).
    pub fn heatmap(&self, index: u64) -> anyhow::Result<Vec<u8>> {
        let side = self.summary.image;
        let mut file = File::open(self.dir.join(HEATMAPS))?;
        file.seek(SeekFrom::Start(index * (side * side) as u64))?;
        let mut out = vec![0u8; side * side];
        file.read_exact(&mut out).with_context(|| format!("heatmap {index} is past the end of {HEATMAPS}"))?;
        Ok(out)
    }
}
