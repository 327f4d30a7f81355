//! The Scenes artifact: per frame, radar images, every actor's state, and each actor's pixel
//! position in the primary image.
//!
//! ```text
//! scenes.mcap   MCAP, unchunked and uncompressed, so that any byte range is readable in place:
//!               /radar/<view>  foxglove.RawImage (protobuf, mono8), one message per frame per
//!                              image; value / 255 is the normalised log power
//!               /actors        the frame's identity, episode and actors, JSON (a Frame),
//!                              one message per frame
//! scenes.index  little-endian u64s, per frame: the /actors message's byte offset and length,
//!               then for each image the byte offset of its pixels, all into scenes.mcap
//! scenes.json   summary: format, frames, images (the first is the primary), radar range, the
//!               generator's settings, dataset statistics
//! ```
//!
//! Stock MCAP readers (the Python `mcap` package, Foxglove) read the file as is; the index gives
//! a training loader random access by frame without parsing it.
//!
//! Actor positions are in the ego frame (x forward, y left, metres; headings relative to the
//! ego's, radians, counter-clockwise).

use std::collections::BTreeMap;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use serde::{Deserialize, Serialize};

pub const SUMMARY: &str = "scenes.json";
pub const MCAP: &str = "scenes.mcap";
pub const INDEX: &str = "scenes.index";
pub const FORMAT: u32 = 3;
pub const ACTORS_TOPIC: &str = "/actors";

/// One actor in one frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Actor {
    pub id: u32,
    /// `car`, `truck`, `walker`, or `sign:<name>` for a traffic sign (`sign:stop`, `sign:speed limit`).
    pub class: String,
    pub x: f64,
    pub y: f64,
    pub heading: f64,
    pub length: f64,
    pub width: f64,
    pub speed: f64,
    /// The heading of the lane it drives in, relative to the ego's lane; absent where the
    /// generator knows no lanes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lane_heading: Option<f64>,
    /// Pixel coordinates of its centre in the primary image (pixel centres at integer + 0.5);
    /// outside [0, size) where the image does not show it.
    pub row: f64,
    pub col: f64,
}

impl Actor {
    pub fn is_vehicle(&self) -> bool {
        self.class == "car" || self.class == "truck"
    }

    /// The sign's name, for a traffic sign.
    pub fn sign(&self) -> Option<&str> {
        self.class.strip_prefix("sign:")
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Frame {
    /// The frame's position in its artifact, from 0.
    pub index: u64,
    /// The frame's identity ([`crate::identity`]): the digest of its content, set where it is
    /// born and kept by every mix, shard and import.
    pub id: String,
    /// The sequence the frame belongs to (a simulated episode, a recording); frames of one
    /// episode share a split. Absent: the frame is its own group.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub episode: Option<String>,
    pub scenario: String,
    pub actors: Vec<Actor>,
    /// The paper's grid JSON, for an imported frame whose recording gives the grid rather than
    /// the actors (`actors` is then empty): the labels stage takes it as it is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grid: Option<serde_json::Value>,
}

impl Frame {
    /// A newly born frame with these images: its identity is the digest of its content.
    pub fn new(index: u64, scenario: String, actors: Vec<Actor>, images: &[Vec<u8>]) -> Frame {
        let id = crate::identity::frame_id(&scenario, &serde_json::to_string(&actors).expect("actors serialise"), images);
        Frame { index, id, episode: None, scenario, actors, grid: None }
    }

    /// A newly born frame labelled by its grid (the paper's JSON) instead of actors.
    pub fn with_grid(index: u64, scenario: String, grid: serde_json::Value, images: &[Vec<u8>]) -> Frame {
        let id = crate::identity::frame_id(&scenario, &format!("grid {grid}"), images);
        Frame { index, id, episode: None, scenario, actors: Vec::new(), grid: Some(grid) }
    }

    /// What the split is decided on: the episode, else the frame itself.
    pub fn group(&self) -> &str {
        self.episode.as_deref().unwrap_or(&self.id)
    }
}

/// One image channel.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Image {
    /// The view, as the radar model names it (`range-azimuth`, `bev`, `radar-front`, ...).
    pub view: String,
    pub topic: String,
    /// Width and height in pixels.
    pub size: usize,
}

/// `scenes.json`: what a reader needs, and the dataset statistics the report shows.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub format: u32,
    pub frames: u64,
    /// The images per frame; actor pixels are in the first.
    pub images: Vec<Image>,
    pub range_max_m: f64,
    /// The generator's settings (operator-specific).
    pub generator: serde_json::Value,
    pub frames_per_scenario: BTreeMap<String, u64>,
    /// Entry n: frames with n vehicles.
    pub vehicles_per_scene: Vec<u64>,
    /// Vehicles per grid cell under the default rule, keyed `bin/sector`.
    pub cells: BTreeMap<String, u64>,
    /// Frames labelled by a grid alone, whose vehicles have no place in the image: there is no
    /// segmentation target for them.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub frames_without_positions: u64,
}

