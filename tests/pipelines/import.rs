//! `import`: a researcher's own recordings (a manifest of arrays and images, or an MCAP file)
//! through the real binary. The recordings are written here: range-azimuth maps of received
//! power with each car a bright spot where the manifest puts it.

use std::path::Path;

use rlmflow_test_support::datasets::{f32_bytes, write_npy};

use rlmflow_test_support::Scratch;

use super::{artifacts, rlmflow, root, scratch};

const ROWS: usize = 20;
const COLS: usize = 30;

/// A map of received power (rows: range 0..50 m from the radar; columns: azimuth from +90
/// degrees, the left, to -90) with a spot of high power at each (x, y).
fn power_map(cars: &[(f64, f64)], seed: usize) -> Vec<f32> {
    let mut map: Vec<f32> = (0..ROWS * COLS).map(|i| 1e-3 * (1.0 + ((i * 7 + seed * 13) % 11) as f32)).collect();
    for &(x, y) in cars {
        let (range, azimuth) = (x.hypot(y), y.atan2(x).to_degrees());
        let (row, col) = ((range / 50.0 * ROWS as f64) as usize, ((90.0 - azimuth) / 180.0 * COLS as f64) as usize);
        map[row.min(ROWS - 1) * COLS + col.min(COLS - 1)] = 1e3;
    }
    map
}

/// A recording of 12 episodes x 3 frames: `.npy` maps with the cars as actors, one frame a PNG,
/// and episode `e03`'s first two frames labelled by their grid alone.
fn write_recording(dir: &Path) {
    let mut manifest = String::new();
    for e in 0..12 {
        let episode = format!("e{e:02}");
        for k in 0..3 {
            let cars: Vec<(f64, f64)> =
                (0..1 + (e + k) % 3).map(|c| (8.0 + ((e * 7 + k * 5 + c * 11) % 30) as f64, -12.0 + ((e * 5 + k * 7 + c * 5) % 24) as f64)).collect();
            let name = format!("frames/{episode}-{k:02}.npy");
            let map = power_map(&cars, e * 3 + k);
            let image = if (e, k) == (1, 2) {
                let name = format!("frames/{episode}-{k:02}.png");
                let peak = map.iter().cloned().fold(0.0, f32::max);
                let bytes: Vec<u8> = map.iter().map(|v| (v / peak * 255.0) as u8).collect();
                let mut encoder = png::Encoder::new(std::fs::File::create(dir.join(&name)).unwrap(), COLS as u32, ROWS as u32);
                encoder.set_color(png::ColorType::Grayscale);
                encoder.set_depth(png::BitDepth::Eight);
                encoder.write_header().unwrap().write_image_data(&bytes).unwrap();
                name
            } else {
                write_npy(&dir.join(&name), "<f4", &[ROWS, COLS], &f32_bytes(&map));
                name
            };
            let time = k as f64 * 0.1;
            let line = if e == 3 && k < 2 {
                serde_json::json!({"image": image, "episode": episode, "time": time, "grid": {"10-20m": {"total_vehicles": 1, "in_lane_front_side": 1}, "walkers": 0, "traffic_signs": []}})
            } else {
                let actors: Vec<serde_json::Value> = cars
                    .iter()
                    .map(|&(x, y)| serde_json::json!({"class": "car", "x": x, "y": y, "heading": 0.0, "length": 4.5, "width": 1.8}))
                    .collect();
                serde_json::json!({"image": image, "episode": episode, "time": time, "actors": actors})
            };
            manifest += &format!("{line}\n");
        }
    }
    std::fs::write(dir.join("manifest.jsonl"), manifest).unwrap();
}

/// A recording written once per test process, for tests that only need one to exist: under the
/// build's scratch space (`CARGO_TARGET_TMPDIR`), where the next test process replaces it.
pub(super) fn walk_recording() -> std::path::PathBuf {
    static DIR: std::sync::OnceLock<std::path::PathBuf> = std::sync::OnceLock::new();
    DIR.get_or_init(|| {
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("walk-recording");
        let _ = std::fs::remove_dir_all(&dir);
        write_recording_into(&dir);
        dir
    })
    .clone()
}

