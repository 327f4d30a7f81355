//! `--set STAGE.KEY=VALUE`: a setting changed from the command line is checked as the file is,
//! reruns exactly what `status` says, and is recorded with the run.

use std::fs;

use crate::harness::{CHAIN, Scratch, text};

/// The instances `status --json` says will run or wait on one that will.
fn not_cached(s: &Scratch, extra: &[&str]) -> Vec<String> {
    let mut args = vec!["status", "p.toml", "--json"];
    args.extend_from_slice(extra);
    let out = s.cli(&args);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let mut labels: Vec<String> = text(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .filter(|s| s["state"] != "cached")
        .map(|s| s["stage"].as_str().unwrap().to_owned())
        .collect();
    labels.sort();
    labels
}

#[test]
fn an_override_reruns_exactly_what_status_says_and_the_run_records_it() {
    let s = Scratch::new("override");
    s.pipeline(CHAIN);
    s.run();
    let set = ["--set", "map.suffix=\"?!\"", "--set", "source.text = 'radar'"];
    let expected = not_cached(&s, &set);
    assert_eq!(expected, ["collect", "map", "measure"], "the suffix changes `map` and what reads it; the text is the file's");
    let explained = text(&s.cli(&["explain", "p.toml", "map", "--set", "map.suffix=\"?!\""]).stdout);
    assert!(explained.contains("suffix") && explained.contains("?!"), "{explained}");

    let events = s.run_expecting(0, &set);
    let mut ran = events.with_status("ran");
    ran.sort();
    assert_eq!(ran, expected);
    let run = events.of("run_started")[0]["run"].as_str().unwrap().to_owned();
    let plan: serde_json::Value = serde_json::from_slice(&fs::read(s.store().join("runs").join(&run).join("plan.json")).unwrap()).unwrap();
    assert_eq!(plan["overrides"], serde_json::json!(["--set map.suffix=\"?!\"", "--set source.text = 'radar'"]));
    let provenance = fs::read_to_string(s.store().join("runs").join(&run).join("provenance.md")).unwrap();
    assert!(provenance.contains("`--set map.suffix=\"?!\"`, `--set source.text = 'radar'`"), "{provenance}");
    // The file is untouched: without the override, the first results are current again.
    assert!(not_cached(&s, &[]).is_empty());
    // A new variant only with --set-new: a variant's name mistyped under --set is an error naming
    // the nearest, never a new variant.
    assert_eq!(not_cached(&s, &["--set-new", "map.variants.loud.suffix=\"!!!\""]), ["collect", "map[loud]", "measure[loud]"]);
    let with_variants =
        CHAIN.replace("suffix = \"!\"", "suffix = \"!\"\n[stages.map.variants]\nloud = { suffix = \"!!!\" }\nquiet = { suffix = \".\" }");
    s.pipeline(&with_variants);
    let out = s.cli(&["status", "p.toml", "--set", "map.variants.lod.suffix=\"?\""]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        text(&out.stderr).contains("p.toml: --set map.variants.lod.suffix=\"?\": stage `map` has no variant `lod`; its variants are loud, quiet; did you mean `loud`? (--set-new makes a new one)"),
        "{}",
        text(&out.stderr)
    );
    assert_eq!(
        not_cached(&s, &["--set", "map.variants.loud.suffix=\"?\""]).len(),
        3 + 2,
        "an existing variant is set: its chain and the other variant's"
    );
}

/// The header's keys are overridable too: `--set pipeline.seeds=[1, 2]` fans the seeded stage out
/// over two seeds; a mistyped header key is named.
#[test]
fn the_pipeline_header_is_overridable() {
    let s = Scratch::new("override-header");
    s.pipeline(CHAIN);
    s.run();
    let fanned = not_cached(&s, &["--set", "pipeline.seeds=[1, 2]"]);
    assert_eq!(fanned, ["collect", "measure[seed=1]", "measure[seed=2]"]);
    let out = s.cli(&["status", "p.toml", "--set", "pipeline.seedz=[1]"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        text(&out.stderr).contains("with --set pipeline.seedz=[1]: ") && text(&out.stderr).contains("unknown key `seedz`"),
        "{}",
        text(&out.stderr)
    );
}

#[test]
fn a_bad_override_is_a_config_error_that_names_it_and_creates_no_store() {
    let s = Scratch::new("override-bad");
    s.pipeline(CHAIN);
    let deep = format!("map.suffix={}{}", "[".repeat(20_000), "]".repeat(20_000));
    for (set, says) in [
        (deep.as_str(), "nested more than 32 levels deep"),
        ("mapp.suffix=\"?\"", "no stage `mapp`; the stages are collect, map, measure, other, source; did you mean `map`?"),
        ("map.suffix=?", "`?` is not a TOML value"),
        ("map.suffix=\"a\"\nother = 1", "is not one TOML value"),
        ("map", "has no `=`"),
        ("map=1", "`map` is not STAGE.KEY"),
        ("map.sufix=\"?\"", "stages.map.sufix: unknown setting `sufix`"),
        ("map.suffix=3", "stages.map.suffix:"),
        ("map.suffix.deeper=3", "`map.suffix` is not a table"),
    ] {
        for command in ["run", "status"] {
            let out = s.cli(&[command, "p.toml", "--set", set]);
            let stderr = text(&out.stderr);
            assert_eq!(out.status.code(), Some(2), "{command} --set {set}: {stderr}");
            assert!(stderr.contains(&format!("p.toml with --set {set}: ")) || stderr.contains(&format!("p.toml: --set {set}: ")), "{set}: {stderr}");
            assert!(stderr.contains(says), "{set}: {stderr}");
            assert!(!s.store().exists(), "{set}: nothing was created");
        }
    }
}
