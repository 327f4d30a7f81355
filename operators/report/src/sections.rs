//! The report's sections. Each reads the [`Study`], appends blocks to the document and puts
//! every number it shows into `metrics.json`.

use anyhow::Context as _;
use rlmflow_stages::grid::{CELLS, DISTANCE_BINS, Grid, SECTORS};
use rlmflow_stages::{identity, probe, segment};
use serde_json::{Map, Value, json};

use crate::doc::{Block, Picture};
use crate::images::{self, Gray};
use crate::paper;
use crate::plots::{self, Series};
use crate::samples::{Captioner, Sample};
use crate::stats::{Stat, name, rows};
use crate::study::{EncoderRun, Instance, Role, Study};

/// The document and the numbers, built section by section.
pub struct Report {
    pub blocks: Vec<Block>,
    pub metrics: Map<String, Value>,
}

fn table(header: &[&str], rows: Vec<Vec<String>>) -> Block {
    Block::Table { header: header.iter().map(|h| h.to_string()).collect(), rows }
}

fn cell_key(c: usize) -> String {
    format!("{}/{}", DISTANCE_BINS[c / SECTORS.len()], SECTORS[c % SECTORS.len()])
}

/// The non-zero cells of a grid, one per line: `0-10m in_lane_front_side: 2`.
pub fn grid_text(grid: &Grid) -> String {
    let cells: Vec<String> =
        (0..CELLS).filter(|&c| grid.counts[c] > 0).map(|c| format!("{}: {}", cell_key(c).replace('/', " "), grid.counts[c])).collect();
    if cells.is_empty() { "no vehicles within 40 m".into() } else { cells.join(", ") }
}

/// Where the settings' lines wrap: the report's code blocks stay readable without a scroll.
const SETTINGS_WIDTH: usize = 100;

/// A stage instance's settings as its label, then `key = value` pairs (values as JSON writes
/// them) wrapped at [`SETTINGS_WIDTH`] columns between pairs, indented.
fn settings_text(label: &str, settings: &serde_json::Value) -> String {
    let Some(fields) = settings.as_object() else { return format!("{label}: {settings}") };
    let mut text = label.to_owned();
    let mut line = String::new();
    for (key, value) in fields {
        let pair = format!("{key} = {value}");
        // The indent, the line, ", ", the pair and the comma that may follow it.
        if !line.is_empty() && 2 + line.len() + 2 + pair.len() + 1 > SETTINGS_WIDTH {
            text.push_str(&format!("\n  {line},"));
            line.clear();
        }
        line = if line.is_empty() { pair } else { format!("{line}, {pair}") };
    }
    if !line.is_empty() {
        text.push_str(&format!("\n  {line}"));
    }
    text
}

impl Report {
    pub fn inputs(&mut self, study: &Study) {
        self.blocks.push(Block::Heading(1, "Configuration".into()));
        self.blocks.push(Block::Paragraph(
            "The stage instances this report read and their settings. Which stages ran or were reused in a run, with their keys, \
             outputs and times, is in that run's record: `runs/<id>/provenance.md` in the store (also `rlmflow status`)."
                .into(),
        ));
        let encoders = study.encoders.iter().map(|e| (&e.label, &e.encoder.summary.generator));
        let probes = study.probes.iter().map(|p| (&p.label, &p.summary.generator));
        let segments = study.segments.iter().map(|s| (&s.label, &s.summary.generator));
        let instances: Vec<String> = encoders.chain(probes).chain(segments).map(|(label, settings)| settings_text(label, settings)).collect();
        self.blocks.push(Block::Code(instances.join("\n")));
    }

    pub fn dataset(&mut self, study: &Study) -> anyhow::Result<()> {
        let Some(labels) = &study.labels else { return Ok(()) };
        let s = &labels.summary;
        self.blocks.push(Block::Heading(1, "Dataset".into()));
        let vehicles: u64 = s.cells.values().sum();
        self.blocks.push(Block::Paragraph(format!(
            "{} frames ({} train, {} test), {vehicles} vehicles in the 48 cells of the ego grid (4 distance bins by 12 lane sectors).",
            s.frames, s.train, s.test
        )));
        let bars: Vec<(String, f64)> = s.vehicles_per_frame.iter().enumerate().map(|(n, f)| (n.to_string(), *f as f64)).collect();
        self.blocks.push(Block::Chart {
            name: "vehicles-per-frame".into(),
            svg: plots::bars("Vehicles per frame", "vehicles in the grid", "frames", &bars)?,
        });
        let per_cell: Vec<f64> = (0..CELLS).map(|c| s.cells.get(&cell_key(c)).copied().unwrap_or(0) as f64).collect();
        let max = per_cell.iter().cloned().fold(0.0, f64::max);
        self.blocks
            .push(Block::Chart { name: "vehicles-per-cell".into(), svg: plots::cells("Vehicles per cell", &per_cell, max, &|v| format!("{v:.0}"))? });
        self.metrics.insert(
            "dataset".into(),
            json!({"frames": s.frames, "train": s.train, "test": s.test, "vehicles_per_frame": s.vehicles_per_frame, "cells": s.cells}),
        );
        Ok(())
    }

