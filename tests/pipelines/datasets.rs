//! Published radar datasets read in their own layouts through the real binary, on the fixtures of
//! `rlmflow-test-support` (each dataset's exact layout, every object drawn over its footprint in
//! the sensor's own geometry; nothing is downloaded).

use std::path::Path;

use rlmflow_test_support::datasets::{Placed, write_carrada, write_cruw, write_png, write_radiate};

use super::{artifacts, rlmflow, scratch};

/// Imports `format` from `data` at `image` pixels out to `range_max` and checks every written
/// object: imported with its class and position, in its sequence, on its return (a bright
/// pixel, well above the floor, within one pixel of where the actor is placed), and counted by
/// the labels' grid in its distance bin; and the import gives the same bytes in fresh processes.
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
    // Same key, same bytes: the import twice more, each in a fresh process.
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--check-determinism", "scenes"]);
    assert!(ok && out.contains("same bytes"), "{out}");
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

/// Rewrites the text file at `path` through `change`.
fn edit(path: &Path, change: impl FnOnce(String) -> String) {
    std::fs::write(path, change(std::fs::read_to_string(path).unwrap())).unwrap();
}

/// Each bad dataset input stops the import with the file (and line or object) named, and leaves
/// no artifact in the store.
#[test]
fn bad_dataset_input_is_named_and_leaves_nothing() {
    let pipeline = |format: &str| {
        format!("[pipeline]\nname = \"bad\"\nseed = 1\n[stages.scenes]\noperator = \"import\"\nformat = \"{format}\"\npath = \"data\"\nimage = 32\n")
    };
    type Damage = Box<dyn Fn(&Path)>;
    let cases: Vec<(&str, &str, Damage, &str)> = vec![
        (
            "radiate",
            "no-annotations",
            Box::new(|d| std::fs::remove_file(d.join("fog_6_0/annotations/annotations.json")).unwrap()),
            "fog_6_0/annotations/annotations.json: missing",
        ),
        (
            "radiate",
            "unknown-class",
            Box::new(|d| {
                let path = d.join("city_1_0/annotations/annotations.json");
                edit(&path, |t| t.replacen("\"car\"", "\"tram\"", 1));
            }),
            "unknown class `tram`; known: car, van",
        ),
        (
            "radiate",
            "corrupt-png",
            Box::new(|d| std::fs::write(d.join("fog_6_0/Navtech_Polar/000002.png"), b"not a png").unwrap()),
            "data/fog_6_0/Navtech_Polar/000002.png",
        ),
        (
            "radiate",
            "two-sizes",
            Box::new(|d| write_png(&d.join("fog_6_0/Navtech_Polar/000003.png"), 576, 200, &vec![9u8; 576 * 200])),
            "data/fog_6_0/Navtech_Polar/000003.png: 576 wide x 200 high; a Navtech polar scan as RADIATE publishes it is 400 wide (azimuths) x 576 high (range bins)",
        ),
        (
            "radiate",
            "turned",
            Box::new(|d| write_png(&d.join("fog_6_0/Navtech_Polar/000002.png"), 576, 400, &vec![9u8; 576 * 400])),
            "data/fog_6_0/Navtech_Polar/000002.png: 576 wide x 400 high (turned a quarter: rows are range as published)",
        ),
        (
            "radiate",
            "times-go-back",
            Box::new(|d| {
                // Short fractions are nanoseconds without their leading zeros (radiate_sdk's
                // __timestamp_format): .5 is 0.000000005 s, before the frame at .25 s.
                let path = d.join("city_1_0/Navtech_Polar.txt");
                edit(&path, |t| t.replacen(".994660272", ".5", 1));
            }),
            "city_1_0/Navtech_Polar.txt:2: frame 2 at 1574859771 s does not follow frame 1 at 1574859771.7",
        ),
        (
            "cruw",
            "no-annotations",
            Box::new(|d| std::fs::remove_file(d.join("TRAIN_RAD_H_ANNO/2019_05_29_PCMS005.txt")).unwrap()),
            "TRAIN_RAD_H_ANNO/2019_05_29_PCMS005.txt: missing",
        ),
        (
            "cruw",
            "frame-beyond",
            Box::new(|d| {
                let path = d.join("TRAIN_RAD_H_ANNO/2019_04_09_BMS1000.txt");
                edit(&path, |t| t + "7 5.0 0.1 car\n");
            }),
            "frame 7 has no map",
        ),
        (
            "cruw",
            "corrupt-npy",
            Box::new(|d| std::fs::write(d.join("TRAIN_RAD_H/2019_04_09_BMS1000/RADAR_RA_H/000001_0000.npy"), b"\x93NUMPY").unwrap()),
            "000001_0000.npy",
        ),
        (
            "cruw",
            "bad-line",
            Box::new(|d| {
                let path = d.join("TRAIN_RAD_H_ANNO/2019_04_09_BMS1000.txt");
                std::fs::write(&path, "0 13.0809 car\n").unwrap();
            }),
            "TRAIN_RAD_H_ANNO/2019_04_09_BMS1000.txt:1: `0 13.0809 car`; a line is `frame range_m azimuth_rad class`",
        ),
        (
            "carrada",
            "no-annotations",
            Box::new(|d| std::fs::remove_file(d.join("annotations_frame_oriented.json")).unwrap()),
            "annotations_frame_oriented.json: missing",
        ),
        (
            "carrada",
            "frame-beyond",
            Box::new(|d| std::fs::remove_file(d.join("2019-09-16-12-52-12/range_angle_numpy/000002.npy")).unwrap()),
            "sequence `2019-09-16-12-52-12` annotates frame 000002, but data/2019-09-16-12-52-12/range_angle_numpy has no 000002.npy",
        ),
        (
            "carrada",
            "unknown-label",
            Box::new(|d| {
                let path = d.join("annotations_frame_oriented.json");
                edit(&path, |t| t.replacen("\"label\":3", "\"label\":7", 1));
            }),
            "unknown class `label 7`; known: pedestrian, cyclist, car",
        ),
    ];
    for (format, name, damage, expected) in cases {
        let dir = scratch(&format!("bad-{format}-{name}"), &pipeline(format));
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
    edit(&path, |t| t.replace("\"bus\"", "\"tram\""));
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok && out.contains("3 frames from radiate") && out.contains("skipped objects of unknown classes:") && out.contains(" tram"), "{out}");
}

