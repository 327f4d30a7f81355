//! The pipeline's claims as the report decides them: the values of each comparison measured
//! from the probes and segmenters the report gathers, with the same measures and rule as
//! `rlmflow claims` (so both say the same), and per claim the test frames where its two
//! instances differ most, for the report to show side by side.

use std::collections::BTreeMap;

use anyhow::{Context as _, bail};
use rlmflow_stages::claims::{Claim, Decision, Metric, Spec, Values, Verdict, decide, signed};
use rlmflow_stages::measure::{self, FrameDifferences};
use rlmflow_stages::{encoder, probe, segment};
use serde_json::Value;

use crate::doc::{Block, Picture};
use crate::images::{self, Gray};
use crate::sections::{Report, grid_text};
use crate::study::{Instance, Study};

/// An instance the report gathered, as a claim reads it.
struct Measured<'s> {
    label: &'s str,
    instance: &'s Instance,
    metrics: Value,
    dir: &'s std::path::Path,
    output: Output,
}

/// What an instance's artifact is, for how two of them differ frame by frame.
#[derive(Clone, Copy, PartialEq)]
enum Output {
    Encoder,
    Probe,
    Segmenter,
}

/// One claim's first comparison at its first shared seed: where the two differ, most first.
pub struct Contrast {
    pub claim: String,
    /// The instances' labels, better first.
    pub labels: [String; 2],
    pub differences: FrameDifferences,
    /// Segmenters: each side's directory, for its sample masks.
    pub segmenter_dirs: Option<[std::path::PathBuf; 2]>,
}

/// Each claim's verdict, and its contrast where both sides keep per-frame outputs.
pub fn decided(study: &Study, spec: &Spec) -> anyhow::Result<(Vec<Verdict>, Vec<Contrast>)> {
    let measured = measured(study)?;
    let mut verdicts = Vec::new();
    let mut contrasts = Vec::new();
    for claim in &spec.claims {
        let values = claim
            .comparisons
            .iter()
            .map(|c| Ok((values(&measured, claim, &c.better)?, values(&measured, claim, &c.than)?)))
            .collect::<anyhow::Result<Vec<_>>>()?;
        verdicts.push(decide(claim, spec.level, spec.looks, &values));
        if let Some(c) = contrast(&measured, claim)? {
            contrasts.push(c);
        }
    }
    Ok((verdicts, contrasts))
}

fn measured(study: &Study) -> anyhow::Result<Vec<Measured<'_>>> {
    let encoders = study.encoders.iter().map(|e| Measured {
        label: &e.label,
        instance: &e.instance,
        metrics: encoder::metrics(&e.encoder.summary),
        dir: &e.encoder.dir,
        output: Output::Encoder,
    });
    let probes = study.probes.iter().map(|p| Measured {
        label: &p.label,
        instance: &p.instance,
        metrics: probe::metrics(&p.summary),
        dir: &p.dir,
        output: Output::Probe,
    });
    let segments = study.segments.iter().map(|s| Measured {
        label: &s.label,
        instance: &s.instance,
        metrics: segment::metrics(&s.summary),
        dir: &s.dir,
        output: Output::Segmenter,
    });
    Ok(encoders.chain(probes).chain(segments).collect())
}

/// Whether `m` is one of the instances `metric` pools over seeds.
fn reads(metric: &Metric, m: &Measured) -> bool {
    m.instance.stage == metric.stage && m.instance.row().assignment == metric.variant
}

fn values(measured: &[Measured], claim: &Claim, metric: &Metric) -> anyhow::Result<Values> {
    let mut seeded = BTreeMap::new();
    let mut fixed = None;
    let mut found = false;
    for m in measured.iter().filter(|m| reads(metric, m)) {
        found = true;
        let value = measure::lookup(&m.metrics, &metric.path)
            .with_context(|| format!("claim `{}`: {} measures no `{}`", claim.name, m.label, metric.path))?;
        match m.instance.seed {
            Some(seed) => {
                seeded.insert(seed, value);
            }
            None => fixed = Some(value),
        }
    }
    if !found {
        bail!("claim `{}` reads `{}`, which the report does not gather: its stage must feed the report", claim.name, metric.label());
    }
    Ok(fixed.map_or(Values::Seeded(seeded), Values::Fixed))
}

