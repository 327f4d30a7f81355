//! Every setting of every operator either enters the key or leaves the bytes alone.

use super::*;

/// Every key path of a settings object, tables too (`radar` and `radar.image`; arrays are
/// values): a setting that is null by default and a table where it is set (the report's
/// `claims`) is one path either way.
fn key_paths(value: &serde_json::Value, prefix: &str, out: &mut std::collections::BTreeSet<String>) {
    if let serde_json::Value::Object(map) = value {
        for (key, v) in map {
            let path = if prefix.is_empty() { key.clone() } else { format!("{prefix}.{key}") };
            key_paths(v, &path, out);
            out.insert(path);
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
        script if script.starts_with("script@") => format!("{SCRIPT_DATA}[stages.x]\n{}", script_stage(&script["script@".len()..])),
        other => panic!("no tiny pipeline for `{other}`, which declares settings outside its key: add one here"),
    };
    format!("[pipeline]\nname = \"walk\"\nseed = 3\n{stage}{setting} = {value}\n")
}

/// What a script stage of any kind reads: scenes, labels, captions, tokens.
const SCRIPT_DATA: &str = "[stages.scenes]\noperator = \"procedural\"\nframes = 12\nradar = { image = 16 }\n[stages.labels]\noperator = \"ego-grid\"\n\
     [stages.captions]\noperator = \"template\"\n[stages.tokens]\noperator = \"bpe\"\nvocab = 300\ncontext = 32\n";

/// The body of a script stage of `kind` (its table's keys), a one-line program that predicts
/// nothing for every test frame (a probe, a segmenter) or writes its settings (files).
fn script_stage(kind: &str) -> String {
    let code = match kind {
        "probe" => {
            "from rlmflow import stage; import json; c = stage.context(); l = c.read('labels'); open(c.output / 'predictions.jsonl', 'w').write(''.join(json.dumps({'frame': i, 'features': 'zero', 'counts': [0] * 48}) + '\\n' for i, s in enumerate(l.split) if s == 'test'))"
        }
        "segment" => {
            "from rlmflow import stage; import numpy as np; c = stage.context(); l = c.read('labels'); m = l.masks(); np.save(c.output / 'predictions.npy', np.zeros((int((l.split == 'test').sum()),) + m.shape[1:], np.float32))"
        }
        "files" => "from rlmflow import stage; import json; c = stage.context(); open(c.output / 'settings.json', 'w').write(json.dumps(c.settings))",
        other => panic!("no script stage of kind `{other}`"),
    };
    let inputs = if kind == "files" { "inputs = { scenes = \"scenes\" }\n" } else { "" };
    format!("kind = \"{kind}\"\noperator = \"script\"\nrun = [\"python\", \"-c\", {}]\nsettings = {{ k = 1 }}\n{inputs}", serde_json::json!(code))
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
    let llm = &llm.url;

    // Stores in which every operator ran: the CI pipeline's shared run, and an `llm` pipeline's.
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
    let (ok, out) = rlmflow(&llm_dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    // A user's program as each kind it serves.
    let script_dir = scratch("walk-script", &format!("[pipeline]\nname = \"walk-script\"\nseed = 3\n{}", SCRIPT_DATA));
    let mut stages = String::new();
    for kind in ["probe", "segment", "files"] {
        stages += &format!("[stages.{kind}-script]\n{}", script_stage(kind));
    }
    std::fs::write(script_dir.join("p.toml"), std::fs::read_to_string(script_dir.join("p.toml")).unwrap() + &stages).unwrap();
    let (ok, out) = rlmflow(&script_dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    for store in [ci::ci_run().store(), llm_dir.join(".rlmflow"), script_dir.join(".rlmflow")] {
        let store = rlmflow_cache::Store::open_existing(&store).unwrap().unwrap();
        for key in store.record_keys().unwrap() {
            let preimage = store.record(&key).unwrap().unwrap().preimage;
            let mut paths = Default::default();
            key_paths(&preimage.config, "", &mut paths);
            config_paths.entry(preimage.operator).or_default().push((paths, preimage.config));
        }
    }
    for op in &operators {
        let name = op["id"].as_str().unwrap();
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
        let name = op["id"].as_str().unwrap();
        for setting in op["non_result"].as_array().unwrap().iter().map(|k| k.as_str().unwrap()) {
            let default = &op["defaults"][setting];
            let digests: Vec<rlmflow_cache::Digest> = [default.clone(), another(default)]
                .iter()
                .enumerate()
                .map(|(i, value)| {
                    let dir = scratch(&format!("walk-{name}-{setting}-{i}"), &tiny_pipeline(name, setting, value, llm));
                    let out = Command::new(env!("CARGO_BIN_EXE_rlmflow"))
                        .current_dir(&dir)
                        .args(["run", "p.toml"])
                        .envs([("OPENAI_API_KEY", "sk-walk"), ("OPENAI_API_KEY_OTHER", "sk-walk")])
                        .output()
                        .unwrap();
                    assert!(out.status.success(), "`{name}` with {setting} = {value}: {}", String::from_utf8_lossy(&out.stderr));
                    output_digest(&dir, "walk", "x")
                })
                .collect();
            assert_eq!(digests[0], digests[1], "`{name}`: `{setting}` changed the output bytes");
        }
    }
}