    pub fn pretraining(&mut self, study: &Study) -> anyhow::Result<()> {
        if study.encoders.is_empty() {
            return Ok(());
        }
        self.blocks.push(Block::Heading(1, "Pretraining".into()));
        let mut table_rows = Vec::new();
        let mut metrics = Map::new();
        let (mut loss, mut top1, mut lr, mut off) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for (row, group) in rows(&study.encoders, |e| &e.instance) {
            let first = group[0];
            let last = |key: &str| Stat::of(group.iter().filter_map(|e| e.log.last().and_then(|l| l[key].as_f64())));
            let s = &first.encoder.summary;
            let (l, t1, t5, o, mse) = (last("loss"), last("top1"), last("top5"), last("off_diagonal"), last("test_mse"));
            table_rows.push(vec![
                name(&row),
                first.objective(),
                first.role().describe(),
                s.epochs.to_string(),
                s.steps.to_string(),
                l.show(),
                t1.show(),
                t5.show(),
                format!("{:.3}", s.chance_top1),
                mse.show(),
                o.show(),
            ]);
            metrics.insert(
                name(&row),
                json!({"instances": group.iter().map(|e| e.label.clone()).collect::<Vec<_>>(), "objective": first.objective(),
                       "epochs": s.epochs, "steps": s.steps, "loss": l.json(), "top1": t1.json(), "top5": t5.json(),
                       "chance_top1": s.chance_top1, "test_mse": mse.json(), "off_diagonal": o.json()}),
            );
            let curve = |key: &str| Series { name: name(&row), points: mean_curve(&group, key) };
            if s.epochs > 0 {
                loss.push(curve("loss"));
                lr.push(curve("lr"));
                if first.encoder.summary.objective == "sg-clip" {
                    off.push(curve("off_diagonal"));
                }
            }
            top1.push(curve("top1"));
        }
        self.blocks.push(table(
            &["encoder", "objective", "row", "epochs", "steps", "loss", "top-1", "top-5", "chance top-1", "test MSE (counts)", "off-diagonal mass"],
            table_rows,
        ));
        self.blocks.push(Block::Paragraph(
            "Retrieval is radar to text on the test split (one caption per frame); a tower trained on the counts reports its test-split mean squared error instead. Off-diagonal mass is the share of the soft \
             targets off the diagonal, averaged over the last epoch's batches: 0 for vanilla CLIP by construction; near 0 for an \
             SG-CLIP variant means its targets were almost CLIP's on this data, so the two could not differ much."
                .into(),
        ));
        if !loss.is_empty() {
            self.blocks.push(Block::Chart { name: "pretrain-loss".into(), svg: plots::lines("Training loss", "epoch", "loss", &loss, false)? });
            self.blocks.push(Block::Chart { name: "pretrain-lr".into(), svg: plots::lines("Learning rate", "epoch", "lr", &lr, false)? });
        }
        if top1.iter().any(|s| !s.points.is_empty()) {
            self.blocks
                .push(Block::Chart { name: "pretrain-top1".into(), svg: plots::lines("Test retrieval top-1", "epoch", "top-1", &top1, true)? });
        }
        if !off.is_empty() {
            self.blocks.push(Block::Chart {
                name: "pretrain-off-diagonal".into(),
                svg: plots::lines("SG-CLIP target mass off the diagonal", "epoch", "share", &off, false)?,
            });
        }
        self.metrics.insert("pretrain".into(), Value::Object(metrics));
        Ok(())
    }

