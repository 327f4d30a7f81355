//! The `procedural` operator: vehicles placed (no dynamics) on sampled road layouts, aimed at
//! the 48 grid cells with a configurable target distribution, rendered by the radar model.

use std::collections::BTreeMap;

use anyhow::Context as _;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rlmflow_radar::{RadarConfig, VehicleBox};
use rlmflow_stages::grid::{CELLS, Cell, GridRule, SECTORS};
use rlmflow_stages::{Context, InputOutlines, Items, Operator, OperatorSpec, Outcome, Outline, Resources, SettingError, Settings, Sharding};
use serde::{Deserialize, Serialize};

use crate::layout::{LAYOUTS, Layout};
use crate::render::{MAX_FRAMES, Rendered, Renderer, Scene, Vehicle, check_views, parallel_map, weighted};
use crate::writer::SceneWriter;

pub struct Procedural;

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ProceduralSettings {
    /// Frames written, 1..=10,000,000.
    pub frames: u64,
    /// Where in the endless sequence of frames this seed defines the first written one lies:
    /// frame `k` of the output is frame `first_frame + k` of the sequence (frames are numbered
    /// from 0 in the output). A shard of a sharded stage is a range of the whole stage's frames.
    pub first_frame: u64,
    /// Road layouts to draw from, uniformly: straight, two-way, junction.
    pub layouts: Vec<String>,
    pub min_vehicles: usize,
    /// At most 20, the paper's filter.
    pub max_vehicles: usize,
    pub truck_fraction: f64,
    /// Relative weight of each distance bin when aiming a vehicle at a cell.
    pub bin_weights: [f64; 4],
    /// Relative weight of each sector (by key; missing sectors weigh 1).
    pub sector_weights: BTreeMap<String, f64>,
    pub radar: RadarConfig,
    /// Radar views written per frame (`range-azimuth`, `bev`, `radar-front`, ...); actor pixels
    /// are recorded in the first.
    pub images: Vec<String>,
    /// Render through the exact ADC-cube path instead of the fast one (much slower).
    pub exact: bool,
    /// Frames per checkpointed batch, 1..=4,096, held in memory (does not change the result).
    pub batch: u64,
}

impl Default for ProceduralSettings {
    fn default() -> Self {
        ProceduralSettings {
            frames: 200,
            first_frame: 0,
            layouts: LAYOUTS.iter().map(|s| s.to_string()).collect(),
            min_vehicles: 2,
            max_vehicles: 12,
            truck_fraction: 0.15,
            bin_weights: [1.0; 4],
            sector_weights: BTreeMap::new(),
            radar: RadarConfig::default(),
            images: vec!["range-azimuth".into()],
            exact: false,
            batch: 64,
        }
    }
}

impl Settings for ProceduralSettings {
    const NON_RESULT: &'static [&'static str] = &["batch"];

    fn check(&self) -> Result<(), SettingError> {
        let err = |k: &str, m: String| Err(SettingError::new(k, m));
        SettingError::check_range("frames", self.frames, 1..=MAX_FRAMES)?;
        SettingError::check_range("first_frame", self.first_frame, 0..=MAX_FRAMES)?;
        if self.layouts.is_empty() {
            return err("layouts", format!("must name at least one of {}", LAYOUTS.join(", ")));
        }
        for l in &self.layouts {
            if !LAYOUTS.contains(&l.as_str()) {
                let mut e = SettingError::new("layouts", format!("unknown layout `{l}`; valid: {}", LAYOUTS.join(", ")));
                e.valid = vec![];
                return Err(e);
            }
        }
        if self.max_vehicles > 20 {
            return err(
                "max_vehicles",
                format!("must be at most 20 (scenes over 20 vehicles are dropped, as in the paper), not {}", self.max_vehicles),
            );
        }
        if self.min_vehicles > self.max_vehicles {
            return err("min_vehicles", format!("must not exceed max_vehicles ({})", self.max_vehicles));
        }
        if !(0.0..=1.0).contains(&self.truck_fraction) {
            return err("truck_fraction", "must be in [0, 1]".into());
        }
        if self.bin_weights.iter().any(|w| !(0.0..=1e6).contains(w)) || self.bin_weights.iter().sum::<f64>() <= 0.0 {
            return err("bin_weights", "must be in 0..=1e6 each, with a positive sum".into());
        }
        for (k, w) in &self.sector_weights {
            if !SECTORS.contains(&k.as_str()) {
                let mut e = SettingError::new(format!("sector_weights.{k}"), format!("unknown sector `{k}`"));
                e.valid = SECTORS.iter().map(|s| s.to_string()).collect();
                return Err(e);
            }
            SettingError::check_range(&format!("sector_weights.{k}"), *w, 0.0..=1e6)?;
        }
        SettingError::check_range("batch", self.batch, 1..=4_096)?;
        check_views(&self.images)?;
        self.radar.check().map_err(|(k, m)| SettingError::new(format!("radar.{k}"), m))
    }
}

