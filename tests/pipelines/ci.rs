//! `examples/ci.toml` end to end, run once per test process ([`ci_run`]), and what that run
//! must hold, one test each: a second run reuses every stage; a changed probe setting reruns only
//! what it touches; a fresh store pulls every result from a remote; a local HyperQueue cluster
//! computes the same keys and bytes in fresh processes; and the results read from outside as from
//! inside (the report's tables and Rerun recording, a stock MCAP reader, `rlmflow parse`,
//! Python's `tokenizers`).

use std::sync::OnceLock;

use super::*;

/// The first run of `examples/ci.toml` that the tests of this process share.
pub(super) struct CiRun {
    pub(super) dir: PathBuf,
    /// Its `--json` event log.
    events: String,
}

impl CiRun {
    pub(super) fn store(&self) -> PathBuf {
        self.dir.join(".rlmflow")
    }

    /// The output directory of stage instance `label`.
    pub(super) fn output(&self, label: &str) -> PathBuf {
        rlmflow_test_support::cli::output_dir(&self.store(), "ci", label)
    }

    /// How many stage instances the run ran.
    fn stages(&self) -> usize {
        finished(&self.events, "ran").len()
    }
}

/// `examples/ci.toml` run once, by whichever test asks first, in a directory under the build's
/// scratch space that the next test process replaces. A failed run fails every test that reads
/// it, with its output.
pub(super) fn ci_run() -> &'static CiRun {
    static RUN: OnceLock<Result<CiRun, String>> = OnceLock::new();
    let run = RUN.get_or_init(|| {
        let dir = rlmflow_test_support::scratch::shared_dir(Path::new(env!("CARGO_TARGET_TMPDIR")), "ci-run");
        std::fs::copy(root().join("examples/ci.toml"), dir.join("ci.toml")).unwrap();
        let (ok, events) = rlmflow(&dir, &["run", "ci.toml", "--json"]);
        if ok { Ok(CiRun { dir, events }) } else { Err(events) }
    });
    run.as_ref().unwrap_or_else(|events| panic!("examples/ci.toml failed: {events}"))
}

/// The `stage_finished` events of `log` with `status`: each instance's label and output digest,
/// sorted.
pub(super) fn finished(log: &str, status: &str) -> Vec<(String, String)> {
    let mut found: Vec<(String, String)> = log
        .lines()
        .filter(|l| l.contains("\"stage_finished\"") && l.contains(&format!("\"status\":\"{status}\"")))
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .map(|e| (e["stage"].as_str().unwrap().to_owned(), e["output"].as_str().unwrap().to_owned()))
        .collect();
    found.sort();
    found
}

/// A directory beside the shared run holding `ci.toml` as given, with the run's store (a link)
/// or a store of its own.
fn beside_the_run(name: &str, pipeline: &str, share_store: bool) -> PathBuf {
    let run = ci_run();
    let dir = run.dir.join(name);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("ci.toml"), pipeline).unwrap();
    if share_store {
        std::os::unix::fs::symlink(run.store(), dir.join(".rlmflow")).unwrap();
    }
    dir
}

#[test]
fn the_ci_pipeline_runs_and_a_second_run_reuses_every_stage() {
    let run = ci_run();
    assert!(run.stages() >= 1, "{}", run.events);
    let (ok, second) = rlmflow(&run.dir, &["run", "ci.toml", "--json"]);
    assert!(ok, "{second}");
    assert_eq!((finished(&second, "reused").len(), finished(&second, "ran").len()), (run.stages(), 0), "{second}");
    let (ok, verify) = rlmflow(&run.dir, &["verify", "ci.toml"]);
    assert!(ok, "{verify}");
}