    pub fn captioning(&mut self, study: &Study) -> anyhow::Result<()> {
        if study.probes.is_empty() {
            return Ok(());
        }
        self.blocks.push(Block::Heading(1, "Caption probing".into()));
        self.blocks.push(Block::Paragraph(
            "Per distance bin, the paper's definition: precision, recall and F1 micro-averaged over the test frames per cell (TP = \
             min(pred, true), FP = max(0, pred - true), FN = max(0, true - pred)), then averaged over the bin's sectors; a cell with \
             no true and no predicted vehicle in any test frame has no score and is left out of the average. \"F1\" is all 48 cells \
             pooled; \"pooled F1 by bin\" pools each bin's 12 cells instead of averaging them. Caption rows generate captions from \
             the frozen CLS embedding and parse them back with the LLM-free parser; linear rows are ridge regression to the counts \
             (sanity rows). The paper's F1 per bin is its own result (CARLA, ViT-B/16, 4xA100), beside ours for direction, not \
             equality."
                .into(),
        ));
        let mut header = vec!["probe".to_string(), "row".into()];
        for bin in DISTANCE_BINS {
            header.extend([format!("{bin} P"), format!("{bin} R"), format!("{bin} F1")]);
        }
        header.extend(["F1".into(), "pooled F1 by bin".into(), "paper F1 by bin".into()]);
        let mut table_rows = Vec::new();
        let mut metrics = Map::new();
        let mut heatmaps = Vec::new();
        for (row, group) in rows(&study.probes, |p| &p.instance) {
            for features in group[0].summary.rows.iter().map(|r| r.features.clone()) {
                let scores: Vec<&probe::Scores> =
                    group.iter().filter_map(|p| p.summary.rows.iter().find(|r| r.features == features)).map(|r| &r.scores).collect();
                let role = study.role(&row, &group[0].summary.probe, &features);
                // The paper's numbers are caption probing's; a linear row is ours alone.
                let captioner = group[0].summary.probe == "clipcap";
                let title = if captioner { name(&row) } else { format!("{} ({features})", name(&row)) };
                let paper = match role {
                    Role::Paper(m) if captioner => paper::captioning(m),
                    _ => None,
                };
                let mut cells = vec![title.clone(), role.describe()];
                let mut bins = Map::new();
                for bin in DISTANCE_BINS {
                    let get = |f: fn(&probe::CellMean) -> f64| Stat::of(scores.iter().map(|s| f(&s.bins[bin])));
                    let (p, r, f) = (get(|s| s.precision), get(|s| s.recall), get(|s| s.f1));
                    cells.extend([p.show(), r.show(), f.show()]);
                    let pooled = |f: fn(&probe::Score) -> f64| Stat::of(scores.iter().map(|s| f(&s.bins_pooled[bin])));
                    bins.insert(
                        bin.into(),
                        json!({"precision": p.json(), "recall": r.json(), "f1": f.json(), "cells": scores[0].bins[bin].cells,
                               "pooled": {"precision": pooled(|s| s.precision).json(), "recall": pooled(|s| s.recall).json(), "f1": pooled(|s| s.f1).json()}}),
                    );
                }
                let overall = |f: fn(&probe::Score) -> f64| Stat::of(scores.iter().map(|s| f(&s.overall)));
                cells.push(overall(|s| s.f1).show());
                let pooled_f1 = |bin: &str| Stat::of(scores.iter().map(|s| s.bins_pooled[bin].f1)).mean();
                cells.push(DISTANCE_BINS.iter().map(|b| format!("{:.3}", pooled_f1(b))).collect::<Vec<_>>().join(" / "));
                cells.push(paper.map_or("–".into(), |p| p.iter().map(|b| format!("{:.3}", b[2])).collect::<Vec<_>>().join(" / ")));
                table_rows.push(cells);
                metrics.insert(
                    title.clone(),
                    json!({"instances": group.iter().map(|p| p.label.clone()).collect::<Vec<_>>(), "probe": group[0].summary.probe,
                           "features": features, "row": role.describe(), "test_frames": group[0].summary.test_frames,
                           "overall": {"precision": overall(|s| s.precision).json(), "recall": overall(|s| s.recall).json(), "f1": overall(|s| s.f1).json()},
                           "bins": bins, "paper": paper.map(|p| json!(p))}),
                );
                if captioner {
                    let f1: Vec<f64> = (0..CELLS).map(|c| Stat::of(scores.iter().map(|s| s.cells[&cell_key(c)].f1)).mean()).collect();
                    heatmaps.push((title, f1));
                }
            }
        }
        self.blocks.push(Block::Table { header, rows: table_rows });
        for (i, (title, f1)) in heatmaps.into_iter().enumerate() {
            self.blocks.push(Block::Chart {
                name: format!("cell-f1-{i}"),
                svg: plots::cells(&format!("Per-cell F1: {title}"), &f1, 1.0, &|v| format!("{v:.2}"))?,
            });
        }
        self.metrics.insert("captioning".into(), Value::Object(metrics));
        Ok(())
    }

