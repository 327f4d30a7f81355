//! The linear probe end to end through the real binaries: on small data the test makes through
//! the pipeline, ridge from the frozen encoder's features and from raw pixels both read the
//! counts back better than a trivial predictor (each frame given the training split's mean
//! counts, rounded), and the pixel baseline does not fan out over the encoder's variants.

use std::path::{Path, PathBuf};

use crate::common::rlmflow;
use rlmflow_stages::grid::CELLS;
use rlmflow_stages::identity::Split;
use rlmflow_stages::labels::Labels;
use rlmflow_stages::probe::score;

const LINEAR: &str = r#"
[stages.linear]
kind = "probe"
operator = "linear"
numerics = "native"

[stages.pixels]
kind = "probe"
operator = "linear"
numerics = "native"
source = "pixels"
inputs = { encoder = [] }
"#;

fn object(dir: &Path, label: &str) -> PathBuf {
    crate::common::output(dir, "probe", label)
}

#[test]
fn ridge_on_encoder_features_and_on_pixels_beats_a_trivial_predictor() {
    let _turn = crate::common::one_at_a_time();
    let dir = crate::common::scratch("probe-linear", &format!("{}{}{LINEAR}", crate::common::data_stages("probe"), crate::common::encoders(true)));
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--json"]);
    assert!(ok, "{out}");
    let pixel_runs = out.lines().filter(|l| l.contains("\"stage_finished\"") && l.contains("\"stage\":\"pixels")).count();
    assert_eq!(pixel_runs, 1, "the pixel baseline runs once, not per encoder variant");

    // The trivial predictor: the training split's mean counts, rounded, for every test frame.
    let labels = Labels::open(&object(&dir, "labels")).unwrap();
    let train: Vec<&[u32; CELLS]> = labels.split(Split::Train).map(|f| &f.grid.counts).collect();
    let mean: [u32; CELLS] = std::array::from_fn(|c| (train.iter().map(|t| f64::from(t[c])).sum::<f64>() / train.len() as f64).round() as u32);
    let truth: Vec<[u32; CELLS]> = labels.split(Split::Test).map(|f| f.grid.counts).collect();
    let trivial = score(&vec![mean; truth.len()], &truth).overall.f1;

    for (label, rows) in
        [("pixels", vec!["pixels"]), ("linear[clip]", vec!["cls", "mean-patch", "patches"]), ("linear[random]", vec!["cls", "mean-patch", "patches"])]
    {
        let summary = rlmflow_stages::probe::read_summary(&object(&dir, label)).unwrap();
        let names: Vec<&str> = summary.rows.iter().map(|r| r.features.as_str()).collect();
        assert_eq!(names, rows, "{label}");
        assert_eq!(summary.test_frames as usize, truth.len());
        let predictions = std::fs::read_to_string(object(&dir, label).join("predictions.jsonl")).unwrap();
        assert_eq!(predictions.lines().count(), truth.len() * rows.len());
        for row in &summary.rows {
            assert!(row.scores.overall.f1 > trivial, "{label} {}: F1 {} vs trivial {trivial}", row.features, row.scores.overall.f1);
        }
    }
}

const CAPTIONER: &str = r#"
[stages.clipcap]
kind = "probe"
operator = "clipcap"
device = "cpu"
numerics = "native"
epochs = 12
batch = 32
lr = 3e-3
"#;

#[test]
fn clipcap_learns_to_caption_and_true_captions_score_perfectly() {
    let _turn = crate::common::one_at_a_time();
    let dir =
        crate::common::scratch("probe-clipcap", &format!("{}{}{CAPTIONER}", crate::common::data_stages("clipcap"), crate::common::encoders(false)));
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    let labels = Labels::open(&crate::common::output(&dir, "clipcap", "labels")).unwrap();
    let test: Vec<u64> = labels.split(Split::Test).map(|f| f.frame).collect();
    let truth: Vec<[u32; CELLS]> = labels.split(Split::Test).map(|f| f.grid.counts).collect();

    // The scoring path itself: the true template captions parse back to precision = recall = 1.
    let captions = rlmflow_stages::captions::Captions::open(&crate::common::output(&dir, "clipcap", "captions")).unwrap();
    let first: Vec<String> =
        test.iter().map(|&f| captions.captions.iter().find(|c| c.frame == f).expect("every frame has captions").caption.clone()).collect();
    let (_, perfect) = rlmflow_probe_torch::score_captions(&first, &truth);
    assert_eq!((perfect.overall.precision, perfect.overall.recall), (1.0, 1.0));

    let object = crate::common::output(&dir, "clipcap", "clipcap");
    let summary = rlmflow_stages::probe::read_summary(&object).unwrap();
    let row = &summary.rows[0];
    let log = row.details["log"].as_array().unwrap();
    let loss = |i: usize, k: &str| log[i][k].as_f64().unwrap();
    assert!(loss(log.len() - 1, "loss") < loss(0, "loss") && loss(log.len() - 1, "validation_loss") < loss(0, "validation_loss"), "{log:?}");
    crate::common::assert_curves_hold(&object, log);
    // The trivial predictor: the training split's mean counts, rounded, for every test frame.
    let train: Vec<&[u32; CELLS]> = labels.split(Split::Train).map(|f| &f.grid.counts).collect();
    let mean: [u32; CELLS] = std::array::from_fn(|c| (train.iter().map(|t| f64::from(t[c])).sum::<f64>() / train.len() as f64).round() as u32);
    let trivial = score(&vec![mean; truth.len()], &truth).overall.f1;
    assert!(row.scores.overall.f1 > trivial, "F1 {} vs trivial {trivial}", row.scores.overall.f1);
    let predictions = std::fs::read_to_string(object.join("predictions.jsonl")).unwrap();
    assert_eq!(predictions.lines().count(), truth.len());
    assert!(predictions.lines().all(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["caption"].is_string()));
}
