//! RADIATE, CRUW (ROD2021) and CARRADA fixtures; see the crate docs.

use std::f64::consts::PI;
use std::path::Path;

/// A `.npy` file of float32 (`<f4`) or uint8 (`|u1`) values in `shape`.
pub fn write_npy(path: &Path, descr: &str, shape: &[usize], data: &[u8]) {
    let dims: Vec<String> = shape.iter().map(usize::to_string).collect();
    let mut header =
        format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': ({}), }}", dims.join(", ") + if shape.len() == 1 { "," } else { "" });
    let total = (10 + header.len() + 1).div_ceil(64) * 64;
    header.push_str(&" ".repeat(total - 10 - header.len() - 1));
    header.push('\n');
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend((header.len() as u16).to_le_bytes());
    bytes.extend(header.as_bytes());
    bytes.extend(data);
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, bytes).unwrap();
}

pub fn f32_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// An object the fixtures draw: centre ahead and to the left (metres), its box, its class in the
/// dataset's own words, and the rlmflow class it must import as.
#[derive(Clone, Debug)]
pub struct Placed {
    pub ahead: f64,
    pub left: f64,
    pub length: f64,
    pub width: f64,
    pub theirs: &'static str,
    pub ours: &'static str,
}

/// Whether the point (ahead, left) lies in `o`'s box (aligned with the ego's heading).
fn inside(o: &Placed, ahead: f64, left: f64) -> bool {
    (ahead - o.ahead).abs() <= o.length / 2.0 && (left - o.left).abs() <= o.width / 2.0
}

/// Frame `k` of sequence `s`: a few objects spread around the sensor within `reach` metres, in
/// front only (`front`) or all round.
fn scene(s: usize, k: usize, reach: f64, front: bool, classes: &[(&'static str, &'static str, f64, f64)]) -> Vec<Placed> {
    (0..2 + (s + k) % 3)
        .map(|j| {
            let n = s * 31 + k * 17 + j * 7;
            let range = 6.0 + (n % 13) as f64 / 13.0 * (reach - 8.0);
            let spread = if front { 100.0 } else { 360.0 };
            let bearing = ((n * 53 % 360) as f64 / 360.0 * spread - spread / 2.0).to_radians();
            let (theirs, ours, length, width) = classes[n % classes.len()];
            Placed { ahead: range * bearing.cos(), left: range * bearing.sin(), length, width, theirs, ours }
        })
        .collect()
}

const RADIATE_RES: f64 = 0.173611;

/// A RADIATE root with sequences `city_1_0` and `fog_6_0` of three radar frames each (see
/// [`write_radiate_sized`]).
pub fn write_radiate(root: &Path) -> Vec<Vec<Placed>> {
    write_radiate_sized(root, &["city_1_0", "fog_6_0"], 3)
}

/// A writer of one dataset's fixture: a root, its sequence names and frames per sequence in; each
/// frame's objects out.
pub type WriteSized = fn(&Path, &[&str], usize) -> Vec<Vec<Placed>>;

