//! A user's program as a stage (`operator = "script"`), through the real binary, on data stages
//! alone (no model): what it is told and reports, resume from its checkpoint, determinism, the
//! checks of a probe's predictions, and every bad input leaving the store as it was. The shipped
//! example with `embed` and the report is in `ci.rs` (it reads the CI run's encoders).

use super::*;
use crate::ci::finished;

/// Procedural scenes with their labels, captions and tokens: what a probe kind reads.
const DATA: &str = r#"
[pipeline]
name = "p"
seed = 1

[stages.scenes]
operator = "procedural"
frames = 24
radar = { image = 16 }

[stages.labels]
operator = "ego-grid"

[stages.captions]
operator = "template"

[stages.tokens]
operator = "bpe"
vocab = 300
context = 64
"#;

/// Every file below the store's `objects/` and `actions/` but the snapshots of tracked files
/// (a script's sources, a lock: inputs, copied before it runs): what a failed stage must not add.
fn committed(dir: &Path) -> Vec<PathBuf> {
    let store = dir.join(".rlmflow");
    let snapshot = |path: &Path| {
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default();
        store.join("external/manifests").join(name.trim_end_matches(".tree")).exists()
    };
    let mut found = Vec::new();
    for sub in ["objects", "actions"] {
        let mut stack = vec![store.join(sub)];
        while let Some(at) = stack.pop() {
            for entry in std::fs::read_dir(&at).into_iter().flatten().flatten() {
                if snapshot(&entry.path()) {
                    continue;
                }
                if entry.path().is_dir() {
                    stack.push(entry.path());
                } else {
                    found.push(entry.path());
                }
            }
        }
    }
    found.sort();
    found
}

/// A scratch pipeline of the data stages and `stages`, with `files` written beside it.
fn pipeline(name: &str, stages: &str, files: &[(&str, &str)]) -> Scratch {
    let dir = scratch(name, &format!("{DATA}\n{stages}"));
    for (path, text) in files {
        dir.write(path, text);
    }
    dir
}

/// The mean training grid for every test frame: a probe in a dozen lines of numpy.
const MEAN_PROBE: &str = r#"
import json
import numpy as np
from rlmflow import stage
ctx = stage.context()
labels = ctx.read("labels")
train, test = np.flatnonzero(labels.split == "train"), np.flatnonzero(labels.split == "test")
mean = np.rint(labels.counts[train].mean(axis=0) * ctx.settings.get("scale", 1.0)).astype(int)
with open(ctx.output / "predictions.jsonl", "w") as out:
    for f in reversed(test):
        out.write(json.dumps({"frame": int(f), "features": "mean", "counts": mean.tolist()}) + "\n")
stage.progress(1, 1, "rows")
stage.event("row", features="mean")
stage.metrics(train_frames=int(len(train)))
print("the program's own line")
"#;

const MEAN_STAGE: &str = r#"
[stages.mean]
kind = "probe"
operator = "script"
run = ["python", "probes/mean.py"]
sources = ["probes/*.py"]
settings = { scale = 1.0 }
"#;

