//! The researcher's loop over runs: `rlmflow runs` lists a pipeline's runs from the store with
//! their git state, overrides and counts; `rlmflow compare` sets two runs, or the variants of
//! one, side by side with seeds pooled; `results/` links each instance to its current output
//! and keeps saying where it is after `gc`.

use std::fs;
use std::process::Command;

use serde_json::Value;

use crate::harness::{CHAIN, Scratch, text};

fn git(s: &Scratch, args: &[&str]) {
    let out = Command::new("git")
        .current_dir(&s.dir)
        .args(["-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false"])
        .args(args)
        .output()
        .expect("git is installed wherever the repository was cloned");
    assert!(out.status.success(), "git {args:?}: {}", text(&out.stderr));
}

fn stdout_of(s: &Scratch, args: &[&str]) -> String {
    let out = s.cli(args);
    assert!(out.status.success(), "{args:?}: {}", text(&out.stderr));
    text(&out.stdout)
}

/// The rows of `compare --json`'s one table, and the table.
fn compared(s: &Scratch, args: &[&str]) -> (Vec<Value>, Value) {
    let mut all = vec!["compare", "p.toml", "--json"];
    all.extend_from_slice(args);
    let table: Value = serde_json::from_str(stdout_of(s, &all).lines().next().unwrap()).unwrap();
    (table["rows"].as_array().unwrap().clone(), table)
}

fn row<'r>(rows: &'r [Value], instance: &str, name: &str) -> &'r Value {
    rows.iter().find(|r| r["instance"] == instance && r["name"] == name).unwrap_or_else(|| panic!("no row {instance} {name} in {rows:#?}"))
}

