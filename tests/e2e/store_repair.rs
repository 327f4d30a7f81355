//! Damage the store reports, it repairs: a damaged record or ref never stops a run, `verify`
//! quarantines every damaged file it names, abandoned scratch files are swept, `--verify-inputs`
//! re-hashes reused outputs, and `--check-determinism` finds an operator that is not a function
//! of its settings, inputs and seed.

use std::fs;
use std::os::unix::fs::PermissionsExt;

use rlmflow_cache::Store;

use crate::harness::*;

fn record_file(s: &Scratch, label: &str) -> std::path::PathBuf {
    let store = Store::open_existing(&s.store()).unwrap().unwrap();
    let key = rlmflow_test_support::cli::last_keys(&store, "chain")[label];
    s.store().join("actions").join(&key.hex()[..2]).join(format!("{}.json", key.hex()))
}

#[test]
fn a_truncated_or_empty_record_is_a_miss_and_verify_quarantines_it() {
    for damage in [Some(20), None] {
        let s = Scratch::new(&format!("damaged-record-{damage:?}"));
        s.pipeline(CHAIN);
        s.run();
        let record = record_file(&s, "map");
        let bytes = fs::read(&record).unwrap();
        fs::write(&record, damage.map_or(Vec::new(), |n| bytes[..n].to_vec())).unwrap();

        // status and run go on: the damaged record is a miss, and map reruns.
        let status = s.cli(&["status", "p.toml"]);
        assert!(status.status.success(), "{}", text(&status.stderr));
        assert!(text(&status.stderr).contains("is damaged"), "{}", text(&status.stderr));
        let events = s.run();
        assert_eq!(events.status_of("map"), "ran");
        assert_eq!(events.status_of("measure"), "reused", "map reproduced its bytes");
        assert!(s.cli(&["verify", "p.toml"]).status.success(), "the rerun rewrote the record");

        // Damaged again, verify names it and moves it aside; the next run repairs it.
        fs::write(&record, b"").unwrap();
        let out = s.cli(&["verify", "p.toml"]);
        assert_eq!(out.status.code(), Some(1));
        assert!(text(&out.stdout).contains(&format!("damaged {}", record.display())), "{}", text(&out.stdout));
        assert!(!record.exists());
        assert_eq!(s.run().status_of("map"), "ran");
        assert!(s.cli(&["verify", "p.toml"]).status.success());
    }
}

#[test]
fn a_record_under_another_key_is_a_miss() {
    let s = Scratch::new("swapped-record");
    s.pipeline(CHAIN);
    s.run();
    fs::copy(record_file(&s, "source"), record_file(&s, "map")).unwrap();
    assert_eq!(s.run().status_of("map"), "ran");
}