#[test]
fn a_probe_script_is_scored_by_rlmflow_reports_through_the_protocol_and_follows_its_sources() {
    let dir = pipeline("script-probe", MEAN_STAGE, &[("probes/mean.py", MEAN_PROBE), ("probes/notes.txt", "not a source\n")]);
    let (ok, out) = rlmflow(dir.path(), &["run", "p.toml", "--json"]);
    assert!(ok, "{out}");
    // rlmflow wrote probe.json from the predictions, scored with the paper's rule, and the
    // predictions in the split's order whatever order the program wrote them in.
    let output = rlmflow_test_support::cli::output_dir(&dir.path().join(".rlmflow"), "p", "mean");
    let summary: serde_json::Value = serde_json::from_slice(&std::fs::read(output.join("probe.json")).unwrap()).unwrap();
    assert_eq!(summary["probe"], "script");
    assert_eq!(summary["rows"][0]["features"], "mean");
    let predicted = rlmflow_stages::probe::read_predictions(&output).unwrap();
    let frames: Vec<u64> = predicted.iter().map(|p| p.0).collect();
    assert!(frames.windows(2).all(|w| w[0] < w[1]) && frames.len() as u64 == summary["test_frames"].as_u64().unwrap(), "{frames:?}");
    let labels = rlmflow_stages::labels::Labels::open(&rlmflow_test_support::cli::output_dir(&dir.path().join(".rlmflow"), "p", "labels")).unwrap();
    let truth: Vec<_> = frames.iter().map(|&f| labels.frames[f as usize].grid.counts).collect();
    let grids: Vec<_> = predicted.iter().map(|p| p.2).collect();
    let f1 = rlmflow_stages::probe::score(&grids, &truth).overall.f1;
    assert_eq!(summary["rows"][0]["scores"]["overall"]["f1"].as_f64().unwrap(), f1);
    // The protocol: the event in the run's log, the metrics in the record, the line in the log.
    assert!(out.lines().any(|l| l.contains("\"operator_event\"") && l.contains("\"name\":\"row\"") && l.contains("\"mean\"")), "{out}");
    let (ok, shown) = rlmflow(dir.path(), &["show", "p.toml", "mean", "--json"]);
    assert!(ok, "{shown}");
    let shown: serde_json::Value = serde_json::from_str(&shown).unwrap();
    let record = &shown["instances"][0]["record"];
    assert_eq!(record["metrics"]["script"]["train_frames"], summary["train_frames"], "{shown}");
    assert_eq!(record["metrics"]["mean"]["f1"].as_f64(), Some(f1), "{shown}");
    let log =
        std::fs::read_dir(dir.path().join(".rlmflow/runs")).unwrap().flatten().map(|r| r.path().join("logs/mean.log")).find(|l| l.exists()).unwrap();
    assert!(std::fs::read_to_string(log).unwrap().contains("the program's own line"));

    // A file outside `sources` changes nothing; a comment in the script reruns it, with the
    // file named, and the same predictions cut off what follows (nothing here).
    dir.write("probes/notes.txt", "edited\n");
    let (ok, status) = rlmflow(dir.path(), &["status", "p.toml"]);
    assert!(ok && !status.contains("will run"), "{status}");
    dir.write("probes/mean.py", &format!("{MEAN_PROBE}# a comment\n"));
    let (ok, status) = rlmflow(dir.path(), &["status", "p.toml"]);
    assert!(ok && status.contains("mean") && status.contains("probes/mean.py changed"), "{status}");
    let before = output_digest(dir.path(), "p", "mean");
    let (ok, out) = rlmflow(dir.path(), &["run", "p.toml", "--json"]);
    assert!(ok, "{out}");
    assert_eq!(finished(&out, "ran").iter().map(|(s, _)| s.as_str()).collect::<Vec<_>>(), ["mean"]);
    assert_eq!(output_digest(dir.path(), "p", "mean"), before, "a comment changes no byte of the output");
    // A setting reaches the program through --set, and changes its key.
    let (ok, out) = rlmflow(dir.path(), &["run", "p.toml", "--json", "--set", "mean.settings.scale=0.0"]);
    assert!(ok, "{out}");
    assert_eq!(finished(&out, "ran").len(), 1, "{out}");
}

/// Counts to 6 in steps kept in its checkpoint directory; with `HANG_AFTER=N` in its
/// environment it hangs once after step N (the stage's timeout stops it), as a killed run would.
const STEPS: &str = r#"#!/bin/sh
set -eu
c="$RLMFLOW_CHECKPOINT"
i=0
while [ "$i" -lt 6 ]; do
  if [ ! -f "$c/step-$i" ]; then
    echo "$((i * i + $RLMFLOW_SEED))" > "$c/step-$i.part" && mv "$c/step-$i.part" "$c/step-$i"
    echo "@rlmflow {\"event\": \"step\", \"data\": {\"step\": $i}}"
  fi
  if [ "$i" = "${HANG_AFTER:-none}" ] && [ ! -f "$c/hung" ]; then touch "$c/hung"; sleep 60; fi
  i=$((i + 1))
done
cat "$c"/step-* > "$RLMFLOW_OUTPUT/steps.txt"
"#;

const STEPS_STAGE: &str = r#"
[stages.steps]
kind = "files"
operator = "script"
run = ["./steps.sh"]
inputs = { scenes = "scenes" }
timeout = 3
retries = 1
"#;