/// The recording of [`write_recording`] in a new directory `dir`.
pub(super) fn write_recording_into(dir: &Path) {
    std::fs::create_dir_all(dir.join("frames")).unwrap();
    write_recording(dir);
}

fn new_recording(name: &str, pipeline: &str) -> Scratch {
    let dir = scratch(name, pipeline);
    write_recording_into(&dir.join("recording"));
    dir
}

fn json_of(dir: &Path, file: &str) -> serde_json::Value {
    let found = artifacts(&dir.join(".rlmflow/objects"), file);
    assert_eq!(found.len(), 1, "{file}: {found:?}");
    serde_json::from_slice(&std::fs::read(found[0].join(file)).unwrap()).unwrap()
}

/// `examples/import.toml` at tiny scale: the written recording imports (actors placed on their
/// pixels, grid-only frames kept), labels, captions, trains and reaches the report.
#[test]
fn a_recording_imports_labels_captions_and_trains_through_the_example() {
    let example = std::fs::read_to_string(root().join("examples/import.toml")).unwrap();
    let tiny = example.replace("epochs = 4", "epochs = 1").replace("image = 64", "image = 32");
    let dir = new_recording("import-example", &tiny);
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--json"]);
    assert!(ok, "{out}");
    let ran = out.lines().filter(|l| l.contains("\"stage_finished\"") && l.contains("\"status\":\"ran\"")).count();
    assert_eq!(ran, 10, "import, labels, captions, tokens, two encoders, two encoder probes, the pixel probe and the report: {out}");
    let scenes = json_of(&dir, "scenes.json");
    assert_eq!((scenes["frames"].as_u64(), scenes["frames_without_positions"].as_u64()), (Some(36), Some(2)), "{scenes}");
    assert_eq!(scenes["images"][0]["view"], "range-azimuth");
    let labels = json_of(&dir, "labels.json");
    assert_eq!(labels["split"]["groups"].as_u64(), Some(12), "the split follows the 12 episodes: {labels}");
    // The grid-only frames keep their grids: one vehicle each, in the cell the manifest names.
    let lines = std::fs::read_to_string(artifacts(&dir.join(".rlmflow/objects"), "labels.jsonl")[0].join("labels.jsonl")).unwrap();
    let grid_only: serde_json::Value = serde_json::from_str(lines.lines().nth(9).unwrap()).unwrap();
    assert_eq!(grid_only["grid"]["10-20m"]["in_lane_front_side"], 1, "{grid_only}");
    assert_eq!(grid_only["episode"], "e03");
    assert!(!artifacts(&dir.join(".rlmflow/objects"), "report.md").is_empty());
}

const IMPORT_AND_LABELS: &str = "[pipeline]\nname = \"imp\"\nseed = 1\n\
    [stages.scenes]\noperator = \"import\"\npath = \"recording\"\nimage = 32\n\
    [stages.labels]\noperator = \"ego-grid\"\n";

/// An image placed where its actors are: the import's pixel for a car holds its bright spot.
#[test]
fn an_edited_image_reruns_the_import_and_is_named_and_a_touched_one_reruns_nothing() {
    let dir = new_recording("import-edit", IMPORT_AND_LABELS);
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok, "{out}");

    // Touched, not changed: a stat shows a new time, the file is hashed again, nothing reruns.
    let image = dir.join("recording/frames/e01-01.npy");
    std::fs::File::options().write(true).open(&image).unwrap().set_modified(std::time::SystemTime::now()).unwrap();
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok && out.contains("done: 0 ran, 2 reused"), "{out}");

    // Changed: the import and its labels rerun, and status and explain name the file.
    let mut bytes = std::fs::read(&image).unwrap();
    let last = bytes.len() - 4;
    bytes[last..].copy_from_slice(&500f32.to_le_bytes());
    std::fs::write(&image, bytes).unwrap();
    let (ok, status) = rlmflow(&dir, &["status", "p.toml"]);
    assert!(ok && status.contains("input path changed: frames/e01-01.npy changed"), "{status}");
    let (ok, explain) = rlmflow(&dir, &["explain", "p.toml", "scenes"]);
    assert!(ok && explain.contains("frames/e01-01.npy"), "{explain}");
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok && out.contains("done: 2 ran, 0 reused"), "{out}");
    // An added file reruns it too.
    std::fs::write(dir.join("recording/notes.txt"), "calibrated 2026-11-01").unwrap();
    let (_, status) = rlmflow(&dir, &["status", "p.toml"]);
    assert!(status.contains("notes.txt changed"), "{status}");
    // Same key, same bytes: the import twice more, each in a fresh process.
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--check-determinism", "scenes"]);
    assert!(ok && out.contains("same bytes"), "{out}");
}

