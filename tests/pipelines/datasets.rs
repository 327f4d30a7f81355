//! Published radar datasets read in their own layouts through the real binary, on the fixtures of
//! `rlmflow-test-support` (each dataset's exact layout, every object drawn over its footprint in
//! the sensor's own geometry; nothing is downloaded).

use std::path::Path;

use rlmflow_test_support::datasets::{Placed, write_carrada, write_cruw, write_png, write_radiate, write_radiate_sized};

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
            "frame-beyond",
            Box::new(|d| {
                let path = d.join("city_1_0/Navtech_Polar.txt");
                edit(&path, |t| t.lines().take(2).map(|l| format!("{l}\n")).collect());
            }),
            "has a box for frame 3, but data/city_1_0/Navtech_Polar.txt lists no such radar frame",
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
            "data/fog_6_0/Navtech_Polar/000003.png: 200 x 576 pixels; a Navtech polar scan is 400 azimuths x 576 range bins",
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
}
