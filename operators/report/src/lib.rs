//! The `paper` report operator: every encoder, probe and segmenter a pipeline ran, gathered into
//! the paper's tables and figures for this run.
//!
//! ```text
//! report.md      the report, linking the figures below
//! report.html    the same report in one self-contained page (figures inline, nothing fetched)
//! figures/       SVG charts (plotters) and PNG sample frames
//! metrics.json   every number in the tables: per row, mean, sd and the per-seed values
//! report.rrd     a Rerun recording: sample frames, masks, actors, captions, training curves
//! ```
//!
//! Rows are stage instances; instances that differ only in their `seed` dimension are one row
//! shown as mean ± sd (sample standard deviation). A row's meaning comes from the encoder it
//! read: `epochs = 0` is the random-init sanity row, the `counts` objective the upper reference,
//! `clip` and `sg-clip` the paper's methods (whose own numbers stand beside ours), a probe on
//! pixels and the U-Net the baselines.

mod claims;
mod doc;
mod images;
mod paper;
mod plots;
#[cfg(feature = "rerun")]
mod recording;
mod samples;
mod sections;
mod stats;
mod study;

use rlmflow_stages::{Context, Operator, OperatorSpec, Outcome, SettingError, Settings};
use serde::{Deserialize, Serialize};

pub use study::Instance;

/// The `paper` operator.
pub struct Paper;

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PaperSettings {
    pub title: String,
    /// Sample test frames shown (of those the segmenters kept), 0..=32.
    pub samples: usize,
    /// Test frames whose generated captions are shown, 0..=64.
    pub captions: usize,
    /// Write `report.rrd` (needs the build's Python feature).
    pub rerun: bool,
    /// The paper's segmentation table quoted beside ours: `carla` (its simulated test set) or
    /// `radiate` (its sim-to-real table, for segmenters trained and tested on RADIATE).
    pub paper: paper::Table,
    /// The pipeline's `[claims]`, which the engine hands over: the report opens with them.
    pub claims: Option<rlmflow_stages::claims::Spec>,
}

impl Default for PaperSettings {
    fn default() -> Self {
        PaperSettings { title: "rlmflow report".into(), samples: 4, captions: 3, rerun: true, paper: paper::Table::Carla, claims: None }
    }
}

impl Settings for PaperSettings {
    const CLAIMS: Option<&'static str> = Some("claims");

    fn check(&self) -> Result<(), SettingError> {
        SettingError::check_range("samples", self.samples, 0..=32)?;
        SettingError::check_range("captions", self.captions, 0..=64)?;
        if self.rerun && !cfg!(feature = "rerun") {
            return Err(SettingError::new("rerun", "this build has no Python (feature `python`), so it cannot write report.rrd; set rerun = false"));
        }
        Ok(())
    }
}

impl Operator for Paper {
    type Settings = PaperSettings;

    fn spec(&self) -> OperatorSpec {
        OperatorSpec {
            name: "paper",
            kind: "report",
            version: 7,
            inputs: None,
            summary: "the paper's tables and figures for this run: Markdown, self-contained HTML, metrics.json and a Rerun recording",
        }
    }

    fn run(&self, s: &PaperSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let study = study::Study::read(ctx)?;
        let progress = ctx.progress(8, "sections");
        let mut report = sections::Report { blocks: Vec::new(), metrics: serde_json::Map::new() };
        // Results first: the claims, the hygiene's verdict, the probes' and segmenters' tables.
        let (verdicts, contrasts) = match &s.claims {
            Some(spec) => claims::decided(&study, spec)?,
            None => Default::default(),
        };
        if let Some(spec) = &s.claims {
            report.claims(spec, &verdicts);
        }
        report.hygiene_verdict(&study);
        report.captioning(&study)?;
        progress.inc(1);
        report.segmentation(&study, s.paper)?;
        progress.inc(1);
        report.contrasts(&study, &contrasts)?;
        progress.inc(1);
        report.pretraining(&study)?;
        progress.inc(1);
        let (samples, captioners) = (samples::samples(&study, s.samples)?, samples::captioners(&study)?);
        report.samples(&samples)?;
        progress.inc(1);
        report.captions(&study, &captioners, s.captions)?;
        report.dataset(&study)?;
        report.hygiene(&study);
        report.inputs(&study);
        progress.inc(1);
        doc::write(&ctx.output_dir, &s.title, &report.blocks)?;
        let metrics = serde_json::Value::Object(report.metrics);
        let text = serde_json::to_string_pretty(&metrics)? + "\n";
        std::fs::write(ctx.output_dir.join("metrics.json"), &text)?;
        progress.inc(1);
        #[cfg(feature = "rerun")]
        let entities = if s.rerun {
            let id = format!("rlmflow-report-{}", &blake3::hash(text.as_bytes()).to_hex()[..16]);
            recording::write(ctx, &study, (&samples, &captioners, &contrasts), &ctx.output_dir, &id)?
        } else {
            0
        };
        // Settings::check refuses rerun = true without the feature.
        #[cfg(not(feature = "rerun"))]
        let entities = 0;
        progress.inc(1);
        progress.finish();
        let rows = |key: &str| metrics.get(key).and_then(|v| v.as_object()).map_or(0, |o| o.len());
        let counts =
            serde_json::json!({"captioning_rows": rows("captioning"), "segmentation_rows": rows("segmentation"), "rerun_entities": entities});
        ctx.event("report", counts.clone());
        Ok(Outcome {
            metrics: counts,
            summary: format!(
                "{} encoders, {} caption-table rows, {} segmentation rows{}",
                rows("pretrain"),
                rows("captioning"),
                rows("segmentation"),
                if entities > 0 { format!(", {entities} Rerun entities") } else { String::new() }
            ),
        })
    }
}
