//! The `concat` operator (kind `mix`): one Scenes artifact holding the frames of several, in the
//! order the engine gathers them (by instance label), renumbered from 0. The default pipeline
//! pretrains on highway-env drives mixed with placed scenes this way.
//!
//! The inputs must agree on the images (views and sizes) and the radar range, since every
//! reader takes them from one summary. The summary's `generator` lists each input's generator
//! and frame count; stage names stay out of the bytes, as they are not part of the key.

use anyhow::{Context as _, bail};
use rlmflow_stages::scenes::Scenes;
use rlmflow_stages::{Context, Operator, OperatorSpec, Outcome, Resources, SettingError, Settings};
use serde::{Deserialize, Serialize};

use crate::render::Rendered;
use crate::writer::SceneWriter;

pub struct Concat;

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ConcatSettings {
    /// Frames per checkpointed batch, 1..=4,096, held in memory (does not change the result).
    pub batch: u64,
}

impl Default for ConcatSettings {
    fn default() -> Self {
        ConcatSettings { batch: 256 }
    }
}

impl Settings for ConcatSettings {
    const NON_RESULT: &'static [&'static str] = &["batch"];

    fn check(&self) -> Result<(), SettingError> {
        SettingError::check_range("batch", self.batch, 1..=4_096)
    }
}

impl Operator for Concat {
    type Settings = ConcatSettings;

    fn spec(&self) -> OperatorSpec {
        OperatorSpec {
            name: "concat",
            kind: "mix",
            version: 1,
            inputs: None,
            summary: "the frames of several Scenes artifacts, one after another, as one Scenes artifact",
        }
    }

    fn resources(&self, _: &ConcatSettings) -> Resources {
        Resources { threads: 1, gpu: false }
    }

    fn run(&self, s: &ConcatSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let inputs = ctx.gathered("scenes");
        if inputs.is_empty() {
            bail!("`concat` needs at least one scenes input (set `inputs = {{ scenes = [...] }}`)");
        }
        let sources: Vec<(&str, Scenes)> = inputs
            .iter()
            .map(|i| Ok((i.label.as_str(), Scenes::open(&i.path).with_context(|| format!("opening the scenes of `{}`", i.label))?)))
            .collect::<anyhow::Result<_>>()?;
        let (first_label, first) = &sources[0];
        for (label, scenes) in &sources[1..] {
            if scenes.summary.images != first.summary.images {
                bail!(
                    "`{label}` has images {:?} but `{first_label}` has {:?}: every input of `concat` needs the same views and sizes (`images`, `radar.image`)",
                    scenes.summary.images,
                    first.summary.images
                );
            }
            if scenes.summary.range_max_m != first.summary.range_max_m {
                bail!(
                    "`{label}` has a radar range of {} m but `{first_label}` has {} m: every input of `concat` needs the same `radar.range_max_m`",
                    scenes.summary.range_max_m,
                    first.summary.range_max_m
                );
            }
        }
        let images = first.summary.images.clone();
        let range_max_m = first.summary.range_max_m;
        let total: u64 = sources.iter().map(|(_, s)| s.len()).sum();

        let mut writer = SceneWriter::resume(&ctx.checkpoint_dir, images.clone()).context("opening the checkpoint")?;
        let progress = ctx.progress(total, "frames");
        progress.set_position(writer.done());
        while writer.done() < total {
            let start = writer.done();
            let end = (start + s.batch).min(total);
            let batch = (start..end).map(|i| read_frame(&sources, i)).collect::<anyhow::Result<Vec<Rendered>>>()?;
            writer.append(&batch)?;
            progress.set_position(writer.done());
        }
        progress.finish();

        let parts: Vec<serde_json::Value> =
            sources.iter().map(|(_, s)| serde_json::json!({"frames": s.len(), "generator": s.summary.generator})).collect();
        let summary = writer.finish(&ctx.output_dir, range_max_m, serde_json::json!({"operator": "concat", "inputs": parts}))?;
        Ok(Outcome {
            metrics: serde_json::json!({"frames": summary.frames, "inputs": sources.len(), "frames_per_scenario": summary.frames_per_scenario}),
            summary: format!("{} frames from {} inputs, {}/48 cells covered", summary.frames, sources.len(), summary.cells_covered()),
        })
    }
}