#[test]
fn runs_lists_each_run_and_compare_shows_the_setting_that_changed_and_the_metrics_it_moved() {
    let s = Scratch::new("history");
    s.pipeline(CHAIN);
    git(&s, &["init", "-q"]);
    git(&s, &["add", "p.toml"]);
    git(&s, &["commit", "-q", "-m", "first"]);
    let first = s.run().of("run_started")[0]["run"].as_str().unwrap().to_owned();
    let second = s.run_expecting(0, &["--set", "map.suffix=\"?!\""]).of("run_started")[0]["run"].as_str().unwrap().to_owned();

    // Newest first, each with its commit, overrides, counts and the headlines of what it ran.
    let listing = stdout_of(&s, &["runs", "p.toml"]);
    let (at_second, at_first) = (listing.find(&second).unwrap(), listing.find(&first).unwrap());
    assert!(at_second < at_first, "{listing}");
    let second_block = &listing[at_second..at_first];
    assert!(second_block.contains("--set map.suffix=\"?!\""), "{listing}");
    assert!(second_block.contains("3 ran, 2 reused, 0 pulled, 0 failed, 0 skipped"), "{listing}");
    assert!(second_block.contains("ran     measure  7 characters"), "{listing}");
    assert!(!second_block.contains("(dirty)") && second_block.contains("  git "), "{listing}");
    let runs: Vec<Value> = stdout_of(&s, &["runs", "p.toml", "--json"]).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(runs.len(), 2);
    assert_eq!(runs[0]["run"], second.as_str());
    assert_eq!((runs[0]["git"]["dirty"].as_bool(), runs[0]["git"]["commit"].as_str().map(str::len)), (Some(false), Some(40)));
    assert_eq!(runs[1]["outcomes"]["measure"], "ran");
    assert_eq!(runs[0]["counts"], serde_json::json!({"ran": 3, "reused": 2, "pulled": 0, "failed": 0, "skipped": 0}));
    assert_eq!(runs[0]["finished"], true);

    // Plain reruns (the keys of the run before): folded in the listing, passed over by compare.
    let reruns: Vec<String> =
        (0..2).map(|_| s.run_expecting(0, &["--set", "map.suffix=\"?!\""]).of("run_started")[0]["run"].as_str().unwrap().to_owned()).collect();
    let listing = stdout_of(&s, &["runs", "p.toml"]);
    assert!(listing.contains(&format!("2 reruns with the keys of the run before: {} back to {}", reruns[1], reruns[0])), "{listing}");
    assert!(!listing.contains(&format!("{}  ", reruns[0])) && listing.contains(&format!("{second}  ")), "{listing}");
    let every = stdout_of(&s, &["runs", "p.toml", "--all"]);
    assert!(reruns.iter().all(|r| every.contains(&format!("{r}  "))), "{every}");
    let runs: Vec<Value> = stdout_of(&s, &["runs", "p.toml", "--json"]).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(runs.iter().map(|r| r["repeats"].as_bool().unwrap()).collect::<Vec<_>>(), [true, true, false, false]);

    // The last two by default (plain reruns passed over): the setting, the inputs it changed, the metric it moved (with its
    // sign); what kept its key is named, not shown.
    let (rows, table) = compared(&s, &[]);
    assert_eq!(table["columns"], serde_json::json!([first, second]));
    assert_eq!(row(&rows, "map", "suffix")["values"], serde_json::json!(["!", "?!"]));
    let chars = row(&rows, "measure", "chars");
    assert_eq!((chars["values"][0]["mean"].as_f64(), chars["values"][1]["mean"].as_f64()), (Some(6.0), Some(7.0)));
    assert_eq!(chars["change"]["mean"].as_f64(), Some(1.0));
    assert_eq!(row(&rows, "measure", "mapped")["kind"], "input");
    assert!(rows.iter().all(|r| r["instance"] != "source" && r["instance"] != "other"), "{rows:#?}");
    let mut same: Vec<&str> = table["identical"].as_array().unwrap().iter().map(|v| v.as_str().unwrap()).collect();
    same.sort();
    assert_eq!(same, ["other", "source"]);
    let terminal = stdout_of(&s, &["compare", "p.toml"]);
    assert!(terminal.lines().any(|l| l.split_whitespace().collect::<Vec<_>>() == ["measure", "metric", "chars", "6", "7", "+1"]), "{terminal}");
    let markdown = stdout_of(&s, &["compare", "p.toml", &first[..17], &second, "--markdown"]);
    assert!(markdown.contains("| map | suffix | ! | ?! |"), "{markdown}");
    // Everything with --all, including what did not change.
    let (all, _) = compared(&s, &["--all"]);
    assert_eq!(row(&all, "source", "text")["values"], serde_json::json!(["radar", "radar"]));

    // An edited tracked file marks the next run dirty; an unknown run is named with the known.
    fs::write(s.dir.join("p.toml"), CHAIN.replace("seed = 7", "seed = 8")).unwrap();
    s.run();
    let runs: Vec<Value> = stdout_of(&s, &["runs", "p.toml", "--json", "--last", "1"]).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!((runs.len(), runs[0]["git"]["dirty"].as_bool()), (1, Some(true)));
    let out = s.cli(&["compare", "p.toml", "20990101"]);
    assert!(!out.status.success() && text(&out.stderr).contains("no run `20990101` of pipeline `chain`; its newest: "), "{}", text(&out.stderr));
    assert!(text(&out.stderr).contains(&second), "{}", text(&out.stderr));
}

