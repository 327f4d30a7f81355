//! `rlmflow parse`, `rlmflow setup`, and the printing commands into a closed pipe.

use super::*;

#[test]
fn parse_reads_plain_and_json_lines_and_names_the_bad_line() {
    let dir = Scratch::new("parse");
    let captions = dir.join("captions.jsonl");
    std::fs::write(
        &captions,
        "Within zero to ten meters there is one car directly ahead of us in the same lane.\n{\"frame\": 3, \"caption\": \"Further away, two vehicles are in the left adjacent lane behind us.\"}\nnothing here\n",
    )
    .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_rlmflow")).args(["parse", captions.to_str().unwrap()]).output().unwrap();
    assert!(out.status.success());
    let lines: Vec<String> = String::from_utf8(out.stdout).unwrap().lines().map(String::from).collect();
    assert_eq!(lines.len(), 3);
    assert!(lines[0].starts_with(r#"{"0-10m":{"total_vehicles":1,"in_lane_front_side":1}"#), "{}", lines[0]);
    assert!(lines[1].contains(r#""30-40m":{"total_vehicles":2,"left_lane_back_side":2}"#), "{}", lines[1]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("captions.jsonl:3: warning: no distance bin recognised"));
    std::fs::write(&captions, "{\"text\": \"no caption field\"}\n").unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_rlmflow")).args(["parse", captions.to_str().unwrap()]).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("captions.jsonl:1: a JSON line needs a string field `caption`"));
}

#[test]
fn parse_into_a_reader_that_stops_early_is_not_an_error() {
    use std::io::Write;
    let mut child = Command::new(env!("CARGO_BIN_EXE_rlmflow"))
        .arg("parse")
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // `| head -0`: the reader is gone before anything is written, and the output (about 4 MB)
    // is far more than a pipe holds.
    drop(child.stdout.take());
    let line = "From ten to twenty meters, there are two cars in the left adjacent lane ahead of us.\n";
    // rlmflow stops reading once it cannot write, so this write may itself find a closed pipe.
    let _ = child.stdin.take().unwrap().write_all(line.repeat(20_000).as_bytes());
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(String::from_utf8_lossy(&out.stderr), "");
}

/// `rlmflow operators | head -0` and the like: the commands that only print end as `ls` would,
/// by SIGPIPE, with nothing on stderr (no panic over a failed write).
#[test]
fn printing_commands_into_a_reader_that_stops_early_end_quietly() {
    use std::os::unix::process::ExitStatusExt;
    let dir = scratch("closed-pipe", "[pipeline]\nname = \"pipe\"\n[stages.scenes]\noperator = \"procedural\"\nframes = 4\n");
    for args in [
        &["operators"][..],
        &["operators", "--json"],
        &["status", "p.toml"],
        &["dag", "p.toml"],
        &["explain", "p.toml", "scenes"],
        &["show", "p.toml", "scenes"],
    ] {
        let mut child = Command::new(env!("CARGO_BIN_EXE_rlmflow"))
            .args(args)
            .current_dir(&dir)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        drop(child.stdout.take());
        let out = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success() || out.status.signal() == Some(libc::SIGPIPE), "{args:?}: {:?} {stderr}", out.status);
        assert_eq!(stderr, "", "{args:?}");
    }
}

#[test]
fn setup_reports_the_managed_environment_the_stages_use() {
    let env = rlmflow_python::ensure(&mut |_| {}).unwrap();
    let (ok, out) = rlmflow(&root(), &["setup"]);
    assert!(ok, "{out}");
    assert!(out.contains(&format!("environment: {}", env.root.display())), "{out}");
    assert!(env.site_packages.join("highway_env").is_dir(), "{}", env.site_packages.display());
}
