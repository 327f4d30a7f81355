//! Sharded stages (`shards = N`, `shard_size = K`): parts are actions of their own, merged into
//! the artifact consumers read, with the bytes of the unsharded stage.

use std::fs;
use std::os::unix::process::CommandExt;
use std::time::{Duration, Instant};

use crate::harness::{CHAIN, Scratch, output_dir, text};

fn sharded(pipeline: &str, key: &str) -> String {
    pipeline.replacen("text = \"radar\"\n", &format!("text = \"radar\"\n{key}\n"), 1)
}

fn source_text(s: &Scratch) -> String {
    fs::read_to_string(output_dir(&s.store(), "chain", "source").join("text.txt")).unwrap()
}

#[test]
fn sharding_a_stage_changes_no_byte_so_its_consumers_are_reused() {
    let s = Scratch::new("shards-same");
    s.pipeline(CHAIN);
    s.run();
    let whole = output_dir(&s.store(), "chain", "source");

    s.pipeline(&sharded(CHAIN, "shards = 3"));
    let events = s.run();
    assert_eq!(events.with_status("ran"), ["source", "source#0", "source#1", "source#2"], "{:?}", events.finished());
    assert_eq!(events.status_of("map"), "reused", "the merged text has the unsharded bytes");
    assert_eq!(output_dir(&s.store(), "chain", "source"), whole);
    let parts: Vec<String> =
        (0..3).map(|j| fs::read_to_string(output_dir(&s.store(), "chain", &format!("source#{j}")).join("text.txt")).unwrap()).collect();
    assert_eq!(parts, ["r", "ad", "ar"], "part j holds items j*5/3 up to (j+1)*5/3");

    // Another split runs its new parts and a new merge, and still reuses everything downstream.
    // Its last part, "r", has the key of the first part of the three-way split.
    s.pipeline(&sharded(CHAIN, "shard_size = 2"));
    let events = s.run();
    assert_eq!(events.with_status("ran"), ["source", "source#0", "source#1"]);
    assert_eq!(events.status_of("source#2"), "reused");
    assert_eq!(events.status_of("map"), "reused");
    assert_eq!(source_text(&s), "radar");
}

#[test]
fn growing_a_stage_with_a_shard_size_runs_only_the_parts_it_touches() {
    let s = Scratch::new("shards-grow");
    s.pipeline(&sharded(CHAIN, "shard_size = 2"));
    s.run();
    s.pipeline(&sharded(CHAIN, "shard_size = 2").replace("text = \"radar\"", "text = \"radar!!\""));
    let status = text(&s.cli(&["status", "p.toml"]).stdout);
    assert!(status.contains("will run  source#2  source.text"), "{status}");
    assert!(status.contains("will run  source#3  never run"), "{status}");
    let events = s.run();
    assert_eq!(events.status_of("source#0"), "reused");
    assert_eq!(events.status_of("source#1"), "reused");
    assert_eq!(events.with_status("ran"), ["collect", "map", "measure", "source", "source#2", "source#3"]);
    assert_eq!(source_text(&s), "radar!!");
}

#[test]
fn a_killed_run_resumes_the_killed_shard_and_redoes_no_finished_one() {
    let s = Scratch::new("shards-kill");
    let slow = CHAIN.replace("text = \"radar\"", "text = \"radar\"\nsteps = 20\nstep_ms = 25\nshards = 3");
    s.pipeline(&slow);
    let mut child = s.command(&["run", "p.toml", "--jobs", "1"]).process_group(0).stdout(std::process::Stdio::null()).spawn().unwrap();
    let t0 = Instant::now();
    while !s.trace().iter().any(|l| l.starts_with("step write-text source#1 5 ")) {
        assert!(t0.elapsed() < Duration::from_secs(60), "{:?}", s.trace());
        std::thread::sleep(Duration::from_millis(10));
    }
    unsafe { libc::kill(-(child.id() as i32), libc::SIGKILL) };
    child.wait().unwrap();

    s.clear_trace();
    let events = s.run();
    assert_eq!(events.status_of("source#0"), "reused", "{:?}", events.finished());
    // The two parts run side by side, so they may start in either order.
    let mut starts: Vec<String> = s.trace().into_iter().filter(|l| l.starts_with("start write-text source")).collect();
    starts.sort();
    assert_eq!(starts.len(), 2, "only the killed and the unstarted part run: {starts:?}");
    assert!(starts[0].starts_with("start write-text source#1 from=") && !starts[0].contains("from=0 "), "resumed: {starts:?}");
    assert!(starts[1].starts_with("start write-text source#2 from=0 "), "{starts:?}");
    assert_eq!(source_text(&s), "radar");
}

#[test]
fn shards_of_a_stage_whose_operator_cannot_split_are_a_config_error() {
    let s = Scratch::new("shards-config");
    s.pipeline(&CHAIN.replace("suffix = \"!\"", "suffix = \"!\"\nshards = 2"));
    let err = text(&s.cli(&["run", "p.toml", "--dry-run"]).stderr);
    assert!(
        err.contains("p.toml:14: stages.map.shards: operator `shout` cannot run as shards") && err.contains("operators that can: write-text"),
        "{err}"
    );
    s.pipeline(&sharded(CHAIN, "shards = 9"));
    let err = text(&s.cli(&["run", "p.toml", "--dry-run"]).stderr);
    assert!(err.contains("stages.source.shards: 9 shards, but `write-text` makes only 5 characters"), "{err}");
}