/// The RADIATE SDK's own sample (`datasets/radiate/tiny_foggy`, as published) through the real
/// binary: all 18 radar frames, each annotated vehicle an actor of its class, the boxes the
/// annotations hold for frames past the sample's last counted in one warning, and the same bytes
/// in fresh processes. (Each box against the published Cartesian image: `rlmflow-scenes`'s
/// `datasets::radiate_sample`.)
#[test]
fn the_published_radiate_sample_imports_as_it_stands() {
    let sample = super::root().join("datasets/radiate/tiny_foggy");
    let pipeline = format!(
        "[pipeline]\nname = \"sample\"\nseed = 1\n[stages.scenes]\noperator = \"import\"\nformat = \"radiate\"\npath = {:?}\nimage = 64\nrange_max_m = 100.0\n",
        sample.display().to_string()
    );
    let dir = scratch("radiate-sample", &pipeline);
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    assert!(out.contains("18 frames from radiate, 42 vehicles"), "{out}");
    assert!(out.contains("warning: boxes for frames past the last radar frame ignored, as radiate_sdk never reads them: tiny_foggy (367)"), "{out}");
    let scenes = rlmflow_stages::scenes::Scenes::open(&artifacts(&dir.join(".rlmflow/objects"), "scenes.json")[0]).unwrap();
    let frames = scenes.frames().unwrap();
    assert_eq!(frames.len(), 18);
    assert!(frames.iter().all(|f| f.episode.as_deref() == Some("tiny_foggy") && f.scenario == "radiate-fog"));
    // fog_6_0's annotated objects 1-4 on these frames: a bus, then three cars.
    let classes: Vec<&str> = frames.iter().flat_map(|f| f.actors.iter().map(|a| a.class.as_str())).collect();
    assert_eq!((classes.iter().filter(|&&c| c == "truck").count(), classes.iter().filter(|&&c| c == "car").count()), (18, 24));
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--check-determinism", "scenes"]);
    assert!(ok && out.contains("same bytes"), "{out}");
}

