//! Published radar datasets read in their own on-disk layout, as their devkits read them:
//! sequences become episodes, annotations their objects in the ego frame (x ahead, y left,
//! metres), and each frame's map comes with the sensor geometry that places its bins.
//!
//! A reader indexes the dataset when opened (every sequence, timestamp and annotation file, so a
//! bad one is named before anything is written) and hands back a reader per frame, which reads
//! that frame's map when called.

pub mod carrada;
pub mod cruw;
#[cfg(test)]
mod devkit_grids;
pub mod radiate;
#[cfg(test)]
mod radiate_sample;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::bail;

use crate::geometry::RangeAzimuthMap;
use serde::{Deserialize, Serialize};

/// What an annotated object of a class the dataset's table does not map does: stop the import
/// with an error naming it, or be counted and skipped.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum UnknownClasses {
    Error,
    Skip,
}

/// One frame of a dataset.
pub struct Recorded {
    pub map: RangeAzimuthMap,
    pub objects: Vec<Object>,
    pub episode: String,
    pub scenario: String,
}

/// An annotated object in the ego frame, of an rlmflow class.
#[derive(Clone, Copy, Debug)]
pub struct Object {
    pub class: &'static str,
    pub x: f64,
    pub y: f64,
    /// Radians counter-clockwise from straight ahead (0 where the dataset gives none).
    pub heading: f64,
    pub length: f64,
    pub width: f64,
}

/// A dataset opened for reading: a reader for each frame, in sequence order, the objects of
/// classes with no rlmflow class skipped meanwhile (`unknown_classes = "skip"`), by class, and
/// what was read but left out as the devkit leaves it out, each a sentence for the user.
pub struct Opened {
    pub frames: Vec<FrameReader>,
    pub skipped: BTreeMap<String, usize>,
    pub warnings: Vec<String>,
}

/// Reads one frame's map; its objects were read when the dataset was opened.
pub type FrameReader = Box<dyn FnOnce() -> anyhow::Result<Recorded>>;

/// A dataset's class table: its class names and the rlmflow class each becomes.
pub struct Classes(pub &'static [(&'static str, &'static str)]);

impl Classes {
    /// The rlmflow class of `name`; `Ok(None)` for an unknown one to skip (counted in
    /// `skipped`), an error naming it and the known ones otherwise.
    pub fn map(&self, name: &str, unknown: UnknownClasses, skipped: &mut BTreeMap<String, usize>) -> Result<Option<&'static str>, String> {
        if let Some((_, ours)) = self.0.iter().find(|(theirs, _)| *theirs == name) {
            return Ok(Some(ours));
        }
        if unknown == UnknownClasses::Skip {
            *skipped.entry(name.to_owned()).or_default() += 1;
            return Ok(None);
        }
        let known: Vec<&str> = self.0.iter().map(|(theirs, _)| *theirs).collect();
        Err(format!("unknown class `{name}`; known: {} (or set unknown_classes = \"skip\" to count and skip it)", known.join(", ")))
    }
}

/// One sequence folder: its name (the episode), where its snapshot is, and the user's path for it
/// in messages.
#[derive(Clone)]
pub struct Sequence {
    pub name: String,
    pub dir: PathBuf,
    pub shown: PathBuf,
}

/// The sequence folders under `root` holding `marker` (or `root` itself when it does), by name,
/// narrowed to `wanted` when it names any; a wanted one that is missing is an error listing those
/// found. `shown` is `root` as the user names it.
pub fn sequences(root: &Path, shown: &Path, marker: &str, wanted: &[String]) -> anyhow::Result<Vec<Sequence>> {
    if root.join(marker).exists() {
        let name = shown.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "sequence".into());
        return Ok(vec![Sequence { name, dir: root.to_path_buf(), shown: shown.to_path_buf() }]);
    }
    let mut found: Vec<Sequence> = std::fs::read_dir(root)?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.join(marker).exists())
        .map(|dir| {
            let name = dir.file_name().unwrap_or_default().to_string_lossy().into_owned();
            Sequence { shown: shown.join(&name), name, dir }
        })
        .collect();
    found.sort_by(|a, b| a.name.cmp(&b.name));
    if found.is_empty() {
        bail!("{}: no sequence (a folder holding {marker}) here or in its folders", shown.display());
    }
    if wanted.is_empty() {
        return Ok(found);
    }
    let names: Vec<&str> = found.iter().map(|s| s.name.as_str()).collect();
    if let Some(missing) = wanted.iter().find(|w| !names.contains(&w.as_str())) {
        bail!("{}: no sequence `{missing}` (a folder holding {marker}); found: {}", shown.display(), names.join(", "));
    }
    Ok(found.into_iter().filter(|s| wanted.contains(&s.name)).collect())
}
