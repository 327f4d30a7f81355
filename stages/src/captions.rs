//! The Captions artifact: several captions per labelled frame.
//!
//! ```text
//! captions.json   summary: format, frames, captions, the generator's settings and statistics
//! captions.jsonl  one line per caption, grouped by frame in frame order:
//!                 {"frame": 0, "id": "<the frame's identity>", "split": "train", "caption": "..."}
//! ```
//!
//! The lines are what `rlmflow parse` reads, so a Captions artifact can be checked against its
//! labels from the command line.

use std::path::Path;

use anyhow::bail;
use serde::{Deserialize, Serialize};

use crate::identity::Split;

pub const SUMMARY: &str = "captions.json";
pub const LINES: &str = "captions.jsonl";
pub const FORMAT: u32 = 2;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub format: u32,
    pub frames: u64,
    pub captions: u64,
    /// The operator's settings and statistics (operator-specific).
    pub generator: serde_json::Value,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Caption {
    pub frame: u64,
    /// The frame's identity (see `crate::identity`).
    pub id: String,
    pub split: Split,
    pub caption: String,
}

impl Caption {
    pub fn to_line(&self) -> String {
        serde_json::to_string(self).expect("captions serialise")
    }
}

/// A Captions artifact, read.
pub struct Captions {
    pub summary: Summary,
    pub captions: Vec<Caption>,
}

impl Captions {
    pub fn open(dir: &Path) -> anyhow::Result<Captions> {
        let summary: Summary = crate::reading::read_summary(dir, SUMMARY, crate::artifact::CAPTIONS, "captions", FORMAT)?;
        let path = dir.join(LINES);
        let captions: Vec<Caption> = crate::reading::read_lines(&path, |l| serde_json::from_str(l).map_err(|e| format!("not a caption line: {e}")))?;
        if captions.len() as u64 != summary.captions {
            bail!("{}: {} captions, but the summary says {}", path.display(), captions.len(), summary.captions);
        }
        Ok(Captions { summary, captions })
    }
}
