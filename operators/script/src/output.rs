//! What a script's output must be, by its kind, checked (and for a probe or a segmenter scored)
//! before anything is committed: an error names the file and what is wrong, and the engine then
//! commits nothing.
//!
//! - `probe`: `predictions.jsonl`, per test frame and row `{"frame", "features", "grid"}` (the
//!   grid in the paper's JSON, as `linear` writes it) or `{"frame", "features", "counts"}` (the
//!   48 cell counts in the labels' order); every row predicts every test frame of
//!   the labels' split once and nothing else. rlmflow scores the rows with the paper's rule and
//!   writes `probe.json` itself, with the hygiene check, so the report gathers the rows beside
//!   the built-in probes' and no script reports a score of its own making.
//! - `segment`: `predictions.npy`, float32 in [0, 1] (or uint8, /255) shaped (test frames, side,
//!   side) in the split's order; rlmflow writes `segment.json`, `frames.jsonl` and the sample
//!   masks as every segmenter's.
//! - `files`: at least one file.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{Context as _, bail};
use rlmflow_stages::grid::{CELLS, Grid};
use rlmflow_stages::identity::Split;
use rlmflow_stages::labels::Labels;
use rlmflow_stages::npy::{Dtype, Npy, NpyWriter};
use rlmflow_stages::{Context, Outcome, Settings, probe, segment};
use serde_json::{Value, json};

use crate::ScriptSettings;
use crate::program::Reported;

/// A probe's predictions, read from the program's output.
const PREDICTIONS_NPY: &str = "predictions.npy";
/// Sample frames a segmenter's artifact holds, spread over the test split as the built-in
/// segmenters' default spreads them.
const SAMPLES: usize = 8;

pub fn check(kind: &str, s: &ScriptSettings, ctx: &Context, reported: Reported) -> anyhow::Result<Outcome> {
    let out = &ctx.output_dir;
    let files = list(out)?;
    if files.is_empty() {
        bail!("{}: `{}` wrote nothing into its output directory ($RLMFLOW_OUTPUT)", ctx.stage, s.run.join(" "));
    }
    let Reported { metrics, summary } = reported;
    let mut metrics = Value::Object(metrics);
    let summary = match kind {
        "probe" => {
            let probe = score_probe(s, ctx)?;
            let line = probe.rows.iter().map(|r| format!("{} F1 {:.3}", r.features, r.scores.overall.f1)).collect::<Vec<_>>().join(", ");
            metrics = with_script(probe::metrics(&probe), metrics);
            if summary.is_empty() { line } else { format!("{line}; {summary}") }
        }
        "segment" => {
            let seg = score_segmenter(s, ctx)?;
            let line = format!("IoU {:.3}, AP {:.3}", seg.metrics.iou, seg.metrics.ap);
            metrics = with_script(segment::metrics(&seg), metrics);
            if summary.is_empty() { line } else { format!("{line}; {summary}") }
        }
        _ if summary.is_empty() => format!("{} file{}", files.len(), if files.len() == 1 { "" } else { "s" }),
        _ => summary,
    };
    Ok(Outcome { metrics, summary })
}

/// The artifact's own figures, with the program's metrics beside them under `script`.
fn with_script(mut measured: Value, script: Value) -> Value {
    if script.as_object().is_some_and(|m| !m.is_empty()) {
        measured["script"] = script;
    }
    measured
}

/// Every file below `dir`, relative; a symbolic link is refused (an artifact is its bytes).
fn list(dir: &Path) -> anyhow::Result<Vec<String>> {
    let mut files = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(at) = stack.pop() {
        for entry in std::fs::read_dir(&at).with_context(|| format!("reading {}", at.display()))? {
            let entry = entry?;
            let kind = entry.file_type()?;
            let rel = entry.path().strip_prefix(dir).expect("below the output").to_string_lossy().into_owned();
            if kind.is_symlink() {
                bail!("{}: `{rel}` is a symbolic link; an output holds files and directories only", dir.display());
            } else if kind.is_dir() {
                stack.push(entry.path());
            } else {
                files.push(rel);
            }
        }
    }
    Ok(files)
}