/// The run computes, at every key, the bytes of the shipped digests (docs/digests/, another
/// machine's run: its CPU is in the file's header). On a machine of the file's portable class
/// every key must be there: a change that moves a key regenerates the file (`cargo xtask digests
/// examples/ci.toml`). A machine of another class (another vendor, no AVX2) has other model keys
/// and compares the rest.
#[test]
fn the_ci_pipeline_computes_the_shipped_digests_of_another_machine() {
    let run = ci_run();
    let shipped = root().join("docs/digests/ci.toml.digests");
    let (ok, out) = rlmflow(&run.dir, &["verify", "ci.toml", "--against", shipped.to_str().unwrap()]);
    assert!(ok && out.contains(" 0 differ"), "{out}");
    let (ok, mine) = rlmflow(&run.dir, &["digests", "ci.toml"]);
    assert!(ok, "{mine}");
    let portable = |text: &str| text.lines().find(|l| l.starts_with("# classes: ")).and_then(|l| l.split(';').next()).map(str::to_owned);
    if portable(&mine) == portable(&std::fs::read_to_string(&shipped).unwrap()) {
        assert!(
            out.contains(" 0 not in this store"),
            "a key of the shipped digests moved: `cargo xtask digests examples/ci.toml` regenerates them\n{out}"
        );
    }
}

/// One probe setting changed: only that probe's instances and what reads them (the report, the
/// `f1` table) run again.
#[test]
fn a_changed_probe_setting_reruns_only_that_probe_and_the_report() {
    let text = std::fs::read_to_string(root().join("examples/ci.toml")).unwrap();
    let edited =
        text.replacen("source = \"pixels\"", "source = \"pixels\"\nlambdas = [0.1, 10.0]", 1).replacen("name = \"ci\"", "name = \"ci-edited\"", 1);
    let dir = beside_the_run("edited", &edited, true);
    let (ok, third) = rlmflow(&dir, &["run", "ci.toml", "--json"]);
    assert!(ok, "{third}");
    let ran: Vec<String> = finished(&third, "ran").into_iter().map(|(stage, _)| stage).collect();
    assert_eq!(ran, ["f1", "pixels", "report"], "{third}");
}

/// `rlmflow push` of the CI pipeline's results to a directory remote; a fresh store in a folder of
/// its own then computes nothing: every stage is pulled, with the output digests of the run that
/// computed them.
#[test]
fn a_fresh_store_pulls_every_stage_from_a_remote_and_computes_nothing() {
    let run = ci_run();
    let remote = format!("file://{}", run.dir.join("remote").display());
    let (ok, out) = rlmflow(&run.dir, &["push", "ci.toml", "--remote", &remote]);
    assert!(ok, "{out}");
    let fresh = beside_the_run("pulled", &std::fs::read_to_string(run.dir.join("ci.toml")).unwrap(), false);
    let (ok, pulled) = rlmflow(&fresh, &["run", "ci.toml", "--json", "--remote", &remote]);
    assert!(ok, "{pulled}");
    assert_eq!(finished(&pulled, "pulled"), finished(&run.events, "ran"), "pulled everything, the same digests: {pulled}");
    let (ok, verify) = rlmflow(&fresh, &["verify", "ci.toml"]);
    assert!(ok, "{verify}");
}

/// `examples/ci.toml` run (by the local executor) again through a local HyperQueue cluster into a
/// store of its own: every action has the same key and output digest, and a second run reuses
/// everything and starts no cluster. So every stage (the models, the report and its Rerun
/// recording, the scenes mix) gives the same bytes in fresh processes, on another executor.
#[test]
fn a_local_hyperqueue_cluster_gives_the_same_keys_and_bytes() {
    let run = ci_run();
    let dir = beside_the_run("hyperqueue", &std::fs::read_to_string(run.dir.join("ci.toml")).unwrap(), false);
    let (ok, first) = rlmflow(&dir, &["run", "ci.toml", "--json", "--executor", "hyperqueue"]);
    assert!(ok, "{first}");
    assert!(first.contains("\"executor\":\"hyperqueue (local cluster"), "{first}");
    let actions = |store: &Path| {
        let store = rlmflow_cache::Store::open_existing(store).unwrap().unwrap();
        let keys = rlmflow_test_support::cli::last_keys(&store, "ci");
        keys.into_iter().map(|(label, key)| (label, key, store.record(&key).unwrap().unwrap().output)).collect::<Vec<_>>()
    };
    let (through_hq, locally) = (actions(&dir.join(".rlmflow")), actions(&run.store()));
    assert_eq!(through_hq.len(), run.stages());
    assert_eq!(through_hq, locally);
    let (ok, second) = rlmflow(&dir, &["run", "ci.toml", "--json", "--executor", "hyperqueue"]);
    assert!(ok, "{second}");
    assert_eq!(second.matches("\"status\":\"reused\"").count(), run.stages(), "{second}");
    let id = second.lines().find(|l| l.contains("\"run_started\"")).unwrap();
    let id = serde_json::from_str::<serde_json::Value>(id).unwrap()["run"].as_str().unwrap().to_owned();
    assert!(!dir.join(".rlmflow/runs").join(id).join("hyperqueue/server").exists(), "a warm run starts no cluster");
}