#[test]
fn an_invalid_ref_is_absent_with_a_warning_for_run_status_and_gc_and_verify_quarantines_it() {
    let s = Scratch::new("damaged-ref");
    s.pipeline(CHAIN);
    s.run();
    let reference = s.store().join("refs/pipelines/chain.json");
    fs::write(&reference, b"{\"map\": \"not a digest").unwrap();
    for args in [vec!["status", "p.toml"], vec!["gc", "p.toml"]] {
        let out = s.cli(&args);
        assert!(out.status.success(), "{args:?}: {}", text(&out.stderr));
        assert!(text(&out.stderr).contains("chain.json is damaged"), "{args:?}: {}", text(&out.stderr));
    }
    // gc treated the ref as absent and may have collected; the run recomputes what it must.
    let events = s.run();
    assert_eq!(events.finished().len(), 5);
    let fixed: serde_json::Value = serde_json::from_slice(&fs::read(&reference).unwrap()).unwrap();
    assert_eq!(fixed["instances"].as_array().unwrap().len(), 5, "the run rewrote the ref");

    fs::write(&reference, b"").unwrap();
    let out = s.cli(&["verify", "p.toml"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(text(&out.stdout).contains("chain.json: unreadable"), "{}", text(&out.stdout));
    assert!(!reference.exists());
    assert_eq!(s.run().with_status("reused").len(), 5);
    assert!(s.cli(&["verify", "p.toml"]).status.success());
}

#[test]
fn verify_reports_an_object_directory_without_its_manifest() {
    let s = Scratch::new("no-manifest");
    s.pipeline(CHAIN);
    s.run();
    let object = output_dir(&s.store(), "chain", "source");
    let manifest = object.with_extension("tree");
    fs::remove_file(&manifest).unwrap();
    let out = s.cli(&["verify", "p.toml"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(text(&out.stdout).contains("an object directory without its manifest"), "{}", text(&out.stdout));
    assert!(!object.exists(), "quarantined");
    let events = s.run();
    assert_eq!(events.status_of("source"), "ran");
    assert!(s.cli(&["verify", "p.toml"]).status.success());
}

#[test]
fn verify_reports_a_missing_object_directory_and_the_records_that_need_it() {
    let s = Scratch::new("no-object-dir");
    s.pipeline(CHAIN);
    s.run();
    let object = output_dir(&s.store(), "chain", "source");
    fs::remove_dir_all(&object).unwrap();
    let out = s.cli(&["verify", "p.toml"]);
    let stdout = text(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{stdout}{}", text(&out.stderr));
    assert!(stdout.contains("the object's directory is missing"), "{stdout}");
    assert!(stdout.contains("its action reruns when needed"), "{stdout}");
    assert!(!object.with_extension("tree").exists(), "the manifest is quarantined");
    assert_eq!(s.run().status_of("source"), "ran");
    assert!(s.cli(&["verify", "p.toml"]).status.success());
}

#[test]
fn a_run_sweeps_write_files_abandoned_by_a_killed_process() {
    let s = Scratch::new("abandoned-write");
    s.pipeline(CHAIN);
    s.run();
    let mut gone = std::process::Command::new("true").spawn().unwrap();
    let dead = gone.id();
    gone.wait().unwrap();
    let abandoned = s.store().join(format!("tmp/write-{dead}-0"));
    let live = s.store().join(format!("tmp/write-{}-0", std::process::id()));
    fs::write(&abandoned, b"{\"half\": ").unwrap();
    fs::write(&live, b"{\"being written").unwrap();
    s.run();
    assert!(!abandoned.exists(), "a dead writer's file is swept");
    assert!(live.exists(), "a live writer's file is left alone");
}

#[test]
fn verify_inputs_rehashes_a_reused_output_and_recomputes_it_when_damaged() {
    let s = Scratch::new("verify-inputs");
    s.pipeline(CHAIN);
    s.run();
    let file = output_dir(&s.store(), "chain", "source").join("text.txt");
    fs::set_permissions(&file, fs::Permissions::from_mode(0o644)).unwrap();
    fs::write(&file, "rAdar").unwrap();
    // By design a plain run reuses it (nothing that must run reads it) ...
    assert_eq!(s.run().with_status("reused").len(), 5);
    // ... and --verify-inputs catches it.
    let events = s.run_expecting(0, &["--verify-inputs"]);
    assert_eq!(events.of("output_corrupt").len(), 1);
    assert_eq!(events.status_of("source"), "ran");
    assert_eq!(fs::read_to_string(output_dir(&s.store(), "chain", "source").join("text.txt")).unwrap(), "radar");
    assert_eq!(s.run_expecting(0, &["--verify-inputs"]).with_status("reused").len(), 5);
}

#[test]
fn check_determinism_passes_a_pure_operator_and_names_the_file_an_impure_one_changes() {
    let s = Scratch::new("check-determinism");
    s.pipeline(CHAIN);
    let out = s.cli(&["run", "p.toml", "--check-determinism", "map"]);
    let stdout = text(&out.stdout);
    assert!(out.status.success(), "{stdout}{}", text(&out.stderr));
    assert!(stdout.contains("check-determinism map") && stdout.contains("attempt 2 (fresh process") && stdout.contains("same bytes"), "{stdout}");
    // What map needs ran and was stored; the check itself committed nothing.
    let events = s.run();
    assert_eq!(events.status_of("source"), "reused");
    assert_eq!(events.status_of("map"), "ran");

    s.pipeline(&CHAIN.replace(r#"text = "radar""#, "text = \"radar\"\nnondeterministic = true"));
    let out = s.cli(&["run", "p.toml", "--check-determinism", "source"]);
    let stdout = text(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{stdout}");
    assert!(stdout.contains("NOT DETERMINISTIC: 1 of 1 files differ: text.txt"), "{stdout}");
    assert!(stdout.contains("first difference: text.txt at byte "), "{stdout}");
}