#[test]
fn a_script_killed_mid_run_resumes_from_its_checkpoint_to_the_uninterrupted_runs_bytes() {
    let whole = pipeline("script-whole", STEPS_STAGE, &[("steps.sh", STEPS)]);
    let killed = pipeline("script-killed", STEPS_STAGE, &[("steps.sh", STEPS)]);
    for dir in [&whole, &killed] {
        std::fs::set_permissions(dir.path().join("steps.sh"), std::os::unix::fs::PermissionsExt::from_mode(0o755)).unwrap();
    }
    let (ok, out) = rlmflow(whole.path(), &["run", "p.toml", "--json"]);
    assert!(ok, "{out}");
    let exe = env!("CARGO_BIN_EXE_rlmflow");
    let run = Command::new(exe).args(["run", "p.toml", "--json"]).current_dir(killed.path()).env("HANG_AFTER", "2").output().unwrap();
    let out = String::from_utf8_lossy(&run.stdout);
    assert!(run.status.success(), "{out}{}", String::from_utf8_lossy(&run.stderr));
    // The first attempt was stopped at its timeout after three steps; the second did the rest.
    assert!(out.contains("\"stage_retry\""), "{out}");
    let steps: Vec<&str> = out.lines().filter(|l| l.contains("\"name\":\"step\"")).collect();
    assert_eq!(steps.len(), 6, "each step once, across both attempts: {out}");
    assert_eq!(output_digest(killed.path(), "p", "steps"), output_digest(whole.path(), "p", "steps"));
}

#[test]
fn check_determinism_catches_a_script_that_writes_the_time_or_an_unseeded_random_number() {
    let stages = r#"
[stages.clock]
kind = "files"
operator = "script"
run = ["sh", "-c", "date +%s%N > $RLMFLOW_OUTPUT/now"]
inputs = { scenes = "scenes" }

[stages.draw]
kind = "files"
operator = "script"
run = ["python", "draw.py"]
inputs = { scenes = "scenes" }

[stages.seeded]
kind = "files"
operator = "script"
run = ["python", "seeded.py"]
inputs = { scenes = "scenes" }
"#;
    let draw = "import os, random\nopen(os.environ['RLMFLOW_OUTPUT'] + '/x', 'w').write(str(random.random()))\n";
    let seeded = "import os, random\nrandom.seed(int(os.environ['RLMFLOW_SEED']))\nopen(os.environ['RLMFLOW_OUTPUT'] + '/x', 'w').write(str(random.random()))\n";
    let dir = pipeline("script-determinism", stages, &[("draw.py", draw), ("seeded.py", seeded)]);
    for (stage, deterministic) in [("clock", false), ("draw", false), ("seeded", true)] {
        let (ok, out) = rlmflow(dir.path(), &["run", "p.toml", "--check-determinism", stage]);
        assert_eq!(ok, deterministic, "{stage}: {out}");
        assert_eq!(out.contains("NOT DETERMINISTIC"), !deterministic, "{stage}: {out}");
    }
}

