//! `report.rrd`: the sample test frames (heatmap, true and predicted masks, actor positions,
//! true grid and generated captions) and the training curves, written by the rerun-sdk package
//! in the managed Python environment (`rerun_report.py`, compiled in).

use std::collections::BTreeMap;
use std::path::Path;

use rlmflow_python::embed::{self, pyo3};
use rlmflow_stages::Context;
use serde_json::json;

use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict};

use crate::claims::{Contrast, sample_mask};
use crate::samples::{Captioner, Sample};
use crate::sections::grid_text;
use crate::stats::rows;
use crate::study::{Instance, Study};

const HELPER: &str = include_str!("rerun_report.py");
pub const FILE: &str = "report.rrd";

/// An entity path part from a row: its stage and variant, with anything but letters, digits,
/// `-`, `_` and `=` replaced by `_`.
fn entity(row: &Instance) -> String {
    let variant: String = row.variant().chars().map(|c| if c.is_ascii_alphanumeric() || "-_=".contains(c) { c } else { '_' }).collect();
    if variant.is_empty() { row.stage.clone() } else { format!("{}/{variant}", row.stage) }
}

/// The sample frames, the caption probes and the claims' contrasts, as the document shows them.
type Shown<'a> = (&'a [Sample], &'a [Captioner], &'a [Contrast]);

/// Writes the recording; returns how many entities it holds.
pub fn write(ctx: &Context, study: &Study, (samples, captioners, contrasts): Shown, dir: &Path, recording_id: &str) -> anyhow::Result<usize> {
    let mut scalars = serde_json::Map::new();
    for (row, group) in rows(&study.encoders, |e| &e.instance) {
        for key in ["loss", "top1", "off_diagonal"] {
            let points: Vec<serde_json::Value> = group[0].log.iter().filter_map(|l| Some(json!([l["epoch"].as_u64()?, l[key].as_f64()?]))).collect();
            if !points.is_empty() {
                scalars.insert(format!("train/{}/{key}", entity(&row)), points.into());
            }
        }
    }
    let env = rlmflow_python::ensure(&mut |note| ctx.event("python", json!({ "note": note })))?;
    embed::start(&env)?;
    Python::attach(|py| -> anyhow::Result<usize> {
        let py_err = |e: PyErr| anyhow::anyhow!("writing {FILE}: {}", embed::traceback(py, &e));
        let module = embed::module(py, "rlmflow_rerun_report", HELPER)?;
        let list = samples
            .iter()
            .map(|f| -> PyResult<Bound<'_, PyDict>> {
                let d = PyDict::new(py);
                d.set_item("frame", f.frame)?;
                d.set_item("side", f.side)?;
                d.set_item("heatmap", PyBytes::new(py, &f.heatmap))?;
                d.set_item("truth", PyBytes::new(py, &f.truth))?;
                let masks = PyDict::new(py);
                for (_, row, mask) in &f.masks {
                    masks.set_item(entity(row), PyBytes::new(py, mask))?;
                }
                d.set_item("masks", masks)?;
                d.set_item("actors", f.actors.iter().map(|a| a.to_vec()).collect::<Vec<_>>())?;
                let truth = study.labels.as_ref().map(|l| grid_text(&l.frames[f.frame as usize].grid)).unwrap_or_default();
                d.set_item("true_grid", truth)?;
                let captions: BTreeMap<String, &String> =
                    captioners.iter().filter_map(|c| c.generated.get(&f.frame).map(|(caption, _)| (entity(&c.row), caption))).collect();
                d.set_item("captions", captions)?;
                Ok(d)
            })
            .collect::<PyResult<Vec<_>>>()
            .map_err(py_err)?;
        let contrasted = contrast_frames(py, study, contrasts).map_err(|e| anyhow::anyhow!("{FILE}: {e:#}"))?;
        let path = dir.join(FILE);
        let entities = module
            .getattr("record")
            .and_then(|f| f.call1((path.to_string_lossy().as_ref(), recording_id, serde_json::Value::Object(scalars).to_string(), list, contrasted)))
            .and_then(|n| n.extract::<usize>())
            .map_err(py_err)?;
        Ok(entities)
    })
}

/// Each claim's most different frames (as the document shows them) for the recording: per
/// frame the claim, its rank, the heatmap, the true grid, each side's output and, for
/// segmenters, the true and predicted masks the sides kept.
fn contrast_frames<'py>(py: Python<'py>, study: &Study, contrasts: &[Contrast]) -> anyhow::Result<Vec<Bound<'py, PyDict>>> {
    let Some(scenes) = &study.scenes else { return Ok(Vec::new()) };
    let side = scenes.summary.images[0].size;
    let mut out = Vec::new();
    for c in contrasts {
        for (rank, f) in c.differences.frames.iter().take(crate::claims::CONTRAST_FRAMES).enumerate() {
            let py_err = |e: PyErr| anyhow::anyhow!("{}", embed::traceback(py, &e));
            let d = PyDict::new(py);
            let truth = study.labels.as_ref().and_then(|l| l.frames.get(f.frame as usize)).map(|t| grid_text(&t.grid)).unwrap_or_default();
            let outputs = BTreeMap::from([(c.labels[0].clone(), f.a.clone()), (c.labels[1].clone(), f.b.clone())]);
            let masks = PyDict::new(py);
            if let (Some(dirs), Some(labels)) = (&c.segmenter_dirs, &study.labels) {
                d.set_item("truth_mask", PyBytes::new(py, &labels.mask(f.frame)?)).map_err(py_err)?;
                for (label, dir) in c.labels.iter().zip(dirs) {
                    if let Some(mask) = sample_mask(dir, f.frame)? {
                        masks.set_item(label, PyBytes::new(py, &mask)).map_err(py_err)?;
                    }
                }
            }
            let entity: String = c.claim.chars().map(|ch| if ch.is_ascii_alphanumeric() || "-_".contains(ch) { ch } else { '_' }).collect();
            for (key, value) in [("claim", entity), ("true_grid", truth)] {
                d.set_item(key, value).map_err(py_err)?;
            }
            d.set_item("rank", rank).map_err(py_err)?;
            d.set_item("frame", f.frame).map_err(py_err)?;
            d.set_item("side", side).map_err(py_err)?;
            d.set_item("heatmap", PyBytes::new(py, &scenes.heatmap(f.frame)?)).map_err(py_err)?;
            d.set_item("outputs", outputs).map_err(py_err)?;
            d.set_item("masks", masks).map_err(py_err)?;
            out.push(d);
        }
    }
    Ok(out)
}