fn is_zero(n: &u64) -> bool {
    *n == 0
}

impl Summary {
    /// Vehicles over all frames.
    pub fn vehicles(&self) -> u64 {
        self.vehicles_per_scene.iter().enumerate().map(|(n, frames)| n as u64 * frames).sum()
    }

    /// Grid cells with at least one vehicle.
    pub fn cells_covered(&self) -> usize {
        self.cells.values().filter(|&&n| n > 0).count()
    }

    /// u64 entries per frame in `scenes.index`.
    pub fn index_stride(&self) -> usize {
        2 + self.images.len()
    }
}

/// Reads a Scenes artifact directory, by frame, in place.
pub struct Scenes {
    dir: PathBuf,
    pub summary: Summary,
    index: Vec<u64>,
    mcap: File,
}

impl Scenes {
    pub fn open(dir: &Path) -> anyhow::Result<Scenes> {
        let summary: Summary = crate::reading::read_summary(dir, SUMMARY, crate::artifact::SCENES, "scenes", FORMAT)?;
        let index_path = dir.join(INDEX);
        let bytes = std::fs::read(&index_path).with_context(|| format!("reading {}", index_path.display()))?;
        let index: Vec<u64> = bytes.chunks_exact(8).map(|b| u64::from_le_bytes(b.try_into().expect("chunks of 8"))).collect();
        if bytes.len() % 8 != 0 || index.len() as u64 != summary.frames * summary.index_stride() as u64 {
            bail!("{}: {} bytes, expected {} frames x {} offsets", index_path.display(), bytes.len(), summary.frames, summary.index_stride());
        }
        let mcap_path = dir.join(MCAP);
        let mcap = File::open(&mcap_path).with_context(|| format!("reading {}", mcap_path.display()))?;
        Ok(Scenes { dir: dir.to_path_buf(), summary, index, mcap })
    }

    pub fn len(&self) -> u64 {
        self.summary.frames
    }

    pub fn is_empty(&self) -> bool {
        self.summary.frames == 0
    }

    fn entry(&self, index: u64, what: usize) -> anyhow::Result<u64> {
        if index >= self.summary.frames {
            bail!("frame {index} is past the end of {} ({} frames)", self.dir.display(), self.summary.frames);
        }
        Ok(self.index[index as usize * self.summary.index_stride() + what])
    }

    fn read_at(&self, offset: u64, len: usize) -> anyhow::Result<Vec<u8>> {
        let mut out = vec![0u8; len];
        self.mcap.read_exact_at(&mut out, offset).with_context(|| format!("reading {} at byte {offset}", self.dir.join(MCAP).display()))?;
        Ok(out)
    }

    /// Frame `index`'s actors.
    pub fn frame(&self, index: u64) -> anyhow::Result<Frame> {
        let (offset, len) = (self.entry(index, 0)?, self.entry(index, 1)?);
        serde_json::from_slice(&self.read_at(offset, len as usize)?)
            .with_context(|| format!("{}: frame {index} at byte {offset} is not a frame", self.dir.join(MCAP).display()))
    }

    pub fn frames(&self) -> anyhow::Result<Vec<Frame>> {
        (0..self.summary.frames).map(|i| self.frame(i)).collect()
    }

    /// Frame `index`'s `image`-th image (size x size bytes, row-major).
    pub fn image(&self, image: usize, index: u64) -> anyhow::Result<Vec<u8>> {
        let Some(info) = self.summary.images.get(image) else {
            bail!("{} has {} images, not {}", self.dir.display(), self.summary.images.len(), image + 1);
        };
        self.read_at(self.entry(index, 2 + image)?, info.size * info.size)
    }

    /// Frame `index`'s primary image.
    pub fn heatmap(&self, index: u64) -> anyhow::Result<Vec<u8>> {
        self.image(0, index)
    }
}
