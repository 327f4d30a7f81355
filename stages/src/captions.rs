//! The Captions artifact: several captions per labelled frame.
//!
//! ```text
//! captions.json   summary: format, frames, captions, the generator's settings and statistics
//! captions.jsonl  one line per caption, grouped by frame in frame order:
//!                 {"frame": 0, "split": "train", "caption": "..."}
//! ```
//!
//! The lines are what `rlmflow parse` reads, so a Captions artifact can be checked against its
//! labels from the command line.

use std::fs;
use std::path::Path;

use anyhow::{Context as _, bail};
use serde::{Deserialize, Serialize};

use crate::labels::Split;

pub const SUMMARY: &str = "captions.json";
pub const LINES: &str = "captions.jsonl";
pub const FORMAT: u32 = 1;

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
        let path = dir.join(SUMMARY);
        let summary: Summary = serde_json::from_slice(&fs::read(&path).with_context(|| format!("reading {}", path.display()))?)
            .with_context(|| format!("{} is not a Captions summary", path.display()))?;
        if summary.format != FORMAT {
            bail!("{}: Captions format {} (this build reads {FORMAT}); rerun the captions stage", path.display(), summary.format);
        }
        let path = dir.join(LINES);
        let text = fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
        let captions = text
            .lines()
            .enumerate()
            .map(|(i, l)| serde_json::from_str(l).with_context(|| format!("{}:{}: not a caption line", path.display(), i + 1)))
            .collect::<anyhow::Result<Vec<Caption>>>()?;
        if captions.len() as u64 != summary.captions {
            bail!("{}: {} captions, but the summary says {}", path.display(), captions.len(), summary.captions);
        }
        Ok(Captions { summary, captions })
    }
}