#[test]
fn compare_pools_seeds_into_mean_and_sd_and_sets_variants_side_by_side() {
    let s = Scratch::new("history-seeds");
    let seeded = CHAIN.replace("seed = 7", "seed = 7\nseeds = [5, 6, 7]").replace(r#"operator = "count""#, r#"operator = "sample""#);
    s.pipeline(&seeded);
    s.run();
    s.pipeline(&seeded.replace(r#"suffix = "!""#, r#"suffix = "!?""#));
    s.run();
    // 6 characters then 7: seeds 5, 6, 7 pick indices 5, 0, 1 then 5, 6, 0.
    let (rows, _) = compared(&s, &[]);
    let index = row(&rows, "measure", "index");
    assert_eq!(index["values"][0]["n"], 3);
    assert!((index["values"][0]["mean"].as_f64().unwrap() - 2.0).abs() < 1e-12);
    assert!((index["values"][1]["mean"].as_f64().unwrap() - 11.0 / 3.0).abs() < 1e-12);
    // The change of paired seeds: differences 0, 6, -1.
    let change = &index["change"];
    assert!((change["mean"].as_f64().unwrap() - 5.0 / 3.0).abs() < 1e-12, "{change}");
    let sd = ((0.0f64 - 5.0 / 3.0).powi(2) + (6.0f64 - 5.0 / 3.0).powi(2) + (-1.0f64 - 5.0 / 3.0).powi(2)) / 2.0;
    assert!((change["sd"].as_f64().unwrap() - sd.sqrt()).abs() < 1e-12, "{change}");
    let terminal = stdout_of(&s, &["compare", "p.toml"]);
    assert!(terminal.contains("+1.667 ± 3.786 (n=3)"), "{terminal}");

    // Variants of one run: one table per stage, a column per variant.
    s.pipeline(&CHAIN.replace(r#"suffix = "!""#, "[stages.map.variants]\nloud = { suffix = \"!!!\" }\nquiet = { suffix = \".\" }"));
    s.run();
    let tables: Vec<Value> =
        stdout_of(&s, &["compare", "p.toml", "--variants", "--json"]).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let table = |stage: &str| tables.iter().find(|t| t["title"].as_str().unwrap().starts_with(&format!("{stage} in run "))).unwrap();
    assert_eq!(table("map")["columns"], serde_json::json!(["map[loud]", "map[quiet]"]));
    assert_eq!(row(table("map")["rows"].as_array().unwrap(), "map", "suffix")["values"], serde_json::json!(["!!!", "."]));
    let chars = row(table("measure")["rows"].as_array().unwrap(), "measure", "chars");
    assert_eq!((chars["values"][0]["mean"].as_f64(), chars["values"][1]["mean"].as_f64()), (Some(8.0), Some(6.0)));
    assert!(tables.iter().all(|t| !t["title"].as_str().unwrap().starts_with("source ")), "a stage without variants shows only with --all");
    let terminal = stdout_of(&s, &["compare", "p.toml", "--variants"]);
    assert!(!terminal.contains("nothing differs"), "a table with nothing to show is left out: {terminal}");
    let out = s.cli(&["compare", "p.toml", "--variants", "a", "b"]);
    assert_eq!(out.status.code(), Some(2), "{}", text(&out.stderr));
}

#[test]
fn results_link_each_instance_to_its_current_output_and_say_so_when_gc_collected_it() {
    let s = Scratch::new("results");
    s.pipeline(CHAIN);
    s.run();
    let mapped = s.dir.join("results/map/mapped.txt");
    assert_eq!(fs::read_to_string(&mapped).unwrap(), "RADAR!");
    assert!(fs::symlink_metadata(s.dir.join("results/map")).unwrap().file_type().is_symlink());
    s.run_expecting(0, &["--set", "map.suffix=\"?\""]);
    assert_eq!(fs::read_to_string(&mapped).unwrap(), "RADAR?", "the link follows the latest output");
    let out = s.cli(&["gc", "p.toml", "--keep-runs", "0"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert_eq!(fs::read_to_string(&mapped).unwrap(), "RADAR?", "gc keeps the current outputs, so the links still resolve");

    // Variants: a directory of links per stage; a link is a plain relative link into the store.
    s.pipeline(&CHAIN.replace(r#"suffix = "!""#, "[stages.map.variants]\nloud = { suffix = \"!!!\" }\nquiet = { suffix = \".\" }"));
    s.run();
    assert_eq!(fs::read_to_string(s.dir.join("results/map/loud/mapped.txt")).unwrap(), "RADAR!!!");
    assert_eq!(fs::read_to_string(s.dir.join("results/measure/quiet/count.txt")).unwrap(), "6");
    let link = fs::read_link(s.dir.join("results/map/loud")).unwrap();
    assert!(link.starts_with("../../.rlmflow/objects"), "{}", link.display());

    // Without the refs that keep them, gc collects the outputs; each link then says so.
    fs::remove_dir_all(s.store().join("refs/pipelines")).unwrap();
    let out = s.cli(&["gc", "p.toml", "--keep-runs", "0"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let note = fs::read_to_string(s.dir.join("results/map/loud/COLLECTED.txt")).unwrap();
    assert!(note.contains("was removed by `rlmflow gc`") && note.contains("Run the pipeline again"), "{note}");
    s.run();
    assert_eq!(fs::read_to_string(s.dir.join("results/map/loud/mapped.txt")).unwrap(), "RADAR!!!");

    // A results directory that is someone else's is never written into; "" turns results off.
    fs::create_dir_all(s.dir.join("mine")).unwrap();
    fs::write(s.dir.join("mine/notes.txt"), "keep").unwrap();
    s.pipeline(&CHAIN.replace("seed = 7", "seed = 7\nresults = \"mine\""));
    let out = s.cli(&["run", "p.toml"]);
    assert!(!out.status.success() && text(&out.stderr).contains("holds files rlmflow did not put there"), "{}", text(&out.stderr));
    assert_eq!(fs::read_dir(s.dir.join("mine")).unwrap().count(), 1);
    fs::remove_dir_all(s.dir.join("results")).unwrap();
    s.pipeline(&CHAIN.replace("seed = 7", "seed = 7\nresults = \"\""));
    s.run();
    assert!(!s.dir.join("results").exists());
    // The store is no place for them.
    s.pipeline(&CHAIN.replace("seed = 7", "seed = 7\nresults = \".rlmflow/results\""));
    let out = s.cli(&["status", "p.toml"]);
    assert_eq!(out.status.code(), Some(2), "{}", text(&out.stderr));
    assert!(text(&out.stderr).contains("pipeline.results"), "{}", text(&out.stderr));
}

/// A label as the run prints it (`map[loud]`, or its long form `map[map=loud]`) is taken
/// wherever a stage is: `run --only`, `status --only`, `show`, `explain`, `pin --only`,
/// `--check-determinism`, `verify --recompute --only`; a typo is answered with the nearest label.
#[test]
fn every_command_that_takes_a_stage_takes_the_label_a_run_prints() {
    let s = Scratch::new("labels");
    s.pipeline(&CHAIN.replace(r#"suffix = "!""#, "[stages.map.variants]\nloud = { suffix = \"!!!\" }\nquiet = { suffix = \".\" }"));
    let events = s.run_expecting(0, &["--only", "map[loud]"]);
    let mut ran: Vec<String> = events.finished().into_iter().map(|(stage, _)| stage).collect();
    ran.sort();
    assert_eq!(ran, ["map[loud]", "source"], "the instance and what it needs, nothing else");

    let status: Vec<Value> =
        stdout_of(&s, &["status", "p.toml", "--json", "--only", "map[map=loud]"]).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let shown: Vec<(&str, &str)> = status.iter().map(|l| (l["stage"].as_str().unwrap(), l["state"].as_str().unwrap())).collect();
    assert_eq!(shown, [("source", "cached"), ("map[loud]", "cached")], "{status:#?}");
    let whole = stdout_of(&s, &["status", "p.toml"]);
    assert!(whole.contains("map[quiet]") && whole.contains("measure[loud]"), "{whole}");

    for command in ["show", "explain"] {
        let out = stdout_of(&s, &[command, "p.toml", "map[loud]"]);
        assert!(out.contains("map[loud]") && !out.contains("map[quiet]"), "{command}: {out}");
        let both = stdout_of(&s, &[command, "p.toml", "map"]);
        assert!(both.contains("map[loud]") && both.contains("map[quiet]"), "{command}: {both}");
    }
    assert!(stdout_of(&s, &["pin", "p.toml", "loud", "--only", "map[loud]"]).starts_with("pinned 2 cached stage instances"));
    let checked = stdout_of(&s, &["run", "p.toml", "--check-determinism", "map[loud]"]);
    assert!(checked.contains("check-determinism map[loud] (key ") && !checked.contains("check-determinism map[quiet]"), "{checked}");
    let recomputed = stdout_of(&s, &["verify", "p.toml", "--recompute", "--only", "map[loud]"]);
    let agrees: Vec<&str> = recomputed.lines().filter(|l| l.trim_start().starts_with("agrees")).collect();
    assert!(agrees.len() == 1 && agrees[0].contains("map[loud]"), "{recomputed}");

    for (args, nearest) in [
        (vec!["show", "p.toml", "map[lod]"], "did you mean `map[loud]`?"),
        (vec!["explain", "p.toml", "mpa[loud]"], "did you mean `map[loud]`?"),
        (vec!["status", "p.toml", "--only", "map[qiet]"], "did you mean `map[quiet]`?"),
        (vec!["run", "p.toml", "--only", "maploud"], "did you mean `map[loud]`?"),
    ] {
        let out = s.cli(&args);
        assert!(!out.status.success() && text(&out.stderr).contains(nearest), "{args:?}: {}", text(&out.stderr));
    }
}
