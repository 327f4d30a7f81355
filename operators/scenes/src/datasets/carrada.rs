//! CARRADA (Valeo; carrada_dataset): a 77 GHz FMCW radar's range-angle maps with per-frame
//! annotations.
//!
//! ```text
//! <root>/<seq>/range_angle_numpy/000000.npy   256 x 256 float32: rows range, columns angle
//! <root>/annotations_frame_oriented.json
//!     {"<seq>": {"000000": {"<instance>": {"range_angle": {"box": [[r0, a0], [r1, a1]], "label": 3, ...}, ...}}}}
//! ```
//!
//! Geometry as the devkit's `AnnotationTransformer.to_ra` places annotations in the matrix: row
//! `256 - floor(range / 0.1953125)` (far rows first, 50 m at row 0), column `128 + trunc(angle /
//! (pi / 256))` (evenly in angle over -90..90 degrees; column 128 spans both sides of straight
//! ahead), the angle `atan(x / y)` with `x` lateral, read as positive to the right. A box's centre
//! is the object's position. Labels: 1 pedestrian, 2 cyclist, 3 car.

use std::collections::BTreeMap;
use std::f64::consts::PI;
use std::path::Path;

use anyhow::{Context as _, bail};
use rlmflow_stages::npy::{Dtype, Npy};
use serde::Deserialize;

use super::UnknownClasses;
use super::{Classes, FrameReader, Object, Opened, Recorded, Sequence, sequences};
use crate::geometry::{Bins, RangeAzimuthMap};
use crate::raw::{Power, Raw, normalise};

pub const SIZE: usize = 256;
pub const RANGE_RES: f64 = 0.1953125;
pub const ANGLE_RES: f64 = PI / 256.0;

pub const CLASSES: Classes = Classes(&[("pedestrian", "walker"), ("cyclist", "walker"), ("car", "car")]);

/// The dataset's label numbers, by class name.
const LABELS: [&str; 4] = ["background", "pedestrian", "cyclist", "car"];

/// Row `i`'s range centre in metres.
fn range_of_row(i: f64) -> f64 {
    (SIZE as f64 - i + 0.5) * RANGE_RES
}

/// Column `j`'s angle centre in radians, positive to the right (column 128 spans both sides).
fn angle_of_column(j: usize) -> f64 {
    let k = j as f64 - 128.0;
    if k == 0.0 { 0.0 } else { (k + 0.5 * k.signum()) * ANGLE_RES }
}

/// Where a map's rows and columns lie (see the module doc).
pub fn bins() -> (Bins, Bins) {
    // Counter-clockwise: column 0 is the left.
    (Bins::Centres((0..SIZE).map(|i| range_of_row(i as f64)).collect()), Bins::Centres((0..SIZE).map(|j| -angle_of_column(j)).collect()))
}

#[derive(Deserialize)]
struct Annotated {
    range_angle: Option<View>,
}

#[derive(Deserialize)]
struct View {
    #[serde(rename = "box")]
    corners: [[f64; 2]; 2],
    label: i64,
}

