//! highway-env scenes: the same bytes in fresh processes and after a kill.

use super::*;

const SCENARIOS: [&str; 6] = ["highway", "merge", "roundabout", "intersection", "two-way", "divided"];

/// A pipeline with one highway-env scenes stage per scenario, named after it.
fn highway_stages(name: &str, scenarios: &[&str], settings: &str) -> String {
    let mut text = format!("[pipeline]\nname = \"{name}\"\nseed = 5\n");
    for s in scenarios {
        text += &format!(
            "\n[stages.{s}]\nkind = \"scenes\"\noperator = \"highway-env\"\nradar = {{ image = 32 }}\nscenarios = {{ {s} = {{}} }}\n{settings}\n"
        );
    }
    text
}

/// Every scenario, each attempt a fresh process (fresh hash seeds, allocator addresses and
/// Python interpreter) with a different thread count, the second asking numpy for every loop it
/// has (AVX-512 where the machine has it; the embedded interpreter keeps them off): the same
/// bytes.
#[test]
fn highway_env_scenes_are_the_same_bytes_in_fresh_processes_for_every_scenario() {
    if !std::arch::is_x86_feature_detected!("avx512f") {
        println!(
            "this machine has no AVX-512: numpy's AVX-512 loops cannot run here, only its AVX2 ones (rlmflow-python's unit test checks both are off)"
        );
    }
    let dir = scratch("highway-determinism", &highway_stages("determinism", &SCENARIOS, "frames = 12\nepisode_frames = 4"));
    let mut args = vec!["run", "p.toml", "--jobs", "2"];
    for s in SCENARIOS {
        args.extend(["--check-determinism", s]);
    }
    let (ok, out) = rlmflow(&dir, &args);
    assert!(ok, "{out}");
    assert_eq!(out.matches("same bytes").count(), SCENARIOS.len(), "{out}");
}

/// Killed with SIGKILL right after an episode was checkpointed, and again in the middle of an
/// episode, a highway-env stage resumes to the bytes of an uninterrupted run.
#[test]
fn highway_env_scenes_resume_after_sigkill_to_the_same_bytes() {
    use std::os::unix::process::CommandExt;
    let pipeline = highway_stages("resume", &["intersection"], "frames = 16\nepisode_frames = 4\nwarmup_steps = 60");
    let reference = scratch("highway-reference", &pipeline);
    let (ok, out) = rlmflow(&reference, &["run", "p.toml"]);
    assert!(ok, "{out}");
    let expected = output_digest(&reference, "resume", "intersection");

    // Frames checkpointed so far by the one running action.
    let checkpointed = |dir: &Path| -> Option<u64> {
        let checkpoints = std::fs::read_dir(dir.join(".rlmflow/checkpoints")).ok()?;
        let progress = checkpoints.flatten().map(|c| c.path().join("progress.json")).find(|p| p.exists())?;
        let value: serde_json::Value = serde_json::from_slice(&std::fs::read(progress).ok()?).ok()?;
        value["frames"].as_u64()
    };
    for (name, after_boundary) in [("boundary", Duration::ZERO), ("mid-episode", Duration::from_millis(150))] {
        let dir = scratch(&format!("highway-kill-{name}"), &pipeline);
        let mut run = Command::new(env!("CARGO_BIN_EXE_rlmflow"))
            .current_dir(&dir)
            .args(["run", "p.toml"])
            .stdout(std::process::Stdio::null())
            .process_group(0)
            .spawn()
            .unwrap();
        let t0 = Instant::now();
        while checkpointed(&dir).unwrap_or(0) == 0 {
            assert!(t0.elapsed() < Duration::from_secs(120), "{name}: no episode was checkpointed");
            std::thread::sleep(Duration::from_millis(5));
        }
        std::thread::sleep(after_boundary);
        // The whole group: the engine and its `rlmflow exec` child.
        unsafe { libc::kill(-(run.id() as i32), libc::SIGKILL) };
        run.wait().unwrap();
        let done = checkpointed(&dir).unwrap();
        assert!((4..16).contains(&done), "{name}: killed with {done} of 16 frames checkpointed");
        let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
        assert!(ok, "{name}: {out}");
        assert_eq!(output_digest(&dir, "resume", "intersection"), expected, "{name}: resumed from {done} frames");
    }
}