impl ProceduralSettings {
    fn renderer(&self) -> Renderer {
        Renderer::new(&self.radar, &check_views(&self.images).expect("settings were checked"), self.exact)
    }

    fn cell_weights(&self) -> Vec<f64> {
        (0..CELLS)
            .map(|i| {
                let c = Cell::from_index(i);
                self.bin_weights[c.bin] * self.sector_weights.get(SECTORS[c.sector]).copied().unwrap_or(1.0)
            })
            .collect()
    }
}

impl Operator for Procedural {
    type Settings = ProceduralSettings;

    fn spec(&self) -> OperatorSpec {
        OperatorSpec {
            name: "procedural",
            kind: "scenes",
            version: 6,
            inputs: None,
            summary: "vehicles placed on sampled road layouts to cover every grid cell, rendered by the radar model",
        }
    }

    fn resources(&self, _: &ProceduralSettings) -> Resources {
        Resources { threads: usize::MAX, ..Resources::default() }
    }

    /// A shard is a range of frames; `concat` joins consecutive ranges into the whole's bytes.
    fn sharding(&self) -> Option<Sharding<ProceduralSettings>> {
        Some(Sharding {
            unit: "frames",
            items: Items::Counted {
                count: |s| s.frames,
                part: |s, range| ProceduralSettings { first_frame: s.first_frame + range.start, frames: range.end - range.start, ..s.clone() },
            },
            merge: "concat",
        })
    }

    fn outline(&self, s: &ProceduralSettings, _: &InputOutlines) -> Result<Outline, SettingError> {
        // Placed frames belong to no sequence: each is its own split group.
        Ok(Outline { image: Some(s.radar.image as u64), frames: Some(s.frames), groups: Some(s.frames), ..Outline::default() })
    }

    fn run(&self, s: &ProceduralSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let renderer = s.renderer();
        let mut writer = SceneWriter::resume(&ctx.checkpoint_dir, renderer.images()).context("opening the checkpoint")?;
        let progress = ctx.progress(s.frames, "frames");
        progress.set_position(writer.done());
        let weights = s.cell_weights();

        while writer.done() < s.frames {
            let start = writer.done();
            let end = (start + s.batch).min(s.frames);
            let indices: Vec<u64> = (start..end).collect();
            let batch = parallel_map(&indices, ctx.threads, |&i| frame(s, &renderer, &weights, ctx.seed, i));
            writer.append(&batch)?;
            progress.set_position(writer.done());
        }
        progress.finish();
        let summary = writer.finish(&ctx.output_dir, s.radar.range_max_m, s.result_settings())?;
        let (covered, vehicles) = (summary.cells_covered(), summary.vehicles());
        Ok(Outcome {
            metrics: serde_json::json!({"frames": summary.frames, "vehicles": vehicles, "cells_covered": covered, "frames_per_scenario": summary.frames_per_scenario}),
            summary: format!("{} frames, {vehicles} vehicles, {covered}/{CELLS} cells covered", summary.frames),
        })
    }
}

