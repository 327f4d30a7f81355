//! `cargo bench -p rlmflow-scenes --bench scenes`: the scenes stage's frames/s per highway-env
//! scenario (simulator, ego choice, radar and MCAP included) and for the procedural operator,
//! on every core; then MCAP write and random-read throughput for 224 x 224 frames.

use std::path::PathBuf;
use std::time::Instant;

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rlmflow_radar::RadarConfig;
use rlmflow_scenes::{HighwayEnv, HighwaySettings, Procedural, ProceduralSettings, ScenarioMix, SceneWriter};
use rlmflow_stages::scenes::{Actor, Frame, Image, Scenes};
use rlmflow_stages::{Context, Operator};

fn scratch(name: &str) -> (PathBuf, PathBuf) {
    let root = std::env::temp_dir().join(format!("rlmflow-bench-scenes-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let (out, ckpt) = (root.join("out"), root.join("ckpt"));
    std::fs::create_dir_all(&out).unwrap();
    std::fs::create_dir_all(&ckpt).unwrap();
    (out, ckpt)
}

fn context(name: &str, threads: usize) -> Context {
    let (out, ckpt) = scratch(name);
    Context::standalone("scenes", &[], &out, &ckpt, 1, threads)
}

fn main() {
    rlmflow_python::embed::pin_home();
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let env = rlmflow_python::ensure(&mut |note| eprintln!("{note}")).unwrap();
    rlmflow_python::embed::start(&env).unwrap();
    println!("scenes stage, {cores} cores, frames/s (simulator + ego choice + 4 radars + MCAP):");
    for image in [64, 224] {
        let radar = RadarConfig { image, ..RadarConfig::default() };
        for scenario in rlmflow_scenes::SCENARIOS {
            let s = HighwaySettings {
                frames: 60,
                episode_frames: 30,
                scenarios: [(scenario.to_string(), ScenarioMix::default())].into(),
                radar: radar.clone(),
                ..HighwaySettings::default()
            };
            let t0 = Instant::now();
            HighwayEnv.run(&s, &mut context(scenario, cores)).unwrap();
            println!("  {image:3} px  highway-env {scenario:13} {:7.1}", s.frames as f64 / t0.elapsed().as_secs_f64());
        }
        let s = ProceduralSettings { frames: 400, radar, ..ProceduralSettings::default() };
        let t0 = Instant::now();
        Procedural.run(&s, &mut context("procedural", cores)).unwrap();
        println!("  {image:3} px  procedural              {:7.1}", s.frames as f64 / t0.elapsed().as_secs_f64());
    }
    mcap_throughput(2000, 224);
}

/// Writes `frames` synthetic frames through the Scenes writer, then reads random frames back.
fn mcap_throughput(frames: u64, size: usize) {
    let (out, ckpt) = scratch("mcap");
    let image = Image { view: "range-azimuth".into(), topic: "/radar/range-azimuth".into(), size };
    let mut writer = SceneWriter::resume(&ckpt, vec![image]).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let actor = Actor {
        id: 1,
        class: "car".into(),
        x: 10.0,
        y: 3.5,
        heading: 0.0,
        length: 4.5,
        width: 1.8,
        speed: 20.0,
        lane_heading: Some(0.0),
        row: 10.0,
        col: 100.0,
    };
    for start in (0..frames).step_by(100) {
        let batch: Vec<_> = (start..(start + 100).min(frames))
            .map(|i| {
                let pixels: Vec<u8> = (0..size * size).map(|_| rng.random()).collect();
                (
                    Frame { index: i, id: String::new(), episode: None, scenario: "bench".into(), actors: vec![actor.clone(); 8], grid: None },
                    vec![pixels],
                )
            })
            .collect();
        writer.append(&batch).unwrap();
    }
    let t0 = Instant::now();
    writer.finish(&out, 44.0, serde_json::Value::Null).unwrap();
    let write = t0.elapsed().as_secs_f64();
    let bytes = std::fs::metadata(out.join("scenes.mcap")).unwrap().len() as f64;
    let scenes = Scenes::open(&out).unwrap();
    let reads = 5000;
    let t0 = Instant::now();
    for _ in 0..reads {
        let i = rng.random_range(0..frames);
        std::hint::black_box(scenes.heatmap(i).unwrap());
        std::hint::black_box(scenes.frame(i).unwrap());
    }
    let read = t0.elapsed().as_secs_f64();
    println!(
        "MCAP, {frames} frames of {size}x{size}: write {:.0} MB/s ({:.0} frames/s); random read (image + actors) {:.0} frames/s, {:.0} MB/s",
        bytes / write / 1e6,
        frames as f64 / write,
        reads as f64 / read,
        reads as f64 * (size * size) as f64 / read / 1e6
    );
}
