//! A stage's `timeout` and `retries`: an attempt past its time is stopped with its checkpoint
//! kept, the next attempt resumes from it, every attempt is in the events, and the error of the
//! last names the stage, the limit and the attempts. On the local executor and on HyperQueue.

use crate::harness::{CHAIN, Scratch, text};

/// `source` writes 8 steps of 300 ms (2.4 s), keeping its progress in its checkpoint.
fn slow(bounds: &str) -> String {
    CHAIN.replace(r#"text = "radar""#, &format!("text = \"radar\"\nsteps = 8\nstep_ms = 300\n{bounds}"))
}

/// The step each attempt of `source` started from, from the trace.
fn starts(s: &Scratch) -> Vec<u32> {
    s.trace().iter().filter_map(|l| l.strip_prefix("start write-text source from=")?.split(' ').next()?.parse().ok()).collect()
}

#[test]
fn a_stage_past_its_timeout_is_stopped_and_retried_from_its_checkpoint() {
    let s = Scratch::new("timeout");
    s.pipeline(&slow("timeout = 1.0\nretries = 5"));
    let events = s.run();
    assert_eq!(events.status_of("source"), "ran");
    let retries = events.of("stage_retry");
    assert!(!retries.is_empty(), "{:?}", events.0);
    for (n, retry) in retries.iter().enumerate() {
        assert_eq!((retry["stage"].as_str(), retry["attempt"].as_u64()), (Some("source"), Some(n as u64 + 1)));
        assert_eq!(retry["error"], "stopped at its timeout of 1 s");
    }
    let started: Vec<u64> = events.of("stage_started").iter().filter(|e| e["stage"] == "source").map(|e| e["attempt"].as_u64().unwrap()).collect();
    assert_eq!(started, (1..=retries.len() as u64 + 1).collect::<Vec<_>>());
    // Each attempt went on from the steps the one before kept.
    let from = starts(&s);
    assert_eq!(from.len(), retries.len() + 1);
    assert!(from[0] == 0 && from.windows(2).all(|w| w[1] > w[0]), "{from:?}");
    assert_eq!(std::fs::read_to_string(crate::harness::output_dir(&s.store(), "chain", "source").join("text.txt")).unwrap(), "radar");
    // Its time is every attempt's, not the last one's alone.
    let finished = events.of("stage_finished").into_iter().find(|e| e["stage"] == "source").unwrap();
    assert_eq!(finished["attempts"].as_u64(), Some(retries.len() as u64 + 1));
    let earlier: f64 = retries.iter().map(|r| r["duration_s"].as_f64().unwrap()).sum();
    let (total, last) = (finished["total_s"].as_f64().unwrap(), finished["duration_s"].as_f64().unwrap());
    assert!((total - earlier - last).abs() < 1e-9 && total > last && total >= 2.0, "total {total} s, last {last} s, earlier {earlier} s");

    // Out of retries: the error names the stage, the limit and the attempts; downstream is
    // skipped, the checkpoint kept for the next run.
    let s = Scratch::new("timeout-fails");
    s.pipeline(&slow("timeout = 0.5\nretries = 1"));
    let out = s.cli(&["run", "p.toml"]);
    let stdout = text(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{stdout}");
    assert!(stdout.contains("retry    source  attempt 1 of 2 ended after"), "{stdout}");
    assert!(stdout.contains("FAILED   source") && stdout.contains("stopped at its timeout of 0.5 s, on attempt 2 of 2 (`retries = 1`)"), "{stdout}");
    assert!(stdout.contains("skipped  map"), "{stdout}");
    let status = text(&s.cli(&["status", "p.toml"]).stdout);
    assert!(status.lines().any(|l| l.contains("source") && l.contains("resumes from its checkpoint")), "{status}");
    // Each attempt kept its own log.
    let run = std::fs::read_dir(s.store().join("runs")).unwrap().next().unwrap().unwrap().path();
    assert!(run.join("logs/source.log").is_file() && run.join("logs/source.attempt-2.log").is_file());
    // And says how it ended, though the process was killed mid-step.
    for (log, attempt) in [("source.log", 1), ("source.attempt-2.log", 2)] {
        let text = std::fs::read_to_string(run.join("logs").join(log)).unwrap();
        assert!(
            text.contains(&format!("[rlmflow] attempt {attempt} ended after ")) && text.contains("stopped at its timeout of 0.5 s"),
            "{log}: {text}"
        );
    }

    // The settings are checked as any other, and stay out of the key.
    s.pipeline(&slow("timeout = -1"));
    let err = text(&s.cli(&["status", "p.toml"]).stderr);
    assert!(err.contains("stages.source.timeout: must be a number of seconds in (0, 604800], not -1"), "{err}");
    s.pipeline(&slow("retries = 1000"));
    let err = text(&s.cli(&["status", "p.toml"]).stderr);
    assert!(err.contains("stages.source.retries: must be an integer in 0..=100, not 1000"), "{err}");
    s.pipeline(&slow("timeout = 60"));
    let status = text(&s.cli(&["status", "p.toml"]).stdout);
    assert!(status.lines().any(|l| l.contains("source") && l.contains("resumes from its checkpoint")), "a bound is not a setting: {status}");
}

#[test]
fn a_hyperqueue_task_past_its_timeout_is_stopped_on_its_worker_and_retried() {
    let s = Scratch::new("timeout-hq");
    let pipeline = slow("timeout = 1.5\nretries = 4").replacen(
        "seed = 7\n",
        "seed = 7\nexecutor = \"hyperqueue\"\n\n[pipeline.hyperqueue]\nworkers = 1\ncores = 2\n",
        1,
    );
    s.pipeline(&pipeline);
    let events = s.run();
    assert_eq!(events.status_of("source"), "ran");
    let retries = events.of("stage_retry");
    assert!(!retries.is_empty() && retries.iter().all(|r| r["error"] == "stopped at its timeout of 1.5 s"), "{:?}", events.0);
    let from = starts(&s);
    assert!(from.len() == retries.len() + 1 && from.windows(2).all(|w| w[1] > w[0]), "{from:?}");
}