/// Frame `index` of the concatenation, renumbered.
fn read_frame(sources: &[(&str, Scenes)], mut index: u64) -> anyhow::Result<Rendered> {
    let new_index = index;
    for (label, scenes) in sources {
        if index < scenes.len() {
            let mut frame = scenes.frame(index).with_context(|| format!("reading `{label}`"))?;
            frame.index = new_index;
            let images = (0..scenes.summary.images.len()).map(|k| scenes.image(k, index)).collect::<anyhow::Result<_>>()?;
            return Ok((frame, images));
        }
        index -= scenes.len();
    }
    unreachable!("index is below the total frame count")
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;
    use std::path::{Path, PathBuf};
    use std::sync::Arc;

    use rlmflow_radar::RadarConfig;
    use rlmflow_stages::context::Silent;
    use rlmflow_stages::{Device, Input};

    use super::*;
    use crate::{Procedural, ProceduralSettings};

    fn dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("rlmflow-concat-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn procedural(name: &str, frames: u64, image: usize, seed: u64) -> PathBuf {
        let (out, ckpt) = (dir(&format!("{name}-out")), dir(&format!("{name}-ckpt")));
        let s = ProceduralSettings { frames, radar: RadarConfig { image, ..RadarConfig::default() }, ..ProceduralSettings::default() };
        Operator::run(&Procedural, &s, &mut Context::standalone("scenes", &[], &out, &ckpt, seed, 2)).unwrap();
        out
    }

    fn concat(name: &str, inputs: &[&Path], s: &ConcatSettings) -> anyhow::Result<PathBuf> {
        let (out, ckpt) = (dir(&format!("{name}-out")), dir(&format!("{name}-ckpt")));
        let gathered = inputs.iter().enumerate().map(|(k, p)| Input { label: format!("in{k}"), path: p.to_path_buf() }).collect();
        let inputs = BTreeMap::from([("scenes".to_string(), gathered)]);
        let mut ctx = Context::new("mix".into(), inputs, out.clone(), ckpt, 1, 1, Device::Cpu, Arc::new(Silent));
        Operator::run(&Concat, s, &mut ctx)?;
        Ok(out)
    }

    #[test]
    fn frames_follow_one_another_renumbered_with_their_images_and_statistics() {
        let (a, b) = (procedural("a", 7, 32, 1), procedural("b", 5, 32, 2));
        let mixed = concat("ab", &[&a, &b], &ConcatSettings { batch: 3 }).unwrap();
        let (a, b, mixed) = (Scenes::open(&a).unwrap(), Scenes::open(&b).unwrap(), Scenes::open(&mixed).unwrap());
        assert_eq!(mixed.len(), 12);
        for (i, (source, j)) in (0..7).map(|j| (&a, j)).chain((0..5).map(|j| (&b, j))).enumerate() {
            let (want, got) = (source.frame(j).unwrap(), mixed.frame(i as u64).unwrap());
            assert_eq!(got.index, i as u64);
            assert_eq!((got.scenario, got.actors), (want.scenario, want.actors), "frame {i}");
            assert_eq!(mixed.heatmap(i as u64).unwrap(), source.heatmap(j).unwrap(), "frame {i}");
        }
        for (cell, n) in &mixed.summary.cells {
            assert_eq!(*n, a.summary.cells.get(cell).unwrap_or(&0) + b.summary.cells.get(cell).unwrap_or(&0), "cell {cell}");
        }
        assert_eq!(mixed.summary.generator["inputs"][1]["generator"], b.summary.generator);
    }

    #[test]
    fn the_bytes_do_not_depend_on_the_batch() {
        let (a, b) = (procedural("c", 6, 32, 3), procedural("d", 4, 32, 4));
        let read = |p: PathBuf| std::fs::read(p.join(rlmflow_stages::scenes::MCAP)).unwrap();
        let one = read(concat("cd1", &[&a, &b], &ConcatSettings { batch: 1 }).unwrap());
        assert_eq!(one, read(concat("cd4", &[&a, &b], &ConcatSettings { batch: 4 }).unwrap()));
        assert_ne!(one, read(concat("dc", &[&b, &a], &ConcatSettings { batch: 4 }).unwrap()), "the order is the gathered order");
    }

    #[test]
    fn inputs_with_different_images_are_refused_by_name() {
        let (a, b) = (procedural("e", 2, 32, 5), procedural("f", 2, 16, 6));
        let err = concat("ef", &[&a, &b], &ConcatSettings::default()).unwrap_err().to_string();
        assert!(err.starts_with("`in1` has images") && err.contains("same views and sizes"), "{err}");
        let err = concat("none", &[], &ConcatSettings::default()).unwrap_err().to_string();
        assert!(err.contains("at least one scenes input"), "{err}");
    }
}