/// Output frame `index`: deterministic in (seed, `first_frame + index`) whatever the batch,
/// thread or shard split.
fn frame(s: &ProceduralSettings, renderer: &Renderer, weights: &[f64], seed: u64, index: u64) -> Rendered {
    let global = s.first_frame + index;
    let mut rng = ChaCha8Rng::seed_from_u64(rlmflow_stages::item_seed(seed, global));
    let chosen = &s.layouts[rng.random_range(0..s.layouts.len())];
    let kind = LAYOUTS.iter().find(|l| *l == chosen).expect("layouts were checked against LAYOUTS");
    let layout = Layout::sample(kind, &mut rng);
    let rule = GridRule::default();
    let wanted = rng.random_range(s.min_vehicles..=s.max_vehicles);
    let mut placed: Vec<VehicleBox> = Vec::new();
    let mut vehicles = Vec::new();
    let mut attempts = 0;
    while placed.len() < wanted && attempts < wanted * 8 {
        attempts += 1;
        let truck = rng.random_bool(s.truck_fraction);
        let size = if truck { (rng.random_range(8.0..12.0), 2.5) } else { (rng.random_range(4.0..5.0), rng.random_range(1.7..1.9)) };
        let target = Cell::from_index(weighted(weights, &mut rng));
        if let Some((body, lane_heading)) = layout.place(target, size, &rule, &placed, &mut rng) {
            placed.push(body);
            let speed = if body.heading.cos().abs() > 0.5 { rng.random_range(15.0..30.0) } else { rng.random_range(5.0..15.0) };
            vehicles.push(Vehicle {
                id: placed.len() as u32,
                class: if truck { "truck" } else { "car" },
                body,
                speed,
                lane_heading: Some(lane_heading),
            });
        }
    }
    renderer.render(index, &Scene { scenario: kind.to_string(), vehicles, edges: layout.edges }, &mut rng)
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use rlmflow_stages::DynOperator;
    use rlmflow_stages::scenes::Scenes;

    use super::*;

    fn dirs(name: &str) -> (PathBuf, PathBuf) {
        let root = std::env::temp_dir().join(format!("rlmflow-procedural-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let (out, ckpt) = (root.join("out"), root.join("ckpt"));
        std::fs::create_dir_all(&out).unwrap();
        std::fs::create_dir_all(&ckpt).unwrap();
        (out, ckpt)
    }

    fn run(s: &ProceduralSettings, name: &str, threads: usize, prefill: Option<u64>) -> Vec<u8> {
        let (out, ckpt) = dirs(name);
        if let Some(n) = prefill {
            // A previous attempt recorded `n` frames, then was killed while writing the next
            // batch (extra bytes past the recorded count).
            let renderer = s.renderer();
            let mut writer = SceneWriter::resume(&ckpt, renderer.images()).unwrap();
            let frames: Vec<_> = (0..n).map(|i| frame(s, &renderer, &s.cell_weights(), 7, i)).collect();
            writer.append(&frames).unwrap();
            let side = s.radar.image as u64;
            std::fs::OpenOptions::new().append(true).open(ckpt.join("image-0.u8.part")).unwrap().set_len(n * side * side + 100).unwrap();
        }
        let mut ctx = Context::standalone("scenes", &[], &out, &ckpt, 7, threads);
        Operator::run(&Procedural, s, &mut ctx).unwrap();
        std::fs::read(out.join("scenes.mcap")).unwrap()
    }

    fn small() -> ProceduralSettings {
        ProceduralSettings { frames: 24, batch: 8, radar: RadarConfig { image: 32, ..RadarConfig::default() }, ..ProceduralSettings::default() }
    }

    #[test]
    fn output_depends_on_seed_and_settings_only_not_on_batches_threads_or_resumes() {
        let reference = run(&small(), "ref", 1, None);
        assert_eq!(reference, run(&ProceduralSettings { batch: 5, ..small() }, "batch", 2, None));
        assert_eq!(reference, run(&small(), "resume", 2, Some(8)));
        assert_ne!(reference, run(&ProceduralSettings { truck_fraction: 0.9, ..small() }, "other", 1, None));
    }

    #[test]
    fn the_artifact_reads_back_with_actor_pixels_and_statistics() {
        let (out, ckpt) = dirs("read");
        let s = ProceduralSettings { images: vec!["range-azimuth".into(), "bev".into(), "radar-left".into()], ..small() };
        let mut ctx = Context::standalone("scenes", &[], &out, &ckpt, 3, 2);
        let outcome = Operator::run(&Procedural, &s, &mut ctx).unwrap();
        let scenes = Scenes::open(&out).unwrap();
        let frames = scenes.frames().unwrap();
        assert_eq!(frames.len(), 24);
        assert_eq!(scenes.summary.frames, 24);
        assert_eq!(scenes.summary.vehicles_per_scene.iter().sum::<u64>(), 24);
        let vehicles: usize = frames.iter().map(|f| f.actors.len()).sum();
        assert_eq!(scenes.summary.cells.values().sum::<u64>() as usize, vehicles, "every placed vehicle is within 40 m");
        assert_eq!(outcome.metrics["vehicles"], vehicles);
        for f in &frames {
            assert!((s.min_vehicles..=s.max_vehicles).contains(&f.actors.len()) || f.actors.len() < s.min_vehicles);
            for a in &f.actors {
                assert!((a.lane_heading.unwrap() - a.heading).abs() <= 0.08, "{a:?}");
                assert!(a.row >= 0.0 && a.row < 32.0 * 40.0 / 44.0 + 1.0 && (0.0..32.0).contains(&a.col), "{a:?}");
            }
        }
        let topics: Vec<&str> = scenes.summary.images.iter().map(|i| i.topic.as_str()).collect();
        assert_eq!(topics, ["/radar/range-azimuth", "/radar/bev", "/radar/radar-left"]);
        // Random access by frame through the index equals what the renderer made.
        let renderer = s.renderer();
        for i in [0, 13, 23] {
            let (frame, images) = frame(&s, &renderer, &s.cell_weights(), 3, i);
            assert_eq!(scenes.frame(i).unwrap(), frame);
            for (k, image) in images.iter().enumerate() {
                assert_eq!(&scenes.image(k, i).unwrap(), image, "frame {i} image {k}");
            }
        }
        assert_eq!(scenes.heatmap(23).unwrap().len(), 32 * 32);
        assert!(scenes.heatmap(24).is_err());
        assert!(scenes.image(3, 0).is_err());
    }

    #[test]
    fn impossible_settings_name_their_key() {
        let check = |v: serde_json::Value| Procedural.settings(v).unwrap_err();
        assert_eq!(check(serde_json::json!({"max_vehicles": 21})).key, "max_vehicles");
        assert_eq!(check(serde_json::json!({"layouts": ["highway"]})).message, "unknown layout `highway`; valid: straight, two-way, junction");
        assert_eq!(check(serde_json::json!({"sector_weights": {"left_lane": 2.0}})).key, "sector_weights.left_lane");
        assert_eq!(check(serde_json::json!({"radar": {"range_max_m": 60.0}})).key, "radar.range_max_m");
        assert_eq!(check(serde_json::json!({"radar": {"imag": 64}})).key, "radar.imag");
        assert_eq!(
            check(serde_json::json!({"images": ["polar"]})).message,
            "unknown view `polar`; valid: range-azimuth, bev, radar-front, radar-left, radar-back, radar-right"
        );
        assert_eq!(check(serde_json::json!({"images": ["bev", "bev"]})).message, "`bev` is listed twice");
    }
}
