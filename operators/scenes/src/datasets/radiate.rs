//! RADIATE (Heriot-Watt; radiate_sdk): a Navtech CTS350-X scanning radar, 360 degrees. Read as
//! the SDK's code (`radiate.py`) reads the published files, not as its prose describes them.
//!
//! ```text
//! <root>/<sequence>/Navtech_Polar/000001.png   400 wide (azimuths) x 576 high (range bins), uint8
//! <root>/<sequence>/Navtech_Polar.txt          "Frame: 000001 Time: 1574859771.744660272" per frame
//! <root>/<sequence>/annotations/annotations.json
//!     [{"id": 1, "class_name": "car", "bboxes": [{"position": [x, y, w, h], "rotation": deg}, [], ...]}]
//! <root>/<sequence>/meta.json                  {"type": "fog", ...} (optional: the scenario)
//! ```
//!
//! Geometry, as the published Cartesian images have it (`Navtech_Cartesian/`, checked against
//! them by the tests): row `r` of a polar scan is range `r` x 0.173611 m; column `a` covers
//! azimuths `a` x 0.9 to `(a + 1)` x 0.9 degrees clockwise from straight ahead seen from above. A
//! box is in the 1152 x 1152 Cartesian image's pixels (0.173611 m each, the radar at the corner
//! shared by pixels 575 and 576, ahead up), its `rotation` counter-clockwise in degrees.
//! `bboxes[k]` is the box in radar frame `k + 1` (the SDK's `get_annotation_from_id(id - 1)`);
//! an entry Python finds false (`[]` as published, `{}`, `null`) is no box, and boxes for frames
//! the sequence does not list (annotations run past the last radar frame) are never read, as in
//! the SDK: they are counted and named in one warning.

use std::collections::BTreeMap;
use std::f64::consts::PI;
use std::path::Path;

use anyhow::{Context as _, bail};
use serde::Deserialize;

use super::UnknownClasses;
use super::{Classes, FrameReader, Object, Opened, Recorded, Sequence, sequences};
use crate::geometry::{Bins, RangeAzimuthMap};
use crate::raw::read_image;

/// Metres per range bin and per Cartesian pixel (radiate_sdk's `radar_calib.range_res`).
pub const RANGE_RES: f64 = 0.173611;
/// A polar scan's columns (azimuths) and rows (range bins), as published.
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
    let mut unread = Vec::new();
    for seq in sequences(root, shown, "Navtech_Polar.txt", wanted)? {
        let (scenario, annotated, beyond) = read_sequence(&seq, unknown, &mut skipped)?;
        if beyond > 0 {
            unread.push(format!("{} ({beyond})", seq.name));
        }
        for (number, objects) in annotated {
            let (Sequence { name, dir, shown }, scenario) = (seq.clone(), scenario.clone());
            frames.push(Box::new(move || Ok(Recorded { map: polar_scan(&dir, &shown, number)?, objects, episode: name, scenario })));
        }
    }
    let mut warnings = Vec::new();
    if !unread.is_empty() {
        warnings.push(format!("boxes for frames past the last radar frame ignored, as radiate_sdk never reads them: {}", unread.join(", ")));
    }
    Ok(Opened { frames, skipped, warnings })
}

/// Each radar frame of a sequence in order: its number and its objects.
type Frames = Vec<(u64, Vec<Object>)>;

/// A sequence's scenario, its annotated frames and how many boxes it holds for frames it does
/// not list.
fn read_sequence(seq: &Sequence, unknown: UnknownClasses, skipped: &mut BTreeMap<String, usize>) -> anyhow::Result<(String, Frames, usize)> {
    let (dir, shown) = (&seq.dir, &seq.shown);
    let stamps = shown.join("Navtech_Polar.txt");
    let text = std::fs::read_to_string(dir.join("Navtech_Polar.txt")).with_context(|| format!("reading {}", stamps.display()))?;
    let mut frames = Vec::new();
    for (n, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let words: Vec<&str> = line.split_whitespace().collect();
        let parsed = match words[..] {
            ["Frame:", frame, "Time:", time] => frame.parse::<u64>().ok().zip(seconds(time)),
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
    let mut beyond = 0;
    for object in &annotated {
        let class =
            CLASSES.map(&object.class_name, unknown, skipped).map_err(|e| anyhow::anyhow!("{}: object {}: {e}", annotations.display(), object.id))?;
        for (k, bbox) in object.bboxes.iter().enumerate() {
            if is_no_box(bbox) {
                continue;
            }
            let frame = k as u64 + 1;
            let Some(&at) = index.get(&frame) else {
                beyond += 1;
                continue;
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
    Ok((scenario, frames.into_iter().zip(objects).collect(), beyond))
}

/// Whether a `bboxes` entry holds no box: what Python finds false, as the SDK's
/// `if object['bboxes'][id]` does (`[]` in the published files).
fn is_no_box(entry: &serde_json::Value) -> bool {
    use serde_json::Value;
    match entry {
        Value::Null => true,
        Value::Bool(b) => !b,
        Value::Array(a) => a.is_empty(),
        Value::Object(o) => o.is_empty(),
        Value::String(s) => s.is_empty(),
        Value::Number(n) => n.as_f64() == Some(0.0),
    }
}

/// A timestamp as the SDK's `__timestamp_format` reads it: a fraction of fewer than nine digits
/// is nanoseconds written without their leading zeros (`.2904766` is 0.002904766 s).
fn seconds(time: &str) -> Option<f64> {
    let parsed = match time.split_once('.') {
        Some((whole, fraction)) if fraction.len() < 9 => format!("{whole}.{fraction:0>9}").parse::<f64>().ok(),
        _ => time.parse::<f64>().ok(),
    };
    parsed.filter(|t| t.is_finite())
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

/// Frame `number`'s polar scan in the sequence at `dir` (`shown` in messages): range rows and
/// azimuth columns, as published.
fn polar_scan(dir: &Path, shown: &Path, number: u64) -> anyhow::Result<RangeAzimuthMap> {
    let name = format!("Navtech_Polar/{number:06}.png");
    let raw = read_image(dir, shown, &name).with_context(|| format!("{}", shown.join(&name).display()))?;
    if (raw.width, raw.height) != (AZIMUTHS, RANGE_BINS) {
        let turned = if (raw.width, raw.height) == (RANGE_BINS, AZIMUTHS) { " (turned a quarter: rows are range as published)" } else { "" };
        bail!(
            "{}: {} wide x {} high{turned}; a Navtech polar scan as RADIATE publishes it is {AZIMUTHS} wide (azimuths) x {RANGE_BINS} high (range bins)",
            shown.join(&name).display(),
            raw.width,
            raw.height
        );
    }
    let max = raw.integer_max.unwrap_or(255.0);
    Ok(RangeAzimuthMap {
        values: raw.values.iter().map(|v| v / max).collect(),
        rows: RANGE_BINS,
        cols: AZIMUTHS,
        range: Bins::Even { from: -RANGE_RES / 2.0, to: (RANGE_BINS as f64 - 0.5) * RANGE_RES },
        // Clockwise from ahead: counter-clockwise angles decrease along the columns.
        azimuth: Bins::Even { from: 0.0, to: -2.0 * PI },
        wraps: true,
    })
}