    /// The hygiene table's one-line verdict, for the report's first screen: how many checks,
    /// and whether every overlap is zero.
    pub fn hygiene_verdict(&mut self, study: &Study) {
        let checks = hygiene_checks(study);
        if checks.is_empty() {
            return;
        }
        let rows = checks.iter().map(|(_, _, r)| r.len()).sum::<usize>();
        let flagged = checks.iter().flat_map(|(_, _, rows)| rows.iter()).filter(|r| r.overlap > 0).count();
        self.blocks.push(Block::Paragraph(match flagged {
            0 => format!(
                "Data hygiene: {rows} checks, every overlap 0: no probe or segmenter tests on a frame its encoder trained on or a \
                 tokenizer learnt from (each check under \"Data hygiene\" below)."
            ),
            n => format!("Data hygiene: {rows} checks, {n} OVERLAP by their stages' own choice: those rows are not clean test results (under \"Data hygiene\" below)."),
        }));
    }

    /// The data-hygiene table: for every probe and segmenter instance, its test frames against
    /// each set of frames upstream learnt from (the encoder's training frames, its tokenizer's,
    /// the probe's own tokenizer's), as the instance counted them before it ran.
    pub fn hygiene(&mut self, study: &Study) {
        let checks = hygiene_checks(study);
        if checks.is_empty() {
            return;
        }
        let flagged = checks.iter().flat_map(|(_, _, rows)| rows.iter()).filter(|r| r.overlap > 0).count();
        self.blocks.push(Block::Heading(1, "Data hygiene".into()));
        self.blocks.push(Block::Paragraph(format!(
            "Frames are compared by identity (the digest of their content, kept through every mix and shard). Each row counts a \
             probe's test frames among the frames an upstream stage learnt from; a probe refuses to run on a non-zero count unless \
             its stage sets `allow_test_overlap`. {}",
            if flagged == 0 {
                "Every count is zero: no probe tests on a frame its encoder trained on or a tokenizer learnt from.".to_string()
            } else {
                format!("{flagged} rows overlap, by the stages' own choice (flagged): their numbers are not clean test results.")
            }
        )));
        let mut table_rows = Vec::new();
        let mut metrics = Vec::new();
        for (label, instance, rows) in checks {
            for r in rows {
                let flag = if r.overlap > 0 { "OVERLAP (allowed)" } else { "clean" };
                // The encoder the instance read, where the study can tell; else the input slot.
                let learnt_by = match study.encoder_of(instance) {
                    Some(encoder) if r.slot == "encoder" => encoder.label.clone(),
                    _ => format!("its `{}` input", r.slot),
                };
                table_rows.push(vec![
                    label.to_string(),
                    r.test_frames.to_string(),
                    r.against.clone(),
                    learnt_by,
                    r.frames.to_string(),
                    r.overlap.to_string(),
                    flag.to_string(),
                ]);
                metrics.push(json!({"instance": label, "check": r}));
            }
        }
        self.blocks.push(table(&["instance", "test frames", "against", "learnt by", "frames learnt from", "overlap", ""], table_rows));
        self.metrics.insert("hygiene".into(), json!(metrics));
    }

