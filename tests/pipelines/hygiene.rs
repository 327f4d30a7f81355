//! Evaluation hygiene: a probe never tests on frames its encoder learnt from.

use super::*;

/// The default pipeline's structure at small scale: the encoder pretrains on drives mixed with
/// placed frames, labelled and tokenised in a chain of their own, and the probe tests on the
/// placed frames labelled alone.
fn hygiene_pipeline(probe_settings: &str, split_seed: u64) -> String {
    format!(
        r#"[pipeline]
name = "hygiene"
seed = 3

[stages.drives]
kind = "scenes"
operator = "highway-env"
frames = 16
episode_frames = 4
radar = {{ image = 32 }}

[stages.procedural]
kind = "scenes"
operator = "procedural"
frames = 60
radar = {{ image = 32 }}

[stages.mixed]
kind = "mix"
operator = "concat"
inputs = {{ scenes = ["drives", "procedural"] }}

[stages.mixed_labels]
kind = "labels"
operator = "ego-grid"
inputs = {{ scenes = "mixed" }}
split_seed = {split_seed}

[stages.labels]
operator = "ego-grid"
inputs = {{ scenes = "procedural" }}

[stages.mixed_captions]
kind = "captions"
operator = "template"
per_frame = 2
inputs = {{ labels = "mixed_labels" }}

[stages.mixed_tokens]
kind = "tokens"
operator = "bpe"
vocab = 300
context = 96
inputs = {{ captions = "mixed_captions" }}

[stages.pretrain]
operator = "clip"
inputs = {{ scenes = "mixed", labels = "mixed_labels", tokens = "mixed_tokens" }}
epochs = 1
batch = 8
device = "cpu"

[stages.linear]
kind = "probe"
operator = "linear"
inputs = {{ scenes = "procedural", labels = "labels" }}
lambdas = [1.0]
{probe_settings}

[stages.report]
operator = "paper"
inputs = {{ scenes = "procedural", labels = "labels" }}
samples = 1
captions = 1
"#
    )
}

/// The report's hygiene rows of a run in `dir`: (instance, against, learnt-from frames, overlap).
fn hygiene_rows(dir: &Path) -> Vec<(String, String, u64, u64)> {
    let store = rlmflow_cache::Store::open_existing(&dir.join(".rlmflow")).unwrap().unwrap();
    let report = store.object_dir(&output_digest(dir, "hygiene", "report"));
    let metrics: serde_json::Value = serde_json::from_slice(&std::fs::read(report.join("metrics.json")).unwrap()).unwrap();
    metrics["hygiene"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            let c = &r["check"];
            (
                r["instance"].as_str().unwrap().into(),
                c["against"].as_str().unwrap().into(),
                c["frames"].as_u64().unwrap(),
                c["overlap"].as_u64().unwrap(),
            )
        })
        .collect()
}

#[test]
fn a_probe_never_tests_on_frames_its_encoder_learnt_from_and_a_leak_is_refused_unless_allowed() {
    // The shipped structure: the same split settings in both labels chains, so a placed frame is
    // in the same split in the mix as alone, and every count is zero.
    let dir = scratch("hygiene-clean", &hygiene_pipeline("", 0));
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    let rows = hygiene_rows(&dir);
    let against: Vec<&str> = rows.iter().map(|r| r.1.as_str()).collect();
    assert_eq!(against, ["encoder training", "encoder's tokenizer"], "{rows:?}");
    assert!(rows.iter().all(|(instance, _, frames, overlap)| instance == "linear" && *frames > 0 && *overlap == 0), "{rows:?}");
    // Not vacuous: the encoder trained on placed frames the probe trains on.
    let store = rlmflow_cache::Store::open_existing(&dir.join(".rlmflow")).unwrap().unwrap();
    let trained = std::fs::read_to_string(store.object_dir(&output_digest(&dir, "hygiene", "pretrain")).join("trained_frames.txt")).unwrap();
    let labels = std::fs::read_to_string(store.object_dir(&output_digest(&dir, "hygiene", "labels")).join("labels.jsonl")).unwrap();
    let shared = labels.lines().filter(|l| l.contains("\"split\":\"train\"") && trained.lines().any(|id| l.contains(id))).count();
    assert!(shared > 10, "{shared} placed training frames in the encoder's training set");

    // The mix split with another seed: most of the probe's test frames are in the encoder's
    // training split, and the probe stops, naming both stages and the fix.
    let dir = scratch("hygiene-leak", &hygiene_pipeline("", 1));
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(!ok, "{out}");
    assert!(out.contains("linear: ") && out.contains("test frames are among the") && out.contains("`pretrain` learnt from"), "{out}");
    assert!(out.contains("allow_test_overlap = true"), "{out}");
    // Opted in, it runs and the report flags the row.
    std::fs::write(dir.join("p.toml"), hygiene_pipeline("allow_test_overlap = true", 1)).unwrap();
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    let rows = hygiene_rows(&dir);
    assert!(rows.iter().any(|(_, against, _, overlap)| against == "encoder training" && *overlap > 0), "{rows:?}");
    let report = std::fs::read_to_string(
        rlmflow_cache::Store::open_existing(&dir.join(".rlmflow"))
            .unwrap()
            .unwrap()
            .object_dir(&output_digest(&dir, "hygiene", "report"))
            .join("report.md"),
    )
    .unwrap();
    assert!(report.contains("OVERLAP (allowed)") && report.contains("not clean test results"), "{report}");
}