#[test]
fn every_bad_script_input_names_its_error_and_leaves_the_store_as_it_was() {
    let dir = pipeline("script-bad", "", &[("src/a.py", "print(1)\n"), ("bad.lock", "no-such-package-for-rlmflow-tests==0.0.1\n")]);
    std::os::unix::fs::symlink("/etc/hostname", dir.path().join("src/out.py")).unwrap();
    let (ok, out) = rlmflow(dir.path(), &["run", "p.toml"]);
    assert!(ok, "{out}");
    let store = committed(dir.path());
    let stage = |body: &str| format!("{DATA}\n[stages.x]\nkind = \"files\"\noperator = \"script\"\ninputs = {{ scenes = \"scenes\" }}\n{body}\n");
    // Config errors: exit status 2, nothing run.
    for (body, says) in [
        ("run = []", "stages.x.run: name the program"),
        ("run = [\"python\", \"src/a.py\"]\nsources = [\"src/none*.py\"]", "`src/none*.py` matches no file"),
        ("run = [\"python\", \"../a.py\"]\nsources = [\"../*.py\"]", "leaves the pipeline's directory"),
        ("run = [\"python\", \"src/a.py\"]\nsources = [\"src/*.py\"]", "is a symbolic link out of the pipeline's directory"),
        ("run = [\"true\"]\npython = \"2.7 x\"", "stages.x.python: is filled in by rlmflow"),
    ] {
        dir.write("p.toml", &stage(body));
        let run = Command::new(env!("CARGO_BIN_EXE_rlmflow")).args(["run", "p.toml"]).current_dir(dir.path()).output().unwrap();
        let text = String::from_utf8_lossy(&run.stderr).into_owned() + &String::from_utf8_lossy(&run.stdout);
        assert_eq!(run.status.code(), Some(2), "{body}: {text}");
        assert!(text.contains(says), "{body}: {text}");
    }
    std::fs::remove_file(dir.path().join("src/out.py")).unwrap();
    // The stage's failures: named, with what went wrong, and nothing committed.
    for (body, says) in [
        ("run = [\"sh\", \"-c\", \"echo the-last-words >&2; exit 3\"]", "exited with status 3"),
        ("run = [\"sh\", \"-c\", \"echo '@rlmflow {\\\"metric\\\": 1}'; sleep 30\"]", "line 1 of `sh -c"),
        ("run = [\"no-such-program-here\"]", "program `no-such-program-here` is neither a file of the pipeline's tree nor on PATH"),
        ("run = [\"true\"]", "wrote nothing into its output directory"),
        ("run = [\"sh\", \"-c\", \"echo > $RLMFLOW_OUTPUT/a; ln -s /etc/hostname $RLMFLOW_OUTPUT/b\"]", "`b` is a symbolic link"),
        ("run = [\"sleep\", \"30\"]\ntimeout = 1", "stopped at its timeout of 1 s"),
        ("run = [\"python\", \"src/a.py\"]\nenvironment = \"bad.lock\"", "the environment `bad.lock` does not install"),
    ] {
        dir.write("p.toml", &stage(body));
        let (ok, out) = rlmflow(dir.path(), &["run", "p.toml"]);
        assert!(!ok && out.contains("FAILED   x") && out.contains(says), "{body}: {out}");
        assert_eq!(committed(dir.path()), store, "{body}: the store changed");
    }
    let (ok, out) = rlmflow(dir.path(), &["run", "p.toml", "--set", "x.run=[\"sh\", \"-c\", \"echo the-last-words >&2; exit 3\"]"]);
    assert!(!ok && out.contains("| the-last-words") && out.contains("log: "), "the stderr's tail and the log's path: {out}");
    // A program writing into its input is caught, and the damaged input is found and replaced
    // by the next run rather than read.
    dir.write("p.toml", &stage("run = [\"sh\", \"-c\", \"touch $RLMFLOW_INPUT_SCENES/extra; echo > $RLMFLOW_OUTPUT/a\"]"));
    let (ok, out) = rlmflow(dir.path(), &["run", "p.toml"]);
    assert!(!ok && out.contains("wrote into its input `scenes`"), "{out}");
}

#[test]
fn a_probe_scripts_predictions_must_cover_the_test_split_once_per_row() {
    let predict = |body: &str| {
        format!(
            "import json\nfrom rlmflow import stage\nctx = stage.context()\nl = ctx.read('labels')\ntest = [i for i, s in enumerate(l.split) if s == 'test']\ntrain = [i for i, s in enumerate(l.split) if s == 'train']\nrows = []\n{body}\nopen(ctx.output / 'predictions.jsonl', 'w').write(''.join(json.dumps(r) + '\\n' for r in rows))\n"
        )
    };
    let zero = "[0] * 48";
    for (body, says) in [
        (format!("rows = [{{'frame': f, 'features': 'z', 'counts': {zero}}} for f in test[1:]]"), "misses frame"),
        (format!("rows = [{{'frame': f, 'features': 'z', 'counts': {zero}}} for f in test + train[:1]]"), "is not a test frame"),
        (format!("rows = [{{'frame': f, 'features': 'z', 'counts': {zero}}} for f in test + test[:1]]"), "is predicted twice"),
        ("rows = [{'frame': f, 'features': 'z', 'counts': [0] * 47} for f in test]".to_owned(), "`counts` holds 47 numbers"),
        ("rows = [{'frame': f, 'features': 'z'} for f in test]".to_owned(), "give the prediction as `grid`"),
        ("open(ctx.output / 'probe.json', 'w').write('{}')".to_owned(), "wrote `probe.json`, which rlmflow writes"),
    ] {
        let dir = pipeline("script-predictions", MEAN_STAGE, &[("probes/mean.py", &predict(&body))]);
        let (ok, out) = rlmflow(dir.path(), &["run", "p.toml"]);
        assert!(!ok && out.contains("FAILED   mean") && out.contains(says), "{body}: {out}");
    }
}

