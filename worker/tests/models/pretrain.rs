//! Pretraining end to end through the real binaries: `rlmflow` plans and the `rlmflow-torch`
//! worker beside it trains. On small data the test makes through the pipeline, the CI-size model
//! learns (retrieval well above chance and above the same model untrained), its TensorBoard
//! curves read back as its `train.jsonl` under run names TensorBoard takes from `results/`, and a run killed between epochs resumes to the same
//! weights and curves. (Fresh processes give the stored bytes:
//! `numerics.rs`.)

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use crate::common::{rlmflow, rlmflow_exe, scratch};

/// Pipeline `name`: the data stages, then `pretrain` as given.
fn pipeline(name: &str, pretrain: &str) -> String {
    format!(
        "{}\n[stages.pretrain]\noperator = \"clip\"\ndevice = \"cpu\"\n{}\nbatch = 64\n{pretrain}\n",
        crate::common::data_stages(name),
        crate::common::NATIVE
    )
}

/// The Encoder artifact of `label` in the last run of pipeline `name`.
fn encoder(dir: &Path, name: &str, label: &str) -> PathBuf {
    crate::common::output(dir, name, label)
}

fn summary(dir: &Path, name: &str, label: &str) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(encoder(dir, name, label).join("encoder.json")).unwrap()).unwrap()
}

#[test]
fn the_ci_size_model_learns_retrieval_above_chance_and_above_random_init() {
    let _turn = crate::common::one_at_a_time();
    let dir = scratch(
        "learns",
        &pipeline(
            "learns",
            "epochs = 12\nwarmup_epochs = 1.0\n[stages.pretrain.variants]\nclip = {}\nsgclip = { objective = \"sg-clip\", alpha = 4.0 }\nrandom = { epochs = 0, warmup_epochs = 0.0 }",
        ),
    );
    let reader = std::thread::spawn(rlmflow_test_support::tensorboard::install);
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    reader.join().unwrap();
    // `tensorboard --logdir results/` names each run by its stage and variant.
    assert_eq!(rlmflow_test_support::tensorboard::runs(&dir.join("results")), ["pretrain/clip", "pretrain/random", "pretrain/sgclip"]);
    let random = summary(&dir, "learns", "pretrain[random]");
    for label in ["pretrain[clip]", "pretrain[sgclip]"] {
        let s = summary(&dir, "learns", label);
        let top5 = s["last"]["top5"].as_f64().unwrap();
        let chance = s["chance_top5"].as_f64().unwrap();
        assert!(top5 >= 3.0 * chance, "{label}: top-5 {top5} vs chance {chance}");
        assert!(top5 > random["last"]["top5"].as_f64().unwrap(), "{label}: top-5 {top5} vs random init {}", random["last"]);
        let log = std::fs::read_to_string(encoder(&dir, "learns", label).join("train.jsonl")).unwrap();
        let losses: Vec<f64> = log.lines().map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["loss"].as_f64().unwrap()).collect();
        assert_eq!(losses.len(), 12);
        assert!(losses[11] < losses[0], "{label}: loss {losses:?}");
    }
    // SG-CLIP logs its soft targets' mass off the diagonal per batch (CLIP's is 0).
    for (label, positive) in [("pretrain[sgclip]", true), ("pretrain[clip]", false)] {
        let log = std::fs::read_to_string(encoder(&dir, "learns", label).join("train.jsonl")).unwrap();
        for line in log.lines() {
            let line: serde_json::Value = serde_json::from_str(line).unwrap();
            let per_batch = line["batch_off_diagonal"].as_array().unwrap();
            assert_eq!(per_batch.len(), line["batch_loss"].as_array().unwrap().len());
            let masses: Vec<f64> = per_batch.iter().map(|m| m.as_f64().unwrap()).collect();
            assert!(masses.iter().all(|&m| (0.0..1.0).contains(&m)), "{label}: {line}");
            assert_eq!(masses.iter().any(|&m| m > 0.0), positive, "{label}: {line}");
        }
        assert!(summary(&dir, "learns", label)["last"].get("batch_loss").is_none(), "the summary keeps the epoch figures only");
    }
    // The curves, as TensorBoard's own reader reads them, are train.jsonl's numbers: each step's
    // loss and off-diagonal mass, each epoch's figures at its last step.
    for label in ["pretrain[clip]", "pretrain[sgclip]", "pretrain[random]"] {
        let scalars = rlmflow_test_support::tensorboard::scalars(&encoder(&dir, "learns", label).join("events.out.tfevents.rlmflow"));
        let at = |step: u64, tag: &str| -> f64 {
            let found: Vec<f64> = scalars.iter().filter(|(s, t, _)| *s == step && t == tag).map(|(_, _, v)| *v).collect();
            assert_eq!(found.len(), 1, "{label}: {tag} at step {step}: {found:?}");
            found[0]
        };
        let log = std::fs::read_to_string(encoder(&dir, "learns", label).join("train.jsonl")).unwrap();
        let (mut epoch_figures, mut step_values) = (0, 0);
        for line in log.lines() {
            let line: serde_json::Value = serde_json::from_str(line).unwrap();
            let step = line["step"].as_u64().unwrap();
            for (name, value) in line.as_object().unwrap() {
                let Some(value) = value.as_f64().filter(|_| name != "epoch" && name != "step") else { continue };
                assert_eq!(at(step, &format!("epoch/{name}")), f64::from(value as f32), "{label}: {name} at step {step}");
                epoch_figures += 1;
            }
            let Some(losses) = line["batch_loss"].as_array() else { continue };
            let first = step + 1 - losses.len() as u64;
            for (k, (loss, mass)) in losses.iter().zip(line["batch_off_diagonal"].as_array().unwrap()).enumerate() {
                assert_eq!(at(first + k as u64, "train/loss"), f64::from(loss.as_f64().unwrap() as f32), "{label}");
                assert_eq!(at(first + k as u64, "train/off_diagonal"), f64::from(mass.as_f64().unwrap() as f32), "{label}");
                step_values += 2;
            }
        }
        let per_step = scalars.iter().filter(|(_, t, _)| t.starts_with("train/")).count();
        assert_eq!(per_step, step_values + step_values / 2, "{label}: loss, lr and mass per step");
        assert_eq!(scalars.len() - per_step, epoch_figures, "{label}: nothing else");
    }
}

