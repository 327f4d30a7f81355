//! RADIATE (Heriot-Watt; radiate_sdk): a Navtech CTS350-X scanning radar, 360 degrees.
//!
//! ```text
//! <root>/<sequence>/Navtech_Polar/000001.png   400 azimuths x 576 range bins, uint8 (dB, quantised)
//! <root>/<sequence>/Navtech_Polar.txt          "Frame: 000001 Time: 1574859771.744660272" per frame
//! <root>/<sequence>/annotations/annotations.json
//!     [{"id": 1, "class_name": "car", "bboxes": [{"position": [x, y, w, h], "rotation": deg}, {}, ...]}]
//! <root>/<sequence>/meta.json                  {"type": "fog", ...} (optional: the scenario)
//! ```
//!
//! Geometry, as radiate_sdk has it: azimuth row `a` at `a` x 0.9 degrees (400 over the turn),
//! clockwise from straight ahead seen from above (the scan's direction); range column `r` at `r` x
//! 0.173611 m. A box is in the 1152 x 1152 Cartesian image's pixels (0.173611 m each, the radar at
//! pixel 576, ahead up), its `rotation` counter-clockwise in degrees, and `bboxes[k]` is radar
//! frame `k + 1`'s (`{}`: not in that frame).

use std::collections::BTreeMap;
use std::f64::consts::PI;
use std::path::Path;

use anyhow::{Context as _, bail};
use serde::Deserialize;

use super::{Classes, FrameReader, Object, Opened, Recorded, Sequence, sequences};
use crate::geometry::{Bins, RangeAzimuthMap};
use crate::import::{UnknownClasses, read_image};

/// Metres per range bin and per Cartesian pixel (radiate_sdk's `radar_calib.range_res`).
pub const RANGE_RES: f64 = 0.173611;
pub const AZIMUTHS: usize = 400;
pub const RANGE_BINS: usize = 576;
/// The Cartesian image's half side in pixels: the radar's pixel.
pub const CENTRE: f64 = 576.0;

pub const CLASSES: Classes = Classes(&[
    ("car", "car"),
    ("van", "car"),
    ("vehicle", "car"),
    ("motorbike", "car"),
    ("bus", "truck"),
    ("truck", "truck"),
    ("pedestrian", "walker"),
    ("group_of_pedestrians", "walker"),
    ("bicycle", "walker"),
]);

#[derive(Deserialize)]
struct Annotated {
    id: serde_json::Value,
    class_name: String,
    bboxes: Vec<serde_json::Value>,
}

#[derive(Deserialize)]
struct BoundingBox {
    position: [f64; 4],
    #[serde(default)]
    rotation: f64,
}

/// Opens the RADIATE copy at `root` (named `shown` in messages): every sequence's timestamps and
/// annotations are read now, each polar scan when its frame is.
pub fn open(root: &Path, shown: &Path, wanted: &[String], unknown: UnknownClasses) -> anyhow::Result<Opened> {
    let mut skipped = BTreeMap::new();
    let mut frames: Vec<FrameReader> = Vec::new();
    for seq in sequences(root, shown, "Navtech_Polar.txt", wanted)? {
        let (scenario, annotated) = read_sequence(&seq, unknown, &mut skipped)?;
        for (number, objects) in annotated {
            let (Sequence { name, dir, shown }, scenario) = (seq.clone(), scenario.clone());
            frames.push(Box::new(move || Ok(Recorded { map: polar_scan(&dir, &shown, number)?, objects, episode: name, scenario })));
        }
    }
    Ok(Opened { frames, skipped })
}

/// Each radar frame of a sequence in order: its number and its objects.
type Frames = Vec<(u64, Vec<Object>)>;