/// A RADIATE root with `names` sequences of `frames` radar frames each, in the published layout
/// (checked against the SDK's own sample by `tests/pipelines/radiate.rs`):
/// `Navtech_Polar/00000k.png` (uint8, 400 wide (azimuths) x 576 high (range bins)),
/// `Navtech_Polar.txt`, `annotations/annotations.json` (boxes in the 1152-pixel Cartesian image,
/// `[]` where an object is absent, entries running two frames past the last radar frame as the
/// published ones do) and `meta.json`. Returns each frame's objects.
pub fn write_radiate_sized(root: &Path, names: &[&str], frames: usize) -> Vec<Vec<Placed>> {
    let classes = [("car", "car", 4.5, 1.8), ("bus", "truck", 11.0, 2.6), ("group_of_pedestrians", "walker", 1.6, 1.6), ("van", "car", 5.0, 2.0)];
    let mut all = Vec::new();
    for (s, &name) in names.iter().enumerate() {
        let dir = root.join(name);
        std::fs::create_dir_all(dir.join("Navtech_Polar")).unwrap();
        std::fs::create_dir_all(dir.join("annotations")).unwrap();
        let mut stamps = String::new();
        let mut annotations = Vec::new();
        for k in 0..frames {
            let objects = scene(s, k, 45.0, false, &classes);
            let mut polar = vec![0u8; 576 * 400];
            for (r, row) in polar.chunks_mut(400).enumerate() {
                // Row r is r * 0.173611 m out; column a looks (a + 0.5) * 0.9 degrees clockwise of ahead.
                let range = r as f64 * RADIATE_RES;
                for (a, v) in row.iter_mut().enumerate() {
                    let clockwise = (a as f64 + 0.5) * 2.0 * PI / 400.0;
                    let (ahead, left) = (range * clockwise.cos(), -range * clockwise.sin());
                    *v = if objects.iter().any(|o| inside(o, ahead, left)) { 250 } else { 20 + ((a * 7 + r * 3 + k) % 40) as u8 };
                }
            }
            write_png(&dir.join(format!("Navtech_Polar/{:06}.png", k + 1)), 400, 576, &polar);
            // To the nanosecond, as the published files have them (more digits than an f64 holds).
            let ns = 1_574_859_771_744_660_272 + k as u64 * 250_000_000;
            stamps += &format!("Frame: {:06} Time: {}.{:09}\n", k + 1, ns / 1_000_000_000, ns % 1_000_000_000);
            for o in &objects {
                // The Cartesian image: the radar at pixel 576, ahead up, the left to the left.
                let (col, row) = (576.0 - o.left / RADIATE_RES, 576.0 - o.ahead / RADIATE_RES);
                let (w, h) = (o.width / RADIATE_RES, o.length / RADIATE_RES);
                let mut bboxes = vec![serde_json::json!([]); frames + 2];
                bboxes[k] = serde_json::json!({"position": [col - w / 2.0, row - h / 2.0, w, h], "rotation": 0.0});
                annotations.push(serde_json::json!({"id": annotations.len() + 1, "class_name": o.theirs, "bboxes": bboxes}));
            }
            all.push(objects);
        }
        std::fs::write(dir.join("Navtech_Polar.txt"), stamps).unwrap();
        std::fs::write(dir.join("annotations/annotations.json"), serde_json::to_vec(&annotations).unwrap()).unwrap();
        std::fs::write(
            dir.join("meta.json"),
            format!("{{\"name\": \"{name}\", \"type\": \"{}\", \"set\": \"train\"}}", &name[..name.find('_').unwrap()]),
        )
        .unwrap();
    }
    all
}

pub fn write_png(path: &Path, width: u32, height: u32, bytes: &[u8]) {
    let mut encoder = png::Encoder::new(std::fs::File::create(path).unwrap(), width, height);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.write_header().unwrap().write_image_data(bytes).unwrap();
}

/// ROD2021's range bins (cruw-devkit's `confmap2ra`, `sensor_config_rod2021.json`).
fn cruw_range(k: usize) -> f64 {
    (k + 3) as f64 * 4e6 / 134.0 * 299_792_458.0 / 21.0017e12 / 2.0
}

/// ROD2021's angle bins: even in sine from -90 degrees (column 0) to 90, positive to the right.
fn cruw_azimuth(j: usize) -> f64 {
    (-1.0 + 2.0 * j as f64 / 127.0).asin()
}

/// A ROD2021 root as released: `TRAIN_RAD_H/<seq>/RADAR_RA_H/00000k_0000.npy` (and the other
/// chirps' files), 128 x 128 x 2 float32 (real, imaginary), and `TRAIN_RAD_H_ANNO/<seq>.txt`.
pub fn write_cruw(root: &Path) -> Vec<Vec<Placed>> {
    write_cruw_sized(root, &["2019_04_09_BMS1000", "2019_05_29_PCMS005"], 3)
}

/// A ROD2021 root as [`write_cruw`]'s with `names` sequences of `frames` frames each.
pub fn write_cruw_sized(root: &Path, names: &[&str], count: usize) -> Vec<Vec<Placed>> {
    let classes = [("car", "car", 4.5, 1.8), ("pedestrian", "walker", 0.8, 0.8), ("cyclist", "walker", 1.8, 0.8)];
    let mut all = Vec::new();
    for (s, &name) in names.iter().enumerate() {
        let frames = root.join("TRAIN_RAD_H").join(name).join("RADAR_RA_H");
        std::fs::create_dir_all(&frames).unwrap();
        std::fs::create_dir_all(root.join("TRAIN_RAD_H_ANNO")).unwrap();
        let mut lines = String::new();
        for k in 0..count {
            let objects = scene(s, k, 24.0, true, &classes);
            let mut map = vec![0f32; 128 * 128 * 2];
            for (p, cell) in map.chunks_mut(2).enumerate() {
                let (range, azimuth) = (cruw_range(p / 128), cruw_azimuth(p % 128));
                let (ahead, left) = (range * azimuth.cos(), -range * azimuth.sin());
                cell[0] = if objects.iter().any(|o| inside(o, ahead, left)) { 100.0 } else { 0.01 * (1 + (p * 7 + k) % 5) as f32 };
                cell[1] = cell[0] / 2.0;
            }
            for chirp in ["0000", "0064", "0128", "0192"] {
                write_npy(&frames.join(format!("{k:06}_{chirp}.npy")), "<f4", &[128, 128, 2], &f32_bytes(&map));
            }
            for o in &objects {
                let (range, azimuth) = (o.ahead.hypot(o.left), (-o.left).atan2(o.ahead));
                lines += &format!("{k} {range:.4} {azimuth:.4} {}\n", o.theirs);
            }
            all.push(objects);
        }
        std::fs::write(root.join("TRAIN_RAD_H_ANNO").join(format!("{name}.txt")), lines).unwrap();
    }
    all
}