fn refuse_own(ctx: &Context, file: &str, wanted: &str) -> anyhow::Result<()> {
    if ctx.output_dir.join(file).exists() {
        bail!("{}: the program wrote `{file}`, which rlmflow writes from its {wanted}: write only the {wanted}", ctx.stage);
    }
    Ok(())
}

/// The test frames of the stage's labels, in order, with the labels.
fn test_split(ctx: &Context) -> anyhow::Result<(Labels, Vec<u64>)> {
    let labels = Labels::open(ctx.input("labels")?)?;
    let test = labels.split(Split::Test).map(|f| f.frame).collect();
    Ok((labels, test))
}

fn score_probe(s: &ScriptSettings, ctx: &Context) -> anyhow::Result<probe::Summary> {
    refuse_own(ctx, probe::SUMMARY, probe::PREDICTIONS)?;
    let out = &ctx.output_dir;
    let file = out.join(probe::PREDICTIONS);
    if !file.is_file() {
        bail!(
            "{}: a probe script writes `{}` (per test frame and row: {{\"frame\", \"features\", \"grid\"}}); the program wrote none",
            ctx.stage,
            probe::PREDICTIONS
        );
    }
    // Named as the program wrote it, not by the action's directory in the store.
    let predictions = probe::read_predictions(out)
        .map_err(|e| anyhow::anyhow!("{}: {}", ctx.stage, format!("{e:#}").replace(&format!("{}/", out.display()), "")))?;
    let (labels, test) = test_split(ctx)?;
    let position: BTreeMap<u64, usize> = test.iter().enumerate().map(|(i, &f)| (f, i)).collect();
    // Each row's grids by test position, rows in the order they first appear.
    let mut rows: Vec<(String, Vec<Option<[u32; CELLS]>>)> = Vec::new();
    for (n, (frame, features, grid)) in predictions.into_iter().enumerate() {
        let at = |what: String| anyhow::anyhow!("{}: {}: prediction {}: {what}", ctx.stage, probe::PREDICTIONS, n + 1);
        let Some(&p) = position.get(&frame) else {
            return Err(at(format!("frame {frame} is not a test frame of the labels' split ({} test frames)", test.len())));
        };
        let row = match rows.iter().position(|(f, _)| *f == features) {
            Some(r) => r,
            None => {
                rows.push((features.clone(), vec![None; test.len()]));
                rows.len() - 1
            }
        };
        if rows[row].1[p].replace(grid).is_some() {
            return Err(at(format!("frame {frame} is predicted twice for `{features}`")));
        }
    }
    if rows.is_empty() {
        bail!("{}: {} holds no prediction", ctx.stage, probe::PREDICTIONS);
    }
    let truth: Vec<[u32; CELLS]> = test.iter().map(|&f| labels.frames[f as usize].grid.counts).collect();
    let mut scored = Vec::new();
    let mut canonical = String::new();
    for (features, grids) in rows {
        let missing: Vec<String> = test.iter().zip(&grids).filter(|(_, g)| g.is_none()).map(|(f, _)| f.to_string()).collect();
        if !missing.is_empty() {
            bail!(
                "{}: {}: `{features}` predicts {} of the {} test frames; it misses frame{} {}",
                ctx.stage,
                probe::PREDICTIONS,
                test.len() - missing.len(),
                test.len(),
                if missing.len() == 1 { "" } else { "s" },
                missing.iter().take(5).cloned().collect::<Vec<_>>().join(", ") + if missing.len() > 5 { ", ..." } else { "" }
            );
        }
        let grids: Vec<[u32; CELLS]> = grids.into_iter().map(|g| g.expect("every frame checked")).collect();
        for (frame, counts) in test.iter().zip(&grids) {
            let grid = Grid { counts: *counts, walkers: 0, signs: Vec::new() };
            canonical.push_str(&format!("{{\"frame\":{frame},\"features\":{},\"grid\":{}}}\n", json!(features), grid.to_json()));
        }
        let scores = probe::score(&grids, &truth);
        ctx.event("row", json!({"features": features, "f1": scores.overall.f1}));
        scored.push(probe::Row { features, details: json!({}), scores });
    }
    let hygiene = rlmflow_stages::identity::check_inputs(ctx, &labels.ids(Split::Test), s.allow_test_overlap)?;
    let summary = probe::Summary {
        format: probe::FORMAT,
        probe: "script".into(),
        train_frames: labels.split(Split::Train).count() as u64,
        test_frames: test.len() as u64,
        hygiene,
        rows: scored,
        generator: s.result_settings(),
    };
    // In the split's order, one line format: the bytes follow the predictions, not the order
    // the program wrote them in.
    std::fs::write(&file, canonical)?;
    std::fs::write(out.join(probe::SUMMARY), serde_json::to_vec_pretty(&summary)?)?;
    Ok(summary)
}