/// A segment script's masks are scored as every segmenter's: the true masks themselves score
/// IoU and AP 1, and masks of the wrong shape are refused, naming the shape it must have.
#[test]
fn a_segment_scripts_masks_are_scored_as_every_segmenters() {
    let truth = "import numpy as np\nfrom rlmflow import stage\nctx = stage.context()\nl = ctx.read('labels')\nm = l.masks()[l.split == 'test']\nnp.save(ctx.output / 'predictions.npy', (m / 255.0 >= 0.3).astype(np.float32){})\n";
    let stage = "[stages.masks]\nkind = \"segment\"\noperator = \"script\"\nrun = [\"python\", \"masks.py\"]\n";
    let dir = pipeline("script-segment", stage, &[("masks.py", &truth.replace("{}", ""))]);
    let (ok, out) = rlmflow(dir.path(), &["run", "p.toml"]);
    assert!(ok, "{out}");
    let output = rlmflow_test_support::cli::output_dir(&dir.path().join(".rlmflow"), "p", "masks");
    let summary = rlmflow_stages::segment::read_summary(&output).unwrap();
    assert_eq!((summary.operator.as_str(), summary.metrics.iou, summary.metrics.ap), ("script", 1.0, 1.0), "{summary:?}");
    let frames = rlmflow_stages::segment::read_frames(&output).unwrap();
    assert_eq!(frames.len() as u64, summary.test_frames);
    assert!(frames.iter().all(|f| f.iou == 1.0 && f.truth_pixels == f.predicted_pixels));
    dir.write("masks.py", &truth.replace("{}", "[:, :-1]"));
    let (ok, out) = rlmflow(dir.path(), &["run", "p.toml"]);
    assert!(!ok && out.contains("predictions.npy has shape") && out.contains("it must be ["), "{out}");
}

/// On a HyperQueue cluster whose workers have stores of their own, a script's sources travel
/// with its action through the remote cache, as any input does: the worker runs the program the
/// key names and the run ends with a local run's keys and bytes.
#[test]
fn a_scripts_sources_travel_to_a_hyperqueue_worker_with_its_action() {
    let stage = "[stages.x]\nkind = \"files\"\noperator = \"script\"\nrun = [\"python\", \"tools/count.py\"]\nsources = [\"tools/*.py\"]\ninputs = { labels = \"labels\" }\n";
    let count = "from rlmflow import stage\nfrom helper import line\nctx = stage.context()\n(ctx.output / 'count.txt').write_text(line(len(ctx.read('labels').frames)))\n";
    let files = [("tools/count.py", count), ("tools/helper.py", "def line(n):\n    return f'{n} frames\\n'\n")];
    let local = pipeline("script-hq-local", stage, &files);
    let (ok, out) = rlmflow(local.path(), &["run", "p.toml"]);
    assert!(ok, "{out}");
    let remote = std::env::temp_dir().join(format!("rlmflow-script-hq-remote-{}", std::process::id()));
    let cluster = format!(
        "remote = \"file://{}\"\nremote_push = true\nexecutor = \"hyperqueue\"\n\n[pipeline.hyperqueue]\nworkers = 1\ncores = 2\nworker_store = \"temporary\"\n",
        remote.display()
    );
    let hq = pipeline("script-hq", stage, &files);
    let text = std::fs::read_to_string(hq.path().join("p.toml")).unwrap().replacen("seed = 1\n", &format!("seed = 1\n{cluster}"), 1);
    std::fs::write(hq.path().join("p.toml"), text).unwrap();
    let (ok, out) = rlmflow(hq.path(), &["run", "p.toml"]);
    let _ = std::fs::remove_dir_all(&remote);
    assert!(ok, "{out}");
    assert!(out.contains("hyperqueue"), "{out}");
    assert_eq!(output_digest(hq.path(), "p", "x"), output_digest(local.path(), "p", "x"));
    let output = rlmflow_test_support::cli::output_dir(&hq.path().join(".rlmflow"), "p", "x");
    assert_eq!(std::fs::read_to_string(output.join("count.txt")).unwrap(), "24 frames\n");
}
