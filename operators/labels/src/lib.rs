//! The `labels` stage kind's operator, `ego-grid`: per frame of a Scenes artifact, the paper's
//! grid (the rule in [`rlmflow_stages::grid`]), a fixed train/test split and the segmentation
//! target.
//!
//! Choices where the paper is silent, each a setting:
//! * The split follows the frame, not its place in the artifact: a frame's split group (its
//!   episode for sequences, else the frame) is held out when its hash with `split_seed` falls
//!   below `test_fraction` (the rule in [`rlmflow_stages::identity`]). The same frame is therefore
//!   in the same split in every artifact that holds it, whatever else is mixed in, and no episode
//!   straddles the split (`split_by = "frame"` splits a sequence's frames one by one, for
//!   measuring what that leaks). The seed is `split_seed`, not the pipeline seed, so every
//!   variant of every later stage holds out the same frames. Stratification by vehicle count
//!   holds in expectation (each stratum's test share is binomial around `test_fraction`); the
//!   summary lists the achieved share per stratum.
//! * For sequences the summary measures how alike test frames are to their nearest training
//!   frame against training frames to theirs (pixel correlation over `similarity_sample`
//!   evenly spaced frames of the sequences): near-duplicates across the split show as
//!   test-to-train similarity as high as train-to-train.
//! * Walkers count within 40 m. A traffic sign (actor class `sign:<name>`) applies when it is
//!   within 40 m and ahead (x >= 0); names are listed once each, sorted.
//! * A frame imported with its grid instead of actors keeps that grid (the rule does not apply),
//!   and its mask is empty: segmentation refuses such scenes.
//! * The mask marks every vehicle the primary image shows, also beyond the grid's 40 m, since
//!   the segmentation probe reads the image, not the grid. Each vehicle is a Gaussian of
//!   `sigma_px` cut off at `radius_px` (both given at `reference_size` pixels and scaled to the
//!   image), centred on its pixel position; blobs combine by maximum and the mask is divided by
//!   its maximum, so it spans [0, 1].

use anyhow::Context as _;
use rlmflow_stages::grid::{CELLS, Cell, Grid, GridRule, MAX_RANGE_M};
use rlmflow_stages::identity::{Split, SplitBy, split_of};
use rlmflow_stages::labels::{self, FrameLabel, MaskGeometry, NearestNeighbour, SplitSummary, Stratum};
use rlmflow_stages::npy::{Dtype, NpyWriter};
use rlmflow_stages::scenes::{Frame, Scenes};
use rlmflow_stages::{Context, InputOutlines, Operator, OperatorSpec, Outcome, Outline, SettingError, Settings};
use serde::{Deserialize, Serialize};