/// The claim's first comparison at the first seed both sides ran (or the one each has).
fn contrast(measured: &[Measured], claim: &Claim) -> anyhow::Result<Option<Contrast>> {
    let Some(comparison) = claim.comparisons.first() else { return Ok(None) };
    let sides = |metric: &Metric| -> Vec<&Measured> { measured.iter().filter(|m| reads(metric, m)).collect() };
    let (better, than) = (sides(&comparison.better), sides(&comparison.than));
    let pair = better.iter().find_map(|b| {
        let t = than.iter().find(|t| t.instance.seed.is_none() || b.instance.seed.is_none() || t.instance.seed == b.instance.seed)?;
        Some((*b, *t))
    });
    let Some((b, t)) = pair else { return Ok(None) };
    let mut differences = match (b.output, t.output) {
        (Output::Segmenter, Output::Segmenter) => segment::frame_differences(b.dir, t.dir)?,
        (Output::Probe, Output::Probe) => probe::frame_differences(b.dir, t.dir)?,
        // Encoders keep no per-frame output; nor do a probe and a segmenter share one.
        _ => return Ok(None),
    };
    // A probe's row: the one the claim's metric names (`cls.f1` reads the `cls` row).
    if b.output == Output::Probe {
        let row = comparison.better.path.split('.').next().unwrap_or_default().to_owned();
        differences.frames.retain(|f| f.row == row);
    }
    let segmenter_dirs = (b.output == Output::Segmenter).then(|| [b.dir.to_path_buf(), t.dir.to_path_buf()]);
    Ok(Some(Contrast { claim: claim.name.clone(), labels: [b.label.to_owned(), t.label.to_owned()], differences, segmenter_dirs }))
}

/// How many of each contrast's most different frames the report shows.
pub const CONTRAST_FRAMES: usize = 3;

impl Report {
    /// The report's opening: each claim, the paper's figures beside it where it is the paper's,
    /// the mean paired difference and its interval, the seeds used and the verdict.
    pub fn claims(&mut self, spec: &Spec, verdicts: &[Verdict]) {
        self.blocks.push(Block::Heading(1, "Claims".into()));
        let decided = verdicts.iter().filter(|v| v.decision != Decision::Undecided).count();
        let looks = match spec.looks.first == spec.looks.last {
            true => format!("at its {} seeds", spec.looks.last),
            false => format!("after each seed from {} to {}", spec.looks.first, spec.looks.last),
        };
        self.blocks.push(Block::Paragraph(format!(
            "{decided} of {} claims decided. Each claim compares two metrics paired by seed; it holds when the interval of every \
             comparison's mean per-seed difference lies above the margin, fails when one lies below, and is undecided otherwise. \
             The intervals are {}, looked at {looks}: each verdict is wrong with probability at most {}, however many seeds \
             the run added before it stopped.",
            verdicts.len(),
            rlmflow_stages::claims::METHOD,
            spec.level
        )));
        let mut rows = Vec::new();
        for v in verdicts {
            let verdict = match (v.decision, v.decided_at) {
                (Decision::Holds, Some(n)) => format!("holds (at {n} seeds)"),
                (Decision::Fails, Some(n)) => format!("FAILS (at {n} seeds)"),
                _ => format!("undecided at {} seeds", v.seeds),
            };
            for (i, c) in v.comparisons.iter().enumerate() {
                let interval = c.interval.map_or("–".to_owned(), |(lo, hi)| format!("[{}, {}]", signed(lo), signed(hi)));
                let name = if i == 0 { format!("{}{}", v.claim, if v.required { " (required)" } else { "" }) } else { String::new() };
                rows.push(vec![
                    name,
                    if i == 0 { verdict.clone() } else { String::new() },
                    format!("{} vs {}", c.better, c.than),
                    c.mean.map_or("–".to_owned(), signed),
                    interval,
                    signed(v.margin),
                    c.differences.len().to_string(),
                    if i == 0 { v.paper.clone().unwrap_or_else(|| "–".into()) } else { String::new() },
                ]);
            }
        }
        let header = ["claim", "verdict", "comparison", "mean difference", "interval", "margin", "seeds", "the paper"];
        self.blocks.push(Block::Table { header: header.iter().map(|h| h.to_string()).collect(), rows });
        self.metrics.insert("claims".into(), serde_json::to_value(verdicts).expect("verdicts serialise"));
    }