#[test]
fn a_run_killed_between_epochs_resumes_to_the_weights_of_an_uninterrupted_one() {
    let _turn = crate::common::one_at_a_time();
    use std::os::unix::process::CommandExt;
    let text = pipeline("resumes", "epochs = 4\nwarmup_epochs = 1.0");
    let reference = scratch("reference", &text);
    let (ok, out) = rlmflow(&reference, &["run", "p.toml"]);
    assert!(ok, "{out}");
    let expected = std::fs::read(encoder(&reference, "resumes", "pretrain").join("model.safetensors")).unwrap();

    // Its own store: the reference's record would make the killed run a cache hit.
    let dir = crate::common::scratch_alone("killed", &text);
    let mut run =
        Command::new(rlmflow_exe()).current_dir(&dir).args(["run", "p.toml"]).stdout(std::process::Stdio::null()).process_group(0).spawn().unwrap();
    let epochs_done = |dir: &Path| -> usize {
        let Ok(checkpoints) = std::fs::read_dir(dir.join(".rlmflow/checkpoints")) else { return 0 };
        checkpoints
            .flatten()
            .filter_map(|c| std::fs::read(c.path().join("state.json")).ok())
            .filter_map(|b| serde_json::from_slice::<Vec<serde_json::Value>>(&b).ok())
            .map(|log| log.len())
            .max()
            .unwrap_or(0)
    };
    let t0 = Instant::now();
    while epochs_done(&dir) == 0 {
        assert!(t0.elapsed() < Duration::from_secs(300), "no epoch was checkpointed");
        std::thread::sleep(Duration::from_millis(10));
    }
    unsafe { libc::kill(-(run.id() as i32), libc::SIGKILL) };
    run.wait().unwrap();
    // While it trained, its results link was its checkpoint, where its curves grow.
    let live = dir.join("results/pretrain/events.out.tfevents.rlmflow");
    assert!(
        live.is_file()
            && std::fs::canonicalize(dir.join("results/pretrain")).unwrap().starts_with(dir.join(".rlmflow/checkpoints").canonicalize().unwrap())
    );
    let done = epochs_done(&dir);
    assert!((1..4).contains(&done), "killed after {done} of 4 epochs");
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--json"]);
    assert!(ok, "{out}");
    assert!(out.contains("\"name\":\"resumed\""), "the rerun resumed from the checkpoint: {out}");
    let resumed = std::fs::read(encoder(&dir, "resumes", "pretrain").join("model.safetensors")).unwrap();
    assert!(resumed == expected, "resumed after {done} epochs, the weights differ");
    let curves = |dir: &Path| std::fs::read(dir.join("results/pretrain/events.out.tfevents.rlmflow")).unwrap();
    assert!(curves(&dir) == curves(&reference), "resumed after {done} epochs, the TensorBoard curves differ");
}