/// The fixture the other RADIATE tests write has the published sample's layout: its files, the
/// polar PNGs' shape and type, the timestamp lines, the annotations' structure (`[]` for an absent
/// box) and meta.json's keys.
#[test]
fn the_radiate_fixture_has_the_published_layout() {
    let sample = super::root().join("datasets/radiate/tiny_foggy");
    let dir = scratch("radiate-layout", "");
    write_radiate(&dir.join("data"));
    let fixture = dir.join("data/fog_6_0");
    let png_header = |path: &Path| {
        let info = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap())).read_info().unwrap().info().clone();
        (info.width, info.height, info.color_type, info.bit_depth)
    };
    assert_eq!(png_header(&fixture.join("Navtech_Polar/000001.png")), png_header(&sample.join("Navtech_Polar/000001.png")));
    assert_eq!(png_header(&sample.join("Navtech_Polar/000001.png")).0, 400, "published: 400 wide (azimuths)");
    let line_shape = |line: &str| -> Vec<usize> { line.split([' ', '.']).map(str::len).collect() };
    let stamps = |dir: &Path| std::fs::read_to_string(dir.join("Navtech_Polar.txt")).unwrap();
    let (ours, theirs) = (stamps(&fixture), stamps(&sample));
    assert!(ours.lines().chain(theirs.lines()).all(|l| l.starts_with("Frame: ") && l.contains(" Time: ")));
    assert_eq!(line_shape(ours.lines().next().unwrap()), line_shape(theirs.lines().next().unwrap()));
    // Each object's keys, and each bboxes entry's: `[]`, or a box's keys and the position's length.
    let shape = |dir: &Path| -> std::collections::BTreeSet<String> {
        let json: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.join("annotations/annotations.json")).unwrap()).unwrap();
        let mut shapes = std::collections::BTreeSet::new();
        for object in json.as_array().unwrap() {
            shapes.insert(format!("object {:?}", object.as_object().unwrap().keys().collect::<Vec<_>>()));
            for entry in object["bboxes"].as_array().unwrap() {
                shapes.insert(match entry {
                    serde_json::Value::Array(a) if a.is_empty() => "[]".to_owned(),
                    serde_json::Value::Object(o) => format!("box {:?} of {}", o.keys().collect::<Vec<_>>(), o["position"].as_array().unwrap().len()),
                    other => format!("unexpected {other}"),
                });
            }
        }
        shapes
    };
    assert_eq!(shape(&fixture), shape(&sample));
    let keys = |dir: &Path| -> Vec<String> {
        serde_json::from_slice::<serde_json::Value>(&std::fs::read(dir.join("meta.json")).unwrap())
            .unwrap()
            .as_object()
            .unwrap()
            .keys()
            .cloned()
            .collect()
    };
    assert!(keys(&fixture).iter().all(|k| keys(&sample).contains(k)), "{:?} against {:?}", keys(&fixture), keys(&sample));
}

/// `examples/radiate.toml` end to end on RADIATE's published sample, the simulated half at tiny
/// scale: the decoders train and test on the sample's 18 real frames (split by frame: one
/// sequence cannot be split by sequence), and the report quotes the paper's RADIATE table beside
/// ours, with the threshold curves.
#[test]
fn the_radiate_example_runs_through_the_report_on_the_published_sample() {
    let example = std::fs::read_to_string(super::root().join("examples/radiate.toml")).unwrap();
    let sample = super::root().join("datasets/radiate/tiny_foggy");
    let tiny = example
        .replace("path = \"../data/radiate\"", &format!("path = {:?}", sample.display().to_string()))
        .replace("split_by = \"episode\"", "split_by = \"frame\"")
        .replace("cache = \"../.rlmflow\"", "")
        .replace("frames = 2000", "frames = 80")
        .replace("frames = 6000", "frames = 160")
        .replace("epochs = 10", "epochs = 1")
        .replace("epochs = 4", "epochs = 1")
        .replace("batch = 128", "batch = 32")
        .replace("batch = 64", "batch = 8");
    assert_ne!(tiny, example);
    let dir = scratch("radiate-example", &tiny);
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    assert!(out.contains("18 frames from radiate"), "{out}");
    let report = artifacts(&dir.join(".rlmflow/objects"), "report.md");
    assert_eq!(report.len(), 1);
    let text = std::fs::read_to_string(report[0].join("report.md")).unwrap();
    assert!(text.contains("Vehicle segmentation on RADIATE"), "{text}");
    // The paper's RADIATE rows beside ours, in its columns.
    assert!(text.contains("0.352/0.323/0.202/0.337, 0.207, 0.217") && text.contains("0.468/0.380/0.265/0.419, 0.271, 0.306"), "{text}");
    for row in ["pup[vanilla]", "pup[alpha4]", "pup[random]", "unet"] {
        assert!(text.contains(row), "{row} in the report: {text}");
    }
}