    /// Per claim, the test frames where its two instances (first comparison, first seed) differ
    /// most: the heatmap, the truth and each instance's output, side by side.
    pub fn contrasts(&mut self, study: &Study, contrasts: &[Contrast]) -> anyhow::Result<()> {
        if contrasts.is_empty() {
            return Ok(());
        }
        self.blocks.push(Block::Heading(1, "Where the claims' instances differ".into()));
        self.blocks.push(Block::Paragraph(
            "For each claim, its first comparison at the first seed both sides ran: the test frames where the two instances' \
             outputs differ most (a probe by the cells it predicts differently, a segmenter by its IoU at 0.5), with the radar \
             heatmap and the truth. `rlmflow compare PIPELINE A B` lists every such frame."
                .into(),
        ));
        let mut metrics = serde_json::Map::new();
        for (k, c) in contrasts.iter().enumerate() {
            let shown: Vec<_> = c.differences.frames.iter().take(CONTRAST_FRAMES).collect();
            self.blocks.push(Block::Paragraph(format!(
                "**{}**: `{}` against `{}`, {} of {} test frames differ ({}).",
                c.claim,
                c.labels[0],
                c.labels[1],
                c.differences.frames.len(),
                c.differences.compared,
                c.differences.unit
            )));
            let mut rows = Vec::new();
            for f in &shown {
                let truth = study.labels.as_ref().and_then(|l| l.frames.get(f.frame as usize)).map_or("–".to_owned(), |t| grid_text(&t.grid));
                // A count of cells whole, an IoU difference to three decimals.
                let differ = if f.differ.fract() == 0.0 { format!("{:.0}", f.differ) } else { format!("{:.3}", f.differ) };
                rows.push(vec![f.frame.to_string(), differ, truth, f.a.clone(), f.b.clone()]);
                if let Some(pictures) = pictures(study, c, k, f.frame)? {
                    self.blocks.push(Block::Images(pictures));
                }
            }
            let header = ["frame", c.differences.unit, "true grid", c.labels[0].as_str(), c.labels[1].as_str()];
            self.blocks.push(Block::Table { header: header.iter().map(|h| h.to_string()).collect(), rows });
            metrics.insert(c.claim.clone(), serde_json::to_value(&c.differences).expect("differences serialise"));
        }
        self.metrics.insert("contrasts".into(), Value::Object(metrics));
        Ok(())
    }
}

/// A contrast frame's pictures: the heatmap, and for segmenters the true mask and each side's
/// predicted one where both kept the frame among their samples.
fn pictures(study: &Study, c: &Contrast, k: usize, frame: u64) -> anyhow::Result<Option<Vec<Picture>>> {
    let Some(scenes) = &study.scenes else { return Ok(None) };
    let side = scenes.summary.images[0].size;
    let gray = |pixels: &[u8]| images::gray_png(&Gray { side, pixels });
    let name = |what: &str| format!("claim{k}-frame{frame}-{what}");
    let mut pictures = vec![Picture { name: name("heatmap"), caption: format!("frame {frame}"), png: gray(&scenes.heatmap(frame)?)? }];
    if let (Some(dirs), Some(labels)) = (&c.segmenter_dirs, &study.labels) {
        pictures.push(Picture { name: name("truth"), caption: "true mask".into(), png: gray(&labels.mask(frame)?)? });
        for (i, dir) in dirs.iter().enumerate() {
            if let Some(mask) = sample_mask(dir, frame)? {
                pictures.push(Picture { name: name(&format!("side{i}")), caption: c.labels[i].clone(), png: gray(&mask)? });
            }
        }
    }
    Ok(Some(pictures))
}

/// A segmenter's predicted probability x 255 on `frame`, where it kept the frame as a sample.
pub fn sample_mask(dir: &std::path::Path, frame: u64) -> anyhow::Result<Option<Vec<u8>>> {
    let summary = segment::read_summary(dir)?;
    let Some(k) = summary.sample_frames.iter().position(|&f| f == frame) else { return Ok(None) };
    Ok(Some(rlmflow_stages::npy::Npy::open(&dir.join(segment::SAMPLES))?.row_u8(k)?))
}
