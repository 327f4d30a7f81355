use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use rlmflow_engine::event::{Event, Logged};
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

/// What a `--json` run printed: each line as JSON (for the tests' own questions) and as the
/// engine's typed event.
pub struct Events(pub Vec<Value>, pub Vec<Event>);

impl Events {
    /// The events a `--json` run printed on `stdout`, one JSON object a line, each one of the
    /// engine's [`Event`]s (what `runs` and `compare` read back).
    pub fn parse(stdout: &[u8]) -> Events {
        let text = text(stdout);
        let lines: Vec<&str> = text.lines().collect();
        let typed = lines.iter().map(|l| serde_json::from_str::<Logged>(l).unwrap_or_else(|e| panic!("not an event ({e}): {l}")).event).collect();
        Events(lines.iter().map(|l| serde_json::from_str(l).expect(l)).collect(), typed)
    }

    /// `stage -> status` of every `stage_finished` event, in order.
    pub fn finished(&self) -> Vec<(String, String)> {
        let finished = self.1.iter().filter_map(|e| if let Event::StageFinished(f) = e { Some(f) } else { None });
        finished.map(|f| (f.stage.clone(), f.status.as_str().to_owned())).collect()
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