/// A sequence's scenario and its annotated frames.
fn read_sequence(seq: &Sequence, unknown: UnknownClasses, skipped: &mut BTreeMap<String, usize>) -> anyhow::Result<(String, Frames)> {
    let (dir, shown) = (&seq.dir, &seq.shown);
    let stamps = shown.join("Navtech_Polar.txt");
    let text = std::fs::read_to_string(dir.join("Navtech_Polar.txt")).with_context(|| format!("reading {}", stamps.display()))?;
    let mut frames = Vec::new();
    for (n, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let words: Vec<&str> = line.split_whitespace().collect();
        let parsed = match words[..] {
            ["Frame:", frame, "Time:", time] => frame.parse::<u64>().ok().zip(time.parse::<f64>().ok().filter(|t| t.is_finite())),
            _ => None,
        };
        let Some((frame, time)) = parsed else {
            bail!("{}:{}: `{line}`; a line is `Frame: 000001 Time: 1574859771.744660272`", stamps.display(), n + 1);
        };
        if let Some(&(before, then)) = frames.last().filter(|&&(before, then)| frame <= before || time < then) {
            bail!(
                "{}:{}: frame {frame} at {time} s does not follow frame {before} at {then} s; frames and times must increase",
                stamps.display(),
                n + 1
            );
        }
        frames.push((frame, time));
    }
    if frames.is_empty() {
        bail!("{}: no frames", stamps.display());
    }
    let frames: Vec<u64> = frames.into_iter().map(|(frame, _)| frame).collect();
    let annotations = shown.join("annotations/annotations.json");
    let bytes = std::fs::read(dir.join("annotations/annotations.json"))
        .with_context(|| format!("{}: missing; every RADIATE sequence has its annotations there", annotations.display()))?;
    let annotated: Vec<Annotated> = serde_json::from_slice(&bytes).map_err(|e| {
        anyhow::anyhow!(
            "{}:{}: {e}; valid: [{{\"id\": 1, \"class_name\": \"car\", \"bboxes\": [{{\"position\": [x, y, w, h], \"rotation\": 0.0}}, {{}}]}}]",
            annotations.display(),
            e.line()
        )
    })?;
    // Frame numbers start at 1 and bboxes[k] is frame k + 1's.
    let index: BTreeMap<u64, usize> = frames.iter().enumerate().map(|(k, &frame)| (frame, k)).collect();
    let mut objects: Vec<Vec<Object>> = (0..frames.len()).map(|_| Vec::new()).collect();
    for object in &annotated {
        let class =
            CLASSES.map(&object.class_name, unknown, skipped).map_err(|e| anyhow::anyhow!("{}: object {}: {e}", annotations.display(), object.id))?;
        for (k, bbox) in object.bboxes.iter().enumerate() {
            if bbox.as_object().is_some_and(|o| o.is_empty()) || bbox.is_null() {
                continue;
            }
            let frame = k as u64 + 1;
            let Some(&at) = index.get(&frame) else {
                bail!(
                    "{}: object {} has a box for frame {frame}, but {} lists no such radar frame (it has {} frames)",
                    annotations.display(),
                    object.id,
                    stamps.display(),
                    frames.len()
                );
            };
            let b: BoundingBox = serde_json::from_value(bbox.clone()).map_err(|e| {
                anyhow::anyhow!(
                    "{}: object {}, frame {frame}: {e}; a box is {{\"position\": [x, y, w, h], \"rotation\": degrees}}",
                    annotations.display(),
                    object.id
                )
            })?;
            if let Some(class) = class {
                objects[at].push(object_of(class, &b));
            }
        }
    }
    let scenario = std::fs::read(dir.join("meta.json"))
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .and_then(|m| m["type"].as_str().map(|t| format!("radiate-{t}")))
        .unwrap_or_else(|| "radiate".into());
    Ok((scenario, frames.into_iter().zip(objects).collect()))
}

/// A box of the Cartesian image in the ego frame: its centre, its long side as length along
/// its heading.
fn object_of(class: &'static str, b: &BoundingBox) -> Object {
    let [x, y, w, h] = b.position;
    let (col, row) = (x + w / 2.0, y + h / 2.0);
    // Ahead is up the image, the ego's left is the image's left.
    let (ahead, left) = ((CENTRE - row) * RANGE_RES, (CENTRE - col) * RANGE_RES);
    let turn = b.rotation.to_radians();
    let (length, width, heading) = if h >= w { (h, w, turn) } else { (w, h, turn + PI / 2.0) };
    Object { class, x: ahead, y: left, heading: (heading + PI).rem_euclid(2.0 * PI) - PI, length: length * RANGE_RES, width: width * RANGE_RES }
}

/// Frame `number`'s polar scan in the sequence at `dir` (`shown` in messages), as a map of range
/// rows and azimuth columns.
fn polar_scan(dir: &Path, shown: &Path, number: u64) -> anyhow::Result<RangeAzimuthMap> {
    let name = format!("Navtech_Polar/{number:06}.png");
    let raw = read_image(dir, shown, &name).with_context(|| format!("{}", shown.join(&name).display()))?;
    if (raw.height, raw.width) != (AZIMUTHS, RANGE_BINS) {
        bail!(
            "{}: {} x {} pixels; a Navtech polar scan is {AZIMUTHS} azimuths x {RANGE_BINS} range bins",
            shown.join(&name).display(),
            raw.height,
            raw.width
        );
    }
    let max = raw.integer_max.unwrap_or(255.0);
    // Rows become range, columns azimuth.
    let values = (0..RANGE_BINS * AZIMUTHS).map(|p| raw.values[(p % AZIMUTHS) * RANGE_BINS + p / AZIMUTHS] / max).collect();
    let half = PI / AZIMUTHS as f64;
    Ok(RangeAzimuthMap {
        values,
        rows: RANGE_BINS,
        cols: AZIMUTHS,
        range: Bins::Even { from: -RANGE_RES / 2.0, to: (RANGE_BINS as f64 - 0.5) * RANGE_RES },
        // Clockwise from ahead: counter-clockwise angles decrease along the columns.
        azimuth: Bins::Even { from: half, to: half - 2.0 * PI },
        wraps: true,
    })
}