/// Frames labelled by their grid alone have no vehicle positions: a segmentation stage on them
/// refuses, saying why, rather than train on empty masks.
#[test]
fn segmentation_refuses_frames_imported_without_positions() {
    let pipeline = format!(
        "{IMPORT_AND_LABELS}[stages.unet]\nkind = \"segment\"\noperator = \"unet\"\ndevice = \"cpu\"\nepochs = 1\nbatch = 8\nchannels = [4, 8]\n"
    );
    let dir = new_recording("import-segment", &pipeline);
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(
        !ok && out.contains("2 of the 36 frames were imported with a grid but no actors") && out.contains("segmentation needs actors with positions"),
        "{out}"
    );
}

/// The import of a Scenes artifact's own `scenes.mcap` gives frames whose labels are the
/// original's, byte for byte.
#[test]
fn importing_a_procedural_stages_mcap_gives_byte_identical_labels() {
    let sim = "[pipeline]\nname = \"sim\"\nseed = 3\n[stages.scenes]\noperator = \"procedural\"\nframes = 12\nradar = { image = 32 }\n\
               [stages.labels]\noperator = \"ego-grid\"\n";
    let dir = scratch("import-mcap", sim);
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    let original = artifacts(&dir.join(".rlmflow/objects"), "labels.jsonl");
    let mcap = artifacts(&dir.join(".rlmflow/objects"), "scenes.mcap")[0].join("scenes.mcap");
    std::fs::copy(&mcap, dir.join("recorded.mcap")).unwrap();
    let imported = "[pipeline]\nname = \"imp\"\nseed = 3\n[stages.scenes]\noperator = \"import\"\npath = \"recorded.mcap\"\nimage = 0\n\
                    [stages.labels]\noperator = \"ego-grid\"\n";
    std::fs::write(dir.join("p.toml"), imported).unwrap();
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok && out.contains("ran      scenes") && out.contains("labels"), "{out}");
    let labels = artifacts(&dir.join(".rlmflow/objects"), "labels.jsonl");
    assert_eq!(labels, original, "one labels artifact: the import's labels are the same bytes as the original's");
}