pub struct EgoGrid;

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EgoGridSettings {
    pub rule: GridRule,
    /// Share of frames held out for testing, in [0, 1).
    pub test_fraction: f64,
    /// Fixes the split (any integer); not the pipeline seed, so every variant holds out the same frames.
    pub split_seed: u64,
    /// `episode`: a sequence's frames share one split; `frame`: each frame is split on its own
    /// (near-duplicate neighbours then straddle the split; for measuring that only).
    pub split_by: SplitBy,
    /// Frames of the sequences sampled for the nearest-neighbour similarity, 0..=20,000 (0: not
    /// measured).
    pub similarity_sample: usize,
    pub mask: MaskSettings,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MaskSettings {
    /// Blob cut-off radius, at `reference_size` pixels.
    pub radius_px: f64,
    /// Blob standard deviation, at `reference_size` pixels.
    pub sigma_px: f64,
    /// The image size the two above are given at (the paper's 224), 1..=4,096; the radius is at
    /// most this.
    pub reference_size: usize,
}

impl Default for EgoGridSettings {
    fn default() -> Self {
        EgoGridSettings {
            rule: GridRule::default(),
            test_fraction: 0.2,
            split_seed: 0,
            split_by: SplitBy::Episode,
            similarity_sample: 1_000,
            mask: MaskSettings::default(),
        }
    }
}

impl Default for MaskSettings {
    fn default() -> Self {
        MaskSettings { radius_px: 7.0, sigma_px: 2.5, reference_size: 224 }
    }
}

impl Settings for EgoGridSettings {
    fn check(&self) -> Result<(), SettingError> {
        let positive =
            |key: &str, v: f64| if v > 0.0 && v.is_finite() { Ok(()) } else { Err(SettingError::new(key, format!("must be positive, not {v}"))) };
        SettingError::check_range("rule.lane_width_m", self.rule.lane_width_m, 0.5..=20.0)?;
        if !(0.0..1.0).contains(&self.rule.direction_dot) {
            return Err(SettingError::new("rule.direction_dot", format!("must be in [0, 1), not {}", self.rule.direction_dot)));
        }
        SettingError::check_range("rule.beside_m", self.rule.beside_m, 0.0..=10.0)?;
        if !(0.0..1.0).contains(&self.test_fraction) {
            return Err(SettingError::new("test_fraction", format!("must be in [0, 1), not {}", self.test_fraction)));
        }
        SettingError::check_range("similarity_sample", self.similarity_sample, 0..=20_000)?;
        positive("mask.radius_px", self.mask.radius_px)?;
        positive("mask.sigma_px", self.mask.sigma_px)?;
        SettingError::check_range("mask.sigma_px", self.mask.sigma_px, 0.0..=self.mask.reference_size as f64)?;
        SettingError::check_range("mask.reference_size", self.mask.reference_size, 1..=4_096)?;
        SettingError::check_range("mask.radius_px", self.mask.radius_px, 0.0..=self.mask.reference_size as f64)?;
        Ok(())
    }
}

impl MaskSettings {
    /// The blob geometry for an image of `size` pixels.
    pub fn geometry(&self, size: usize) -> MaskGeometry {
        let scale = size as f64 / self.reference_size as f64;
        MaskGeometry { size, radius_px: self.radius_px * scale, sigma_px: self.sigma_px * scale }
    }
}

impl Operator for EgoGrid {
    type Settings = EgoGridSettings;

    fn spec(&self) -> OperatorSpec {
        OperatorSpec {
            name: "ego-grid",
            kind: "labels",
            version: 2,
            inputs: None,
            summary: "the paper's 4 x 12 ego grid, a train/test split that follows each frame (and episode), and Gaussian vehicle masks",
        }
    }

    /// The split in expectation, where the scenes' settings tell their frames and groups: both
    /// sides need at least one group, or every model stage downstream fails after the scenes
    /// are made.
    fn outline(&self, s: &EgoGridSettings, inputs: &InputOutlines) -> Result<Outline, SettingError> {
        let scenes = Outline::passed_on(inputs);
        let (Some(frames), Some(groups)) = (scenes.frames, scenes.groups) else { return Ok(scenes) };
        let (groups, unit) = match s.split_by {
            SplitBy::Episode => (groups, "split groups (sequences, or frames outside any)"),
            SplitBy::Frame => (frames, "frames"),
        };
        let test = groups as f64 * s.test_fraction;
        if test < 1.0 || groups as f64 - test < 1.0 {
            return Err(SettingError::new(
                "test_fraction",
                format!(
                    "{} holds out {test:.1} of the scenes' {groups} {unit} in expectation and trains on {:.1}; a model needs both sides: more frames (or shorter sequences), or a test_fraction nearer 0.5",
                    s.test_fraction,
                    groups as f64 - test
                ),
            ));
        }
        Ok(Outline { train_frames: Some((frames as f64 * (1.0 - s.test_fraction)).floor() as u64), ..scenes })
    }

    fn run(&self, s: &EgoGridSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let scenes = Scenes::open(ctx.input("scenes")?)?;
        let frames = scenes.len();
        let size = scenes.summary.images.first().context("the Scenes artifact has no images")?.size;
        let geometry = s.mask.geometry(size);
        let progress = ctx.progress(frames, "frames");
        let mut masks = NpyWriter::create(&ctx.output_dir.join(labels::MASKS), Dtype::U8, frames as usize, &[size, size])?;
        let mut grids = Vec::with_capacity(frames as usize);
        let mut identities = Vec::with_capacity(frames as usize);
        for i in 0..frames {
            let frame = scenes.frame(i)?;
            grids.push(match &frame.grid {
                Some(given) => Grid::from_json(given).map_err(|e| anyhow::anyhow!("frame {i} ({}): its grid: {e}", frame.id))?,
                None => grid(&s.rule, &frame),
            });
            masks.write_u8(&mask(&frame, &geometry))?;
            identities.push((frame.id, frame.episode));
            progress.inc(1);
        }
        masks.finish()?;
        progress.finish();

        let group = |(id, episode): &(String, Option<String>)| s.split_by.group(id, episode.as_deref()).to_owned();
        let splits: Vec<Split> = identities.iter().map(|f| split_of(&group(f), s.test_fraction, s.split_seed)).collect();
        let vehicles: Vec<u32> = grids.iter().map(Grid::vehicles).collect();
        let mut cells = [0u64; CELLS];
        for grid in &grids {
            for (total, n) in cells.iter_mut().zip(grid.counts) {
                *total += n as u64;
            }
        }
        let nearest_neighbour = if identities.iter().any(|(_, e)| e.is_some()) && s.similarity_sample > 0 {
            let sequences: Vec<u64> = (0..frames).filter(|&i| identities[i as usize].1.is_some()).collect();
            nearest_neighbour(&scenes, &sequences, &splits, s.similarity_sample, ctx.threads)?
        } else {
            None
        };
        let lines: String = grids
            .into_iter()
            .zip(&splits)
            .zip(identities.iter().cloned())
            .enumerate()
            .map(|(i, ((grid, &split), (id, episode)))| FrameLabel { frame: i as u64, id, episode, split, grid }.to_line() + "\n")
            .collect();
        std::fs::write(ctx.output_dir.join(labels::LINES), lines)?;

        let mut per_frame = vec![0u64; vehicles.iter().max().map_or(1, |m| *m as usize + 1)];
        let mut strata: Vec<Stratum> = (0..per_frame.len() as u32).map(|vehicles| Stratum { vehicles, frames: 0, test: 0 }).collect();
        for (&v, &split) in vehicles.iter().zip(&splits) {
            per_frame[v as usize] += 1;
            strata[v as usize].frames += 1;
            strata[v as usize].test += u64::from(split == Split::Test);
        }
        strata.retain(|s| s.frames > 0);
        let test = splits.iter().filter(|&&s| s == Split::Test).count() as u64;
        let mut groups: std::collections::BTreeMap<String, Split> = std::collections::BTreeMap::new();
        for (f, &split) in identities.iter().zip(&splits) {
            groups.insert(group(f), split);
        }
        let split = SplitSummary {
            rule: format!(
                "a frame's {} is held out when BLAKE3(\"rlmflow split v1\", split_seed, its identity) as a number in [0, 1) is below test_fraction; stratification by vehicle count holds in expectation",
                if s.split_by == SplitBy::Episode { "episode (or the frame, outside sequences)" } else { "frame" }
            ),
            by: s.split_by,
            test_fraction: s.test_fraction,
            seed: s.split_seed,
            groups: groups.len() as u64,
            test_groups: groups.values().filter(|&&s| s == Split::Test).count() as u64,
            strata,
        };
        let summary = labels::Summary {
            format: labels::FORMAT,
            frames,
            train: frames - test,
            test,
            split,
            nearest_neighbour,
            rule: s.rule.clone(),
            mask: geometry,
            cells: cells.iter().enumerate().map(|(i, &n)| (Cell::from_index(i).name(), n)).collect(),
            vehicles_per_frame: per_frame,
        };
        std::fs::write(ctx.output_dir.join(labels::SUMMARY), serde_json::to_vec_pretty(&summary)?)?;
        let covered = summary.cells.values().filter(|&&n| n > 0).count();
        let total: u64 = vehicles.iter().map(|&v| v as u64).sum();
        let mut metrics = serde_json::json!({
            "frames": frames, "train": summary.train, "test": test, "vehicles": total, "cells_covered": covered,
            "groups": summary.split.groups, "test_groups": summary.split.test_groups,
        });
        if let Some(nn) = &summary.nearest_neighbour {
            metrics["nearest_neighbour"] = serde_json::to_value(nn)?;
        }
        Ok(Outcome {
            metrics,
            summary: format!("{frames} frames ({} train, {test} test), {total} vehicles in the grid, {covered}/48 cells", summary.train),
        })
    }
}

/// A frame's grid under `rule`, with its walkers and applicable signs.
pub fn grid(rule: &GridRule, frame: &Frame) -> Grid {
    let mut grid = Grid::default();
    let mut signs = Vec::new();
    for actor in &frame.actors {
        if actor.is_vehicle() {
            if let Some(cell) = rule.classify(actor.x, actor.y, rule.direction(actor.heading, actor.lane_heading)) {
                grid.counts[cell.index()] += 1;
            }
        } else if actor.x.hypot(actor.y) < MAX_RANGE_M {
            if actor.class == "walker" {
                grid.walkers += 1;
            } else if let Some(name) = actor.sign().filter(|_| actor.x >= 0.0) {
                signs.push(name.to_owned());
            }
        }
    }
    signs.sort();
    signs.dedup();
    grid.signs = signs;
    grid
}

/// The mean nearest-neighbour pixel correlation from test frames to training frames and from
/// training frames to other training frames, over at most `sample` evenly spaced `frames`.
fn nearest_neighbour(scenes: &Scenes, frames: &[u64], splits: &[Split], sample: usize, threads: usize) -> anyhow::Result<Option<NearestNeighbour>> {
    let step = frames.len().div_ceil(sample).max(1);
    let chosen: Vec<u64> = frames.iter().step_by(step).copied().collect();
    // Each image centred and scaled to unit length: a dot product is then the correlation.
    let unit = |i: u64| -> anyhow::Result<Vec<f32>> {
        let pixels = scenes.heatmap(i)?;
        let mean = pixels.iter().map(|&p| f64::from(p)).sum::<f64>() / pixels.len() as f64;
        let centred: Vec<f64> = pixels.iter().map(|&p| f64::from(p) - mean).collect();
        let norm = centred.iter().map(|v| v * v).sum::<f64>().sqrt().max(1e-12);
        Ok(centred.iter().map(|v| (v / norm) as f32).collect())
    };
    let (mut train, mut test) = (Vec::new(), Vec::new());
    for &i in &chosen {
        match splits[i as usize] {
            Split::Train => train.push(unit(i)?),
            Split::Test => test.push(unit(i)?),
        }
    }
    if train.len() < 2 || test.is_empty() {
        return Ok(None);
    }
    let best = |queries: &[Vec<f32>], skip_self: bool| -> f64 {
        let indices: Vec<usize> = (0..queries.len()).collect();
        let sims = rlmflow_stages::parallel_map(&indices, threads, |&q| {
            train
                .iter()
                .enumerate()
                .filter(|(t, _)| !(skip_self && *t == q))
                .map(|(_, t)| queries[q].iter().zip(t).map(|(a, b)| a * b).sum::<f32>())
                .fold(f32::MIN, f32::max) as f64
        });
        sims.iter().sum::<f64>() / sims.len() as f64
    };
    Ok(Some(NearestNeighbour {
        sample_train: train.len() as u64,
        sample_test: test.len() as u64,
        test_to_train: best(&test, false),
        train_to_train: best(&train, true),
    }))
}

/// The segmentation target of a frame: `size` x `size` bytes, value / 255 in [0, 1].
pub fn mask(frame: &Frame, g: &MaskGeometry) -> Vec<u8> {
    let size = g.size;
    let mut field = vec![0f64; size * size];
    let reach = g.radius_px.ceil() as i64;
    for actor in frame.actors.iter().filter(|a| a.is_vehicle()) {
        // Pixel centres sit at integer + 0.5.
        let (r0, c0) = ((actor.row - 0.5).round() as i64, (actor.col - 0.5).round() as i64);
        for r in (r0 - reach).max(0)..=(r0 + reach).min(size as i64 - 1) {
            for c in (c0 - reach).max(0)..=(c0 + reach).min(size as i64 - 1) {
                let (dr, dc) = (r as f64 + 0.5 - actor.row, c as f64 + 0.5 - actor.col);
                let d2 = dr * dr + dc * dc;
                if d2 <= g.radius_px * g.radius_px {
                    let v = &mut field[r as usize * size + c as usize];
                    *v = v.max((-d2 / (2.0 * g.sigma_px * g.sigma_px)).exp());
                }
            }
        }
    }
    let peak = field.iter().copied().fold(0.0, f64::max);
    let scale = if peak > 0.0 { 255.0 / peak } else { 0.0 };
    field.iter().map(|v| (v * scale).round() as u8).collect()
}

#[cfg(test)]
mod tests {
    use std::f64::consts::PI;
    use std::path::{Path, PathBuf};

    use std::sync::Arc;

    use rlmflow_scenes::{Concat, ConcatSettings, Procedural, ProceduralSettings};
    use rlmflow_stages::context::Silent;
    use rlmflow_stages::grid::Heading;
    use rlmflow_stages::labels::Labels;
    use rlmflow_stages::scenes::Actor;

    use super::*;

    fn actor(class: &str, x: f64, y: f64, heading: f64, (row, col): (f64, f64)) -> Actor {
        Actor { id: 0, class: class.into(), x, y, heading, length: 4.5, width: 1.8, speed: 10.0, lane_heading: None, row, col }
    }

    fn scratch(name: &str) -> PathBuf {
        let root = std::env::temp_dir().join(format!("rlmflow-labels-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        for d in ["out", "ckpt", "scenes", "scenes-ckpt"] {
            std::fs::create_dir_all(root.join(d)).unwrap();
        }
        root
    }

    #[test]
    fn a_frame_grid_counts_vehicles_walkers_and_applicable_signs() {
        let frame = Frame {
            index: 0,
            id: String::new(),
            episode: None,
            scenario: "test".into(),
            actors: vec![
                actor("car", 5.0, 0.2, 0.0, (0.0, 0.0)),
                actor("truck", 5.0, -0.4, 0.1, (0.0, 0.0)),
                actor("car", 22.0, 7.0, PI, (0.0, 0.0)),
                actor("car", 45.0, 0.0, 0.0, (0.0, 0.0)),
                actor("walker", 3.0, 8.0, 0.0, (0.0, 0.0)),
                actor("walker", 50.0, 8.0, 0.0, (0.0, 0.0)),
                actor("sign:stop", 20.0, -5.0, PI, (0.0, 0.0)),
                actor("sign:stop", 25.0, -5.0, PI, (0.0, 0.0)),
                actor("sign:yield", -10.0, -5.0, PI, (0.0, 0.0)),
            ],
            grid: None,
        };
        let g = grid(&GridRule::default(), &frame);
        assert_eq!(
            g.to_json(),
            r#"{"0-10m":{"total_vehicles":2,"in_lane_front_side":2},"10-20m":{"total_vehicles":0},"20-30m":{"total_vehicles":1,"opposing_lane_front":1},"30-40m":{"total_vehicles":0},"traffic_signs":["stop"],"walkers":1}"#
        );
    }

    #[test]
    fn lane_headings_keep_a_lane_changing_vehicle_in_its_lanes_direction() {
        let mut changing = actor("car", 12.0, 0.5, 1.2, (0.0, 0.0));
        changing.lane_heading = Some(0.0);
        let frame = Frame { index: 0, id: String::new(), episode: None, scenario: "t".into(), actors: vec![changing], grid: None };
        assert_eq!(grid(&GridRule::default(), &frame).get(1, 10), 1, "by body heading it crosses: other_lane_front");
        let lane = GridRule { heading: Heading::Lane, ..GridRule::default() };
        assert_eq!(grid(&lane, &frame).get(1, 3), 1, "by lane heading it is ahead in our lane");
    }

    fn procedural(root: &Path, name: &str, settings: &ProceduralSettings, seed: u64) -> PathBuf {
        let (out, ckpt) = (root.join(name), root.join(format!("{name}-ckpt")));
        std::fs::create_dir_all(&out).unwrap();
        std::fs::create_dir_all(&ckpt).unwrap();
        let mut ctx = Context::standalone("scenes", &[], &out, &ckpt, seed, 2);
        Operator::run(&Procedural, settings, &mut ctx).unwrap();
        out
    }

    fn concat(root: &Path, name: &str, parts: &[&Path]) -> PathBuf {
        let (out, ckpt) = (root.join(name), root.join(format!("{name}-ckpt")));
        std::fs::create_dir_all(&out).unwrap();
        std::fs::create_dir_all(&ckpt).unwrap();
        let gathered = parts.iter().enumerate().map(|(k, p)| rlmflow_stages::Input::new(format!("in{k}"), p)).collect();
        let inputs = std::collections::BTreeMap::from([("scenes".to_string(), gathered)]);
        let mut ctx = Context::new("mix".into(), inputs, out.clone(), ckpt, 1, 1, rlmflow_stages::Device::Cpu, Arc::new(Silent));
        Operator::run(&Concat, &ConcatSettings::default(), &mut ctx).unwrap();
        out
    }

    /// Labels the scenes in `scenes` and returns each frame's (identity, split) in frame order.
    fn splits(root: &Path, name: &str, scenes: &Path, settings: &EgoGridSettings) -> (Labels, Vec<(String, Split)>) {
        let (out, ckpt) = (root.join(name), root.join(format!("{name}-ckpt")));
        std::fs::create_dir_all(&out).unwrap();
        std::fs::create_dir_all(&ckpt).unwrap();
        let mut ctx = Context::standalone("labels", &[("scenes", scenes)], &out, &ckpt, 1, 1);
        Operator::run(&EgoGrid, settings, &mut ctx).unwrap();
        let labels = Labels::open(&out).unwrap();
        let pairs = labels.frames.iter().map(|f| (f.id.clone(), f.split)).collect();
        (labels, pairs)
    }

    #[test]
    fn a_frames_split_is_the_same_alone_mixed_sharded_and_in_either_order() {
        let root = scratch("identity");
        let whole = ProceduralSettings { frames: 60, radar: rlmflow_radar_image(32), ..ProceduralSettings::default() };
        let a = procedural(&root, "a", &whole, 1);
        let b = procedural(&root, "b", &ProceduralSettings { frames: 40, ..whole.clone() }, 2);
        let a0 = procedural(&root, "a0", &ProceduralSettings { frames: 25, ..whole.clone() }, 1);
        let a1 = procedural(&root, "a1", &ProceduralSettings { first_frame: 25, frames: 35, ..whole.clone() }, 1);
        let s = EgoGridSettings::default();
        let (_, alone_a) = splits(&root, "la", &a, &s);
        let (_, alone_b) = splits(&root, "lb", &b, &s);
        let reference: std::collections::BTreeMap<String, Split> = alone_a.iter().chain(&alone_b).cloned().collect();
        assert_eq!(reference.len(), 100, "every frame has its own identity");
        assert!(alone_a.iter().any(|(_, s)| *s == Split::Test) && alone_a.iter().any(|(_, s)| *s == Split::Train));
        let pairs: [(&str, [&Path; 2]); 4] = [("ab", [&a, &b]), ("ba", [&b, &a]), ("shards", [&a0, &a1]), ("b-a1", [&b, &a1])];
        for (name, parts) in pairs {
            let mixed = concat(&root, name, &parts);
            let (_, got) = splits(&root, &format!("l-{name}"), &mixed, &s);
            for (id, split) in &got {
                assert_eq!(reference[id], *split, "{name}: frame {id}");
            }
        }
        // Another seed is another split; a smaller test fraction holds out a subset.
        let (_, reseeded) = splits(&root, "seed", &a, &EgoGridSettings { split_seed: 7, ..EgoGridSettings::default() });
        assert_ne!(reseeded, alone_a);
        let (_, fewer) = splits(&root, "fewer", &a, &EgoGridSettings { test_fraction: 0.1, ..EgoGridSettings::default() });
        assert!(fewer.iter().all(|(id, s)| *s == Split::Train || reference[id] == Split::Test));
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn the_stratification_by_vehicle_count_stays_within_three_binomial_deviations() {
        let root = scratch("strata");
        let scenes =
            procedural(&root, "s", &ProceduralSettings { frames: 600, min_vehicles: 0, radar: rlmflow_radar_image(32), ..Default::default() }, 4);
        let (labels, _) = splits(&root, "l", &scenes, &EgoGridSettings::default());
        let strata = &labels.summary.split.strata;
        assert_eq!(strata.iter().map(|s| s.frames).sum::<u64>(), 600);
        assert_eq!(strata.iter().map(|s| s.test).sum::<u64>(), labels.summary.test);
        assert!(strata.len() > 5, "{strata:?}");
        for s in strata {
            let (n, f) = (s.frames as f64, 0.2);
            let tolerance = 3.0 * (n * f * (1.0 - f)).sqrt() + 1.0;
            assert!((s.test as f64 - n * f).abs() <= tolerance, "{} vehicles: {} of {} held out", s.vehicles, s.test, s.frames);
        }
        assert!(labels.summary.split.rule.contains("BLAKE3"));
        assert_eq!(labels.summary.nearest_neighbour, None, "placed frames are not sequences");
        std::fs::remove_dir_all(&root).unwrap();
    }

    /// A Scenes artifact of `episodes` sequences of `length` frames each: within an episode each
    /// frame is the previous one with a little noise (near-duplicates), across episodes unrelated.
    fn sequences(root: &Path, episodes: u64, length: u64) -> PathBuf {
        use rand::{RngExt, SeedableRng};
        let (out, ckpt) = (root.join("seq"), root.join("seq-ckpt"));
        std::fs::create_dir_all(&out).unwrap();
        std::fs::create_dir_all(&ckpt).unwrap();
        let images = vec![rlmflow_stages::scenes::Image { view: "range-azimuth".into(), topic: "/radar/range-azimuth".into(), size: 16 }];
        let mut writer = rlmflow_scenes::SceneWriter::resume(&ckpt, images).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for e in 0..episodes {
            let mut pixels: Vec<u8> = (0..256).map(|_| rng.random_range(0..200u8)).collect();
            let mut batch = Vec::new();
            for k in 0..length {
                for p in pixels.iter_mut() {
                    *p = p.saturating_add(rng.random_range(0..4u8));
                }
                let car = actor("car", 5.0 + k as f64, 0.0, 0.0, (4.5, 8.5));
                let mut frame = Frame::new(e * length + k, "drive".into(), vec![car], std::slice::from_ref(&pixels));
                frame.episode = Some(format!("episode-{e}"));
                batch.push((frame, vec![pixels.clone()]));
            }
            writer.append(&batch).unwrap();
        }
        writer.finish(&out, 50.0, serde_json::json!({"operator": "test"})).unwrap();
        out
    }

    #[test]
    fn no_episode_straddles_the_split_and_the_nearest_neighbour_shows_the_difference() {
        let root = scratch("episodes");
        let scenes = sequences(&root, 40, 10);
        let straddling = |labels: &Labels| {
            let mut by_episode: std::collections::BTreeMap<&str, std::collections::BTreeSet<Split>> = Default::default();
            for f in &labels.frames {
                by_episode.entry(f.episode.as_deref().unwrap()).or_default().insert(f.split);
            }
            by_episode.values().filter(|s| s.len() > 1).count()
        };
        let (episode, _) = splits(&root, "by-episode", &scenes, &EgoGridSettings::default());
        assert_eq!(straddling(&episode), 0);
        assert_eq!(episode.summary.split.groups, 40);
        // The validation slice takes whole training episodes, about the share asked for.
        let (fit, validation) = episode.train_validation(0.25);
        let episodes = |frames: &[&FrameLabel]| frames.iter().map(|f| f.episode.clone().unwrap()).collect::<std::collections::BTreeSet<_>>();
        let (fit_episodes, validation_episodes) = (episodes(&fit), episodes(&validation));
        assert!(fit_episodes.is_disjoint(&validation_episodes));
        let train_episodes = (fit_episodes.len() + validation_episodes.len()) as f64;
        assert_eq!(validation_episodes.len(), (train_episodes * 0.25).round() as usize);
        assert_eq!(fit.len() + validation.len(), episode.summary.train as usize);
        assert!(episode.summary.test > 0 && episode.summary.train > 0);
        let (frame, _) = splits(&root, "by-frame", &scenes, &EgoGridSettings { split_by: SplitBy::Frame, ..Default::default() });
        assert!(straddling(&frame) > 10, "frame by frame, most episodes straddle");
        // Split by episode, a test frame's nearest training frame is another episode's; split by
        // frame, it is its own episode's neighbour, as alike as two training frames.
        let (e, f) = (episode.summary.nearest_neighbour.unwrap(), frame.summary.nearest_neighbour.unwrap());
        assert!(e.test_to_train < e.train_to_train - 0.3, "{e:?}");
        assert!((f.test_to_train - f.train_to_train).abs() < 0.05, "{f:?}");
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn masks_are_gaussian_blobs_cut_at_the_radius_and_scaled_with_the_image() {
        let g = MaskSettings::default().geometry(112);
        assert_eq!((g.radius_px, g.sigma_px), (3.5, 1.25));
        let frame = Frame {
            index: 0,
            id: String::new(),
            episode: None,
            scenario: "t".into(),
            actors: vec![actor("car", 10.0, 0.0, 0.0, (20.5, 30.5)), actor("walker", 5.0, 0.0, 0.0, (60.5, 60.5))],
            grid: None,
        };
        let m = mask(&frame, &g);
        let at = |r: usize, c: usize| m[r * 112 + c];
        assert_eq!(at(20, 30), 255);
        let expected = (255.0 * (-1.0f64 / (2.0 * 1.25 * 1.25)).exp()).round() as u8;
        assert_eq!((at(21, 30), at(20, 29)), (expected, expected));
        assert_eq!(at(20, 34), 0, "beyond the radius");
        assert_eq!(at(60, 60), 0, "walkers are not vehicles");
        assert_eq!(m.iter().filter(|v| **v > 0).count(), 37, "pixels within 3.5 px of a pixel centre");
        let off = Frame {
            index: 0,
            id: String::new(),
            episode: None,
            scenario: "t".into(),
            actors: vec![actor("car", 10.0, 0.0, 0.0, (-40.0, 30.5))],
            grid: None,
        };
        assert!(mask(&off, &g).iter().all(|v| *v == 0));
    }

    fn labels_of(root: &Path, settings: &EgoGridSettings) -> Labels {
        let mut ctx = Context::standalone("labels", &[("scenes", &root.join("scenes"))], &root.join("out"), &root.join("ckpt"), 1, 1);
        Operator::run(&EgoGrid, settings, &mut ctx).unwrap();
        Labels::open(&root.join("out")).unwrap()
    }

    #[test]
    fn labels_of_a_scenes_artifact_agree_with_its_statistics_and_read_back() {
        let root = scratch("run");
        let scenes = ProceduralSettings { frames: 30, radar: rlmflow_radar_image(48), ..ProceduralSettings::default() };
        let mut ctx = Context::standalone("scenes", &[], &root.join("scenes"), &root.join("scenes-ckpt"), 3, 2);
        Operator::run(&Procedural, &scenes, &mut ctx).unwrap();
        let summary = Scenes::open(&root.join("scenes")).unwrap().summary;

        let labels = labels_of(&root, &EgoGridSettings::default());
        assert_eq!(labels.summary.cells, summary.cells.iter().map(|(k, v)| (k.clone(), *v)).collect());
        let held_out = frames_of(&root).iter().filter(|f| rlmflow_stages::identity::split_of(&f.id, 0.2, 0) == Split::Test).count();
        assert_eq!((labels.summary.train + labels.summary.test, labels.summary.test), (30, held_out as u64));
        assert_eq!(labels.summary.mask.size, 48);
        let frames = Scenes::open(&root.join("scenes")).unwrap().frames().unwrap();
        for (label, frame) in labels.frames.iter().zip(&frames) {
            assert_eq!(label.grid, grid(&GridRule::default(), frame));
            let m = labels.mask(label.frame).unwrap();
            assert_eq!(m, mask(frame, &labels.summary.mask));
            let visible = frame.actors.iter().any(|a| a.is_vehicle() && (0.0..48.0).contains(&a.row) && (0.0..48.0).contains(&a.col));
            assert_eq!(m.contains(&255), visible, "frame {}", label.frame);
        }
        // A wider beside band moves vehicles between sectors, and only the labels change.
        let wide = labels_of(&root, &EgoGridSettings { rule: GridRule { beside_m: 6.0, ..GridRule::default() }, ..EgoGridSettings::default() });
        assert_ne!(wide.summary.cells, labels.summary.cells);
        std::fs::remove_dir_all(&root).unwrap();
    }

    fn frames_of(root: &Path) -> Vec<Frame> {
        Scenes::open(&root.join("scenes")).unwrap().frames().unwrap()
    }

    fn rlmflow_radar_image(size: usize) -> rlmflow_radar::RadarConfig {
        rlmflow_radar::RadarConfig { image: size, ..rlmflow_radar::RadarConfig::default() }
    }

    #[test]
    fn impossible_settings_name_their_key() {
        let bad = |s: EgoGridSettings| s.check().unwrap_err().key;
        assert_eq!(bad(EgoGridSettings { test_fraction: 1.0, ..Default::default() }), "test_fraction");
        assert_eq!(bad(EgoGridSettings { mask: MaskSettings { sigma_px: 0.0, ..Default::default() }, ..Default::default() }), "mask.sigma_px");
        assert_eq!(bad(EgoGridSettings { rule: GridRule { direction_dot: 1.5, ..GridRule::default() }, ..Default::default() }), "rule.direction_dot");
    }
}
