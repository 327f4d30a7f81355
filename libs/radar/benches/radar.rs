//! `cargo bench -p rlmflow-radar --bench radar`: frames per second for four radars rendered
//! into one 224 x 224 image, on every core, fast and exact paths; the fast path's target is
//! 150 frames/s on 2 cores.

use std::time::Instant;

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rlmflow_radar::{ImageMap, Path, RadarConfig, Segment, VehicleBox, View};

/// A busy highway frame: twelve vehicles on four lanes, two road edges.
fn scene(seed: u64) -> (Vec<VehicleBox>, Vec<Segment>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let vehicles = (0..12)
        .map(|i| VehicleBox {
            x: rng.random_range(-38.0..38.0),
            y: [-3.5, 0.0, 3.5, 7.0][i % 4],
            heading: if i % 4 == 3 { std::f64::consts::PI } else { 0.0 },
            length: 4.6,
            width: 1.8,
        })
        .filter(|v| v.x.abs() > 4.0 || v.y != 0.0)
        .collect();
    let edges = vec![Segment { a: (-50.0, -5.25), b: (50.0, -5.25) }, Segment { a: (-50.0, 8.75), b: (50.0, 8.75) }];
    (vehicles, edges)
}

fn frames_per_second(map: &ImageMap, path: Path, frames: u64) -> f64 {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get()) as u64;
    let t0 = Instant::now();
    std::thread::scope(|s| {
        for t in 0..threads {
            s.spawn(move || {
                for f in (t..frames).step_by(threads as usize) {
                    let (v, e) = scene(f);
                    std::hint::black_box(map.render(&v, &e, path, &mut ChaCha8Rng::seed_from_u64(f)));
                }
            });
        }
    });
    frames as f64 / t0.elapsed().as_secs_f64()
}

fn main() {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    for image in [64, 224] {
        let map = ImageMap::new(&RadarConfig { image, ..RadarConfig::default() }, View::RangeAzimuth);
        let fast = frames_per_second(&map, Path::Fast, 400);
        let exact = frames_per_second(&map, Path::Exact, 8);
        let target = if image == 224 { format!("  target 150 frames/s: {:.2}x", fast / 150.0) } else { String::new() };
        println!(
            "{image}x{image}, 4 radars, {cores} cores: fast {fast:8.1} frames/s   exact {exact:6.2} frames/s   fast/exact {:.0}x{target}",
            fast / exact
        );
    }
}
