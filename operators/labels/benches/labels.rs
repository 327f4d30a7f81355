//! `cargo bench -p rlmflow-labels --bench labels`: the labels stage's frames/s on one core (read
//! the frame, grid, mask, write), for procedural scenes at 64 and 224 px.

use std::path::PathBuf;
use std::time::Instant;

use rlmflow_labels::{EgoGrid, EgoGridSettings};
use rlmflow_radar::RadarConfig;
use rlmflow_scenes::{Procedural, ProceduralSettings};
use rlmflow_stages::{Context, Operator};

fn scratch(name: &str) -> PathBuf {
    let root = std::env::temp_dir().join(format!("rlmflow-bench-labels-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    for d in ["scenes", "scenes-ckpt", "out", "ckpt"] {
        std::fs::create_dir_all(root.join(d)).unwrap();
    }
    root
}

fn main() {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    println!("labels stage (ego-grid), one core, frames/s:");
    for image in [64, 224] {
        let root = scratch(&image.to_string());
        let scenes = ProceduralSettings {
            frames: 2000,
            max_vehicles: 20,
            radar: RadarConfig { image, ..RadarConfig::default() },
            ..ProceduralSettings::default()
        };
        Procedural.run(&scenes, &mut Context::standalone("scenes", &[], &root.join("scenes"), &root.join("scenes-ckpt"), 1, cores)).unwrap();
        let mut ctx = Context::standalone("labels", &[("scenes", &root.join("scenes"))], &root.join("out"), &root.join("ckpt"), 1, 1);
        let t0 = Instant::now();
        EgoGrid.run(&EgoGridSettings::default(), &mut ctx).unwrap();
        println!("  {image:3} px  {:9.0}", scenes.frames as f64 / t0.elapsed().as_secs_f64());
        std::fs::remove_dir_all(&root).unwrap();
    }
}
