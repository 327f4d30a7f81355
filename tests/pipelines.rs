//! The shipped pipelines through the real `rlmflow` binary: every one validates, and the CI
//! pipeline runs twice with the second run reusing every stage.

use std::path::{Path, PathBuf};
use std::process::Command;

fn rlmflow(dir: &Path, args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_rlmflow")).current_dir(dir).args(args).output().unwrap();
    (out.status.success(), format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn every_shipped_pipeline_validates() {
    let mut files = vec![root().join("pipeline.toml")];
    files.extend(
        std::fs::read_dir(root().join("examples")).unwrap().map(|e| e.unwrap().path()).filter(|p| p.extension().is_some_and(|e| e == "toml")),
    );
    for file in files {
        // --dry-run validates everything and writes nothing.
        let (ok, out) = rlmflow(&root(), &["run", file.to_str().unwrap(), "--dry-run"]);
        assert!(ok, "{}: {out}", file.display());
    }
}

#[test]
fn the_ci_pipeline_runs_and_a_second_run_reuses_every_stage() {
    let dir = std::env::temp_dir().join(format!("rlmflow-ci-pipeline-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(root().join("examples/ci.toml"), dir.join("ci.toml")).unwrap();
    let (ok, first) = rlmflow(&dir, &["run", "ci.toml", "--json"]);
    assert!(ok, "{first}");
    let finished =
        |log: &str, status: &str| log.lines().filter(|l| l.contains("\"stage_finished\"") && l.contains(&format!("\"status\":\"{status}\""))).count();
    let stages = finished(&first, "ran");
    assert!(stages >= 1, "{first}");
    let (ok, second) = rlmflow(&dir, &["run", "ci.toml", "--json"]);
    assert!(ok, "{second}");
    assert_eq!((finished(&second, "reused"), finished(&second, "ran")), (stages, 0), "{second}");
    let (ok, verify) = rlmflow(&dir, &["verify", "ci.toml"]);
    assert!(ok, "{verify}");
}
