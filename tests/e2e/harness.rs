use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use serde_json::Value;

pub use rlmflow_test_support::cli::output_dir;

/// A scratch directory (removed when its test passes) with a pipeline file, a trace file and the
/// store beside them.
pub struct Scratch {
    pub dir: PathBuf,
    _removed_when_passed: rlmflow_test_support::Scratch,
}

impl Scratch {
    pub fn new(name: &str) -> Scratch {
        let scratch = rlmflow_test_support::Scratch::new(&format!("e2e-{name}"));
        Scratch { dir: scratch.to_path_buf(), _removed_when_passed: scratch }
    }

    pub fn pipeline(&self, text: &str) -> &Self {
        fs::write(self.dir.join("p.toml"), text).unwrap();
        self
    }

    pub fn store(&self) -> PathBuf {
        self.dir.join(".rlmflow")
    }

    pub fn command(&self, args: &[&str]) -> Command {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_rlmflow-test"));
        cmd.current_dir(&self.dir).args(args).env("RLMFLOW_TEST_TRACE", self.dir.join("trace.txt"));
        cmd
    }

    pub fn cli(&self, args: &[&str]) -> Output {
        self.command(args).output().unwrap()
    }

    /// `rlmflow run p.toml --json`, returning the events; panics if the exit status is not `code`.
    pub fn run_expecting(&self, code: i32, extra: &[&str]) -> Events {
        let mut args = vec!["run", "p.toml", "--json"];
        args.extend_from_slice(extra);
        let out = self.cli(&args);
        assert_eq!(out.status.code(), Some(code), "stdout:\n{}\nstderr:\n{}", text(&out.stdout), text(&out.stderr));
        Events::parse(&out.stdout)
    }

    pub fn run(&self) -> Events {
        self.run_expecting(0, &[])
    }

    pub fn trace(&self) -> Vec<String> {
        fs::read_to_string(self.dir.join("trace.txt")).unwrap_or_default().lines().map(str::to_owned).collect()
    }

    pub fn clear_trace(&self) {
        let _ = fs::remove_file(self.dir.join("trace.txt"));
    }
}

pub fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

pub struct Events(pub Vec<Value>);

impl Events {
    /// The events a `--json` run printed on `stdout`, one JSON object a line.
    pub fn parse(stdout: &[u8]) -> Events {
        Events(text(stdout).lines().map(|l| serde_json::from_str(l).expect(l)).collect())
    }

    /// `stage -> status` of every `stage_finished` event, in order.
    pub fn finished(&self) -> Vec<(String, String)> {
        self.0
            .iter()
            .filter(|e| e["event"] == "stage_finished")
            .map(|e| (e["stage"].as_str().unwrap().to_owned(), e["status"].as_str().unwrap().to_owned()))
            .collect()
    }

    pub fn status_of(&self, stage: &str) -> String {
        let all = self.finished();
        all.iter().find(|(s, _)| s == stage).map(|(_, st)| st.clone()).unwrap_or_else(|| panic!("{stage} not in {all:?}"))
    }

    /// Stages whose status is `status`, sorted.
    pub fn with_status(&self, status: &str) -> Vec<String> {
        let mut v: Vec<String> = self.finished().into_iter().filter(|(_, st)| st == status).map(|(s, _)| s).collect();
        v.sort();
        v
    }

    pub fn of(&self, event: &str) -> Vec<&Value> {
        self.0.iter().filter(|e| e["event"] == event).collect()
    }
}

/// Every file below `dir` with its size and modification time.
pub fn snapshot(dir: &Path) -> Vec<(PathBuf, u64, std::time::SystemTime)> {
    let mut out = Vec::new();
    if let Ok(rd) = fs::read_dir(dir) {
        for e in rd.flatten() {
            let m = e.metadata().unwrap();
            if m.is_dir() {
                out.push((e.path(), 0, m.modified().unwrap()));
                out.extend(snapshot(&e.path()));
            } else {
                out.push((e.path(), m.len(), m.modified().unwrap()));
            }
        }
    }
    out.sort();
    out
}

pub const CHAIN: &str = r#"
[pipeline]
name = "chain"
seed = 7

[stages.source]
operator = "write-text"
text = "radar"

[stages.map]
operator = "shout"
inputs = { text = "source" }
suffix = "!"

[stages.measure]
operator = "count"

[stages.collect]
operator = "collect"

[stages.other]
kind = "source"
operator = "write-text"
text = "independent"
"#;