const CARRADA_RANGE: f64 = 0.1953125;
const CARRADA_ANGLE: f64 = PI / 256.0;

/// CARRADA's row `i` range centre: the devkit's `to_ra` puts range r at row `256 - floor(r /
/// 0.1953125)`, far rows first.
fn carrada_range(i: usize) -> f64 {
    (256.0 - i as f64 + 0.5) * CARRADA_RANGE
}

/// CARRADA's column `j` angle centre (`128 + trunc(angle / (pi / 256))`), positive to the right.
fn carrada_angle(j: usize) -> f64 {
    let k = j as f64 - 128.0;
    if k == 0.0 { 0.0 } else { (k + 0.5 * k.signum()) * CARRADA_ANGLE }
}

/// A CARRADA root: `<seq>/range_angle_numpy/00000k.npy` (256 x 256 float32 received power) and
/// `annotations_frame_oriented.json` with each object's range-angle box (the matrix cells of its
/// footprint, min and max, as the devkit's `get_box`) and label (1 pedestrian, 2 cyclist, 3 car).
pub fn write_carrada(root: &Path) -> Vec<Vec<Placed>> {
    write_carrada_sized(root, &["2019-09-16-12-52-12", "2020-02-28-13-09-58"], 3)
}

/// A CARRADA root as [`write_carrada`]'s with `names` sequences of `frames` frames each.
pub fn write_carrada_sized(root: &Path, names: &[&str], count: usize) -> Vec<Vec<Placed>> {
    let classes = [("car", "car", 4.5, 1.8), ("pedestrian", "walker", 1.0, 1.0), ("cyclist", "walker", 1.8, 1.0)];
    let label = |theirs: &str| ["background", "pedestrian", "cyclist", "car"].iter().position(|l| *l == theirs).unwrap();
    let mut all = Vec::new();
    let mut annotations = serde_json::Map::new();
    for (s, &name) in names.iter().enumerate() {
        let dir = root.join(name).join("range_angle_numpy");
        std::fs::create_dir_all(&dir).unwrap();
        let mut frames = serde_json::Map::new();
        for k in 0..count {
            let objects = scene(s, k, 40.0, true, &classes);
            let mut map = vec![0f32; 256 * 256];
            let mut boxes: Vec<[usize; 4]> = vec![[usize::MAX, usize::MAX, 0, 0]; objects.len()];
            for (p, v) in map.iter_mut().enumerate() {
                let (range, angle) = (carrada_range(p / 256), carrada_angle(p % 256));
                let (ahead, left) = (range * angle.cos(), -range * angle.sin());
                *v = 0.01 * (1 + (p * 7 + k) % 5) as f32;
                for (o, b) in objects.iter().zip(&mut boxes) {
                    if inside(o, ahead, left) {
                        *v = 1e4;
                        *b = [b[0].min(p / 256), b[1].min(p % 256), b[2].max(p / 256), b[3].max(p % 256)];
                    }
                }
            }
            write_npy(&dir.join(format!("{k:06}.npy")), "<f4", &[256, 256], &f32_bytes(&map));
            let mut instances = serde_json::Map::new();
            for (n, (o, b)) in objects.iter().zip(&boxes).enumerate() {
                assert!(b[0] != usize::MAX, "{o:?} covers a cell");
                let view = serde_json::json!({"box": [[b[0], b[1]], [b[2], b[3]]], "label": label(o.theirs), "sparse": [], "dense": []});
                instances.insert(format!("{}", 100 * s + n), serde_json::json!({"range_angle": view, "range_doppler": view}));
            }
            frames.insert(format!("{k:06}"), serde_json::Value::Object(instances));
            all.push(objects);
        }
        annotations.insert(name.into(), serde_json::Value::Object(frames));
    }
    std::fs::write(root.join("annotations_frame_oriented.json"), serde_json::to_vec(&annotations).unwrap()).unwrap();
    all
}