fn score_segmenter(s: &ScriptSettings, ctx: &Context) -> anyhow::Result<segment::Summary> {
    for own in [segment::SUMMARY, segment::FRAMES, segment::SAMPLES] {
        refuse_own(ctx, own, PREDICTIONS_NPY)?;
    }
    let out = &ctx.output_dir;
    let file = out.join(PREDICTIONS_NPY);
    if !file.is_file() {
        bail!("{}: a segment script writes `{PREDICTIONS_NPY}` (float32 in [0, 1], one mask per test frame); the program wrote none", ctx.stage);
    }
    let (labels, test) = test_split(ctx)?;
    let side = labels.summary.mask.size;
    let npy = Npy::open(&file).map_err(|e| anyhow::anyhow!("{}: {e:#}", ctx.stage))?;
    if npy.shape != [test.len(), side, side] {
        bail!(
            "{}: {PREDICTIONS_NPY} has shape {:?}; it must be [{}, {side}, {side}] (the test frames, in the split's order, at the masks' size)",
            ctx.stage,
            npy.shape,
            test.len()
        );
    }
    let scale = if npy.dtype == Dtype::U8 { 1.0 / 255.0 } else { 1.0 };
    let all = npy.all_f32().map_err(|e| anyhow::anyhow!("{}: {e:#}", ctx.stage))?;
    if let Some(i) = all.iter().position(|v| !v.is_finite() || *v * scale < 0.0 || *v * scale > 1.0) {
        bail!("{}: {PREDICTIONS_NPY}: value {} at index {i} (test frame {}) is not in [0, 1]", ctx.stage, all[i], test[i / (side * side)]);
    }
    // Scaled to [0, 1] once; each test frame's mask is one chunk of it.
    let all: Vec<f32> = all.into_iter().map(|v| v * scale).collect();
    let maps: Vec<&[f32]> = all.chunks_exact(side * side).collect();
    let mut counts = segment::PixelCounts::new();
    let mut frames = String::new();
    for (&predicted, &frame) in maps.iter().zip(&test) {
        let mask = labels.mask(frame)?;
        counts.add(predicted, &mask);
        frames.push_str(&(serde_json::to_string(&segment::FrameScore::of(frame, predicted, &mask))? + "\n"));
    }
    std::fs::write(out.join(segment::FRAMES), frames)?;
    let n = SAMPLES.min(test.len());
    let samples: Vec<usize> = (0..n).map(|i| i * test.len() / n).collect();
    let mut writer = NpyWriter::create(&out.join(segment::SAMPLES), Dtype::U8, n, &[side, side])?;
    for &k in &samples {
        writer.write_u8(&maps[k].iter().map(|p| (p * 255.0).round() as u8).collect::<Vec<_>>())?;
    }
    writer.finish()?;
    let metrics = counts.metrics();
    let summary = segment::Summary {
        format: segment::FORMAT,
        operator: "script".into(),
        train_frames: labels.split(Split::Train).count() as u64,
        test_frames: test.len() as u64,
        hygiene: rlmflow_stages::identity::check_inputs(ctx, &labels.ids(Split::Test), s.allow_test_overlap)?,
        epochs: 0,
        steps: 0,
        metrics,
        log: Vec::new(),
        sample_frames: samples.iter().map(|&k| test[k]).collect(),
        rollout_blocks: Vec::new(),
        generator: s.result_settings(),
    };
    std::fs::write(out.join(segment::SUMMARY), serde_json::to_vec_pretty(&summary)?)?;
    Ok(summary)
}
