//! The `highway-env` operator: traffic from highway-env (embedded Python), the ego chosen per
//! frame among all vehicles, rendered by the radar model in Rust threads.
//!
//! Frames come in episodes: a scenario drawn by `share`, simulated from a seed, `warmup_steps`
//! steps, then a frame every `steps_per_frame` steps. Every frame of an episode carries the
//! episode's id (its first frame's identity), so the split keeps an episode whole. The GIL is held only while stepping and
//! reading the state; a finished episode's frames are rendered on every granted thread. An
//! episode is the checkpoint unit, so a killed run resumes at the next episode and reproduces
//! exactly what an uninterrupted run would have written.
//!
//! Ego choice (`balance_cells`): each frame takes as ego the vehicle whose neighbours fall in the
//! grid cells seen least so far (ties broken at random), which spreads the 48 distance-sector
//! cells; candidates with more than `max_vehicles` vehicles in range are skipped, and a frame
//! with no candidate is dropped (the paper's filter).

use std::collections::BTreeMap;

use anyhow::{Context as _, bail};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rlmflow_python::embed::{self, pyo3};
use rlmflow_radar::{RadarConfig, Segment, VehicleBox};
use rlmflow_stages::grid::{CELLS, GridRule};
use rlmflow_stages::{Context, InputOutlines, Operator, OperatorSpec, Outcome, Outline, Resources, SettingError, Settings};
use serde::{Deserialize, Serialize};

use pyo3::prelude::*;

use crate::render::{MAX_FRAMES, Renderer, Scene, Vehicle, check_views, parallel_map, weighted};
use crate::writer::SceneWriter;

const HELPER: &str = include_str!("highway.py");
pub const SCENARIOS: [&str; 6] = ["highway", "merge", "roundabout", "intersection", "two-way", "divided"];
/// Columns of a state row (see highway.py).
const COLUMNS: usize = 9;

pub struct HighwayEnv;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ScenarioMix {
    /// Relative share of episodes.
    pub share: f64,
    /// Traffic density: 1 keeps the scenario's usual vehicle count on the road.
    pub density: f64,
}

