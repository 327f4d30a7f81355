//! CRUW's ROD2021 release (cruw-devkit): a TI AWR1843 FMCW radar's range-azimuth maps, as released or as the devkit's `reorganize_rod2021.sh` leaves them.
//!
//! ```text
//! <root>/TRAIN_RAD_H/<seq>/RADAR_RA_H/000000_0000.npy   128 x 128 x 2 float32 (real, imaginary); chirp 0000 read
//! <root>/TRAIN_RAD_H_ANNO/<seq>.txt                     "frame range_m azimuth_rad class" per object
//!   or  <root>/sequences/train/<seq>/RADAR_RA_H/...  and  <root>/annotations/train/<seq>.txt
//! ```
//!
//! Geometry from `sensor_config_rod2021.json` as the devkit's `confmap2ra` computes it: row `k`
//! at range `(k + 3) * fs / 134 * c / (2 * slope)` (fs 4 MHz, slope 21.0017 MHz/us, 3 of 134 FFT
//! bins cropped each end), column `j` at azimuth `asin(-1 + 2j / 127)`: bins even in sine, not in
//! degrees, from -90 degrees (column 0) to 90. Azimuth is positive to the right (the devkit's
//! `pol2cart_ramap`: lateral `x = r sin a`, ahead `y = r cos a`).

use std::collections::BTreeMap;
use std::f64::consts::PI;
use std::path::Path;

use anyhow::{Context as _, bail};
use rlmflow_stages::npy::{Dtype, Npy};

use super::UnknownClasses;
use super::{Classes, FrameReader, Object, Opened, Recorded, Sequence, sequences};
use crate::geometry::{Bins, RangeAzimuthMap};
use crate::raw::{Power, Raw, normalise};

pub const SIZE: usize = 128;
const SAMPLE_RATE: f64 = 4e6;
const SWEEP_SLOPE: f64 = 21.0017e12;
const CROP: usize = 3;
const SPEED_OF_LIGHT: f64 = 299_792_458.0;

pub const CLASSES: Classes = Classes(&[("car", "car"), ("pedestrian", "walker"), ("cyclist", "walker")]);

/// Row `k`'s range in metres.
pub fn range_of_row(k: usize) -> f64 {
    let bins = (SIZE + 2 * CROP) as f64;
    (k + CROP) as f64 * SAMPLE_RATE / bins * SPEED_OF_LIGHT / SWEEP_SLOPE / 2.0
}

/// Where a map's rows and columns lie (see the module doc).
pub fn bins() -> (Bins, Bins) {
    // Column 0 is -90 degrees, to the right: +90 counter-clockwise.
    (Bins::Centres((0..SIZE).map(range_of_row).collect()), Bins::Sine { first: PI / 2.0, last: -PI / 2.0 })
}

/// Length and width the labels draw an object of `class` with (CRUW annotates centres only).
fn size_of(class: &str) -> (f64, f64) {
    match class {
        "car" => (4.5, 1.8),
        _ => (0.6, 0.6),
    }
}

/// Opens the ROD2021 copy at `root` (named `shown` in messages): every sequence's maps are listed
/// and its annotations read now, each map when its frame is. `dynamic_range_db`: the span below
/// each map's peak shown.
pub fn open(root: &Path, shown: &Path, wanted: &[String], unknown: UnknownClasses, dynamic_range_db: f64) -> anyhow::Result<Opened> {
    let layouts = [("TRAIN_RAD_H", "TRAIN_RAD_H_ANNO"), ("sequences/train", "annotations/train")];
    let Some((radar, annotations)) = layouts.into_iter().find(|(radar, _)| root.join(radar).is_dir()) else {
        bail!(
            "{}: neither TRAIN_RAD_H/ (as released) nor sequences/train/ (as reorganize_rod2021.sh leaves it); point `path` at the ROD2021 root",
            shown.display()
        );
    };
    let mut skipped = BTreeMap::new();
    let mut frames: Vec<FrameReader> = Vec::new();
    for seq in sequences(&root.join(radar), &shown.join(radar), "RADAR_RA_H", wanted)? {
        let file = format!("{}.txt", seq.name);
        let annotated = read_sequence(&seq, &root.join(annotations).join(&file), &shown.join(annotations).join(&file), unknown, &mut skipped)?;
        for (number, objects) in annotated {
            let Sequence { name, dir, shown } = seq.clone();
            frames.push(Box::new(move || {
                Ok(Recorded { map: complex_map(&dir, &shown, number, dynamic_range_db)?, objects, episode: name, scenario: "cruw".into() })
            }));
        }
    }
    Ok(Opened { frames, skipped, warnings: Vec::new() })
}

