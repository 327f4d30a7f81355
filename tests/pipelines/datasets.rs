//! Published radar datasets read in their own layouts through the real binary. The fixtures are
//! written here in each dataset's exact published layout (file names, array shapes and dtypes,
//! annotation syntax and units) with every object drawn as a return over its footprint, in the
//! sensor's own geometry as its devkit documents it; nothing is downloaded.

use std::f64::consts::PI;
use std::path::Path;

use super::import::{f32_bytes, write_npy};
use super::{artifacts, rlmflow, scratch};

/// An object the fixtures draw: centre ahead and to the left (metres), its box, its class in the
/// dataset's own words, and the rlmflow class it must import as.
#[derive(Clone, Debug)]
struct Placed {
    ahead: f64,
    left: f64,
    length: f64,
    width: f64,
    theirs: &'static str,
    ours: &'static str,
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
fn write_radiate(root: &Path) -> Vec<Vec<Placed>> {
    write_radiate_sized(root, &["city_1_0", "fog_6_0"], 3)
}

/// A RADIATE root with `names` sequences of `frames` radar frames each:
/// `Navtech_Polar/00000k.png` (400 azimuths x 576 range bins, uint8), `Navtech_Polar.txt`,
/// `annotations/annotations.json` (boxes in the 1152-pixel Cartesian image, `{}` where an object is
/// absent) and `meta.json`. Returns each frame's objects.
fn write_radiate_sized(root: &Path, names: &[&str], frames: usize) -> Vec<Vec<Placed>> {
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
            let mut polar = vec![0u8; 400 * 576];
            for (a, row) in polar.chunks_mut(576).enumerate() {
                // Row a looks a * 0.9 degrees clockwise of ahead; column r is r * 0.173611 m out.
                let clockwise = a as f64 * 2.0 * PI / 400.0;
                for (r, v) in row.iter_mut().enumerate() {
                    let range = r as f64 * RADIATE_RES;
                    let (ahead, left) = (range * clockwise.cos(), -range * clockwise.sin());
                    *v = if objects.iter().any(|o| inside(o, ahead, left)) { 250 } else { 20 + ((a * 7 + r * 3 + k) % 40) as u8 };
                }
            }
            write_png(&dir.join(format!("Navtech_Polar/{:06}.png", k + 1)), 576, 400, &polar);
            stamps += &format!("Frame: {:06} Time: {:.9}\n", k + 1, 1_574_859_771.744_660_272 + k as f64 * 0.25);
            for o in &objects {
                // The Cartesian image: the radar at pixel 576, ahead up, the left to the left.
                let (col, row) = (576.0 - o.left / RADIATE_RES, 576.0 - o.ahead / RADIATE_RES);
                let (w, h) = (o.width / RADIATE_RES, o.length / RADIATE_RES);
                let mut bboxes = vec![serde_json::json!({}); frames];
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

fn write_png(path: &Path, width: u32, height: u32, bytes: &[u8]) {
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
fn write_cruw(root: &Path) -> Vec<Vec<Placed>> {
    let classes = [("car", "car", 4.5, 1.8), ("pedestrian", "walker", 0.8, 0.8), ("cyclist", "walker", 1.8, 0.8)];
    let mut all = Vec::new();
    for (s, name) in ["2019_04_09_BMS1000", "2019_05_29_PCMS005"].into_iter().enumerate() {
        let frames = root.join("TRAIN_RAD_H").join(name).join("RADAR_RA_H");
        std::fs::create_dir_all(&frames).unwrap();
        std::fs::create_dir_all(root.join("TRAIN_RAD_H_ANNO")).unwrap();
        let mut lines = String::new();
        for k in 0..3 {
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
fn write_carrada(root: &Path) -> Vec<Vec<Placed>> {
    let classes = [("car", "car", 4.5, 1.8), ("pedestrian", "walker", 1.0, 1.0), ("cyclist", "walker", 1.8, 1.0)];
    let label = |theirs: &str| ["background", "pedestrian", "cyclist", "car"].iter().position(|l| *l == theirs).unwrap();
    let mut all = Vec::new();
    let mut annotations = serde_json::Map::new();
    for (s, name) in ["2019-09-16-12-52-12", "2020-02-28-13-09-58"].into_iter().enumerate() {
        let dir = root.join(name).join("range_angle_numpy");
        std::fs::create_dir_all(&dir).unwrap();
        let mut frames = serde_json::Map::new();
        for k in 0..3 {
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

/// Imports `format` from `data` at `image` pixels out to `range_max` and checks every written
/// object: imported with its class and position, in its sequence, on its return (a bright
/// pixel, well above the floor, within one pixel of where the actor is placed), and counted by
/// the labels' grid in its distance bin.
/// Positions are compared within `tolerance` metres (a dataset that annotates bins, not metres,
/// gives a position to a bin).
fn imports_on_returns(name: &str, format: &str, write: fn(&Path) -> Vec<Vec<Placed>>, range_max: f64, sequences: usize, tolerance: f64) {
    let pipeline = format!(
        "[pipeline]\nname = \"{name}\"\nseed = 1\n[stages.scenes]\noperator = \"import\"\nformat = \"{format}\"\npath = \"data\"\nimage = 256\nrange_max_m = {range_max}\n\
         [stages.labels]\noperator = \"ego-grid\"\nsplit_by = \"frame\"\n"
    );
    let dir = scratch(name, &pipeline);
    let placed = write(&dir.join("data"));
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    let found = artifacts(&dir.join(".rlmflow/objects"), "scenes.json");
    let scenes = rlmflow_stages::scenes::Scenes::open(&found[0]).unwrap();
    let frames = scenes.frames().unwrap();
    assert_eq!(frames.len(), placed.len());
    let mut episodes: Vec<String> = frames.iter().map(|f| f.episode.clone().unwrap()).collect();
    episodes.dedup();
    assert_eq!(episodes.len(), sequences, "one episode per sequence, in order: {episodes:?}");
    let (mut objects, mut on_return) = (0, 0);
    for (frame, expected) in frames.iter().zip(&placed) {
        let image = scenes.image(0, frame.index).unwrap();
        assert_eq!(frame.actors.len(), expected.len(), "frame {}", frame.index);
        for (actor, o) in frame.actors.iter().zip(expected) {
            assert_eq!(actor.class, o.ours);
            assert!((actor.x - o.ahead).abs() < tolerance && (actor.y - o.left).abs() < tolerance, "{actor:?} against {o:?}");
            let (row, col) = (actor.row as i64, actor.col as i64);
            let bright = (-1..=1)
                .flat_map(|dr| (-1..=1).map(move |dc| (row + dr, (col + dc).rem_euclid(256))))
                .filter(|&(r, _)| (0..256).contains(&r))
                .map(|(r, c)| image[r as usize * 256 + c as usize])
                .max()
                .unwrap();
            objects += 1;
            on_return += usize::from(bright >= 100);
        }
    }
    assert_eq!(on_return, objects, "{on_return} of {objects} objects on their return");
    // The labels' grid counts each vehicle in the bin of its distance (10 m bins to 40 m).
    let lines = std::fs::read_to_string(artifacts(&dir.join(".rlmflow/objects"), "labels.jsonl")[0].join("labels.jsonl")).unwrap();
    for (line, expected) in lines.lines().zip(&placed) {
        let grid: serde_json::Value = serde_json::from_str::<serde_json::Value>(line).unwrap()["grid"].clone();
        for (bin, name) in ["0-10m", "10-20m", "20-30m", "30-40m"].iter().enumerate() {
            let want = expected
                .iter()
                .filter(|o| matches!(o.ours, "car" | "truck") && o.ahead.hypot(o.left) < 40.0 && (o.ahead.hypot(o.left) / 10.0) as usize == bin)
                .count();
            assert_eq!(grid[name]["total_vehicles"].as_u64(), Some(want as u64), "{name}: {grid}");
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn radiate_imports_with_every_object_on_its_return() {
    imports_on_returns("radiate", "radiate", write_radiate, 50.0, 2, 1e-3);
}

#[test]
fn cruw_imports_with_every_object_on_its_return() {
    imports_on_returns("cruw", "cruw", write_cruw, 30.0, 2, 1e-3);
}

#[test]
fn carrada_imports_with_every_object_on_its_return() {
    imports_on_returns("carrada", "carrada", write_carrada, 50.0, 2, 0.6);
}

/// Each bad dataset input stops the import with the file (and line or object) named, and leaves
/// no artifact in the store.
#[test]
fn bad_dataset_input_is_named_and_leaves_nothing() {
    let pipeline = |format: &str, extra: &str| {
        format!(
            "[pipeline]\nname = \"bad\"\nseed = 1\n[stages.scenes]\noperator = \"import\"\nformat = \"{format}\"\npath = \"data\"\nimage = 32\n{extra}"
        )
    };
    let cases: Vec<(&str, &str, &str, Box<dyn Fn(&Path)>, &str)> = vec![
        (
            "radiate",
            "",
            "no-annotations",
            Box::new(|d| std::fs::remove_file(d.join("fog_6_0/annotations/annotations.json")).unwrap()),
            "fog_6_0/annotations/annotations.json: missing",
        ),
        (
            "radiate",
            "",
            "frame-beyond",
            Box::new(|d| {
                let path = d.join("city_1_0/Navtech_Polar.txt");
                let text = std::fs::read_to_string(&path).unwrap();
                std::fs::write(&path, text.lines().take(2).map(|l| format!("{l}\n")).collect::<String>()).unwrap();
            }),
            "has a box for frame 3, but data/city_1_0/Navtech_Polar.txt lists no such radar frame",
        ),
        (
            "radiate",
            "",
            "unknown-class",
            Box::new(|d| {
                let path = d.join("city_1_0/annotations/annotations.json");
                std::fs::write(&path, std::fs::read_to_string(&path).unwrap().replacen("\"car\"", "\"tram\"", 1)).unwrap();
            }),
            "unknown class `tram`; known: car, van",
        ),
        (
            "radiate",
            "",
            "corrupt-png",
            Box::new(|d| std::fs::write(d.join("fog_6_0/Navtech_Polar/000002.png"), b"not a png").unwrap()),
            "data/fog_6_0/Navtech_Polar/000002.png",
        ),
        (
            "radiate",
            "",
            "two-sizes",
            Box::new(|d| write_png(&d.join("fog_6_0/Navtech_Polar/000003.png"), 576, 200, &vec![9u8; 576 * 200])),
            "data/fog_6_0/Navtech_Polar/000003.png: 200 x 576 pixels; a Navtech polar scan is 400 azimuths x 576 range bins",
        ),
        (
            "cruw",
            "",
            "no-annotations",
            Box::new(|d| std::fs::remove_file(d.join("TRAIN_RAD_H_ANNO/2019_05_29_PCMS005.txt")).unwrap()),
            "TRAIN_RAD_H_ANNO/2019_05_29_PCMS005.txt: missing",
        ),
        (
            "cruw",
            "",
            "frame-beyond",
            Box::new(|d| {
                let path = d.join("TRAIN_RAD_H_ANNO/2019_04_09_BMS1000.txt");
                std::fs::write(&path, std::fs::read_to_string(&path).unwrap() + "7 5.0 0.1 car\n").unwrap();
            }),
            "frame 7 has no map",
        ),
        (
            "cruw",
            "",
            "corrupt-npy",
            Box::new(|d| std::fs::write(d.join("TRAIN_RAD_H/2019_04_09_BMS1000/RADAR_RA_H/000001_0000.npy"), b"\x93NUMPY").unwrap()),
            "000001_0000.npy",
        ),
        (
            "cruw",
            "",
            "bad-line",
            Box::new(|d| {
                let path = d.join("TRAIN_RAD_H_ANNO/2019_04_09_BMS1000.txt");
                std::fs::write(&path, "0 13.0809 car\n").unwrap();
            }),
            "TRAIN_RAD_H_ANNO/2019_04_09_BMS1000.txt:1: `0 13.0809 car`; a line is `frame range_m azimuth_rad class`",
        ),
        (
            "carrada",
            "",
            "no-annotations",
            Box::new(|d| std::fs::remove_file(d.join("annotations_frame_oriented.json")).unwrap()),
            "annotations_frame_oriented.json: missing",
        ),
        (
            "carrada",
            "",
            "frame-beyond",
            Box::new(|d| std::fs::remove_file(d.join("2019-09-16-12-52-12/range_angle_numpy/000002.npy")).unwrap()),
            "sequence `2019-09-16-12-52-12` annotates frame 000002, but data/2019-09-16-12-52-12/range_angle_numpy has no 000002.npy",
        ),
        (
            "carrada",
            "",
            "unknown-label",
            Box::new(|d| {
                let path = d.join("annotations_frame_oriented.json");
                std::fs::write(&path, std::fs::read_to_string(&path).unwrap().replacen("\"label\":3", "\"label\":7", 1)).unwrap();
            }),
            "unknown class `label 7`; known: pedestrian, cyclist, car",
        ),
    ];
    for (format, extra, name, damage, expected) in cases {
        let dir = scratch(&format!("bad-{format}-{name}"), &pipeline(format, extra));
        match format {
            "radiate" => drop(write_radiate(&dir.join("data"))),
            "cruw" => drop(write_cruw(&dir.join("data"))),
            _ => drop(write_carrada(&dir.join("data"))),
        }
        damage(&dir.join("data"));
        let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
        assert!(!ok && out.contains(expected), "{format} {name}: expected `{expected}` in:\n{out}");
        assert!(!out.contains("panicked"), "{out}");
        let objects = dir.join(".rlmflow/objects");
        assert!(!objects.exists() || artifacts(&objects, "scenes.json").is_empty(), "{format} {name}: an artifact was left");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

/// With `unknown_classes = "skip"` an object of a class the table lacks is counted and named,
/// and the rest import.
#[test]
fn unknown_classes_can_be_counted_and_skipped() {
    let dir = scratch(
        "radiate-skip",
        "[pipeline]\nname = \"skip\"\nseed = 1\n[stages.scenes]\noperator = \"import\"\nformat = \"radiate\"\npath = \"data\"\nimage = 32\nunknown_classes = \"skip\"\nsequences = [\"city_1_0\"]\n",
    );
    write_radiate(&dir.join("data"));
    let path = dir.join("data/city_1_0/annotations/annotations.json");
    std::fs::write(&path, std::fs::read_to_string(&path).unwrap().replace("\"bus\"", "\"tram\"")).unwrap();
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok && out.contains("3 frames from radiate") && out.contains("skipped objects of unknown classes:") && out.contains(" tram"), "{out}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `examples/radiate.toml` at tiny scale on a RADIATE fixture of ten sequences: the simulated
/// half pretrains, the decoders train and test on RADIATE split by sequence, and the report
/// quotes the paper's RADIATE table beside ours, with the threshold curves.
#[test]
fn the_radiate_example_runs_through_the_report_on_a_fixture() {
    let example = std::fs::read_to_string(super::root().join("examples/radiate.toml")).unwrap();
    let tiny = example
        .replace("path = \"../data/radiate\"", "path = \"radiate\"")
        .replace("cache = \"../.rlmflow\"", "")
        .replace("frames = 2000", "frames = 80")
        .replace("frames = 6000", "frames = 160")
        .replace("epochs = 10", "epochs = 1")
        .replace("epochs = 4", "epochs = 1")
        .replace("batch = 128", "batch = 32")
        .replace("batch = 64", "batch = 16");
    assert_ne!(tiny, example);
    let dir = scratch("radiate-example", &tiny);
    let names: Vec<String> = (0..10).map(|i| format!("{}_{i}_0", ["city", "fog", "rain", "night", "snow"][i % 5])).collect();
    let names: Vec<&str> = names.iter().map(String::as_str).collect();
    write_radiate_sized(&dir.join("radiate"), &names, 4);
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    let report = artifacts(&dir.join(".rlmflow/objects"), "report.md");
    assert_eq!(report.len(), 1);
    let text = std::fs::read_to_string(report[0].join("report.md")).unwrap();
    assert!(text.contains("Vehicle segmentation on RADIATE"), "{text}");
    // The paper's RADIATE rows beside ours, in its columns.
    assert!(text.contains("0.352/0.323/0.202/0.337, 0.207, 0.217") && text.contains("0.468/0.380/0.265/0.419, 0.271, 0.306"), "{text}");
    for row in ["pup[vanilla]", "pup[alpha4]", "pup[random]", "unet"] {
        assert!(text.contains(row), "{row} in the report: {text}");
    }
    let labels = artifacts(&dir.join(".rlmflow/objects"), "labels.json");
    let radiate_labels: Vec<serde_json::Value> = labels
        .iter()
        .map(|d| serde_json::from_slice::<serde_json::Value>(&std::fs::read(d.join("labels.json")).unwrap()).unwrap())
        .filter(|l| l["split"]["groups"].as_u64() == Some(10))
        .collect();
    assert_eq!(radiate_labels.len(), 1, "RADIATE's labels split its ten sequences");
    std::fs::remove_dir_all(&dir).unwrap();
}
