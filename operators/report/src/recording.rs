//! `report.rrd`: the sample test frames (heatmap, true and predicted masks, actor positions,
//! true grid and generated captions) and the training curves, written by the rerun-sdk package
//! in the managed Python environment (`rerun_report.py`, compiled in).

use std::collections::BTreeMap;
use std::path::Path;

use rlmflow_python::embed::{self, pyo3};
use rlmflow_stages::npy::Npy;
use rlmflow_stages::{Context, segment};
use serde_json::json;

use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict};

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

struct Frame {
    frame: u64,
    side: usize,
    heatmap: Vec<u8>,
    truth: Vec<u8>,
    masks: BTreeMap<String, Vec<u8>>,
    actors: Vec<[f64; 2]>,
    true_grid: String,
    captions: BTreeMap<String, String>,
}

/// Writes the recording; returns how many entities it holds.
pub fn write(ctx: &Context, study: &Study, dir: &Path, recording_id: &str, samples: usize) -> anyhow::Result<usize> {
    let mut scalars = serde_json::Map::new();
    for (row, group) in rows(&study.encoders, |e| &e.instance) {
        for key in ["loss", "top1", "off_diagonal"] {
            let points: Vec<serde_json::Value> = group[0].log.iter().filter_map(|l| Some(json!([l["epoch"].as_u64()?, l[key].as_f64()?]))).collect();
            if !points.is_empty() {
                scalars.insert(format!("train/{}/{key}", entity(&row)), points.into());
            }
        }
    }
    let frames = sample_frames(study, samples)?;
    let env = rlmflow_python::ensure(&mut |note| ctx.event("python", json!({ "note": note })))?;
    embed::start(&env)?;
    Python::attach(|py| -> anyhow::Result<usize> {
        let py_err = |e: PyErr| anyhow::anyhow!("writing {FILE}: {}", embed::traceback(py, &e));
        let module = embed::module(py, "rlmflow_rerun_report", HELPER)?;
        let list = frames
            .iter()
            .map(|f| -> PyResult<Bound<'_, PyDict>> {
                let d = PyDict::new(py);
                d.set_item("frame", f.frame)?;
                d.set_item("side", f.side)?;
                d.set_item("heatmap", PyBytes::new(py, &f.heatmap))?;
                d.set_item("truth", PyBytes::new(py, &f.truth))?;
                let masks = PyDict::new(py);
                for (name, mask) in &f.masks {
                    masks.set_item(name, PyBytes::new(py, mask))?;
                }
                d.set_item("masks", masks)?;
                d.set_item("actors", f.actors.iter().map(|a| a.to_vec()).collect::<Vec<_>>())?;
                d.set_item("true_grid", &f.true_grid)?;
                d.set_item("captions", f.captions.clone())?;
                Ok(d)
            })
            .collect::<PyResult<Vec<_>>>()
            .map_err(py_err)?;
        let path = dir.join(FILE);
        let entities = module
            .getattr("record")
            .and_then(|f| f.call1((path.to_string_lossy().as_ref(), recording_id, serde_json::Value::Object(scalars).to_string(), list)))
            .and_then(|n| n.extract::<usize>())
            .map_err(py_err)?;
        Ok(entities)
    })
}

/// The sample test frames every segmenter kept, with what each probe said of them.
fn sample_frames(study: &Study, samples: usize) -> anyhow::Result<Vec<Frame>> {
    let (Some(scenes), Some(labels)) = (&study.scenes, &study.labels) else { return Ok(Vec::new()) };
    let Some(first) = study.segments.iter().find(|s| !s.summary.sample_frames.is_empty()) else { return Ok(Vec::new()) };
    let segmenters = rows(&study.segments, |s| &s.instance);
    let captioners: Vec<(String, BTreeMap<u64, (String, rlmflow_stages::grid::Grid)>)> = rows(&study.probes, |p| &p.instance)
        .into_iter()
        .filter(|(_, g)| g[0].summary.probe == "clipcap")
        .map(|(row, g)| Ok((entity(&row), crate::sections::generated(g[0])?)))
        .collect::<anyhow::Result<_>>()?;
    let side = scenes.summary.images[0].size;
    let mut frames = Vec::new();
    for &frame in first.summary.sample_frames.iter().take(samples) {
        let mut masks = BTreeMap::new();
        for (row, group) in &segmenters {
            if let Some(k) = group[0].summary.sample_frames.iter().position(|&f| f == frame) {
                masks.insert(entity(row), Npy::open(&group[0].dir.join(segment::SAMPLES))?.row_u8(k)?);
            }
        }
        let actors = scenes
            .frame(frame)?
            .actors
            .iter()
            .filter(|a| a.is_vehicle() && (0.0..side as f64).contains(&a.col) && (0.0..side as f64).contains(&a.row))
            .map(|a| [a.col, a.row])
            .collect();
        let captions = captioners.iter().filter_map(|(name, g)| g.get(&frame).map(|(c, _)| (name.clone(), c.clone()))).collect();
        frames.push(Frame {
            frame,
            side,
            heatmap: scenes.heatmap(frame)?,
            truth: labels.mask(frame)?,
            masks,
            actors,
            true_grid: grid_text(&labels.frames[frame as usize].grid),
            captions,
        });
    }
    Ok(frames)
}
