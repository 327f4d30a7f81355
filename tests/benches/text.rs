//! `cargo bench -p rlmflow-e2e --bench text`: the text half of the pipeline on a corpus of
//! procedural scenes. `import` frames/s of those scenes, from their MCAP and from a manifest of
//! `.npy` images, and of each published dataset's reader on its fixture (RADIATE, CRUW,
//! CARRADA, at 64 px); labels frames/s and template captions/s on one core; parser captions/s on
//! one core against its target (>= 50,000, printed as a ratio; above 1.00 meets it); BPE
//! training plus tokenisation captions/s on one core and on every core.

use std::path::{Path, PathBuf};
use std::time::Instant;

use rlmflow_captions::{Template, TemplateSettings};
use rlmflow_labels::{EgoGrid, EgoGridSettings};
use rlmflow_radar::RadarConfig;
use rlmflow_scenes::{Axes, Format, Import, ImportSettings, Layout, Power, Procedural, ProceduralSettings};
use rlmflow_stages::captions::Captions;
use rlmflow_stages::{Context, Operator};
use rlmflow_tokens::{Bpe, BpeSettings};

const FRAMES: u64 = 2000;
const PARSER_TARGET: f64 = 50_000.0;

fn scratch(root: &Path, name: &str) -> (PathBuf, PathBuf) {
    let (out, ckpt) = (root.join(name), root.join(format!("{name}-ckpt")));
    std::fs::create_dir_all(&out).unwrap();
    std::fs::create_dir_all(&ckpt).unwrap();
    (out, ckpt)
}

/// Runs `op` as stage `name` reading `inputs`; returns the output directory and the seconds taken.
fn stage<O: Operator>(root: &Path, name: &str, op: &O, s: &O::Settings, inputs: &[(&str, &Path)], threads: usize) -> (PathBuf, f64) {
    let (out, ckpt) = scratch(root, name);
    let mut ctx = Context::standalone(name, inputs, &out, &ckpt, 1, threads);
    let t0 = Instant::now();
    op.run(s, &mut ctx).unwrap();
    (out, t0.elapsed().as_secs_f64())
}

/// A directory holding the scenes' MCAP file alone, as a recording to import.
fn mcap_recording(root: &Path, scenes: &Path, image: usize) -> PathBuf {
    let dir = root.join(format!("mcap-recording-{image}"));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(scenes.join(rlmflow_stages::scenes::MCAP), dir.join("drive.mcap")).unwrap();
    dir
}

/// The scenes as a manifest recording: each image a uint8 `.npy` kept as given, each actor with
/// its pixel.
fn manifest_recording(root: &Path, scenes: &Path, image: usize) -> PathBuf {
    use rlmflow_stages::npy::{Dtype, NpyWriter};
    let dir = root.join(format!("manifest-recording-{image}"));
    std::fs::create_dir_all(&dir).unwrap();
    let scenes = rlmflow_stages::scenes::Scenes::open(scenes).unwrap();
    let mut manifest = String::new();
    for i in 0..scenes.len() {
        let mut npy = NpyWriter::create(&dir.join(format!("{i:06}.npy")), Dtype::U8, image, &[image]).unwrap();
        scenes.heatmap(i).unwrap().chunks(image).for_each(|row| npy.write_u8(row).unwrap());
        npy.finish().unwrap();
        let frame = scenes.frame(i).unwrap();
        let actors: Vec<serde_json::Value> = frame
            .actors
            .iter()
            .map(|a| serde_json::json!({"class": a.class, "x": a.x, "y": a.y, "heading": a.heading, "length": a.length, "width": a.width, "row": a.row, "col": a.col}))
            .collect();
        manifest += &format!("{}\n", serde_json::json!({"image": format!("{i:06}.npy"), "actors": actors}));
    }
    std::fs::write(dir.join("manifest.jsonl"), manifest).unwrap();
    dir
}