/// Each bad recording: an error naming the file and line (or frame) and what is valid, and no
/// artifact or record in the store.
#[test]
fn each_bad_recording_says_what_is_wrong_and_leaves_no_artifact() {
    type Spoil = fn(&Path);
    let cases: [(&str, Spoil, &str); 13] = [
        (
            "an absolute image path",
            |d| append(d, "{\"image\": \"/etc/hostname\", \"actors\": []}\n"),
            "manifest.jsonl:37: image `/etc/hostname`: is an absolute path, outside the recording",
        ),
        (
            "an image path that climbs out",
            |d| append(d, "{\"image\": \"../p.toml\", \"actors\": []}\n"),
            "manifest.jsonl:37: image `../p.toml`: climbs out of the recording with `..`",
        ),
        (
            "a symbolic link out",
            |d| {
                std::os::unix::fs::symlink("/etc/hostname", d.join("frames/link.npy")).unwrap();
                append(d, "{\"image\": \"frames/link.npy\", \"actors\": []}\n");
            },
            "p.toml:6: stages.scenes.path: ",
        ),
        (
            "a 0x0 image",
            |d| write_npy(&d.join("frames/e00-00.npy"), "<f4", &[0, 0], &[]),
            "manifest.jsonl:1: image `frames/e00-00.npy`: an image of 0x0 pixels",
        ),
        (
            "a 0xN image",
            |d| write_npy(&d.join("frames/e00-00.npy"), "<f4", &[0, COLS], &[]),
            "manifest.jsonl:1: image `frames/e00-00.npy`: an image of 0x30 pixels",
        ),
        (
            "a shape whose size overflows",
            |d| write_npy(&d.join("frames/e00-01.npy"), "<f4", &[1 << 62, 8], &[]),
            "recording/frames/e00-01.npy: its header's shape [4611686018427387904, 8] is larger than any file",
        ),
        ("a malformed line", |d| append(d, "{\"image\": \"frames/e00-00.npy\", \"actors\": [}\n"), "recording/manifest.jsonl:37: "),
        (
            "a missing image",
            |d| append(d, "{\"image\": \"frames/gone.npy\", \"actors\": []}\n"),
            "manifest.jsonl:37: image `frames/gone.npy`: no such file",
        ),
        ("a wrong dtype", |d| write_npy(&d.join("frames/e00-00.npy"), "<f8", &[ROWS, COLS], &[0; ROWS * COLS * 8]), "<f4 (float32)"),
        (
            "a wrong shape",
            |d| write_npy(&d.join("frames/e00-01.npy"), "<f4", &[ROWS, COLS, 2], &[0; ROWS * COLS * 8]),
            "shape [20, 30, 2]; valid: a 2-D array",
        ),
        (
            "inconsistent sizes",
            |d| write_npy(&d.join("frames/e01-00.npy"), "<f4", &[ROWS, COLS + 1], &f32_bytes(&vec![1.0; ROWS * (COLS + 1)])),
            "manifest.jsonl:4: image `frames/e01-00.npy` is 20x31, but `frames/e00-00.npy` (the first frame's) is 20x30",
        ),
        (
            "a NaN",
            |d| {
                write_npy(
                    &d.join("frames/e05-01.npy"),
                    "<f4",
                    &[ROWS, COLS],
                    &f32_bytes(&[vec![1.0; 31], vec![f32::NAN], vec![1.0; ROWS * COLS - 32]].concat()),
                )
            },
            "manifest.jsonl:17: image `frames/e05-01.npy` holds NaN at row 1, column 1",
        ),
        (
            "an unknown class",
            |d| {
                append(
                    d,
                    "{\"image\": \"frames/e00-00.npy\", \"actors\": [{\"class\": \"bus\", \"x\": 1, \"y\": 0, \"heading\": 0, \"length\": 4, \"width\": 2}]}\n",
                )
            },
            "actor 0: unknown class `bus`; valid: car, truck, walker, sign:<name>",
        ),
    ];
    for (what, spoil, expected) in cases {
        let dir = new_recording("import-bad", IMPORT_AND_LABELS);
        spoil(&dir.join("recording"));
        let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
        assert!(!ok && out.contains(expected), "{what}: expected `{expected}` in {out}");
        assert!(!out.contains("panicked"), "{what}: {out}");
        if let Some(store) = rlmflow_cache::Store::open_existing(&dir.join(".rlmflow")).unwrap() {
            assert!(store.record_keys().unwrap().is_empty(), "{what}: no record");
            assert!(artifacts(&dir.join(".rlmflow/objects"), "scenes.json").is_empty(), "{what}: no Scenes artifact");
        }
    }
    // A manifest named outside the recording is a settings error, before anything is read.
    for (manifest, problem) in [("/etc/passwd", "is an absolute path, outside the recording"), ("../p.toml", "climbs out of the recording with `..`")]
    {
        let dir = new_recording("import-bad", &IMPORT_AND_LABELS.replace("image = 32", &format!("image = 32\nmanifest = \"{manifest}\"")));
        let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
        assert!(!ok && out.contains(&format!("stages.scenes.manifest: `{manifest}` {problem}")), "{out}");
        assert!(!dir.join(".rlmflow").exists(), "nothing ran");
    }
    // A span the azimuths cannot have is a settings error, before anything runs.
    let dir = new_recording("import-bad", &IMPORT_AND_LABELS.replace("image = 32", "image = 32\naxes = { azimuth_span_deg = 400.0 }"));
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(!ok && out.contains("stages.scenes.axes.azimuth_span_deg: must be in (0, 360]"), "{out}");
    assert!(!dir.join(".rlmflow").exists(), "nothing ran");
}

fn append(recording: &Path, line: &str) {
    let path = recording.join("manifest.jsonl");
    let text = std::fs::read_to_string(&path).unwrap() + line;
    std::fs::write(path, text).unwrap();
}