/// The report reads every probe and segmenter instance: its tables name them, `metrics.json`
/// holds their numbers, and the Python `rerun` package reads its recording's entities.
#[test]
fn the_report_holds_every_probe_and_rerun_reads_its_recording() {
    let report = &ci_run().output("report");
    let html = std::fs::read_to_string(report.join("report.html")).unwrap();
    // At the stable path beside the pipeline too.
    assert_eq!(std::fs::read_to_string(ci_run().dir.join("results/report/report.html")).unwrap(), html);
    let markdown = std::fs::read_to_string(report.join("report.md")).unwrap();
    let metrics: serde_json::Value = serde_json::from_slice(&std::fs::read(report.join("metrics.json")).unwrap()).unwrap();
    let captioning = metrics["captioning"].as_object().unwrap();
    for row in [
        "clipcap · clip",
        "clipcap · random",
        "clipcap-beam · clip",
        "linear · clip (cls)",
        "linear · random (mean-patch)",
        "linear · clip (patches)",
        "pixels (pixels)",
    ] {
        assert!(captioning.contains_key(row), "captioning row {row}: {:?}", captioning.keys());
        assert!(html.contains(row) && markdown.contains(row), "{row} not in the report");
    }
    assert_eq!(captioning["clipcap · random"]["row"], "random init (sanity)");
    // The CI-size decoders emit bytes no caption holds: shown as `\xNN`, never as U+FFFD; the
    // settings wrap (at most 100 columns in the configuration block).
    assert!(!markdown.contains('\u{fffd}') && !html.contains('\u{fffd}'), "a generated caption lost its bytes");
    let configuration = markdown.split("## Configuration").nth(1).unwrap().split("```").nth(1).unwrap();
    assert!(configuration.lines().all(|l| l.len() <= 100), "{configuration}");
    assert_eq!(captioning["pixels (pixels)"]["row"], "pixels (baseline)");
    // Every probe and segmenter on an encoder counted its test frames among the encoder's
    // training frames and each tokenizer's: all zero, shown in the hygiene table.
    let hygiene = metrics["hygiene"].as_array().unwrap();
    let checked: std::collections::BTreeSet<&str> = hygiene.iter().map(|r| r["instance"].as_str().unwrap()).collect();
    for instance in ["clipcap[clip]", "clipcap-beam[random]", "linear[clip]", "pup[random]"] {
        assert!(checked.contains(instance), "{instance} not in {checked:?}");
    }
    assert!(hygiene.iter().all(|r| r["check"]["overlap"] == 0), "{hygiene:?}");
    let trained_on = |r: &&serde_json::Value| r["check"]["against"] == "encoder training" && r["check"]["frames"].as_u64().unwrap() > 0;
    assert!(hygiene.iter().filter(trained_on).all(|r| r["instance"].as_str().unwrap().contains("[clip]")), "an untrained encoder trained on nothing");
    assert!(hygiene.iter().filter(trained_on).count() >= 4, "{hygiene:?}");
    assert!(markdown.contains("# Data hygiene") && markdown.contains("Every count is zero"), "no hygiene table");
    let segmentation = metrics["segmentation"].as_object().unwrap();
    assert_eq!(segmentation.keys().collect::<Vec<_>>(), ["pup · clip", "pup · random", "unet"]);
    assert_eq!(segmentation["unet"]["paper"][2], 0.489, "the paper's U-Net IoU stands beside ours");
    for figure in ["vehicles-per-frame.svg", "pretrain-loss.svg", "iou-threshold.svg"] {
        assert!(report.join("figures").join(figure).exists(), "{figure}");
    }
    assert!(html.contains("<svg") && html.contains("data:image/png;base64,"), "figures inline");
    const ENTITIES: &str = r#"
import sys, warnings
warnings.simplefilter("ignore")
from rerun.chunk import RrdReader
print("\n".join(sorted({c.entity_path for c in RrdReader(sys.argv[1]).stream()})))
"#;
    let env = rlmflow_python::ensure(&mut |_| {}).unwrap();
    let out = Command::new(&env.python).arg("-c").arg(ENTITIES).arg(report.join("report.rrd")).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let entities: Vec<String> = String::from_utf8_lossy(&out.stdout).lines().map(str::to_owned).collect();
    for entity in [
        "/radar/heatmap",
        "/radar/truth",
        "/radar/actors",
        "/radar/predicted/pup/clip",
        "/radar/predicted/unet",
        "/captions/true",
        "/captions/clipcap/clip",
        "/train/pretrain/clip/loss",
    ] {
        assert!(entities.contains(&entity.to_string()), "{entity} not in {entities:?}");
    }
}