fn main() {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let root = std::env::temp_dir().join(format!("rlmflow-bench-text-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    println!("text stages on {FRAMES} procedural frames ({cores} cores here):");
    let mut captions_dir = PathBuf::new();
    for image in [64, 224] {
        let scenes = ProceduralSettings {
            frames: FRAMES,
            max_vehicles: 20,
            radar: RadarConfig { image, ..RadarConfig::default() },
            ..ProceduralSettings::default()
        };
        let (scenes_dir, _) = stage(&root, &format!("scenes-{image}"), &Procedural, &scenes, &[], cores);
        for (from, recording) in [("MCAP", mcap_recording(&root, &scenes_dir, image)), ("manifest", manifest_recording(&root, &scenes_dir, image))] {
            // The manifest's images are kept as given, so the actors keep their pixels.
            let axes = Axes { layout: Layout::AsGiven, power: Power::Normalised, ..Axes::default() };
            let settings = ImportSettings { path: format!("{from}-{image}"), image: 0, axes, ..ImportSettings::default() };
            let (_, t) = stage(&root, &format!("import-{from}-{image}"), &Import, &settings, &[("path", &recording)], 1);
            println!("  import from {from:8}, {image:3} px, one core     {:>10.0} frames/s", FRAMES as f64 / t);
        }
        let (labels_dir, t) = stage(&root, &format!("labels-{image}"), &EgoGrid, &EgoGridSettings::default(), &[("scenes", &scenes_dir)], 1);
        println!("  labels (ego-grid), {image:3} px masks, one core   {:>10.0} frames/s", FRAMES as f64 / t);
        let (dir, t) = stage(&root, &format!("captions-{image}"), &Template, &TemplateSettings::default(), &[("labels", &labels_dir)], 1);
        if image == 64 {
            println!("  captions (template, 5 per frame), one core  {:>10.0} captions/s", 5.0 * FRAMES as f64 / t);
            captions_dir = dir;
        }
    }

    let captions = Captions::open(&captions_dir).unwrap();
    let texts: Vec<&str> = captions.captions.iter().map(|c| c.caption.as_str()).collect();
    let mut best = f64::MAX;
    for _ in 0..3 {
        let t0 = Instant::now();
        let vehicles: u32 = texts.iter().map(|t| rlmflow_parser::parse(t).grid.vehicles()).sum();
        best = best.min(t0.elapsed().as_secs_f64());
        assert!(vehicles > 0);
    }
    let rate = texts.len() as f64 / best;
    let words = texts.iter().map(|t| t.split_whitespace().count()).sum::<usize>() as f64 / texts.len() as f64;
    println!(
        "  parser, {words:.0}-word captions, one core        {rate:>10.0} captions/s  target {PARSER_TARGET}: {:.2}x ({})",
        rate / PARSER_TARGET,
        if rate >= PARSER_TARGET { "meets" } else { "MISSES" }
    );

    // Each dataset reader on its fixture: 4 sequences of 50 frames.
    let names = ["seq_0", "seq_1", "seq_2", "seq_3"];
    let datasets: [(&str, Format, rlmflow_test_support::datasets::WriteSized); 3] = [
        ("RADIATE", Format::Radiate, rlmflow_test_support::datasets::write_radiate_sized),
        ("CRUW", Format::Cruw, rlmflow_test_support::datasets::write_cruw_sized),
        ("CARRADA", Format::Carrada, rlmflow_test_support::datasets::write_carrada_sized),
    ];
    for (name, format, write) in datasets {
        let data = root.join(format!("dataset-{name}"));
        let frames = write(&data, &names, 50).len();
        let settings = ImportSettings { path: name.to_lowercase(), format, image: 64, ..ImportSettings::default() };
        let (_, t) = stage(&root, &format!("import-{name}"), &Import, &settings, &[("path", &data)], 1);
        println!("  import from {name:8},  64 px, one core     {:>10.0} frames/s", frames as f64 / t);
    }

    for threads in [1, cores] {
        let s = BpeSettings::default();
        let (_, t) = stage(&root, &format!("tokens-{threads}"), &Bpe, &s, &[("captions", &captions_dir)], threads);
        println!("  tokens (bpe {} vocab: train + encode), {threads} core(s) {:>8.0} captions/s", s.vocab, texts.len() as f64 / t);
    }
    std::fs::remove_dir_all(&root).unwrap();
}
