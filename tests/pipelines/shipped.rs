//! The shipped pipelines: every one validates, the paper's starts from its public checkpoints,
//! and settings a machine cannot run (memory, time, device) or that do not fit their inputs are
//! config errors before anything runs.

use super::*;

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
/// names which file and where docs/guide/paper-scale.md converts it; with files of the right models where its
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
    // CLIP ViT-B/16 (one input channel) and the paper's text tower with MLP heads: 125.99 M; in
    // bf16, whose activations the estimate takes at 55 % of their float32 bytes (17.4 GiB).
    assert_eq!(
        out.matches("126.0 M parameters, peak ~ 10.4 GiB (CUDA device 0:").count(),
        4,
        "the four trained encoders, 640 in chunks of 40, bf16: {out}"
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
    assert_eq!(out.matches("peak ~ 10.4 GiB (CUDA device 1: 79.6 GiB)").count(), 4, "{out}");
    assert!(out.contains("(CUDA device 0: 40.0 GiB)"), "the other stages, on GPU 0: {out}");
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
    let dir = Scratch::new("bounds");
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
    let dir = Scratch::new("fit");
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
