//! Sharded stages of the real operators give the bytes of the unsharded ones; an `llm` stage's
//! answers live in the store.

use super::*;

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

/// The same captions from one `llm` action and from three shares of its labelled frames joined
/// by `concat-captions`: the same bytes, so a consumer of either would be reused.
#[test]
fn a_sharded_llm_stage_gives_the_bytes_of_the_unsharded_one() {
    let llm = fake_llm();
    let url = &llm.url;
    let dir = Scratch::new("llm-shards");
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
    dir.write("p.toml", &pipeline);
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