/// `rlmflow parse` reads every template caption back to the grid it was written from.
#[test]
fn every_caption_parses_to_its_labels() {
    let run = ci_run();
    let labels = rlmflow_stages::labels::Labels::open(&run.output("labels")).unwrap();
    let captions_dir = &run.output("captions");
    let captions = rlmflow_stages::captions::Captions::open(captions_dir).unwrap();
    let (ok, out) = rlmflow(&root(), &["parse", captions_dir.join("captions.jsonl").to_str().unwrap()]);
    assert!(ok, "{out}");
    let grids: Vec<&str> = out.lines().collect();
    assert_eq!(grids.len(), captions.captions.len());
    for (caption, parsed) in captions.captions.iter().zip(grids) {
        assert_eq!(parsed, labels.frames[caption.frame as usize].grid.to_json(), "{}", caption.caption);
    }
}

/// Python's `tokenizers` reads the stored `tokenizer.json` and encodes every caption to the ids
/// rlmflow stored.
#[test]
fn python_tokenizers_gives_the_ids_rlmflow_stored() {
    let run = ci_run();
    let (captions, tokens) = (run.output("captions"), run.output("tokens"));
    const ENCODE: &str = r#"
import json, sys
import numpy as np
from tokenizers import Tokenizer
tokenizer = Tokenizer.from_file(sys.argv[1] + "/tokenizer.json")
ids = np.load(sys.argv[1] + "/tokens.npy")
captions = [json.loads(l)["caption"] for l in open(sys.argv[2] + "/captions.jsonl")]
assert ids.shape[0] == len(captions), (ids.shape, len(captions))
for row, caption in zip(ids, captions):
    assert tokenizer.encode(caption).ids == row.tolist(), caption
print(len(captions))
"#;
    let env = rlmflow_python::ensure(&mut |_| {}).unwrap();
    let out = Command::new(&env.python).arg("-c").arg(ENCODE).arg(tokens).arg(captions).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let checked: usize = String::from_utf8_lossy(&out.stdout).trim().parse().unwrap();
    assert!(checked > 0);
}

/// Reads each scenes artifact's `scenes.mcap` (one per scenes stage and shard, and the mix) with
/// the Python `mcap` package (protobuf decoding from `mcap-protobuf-support`) in the managed
/// environment and compares every message with what rlmflow's reader returns through
/// `scenes.index`.
#[test]
fn a_stock_mcap_reader_reads_what_rlmflow_reads() {
    let run = ci_run();
    let scenes: Vec<PathBuf> =
        finished(&run.events, "ran").iter().map(|(label, _)| run.output(label)).filter(|dir| dir.join("scenes.mcap").exists()).collect();
    assert_eq!(scenes.len(), 6, "scenes, procedural, placed and its two shards, mixed: {scenes:?}");
    for artifact in &scenes {
        a_stock_mcap_reader_agrees(artifact);
    }
}