impl Default for ScenarioMix {
    fn default() -> Self {
        ScenarioMix { share: 1.0, density: 1.0 }
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HighwaySettings {
    /// Frames written, 1..=10,000,000 (the paper generated 800,000).
    pub frames: u64,
    /// Scenarios to simulate, by name: highway, merge, roundabout, intersection, two-way
    /// (highway-env's two-way road, traffic added both ways), divided (a divided two-way
    /// highway built from the road network).
    pub scenarios: BTreeMap<String, ScenarioMix>,
    /// Simulation steps (15 Hz) between frames, 1..=1,000.
    pub steps_per_frame: u32,
    /// Frames per simulated episode, 1..=10,000 (an episode is held in memory).
    pub episode_frames: u32,
    /// Steps simulated before an episode's first frame, 0..=100,000.
    pub warmup_steps: u32,
    pub truck_fraction: f64,
    /// Frames with more vehicles in range are dropped (20, as the paper).
    pub max_vehicles: usize,
    /// Choose the ego per frame to balance the grid cells (else the environment's ego).
    pub balance_cells: bool,
    pub radar: RadarConfig,
    pub images: Vec<String>,
    pub exact: bool,
}

impl Default for HighwaySettings {
    fn default() -> Self {
        HighwaySettings {
            frames: 200,
            scenarios: SCENARIOS.iter().map(|s| (s.to_string(), ScenarioMix::default())).collect(),
            steps_per_frame: 5,
            episode_frames: 40,
            warmup_steps: 30,
            truck_fraction: 0.12,
            max_vehicles: 20,
            balance_cells: true,
            radar: RadarConfig::default(),
            images: vec!["range-azimuth".into()],
            exact: false,
        }
    }
}

impl Settings for HighwaySettings {
    fn check(&self) -> Result<(), SettingError> {
        let err = |k: &str, m: &str| Err(SettingError::new(k, m));
        SettingError::check_range("frames", self.frames, 1..=MAX_FRAMES)?;
        if self.scenarios.is_empty() {
            return err("scenarios", &format!("must name at least one of {}", SCENARIOS.join(", ")));
        }
        for (name, mix) in &self.scenarios {
            if !SCENARIOS.contains(&name.as_str()) {
                let mut e = SettingError::new(format!("scenarios.{name}"), format!("unknown scenario `{name}`"));
                e.valid = SCENARIOS.iter().map(|s| s.to_string()).collect();
                return Err(e);
            }
            SettingError::check_range(&format!("scenarios.{name}.share"), mix.share, 0.0..=1e6)?;
            if !(mix.density > 0.0 && mix.density <= 4.0) {
                return err(&format!("scenarios.{name}.density"), "must be in (0, 4]");
            }
        }
        if self.scenarios.values().map(|m| m.share).sum::<f64>() <= 0.0 {
            return err("scenarios", "the shares must have a positive sum");
        }
        SettingError::check_range("steps_per_frame", self.steps_per_frame, 1..=1_000)?;
        SettingError::check_range("episode_frames", self.episode_frames, 1..=10_000)?;
        SettingError::check_range("warmup_steps", self.warmup_steps, 0..=100_000)?;
        if !(0.0..=1.0).contains(&self.truck_fraction) {
            return err("truck_fraction", "must be in [0, 1]");
        }
        if !(1..=20).contains(&self.max_vehicles) {
            return err("max_vehicles", "must be in 1..=20 (scenes over 20 vehicles are dropped, as in the paper)");
        }
        check_views(&self.images)?;
        self.radar.check().map_err(|(k, m)| SettingError::new(format!("radar.{k}"), m))
    }
}

/// One simulated frame before rendering.
struct Snapshot {
    rows: Vec<[f64; COLUMNS]>,
}

impl Operator for HighwayEnv {
    type Settings = HighwaySettings;

    fn spec(&self) -> OperatorSpec {
        OperatorSpec {
            name: "highway-env",
            kind: "scenes",
            version: 7,
            inputs: None,
            summary: "traffic simulated by highway-env (highway, merge, roundabout, intersection, two-way, divided), rendered by the radar model",
        }
    }

    fn resources(&self, _: &HighwaySettings) -> Resources {
        Resources { threads: usize::MAX, ..Resources::default() }
    }

    fn outline(&self, s: &HighwaySettings, _: &InputOutlines) -> Result<Outline, SettingError> {
        let groups = s.frames.div_ceil(u64::from(s.episode_frames));
        Ok(Outline { image: Some(s.radar.image as u64), frames: Some(s.frames), groups: Some(groups), ..Outline::default() })
    }

    fn run(&self, s: &HighwaySettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let env = rlmflow_python::ensure(&mut |note| {
            ctx.event("python", serde_json::json!({ "note": note }));
            ctx.progress(0, note).set_position(0);
        })?;
        embed::start(&env)?;
        let renderer = Renderer::new(&s.radar, &check_views(&s.images).expect("settings were checked"), s.exact);
        let mut writer = SceneWriter::resume(&ctx.checkpoint_dir, renderer.images()).context("opening the checkpoint")?;
        let mut cursor: Cursor = serde_json::from_value(writer.cursor().clone()).unwrap_or_default();
        let progress = ctx.progress(s.frames, "frames");
        progress.set_position(writer.done());
        let names: Vec<&String> = s.scenarios.keys().collect();
        let shares: Vec<f64> = s.scenarios.values().map(|m| m.share).collect();
        let rule = GridRule::default();
        while writer.done() < s.frames {
            let episode = cursor.episodes;
            let mut rng = ChaCha8Rng::seed_from_u64(ctx.seed ^ episode.wrapping_mul(0xD1B5_4A32_D192_ED03));
            let scenario = names[weighted(&shares, &mut rng)];
            let snapshots = simulate(s, scenario, rng.random())?;
            // Choose egos in order (the balance depends on earlier frames), then render in parallel.
            let wanted = (s.frames - writer.done()) as usize;
            let mut scenes = Vec::new();
            for snap in &snapshots.frames {
                if scenes.len() == wanted {
                    break;
                }
                match choose_ego(s, &rule, scenario, snap, &snapshots.edges, &mut cursor.cells, &mut rng) {
                    Some(scene) => scenes.push((scene, rng.random::<u64>())),
                    None => cursor.dropped += 1,
                }
            }
            let start = writer.done();
            let numbered: Vec<(u64, Scene, u64)> = scenes.into_iter().enumerate().map(|(i, (scene, seed))| (start + i as u64, scene, seed)).collect();
            let mut batch =
                parallel_map(&numbered, ctx.threads, |(i, scene, seed)| renderer.render(*i, scene, &mut ChaCha8Rng::seed_from_u64(*seed)));
            // One episode, one split group: named by its first frame's identity.
            if let Some(first) = batch.first().map(|(frame, _)| frame.id.clone()) {
                for (frame, _) in &mut batch {
                    frame.episode = Some(first.clone());
                }
            }
            cursor.episodes += 1;
            writer.append_with_cursor(&batch, serde_json::to_value(&cursor)?)?;
            progress.set_position(writer.done());
        }
        progress.finish();
        let summary = writer.finish(&ctx.output_dir, s.radar.range_max_m, s.result_settings())?;
        let (covered, vehicles) = (summary.cells_covered(), summary.vehicles());
        let metrics = serde_json::json!({
            "frames": summary.frames, "vehicles": vehicles, "cells_covered": covered, "episodes": cursor.episodes,
            "dropped_frames": cursor.dropped, "frames_per_scenario": summary.frames_per_scenario, "cells": summary.cells,
        });
        Ok(Outcome {
            metrics,
            summary: format!(
                "{} frames from {} episodes ({} dropped), {covered}/{CELLS} cells covered",
                summary.frames, cursor.episodes, cursor.dropped
            ),
        })
    }
}

/// What the checkpoint records beyond the frames: episodes simulated, frames dropped, and the
/// cell counts the ego choice balances against.
#[derive(Default, Serialize, Deserialize)]
struct Cursor {
    episodes: u64,
    dropped: u64,
    cells: Vec<u64>,
}

struct Episode {
    frames: Vec<Snapshot>,
    edges: Vec<Segment>,
}

/// Runs one episode in the embedded interpreter (the GIL is held only here).
fn simulate(s: &HighwaySettings, scenario: &str, seed: u64) -> anyhow::Result<Episode> {
    Python::attach(|py| -> anyhow::Result<Episode> {
        let py_err = |e: PyErr| anyhow::anyhow!("highway-env ({scenario}): {}", embed::traceback(py, &e));
        let module = embed::module(py, "rlmflow_highway", HELPER)?;
        let mix = &s.scenarios[scenario];
        let sim = module.getattr("Simulation").and_then(|c| c.call1((scenario, seed, mix.density, s.truck_fraction))).map_err(py_err)?;
        let edges: Vec<f64> = floats(&sim.call_method0("edges").map_err(py_err)?)?;
        let edges = edges.chunks_exact(4).map(|e| Segment { a: (e[0], -e[1]), b: (e[2], -e[3]) }).collect();
        sim.call_method1("step", (s.warmup_steps,)).map_err(py_err)?;
        let mut frames = Vec::with_capacity(s.episode_frames as usize);
        for _ in 0..s.episode_frames {
            sim.call_method1("step", (s.steps_per_frame,)).map_err(py_err)?;
            let flat = floats(&sim.call_method0("state").map_err(py_err)?)?;
            frames.push(Snapshot { rows: flat.chunks_exact(COLUMNS).map(|r| r.try_into().expect("COLUMNS wide")).collect() });
        }
        Ok(Episode { frames, edges })
    })
}

/// A Python `bytes` of native f64s.
fn floats(value: &Bound<'_, PyAny>) -> anyhow::Result<Vec<f64>> {
    let bytes: &[u8] = value.extract().map_err(|e| anyhow::anyhow!("expected bytes from highway.py: {e}"))?;
    if !bytes.len().is_multiple_of(8) {
        bail!("highway.py returned {} bytes, not whole f64s", bytes.len());
    }
    Ok(bytes.chunks_exact(8).map(|b| f64::from_ne_bytes(b.try_into().expect("8 bytes"))).collect())
}

/// Row `r` in world coordinates with y flipped to the left (highway-env's y points down).
fn pose(r: &[f64; COLUMNS]) -> (f64, f64, f64) {
    (r[1], -r[2], -r[3])
}

/// The ego-frame box of `other` seen from `ego`.
fn relative(ego: &[f64; COLUMNS], other: &[f64; COLUMNS]) -> VehicleBox {
    let (ex, ey, eh) = pose(ego);
    let (ox, oy, oh) = pose(other);
    let (sin, cos) = eh.sin_cos();
    let (dx, dy) = (ox - ex, oy - ey);
    VehicleBox { x: dx * cos + dy * sin, y: -dx * sin + dy * cos, heading: oh - eh, length: other[4], width: other[5] }
}

/// Picks the frame's ego (see the module doc) and returns the scene around it, or None when no
/// vehicle has at most `max_vehicles` neighbours in range.
fn choose_ego(
    s: &HighwaySettings,
    rule: &GridRule,
    scenario: &str,
    snap: &Snapshot,
    edges: &[Segment],
    counts: &mut Vec<u64>,
    rng: &mut ChaCha8Rng,
) -> Option<Scene> {
    counts.resize(CELLS, 0);
    let range = s.radar.range_max_m;
    let neighbours = |e: usize| -> Vec<(usize, VehicleBox)> {
        (0..snap.rows.len())
            .filter(|&j| j != e)
            .map(|j| (j, relative(&snap.rows[e], &snap.rows[j])))
            .filter(|(_, b)| b.x.hypot(b.y) <= range)
            .collect()
    };
    let candidates: Vec<usize> = if s.balance_cells { (0..snap.rows.len()).collect() } else { vec![0] };
    // (score, ego row, its neighbours)
    type Choice = (f64, usize, Vec<(usize, VehicleBox)>);
    let mut best: Option<Choice> = None;
    for e in candidates {
        let around = neighbours(e);
        if around.len() > s.max_vehicles {
            continue;
        }
        let score: f64 =
            around.iter().filter_map(|(_, b)| rule.classify(b.x, b.y, b.heading)).map(|cell| 1.0 / (1.0 + counts[cell.index()] as f64)).sum::<f64>()
                + rng.random::<f64>() * 1e-6;
        if best.as_ref().is_none_or(|(b, _, _)| score > *b) {
            best = Some((score, e, around));
        }
    }
    let (_, ego, around) = best?;
    for (_, b) in &around {
        if let Some(cell) = rule.classify(b.x, b.y, b.heading) {
            counts[cell.index()] += 1;
        }
    }
    let (ex, ey, eh) = pose(&snap.rows[ego]);
    let (sin, cos) = eh.sin_cos();
    let local = |(x, y): (f64, f64)| ((x - ex) * cos + (y - ey) * sin, -(x - ex) * sin + (y - ey) * cos);
    let near = |p: (f64, f64)| p.0.hypot(p.1) < range + 15.0;
    let edges = edges.iter().map(|e| Segment { a: local(e.a), b: local(e.b) }).filter(|e| near(e.a) || near(e.b)).collect();
    let vehicles = around
        .into_iter()
        .map(|(j, body)| {
            let r = &snap.rows[j];
            // Lane headings relative to the ego's lane (y flipped, as in `pose`).
            let lane_heading = snap.rows[ego][8] - r[8];
            Vehicle { id: r[0] as u32, class: if r[7] > 0.5 { "truck" } else { "car" }, body, speed: r[6], lane_heading: Some(lane_heading) }
        })
        .collect();
    Some(Scene { scenario: scenario.to_string(), vehicles, edges })
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use rlmflow_stages::DynOperator;
    use rlmflow_stages::scenes::Scenes;

    use super::*;

    fn run(s: &HighwaySettings, name: &str) -> (PathBuf, Outcome) {
        // As the binary's main does; std serialises environment access between test threads.
        embed::pin_home();
        let root = std::env::temp_dir().join(format!("rlmflow-highway-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let out = root.join("out");
        let ckpt = root.join("ckpt");
        std::fs::create_dir_all(&out).unwrap();
        std::fs::create_dir_all(&ckpt).unwrap();
        let mut ctx = Context::standalone("scenes", &[], &out, &ckpt, 11, 2);
        let outcome = Operator::run(&HighwayEnv, s, &mut ctx).unwrap();
        (out, outcome)
    }

    fn small(scenarios: &[&str]) -> HighwaySettings {
        HighwaySettings {
            frames: 12,
            episode_frames: 4,
            scenarios: scenarios.iter().map(|s| (s.to_string(), ScenarioMix::default())).collect(),
            radar: RadarConfig { image: 32, ..RadarConfig::default() },
            ..HighwaySettings::default()
        }
    }

    #[test]
    fn every_scenario_runs_and_the_mix_yields_opposing_and_crossing_traffic() {
        let s = HighwaySettings { frames: 36, episode_frames: 6, ..small(&SCENARIOS) };
        let (out, outcome) = run(&s, "mix");
        let scenes = Scenes::open(&out).unwrap();
        let frames = scenes.frames().unwrap();
        assert_eq!(frames.len(), 36);
        let per: BTreeMap<String, u64> = serde_json::from_value(outcome.metrics["frames_per_scenario"].clone()).unwrap();
        assert_eq!(per.values().sum::<u64>(), 36);
        let rule = GridRule::default();
        let sectors: std::collections::BTreeSet<usize> =
            frames.iter().flat_map(|f| &f.actors).filter_map(|a| rule.classify(a.x, a.y, a.heading)).map(|c| c.sector).collect();
        assert!(sectors.iter().any(|&k| k == 8 || k == 9), "no opposing traffic in {sectors:?}");
        assert!(sectors.iter().any(|&k| k >= 10), "no crossing traffic in {sectors:?}");
        for f in &frames {
            assert!(f.actors.len() <= 20);
            assert!(f.actors.iter().all(|a| a.x.hypot(a.y) <= s.radar.range_max_m));
        }
        // Every vehicle carries its lane's heading; bodies mostly point along their lanes.
        let actors: Vec<_> = frames.iter().flat_map(|f| &f.actors).collect();
        let off = |a: &&&rlmflow_stages::scenes::Actor| (a.lane_heading.unwrap() - a.heading).sin().abs() > 0.3;
        assert!(actors.iter().all(|a| a.lane_heading.is_some()));
        assert!(actors.iter().filter(off).count() * 10 < actors.len(), "bodies far off their lanes");
    }

    #[test]
    fn unknown_scenarios_and_impossible_settings_name_their_key() {
        let check = |v: serde_json::Value| HighwayEnv.settings(v).unwrap_err();
        let e = check(serde_json::json!({"scenarios": {"highwya": {}}}));
        assert_eq!(e.key, "scenarios.highwya");
        assert!(e.valid.contains(&"highway".to_string()));
        assert_eq!(check(serde_json::json!({"scenarios": {"merge": {"density": 0.0}}})).key, "scenarios.merge.density");
        assert_eq!(check(serde_json::json!({"scenarios": {"merge": {"speed": 1.0}}})).key, "scenarios.merge.speed");
        assert_eq!(check(serde_json::json!({"max_vehicles": 25})).key, "max_vehicles");
        assert_eq!(check(serde_json::json!({"scenarios": {}})).key, "scenarios");
    }
}