    pub fn segmentation(&mut self, study: &Study, quoted: paper::Table) -> anyhow::Result<()> {
        if study.segments.is_empty() {
            return Ok(());
        }
        let (heading, source) = match quoted {
            paper::Table::Carla => ("Vehicle segmentation", "its simulated test set (Section 5)"),
            paper::Table::Radiate => {
                ("Vehicle segmentation on RADIATE", "its sim-to-real table (supplementary, RADIATE: the decoder fine-tuned, the encoder frozen)")
            }
        };
        self.blocks.push(Block::Heading(1, heading.into()));
        self.blocks.push(Block::Paragraph(format!(
            "Ground truth is the labels' mask at {}; predictions count as positive at 0.5 for P, R, IoU and Dice. Peak IoU is the \
             best IoU over thresholds 0 to 1 in steps of 0.01; AP is the area under that sweep's precision-recall curve. A \
             constant predictor scores AP equal to the positive rate. The paper's column is its own result on {source}, as \
             P/R/IoU/Dice at 0.5, Peak IoU, AP.",
            segment::TRUTH_THRESHOLD
        )));
        let mut table_rows = Vec::new();
        let mut metrics = Map::new();
        let (mut iou, mut dice) = (Vec::new(), Vec::new());
        for (row, group) in rows(&study.segments, |s| &s.instance) {
            let m: Vec<&segment::SegMetrics> = group.iter().map(|s| &s.summary.metrics).collect();
            let get = |f: fn(&segment::SegMetrics) -> f64| Stat::of(m.iter().map(|x| f(x)));
            let role = study.role(&row, &group[0].summary.operator, "");
            let paper = match role {
                Role::Paper(method) => paper::segmentation(method, quoted),
                _ => None,
            };
            let values = [get(|x| x.precision), get(|x| x.recall), get(|x| x.iou), get(|x| x.dice), get(|x| x.peak_iou), get(|x| x.ap)];
            let mut cells = vec![name(&row), role.describe()];
            cells.extend(values.iter().map(Stat::show));
            cells.push(get(|x| x.positive_rate).show());
            cells.push(paper.map_or("–".into(), |p| format!("{:.3}/{:.3}/{:.3}/{:.3}, {:.3}, {:.3}", p[0], p[1], p[2], p[3], p[4], p[5])));
            table_rows.push(cells);
            let keys = ["precision", "recall", "iou", "dice", "peak_iou", "ap"];
            let mut entry: Map<String, Value> = keys.iter().zip(&values).map(|(k, v)| (k.to_string(), v.json())).collect();
            entry.insert("instances".into(), json!(group.iter().map(|s| s.label.clone()).collect::<Vec<_>>()));
            entry.insert("row".into(), json!(role.describe()));
            entry.insert("positive_rate".into(), get(|x| x.positive_rate).json());
            entry.insert("paper".into(), json!(paper));
            metrics.insert(name(&row), Value::Object(entry));
            let curve = |f: fn(&segment::SegMetrics) -> &Vec<f64>| {
                let n = f(m[0]).len();
                (0..n).map(|t| (t as f64 / (n - 1).max(1) as f64, Stat::of(m.iter().map(|x| f(x)[t])).mean())).collect()
            };
            iou.push(Series { name: name(&row), points: curve(|x| &x.iou_curve) });
            dice.push(Series { name: name(&row), points: curve(|x| &x.dice_curve) });
        }
        self.blocks
            .push(table(&["segmenter", "row", "P@0.5", "R@0.5", "IoU@0.5", "Dice@0.5", "Peak IoU", "AP", "positive rate", "paper"], table_rows));
        self.blocks.push(Block::Chart { name: "iou-threshold".into(), svg: plots::lines("IoU vs threshold", "threshold", "IoU", &iou, true)? });
        self.blocks.push(Block::Chart { name: "dice-threshold".into(), svg: plots::lines("Dice vs threshold", "threshold", "Dice", &dice, true)? });
        self.metrics.insert("segmentation".into(), Value::Object(metrics));
        Ok(())
    }

    /// Sample test frames: the heatmap, the true mask, each segmenter's prediction and each
    /// encoder's attention rollout over the heatmap.
    pub fn samples(&mut self, samples: &[Sample]) -> anyhow::Result<()> {
        if samples.is_empty() {
            return Ok(());
        }
        self.blocks.push(Block::Heading(1, "Sample test frames".into()));
        self.blocks.push(Block::Paragraph(
            "Per frame: the radar heatmap, the true mask, each segmenter's predicted probability (first seed), then each encoder's \
             CLS attention rollout laid over the heatmap in red."
                .into(),
        ));
        for sample in samples {
            let (frame, side) = (sample.frame, sample.side);
            let gray = |pixels: &[u8]| images::gray_png(&Gray { side, pixels });
            let mut pictures = vec![
                Picture { name: format!("frame{frame}-heatmap"), caption: format!("frame {frame}"), png: gray(&sample.heatmap)? },
                Picture { name: format!("frame{frame}-truth"), caption: "true mask".into(), png: gray(&sample.truth)? },
            ];
            for (i, row, mask) in &sample.masks {
                pictures.push(Picture { name: format!("frame{frame}-seg{i}"), caption: name(row), png: gray(mask)? });
            }
            for (i, row, grid, map) in &sample.rollouts {
                let png = images::overlay_png(&Gray { side, pixels: &sample.heatmap }, &Gray { side: *grid, pixels: map })?;
                pictures.push(Picture { name: format!("frame{frame}-rollout{i}"), caption: format!("rollout: {}", row.variant()), png });
            }
            self.blocks.push(Block::Images(pictures));
        }
        Ok(())
    }