fn a_stock_mcap_reader_agrees(artifact: &Path) {
    const READ: &str = r#"
import json, sys
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
out = {"actors": [], "images": {}}
protobuf = DecoderFactory()
with open(sys.argv[1], "rb") as f:
    for schema, channel, message in make_reader(f).iter_messages():
        if channel.topic == "/actors":
            assert channel.message_encoding == "json"
            out["actors"].append(json.loads(message.data))
        else:
            decoded = protobuf.decoder_for(channel.message_encoding, schema)(message.data)
            assert schema.name == "foxglove.RawImage" and decoded.encoding == "mono8"
            out["images"].setdefault(channel.topic, []).append([decoded.width, decoded.height, list(decoded.data)])
json.dump(out, sys.stdout)
"#;
    let env = rlmflow_python::ensure(&mut |_| {}).unwrap();
    let out = Command::new(&env.python).arg("-c").arg(READ).arg(artifact.join("scenes.mcap")).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let read: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let scenes = rlmflow_stages::scenes::Scenes::open(artifact).unwrap();
    let frames = scenes.frames().unwrap();
    assert_eq!(read["actors"], serde_json::to_value(&frames).unwrap(), "{}", artifact.display());
    for (k, image) in scenes.summary.images.iter().enumerate() {
        let decoded = read["images"][&image.topic].as_array().unwrap();
        assert_eq!(decoded.len() as u64, scenes.len());
        for (i, d) in decoded.iter().enumerate() {
            assert_eq!(d[0], image.size);
            assert_eq!(d[1], image.size);
            assert_eq!(d[2], serde_json::to_value(scenes.image(k, i as u64).unwrap()).unwrap(), "{} frame {i}", image.topic);
        }
    }
}

/// `rlmflow compare` on two instances lists the test frames where their outputs differ, most
/// first, and each frame it names does differ in the artifacts; an instance against itself
/// differs nowhere.
#[test]
fn per_frame_differences_name_frames_that_differ_and_none_for_an_instance_with_itself() {
    let run = ci_run();
    let compare = |a: &str, b: &str| -> serde_json::Value {
        let (ok, out) = rlmflow(&run.dir, &["compare", "ci.toml", a, b, "--json"]);
        assert!(ok, "{out}");
        serde_json::from_str(out.lines().last().unwrap()).unwrap()
    };
    let probes = compare("linear[clip]", "linear[random]");
    let frames = probes["frames"].as_array().unwrap();
    assert!(!frames.is_empty() && probes["unit"] == "cells predicted differently", "{probes}");
    let grids = |label: &str| rlmflow_stages::probe::read_predictions(&run.output(label)).unwrap();
    let (a, b) = (grids("linear[clip]"), grids("linear[random]"));
    for f in frames {
        let at = |p: &[(u64, String, [u32; 48])]| p.iter().find(|(frame, row, _)| *frame == f["frame"] && *row == f["row"]).unwrap().2;
        let differing = (0..48).filter(|&c| at(&a)[c] != at(&b)[c]).count();
        assert_eq!(differing as f64, f["differ"].as_f64().unwrap(), "{f}");
        assert!(differing > 0);
    }
    let differs: Vec<f64> = frames.iter().map(|f| f["differ"].as_f64().unwrap()).collect();
    assert!(differs.windows(2).all(|w| w[0] >= w[1]), "most first: {differs:?}");
    let segmenters = compare("pup[clip]", "unet");
    assert_eq!(segmenters["compared"], 10, "{segmenters}");
    let scores = |label: &str| rlmflow_stages::segment::read_frames(&run.output(label)).unwrap();
    let (p, u) = (scores("pup[clip]"), scores("unet"));
    for f in segmenters["frames"].as_array().unwrap() {
        let iou = |s: &[rlmflow_stages::segment::FrameScore]| s.iter().find(|x| x.frame == f["frame"]).unwrap().iou;
        assert!(((iou(&p) - iou(&u)).abs() - f["differ"].as_f64().unwrap()).abs() < 1e-12, "{f}");
    }
    for same in ["linear[clip]", "pup[random]"] {
        let itself = compare(same, same);
        assert_eq!(itself["frames"].as_array().unwrap().len(), 0, "{itself}");
    }
    let (ok, out) = rlmflow(&run.dir, &["compare", "ci.toml", "pup[clp]", "unet"]);
    assert!(!ok && out.contains("no instance `pup[clp]`") && out.contains("did you mean `pup[clip]`?"), "{out}");
}