/// Opens the CARRADA copy at `root` (named `shown` in messages): the annotations are read and
/// every sequence's maps listed now, each map when its frame is, its values read as `power` says
/// (dB shown over `dynamic_range_db` below each map's peak).
pub fn open(root: &Path, shown: &Path, wanted: &[String], unknown: UnknownClasses, power: Power, dynamic_range_db: f64) -> anyhow::Result<Opened> {
    let file = shown.join("annotations_frame_oriented.json");
    let bytes = std::fs::read(root.join("annotations_frame_oriented.json"))
        .with_context(|| format!("{}: missing; CARRADA's annotations are read from it", file.display()))?;
    let all: BTreeMap<String, BTreeMap<String, BTreeMap<String, Annotated>>> = serde_json::from_slice(&bytes).map_err(|e| {
        anyhow::anyhow!(
            "{}:{}: {e}; valid: {{\"<seq>\": {{\"000000\": {{\"<instance>\": {{\"range_angle\": {{\"box\": [[r0, a0], [r1, a1]], \"label\": 3}}}}}}}}}}",
            file.display(),
            e.line()
        )
    })?;
    let mut skipped = BTreeMap::new();
    let mut frames: Vec<FrameReader> = Vec::new();
    for seq in sequences(root, shown, "range_angle_numpy", wanted)? {
        let name = &seq.name;
        let mut numbers: Vec<String> = std::fs::read_dir(seq.dir.join("range_angle_numpy"))?
            .flatten()
            .filter_map(|e| e.file_name().to_str()?.strip_suffix(".npy").map(str::to_owned))
            .collect();
        numbers.sort();
        let annotated =
            all.get(name).with_context(|| format!("{}: no sequence `{name}`, whose maps are in {}", file.display(), seq.shown.display()))?;
        if let Some(extra) = annotated.keys().find(|f| numbers.binary_search(f).is_err()) {
            bail!(
                "{}: sequence `{name}` annotates frame {extra}, but {} has no {extra}.npy",
                file.display(),
                seq.shown.join("range_angle_numpy").display()
            );
        }
        for frame in numbers {
            let mut objects = Vec::new();
            for (instance, a) in annotated.get(&frame).into_iter().flatten() {
                let Some(view) = &a.range_angle else { continue };
                let at = || format!("{}: sequence `{name}`, frame {frame}, instance {instance}", file.display());
                let theirs = usize::try_from(view.label)
                    .ok()
                    .and_then(|l| LABELS.get(l))
                    .filter(|&&l| l != "background")
                    .map_or_else(|| format!("label {}", view.label), |l| l.to_string());
                let Some(class) = CLASSES.map(&theirs, unknown, &mut skipped).map_err(|e| anyhow::anyhow!("{}: {e}", at()))? else { continue };
                let [[r0, a0], [r1, a1]] = view.corners;
                if ![r0, a0, r1, a1].iter().all(|v| (0.0..SIZE as f64).contains(v)) {
                    bail!("{}: box {:?} leaves the 256 x 256 map", at(), view.corners);
                }
                let (range, col) = (range_of_row((r0 + r1) / 2.0), (a0 + a1) / 2.0);
                let (lo, hi) = (angle_of_column(col.floor() as usize), angle_of_column((col.floor() as usize + 1).min(SIZE - 1)));
                let angle = lo + (hi - lo) * col.fract();
                let (length, width) = if class == "car" { (4.5, 1.8) } else { (0.6, 0.6) };
                objects.push(Object { class, x: range * angle.cos(), y: -range * angle.sin(), heading: 0.0, length, width });
            }
            let Sequence { name, dir, shown } = seq.clone();
            frames.push(Box::new(move || {
                Ok(Recorded {
                    map: range_angle_map(&dir, &shown, &frame, power, dynamic_range_db)?,
                    objects,
                    episode: name,
                    scenario: "carrada".into(),
                })
            }));
        }
    }
    Ok(Opened { frames, skipped, warnings: Vec::new() })
}

/// Frame `frame`'s range-angle map in the sequence at `dir` (`shown` in messages), its values
/// read as `power` says (dB shown over `dynamic_range_db` below the peak).
fn range_angle_map(dir: &Path, shown: &Path, frame: &str, power: Power, dynamic_range_db: f64) -> anyhow::Result<RangeAzimuthMap> {
    let name = format!("range_angle_numpy/{frame}.npy");
    let shown = shown.join(&name);
    let npy = Npy::open_as(&dir.join(&name), &shown)?;
    if npy.shape != [SIZE, SIZE] || npy.dtype != Dtype::F32 {
        bail!("{}: {:?} {:?}; a CARRADA range-angle map is [256, 256] float32", shown.display(), npy.shape, npy.dtype);
    }
    let values = npy.all_f32()?;
    if let Some(p) = values.iter().position(|v| !v.is_finite()) {
        bail!("{}: {} at row {}, column {}; every value must be a finite number", shown.display(), values[p], p / SIZE, p % SIZE);
    }
    let raw = Raw { height: SIZE, width: SIZE, values, integer_max: None };
    let (range, azimuth) = bins();
    Ok(RangeAzimuthMap {
        values: normalise(&raw, power, dynamic_range_db).with_context(|| format!("{}", shown.display()))?,
        rows: SIZE,
        cols: SIZE,
        range,
        azimuth,
        wraps: false,
    })
}