    /// A few test frames' true grids beside what each caption probe generated and its parse.
    pub fn captions(&mut self, study: &Study, captioners: &[Captioner], count: usize) -> anyhow::Result<()> {
        let Some(labels) = &study.labels else { return Ok(()) };
        let Some(first) = captioners.first() else { return Ok(()) };
        let frames: Vec<u64> = first.generated.keys().copied().take(count).collect();
        if frames.is_empty() {
            return Ok(());
        }
        self.blocks.push(Block::Heading(1, "Sample generated captions".into()));
        let mut text = String::new();
        for frame in frames {
            let truth = &labels.frames.get(frame as usize).with_context(|| format!("frame {frame} is not in the labels"))?.grid;
            text += &format!("frame {frame}\n  true grid: {}\n", grid_text(truth));
            for c in captioners {
                if let Some((caption, grid)) = c.generated.get(&frame) {
                    text += &format!("  {}: {caption}\n    parsed: {}\n", name(&c.row), grid_text(grid));
                }
            }
        }
        self.blocks.push(Block::Code(text));
        Ok(())
    }
}

/// Every probe and segmenter instance with its overlap checks, those that made any.
fn hygiene_checks(study: &Study) -> Vec<(&str, &Instance, &[identity::Overlap])> {
    study
        .probes
        .iter()
        .map(|p| (p.label.as_str(), &p.instance, p.summary.hygiene.as_slice()))
        .chain(study.segments.iter().map(|s| (s.label.as_str(), &s.instance, s.summary.hygiene.as_slice())))
        .filter(|(_, _, rows)| !rows.is_empty())
        .collect()
}

/// An encoder's log averaged across seeds, epoch by epoch.
fn mean_curve(group: &[&EncoderRun], key: &str) -> Vec<(f64, f64)> {
    let epochs = group.iter().map(|e| e.log.len()).min().unwrap_or(0);
    (0..epochs)
        .filter_map(|i| {
            let values: Vec<f64> = group.iter().filter_map(|e| e.log[i][key].as_f64()).collect();
            let epoch = group[0].log[i]["epoch"].as_f64()?;
            (values.len() == group.len()).then(|| (epoch, Stat(values).mean()))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each setting is shown once, as `key = value`, on lines of at most 100 columns (a value
    /// longer than a line has one of its own).
    #[test]
    fn settings_wrap_between_pairs() {
        let long = "x".repeat(120);
        let settings = serde_json::json!({"accumulate": 1, "betas": [0.9, 0.98], "device": "cpu", "encoder": "conv-tiny",
            "epochs": 10, "lr": 0.001, "numerics": "portable", "objective": "sg-clip", "alpha": 4.0, "init": long, "warmup_epochs": 1.0});
        let text = settings_text("pretrain[alpha4]", &settings);
        for width in 1..60 {
            let one = serde_json::json!({"a": "y".repeat(width), "b": "z".repeat(90 - width), "c": 1, "d": "w".repeat(width)});
            assert!(settings_text("s", &one).lines().all(|l| l.len() <= SETTINGS_WIDTH), "{}", settings_text("s", &one));
        }
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "pretrain[alpha4]");
        assert!(lines[1..].iter().all(|l| l.starts_with("  ")), "{text}");
        assert!(lines.iter().all(|l| l.len() <= SETTINGS_WIDTH || l.contains(&long)), "{text}");
        let pairs: Vec<&str> = lines[1..].iter().flat_map(|l| l.trim().trim_end_matches(',').split(", ")).collect();
        let expected: Vec<String> = settings.as_object().unwrap().iter().map(|(k, v)| format!("{k} = {v}")).collect();
        assert_eq!(pairs.len(), expected.len(), "{text}");
        assert!(text.contains("betas = [0.9,0.98]") && text.contains("device = \"cpu\""), "{text}");
    }
}
