//! The shipped pipelines through the real `rlmflow` binary: every one validates, and the CI
//! pipeline runs twice with the second run reusing every stage. Its artifacts then hold up from
//! outside: the Scenes read the same through a stock MCAP reader (the Python `mcap` package) as
//! through rlmflow's index; `rlmflow parse` reads every caption back to its frame's labels; and
//! Python's `tokenizers`, given `tokenizer.json`, produces the stored token ids.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

#[path = "pipelines/datasets.rs"]
mod datasets;
#[path = "pipelines/fuzz.rs"]
mod fuzz;
#[path = "pipelines/import.rs"]
mod import;

fn rlmflow(dir: &Path, args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_rlmflow")).current_dir(dir).args(args).output().unwrap();
    (out.status.success(), format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn every_shipped_pipeline_validates() {
    let mut files = vec![root().join("pipeline.toml")];
    files.extend(
        std::fs::read_dir(root().join("examples"))
            .unwrap()
            .map(|e| e.unwrap().path())
            // The paper's needs its checkpoints, the imports their recordings: each has its own test.
            .filter(|p| p.extension().is_some_and(|e| e == "toml") && !["paper.toml", "import.toml", "radiate.toml"].iter().any(|f| p.ends_with(f))),
    );
    for file in files {
        // --dry-run validates everything and writes nothing.
        let (ok, out) = rlmflow(&root(), &["run", file.to_str().unwrap(), "--dry-run"]);
        assert!(ok, "{}: {out}", file.display());
    }
}

/// A safetensors file at `path` holding one f32 scalar per name.
fn write_safetensors(path: &Path, names: &[&str]) {
    let header: serde_json::Map<String, serde_json::Value> = names
        .iter()
        .enumerate()
        .map(|(i, n)| (n.to_string(), serde_json::json!({"dtype": "F32", "shape": [], "data_offsets": [4 * i, 4 * i + 4]})))
        .collect();
    let header = serde_json::to_vec(&header).unwrap();
    let mut bytes = (header.len() as u64).to_le_bytes().to_vec();
    bytes.extend(header);
    bytes.extend(vec![0u8; 4 * names.len()]);
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, bytes).unwrap();
}

/// `examples/paper.toml` starts from the public checkpoints: without them it says which setting
/// names which file and where the README converts it; with files of the right models where its
/// `init` lines point, it validates and shows each training stage's size and memory.
#[test]
fn the_paper_pipeline_names_its_checkpoints_and_shows_what_each_stage_costs() {
    // The checkpoints beside the pipeline file here, not in the repository's `weights/`.
    let text = std::fs::read_to_string(root().join("examples/paper.toml")).unwrap().replace("\"../weights/", "\"weights/");
    let dir = scratch("paper-validates", &text);
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--dry-run"]);
    assert!(!ok, "{out}");
    assert!(
        out.contains("stages.pretrain.init: `")
            && out.contains("weights/clip-vit-b16-openai.safetensors` is not a file")
            && out.contains("\"Pretrained weights\""),
        "{out}"
    );
    assert!(out.contains("stages.clipcap.init: `") && out.contains("weights/gpt2.safetensors` is not a file"), "{out}");

    write_safetensors(&dir.join("weights/clip-vit-b16-openai.safetensors"), &["visual.conv1.weight"]);
    write_safetensors(&dir.join("weights/gpt2.safetensors"), &["h.0.attn.c_attn.weight"]);
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--dry-run"]);
    assert!(ok, "{out}");
    // CLIP ViT-B/16 (one input channel) and the paper's text tower with MLP heads: 125.99 M.
    assert_eq!(
        out.matches("126.0 M parameters, peak ~ 17.4 GiB (CUDA device 0:").count(),
        4,
        "the four trained encoders, 640 in chunks of 40: {out}"
    );
    assert!(out.contains("126.0 M parameters, peak ~ 0.5 GiB (CUDA device 0:"), "the untrained encoder: {out}");
    assert!(!out.contains("DOES NOT FIT"), "{out}");
    // `init` is tracked by content (a replaced checkpoint changes the key, as
    // tests/e2e/bad_input.rs shows for the mechanism), for both operators that take one.
    let (ok, operators) = rlmflow(&dir, &["operators", "--json"]);
    assert!(ok, "{operators}");
    for name in ["clip", "clipcap"] {
        let line = operators.lines().find(|l| l.contains(&format!("\"name\":\"{name}\""))).unwrap();
        assert!(line.contains("\"tracked\":[\"init\"]"), "{line}");
    }
    // A stage that names another device is set against that device's memory: an `nvidia-smi`
    // that knows two GPUs of different sizes answers for each.
    let text = std::fs::read_to_string(dir.join("p.toml")).unwrap().replacen("device = \"cuda\"", "device = \"cuda:1\"", 1);
    std::fs::write(dir.join("p.toml"), text).unwrap();
    let bin = dir.join("fake-bin");
    std::fs::create_dir_all(&bin).unwrap();
    let smi = bin.join("nvidia-smi");
    std::fs::write(&smi, "#!/bin/sh\nfor a in \"$@\"; do case $a in --id=0) echo 40960;; --id=1) echo 81559;; esac; done\n").unwrap();
    std::fs::set_permissions(&smi, std::os::unix::fs::PermissionsExt::from_mode(0o755)).unwrap();
    let path = format!("{}:{}", bin.display(), std::env::var("PATH").unwrap());
    let out = Command::new(env!("CARGO_BIN_EXE_rlmflow")).current_dir(&dir).args(["run", "p.toml", "--dry-run"]).env("PATH", path).output().unwrap();
    let out = String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.matches("peak ~ 17.4 GiB (CUDA device 1: 79.6 GiB)").count(), 4, "{out}");
    assert!(out.contains("(CUDA device 0: 40.0 GiB)"), "the other stages, on GPU 0: {out}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `init` is a path tracked by content, resolved against the pipeline file: a replaced
/// checkpoint changes its stage's key (`status` names it), and a FIFO in its place is refused
/// without being opened, in bounded time.
#[test]
fn a_replaced_init_checkpoint_reruns_its_stage_and_a_fifo_is_refused_unopened() {
    let pipeline = "[pipeline]\nname = \"init\"\n[stages.scenes]\noperator = \"procedural\"\nframes = 20\nradar = { image = 32 }\n\
                    [stages.labels]\noperator = \"ego-grid\"\ntest_fraction = 0.25\n[stages.captions]\noperator = \"template\"\n[stages.tokens]\noperator = \"bpe\"\n\
                    [stages.pretrain]\noperator = \"clip\"\nencoder = \"vit-b16\"\nbatch = 4\ndevice = \"cpu\"\ninit = \"weights/clip.safetensors\"\n";
    let dir = scratch("init-tracked", pipeline);
    write_safetensors(&dir.join("weights/clip.safetensors"), &["visual.conv1.weight"]);
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--only", "tokens"]);
    assert!(ok, "{out}");
    let key = |dir: &Path| {
        let (ok, out) = rlmflow(dir, &["explain", "p.toml", "pretrain"]);
        assert!(ok, "{out}");
        out.lines().find_map(|l| l.trim().strip_prefix("will run: key ").map(str::to_owned)).unwrap_or_else(|| panic!("{out}"))
    };
    let before = key(&dir);
    // Run from elsewhere: the file beside the pipeline is the one read.
    let (ok, out) = rlmflow(&dir.join("weights"), &["explain", "../p.toml", "pretrain"]);
    assert!(ok && out.contains(&before), "{out}");
    write_safetensors(&dir.join("weights/clip.safetensors"), &["visual.conv1.weight", "visual.proj"]);
    assert_ne!(key(&dir), before, "a replaced checkpoint is a new key");
    let (_, status) = rlmflow(&dir, &["status", "p.toml"]);
    assert!(status.contains("pretrain") && status.contains("never run"), "{status}");

    std::fs::remove_file(dir.join("weights/clip.safetensors")).unwrap();
    let fifo = std::ffi::CString::new(dir.join("weights/clip.safetensors").to_str().unwrap()).unwrap();
    assert_eq!(unsafe { libc::mkfifo(fifo.as_ptr(), 0o644) }, 0);
    let mut child = Command::new(env!("CARGO_BIN_EXE_rlmflow"))
        .current_dir(&dir)
        .args(["run", "p.toml", "--dry-run"])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if t0.elapsed() > Duration::from_secs(20) {
            child.kill().unwrap();
            panic!("a FIFO as `init` blocked the dry run");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && stderr.contains("stages.pretrain.init: `weights/clip.safetensors` is a FIFO"), "{stderr}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A stage whose estimate exceeds its device's memory is refused before anything runs, with the
/// settings that lower it; the same batch in chunks fits.
#[test]
fn a_stage_that_would_not_fit_its_device_is_refused_with_the_setting_to_change() {
    let pipeline = |chunk: u64| {
        format!(
            "[pipeline]\nname = \"big\"\n[stages.scenes]\noperator = \"procedural\"\nframes = 12000\nradar = {{ image = 224 }}\n\
             [stages.labels]\noperator = \"ego-grid\"\n[stages.captions]\noperator = \"template\"\n\
             [stages.tokens]\noperator = \"bpe\"\ncontext = 400\n\
             [stages.pretrain]\noperator = \"clip\"\nencoder = \"vit-b16\"\ntext = \"paper\"\nbatch = 8192\nchunk = {chunk}\ndevice = \"cpu\"\n"
        )
    };
    let dir = scratch("too-big", &pipeline(0));
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--dry-run"]);
    assert!(!ok, "{out}");
    assert!(out.contains("DOES NOT FIT") && out.contains("stages.pretrain: `pretrain` would not fit: 125.1 M parameters, peak ~"), "{out}");
    assert!(out.contains("lower it with `chunk` (gradient caching, the same loss) or `batch`"), "{out}");
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(!ok && out.contains("would not fit") && !dir.join(".rlmflow/objects").exists(), "refused before anything ran: {out}");
    std::fs::write(dir.join("p.toml"), pipeline(2)).unwrap();
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--dry-run"]);
    assert!(ok && !out.contains("DOES NOT FIT"), "{out}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `examples/paper-smoke.toml`: the paper's model shapes (ViT-B/16 at 224 px with MLP heads and
/// gradient caching, the text tower at context 400, ClipCap into GPT-2 small's shape with
/// accumulated micro-batches, PUP on 768 x 14 x 14 tokens, the U-Net) through the report on the
/// CPU, by the real binary.
#[test]
fn the_paper_shapes_run_end_to_end_on_cpu() {
    // The fastest kernels: this test checks the paper's shapes, not the portable kernels (the CI
    // pipeline and the numerics tests run those), and MKL's portable branch halves their speed.
    let text = std::fs::read_to_string(root().join("examples/paper-smoke.toml")).unwrap();
    let native = text
        .replace("device = \"cpu\"", "device = \"cpu\"\nnumerics = \"native\"")
        .replace("operator = \"linear\"", "operator = \"linear\"\nnumerics = \"native\"");
    let dir = scratch("paper-smoke", &native);
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--json"]);
    assert!(ok, "{out}");
    let ran = out.lines().filter(|l| l.contains("\"stage_finished\"") && l.contains("\"status\":\"ran\"")).count();
    assert_eq!(ran, 11, "{out}");
    let objects = dir.join(".rlmflow/objects");
    let only = |file: &str| {
        let found = artifacts(&objects, file);
        assert_eq!(found.len(), 1, "{file}: {found:?}");
        found[0].join(file)
    };
    let encoder: serde_json::Value = serde_json::from_slice(&std::fs::read(only("config.json")).unwrap()).unwrap();
    let (vision, text) = (&encoder["vision"], &encoder["text"]);
    assert_eq!((vision["image"].as_i64(), vision["width"].as_i64(), vision["layers"].as_i64()), (Some(224), Some(768), Some(12)));
    assert_eq!((vision["head"].as_str(), vision["quick_gelu"].as_bool()), (Some("mlp"), Some(true)));
    assert_eq!(
        (text["context"].as_i64(), text["width"].as_i64(), text["layers"].as_i64(), text["head"].as_str()),
        (Some(400), Some(512), Some(12), Some("mlp"))
    );
    assert!(encoder["open_clip"].as_str().unwrap().starts_with("open_clip cannot build this model"), "MLP heads: {encoder}");
    // pup's and the U-Net's heads share a file name; pup's has the stages.
    let heads: Vec<_> = artifacts(&objects, "head.safetensors").iter().map(|a| safetensors_shapes(&a.join("head.safetensors"))).collect();
    let pup = heads.iter().find(|h| h.contains_key("stages.0.conv.weight")).expect("pup's head");
    assert_eq!(pup["stages.0.conv.weight"], [256, 768, 3, 3], "the paper's PUP table on 768-wide tokens");
    assert_eq!(pup["stages.3.conv.weight"], [64, 128, 3, 3]);
    let clipcap = safetensors_shapes(&only("clipcap.safetensors"));
    assert_eq!(clipcap["gpt.transformer.resblocks.11.mlp.c_fc.weight"], [3072, 768], "GPT-2 small's blocks");
    assert_eq!(clipcap.keys().filter(|k| k.starts_with("mapper.transformer.resblocks.") && k.ends_with(".ln_1.weight")).count(), 8);
    only("report.md");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Each tensor's shape in a safetensors file, from its JSON header.
fn safetensors_shapes(path: &Path) -> std::collections::BTreeMap<String, Vec<u64>> {
    let bytes = std::fs::read(path).unwrap();
    let length = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Map<String, serde_json::Value> = serde_json::from_slice(&bytes[8..8 + length]).unwrap();
    header
        .into_iter()
        .filter(|(name, _)| name != "__metadata__")
        .map(|(name, t)| (name, t["shape"].as_array().unwrap().iter().map(|d| d.as_u64().unwrap()).collect()))
        .collect()
}

/// Settings that once validated and then exhausted memory, overflowed or ran forever inside the
/// stage are config errors that name the key and its bounds.
#[test]
fn settings_that_would_exhaust_memory_or_never_finish_are_config_errors() {
    const BASE: &str = "[pipeline]\nname = \"bounds\"\n[stages.scenes]\noperator = \"highway-env\"\n[stages.procedural]\nkind = \"scenes\"\noperator = \"procedural\"\n\
                        [stages.labels]\noperator = \"ego-grid\"\ninputs = { scenes = \"scenes\" }\n[stages.captions]\noperator = \"template\"\n[stages.tokens]\noperator = \"bpe\"\n";
    let dir = std::env::temp_dir().join(format!("rlmflow-bounds-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let cases = [
        ("bpe", "context = 9223372036854775807", "stages.tokens.context: must be in 3..=8192, not 9223372036854775807"),
        ("bpe", "vocab = 9223372036854775807", "stages.tokens.vocab: must be in 259..=262144"),
        ("procedural", "radar = { range_samples = 1048576, angle_bins = 65536 }", "stages.procedural.radar.range_samples: must be in 16..=8192"),
        (
            "procedural",
            "radar = { range_samples = 8192, angle_bins = 8192 }",
            "radar.angle_bins: range_samples x angle_bins needs 3072 MiB per render thread",
        ),
        ("template", "per_frame = 10000000000000", "stages.captions.per_frame: must be in 1..=100"),
        ("highway-env", "episode_frames = 1000000000\nframes = 24", "stages.scenes.episode_frames: must be in 1..=10000"),
        ("highway-env", "frames = 10000000000000", "stages.scenes.frames: must be in 1..=10000000"),
        ("procedural", "frames = 10000000000000", "stages.procedural.frames: must be in 1..=10000000"),
        ("procedural", "frames = 1e13", "stages.procedural.frames: invalid type: floating point"),
    ];
    for (operator, setting, expected) in cases {
        let text = BASE.replace(&format!("operator = \"{operator}\"\n"), &format!("operator = \"{operator}\"\n{setting}\n"));
        std::fs::write(dir.join("p.toml"), text).unwrap();
        let out = Command::new(env!("CARGO_BIN_EXE_rlmflow")).current_dir(&dir).args(["run", "p.toml", "--dry-run"]).output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{setting}: {stderr}");
        assert!(stderr.contains(expected), "{setting}: expected `{expected}` in {stderr}");
    }
}

/// Settings that do not fit what their inputs will be are config errors before anything runs,
/// with the stage's file, line and key: a batch larger than the scenes, an image a ViT patch or
/// the U-Net's levels do not divide, scenes of two sizes mixed.
#[test]
fn settings_that_do_not_fit_their_inputs_are_config_errors() {
    const BASE: &str = "[pipeline]\nname = \"fit\"\n[stages.scenes]\noperator = \"procedural\"\nframes = 100\nradar = { image = 32 }\n\
                        [stages.labels]\noperator = \"ego-grid\"\n[stages.captions]\noperator = \"template\"\n[stages.tokens]\noperator = \"bpe\"\n";
    let dir = std::env::temp_dir().join(format!("rlmflow-fit-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let cases = [
        (
            "[stages.pretrain]\noperator = \"clip\"\nbatch = 128\n",
            "p.toml:16: stages.pretrain.batch: 128 is more than the 100 frames its scenes hold",
        ),
        (
            "[stages.pretrain]\noperator = \"clip\"\nbatch = 90\n",
            "p.toml:16: stages.pretrain.batch: 90 is more than the about 80 frames of the labels' training split",
        ),
        (
            "[stages.pretrain]\noperator = \"clip\"\nencoder = \"vit-b16\"\nbatch = 16\n",
            "stages.pretrain.encoder: `vit-b16` needs an image side divisible by 16; the scenes have 40",
        ),
        (
            "[stages.unet]\nkind = \"segment\"\noperator = \"unet\"\nbatch = 8\nchannels = [4, 4, 4, 4, 4, 4, 4]\n",
            "stages.unet.channels: 7 levels need an image side divisible by 64; the scenes have 32",
        ),
        (
            "[stages.big]\nkind = \"scenes\"\noperator = \"procedural\"\nradar = { image = 64 }\n[stages.mixed]\nkind = \"mix\"\noperator = \"concat\"\ninputs = { scenes = [\"scenes\", \"big\"] }\n",
            "stages.mixed.inputs.scenes: mixes scenes of 32 px and 64 px; a mix needs one image size",
        ),
    ];
    for (stage, expected) in cases {
        let mut text = BASE
            .replace("[stages.labels]\noperator = \"ego-grid\"\n", "[stages.labels]\noperator = \"ego-grid\"\ninputs = { scenes = \"scenes\" }\n");
        if stage.contains("vit-b16") {
            text = text.replace("image = 32", "image = 40");
        }
        std::fs::write(dir.join("p.toml"), format!("{text}{stage}")).unwrap();
        let out = Command::new(env!("CARGO_BIN_EXE_rlmflow")).current_dir(&dir).args(["run", "p.toml", "--dry-run"]).output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{stage}: {stderr}");
        assert!(stderr.contains(expected), "{stage}: expected `{expected}` in {stderr}");
    }
    // A split that leaves no test or no training group fails every model stage after the scenes
    // are made: it is the labels' config error.
    let split_cases = [
        (("frames = 100", "frames = 2"), "p.toml:7: stages.labels.test_fraction: 0.2 holds out 0.4 of the scenes' 2 split groups"),
        (
            ("operator = \"ego-grid\"\n", "operator = \"ego-grid\"\ntest_fraction = 0.0\n"),
            "stages.labels.test_fraction: 0 holds out 0.0 of the scenes' 100",
        ),
        (("operator = \"ego-grid\"\n", "operator = \"ego-grid\"\ntest_fraction = 0.999\n"), "and trains on 0.1"),
        (
            ("operator = \"procedural\"\nframes = 100\n", "operator = \"highway-env\"\nframes = 40\nepisode_frames = 40\n"),
            "0.2 holds out 0.2 of the scenes' 1 split groups (sequences, or frames outside any)",
        ),
    ];
    for ((from, to), expected) in split_cases {
        std::fs::write(dir.join("p.toml"), BASE.replace(from, to)).unwrap();
        let out = Command::new(env!("CARGO_BIN_EXE_rlmflow")).current_dir(&dir).args(["run", "p.toml", "--dry-run"]).output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{to}: {stderr}");
        assert!(stderr.contains(expected), "{to}: expected `{expected}` in {stderr}");
    }
}

#[test]
fn the_ci_pipeline_runs_and_a_second_run_reuses_every_stage() {
    let dir = std::env::temp_dir().join(format!("rlmflow-ci-pipeline-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(root().join("examples/ci.toml"), dir.join("ci.toml")).unwrap();
    let (ok, first) = rlmflow(&dir, &["run", "ci.toml", "--json"]);
    assert!(ok, "{first}");
    let finished =
        |log: &str, status: &str| log.lines().filter(|l| l.contains("\"stage_finished\"") && l.contains(&format!("\"status\":\"{status}\""))).count();
    let stages = finished(&first, "ran");
    assert!(stages >= 1, "{first}");
    let (ok, second) = rlmflow(&dir, &["run", "ci.toml", "--json"]);
    assert!(ok, "{second}");
    assert_eq!((finished(&second, "reused"), finished(&second, "ran")), (stages, 0), "{second}");
    let (ok, verify) = rlmflow(&dir, &["verify", "ci.toml"]);
    assert!(ok, "{verify}");
    // The caption probes, greedy and beam, the report (its Rerun recording included) and the
    // scenes mix give the same bytes in fresh processes.
    let checked = ["clipcap", "clipcap-beam", "report", "mixed"];
    let args: Vec<&str> = ["run", "ci.toml"].into_iter().chain(checked.iter().flat_map(|s| ["--check-determinism", s])).collect();
    let (ok, check) = rlmflow(&dir, &args);
    assert!(ok && check.matches("same bytes").count() == 6, "{check}");
    let objects = dir.join(".rlmflow/objects");
    the_report_holds_every_probe(&objects);
    a_local_hyperqueue_cluster_gives_the_same_keys_and_bytes(&dir, stages);
    a_fresh_store_pulls_every_stage_from_a_remote_and_computes_nothing(&dir, &first);

    // One probe setting changed: only that probe's instances and the report run again.
    let edited =
        std::fs::read_to_string(dir.join("ci.toml")).unwrap().replacen("source = \"pixels\"", "source = \"pixels\"\nlambdas = [0.1, 10.0]", 1);
    std::fs::write(dir.join("ci.toml"), edited).unwrap();
    let (ok, third) = rlmflow(&dir, &["run", "ci.toml", "--json"]);
    assert!(ok, "{third}");
    let ran: Vec<String> = third
        .lines()
        .filter(|l| l.contains("\"stage_finished\"") && l.contains("\"status\":\"ran\""))
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["stage"].as_str().unwrap().to_owned())
        .collect();
    assert_eq!(ran, ["pixels", "report"], "{third}");
    let scenes = artifacts(&objects, "scenes.mcap");
    assert_eq!(scenes.len(), 6, "one per scenes stage and shard, and the mix: {scenes:?}");
    for artifact in scenes {
        a_stock_mcap_reader_agrees(&artifact);
    }
    let [labels, captions, tokens] = ["labels.jsonl", "captions.jsonl", "tokenizer.json"].map(|file| {
        let found = artifacts(&objects, file);
        assert_eq!(found.len(), 1, "{file}: {found:?}");
        found[0].clone()
    });
    every_caption_parses_to_its_labels(&labels, &captions);
    python_tokenizers_gives_the_same_ids(&captions, &tokens);
}

/// `rlmflow push` of the CI pipeline's results to a directory remote; a fresh store beside it
/// then computes nothing: every stage is pulled, with the output digests of the run that
/// computed them.
fn a_fresh_store_pulls_every_stage_from_a_remote_and_computes_nothing(local: &Path, computed: &str) {
    let remote = format!("file://{}", local.with_extension("remote").display());
    let (ok, out) = rlmflow(local, &["push", "ci.toml", "--remote", &remote]);
    assert!(ok, "{out}");
    let fresh = local.with_extension("pulled");
    let _ = std::fs::remove_dir_all(&fresh);
    std::fs::create_dir_all(&fresh).unwrap();
    std::fs::copy(local.join("ci.toml"), fresh.join("ci.toml")).unwrap();
    let (ok, pulled) = rlmflow(&fresh, &["run", "ci.toml", "--json", "--remote", &remote]);
    assert!(ok, "{pulled}");
    let outputs = |log: &str, status: &str| -> Vec<(String, String)> {
        let mut v: Vec<(String, String)> = log
            .lines()
            .filter(|l| l.contains("\"stage_finished\"") && l.contains(&format!("\"status\":\"{status}\"")))
            .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
            .map(|e| (e["stage"].as_str().unwrap().to_owned(), e["output"].as_str().unwrap().to_owned()))
            .collect();
        v.sort();
        v
    };
    assert_eq!(outputs(&pulled, "pulled"), outputs(computed, "ran"), "pulled everything, the same digests: {pulled}");
    let (ok, verify) = rlmflow(&fresh, &["verify", "ci.toml"]);
    assert!(ok, "{verify}");
    std::fs::remove_dir_all(&fresh).unwrap();
}

/// `examples/ci.toml` run in `local` (by the local executor) again through a local HyperQueue
/// cluster into a store of its own: every action has the same key and output digest, and a second
/// run reuses everything and starts no cluster.
fn a_local_hyperqueue_cluster_gives_the_same_keys_and_bytes(local: &Path, stages: usize) {
    let dir = local.with_extension("hyperqueue");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(local.join("ci.toml"), dir.join("ci.toml")).unwrap();
    let (ok, first) = rlmflow(&dir, &["run", "ci.toml", "--json", "--executor", "hyperqueue"]);
    assert!(ok, "{first}");
    assert!(first.contains("\"executor\":\"hyperqueue (local cluster"), "{first}");
    let actions = |dir: &Path| {
        let store = rlmflow_cache::Store::open_existing(&dir.join(".rlmflow")).unwrap().unwrap();
        let keys = store.last_keys("ci").unwrap();
        keys.into_iter().map(|(label, key)| (label, key, store.record(&key).unwrap().unwrap().output)).collect::<Vec<_>>()
    };
    let (through_hq, locally) = (actions(&dir), actions(local));
    assert_eq!(through_hq.len(), stages);
    assert_eq!(through_hq, locally);
    let (ok, second) = rlmflow(&dir, &["run", "ci.toml", "--json", "--executor", "hyperqueue"]);
    assert!(ok, "{second}");
    assert_eq!(second.matches("\"status\":\"reused\"").count(), stages, "{second}");
    let run = second.lines().find(|l| l.contains("\"run_started\"")).unwrap();
    let run = serde_json::from_str::<serde_json::Value>(run).unwrap()["run"].as_str().unwrap().to_owned();
    assert!(!dir.join(".rlmflow/runs").join(run).join("hyperqueue/server").exists(), "a warm run starts no cluster");
}

/// The report reads every probe and segmenter instance: its tables name them, `metrics.json`
/// holds their numbers, and the Python `rerun` package reads its recording's entities.
fn the_report_holds_every_probe(objects: &Path) {
    let reports = artifacts(objects, "report.html");
    assert_eq!(reports.len(), 1, "{reports:?}");
    let report = &reports[0];
    let html = std::fs::read_to_string(report.join("report.html")).unwrap();
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

/// The artifact directories in a store that hold `file`.
fn artifacts(objects: &Path, file: &str) -> Vec<PathBuf> {
    let mut found = Vec::new();
    for shard in std::fs::read_dir(objects).unwrap() {
        for object in std::fs::read_dir(shard.unwrap().path()).unwrap() {
            let path = object.unwrap().path();
            if path.join(file).exists() {
                found.push(path);
            }
        }
    }
    found
}

fn every_caption_parses_to_its_labels(labels: &Path, captions_dir: &Path) {
    let labels = rlmflow_stages::labels::Labels::open(labels).unwrap();
    let captions = rlmflow_stages::captions::Captions::open(captions_dir).unwrap();
    let (ok, out) = rlmflow(&root(), &["parse", captions_dir.join("captions.jsonl").to_str().unwrap()]);
    assert!(ok, "{out}");
    let grids: Vec<&str> = out.lines().collect();
    assert_eq!(grids.len(), captions.captions.len());
    for (caption, parsed) in captions.captions.iter().zip(grids) {
        assert_eq!(parsed, labels.frames[caption.frame as usize].grid.to_json(), "{}", caption.caption);
    }
}

fn python_tokenizers_gives_the_same_ids(captions: &Path, tokens: &Path) {
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

/// Reads `scenes.mcap` with the Python `mcap` package (protobuf decoding from
/// `mcap-protobuf-support`) in the managed environment and compares every message with what
/// rlmflow's reader returns through `scenes.index`.
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

#[test]
fn parse_reads_plain_and_json_lines_and_names_the_bad_line() {
    let dir = std::env::temp_dir().join(format!("rlmflow-parse-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let captions = dir.join("captions.jsonl");
    std::fs::write(
        &captions,
        "Within zero to ten meters there is one car directly ahead of us in the same lane.\n{\"frame\": 3, \"caption\": \"Further away, two vehicles are in the left adjacent lane behind us.\"}\nnothing here\n",
    )
    .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_rlmflow")).args(["parse", captions.to_str().unwrap()]).output().unwrap();
    assert!(out.status.success());
    let lines: Vec<String> = String::from_utf8(out.stdout).unwrap().lines().map(String::from).collect();
    assert_eq!(lines.len(), 3);
    assert!(lines[0].starts_with(r#"{"0-10m":{"total_vehicles":1,"in_lane_front_side":1}"#), "{}", lines[0]);
    assert!(lines[1].contains(r#""30-40m":{"total_vehicles":2,"left_lane_back_side":2}"#), "{}", lines[1]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("captions.jsonl:3: warning: no distance bin recognised"));
    std::fs::write(&captions, "{\"text\": \"no caption field\"}\n").unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_rlmflow")).args(["parse", captions.to_str().unwrap()]).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("captions.jsonl:1: a JSON line needs a string field `caption`"));
}

#[test]
fn parse_into_a_reader_that_stops_early_is_not_an_error() {
    use std::io::Write;
    let mut child = Command::new(env!("CARGO_BIN_EXE_rlmflow"))
        .arg("parse")
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // `| head -0`: the reader is gone before anything is written, and the output (about 4 MB)
    // is far more than a pipe holds.
    drop(child.stdout.take());
    let line = "From ten to twenty meters, there are two cars in the left adjacent lane ahead of us.\n";
    // rlmflow stops reading once it cannot write, so this write may itself find a closed pipe.
    let _ = child.stdin.take().unwrap().write_all(line.repeat(20_000).as_bytes());
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(String::from_utf8_lossy(&out.stderr), "");
}

#[test]
fn setup_reports_the_managed_environment_the_stages_use() {
    let env = rlmflow_python::ensure(&mut |_| {}).unwrap();
    let (ok, out) = rlmflow(&root(), &["setup"]);
    assert!(ok, "{out}");
    assert!(out.contains(&format!("environment: {}", env.root.display())), "{out}");
    assert!(env.site_packages.join("highway_env").is_dir(), "{}", env.site_packages.display());
}

const SCENARIOS: [&str; 6] = ["highway", "merge", "roundabout", "intersection", "two-way", "divided"];

/// A pipeline with one highway-env scenes stage per scenario, named after it.
fn highway_stages(name: &str, scenarios: &[&str], settings: &str) -> String {
    let mut text = format!("[pipeline]\nname = \"{name}\"\nseed = 5\n");
    for s in scenarios {
        text += &format!(
            "\n[stages.{s}]\nkind = \"scenes\"\noperator = \"highway-env\"\nradar = {{ image = 32 }}\nscenarios = {{ {s} = {{}} }}\n{settings}\n"
        );
    }
    text
}

fn scratch(name: &str, pipeline: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("rlmflow-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("p.toml"), pipeline).unwrap();
    dir
}

/// The output digest of stage `label` of `pipeline` in the store beside `dir`'s pipeline.
fn output_digest(dir: &Path, pipeline: &str, label: &str) -> rlmflow_cache::Digest {
    let store = rlmflow_cache::Store::open_existing(&dir.join(".rlmflow")).unwrap().unwrap();
    store.record(&store.last_keys(pipeline).unwrap()[label]).unwrap().unwrap().output
}

/// The same placed frames as one action and as shards of several sizes: the same bytes.
#[test]
fn a_sharded_procedural_stage_gives_the_bytes_of_the_unsharded_one() {
    let stage = |name: &str, split: &str| {
        format!("\n[stages.{name}]\nkind = \"scenes\"\noperator = \"procedural\"\nframes = 30\nradar = {{ image = 32 }}\n{split}\n")
    };
    let pipeline =
        format!("[pipeline]\nname = \"shards\"\nseed = 3\n{}{}{}", stage("whole", ""), stage("four", "shards = 4"), stage("sized", "shard_size = 7"));
    let dir = scratch("procedural-shards", &pipeline);
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    let whole = output_digest(&dir, "shards", "whole");
    assert_eq!(output_digest(&dir, "shards", "four"), whole);
    assert_eq!(output_digest(&dir, "shards", "sized"), whole);
    assert_ne!(output_digest(&dir, "shards", "four#0"), whole, "a part holds only its own frames");
}

/// An OpenAI-compatible endpoint on loopback answering every request with `n` copies of one
/// caption per frame prompt (the grid's first number word, so answers differ between frames).
fn fake_llm() -> String {
    use std::io::{BufRead, BufReader, Read, Write};
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}/v1", listener.local_addr().unwrap());
    std::thread::spawn(move || {
        for stream in listener.incoming().flatten() {
            std::thread::spawn(move || {
                let mut reader = BufReader::new(stream.try_clone().unwrap());
                let mut stream = stream;
                loop {
                    let mut length = 0;
                    let mut line = String::new();
                    loop {
                        line.clear();
                        if reader.read_line(&mut line).unwrap_or(0) == 0 {
                            return;
                        }
                        if let Some(v) = line.to_ascii_lowercase().strip_prefix("content-length:") {
                            length = v.trim().parse().unwrap();
                        }
                        if line == "\r\n" {
                            break;
                        }
                    }
                    let mut body = vec![0; length];
                    reader.read_exact(&mut body).unwrap();
                    let request: serde_json::Value = serde_json::from_slice(&body).unwrap();
                    let prompt = request["messages"][1]["content"].as_str().unwrap();
                    let words: Vec<&str> = prompt.split('"').filter(|w| w.chars().all(|c| c.is_ascii_lowercase()) && !w.is_empty()).take(6).collect();
                    let caption = format!("The scene holds {}.", words.join(" "));
                    let choices: Vec<_> = (0..request["n"].as_u64().unwrap()).map(|_| serde_json::json!({"message": {"content": caption}})).collect();
                    let answer = serde_json::json!({"choices": choices, "usage": {"prompt_tokens": 9, "completion_tokens": 4}}).to_string();
                    let head = format!("HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n", answer.len());
                    if stream.write_all(head.as_bytes()).and_then(|()| stream.write_all(answer.as_bytes())).is_err() {
                        return;
                    }
                }
            });
        }
    });
    url
}

/// The same captions from one `llm` action and from three shares of its labelled frames joined
/// by `concat-captions`: the same bytes, so a consumer of either would be reused.
#[test]
fn a_sharded_llm_stage_gives_the_bytes_of_the_unsharded_one() {
    let url = fake_llm();
    let dir = std::env::temp_dir().join(format!("rlmflow-llm-shards-{}", std::process::id()));
    let stage = |name: &str, split: &str| {
        format!(
            "\n[stages.{name}]\nkind = \"captions\"\noperator = \"llm\"\nbase_url = \"{url}\"\nmodel = \"fake\"\napi_key_env = \"\"\nn = 2\nregenerate = 0\non_mismatch = \"keep\"\nresponse_cache = \"{}\"\n{split}\n",
            dir.join("answers").display()
        )
    };
    let pipeline = format!(
        "[pipeline]\nname = \"llm-shards\"\nseed = 3\n[stages.scenes]\noperator = \"procedural\"\nframes = 10\nradar = {{ image = 32 }}\n[stages.labels]\noperator = \"ego-grid\"\ntest_fraction = 0.2\n{}{}",
        stage("whole", ""),
        stage("three", "shards = 3")
    );
    let dir = scratch("llm-shards", &pipeline);
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    let whole = output_digest(&dir, "llm-shards", "whole");
    assert_eq!(output_digest(&dir, "llm-shards", "three"), whole);
    assert_ne!(output_digest(&dir, "llm-shards", "three#1"), whole, "a share holds only its own frames");
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--dry-run"]);
    assert!(ok && out.contains("three#2"), "{out}");
}

/// An `llm` stage keeps its answers in the store: `verify` quarantines a damaged one, and `gc
/// --responses` clears them.
#[test]
fn llm_answers_live_in_the_store_where_verify_and_gc_see_them() {
    let url = fake_llm();
    let pipeline = format!(
        "[pipeline]\nname = \"llm-store\"\nseed = 3\n[stages.scenes]\noperator = \"procedural\"\nframes = 6\nradar = {{ image = 32 }}\n[stages.labels]\noperator = \"ego-grid\"\ntest_fraction = 0.2\n\
         [stages.captions]\noperator = \"llm\"\nbase_url = \"{url}\"\nmodel = \"fake\"\napi_key_env = \"\"\nn = 2\nregenerate = 0\non_mismatch = \"keep\"\n"
    );
    let dir = scratch("llm-store", &pipeline);
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    let answers = dir.join(".rlmflow/responses/llm");
    let mut stored: Vec<PathBuf> = std::fs::read_dir(&answers).unwrap().map(|e| e.unwrap().path()).collect();
    stored.sort();
    assert!(!stored.is_empty() && stored.iter().all(|p| p.extension().is_some_and(|e| e == "json")), "{stored:?}");
    let (ok, out) = rlmflow(&dir, &["verify", "p.toml"]);
    assert!(ok, "{out}");
    std::fs::write(&stored[0], b"{\"half").unwrap();
    let (ok, out) = rlmflow(&dir, &["verify", "p.toml"]);
    assert!(!ok && out.contains(stored[0].file_name().unwrap().to_str().unwrap()), "{out}");
    assert!(!stored[0].exists(), "the damaged answer is quarantined");
    let (ok, out) = rlmflow(&dir, &["gc", "p.toml", "--responses"]);
    assert!(ok && out.contains("1 responses"), "{out}");
    assert!(!answers.exists());
}

/// Every scenario, each attempt a fresh process (fresh hash seeds, allocator addresses and
/// Python interpreter) with a different thread count, the second asking numpy for every loop it
/// has (AVX-512 where the machine has it; the embedded interpreter keeps them off): the same
/// bytes.
#[test]
fn highway_env_scenes_are_the_same_bytes_in_fresh_processes_for_every_scenario() {
    if !std::arch::is_x86_feature_detected!("avx512f") {
        println!(
            "this machine has no AVX-512: numpy's AVX-512 loops cannot run here, only its AVX2 ones (rlmflow-python's unit test checks both are off)"
        );
    }
    let dir = scratch("highway-determinism", &highway_stages("determinism", &SCENARIOS, "frames = 12\nepisode_frames = 4"));
    let mut args = vec!["run", "p.toml", "--jobs", "2"];
    for s in SCENARIOS {
        args.extend(["--check-determinism", s]);
    }
    let (ok, out) = rlmflow(&dir, &args);
    assert!(ok, "{out}");
    assert_eq!(out.matches("same bytes").count(), SCENARIOS.len(), "{out}");
}

/// Killed with SIGKILL right after an episode was checkpointed, and again in the middle of an
/// episode, a highway-env stage resumes to the bytes of an uninterrupted run.
#[test]
fn highway_env_scenes_resume_after_sigkill_to_the_same_bytes() {
    use std::os::unix::process::CommandExt;
    let pipeline = highway_stages("resume", &["intersection"], "frames = 16\nepisode_frames = 4\nwarmup_steps = 60");
    let reference = scratch("highway-reference", &pipeline);
    let (ok, out) = rlmflow(&reference, &["run", "p.toml"]);
    assert!(ok, "{out}");
    let expected = output_digest(&reference, "resume", "intersection");

    // Frames checkpointed so far by the one running action.
    let checkpointed = |dir: &Path| -> Option<u64> {
        let checkpoints = std::fs::read_dir(dir.join(".rlmflow/checkpoints")).ok()?;
        let progress = checkpoints.flatten().map(|c| c.path().join("progress.json")).find(|p| p.exists())?;
        let value: serde_json::Value = serde_json::from_slice(&std::fs::read(progress).ok()?).ok()?;
        value["frames"].as_u64()
    };
    for (name, after_boundary) in [("boundary", Duration::ZERO), ("mid-episode", Duration::from_millis(150))] {
        let dir = scratch(&format!("highway-kill-{name}"), &pipeline);
        let mut run = Command::new(env!("CARGO_BIN_EXE_rlmflow"))
            .current_dir(&dir)
            .args(["run", "p.toml"])
            .stdout(std::process::Stdio::null())
            .process_group(0)
            .spawn()
            .unwrap();
        let t0 = Instant::now();
        while checkpointed(&dir).unwrap_or(0) == 0 {
            assert!(t0.elapsed() < Duration::from_secs(120), "{name}: no episode was checkpointed");
            std::thread::sleep(Duration::from_millis(5));
        }
        std::thread::sleep(after_boundary);
        // The whole group: the engine and its `rlmflow exec` child.
        unsafe { libc::kill(-(run.id() as i32), libc::SIGKILL) };
        run.wait().unwrap();
        let done = checkpointed(&dir).unwrap();
        assert!((4..16).contains(&done), "{name}: killed with {done} of 16 frames checkpointed");
        let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
        assert!(ok, "{name}: {out}");
        assert_eq!(output_digest(&dir, "resume", "intersection"), expected, "{name}: resumed from {done} frames");
    }
}

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

/// Every key path of a settings object (`radar.image`; arrays are values).
fn key_paths(value: &serde_json::Value, prefix: &str, out: &mut std::collections::BTreeSet<String>) {
    if let serde_json::Value::Object(map) = value {
        for (key, v) in map {
            let path = if prefix.is_empty() { key.clone() } else { format!("{prefix}.{key}") };
            match v {
                serde_json::Value::Object(_) => key_paths(v, &path, out),
                _ => {
                    out.insert(path);
                }
            }
        }
    }
}

/// A pipeline holding one stage `x` of `operator` with `setting = value`, on tiny inputs.
fn tiny_pipeline(operator: &str, setting: &str, value: &serde_json::Value, llm: &str) -> String {
    let scenes = "[stages.scenes]\noperator = \"procedural\"\nframes = 6\nradar = { image = 32 }\n";
    // Numbers and plain strings read the same in JSON and TOML.
    let stage = match operator {
        "procedural" => "[stages.x]\nkind = \"scenes\"\noperator = \"procedural\"\nframes = 6\nradar = { image = 32 }\n".to_owned(),
        "concat" => format!(
            "{scenes}[stages.more]\nkind = \"scenes\"\noperator = \"procedural\"\nframes = 4\nfirst_frame = 6\nradar = {{ image = 32 }}\n\
             [stages.x]\nkind = \"mix\"\noperator = \"concat\"\ninputs = {{ scenes = [\"scenes\", \"more\"] }}\n"
        ),
        "llm" => format!(
            "{scenes}[stages.labels]\noperator = \"ego-grid\"\ntest_fraction = 0.2\n\
             [stages.x]\nkind = \"captions\"\noperator = \"llm\"\nbase_url = \"{llm}\"\nmodel = \"fake\"\nn = 2\nregenerate = 0\non_mismatch = \"keep\"\n"
        ),
        "import" => format!("[stages.x]\nkind = \"scenes\"\noperator = \"import\"\npath = \"{}\"\nimage = 32\n", import::walk_recording().display()),
        other => panic!("no tiny pipeline for `{other}`, which declares settings outside its key: add one here"),
    };
    format!("[pipeline]\nname = \"walk\"\nseed = 3\n{stage}{setting} = {value}\n")
}

/// Another valid value for a setting that cannot change a result.
fn another(value: &serde_json::Value) -> serde_json::Value {
    match value {
        serde_json::Value::Number(n) if n.is_u64() => (n.as_u64().unwrap() * 2 + 1).into(),
        serde_json::Value::Number(n) => (n.as_f64().unwrap() * 2.0 + 1.0).into(),
        serde_json::Value::String(s) if s.is_empty() => "answers-elsewhere".into(),
        serde_json::Value::String(s) => format!("{s}_OTHER").into(),
        other => panic!("no second value for {other}: teach `another` this type"),
    }
}

/// Same key, same bytes, for every setting of every registered operator (`rlmflow operators
/// --json`): every setting an operator does not declare as outside the result is in its
/// actions' preimages (whose BLAKE3 is the key), as the stores of the CI pipeline and of an
/// `llm` pipeline show for every operator; and every setting it declares outside the result,
/// run at two values on tiny inputs, gives the same output bytes. A new setting is covered
/// without anyone listing it.
#[test]
fn every_setting_of_every_operator_enters_the_key_or_leaves_the_bytes_alone() {
    let (ok, listing) = rlmflow(&root(), &["operators", "--json"]);
    assert!(ok, "{listing}");
    let operators: Vec<serde_json::Value> = listing.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let llm = fake_llm();

    // Stores in which every operator ran.
    let ci = scratch("walk-ci", &std::fs::read_to_string(root().join("examples/ci.toml")).unwrap());
    let llm_dir = scratch(
        "walk-llm",
        &format!(
            "[pipeline]\nname = \"walk-llm\"\nseed = 3\n[stages.scenes]\noperator = \"procedural\"\nframes = 6\nradar = {{ image = 32 }}\n\
             [stages.labels]\noperator = \"ego-grid\"\ninputs = {{ scenes = \"scenes\" }}\ntest_fraction = 0.2\n\
             [stages.captions]\noperator = \"llm\"\nbase_url = \"{llm}\"\nmodel = \"fake\"\napi_key_env = \"\"\nn = 2\nregenerate = 0\non_mismatch = \"keep\"\nshards = 2\n\
             [stages.imported]\nkind = \"scenes\"\noperator = \"import\"\npath = \"{}\"\nimage = 32\n",
            import::walk_recording().display()
        ),
    );
    let mut config_paths: std::collections::BTreeMap<String, Vec<(std::collections::BTreeSet<String>, serde_json::Value)>> = Default::default();
    for dir in [&ci, &llm_dir] {
        let (ok, out) = rlmflow(dir, &["run", "p.toml"]);
        assert!(ok, "{out}");
        let store = rlmflow_cache::Store::open_existing(&dir.join(".rlmflow")).unwrap().unwrap();
        for key in store.record_keys().unwrap() {
            let preimage = store.record(&key).unwrap().unwrap().preimage;
            let mut paths = Default::default();
            key_paths(&preimage.config, "", &mut paths);
            config_paths.entry(preimage.operator).or_default().push((paths, preimage.config));
        }
    }
    for op in &operators {
        let name = op["name"].as_str().unwrap();
        let non_result: Vec<&str> = op["non_result"].as_array().unwrap().iter().map(|k| k.as_str().unwrap()).collect();
        // A tracked path, when set, enters the key by its content (an input), not by its name;
        // left empty (an optional one, as `init` is by default) it stays in the key as "".
        let tracked: Vec<&str> = op["tracked"].as_array().unwrap().iter().map(|k| k.as_str().unwrap()).collect();
        let mut settings = Default::default();
        key_paths(&op["defaults"], "", &mut settings);
        let instances = config_paths.get(name).unwrap_or_else(|| panic!("`{name}` ran in neither pipeline: add it to one"));
        for (paths, config) in instances {
            for setting in &settings {
                let top = setting.split('.').next().unwrap();
                if tracked.contains(&top) {
                    assert!(!paths.contains(setting) || config[top] == "", "`{name}`: `{setting}`, set, is in the key by its path: {config}");
                    continue;
                }
                let in_key = !non_result.contains(&top);
                assert_eq!(paths.contains(setting), in_key, "`{name}`: `{setting}` in the key: {}", paths.contains(setting));
            }
        }
    }

    // Each setting declared outside the result, at two values: the same bytes.
    for op in &operators {
        let name = op["name"].as_str().unwrap();
        for setting in op["non_result"].as_array().unwrap().iter().map(|k| k.as_str().unwrap()) {
            let default = &op["defaults"][setting];
            let digests: Vec<rlmflow_cache::Digest> = [default.clone(), another(default)]
                .iter()
                .enumerate()
                .map(|(i, value)| {
                    let dir = scratch(&format!("walk-{name}-{setting}-{i}"), &tiny_pipeline(name, setting, value, &llm));
                    let out = Command::new(env!("CARGO_BIN_EXE_rlmflow"))
                        .current_dir(&dir)
                        .args(["run", "p.toml"])
                        .envs([("OPENAI_API_KEY", "sk-walk"), ("OPENAI_API_KEY_OTHER", "sk-walk")])
                        .output()
                        .unwrap();
                    assert!(out.status.success(), "`{name}` with {setting} = {value}: {}", String::from_utf8_lossy(&out.stderr));
                    let digest = output_digest(&dir, "walk", "x");
                    std::fs::remove_dir_all(&dir).unwrap();
                    digest
                })
                .collect();
            assert_eq!(digests[0], digests[1], "`{name}`: `{setting}` changed the output bytes");
        }
    }
    for dir in [ci, llm_dir] {
        std::fs::remove_dir_all(dir).unwrap();
    }
}
