//! The `labels` stage kind's operator, `ego-grid`: per frame of a Scenes artifact, the paper's
//! grid (the rule in [`rlmflow_stages::grid`]), a fixed train/test split and the segmentation
//! target.
//!
//! Choices where the paper is silent, each a setting:
//! * The split is stratified by the grid's vehicle count and seeded by `split_seed`, not the
//!   pipeline seed, so every variant of every later stage holds out the same frames.
//! * Walkers count within 40 m. A traffic sign (actor class `sign:<name>`) applies when it is
//!   within 40 m and ahead (x >= 0); names are listed once each, sorted.
//! * The mask marks every vehicle the primary image shows, also beyond the grid's 40 m, since
//!   the segmentation probe reads the image, not the grid. Each vehicle is a Gaussian of
//!   `sigma_px` cut off at `radius_px` (both given at `reference_size` pixels and scaled to the
//!   image), centred on its pixel position; blobs combine by maximum and the mask is divided by
//!   its maximum, so it spans [0, 1].

use anyhow::Context as _;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rlmflow_stages::grid::{CELLS, Cell, Grid, GridRule, MAX_RANGE_M};
use rlmflow_stages::labels::{self, FrameLabel, MaskGeometry, Split};
use rlmflow_stages::npy::{Dtype, NpyWriter};
use rlmflow_stages::scenes::{Frame, Scenes};
use rlmflow_stages::{Context, Operator, OperatorSpec, Outcome, SettingError, Settings};
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
        EgoGridSettings { rule: GridRule::default(), test_fraction: 0.2, split_seed: 0, mask: MaskSettings::default() }
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
            version: 1,
            inputs: None,
            summary: "the paper's 4 x 12 ego grid, a stratified train/test split and Gaussian vehicle masks",
        }
    }

    fn run(&self, s: &EgoGridSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let scenes = Scenes::open(ctx.input("scenes")?)?;
        let frames = scenes.len();
        let size = scenes.summary.images.first().context("the Scenes artifact has no images")?.size;
        let geometry = s.mask.geometry(size);
        let progress = ctx.progress(frames, "frames");
        let mut masks = NpyWriter::create(&ctx.output_dir.join(labels::MASKS), Dtype::U8, frames as usize, &[size, size])?;
        let mut grids = Vec::with_capacity(frames as usize);
        for i in 0..frames {
            let frame = scenes.frame(i)?;
            grids.push(grid(&s.rule, &frame));
            masks.write_u8(&mask(&frame, &geometry))?;
            progress.inc(1);
        }
        masks.finish()?;
        progress.finish();

        let vehicles: Vec<u32> = grids.iter().map(Grid::vehicles).collect();
        let splits = split(&vehicles, s.test_fraction, s.split_seed);
        let mut cells = [0u64; CELLS];
        for grid in &grids {
            for (total, n) in cells.iter_mut().zip(grid.counts) {
                *total += n as u64;
            }
        }
        let lines: String = grids
            .into_iter()
            .zip(&splits)
            .enumerate()
            .map(|(i, (grid, &split))| FrameLabel { frame: i as u64, split, grid }.to_line() + "\n")
            .collect();
        std::fs::write(ctx.output_dir.join(labels::LINES), lines)?;

        let mut per_frame = vec![0u64; vehicles.iter().max().map_or(1, |m| *m as usize + 1)];
        for &v in &vehicles {
            per_frame[v as usize] += 1;
        }
        let test = splits.iter().filter(|&&s| s == Split::Test).count() as u64;
        let summary = labels::Summary {
            format: labels::FORMAT,
            frames,
            train: frames - test,
            test,
            rule: s.rule.clone(),
            mask: geometry,
            cells: cells.iter().enumerate().map(|(i, &n)| (Cell::from_index(i).name(), n)).collect(),
            vehicles_per_frame: per_frame,
        };
        std::fs::write(ctx.output_dir.join(labels::SUMMARY), serde_json::to_vec_pretty(&summary)?)?;
        let covered = summary.cells.values().filter(|&&n| n > 0).count();
        let total: u64 = vehicles.iter().map(|&v| v as u64).sum();
        Ok(Outcome {
            metrics: serde_json::json!({"frames": frames, "train": summary.train, "test": test, "vehicles": total, "cells_covered": covered}),
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

/// The split of frames with these vehicle counts: frames are ordered by (count, a seeded random
/// key) and every frame where the running share of test frames falls below `test_fraction` is
/// held out, so each count gets its share to within one frame and the total is exact.
pub fn split(vehicles: &[u32], test_fraction: f64, seed: u64) -> Vec<Split> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut order: Vec<(u32, u64, usize)> = vehicles.iter().enumerate().map(|(i, &v)| (v, rng.random::<u64>(), i)).collect();
    order.sort_unstable();
    let mut out = vec![Split::Train; vehicles.len()];
    for (k, &(_, _, i)) in order.iter().enumerate() {
        let before = (k as f64 * test_fraction).floor();
        let after = ((k + 1) as f64 * test_fraction).floor();
        if after > before {
            out[i] = Split::Test;
        }
    }
    out
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

    use rlmflow_scenes::{Procedural, ProceduralSettings};
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
        let frame = Frame { index: 0, scenario: "t".into(), actors: vec![changing] };
        assert_eq!(grid(&GridRule::default(), &frame).get(1, 10), 1, "by body heading it crosses: other_lane_front");
        let lane = GridRule { heading: Heading::Lane, ..GridRule::default() };
        assert_eq!(grid(&lane, &frame).get(1, 3), 1, "by lane heading it is ahead in our lane");
    }

    #[test]
    fn the_split_is_stratified_exact_and_fixed_by_its_seed() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let vehicles: Vec<u32> = (0..1000).map(|_| rng.random_range(0..8u32)).collect();
        let a = split(&vehicles, 0.2, 0);
        assert_eq!(a, split(&vehicles, 0.2, 0));
        assert_ne!(a, split(&vehicles, 0.2, 1));
        assert_eq!(a.iter().filter(|s| **s == Split::Test).count(), 200);
        for n in 0..8 {
            let group: Vec<Split> = vehicles.iter().zip(&a).filter(|(v, _)| **v == n).map(|(_, s)| *s).collect();
            let test = group.iter().filter(|s| **s == Split::Test).count() as f64;
            assert!((test - group.len() as f64 * 0.2).abs() <= 1.0, "{n} vehicles: {test} of {}", group.len());
        }
    }

    #[test]
    fn masks_are_gaussian_blobs_cut_at_the_radius_and_scaled_with_the_image() {
        let g = MaskSettings::default().geometry(112);
        assert_eq!((g.radius_px, g.sigma_px), (3.5, 1.25));
        let frame = Frame {
            index: 0,
            scenario: "t".into(),
            actors: vec![actor("car", 10.0, 0.0, 0.0, (20.5, 30.5)), actor("walker", 5.0, 0.0, 0.0, (60.5, 60.5))],
        };
        let m = mask(&frame, &g);
        let at = |r: usize, c: usize| m[r * 112 + c];
        assert_eq!(at(20, 30), 255);
        let expected = (255.0 * (-1.0f64 / (2.0 * 1.25 * 1.25)).exp()).round() as u8;
        assert_eq!((at(21, 30), at(20, 29)), (expected, expected));
        assert_eq!(at(20, 34), 0, "beyond the radius");
        assert_eq!(at(60, 60), 0, "walkers are not vehicles");
        assert_eq!(m.iter().filter(|v| **v > 0).count(), 37, "pixels within 3.5 px of a pixel centre");
        let off = Frame { index: 0, scenario: "t".into(), actors: vec![actor("car", 10.0, 0.0, 0.0, (-40.0, 30.5))] };
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
        assert_eq!((labels.summary.train, labels.summary.test), (24, 6));
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