/// Every metric an operator declares (what a claim may name, checked when the file is read)
/// is one its artifact measures.
#[test]
fn every_declared_metric_is_measured_by_the_artifact() {
    use rlmflow_stages::DynOperator;
    let run = ci_run();
    let catalog = rlmflow_stages::Catalog::paper();
    let pretrain = rlmflow_pretrain::operator();
    let (linear, clipcap, pup, unet) = (rlmflow_probe::linear(), rlmflow_probe::clipcap(), rlmflow_segment::pup(), rlmflow_segment::unet());
    let cases: [(&dyn DynOperator, serde_json::Value, &str, &str); 6] = [
        (&pretrain, serde_json::json!({}), "pretrain[clip]", "Encoder"),
        (&linear, serde_json::json!({}), "linear[clip]", "ProbeReport"),
        (&linear, serde_json::json!({"source": "pixels"}), "pixels", "ProbeReport"),
        (&clipcap, serde_json::json!({}), "clipcap[random]", "ProbeReport"),
        (&pup, serde_json::json!({}), "pup[clip]", "SegReport"),
        (&unet, serde_json::json!({}), "unet", "SegReport"),
    ];
    for (op, settings, label, artifact) in cases {
        let declared = op.metrics(&op.settings(settings).unwrap());
        let measured = (catalog.measures(artifact).unwrap().metrics)(&run.output(label)).unwrap();
        let paths = rlmflow_stages::measure::paths(&measured);
        assert!(!declared.is_empty(), "{label}");
        for name in &declared {
            assert!(paths.contains(name), "{label} declares `{name}`, which it does not measure: {paths:?}");
        }
    }
}

