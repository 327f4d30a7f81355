//! Bad input never hangs, escapes or misleads: tracked paths resolved against the pipeline file,
//! special files refused unopened, failures about a setting located like config errors, and a
//! failed stage told from an interrupted one.

use std::fs;
use std::time::{Duration, Instant};

use crate::harness::*;

/// Runs `args` and waits at most `limit`; a command still running then is killed and the test
/// fails, so a hang is a failure and not a stuck suite.
fn bounded(s: &Scratch, args: &[&str], limit: Duration) -> std::process::Output {
    let mut child = s.command(args).stdout(std::process::Stdio::piped()).stderr(std::process::Stdio::piped()).spawn().unwrap();
    let t0 = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if t0.elapsed() > limit {
            child.kill().unwrap();
            panic!("`rlmflow {}` still running after {limit:?}", args.join(" "));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

fn mkfifo(path: &std::path::Path) {
    let c = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0, "mkfifo {}", path.display());
}

#[test]
fn a_fifo_as_a_tracked_path_is_refused_without_opening_it() {
    let s = Scratch::new("fifo");
    mkfifo(&s.dir.join("pipe"));
    s.pipeline("[stages.source]\noperator = \"write-text\"\nfrom = \"pipe\"\n");
    for args in [&["run", "p.toml", "--dry-run"][..], &["status", "p.toml"], &["run", "p.toml"]] {
        let out = bounded(&s, args, Duration::from_secs(20));
        assert_eq!(out.status.code(), Some(2), "{args:?}: {}", text(&out.stdout));
        let err = text(&out.stderr);
        assert!(
            err.contains("p.toml:3: stages.source.from: `pipe` is a FIFO") && err.contains("a tracked path must be a regular file or a directory"),
            "{err}"
        );
    }
    // Inside a tracked directory: the walk stops at it, naming it and the setting's line.
    fs::create_dir_all(s.dir.join("recording")).unwrap();
    fs::write(s.dir.join("recording/a.txt"), "a").unwrap();
    mkfifo(&s.dir.join("recording/pipe"));
    s.pipeline("[stages.source]\noperator = \"write-text\"\nfrom = \"recording\"\n");
    let out = bounded(&s, &["run", "p.toml", "--dry-run"], Duration::from_secs(20));
    let err = text(&out.stderr);
    assert!(
        !out.status.success()
            && err.contains("p.toml:3: stages.source.from")
            && err.contains("recording/pipe: a FIFO; a tree may hold only regular files and directories"),
        "{err}"
    );
    assert!(!s.store().join("objects").exists(), "nothing ran");
}

#[test]
fn a_tracked_file_is_read_relative_to_the_pipeline_file_and_a_replaced_one_reruns_its_stage() {
    let s = Scratch::new("tracked-file");
    fs::create_dir_all(s.dir.join("sub")).unwrap();
    fs::write(s.dir.join("sub/prefix.txt"), "PRE-").unwrap();
    // A file of the same name where the run starts must not be the one read.
    fs::write(s.dir.join("prefix.txt"), "WRONG-").unwrap();
    fs::write(
        s.dir.join("sub/p.toml"),
        "[pipeline]\nname = \"t\"\n[stages.source]\noperator = \"write-text\"\ntext = \"radar\"\nfrom = \"prefix.txt\"\n",
    )
    .unwrap();
    let run = || {
        let out = s.cli(&["run", "sub/p.toml"]);
        assert!(out.status.success(), "{}", text(&out.stderr));
        text(&out.stdout)
    };
    run();
    let read = || fs::read_to_string(output_dir(&s.dir.join("sub/.rlmflow"), "t", "source").join("text.txt")).unwrap();
    assert_eq!(read(), "PRE-radar");
    assert!(run().contains("0 ran, 1 reused"));
    // Replaced (not the path: its content): the key changes and the stage reruns.
    fs::write(s.dir.join("sub/prefix.txt"), "NEW-").unwrap();
    let status = text(&s.cli(&["status", "sub/p.toml"]).stdout);
    assert!(status.contains("input from changed"), "{status}");
    assert!(run().contains("1 ran, 0 reused"));
    assert_eq!(read(), "NEW-radar");
}

#[test]
fn a_failure_about_a_setting_names_its_file_line_and_key() {
    let s = Scratch::new("located");
    s.pipeline("[stages.source]\noperator = \"write-text\"\nfail_on = \"steps\"\nvariants = { a = {}, b = { steps = 2 } }\n");
    let events = s.run_expecting(1, &[]);
    let errors: Vec<String> = events.of("stage_finished").iter().map(|e| e["error"].as_str().unwrap().to_owned()).collect();
    assert!(errors.contains(&"p.toml:1: stages.source.steps: is wrong for this data (a check only a run can make)".to_owned()), "{errors:?}");
    assert!(
        errors.contains(&"p.toml:4: stages.source.variants.b.steps: is wrong for this data (a check only a run can make)".to_owned()),
        "{errors:?}"
    );
    // Set on the command line, the key is located at the override (variant b's own line still wins for b).
    let events = s.run_expecting(1, &["--set", "source.steps=3"]);
    let errors: Vec<String> = events.of("stage_finished").iter().map(|e| e["error"].as_str().unwrap().to_owned()).collect();
    let overridden = "p.toml with --set source.steps=3: stages.source.steps: is wrong for this data (a check only a run can make)";
    assert!(errors.contains(&overridden.to_owned()), "{errors:?}");
    assert!(errors.iter().any(|e| e.starts_with("p.toml:4: stages.source.variants.b.steps")), "{errors:?}");
}

#[test]
fn status_tells_a_failed_stage_from_an_interrupted_one_and_a_failure_leaves_no_empty_checkpoint() {
    let s = Scratch::new("failed-status");
    s.pipeline("[stages.source]\noperator = \"write-text\"\nfail = true\n");
    s.run_expecting(1, &[]);
    let status = text(&s.cli(&["status", "p.toml"]).stdout);
    assert!(status.contains("source") && status.contains("failed: asked to fail"), "{status}");
    assert!(!status.contains("interrupted"), "{status}");
    let checkpoints: Vec<_> = fs::read_dir(s.store().join("checkpoints")).map(|d| d.collect()).unwrap_or_default();
    assert!(checkpoints.is_empty(), "the failed action's empty checkpoint folder is gone: {checkpoints:?}");
    // Fixed, it runs, and status has no failure to tell.
    s.pipeline("[stages.source]\noperator = \"write-text\"\n");
    s.run();
    let status = text(&s.cli(&["status", "p.toml"]).stdout);
    assert!(!status.contains("failed"), "{status}");
}
