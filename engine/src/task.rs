//! `rlmflow exec KEY --remote URL --transcript NAME`: one action as a cluster task on a worker
//! with a store of its own, for clusters without a shared filesystem. Its inputs arrive through
//! the remote cache, the action runs in a child `exec`, and the result and a transcript of
//! everything it printed go back through the remote.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::Context as _;
use rlmflow_cache::{ActionRequest, Digest, Store};
use rlmflow_stages::Device;

use crate::protocol::{EXIT_CORRUPT_INPUT, Message, PREFIX, send};

/// Where a cluster task with a store of its own meets the engine: `rlmflow exec KEY --remote
/// URL --transcript NAME`.
pub struct TaskRemote {
    pub url: String,
    pub timeout: std::time::Duration,
    /// Where under the remote's `runs/` the task's transcript goes.
    pub transcript: String,
    /// Upload the result even where the remote has an object by its digest (known corrupt).
    pub replace: bool,
}

/// Runs action `key` as a cluster task on a worker with a store of its own (`store`; `None`: a
/// temporary one, removed afterwards), for clusters without a shared filesystem. The request
/// arrives on stdin; inputs the store lacks come from the remote cache, verified; the action
/// runs in a child `exec` whose output is relayed and kept; the result is pushed; and the
/// transcript (every line the child printed, and the task's own messages) is written to the
/// remote, where the engine reads the outcome, the events and the log.
pub fn exec_task(store: Option<&Path>, key: Digest, threads: usize, device: Device, remote: TaskRemote) -> anyhow::Result<i32> {
    let request: ActionRequest =
        serde_json::from_reader(std::io::stdin().lock()).context("reading the action's request (JSON) from stdin, as the engine sends it")?;
    anyhow::ensure!(request.key == key, "the request on stdin is for action {}, not {key}", request.key);
    let (root, temporary) = match store {
        Some(dir) => (dir.to_path_buf(), None),
        None => {
            let dir = std::env::temp_dir().join(format!("rlmflow-task-{}-{}", key.short(), std::process::id()));
            (dir.clone(), Some(RemoveOnDrop(dir)))
        }
    };
    let store = Store::open(&root)?;
    store.write_request(&request)?;
    let cache = rlmflow_remote::Remote::open(&remote.url, true, remote.timeout)?;
    let mut transcript = Transcript::default();
    let code = run_task(&store, &cache, &request, threads, device, remote.replace, &mut transcript)?;
    if !cache.put_transcript(&remote.transcript, transcript.text()) {
        eprintln!("warning: could not write the transcript to {}: {}", remote.url, cache.down().map(|e| e.to_string()).unwrap_or_default());
    }
    drop(temporary);
    Ok(code)
}

fn run_task(
    store: &Store,
    cache: &rlmflow_remote::Remote,
    request: &ActionRequest,
    threads: usize,
    device: Device,
    replace: bool,
    transcript: &mut Transcript,
) -> anyhow::Result<i32> {
    let key = request.key;
    for input in &request.preimage.inputs {
        use rlmflow_remote::Fetched;
        let why = match cache.fetch_object(store, &input.digest, &mut |_, _| {})? {
            Fetched::Present | Fetched::Downloaded(_) => continue,
            Fetched::Missing => "the remote cache does not have it".into(),
            Fetched::Unreachable(e) => e.to_string(),
            Fetched::Corrupt(why) => why,
        };
        transcript.line(format!("rlmflow task: input {} could not be fetched: {why}", input.digest.short()));
        transcript.send(&Message::CorruptInput { digest: input.digest, files: Vec::new() });
        return Ok(EXIT_CORRUPT_INPUT);
    }
    let exe = std::env::current_exe().context("locating this executable")?;
    let mut child = std::process::Command::new(&exe)
        .args([
            "exec",
            &key.to_string(),
            "--store",
            &store.root().to_string_lossy(),
            "--threads",
            &threads.to_string(),
            "--device",
            &device.to_string(),
        ])
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .with_context(|| format!("starting {}", exe.display()))?;
    let lines = transcript.lines.clone();
    let stderr = child.stderr.take().expect("piped");
    let errors = std::thread::spawn(move || relay(stderr, &lines, |line| eprintln!("{line}")));
    relay(child.stdout.take().expect("piped"), &transcript.lines, |line| println!("{line}"));
    let _ = errors.join();
    let status = child.wait()?;
    let code = status.code().unwrap_or(1);
    if code != 0 {
        if status.code().is_none() {
            transcript.send(&Message::Failed { message: format!("the stage process ended without an exit status ({status})"), setting: None });
        }
        return Ok(code);
    }
    let record = store.fresh(&key)?.context("the action finished without a record")?;
    if let Err(why) = cache.push(store, &record, replace, &mut |_, _| {})? {
        transcript
            .send(&Message::Failed { message: format!("computed, but the result could not be pushed to the remote cache ({why})"), setting: None });
        return Ok(1);
    }
    Ok(0)
}

/// Copies each line of `from` to this process's output (`echo`) and into `lines`.
fn relay(from: impl std::io::Read, lines: &std::sync::Mutex<Vec<String>>, echo: impl Fn(&str)) {
    use std::io::BufRead;
    for line in std::io::BufReader::new(from).lines().map_while(Result::ok) {
        echo(&line);
        lines.lock().unwrap().push(line);
    }
}

/// A cluster task's output, kept for the engine.
#[derive(Default)]
struct Transcript {
    lines: Arc<std::sync::Mutex<Vec<String>>>,
}

impl Transcript {
    fn line(&mut self, line: String) {
        eprintln!("{line}");
        self.lines.lock().unwrap().push(line);
    }

    fn send(&mut self, message: &Message) {
        send(message);
        self.lines.lock().unwrap().push(format!("{PREFIX}{}", serde_json::to_string(message).expect("message serialises")));
    }

    fn text(&self) -> String {
        self.lines.lock().unwrap().iter().map(|l| format!("{l}\n")).collect()
    }
}

struct RemoveOnDrop(PathBuf);

impl Drop for RemoveOnDrop {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}