/// The `rlmflow` Python package, in rlmflow's own environment, reads every computed instance of
/// the CI run (every artifact type it ships) as `rlmflow show --json` places and records it, and
/// what it reads equals what rlmflow's own readers read from the same directories.
#[test]
fn the_python_package_reads_every_artifact_type_as_rlmflow_shows_it() {
    use rlmflow_stages::{captions::Captions, labels::Labels, scenes::Scenes, tokens::Tokens};
    let run = ci_run();
    let env = rlmflow_python::ensure(&mut |_| {}).unwrap();
    let out = Command::new(&env.python)
        .arg("-c")
        .arg(include_str!("python/read_artifacts.py"))
        .arg("ci.toml")
        .current_dir(&run.dir)
        .env("RLMFLOW_BIN", env!("CARGO_BIN_EXE_rlmflow"))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let facts: serde_json::Map<String, serde_json::Value> = serde_json::from_slice(&out.stdout).unwrap();
    let ran = finished(&run.events, "ran");
    let computed: Vec<&String> = ran.iter().map(|(label, _)| label).collect();
    assert_eq!(facts.keys().collect::<Vec<_>>(), computed, "every instance the run computed (shards too), and only those");
    let mut types = std::collections::BTreeSet::new();
    for (label, fact) in &facts {
        let dir = run.output(label);
        assert_eq!(Path::new(fact["dir"].as_str().unwrap()), dir, "{label}");
        let ty = fact["type"].as_str().unwrap();
        types.insert(ty.to_owned());
        match ty {
            "Scenes" => {
                let scenes = Scenes::open(&dir).unwrap();
                let pixels: u64 = (0..scenes.len()).map(|i| scenes.image(0, i).unwrap().iter().map(|&p| p as u64).sum::<u64>()).sum();
                assert_eq!((fact["frames"].as_u64(), fact["pixels"].as_u64()), (Some(scenes.len()), Some(pixels)), "{label}");
            }
            "Labels" => {
                let labels = Labels::open(&dir).unwrap();
                let counts: u64 = labels.frames.iter().map(|f| f.grid.counts.iter().map(|&c| c as u64).sum::<u64>()).sum();
                let test = labels.split(rlmflow_stages::identity::Split::Test).count() as u64;
                let ids: Vec<&str> = labels.frames.iter().map(|f| f.id.as_str()).collect();
                assert_eq!((fact["counts"].as_u64(), fact["test"].as_u64()), (Some(counts), Some(test)), "{label}");
                assert_eq!(fact["ids"], serde_json::json!(ids), "{label}");
            }
            "Captions" => {
                let texts: Vec<String> = Captions::open(&dir).unwrap().captions.into_iter().map(|c| c.caption).collect();
                assert_eq!(fact["captions"], serde_json::json!(texts), "{label}");
            }
            "Tokens" => {
                let tokens = Tokens::open(&dir).unwrap();
                let sum: u64 = (0..tokens.ids.rows()).map(|r| tokens.ids.row_u32(r).unwrap().iter().map(|&t| t as u64).sum::<u64>()).sum();
                assert_eq!(fact["shape"], serde_json::json!(tokens.ids.shape), "{label}");
                assert_eq!(fact["sum"].as_u64(), Some(sum), "{label}");
            }
            "ProbeReport" => {
                let rows = rlmflow_stages::probe::read_predictions(&dir).unwrap().len();
                assert_eq!(fact["predictions"].as_u64(), Some(rows as u64), "{label}");
            }
            "SegReport" => {
                let frames = rlmflow_stages::segment::read_frames(&dir).unwrap();
                assert_eq!(fact["frames"], serde_json::json!(frames.iter().map(|f| f.frame).collect::<Vec<_>>()), "{label}");
                assert_eq!(fact["iou"], serde_json::json!(frames.iter().map(|f| f.iou).collect::<Vec<_>>()), "{label}");
            }
            "Encoder" => assert!(fact["tensors"].as_u64().unwrap() > 0, "{label}"),
            "Embeddings" => {
                let cls = rlmflow_stages::npy::Npy::open(&dir.join(rlmflow_stages::embeddings::CLS)).unwrap();
                let sum: f64 = cls.all_f32().unwrap().iter().map(|&v| f64::from(v)).sum();
                assert_eq!(fact["shape"], serde_json::json!(cls.shape), "{label}");
                assert!((fact["sum"].as_f64().unwrap() - sum).abs() <= 1e-9 * sum.abs().max(1.0), "{label}: {} against {sum}", fact["sum"]);
                let summary = rlmflow_stages::embeddings::read_summary(&dir).unwrap();
                assert_eq!(fact["test"].as_u64(), Some(summary.test_frames), "{label}");
            }
            "Report" => assert!(fact["sections"].as_array().is_some_and(|s| !s.is_empty()), "{label}"),
            "Files" => {
                let csv = std::fs::read_to_string(dir.join("f1.csv")).unwrap();
                assert_eq!(fact["files"], serde_json::json!(["f1.csv"]), "{label}");
                assert!(csv.starts_with("probe,features,f1\n") && csv.contains("pixels,pixels,"), "{label}: {csv}");
            }
            other => panic!("{label}: an artifact type the test does not know: {other}"),
        }
    }
    let all = ["Captions", "Embeddings", "Encoder", "Files", "Labels", "ProbeReport", "Report", "Scenes", "SegReport", "Tokens"];
    assert_eq!(types.iter().map(String::as_str).collect::<Vec<_>>(), all, "every artifact type the CI run ships");
    // A setting changed and not run (under the run's name: the reason is against its last run):
    // the package computes nothing and says why.
    let text = std::fs::read_to_string(run.dir.join("ci.toml")).unwrap();
    let unrun = text.replacen("source = \"pixels\"", "source = \"pixels\"\nlambdas = [0.5, 5.0]", 1);
    let dir = beside_the_run("unrun", &unrun, true);
    const NOT_COMPUTED: &str = "import rlmflow\ntry:\n    rlmflow.load('ci.toml', 'pixels')\nexcept rlmflow.NotComputed as e:\n    print(e)";
    let out =
        Command::new(&env.python).args(["-c", NOT_COMPUTED]).current_dir(&dir).env("RLMFLOW_BIN", env!("CARGO_BIN_EXE_rlmflow")).output().unwrap();
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && said.contains("pixels: not computed yet") && said.contains("lambdas"),
        "{said}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (ok, again) = rlmflow(&dir, &["status", "ci.toml"]);
    assert!(ok && again.contains("pixels"), "{again}");
}

