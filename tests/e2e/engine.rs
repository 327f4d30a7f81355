use std::fs;
use std::os::unix::fs::PermissionsExt;
use std::os::unix::process::CommandExt;
use std::time::{Duration, Instant};

use crate::harness::*;

#[test]
fn a_second_run_reuses_every_stage() {
    let s = Scratch::new("warm");
    s.pipeline(CHAIN);
    let first = s.run();
    assert_eq!(first.with_status("ran").len(), 5);
    assert_eq!(first.of("run_finished")[0]["saved_s"].to_string(), "0.0", "a run that reuses nothing saves 0 s, not -0");
    let second = s.run();
    assert_eq!(second.with_status("reused").len(), 5);
    assert!(second.with_status("ran").is_empty());
    let done = second.of("run_finished")[0];
    assert_eq!((done["ran"].as_u64(), done["reused"].as_u64()), (Some(0), Some(5)));
}

#[test]
fn a_config_change_reruns_exactly_the_changed_stage_and_its_dependants() {
    let s = Scratch::new("rerun");
    s.pipeline(CHAIN);
    s.run();
    s.pipeline(&CHAIN.replace(r#"suffix = "!""#, r#"suffix = "!!""#));
    let events = s.run();
    assert_eq!(events.with_status("ran"), ["collect", "map", "measure"]);
    assert_eq!(events.with_status("reused"), ["other", "source"]);
    let planned = events.of("stage_planned");
    let map = planned.iter().find(|e| e["stage"] == "map").unwrap();
    let setting = serde_json::json!({"reason": "changed", "stage": "map", "change": "setting", "key": "suffix", "old": "!", "new": "!!"});
    assert_eq!(map["reasons"], serde_json::json!([setting]), "the event carries the reason as data");
    let measure = planned.iter().find(|e| e["stage"] == "measure").unwrap();
    assert_eq!(measure["reasons"][0]["change"], "input_changed", "{measure}");
}

#[test]
fn status_says_why_in_words_on_the_terminal_and_as_data_with_json() {
    let s = Scratch::new("why");
    s.pipeline(CHAIN);
    s.run();
    s.pipeline(&CHAIN.replace(r#"suffix = "!""#, r#"suffix = "!!""#));
    let words = text(&s.cli(&["status", "p.toml"]).stdout);
    let map = words.lines().find(|l| l.contains(" map ")).unwrap();
    assert!(map.starts_with("  will run  map") && map.ends_with(r#"map.suffix "!" -> "!!""#), "{words}");
    let measure = words.lines().find(|l| l.contains(" measure ")).unwrap();
    assert!(measure.starts_with("  pending   measure") && measure.ends_with("(map) will be recomputed first"), "{words}");
    let lines: Vec<serde_json::Value> =
        text(&s.cli(&["status", "p.toml", "--json"]).stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let state = |stage: &str| lines.iter().find(|l| l["stage"] == stage).unwrap().clone();
    assert_eq!(state("map")["reasons"][0]["key"], "suffix");
    assert_eq!(state("source")["state"], "cached");
    let pending = state("measure");
    assert_eq!((pending["state"].as_str(), pending["waiting"]["input"].as_str()), (Some("pending"), Some("map")), "{pending}");
}

#[test]
fn settings_that_cannot_change_the_result_do_not_rerun() {
    let s = Scratch::new("nonresult");
    s.pipeline(CHAIN);
    s.run();
    s.pipeline(&CHAIN.replace(r#"text = "radar""#, "text = \"radar\"\nthreads = 2\nstep_ms = 5"));
    assert!(s.run().with_status("ran").is_empty());
}

#[test]
fn early_cutoff_stops_a_rerun_that_reproduces_the_same_bytes() {
    let s = Scratch::new("cutoff");
    s.pipeline(CHAIN);
    s.run();
    // Same length, different text: map and measure rerun, measure's bytes are unchanged.
    s.pipeline(&CHAIN.replace(r#"suffix = "!""#, r#"suffix = "?""#));
    let events = s.run();
    assert_eq!(events.with_status("ran"), ["map", "measure"]);
    assert_eq!(events.status_of("collect"), "reused");
}

#[test]
fn seeds_fan_out_the_stochastic_stages_share_the_data_and_gather_into_one() {
    let s = Scratch::new("seeds");
    let seeded = CHAIN.replace("seed = 7", "seed = 7\nseeds = [1, 2, 3]").replace(r#"operator = "count""#, r#"operator = "sample""#);
    s.pipeline(&seeded);
    let events = s.run();
    assert_eq!(events.with_status("ran"), ["collect", "map", "measure[seed=1]", "measure[seed=2]", "measure[seed=3]", "other", "source"]);
    let listing = fs::read_to_string(output_dir(&s.store(), "chain", "collect").join("listing.txt")).unwrap();
    assert_eq!(listing, "measure[seed=1] seed 1 picks A\nmeasure[seed=2] seed 2 picks D\nmeasure[seed=3] seed 3 picks A\n");
    assert_eq!(s.run().with_status("ran"), Vec::<String>::new());
    // One more seed: only its instance and the gathering stage run.
    s.pipeline(&seeded.replace("seeds = [1, 2, 3]", "seeds = [1, 2, 3, 4]"));
    assert_eq!(s.run().with_status("ran"), ["collect", "measure[seed=4]"]);
    // A stage can opt out: one measure, run with [pipeline] seed.
    s.pipeline(&seeded.replace(r#"operator = "sample""#, "operator = \"sample\"\nper_seed = false"));
    let events = s.run();
    assert_eq!(events.with_status("ran"), ["collect", "measure"]);
    assert_eq!(fs::read_to_string(output_dir(&s.store(), "chain", "collect").join("listing.txt")).unwrap(), "measure seed 7 picks A\n");
}

#[test]
fn variants_fan_out_downstream_and_are_gathered_side_by_side() {
    let s = Scratch::new("variants");
    s.pipeline(&CHAIN.replace(r#"suffix = "!""#, "[stages.map.variants]\nloud = { suffix = \"!!!\" }\nquiet = { suffix = \".\" }"));
    let events = s.run();
    let mut ran = events.with_status("ran");
    ran.sort();
    assert_eq!(ran, ["collect", "map[loud]", "map[quiet]", "measure[loud]", "measure[quiet]", "other", "source"]);
    let listing = fs::read_to_string(output_dir(&s.store(), "chain", "collect").join("listing.txt")).unwrap();
    assert_eq!(listing, "measure[loud] 8\nmeasure[quiet] 6\n");

    // Changing one variant reruns only its branch (and the gatherer).
    s.pipeline(&CHAIN.replace(r#"suffix = "!""#, "[stages.map.variants]\nloud = { suffix = \"!!!!\" }\nquiet = { suffix = \".\" }"));
    assert_eq!(s.run().with_status("ran"), ["collect", "map[loud]", "measure[loud]"]);
}

#[test]
fn dry_run_changes_nothing_on_disk() {
    let s = Scratch::new("dry");
    s.pipeline(CHAIN);
    let out = s.cli(&["run", "p.toml", "--dry-run"]);
    assert!(out.status.success());
    assert!(!s.store().exists(), "a dry run on a new pipeline creates no store");
    assert!(text(&out.stdout).contains("will run  source"), "{}", text(&out.stdout));

    s.run();
    s.pipeline(&CHAIN.replace(r#"suffix = "!""#, r#"suffix = "!!""#));
    let before = snapshot(&s.store());
    let trace_before = s.trace();
    let out = s.cli(&["run", "p.toml", "--dry-run"]);
    assert!(out.status.success());
    let stdout = text(&out.stdout);
    assert!(stdout.contains(r#"will run  map      map.suffix "!" -> "!!""#), "{stdout}");
    assert!(stdout.contains("pending   measure  input mapped (map) will be recomputed first"), "{stdout}");
    assert!(stdout.contains("cached    source"), "{stdout}");
    assert_eq!(before, snapshot(&s.store()));
    assert_eq!(trace_before, s.trace(), "a dry run runs no operator");
}

#[test]
fn status_names_an_operator_version_bump() {
    let s = Scratch::new("version");
    s.pipeline(CHAIN);
    s.run();
    let out = s.command(&["status", "p.toml"]).env("RLMFLOW_TEST_VERSION", "2").output().unwrap();
    let stdout = text(&out.stdout);
    assert!(stdout.contains("will run  source   operator version 1 -> 2"), "{stdout}");
}

#[test]
fn explain_and_show_report_preimages_and_outputs() {
    let s = Scratch::new("explain");
    s.pipeline(CHAIN);
    s.run();
    s.pipeline(&CHAIN.replace("seed = 7", "seed = 8"));
    let out = text(&s.cli(&["explain", "p.toml", "source"]).stdout);
    assert!(out.contains("seed 7 -> 8"), "{out}");
    assert!(out.contains(r#""operator": "write-text""#), "{out}");
    s.pipeline(CHAIN);
    let out = text(&s.cli(&["show", "p.toml", "source"]).stdout);
    assert!(out.contains("source: cached") && out.contains("objects/") && out.contains(r#"{"chars":5}"#), "{out}");
    let out = s.cli(&["show", "p.toml", "sorce"]);
    assert!(text(&out.stderr).contains("did you mean `source`?"), "{}", text(&out.stderr));
}

#[test]
fn only_runs_the_stage_and_what_it_needs() {
    let s = Scratch::new("only");
    s.pipeline(CHAIN);
    let events = s.run_expecting(0, &["--only", "map"]);
    assert_eq!(events.with_status("ran"), ["map", "source"]);
}

#[test]
fn a_failing_stage_skips_its_dependants_while_independent_branches_finish() {
    let s = Scratch::new("fail");
    s.pipeline(&CHAIN.replace(r#"text = "radar""#, "text = \"radar\"\nfail = true"));
    let events = s.run_expecting(1, &[]);
    assert_eq!(events.status_of("source"), "failed");
    assert_eq!(events.with_status("skipped"), ["collect", "map", "measure"]);
    assert_eq!(events.status_of("other"), "ran");
    let failed = events.of("stage_finished").into_iter().find(|e| e["status"] == "failed").unwrap();
    assert_eq!(failed["error"], "asked to fail");
    let log = fs::read_to_string(failed["log"].as_str().unwrap()).unwrap();
    assert!(log.contains("error: asked to fail"), "{log}");

    // A panic is caught the same way; the store stays valid and the fix reruns only what failed.
    s.pipeline(&CHAIN.replace(r#"text = "radar""#, "text = \"radar\"\npanic = true"));
    let events = s.run_expecting(1, &[]);
    let failed = events.of("stage_finished").into_iter().find(|e| e["status"] == "failed").unwrap();
    assert!(failed["error"].as_str().unwrap().contains("panicked: asked to panic"));
    s.pipeline(CHAIN);
    let events = s.run();
    assert_eq!(events.with_status("ran"), ["collect", "map", "measure", "source"]);
    assert_eq!(events.with_status("reused"), ["other"]);
}

#[test]
fn independent_stages_share_the_thread_budget() {
    let s = Scratch::new("budget");
    let two_slow = "[pipeline]\nname = \"b\"\n[stages.a]\nkind = \"source\"\noperator = \"write-text\"\ntext = \"a\"\nsteps = 2\nstep_ms = 50\n\
                    [stages.b]\nkind = \"source\"\noperator = \"write-text\"\ntext = \"b\"\nsteps = 2\nstep_ms = 50\n";
    s.pipeline(two_slow);
    let order = |events: &Events| -> Vec<String> {
        events
            .0
            .iter()
            .filter_map(|e| match e["event"].as_str() {
                Some("stage_started") => Some("start".to_owned()),
                Some("stage_finished") => Some("finish".to_owned()),
                _ => None,
            })
            .collect()
    };
    let threads = |events: &Events| -> Vec<u64> { events.of("stage_started").iter().map(|e| e["threads"].as_u64().unwrap()).collect() };
    let both = s.run_expecting(0, &["--jobs", "2"]);
    assert_eq!(order(&both), ["start", "start", "finish", "finish"]);
    assert_eq!(threads(&both), [1, 1]);

    s.pipeline(&two_slow.replace("step_ms = 50", "step_ms = 50\nthreads = 2").replace("\"a\"", "\"a2\"").replace("\"b\"", "\"b2\""));
    let serial = s.run_expecting(0, &["--jobs", "2"]);
    assert_eq!(order(&serial), ["start", "finish", "start", "finish"]);
    assert!(s.trace().iter().any(|l| l.contains("threads=2")));

    // A stage that could use two threads (`b`, last in the file) starts with the one left
    // beside a one-thread stage (its bytes do not follow its threads), as a model stage
    // (kernels pinned, its `threads` in its key) does not: it waits for both.
    let beside = format!("{two_slow}threads = 2\n").replace("\"a\"", "\"a4\"").replace("\"b\"", "\"b4\"");
    s.pipeline(&beside);
    let shared = s.run_expecting(0, &["--jobs", "2"]);
    assert_eq!(order(&shared), ["start", "start", "finish", "finish"]);
    assert_eq!(threads(&shared), [1, 1]);
    s.pipeline(&beside.replace("threads = 2", "threads = 2\nnumerics = \"portable\"").replace("a4", "a5").replace("b4", "b5"));
    let model = s.run_expecting(0, &["--jobs", "2"]);
    assert_eq!(order(&model), ["start", "finish", "start", "finish"]);
    assert_eq!(threads(&model).iter().max(), Some(&2), "the model stage ran with its two threads");

    // Two stages that can use a GPU, in a run that names one: one GPU, one stage at a time.
    s.pipeline(&two_slow.replace("step_ms = 50", "step_ms = 50\ngpu = true").replace("\"a\"", "\"a3\"").replace("\"b\"", "\"b3\""));
    let gpu = s.run_expecting(0, &["--jobs", "2", "--device", "cuda"]);
    assert_eq!(order(&gpu), ["start", "finish", "start", "finish"]);
}

/// With one thread, of two ready stages the one a longer chain waits on starts first, though
/// plan order (`alone`, `head`, `tail`) puts the other first; among equals, plan order.
#[test]
fn the_stage_a_longer_chain_waits_on_starts_first() {
    let s = Scratch::new("critical-first");
    s.pipeline(
        "[pipeline]\nname = \"c\"\n[stages.alone]\nkind = \"source\"\noperator = \"write-text\"\ntext = \"independent\"\n\
         [stages.head]\nkind = \"source\"\noperator = \"write-text\"\ntext = \"radar\"\n\
         [stages.tail]\nkind = \"map\"\noperator = \"shout\"\ninputs = { text = \"head\" }\nsuffix = \"!\"\n",
    );
    let planned = s.cli(&["status", "p.toml", "--json"]);
    let listed: Vec<String> = std::str::from_utf8(&planned.stdout)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["stage"].as_str().unwrap().to_owned())
        .collect();
    assert_eq!(listed, ["alone", "head", "tail"], "plan order");
    let events = s.run_expecting(0, &["--jobs", "1"]);
    let started: Vec<&str> = events.of("stage_started").iter().map(|e| e["stage"].as_str().unwrap()).collect();
    assert_eq!(started, ["head", "alone", "tail"]);
}

/// Waits until the trace has a line containing `needle`.
fn wait_for(s: &Scratch, needle: &str) {
    let t0 = Instant::now();
    while !s.trace().iter().any(|l| l.contains(needle)) {
        assert!(t0.elapsed() < Duration::from_secs(60), "never saw `{needle}` in {:?}", s.trace());
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn a_killed_run_leaves_a_valid_store_and_the_next_run_resumes_from_the_checkpoint() {
    let s = Scratch::new("kill");
    s.pipeline(&CHAIN.replace(r#"text = "radar""#, "text = \"radar\"\nsteps = 40\nstep_ms = 25"));
    let mut child = s.command(&["run", "p.toml", "--jobs", "1"]).process_group(0).stdout(std::process::Stdio::null()).spawn().unwrap();
    wait_for(&s, "step write-text source 5");
    unsafe { libc::kill(-(child.id() as i32), libc::SIGKILL) };
    child.wait().unwrap();

    let verify = s.cli(&["verify", "p.toml"]);
    assert!(verify.status.success(), "{}", text(&verify.stdout));
    let status = text(&s.cli(&["status", "p.toml"]).stdout);
    assert!(status.contains("will run  source   interrupted; resumes from its checkpoint"), "{status}");

    s.clear_trace();
    let events = s.run();
    assert_eq!(events.status_of("source"), "ran");
    let start = s.trace().into_iter().find(|l| l.starts_with("start write-text source")).unwrap();
    let from: u32 = start.split("from=").nth(1).unwrap().split(' ').next().unwrap().parse().unwrap();
    assert!(from >= 5, "resumed from step {from}: {start}");
    assert!(!s.trace().iter().any(|l| l.starts_with("step write-text source 1 ")), "step 1 ran again");
    assert_eq!(fs::read_to_string(output_dir(&s.store(), "chain", "source").join("text.txt")).unwrap(), "radar");
    let leftovers: Vec<_> = fs::read_dir(s.store().join("tmp")).unwrap().collect();
    assert!(leftovers.is_empty(), "orphaned work dirs were swept: {leftovers:?}");
    assert!(fs::read_dir(s.store().join("checkpoints")).unwrap().next().is_none(), "checkpoint removed after commit");
}

#[test]
fn two_concurrent_runs_compute_a_shared_stage_once() {
    let s = Scratch::new("concurrent");
    s.pipeline(&CHAIN.replace(r#"text = "radar""#, "text = \"radar\"\nsteps = 10\nstep_ms = 30"));
    let spawn = || s.command(&["run", "p.toml", "--json"]).stdout(std::process::Stdio::piped()).spawn().unwrap();
    let a = spawn();
    wait_for(&s, "start write-text source");
    let b = spawn();
    let (a, b) = (a.wait_with_output().unwrap(), b.wait_with_output().unwrap());
    assert!(a.status.success() && b.status.success());
    let starts = s.trace().iter().filter(|l| l.starts_with("start write-text source")).count();
    assert_eq!(starts, 1, "{:?}", s.trace());
    let b_events = Events::parse(&b.stdout);
    assert_eq!(b_events.status_of("source"), "reused");
}

#[test]
fn a_corrupted_object_is_caught_by_verify_and_never_served() {
    let s = Scratch::new("corrupt-verify");
    s.pipeline(CHAIN);
    s.run();
    let file = output_dir(&s.store(), "chain", "source").join("text.txt");
    fs::set_permissions(&file, fs::Permissions::from_mode(0o644)).unwrap();
    fs::write(&file, "rAdar").unwrap();
    let out = s.cli(&["verify", "p.toml"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(text(&out.stdout).contains("text.txt (quarantined"), "{}", text(&out.stdout));
    let events = s.run();
    assert_eq!(events.status_of("source"), "ran");
    assert_eq!(fs::read_to_string(output_dir(&s.store(), "chain", "source").join("text.txt")).unwrap(), "radar");
    assert!(s.cli(&["verify", "p.toml"]).status.success());
}

#[test]
fn a_stage_consuming_a_corrupted_input_recomputes_its_upstream_first() {
    let s = Scratch::new("corrupt-consume");
    s.pipeline(CHAIN);
    s.run();
    let file = output_dir(&s.store(), "chain", "source").join("text.txt");
    fs::set_permissions(&file, fs::Permissions::from_mode(0o644)).unwrap();
    fs::write(&file, "rAdar").unwrap();
    // map must run (new suffix) and reads the damaged source output.
    s.pipeline(&CHAIN.replace(r#"suffix = "!""#, r#"suffix = "?""#));
    let events = s.run();
    let corrupt = events.of("input_corrupt");
    assert_eq!(corrupt.len(), 1);
    assert_eq!(corrupt[0]["files"][0], "text.txt");
    assert_eq!(events.with_status("ran"), ["map", "measure", "source"]);
    let mapped = fs::read_to_string(output_dir(&s.store(), "chain", "map").join("mapped.txt")).unwrap();
    assert_eq!(mapped, "RADAR?");
}

#[test]
fn gc_sweeps_what_no_root_reaches_and_keeps_the_current_results() {
    let s = Scratch::new("gc");
    s.pipeline(CHAIN);
    s.run();
    let old_map = output_dir(&s.store(), "chain", "map");
    s.pipeline(&CHAIN.replace(r#"suffix = "!""#, r#"suffix = "!!""#));
    s.run();
    let dry = s.cli(&["gc", "p.toml", "--keep-runs", "1", "--dry-run"]);
    assert!(text(&dry.stdout).contains("would remove"), "{}", text(&dry.stdout));
    assert!(old_map.exists());
    let out = s.cli(&["gc", "p.toml", "--keep-runs", "1"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(!old_map.exists(), "the superseded map output is collected");
    assert_eq!(fs::read_dir(s.store().join("runs")).unwrap().count(), 1);
    assert_eq!(s.run().with_status("reused").len(), 5);

    // A pin keeps results that the refs no longer reach.
    assert!(s.cli(&["pin", "p.toml", "keep"]).status.success());
    s.pipeline(CHAIN);
    s.run();
    s.cli(&["gc", "p.toml", "--keep-runs", "0"]);
    s.pipeline(&CHAIN.replace(r#"suffix = "!""#, r#"suffix = "!!""#));
    assert_eq!(s.run().with_status("reused").len(), 5, "pinned results survived gc");
}

#[test]
fn operators_lists_kinds_and_defaults() {
    let s = Scratch::new("operators");
    let out = text(&s.cli(&["operators"]).stdout);
    assert!(out.contains("map (text: Text) -> Mapped"), "{out}");
    assert!(out.contains(r#"shout v1: upper-cases"#) && out.contains(r#"{"suffix":"!"}"#), "{out}");
}

#[test]
fn each_run_records_what_it_ran_and_reused_with_keys_outputs_and_times() {
    let s = Scratch::new("provenance");
    s.pipeline(CHAIN);
    let first = s.run();
    s.pipeline(&CHAIN.replace("suffix = \"!\"", "suffix = \"?\""));
    let second = s.run();
    let run = second.of("run_started")[0]["run"].as_str().unwrap().to_owned();
    let md = fs::read_to_string(s.store().join("runs").join(run).join("provenance.md")).unwrap();
    let row = |label: &str| md.lines().find(|l| l.starts_with(&format!("| {label} |"))).unwrap_or_else(|| panic!("no {label} in\n{md}")).to_owned();
    let source = first.of("stage_finished").into_iter().find(|e| e["stage"] == "source").unwrap();
    let (key, output) = (source["key"].as_str().unwrap(), source["output"].as_str().unwrap());
    let reused = row("source");
    assert!(reused.starts_with("| source | reused |") && reused.contains(key) && reused.contains(output), "{reused}");
    let map = second.of("stage_finished").into_iter().find(|e| e["stage"] == "map").unwrap();
    assert!(row("map").starts_with("| map | ran |") && row("map").contains(map["key"].as_str().unwrap()), "{md}");
    assert_eq!(md.lines().filter(|l| l.starts_with("| ") && !l.starts_with("| instance")).count(), 5, "{md}");
}