/// A sequence's frames with a chirp-0 map, in order, each with its objects from the annotation
/// file `anno` (`anno_shown` in messages).
fn read_sequence(
    seq: &Sequence,
    anno: &Path,
    anno_shown: &Path,
    unknown: UnknownClasses,
    skipped: &mut BTreeMap<String, usize>,
) -> anyhow::Result<Vec<(u64, Vec<Object>)>> {
    let (dir, shown) = (&seq.dir, &seq.shown);
    let mut numbers: Vec<u64> = std::fs::read_dir(dir.join("RADAR_RA_H"))?
        .flatten()
        .filter_map(|e| e.file_name().to_str()?.strip_suffix("_0000.npy")?.parse().ok())
        .collect();
    numbers.sort_unstable();
    if numbers.is_empty() {
        bail!("{}: no chirp-0 maps (`000000_0000.npy`, ...)", shown.join("RADAR_RA_H").display());
    }
    let text =
        std::fs::read_to_string(anno).with_context(|| format!("{}: missing; every ROD2021 training sequence has one", anno_shown.display()))?;
    let index: BTreeMap<u64, usize> = numbers.iter().enumerate().map(|(k, &n)| (n, k)).collect();
    let mut frames: Vec<(u64, Vec<Object>)> = numbers.iter().map(|&n| (n, Vec::new())).collect();
    for (n, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let at = format!("{}:{}", anno_shown.display(), n + 1);
        let words: Vec<&str> = line.split_whitespace().collect();
        let parsed = match words[..] {
            [frame, range, azimuth, class] => {
                frame.parse::<u64>().ok().zip(range.parse::<f64>().ok()).zip(azimuth.parse::<f64>().ok()).map(|((f, r), a)| (f, r, a, class))
            }
            _ => None,
        };
        let Some((frame, range, azimuth, class)) = parsed.filter(|(_, r, a, _)| r.is_finite() && a.is_finite() && *r >= 0.0) else {
            bail!("{at}: `{line}`; a line is `frame range_m azimuth_rad class`, e.g. `12 7.3 -0.21 car`");
        };
        let Some(&k) = index.get(&frame) else {
            bail!(
                "{at}: frame {frame} has no map ({} holds frames {}..={})",
                shown.join("RADAR_RA_H").display(),
                numbers[0],
                numbers[numbers.len() - 1]
            );
        };
        let Some(ours) = CLASSES.map(class, unknown, skipped).map_err(|e| anyhow::anyhow!("{at}: {e}"))? else { continue };
        let (length, width) = size_of(ours);
        frames[k].1.push(Object { class: ours, x: range * azimuth.cos(), y: -range * azimuth.sin(), heading: 0.0, length, width });
    }
    Ok(frames)
}

/// Frame `number`'s chirp-0 map in the sequence at `dir` (`shown` in messages), as received
/// power over `dynamic_range_db`.
fn complex_map(dir: &Path, shown: &Path, number: u64, dynamic_range_db: f64) -> anyhow::Result<RangeAzimuthMap> {
    let name = format!("RADAR_RA_H/{number:06}_0000.npy");
    let shown = shown.join(&name);
    let npy = Npy::open_as(&dir.join(&name), &shown)?;
    if npy.shape != [SIZE, SIZE, 2] || npy.dtype != Dtype::F32 {
        bail!("{}: {:?} {:?}; a ROD2021 map is [128, 128, 2] float32 (real, imaginary)", shown.display(), npy.shape, npy.dtype);
    }
    let complex = npy.all_f32()?;
    if let Some(p) = complex.iter().position(|v| !v.is_finite()) {
        bail!("{}: {} at element {p}; every value must be a finite number", shown.display(), complex[p]);
    }
    let power = complex.chunks_exact(2).map(|c| c[0] * c[0] + c[1] * c[1]).collect();
    let raw = Raw { height: SIZE, width: SIZE, values: power, integer_max: None };
    let (range, azimuth) = bins();
    Ok(RangeAzimuthMap { values: normalise(&raw, Power::Linear, dynamic_range_db)?, rows: SIZE, cols: SIZE, range, azimuth, wraps: false })
}
