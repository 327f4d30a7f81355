//! Sharded stages of the real operators give the bytes of the unsharded ones; an `llm` stage's
//! answers live in the store.

use super::*;

/// Every shipped operator that can be sharded (`procedural`'s placed frames, `llm`'s captions of
/// labelled frames, joined by `concat-captions`) gives, as shards of several sizes, the bytes of
/// its unsharded stage, so a consumer of either would be reused; a part holds only its own items.
/// The engine's side of sharding (parts, merges, resharding, resuming) is `tests/e2e/shards.rs`.
#[test]
fn every_shardable_operator_gives_the_bytes_of_its_unsharded_stage() {
    let (ok, listed) = rlmflow(&root(), &["operators", "--json"]);
    assert!(ok, "{listed}");
    let listed: Vec<serde_json::Value> = listed.lines().map(|line| serde_json::from_str(line).unwrap()).collect();
    let mut shardable: Vec<&str> = listed.iter().filter(|o| !o["merge"].is_null()).map(|o| o["name"].as_str().unwrap()).collect();
    shardable.sort();
    assert_eq!(shardable, ["llm", "procedural"], "a shardable operator this test does not shard");

    let procedural = |name: &str, split: &str| {
        format!("\n[stages.{name}]\nkind = \"scenes\"\noperator = \"procedural\"\nframes = 30\nradar = {{ image = 32 }}\n{split}\n")
    };
    let llm = fake_llm();
    let dir = Scratch::new("shards");
    let captions = |name: &str, split: &str| {
        format!(
            "\n[stages.{name}]\nkind = \"captions\"\noperator = \"llm\"\nbase_url = \"{}\"\nmodel = \"fake\"\napi_key_env = \"\"\nn = 2\nregenerate = 0\non_mismatch = \"keep\"\nresponse_cache = \"{}\"\n{split}\n",
            llm.url,
            dir.join("answers").display()
        )
    };
    let pipeline = format!(
        "[pipeline]\nname = \"shards\"\nseed = 3\n{}{}{}\n[stages.labels]\noperator = \"ego-grid\"\ninputs = {{ scenes = \"placed\" }}\ntest_fraction = 0.2\n{}{}",
        procedural("placed", ""),
        procedural("placed-four", "shards = 4"),
        procedural("placed-sized", "shard_size = 7"),
        captions("captions", ""),
        captions("captions-three", "shards = 3"),
    );
    dir.write("p.toml", &pipeline);
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    for (whole, sharded, part) in
        [("placed", "placed-four", "placed-four#0"), ("placed", "placed-sized", "placed-sized#2"), ("captions", "captions-three", "captions-three#1")]
    {
        let bytes = output_digest(&dir, "shards", whole);
        assert_eq!(output_digest(&dir, "shards", sharded), bytes, "{sharded} against {whole}");
        assert_ne!(output_digest(&dir, "shards", part), bytes, "{part} holds only its own items");
    }
    // An `llm` stage's shares are counted when its input is: the plan still names each.
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--dry-run"]);
    assert!(ok && out.contains("captions-three#2"), "{out}");
}

/// An `llm` stage keeps its answers in the store: `verify` quarantines a damaged one, and `gc
/// --responses` clears them.
#[test]
fn llm_answers_live_in_the_store_where_verify_and_gc_see_them() {
    let llm = fake_llm();
    let url = &llm.url;
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