/// `examples/own-probe.toml` beside the CI run, sharing its store (its data and encoders are
/// ci.toml's, at the same keys): `embed` writes each encoder's features, the Python k-NN probe
/// reads them and rlmflow scores it, the report gathers its rows beside `linear`'s and the
/// pixels', and the shell stage keeps the report's tables. A second run reuses everything;
/// editing the script reruns it (the file named) and, its predictions unchanged, nothing after
/// it; a file outside its `sources` reruns nothing.
#[test]
fn the_own_probe_example_runs_a_python_probe_through_the_report_beside_linear() {
    let run = ci_run();
    let dir = beside_the_run("own-probe", "", true);
    std::fs::copy(root().join("examples/own-probe.toml"), dir.join("own-probe.toml")).unwrap();
    std::fs::create_dir_all(dir.join("probes")).unwrap();
    for file in ["knn.py", "tables.sh"] {
        std::fs::copy(root().join("examples/probes").join(file), dir.join("probes").join(file)).unwrap();
    }
    std::fs::write(dir.join("probes/notes.md"), "not a source\n").unwrap();
    let (ok, out) = rlmflow(&dir, &["run", "own-probe.toml", "--json"]);
    assert!(ok, "{out}");
    let ran: Vec<String> = finished(&out, "ran").into_iter().map(|(label, _)| label).collect();
    assert_eq!(ran, ["knn[clip]", "knn[random]", "report", "tables"], "the rest (`embed` too) is ci.toml's: {out}");
    let output = |label: &str| rlmflow_test_support::cli::output_dir(&run.store(), "own-probe", label);
    let probe = rlmflow_stages::probe::read_summary(&output("knn[clip]")).unwrap();
    assert_eq!(probe.rows.iter().map(|r| r.features.as_str()).collect::<Vec<_>>(), ["cls-knn", "mean-patch-knn"]);
    assert!(
        probe.hygiene.iter().any(|h| h.slot == "embeddings" && h.against == "encoder training" && h.overlap == 0 && h.frames > 0),
        "the test frames checked against the encoder's, through its features: {:?}",
        probe.hygiene
    );
    let report = std::fs::read_to_string(output("report").join("report.md")).unwrap();
    for row in ["cls-knn", "mean-patch-knn", "pixels", "mean-patch"] {
        assert!(report.contains(row), "the report's tables hold `{row}`");
    }
    let tables = std::fs::read_to_string(output("tables").join("tables.md")).unwrap();
    assert!(tables.contains("cls-knn") && tables.lines().all(|l| l.starts_with('|') || l.starts_with('#')), "{tables}");
    // The features read from Python as they are stored, with the split rlmflow made.
    let env = rlmflow_python::ensure(&mut |_| {}).unwrap();
    let check = "import rlmflow, sys\ne = rlmflow.load('own-probe.toml', 'embed[clip]').read()\nl = rlmflow.load('own-probe.toml', 'labels').read()\nassert e.cls().shape[0] == len(e.frames) == len(l.frames), e.cls().shape\nassert list(e.split) == list(l.split)\nprint(e.patches().shape)\n";
    let py = Command::new(&env.python).args(["-c", check]).current_dir(&dir).env("RLMFLOW_BIN", env!("CARGO_BIN_EXE_rlmflow")).output().unwrap();
    assert!(py.status.success(), "{}", String::from_utf8_lossy(&py.stderr));

    let (ok, again) = rlmflow(&dir, &["run", "own-probe.toml", "--json"]);
    assert!(ok && finished(&again, "ran").is_empty(), "{again}");
    std::fs::write(dir.join("probes/notes.md"), "edited\n").unwrap();
    let (ok, status) = rlmflow(&dir, &["status", "own-probe.toml"]);
    assert!(ok && !status.contains("will run"), "{status}");
    let script = std::fs::read_to_string(dir.join("probes/knn.py")).unwrap();
    std::fs::write(dir.join("probes/knn.py"), script + "# an edit that changes no prediction\n").unwrap();
    let (ok, status) = rlmflow(&dir, &["status", "own-probe.toml"]);
    assert!(ok && status.lines().any(|l| l.contains("knn[clip]") && l.contains("probes/knn.py changed")), "{status}");
    let (ok, edited) = rlmflow(&dir, &["run", "own-probe.toml", "--json"]);
    assert!(ok, "{edited}");
    let ran: Vec<String> = finished(&edited, "ran").into_iter().map(|(label, _)| label).collect();
    assert_eq!(ran, ["knn[clip]", "knn[random]"], "the same predictions cut off the report: {edited}");
}
