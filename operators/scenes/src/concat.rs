//! The `concat` operator (kind `mix`): one Scenes artifact holding the frames of several, in the
//! order the engine gathers them (by instance label), renumbered from 0, each keeping its
//! identity and episode (so its split). The default pipeline pretrains on highway-env drives
//! mixed with placed scenes this way.
//!
//! The inputs must agree on the images (views and sizes) and the radar range, since every
//! reader takes them from one summary. The summary's `generator` lists each input's generator
//! and frame count; stage names stay out of the bytes, as they are not part of the key.
//!
//! Consecutive ranges of one generator's frames (the same settings but `first_frame` and
//! `frames`, each range starting where the last ended) join into that generator's whole range:
//! the summary records the whole's settings, so the bytes are those of one action writing every
//! frame. This is how the engine merges the shards of a sharded scenes stage.

use anyhow::{Context as _, bail};
use rlmflow_stages::scenes::Scenes;
use rlmflow_stages::{Context, InputOutlines, Operator, OperatorSpec, Outcome, Outline, SettingError, Settings};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

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
            version: 2,
            inputs: None,
            summary: "the frames of several Scenes artifacts, one after another, as one Scenes artifact",
        }
    }

    /// One image size for every input, the frames of all of them.
    fn outline(&self, _: &ConcatSettings, inputs: &InputOutlines) -> Result<Outline, SettingError> {
        let parts = inputs.get("scenes").map(Vec::as_slice).unwrap_or_default();
        let sizes: std::collections::BTreeSet<u64> = parts.iter().filter_map(|o| o.image).collect();
        if sizes.len() > 1 {
            let sizes: Vec<String> = sizes.iter().map(|s| format!("{s} px")).collect();
            return Err(SettingError::new(
                "inputs.scenes",
                format!("mixes scenes of {}; a mix needs one image size (set each input's `radar.image` alike)", sizes.join(" and ")),
            ));
        }
        let image = if parts.iter().all(|o| o.image.is_some()) { sizes.first().copied() } else { None };
        Ok(Outline { image, frames: parts.iter().map(|o| o.frames).sum(), groups: parts.iter().map(|o| o.groups).sum(), ..Outline::default() })
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

        let generators: Vec<&Value> = sources.iter().map(|(_, s)| &s.summary.generator).collect();
        let generator = whole_range(&generators).unwrap_or_else(|| {
            let parts: Vec<Value> = sources.iter().map(|(_, s)| json!({"frames": s.len(), "generator": s.summary.generator})).collect();
            json!({"operator": "concat", "inputs": parts})
        });
        let summary = writer.finish(&ctx.output_dir, range_max_m, generator)?;
        Ok(Outcome {
            metrics: json!({"frames": summary.frames, "inputs": sources.len(), "frames_per_scenario": summary.frames_per_scenario}),
            summary: format!("{} frames from {} inputs, {}/48 cells covered", summary.frames, sources.len(), summary.cells_covered()),
        })
    }
}

/// The generator of the whole range when `parts` are consecutive ranges of one generator's
/// frames (see the module doc).
fn whole_range(parts: &[&Value]) -> Option<Value> {
    let range = |g: &Value| Some((g.get("first_frame")?.as_u64()?, g.get("frames")?.as_u64()?));
    let without_range = |g: &Value| {
        let mut g = g.as_object()?.clone();
        g.remove("first_frame");
        g.remove("frames");
        Some(g)
    };
    let (first, _) = range(parts[0])?;
    let settings = without_range(parts[0])?;
    let mut next = first;
    for part in parts {
        let (start, frames) = range(part)?;
        if start != next || without_range(part)? != settings {
            return None;
        }
        next += frames;
    }
    let mut whole = parts[0].clone();
    whole["frames"] = json!(next - first);
    Some(whole)
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
        let s = ProceduralSettings { frames, radar: RadarConfig { image, ..RadarConfig::default() }, ..ProceduralSettings::default() };
        run_procedural(name, &s, seed)
    }

    fn run_procedural(name: &str, s: &ProceduralSettings, seed: u64) -> PathBuf {
        let (out, ckpt) = (dir(&format!("{name}-out")), dir(&format!("{name}-ckpt")));
        Operator::run(&Procedural, s, &mut Context::standalone("scenes", &[], &out, &ckpt, seed, 2)).unwrap();
        out
    }

    /// Every file of an artifact directory, by name.
    fn files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
        std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap())
            .map(|e| (e.file_name().into_string().unwrap(), std::fs::read(e.path()).unwrap()))
            .collect()
    }

    fn concat(name: &str, inputs: &[&Path], s: &ConcatSettings) -> anyhow::Result<PathBuf> {
        let (out, ckpt) = (dir(&format!("{name}-out")), dir(&format!("{name}-ckpt")));
        let gathered = inputs.iter().enumerate().map(|(k, p)| Input::new(format!("in{k}"), p)).collect();
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
            assert_eq!((got.id, got.episode, got.scenario, got.actors), (want.id, want.episode, want.scenario, want.actors), "frame {i}");
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
    fn consecutive_ranges_of_one_generator_join_into_the_whole_run_byte_for_byte() {
        let whole = ProceduralSettings { frames: 11, radar: RadarConfig { image: 32, ..RadarConfig::default() }, ..ProceduralSettings::default() };
        let range = |first_frame, frames| ProceduralSettings { first_frame, frames, ..whole.clone() };
        let expected = files(&run_procedural("whole", &whole, 9));
        let parts = [run_procedural("r0", &range(0, 4), 9), run_procedural("r1", &range(4, 1), 9), run_procedural("r2", &range(5, 6), 9)];
        let joined = concat("ranges", &[&parts[0], &parts[1], &parts[2]], &ConcatSettings { batch: 2 }).unwrap();
        assert_eq!(files(&joined).keys().collect::<Vec<_>>(), expected.keys().collect::<Vec<_>>());
        for (name, bytes) in files(&joined) {
            assert!(bytes == expected[&name], "{name} differs from the whole run's");
        }
        // A gap is no longer one range: the summary lists the parts.
        let gapped = concat("gap", &[&parts[0], &parts[2]], &ConcatSettings::default()).unwrap();
        let gapped = Scenes::open(&gapped).unwrap();
        assert_eq!(gapped.summary.generator["operator"], "concat");
        assert_eq!(gapped.summary.generator["inputs"][1]["generator"]["first_frame"], 5);
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
