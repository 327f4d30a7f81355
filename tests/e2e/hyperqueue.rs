//! `executor = "hyperqueue"`: a real HyperQueue server and workers (a local cluster on loopback,
//! from the `hyperqueue` package in the managed Python environment).

use std::fs;
use std::time::{Duration, Instant};

use crate::harness::{CHAIN, Events, Scratch, output_dir, text};

fn hyperqueue(pipeline: &str, table: &str) -> String {
    pipeline.replacen("seed = 7\n", &format!("seed = 7\nexecutor = \"hyperqueue\"\n\n[pipeline.hyperqueue]\n{table}\n"), 1)
}

/// Every instance's key and output digest, from the store's last run.
fn keys_and_outputs(s: &Scratch) -> Vec<(String, String, String)> {
    let store = rlmflow_cache::Store::open_existing(&s.store()).unwrap().unwrap();
    rlmflow_test_support::cli::last_keys(&store, "chain")
        .into_iter()
        .map(|(label, key)| (label, key.to_string(), store.record(&key).unwrap().unwrap().output.to_string()))
        .collect()
}

fn wait_for(s: &Scratch, needle: &str) -> String {
    let t0 = Instant::now();
    loop {
        if let Some(line) = s.trace().into_iter().find(|l| l.contains(needle)) {
            return line;
        }
        assert!(t0.elapsed() < Duration::from_secs(120), "never saw `{needle}` in {:?}", s.trace());
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn a_local_cluster_gives_the_keys_and_bytes_of_the_local_executor_and_reuses_everything_next() {
    let local = Scratch::new("hq-same-local");
    local.pipeline(CHAIN).run();
    let hq = Scratch::new("hq-same");
    hq.pipeline(&hyperqueue(CHAIN, "workers = 1\ncores = 2"));
    let first = hq.run();
    assert_eq!(first.with_status("ran").len(), 5, "{:?}", first.finished());
    assert!(first.of("run_started")[0]["executor"].as_str().unwrap().starts_with("hyperqueue (local cluster"));
    assert_eq!(keys_and_outputs(&hq), keys_and_outputs(&local));
    // Progress and operator events come back from the task's output as from a child.
    assert!(first.of("operator_event").iter().any(|e| e["stage"] == "source" && e["name"] == "wrote"), "{:?}", first.0);

    let again = hq.run();
    assert_eq!(again.with_status("reused").len(), 5);
    let run = again.of("run_started")[0]["run"].as_str().unwrap().to_owned();
    // The helper makes that directory when it loads: a warm run starts neither a cluster nor Python.
    assert!(!hq.store().join("runs").join(&run).join("hyperqueue").exists(), "a warm run starts no cluster and no interpreter");
}

#[test]
fn two_workers_run_independent_stages_at_the_same_time() {
    let s = Scratch::new("hq-parallel");
    let slow = CHAIN
        .replace(r#"text = "radar""#, "text = \"radar\"\nsteps = 8\nstep_ms = 150")
        .replace(r#"text = "independent""#, "text = \"independent\"\nsteps = 8\nstep_ms = 150");
    s.pipeline(&hyperqueue(&slow, "workers = 2\ncores = 1"));
    let events = s.run();
    let at = |event: &str, stage: &str| -> f64 {
        events.of(event).iter().find(|e| e["stage"] == stage).unwrap_or_else(|| panic!("no {event} for {stage}"))["t"].as_f64().unwrap()
    };
    let (a0, a1, b0, b1) =
        (at("stage_started", "source"), at("stage_finished", "source"), at("stage_started", "other"), at("stage_finished", "other"));
    assert!(a0 < b1 && b0 < a1, "source {a0}..{a1} and other {b0}..{b1} did not overlap");
}

#[test]
fn shards_spread_over_workers_and_give_the_bytes_of_a_local_run() {
    let slow = CHAIN.replace(r#"text = "radar""#, "text = \"radar\"\nsteps = 6\nstep_ms = 100\nshards = 2");
    let local = Scratch::new("hq-shards-local");
    local.pipeline(&slow).run();
    let hq = Scratch::new("hq-shards");
    hq.pipeline(&hyperqueue(&slow, "workers = 2\ncores = 1"));
    let events = hq.run();
    assert_eq!(keys_and_outputs(&hq), keys_and_outputs(&local));
    let at = |event: &str, stage: &str| events.of(event).iter().find(|e| e["stage"] == stage).unwrap()["t"].as_f64().unwrap();
    let (a0, a1, b0, b1) =
        (at("stage_started", "source#0"), at("stage_finished", "source#0"), at("stage_started", "source#1"), at("stage_finished", "source#1"));
    assert!(a0 < b1 && b0 < a1, "the parts ran on both workers at once: {a0}..{a1} and {b0}..{b1}");
}

#[test]
fn a_killed_task_is_submitted_again_and_resumes_from_its_checkpoint() {
    let (s, code, events) = run_killing_the_source_task("hq-kill-retry", 1);
    assert_eq!(code, Some(0), "{:?}", events.0);
    let retry = events.of("operator_event").into_iter().find(|e| e["name"] == "hyperqueue_retry").expect("a retry event");
    assert!(retry["data"]["reason"].as_str().unwrap().contains("signal 9"), "{retry}");
    let starts: Vec<String> = s.trace().into_iter().filter(|l| l.starts_with("start write-text source")).collect();
    assert_eq!(starts.len(), 2, "{starts:?}");
    assert!(!starts[1].contains("from=0"), "the second attempt resumed: {starts:?}");
    assert_eq!(fs::read_to_string(output_dir(&s.store(), "chain", "source").join("text.txt")).unwrap(), "radar");
}

#[test]
fn without_retries_a_killed_task_fails_its_stage_clearly_and_the_next_run_resumes() {
    let (s, code, events) = run_killing_the_source_task("hq-kill-fail", 0);
    assert_eq!(code, Some(1));
    let failed = events.of("stage_finished").into_iter().find(|e| e["stage"] == "source").unwrap().clone();
    assert_eq!(failed["error"], "the stage process was killed by signal 9", "{failed}");
    assert_eq!(events.status_of("other"), "ran", "an independent branch finishes");
    assert_eq!(events.status_of("map"), "skipped");

    let verify = s.cli(&["verify", "p.toml"]);
    assert!(verify.status.success(), "{}", text(&verify.stdout));
    s.clear_trace();
    let next = s.run();
    assert_eq!(next.status_of("source"), "ran");
    let start = wait_for(&s, "start write-text source");
    assert!(!start.contains("from=0"), "resumed from the checkpoint: {start}");
}

/// Runs a slow chain through a local cluster with `retries`, killing the source stage's task
/// process (the trace names its pid) with SIGKILL at step 5; returns the exit code and events.
fn run_killing_the_source_task(name: &str, retries: u32) -> (Scratch, Option<i32>, Events) {
    let s = Scratch::new(name);
    let slow = CHAIN.replace(r#"text = "radar""#, "text = \"radar\"\nsteps = 30\nstep_ms = 50");
    s.pipeline(&hyperqueue(&slow, &format!("workers = 1\ncores = 2\nretries = {retries}")));
    let child = s.command(&["run", "p.toml", "--json"]).stdout(std::process::Stdio::piped()).spawn().unwrap();
    let line = wait_for(&s, "step write-text source 5 ");
    let pid: i32 = line.rsplit("pid=").next().unwrap().trim().parse().unwrap();
    unsafe { libc::kill(pid, libc::SIGKILL) };
    let out = child.wait_with_output().unwrap();
    let events = Events::parse(&out.stdout);
    (s, out.status.code(), events)
}

#[test]
fn an_unreachable_server_is_a_clear_error_before_anything_runs() {
    let s = Scratch::new("hq-unreachable");
    s.pipeline(&hyperqueue(CHAIN, "server_dir = \"no-server-here\""));
    let out = s.cli(&["run", "p.toml"]);
    assert_eq!(out.status.code(), Some(1));
    let err = text(&out.stderr);
    assert!(err.contains("cannot reach a HyperQueue server in") && err.contains("no-server-here"), "{err}");
    assert!(err.contains("server start`"), "says what to do: {err}");
    assert!(s.trace().is_empty(), "nothing ran: {:?}", s.trace());
}

#[test]
fn bad_hyperqueue_settings_name_their_key_and_line() {
    let s = Scratch::new("hq-config");
    s.pipeline(&hyperqueue(CHAIN, "workers = 2\nretry = 3"));
    let err = text(&s.cli(&["run", "p.toml", "--dry-run"]).stderr);
    assert!(err.contains("p.toml:9: pipeline.hyperqueue.retry: unknown field `retry`, expected one of"), "{err}");
    s.pipeline(&hyperqueue(CHAIN, "workers = 0"));
    let err = text(&s.cli(&["run", "p.toml", "--dry-run"]).stderr);
    assert!(err.contains("p.toml:8: pipeline.hyperqueue.workers: must be in 1..=4096, not 0"), "{err}");
    let err = text(&s.pipeline(CHAIN).cli(&["run", "p.toml", "--executor", "slurm"]).stderr);
    assert!(err.contains("unknown executor `slurm` for --executor; valid: local, hyperqueue"), "{err}");
}

/// Every object directory under a store, by digest.
fn objects(store: &std::path::Path) -> Vec<String> {
    let mut v: Vec<String> = fs::read_dir(store.join("objects")).unwrap().flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect();
    v.sort();
    v
}

#[test]
fn workers_with_stores_of_their_own_share_only_the_remote_and_give_the_bytes_of_a_local_run() {
    let local = Scratch::new("hq-own-local");
    local.pipeline(CHAIN).run();
    let s = Scratch::new("hq-own");
    let remote = s.dir.join("remote");
    let pipeline = hyperqueue(CHAIN, "workers = 2\ncores = 1\nworker_store = \"temporary\"").replacen(
        "seed = 7\n",
        &format!("seed = 7\nremote = \"file://{}\"\nremote_push = true\n", remote.display()),
        1,
    );
    s.pipeline(&pipeline);
    let events = s.run();
    assert_eq!(events.with_status("ran").len(), 5, "{:?}", events.finished());
    assert!(events.of("run_started")[0]["executor"].as_str().unwrap().contains("worker stores temporary, through file://"));
    // The results came back through the remote into this store: the keys and bytes of a local run.
    assert_eq!(keys_and_outputs(&s), keys_and_outputs(&local));
    assert_eq!(objects(&s.store()), objects(&local.store()));
    let verify = s.cli(&["verify", "p.toml"]);
    assert!(verify.status.success(), "{}", text(&verify.stdout));
    // Each task ran in a store of its own, which it removed; none used the run's store.
    let stores: Vec<String> = s.trace().into_iter().filter(|l| l.starts_with("start write-text")).collect();
    assert_eq!(stores.len(), 2, "{stores:?}");
    let run_store = format!("out={}", s.store().display());
    assert!(stores.iter().all(|l| l.contains(" out=") && !l.contains(&run_store)), "tasks ran outside the run's store: {stores:?}");
    // Events travel in the task's transcript.
    assert!(events.of("operator_event").iter().any(|e| e["stage"] == "source" && e["name"] == "wrote"), "{:?}", events.0);
    // What the workers pushed is on the remote, records with their objects.
    assert_eq!(fs::read_dir(remote.join("ac")).unwrap().count(), 5);

    // An operator's error comes back in the transcript, with the operator's words.
    let failing = pipeline.replace("text = \"independent\"", "text = \"independent, failing\"\nfail = true");
    s.pipeline(&failing);
    let failed = s.run_expecting(1, &[]);
    let other = failed.of("stage_finished").into_iter().find(|e| e["stage"] == "other").unwrap().clone();
    assert_eq!(other["status"], "failed");
    assert_eq!(other["error"], "asked to fail", "{other}");
    // The failed task's output stays on its worker (here, this machine's temporary directory).
    let run = failed.of("run_started")[0]["run"].as_str().unwrap().to_owned();
    let kept: Vec<_> = fs::read_dir(std::env::temp_dir())
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.to_string_lossy().contains(&format!("rlmflow-{run}-other.")))
        .collect();
    assert_eq!(kept.len(), 2, "its stdout and stderr: {kept:?}");
    kept.iter().for_each(|p| fs::remove_file(p).unwrap());
}

#[test]
fn workers_with_stores_of_their_own_need_a_remote_this_run_pushes_to() {
    let s = Scratch::new("hq-own-no-remote");
    s.pipeline(&hyperqueue(CHAIN, "worker_store = \"temporary\""));
    let out = s.cli(&["run", "p.toml"]);
    assert_eq!(out.status.code(), Some(1));
    let err = text(&out.stderr);
    assert!(err.contains("worker_store = \"temporary\" hands inputs and results") && err.contains("remote_push = true"), "{err}");
    assert!(s.trace().is_empty(), "nothing ran");
    s.pipeline(&hyperqueue(CHAIN, "worker_store = \"scratch\""));
    let err = text(&s.cli(&["run", "p.toml", "--dry-run"]).stderr);
    assert!(err.contains("pipeline.hyperqueue.worker_store: `scratch` is not valid; valid: \"shared\""), "{err}");
}

#[test]
fn a_worker_store_on_a_path_keeps_what_its_tasks_fetched_and_computed() {
    let s = Scratch::new("hq-own-path");
    let (remote, worker) = (s.dir.join("remote"), s.dir.join("worker-store"));
    let table = format!("workers = 1\ncores = 1\nworker_store = \"{}\"", worker.display());
    s.pipeline(&hyperqueue(CHAIN, &table).replacen(
        "seed = 7\n",
        &format!("seed = 7\nremote = \"file://{}\"\nremote_push = true\n", remote.display()),
        1,
    ));
    let events = s.run();
    assert_eq!(events.with_status("ran").len(), 5, "{:?}", events.finished());
    // The worker's store holds every result its tasks computed (the inputs among them), and the
    // run's store the same objects, pulled back.
    assert_eq!(objects(&worker), objects(&s.store()));
    assert!(
        s.trace().iter().filter(|l| l.starts_with("start write-text")).all(|l| l.contains(&format!("out={}", worker.display()))),
        "{:?}",
        s.trace()
    );
}
