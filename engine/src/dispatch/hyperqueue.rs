//! HyperQueue tasks: each action is one task running the same `exec` command line, with a
//! resource request from what its operator declares (threads -> cpus, a GPU -> `gpus/nvidia`
//! when `gpus = true`: the share of one its memory estimate takes where `gpu_memory_gib`
//! declares the workers' GPUs, else a whole one). The client API and the local cluster come from the `hyperqueue` package
//! in the managed Python environment (`hyperqueue.py`).
//!
//! With `worker_store = "shared"` (the default) a task's stdout and stderr go to files under the
//! run directory (the store must be on a filesystem every worker sees); stdout is followed as it
//! grows, so progress and events arrive as from a local child, and the rest of both files joins
//! the stage's log.
//!
//! With a store of each worker's own (`"temporary"` or a path), nothing is shared but the remote
//! cache: the engine pushes the task's inputs there and sends the request on the task's stdin;
//! the task (`exec --remote`, in `exec.rs`) fetches its inputs, runs, pushes its result and a
//! transcript of its output; the engine then reads the transcript (outcome, events, log) and
//! pulls the result into its own store. Progress arrives with the transcript, when the task ends.
//!
//! A task that ends without an outcome (its process killed, its worker lost) is submitted again
//! up to `retries` times; the action resumes from its checkpoint. An operator's own error is not
//! retried.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::Context as _;
use rlmflow_python::embed::{self, pyo3};
use serde_json::json;

use pyo3::conversion::FromPyObjectOwned;
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use super::{Dispatch, Exit, Launch, Report, Reports, forward_line};
use crate::config::{HyperQueueSettings, RemoteSettings, WorkerStore};
use crate::protocol::Message;

const HELPER: &str = include_str!("hyperqueue.py");

pub struct HyperQueue {
    settings: HyperQueueSettings,
    /// Hears what setting up the Python environment does (a fresh machine creates it).
    note: Box<dyn FnMut(&str) + Send>,
    /// The helper module, loaded with the interpreter when first needed, so a run that submits
    /// nothing to a local cluster never starts Python.
    helper: Option<Py<PyModule>>,
    /// The client, once connected (to the given server, or to the local cluster once started).
    /// The client must not be entered by two threads at once: every call goes through this lock.
    client: Option<Arc<Mutex<Client>>>,
    cluster: Option<Py<PyAny>>,
    /// Where task outputs and a local cluster's server directory go (inside the run directory).
    dir: PathBuf,
    /// With stores of the workers' own: theirs, and the remote cache between them and the engine.
    own: Option<OwnStores>,
}

/// Tasks with stores of their own, and the remote cache their inputs and results travel by.
#[derive(Clone)]
struct OwnStores {
    store: WorkerStore,
    remote: RemoteSettings,
    /// The run's id, under which the transcripts go.
    run: String,
}

/// The helper module and a client connection, used by one thread at a time.
struct Client {
    helper: Py<PyModule>,
    client: Py<PyAny>,
}

impl Client {
    fn connect(helper: &Py<PyModule>, server: &Path) -> anyhow::Result<Client> {
        Python::attach(|py| {
            let client = helper.bind(py).getattr("connect").and_then(|f| f.call1((server.to_string_lossy().as_ref(),))).map_err(|e| {
                anyhow::anyhow!(
                    "cannot reach a HyperQueue server in {}: {}\n    start one there with `hq --server-dir={} server start`, \
                     or leave [pipeline.hyperqueue] server_dir unset to start a local cluster for the run",
                    server.display(),
                    first_paragraph(&e.value(py).to_string()),
                    server.display()
                )
            })?;
            Ok(Client { helper: helper.clone_ref(py), client: client.unbind() })
        })
    }

    /// Calls `helper.name(client, *args)`.
    fn call<T: for<'a, 'py> FromPyObjectOwned<'py>>(
        &self,
        name: &str,
        args: impl for<'py> FnOnce(Python<'py>) -> PyResult<Vec<Bound<'py, PyAny>>>,
    ) -> anyhow::Result<T> {
        Python::attach(|py| {
            let mut all = vec![self.client.bind(py).clone()];
            all.extend(args(py).map_err(|e| anyhow::anyhow!("HyperQueue {name}: {}", embed::traceback(py, &e)))?);
            let args = PyTuple::new(py, all)?;
            self.helper
                .bind(py)
                .getattr(name)
                .and_then(|f| f.call1(args))
                .and_then(|r| r.extract::<T>().map_err(Into::into))
                .map_err(|e| anyhow::anyhow!("HyperQueue {name}: {}", embed::traceback(py, &e)))
        })
    }
}

impl HyperQueue {
    /// For an existing server, connects now, so an unreachable one stops the run before anything
    /// runs. For a local cluster nothing happens until the first task: the Python environment,
    /// the interpreter, the client and the cluster start then, so a run with nothing to do
    /// costs what a local one does.
    ///
    /// Workers with stores of their own need `remote`, pushing: it is how their inputs and
    /// results travel.
    pub fn connect(
        settings: HyperQueueSettings,
        dir: &Path,
        run: &str,
        remote: Option<&RemoteSettings>,
        note: Box<dyn FnMut(&str) + Send>,
    ) -> anyhow::Result<HyperQueue> {
        let store = settings.worker_store().map_err(|(key, why)| anyhow::anyhow!("[pipeline.hyperqueue] {key}: {why}"))?;
        let own = match (store, remote) {
            (WorkerStore::Shared, _) => None,
            (store, Some(remote)) if remote.url.is_some() && remote.push => Some(OwnStores { store, remote: remote.clone(), run: run.to_owned() }),
            _ => anyhow::bail!(
                "[pipeline.hyperqueue] worker_store = \"{}\" hands inputs and results between the workers and this machine through the remote cache, \
                 so it needs one that this run pushes to: set [pipeline] remote and remote_push = true (or pass --remote URL --push), \
                 or use worker_store = \"shared\" with the store on a filesystem every worker sees",
                settings.worker_store
            ),
        };
        let mut hq = HyperQueue { settings, note, helper: None, client: None, cluster: None, dir: dir.to_path_buf(), own };
        if let Some(server) = hq.settings.server_dir.clone() {
            let helper = hq.helper()?;
            hq.client = Some(Arc::new(Mutex::new(Client::connect(&helper, &server)?)));
        }
        Ok(hq)
    }

    /// The helper module, starting the interpreter the first time.
    fn helper(&mut self) -> anyhow::Result<Py<PyModule>> {
        if self.helper.is_none() {
            let env = rlmflow_python::ensure(&mut *self.note)?;
            embed::start(&env)?;
            let helper = Python::attach(|py| embed::module(py, "rlmflow_hyperqueue", HELPER).map(|m| m.unbind()))?;
            std::fs::create_dir_all(&self.dir).with_context(|| format!("creating {}", self.dir.display()))?;
            self.helper = Some(helper);
        }
        Ok(Python::attach(|py| self.helper.as_ref().expect("loaded above").clone_ref(py)))
    }

    /// The client, starting the local cluster first if there is no server.
    fn client(&mut self) -> anyhow::Result<Arc<Mutex<Client>>> {
        if let Some(client) = &self.client {
            return Ok(client.clone());
        }
        let helper = self.helper()?;
        let (workers, cores) = (self.settings.workers, self.settings.cores());
        let local = self.dir.join("server");
        // The cluster prints its server's details to stdout, where `--json` writes events.
        let _quiet = StdoutTo::file(&self.dir.join("cluster.log"))?;
        let (cluster, server) = Python::attach(|py| -> anyhow::Result<(Py<PyAny>, PathBuf)> {
            let helper = helper.bind(py);
            let err = |e: PyErr| anyhow::anyhow!("starting a local HyperQueue cluster: {}", embed::traceback(py, &e));
            let cluster = helper.getattr("start_cluster").and_then(|f| f.call1((local.to_string_lossy().as_ref(), workers, cores))).map_err(err)?;
            let server: String = helper.getattr("server_dir").and_then(|f| f.call1((&cluster,))).and_then(|d| d.extract()).map_err(err)?;
            Ok((cluster.unbind(), PathBuf::from(server)))
        })?;
        self.cluster = Some(cluster);
        let client = Arc::new(Mutex::new(Client::connect(&helper, &server)?));
        self.client = Some(client.clone());
        Ok(client)
    }
}

impl Drop for HyperQueue {
    fn drop(&mut self) {
        if let (Some(cluster), Some(helper)) = (self.cluster.take(), &self.helper) {
            Python::attach(|py| {
                let _ = helper.bind(py).getattr("stop_cluster").and_then(|f| f.call1((cluster,)));
            });
        }
    }
}

/// One task's life, from its thread: submit, follow, and submit again while it is lost.
struct Task {
    client: Arc<Mutex<Client>>,
    dir: PathBuf,
    launch: Launch,
    retries: u32,
    /// What a stage that can use a GPU asks of `gpus/nvidia` (0: none, the cluster has none).
    gpu_share: f64,
    own: Option<OwnStores>,
}

impl Dispatch for HyperQueue {
    fn start(&mut self, launch: Launch, reports: Reports) -> anyhow::Result<()> {
        let client = self.client()?;
        let gpu_share = match self.settings.gpus && launch.gpu {
            true => self.settings.gpu_share(launch.estimate),
            false => 0.0,
        };
        let task = Task { client, dir: self.dir.clone(), launch, retries: self.settings.retries, gpu_share, own: self.own.clone() };
        let log = Arc::new(Mutex::new(File::create(&task.launch.log).with_context(|| format!("creating {}", task.launch.log.display()))?));
        std::thread::spawn(move || {
            let exit = task.run(&reports, &log).unwrap_or_else(|e| Exit::Lost(format!("{e:#}")));
            reports(Report::Exited(exit));
        });
        Ok(())
    }

    fn max_threads(&self) -> Option<usize> {
        Some(self.settings.cores())
    }

    fn describe(&self) -> String {
        let HyperQueueSettings { workers, server_dir, .. } = &self.settings;
        let cluster = match server_dir {
            Some(dir) => format!("server {}", dir.display()),
            None => format!("local cluster, {workers} workers x {} cores", self.settings.cores()),
        };
        let stores = match &self.own {
            None => String::new(),
            Some(own) => format!(", worker stores {}, through {}", self.settings.worker_store, own.remote.url.as_deref().unwrap_or_default()),
        };
        format!("hyperqueue ({cluster}{stores})")
    }
}

/// The exit status of coreutils' `timeout` when the command ran past its limit.
const TIMED_OUT: i32 = 124;

/// How often a running task's state and output are looked at.
const POLL: Duration = Duration::from_millis(100);

impl Task {
    fn run(&self, reports: &Reports, log: &Mutex<File>) -> anyhow::Result<Exit> {
        let name = rlmflow_cache::file_safe(&self.launch.label);
        let own = match &self.own {
            Some(own) => match OwnTask::prepare(own, &self.launch)? {
                Ok(task) => Some(task),
                Err(exit) => return Ok(exit),
            },
            None => None,
        };
        let mut attempt = 0;
        loop {
            let (job, exit, outcome) = match &own {
                None => {
                    let stdout = self.dir.join(format!("{name}.{attempt}.stdout"));
                    let stderr = self.dir.join(format!("{name}.{attempt}.stderr"));
                    let job = self.submit(&name, self.launch.args.clone(), &self.dir, [&stdout, &stderr], None)?;
                    let (exit, outcome) = self.follow(job, &stdout, reports, log)?;
                    if let Ok(mut text) = std::fs::read_to_string(&stderr) {
                        if !text.is_empty() && !text.ends_with('\n') {
                            text.push('\n');
                        }
                        let _ = log.lock().unwrap().write_all(text.as_bytes());
                    }
                    (job, exit, outcome)
                }
                Some(own) => {
                    let transcript = format!("{}/{name}.{attempt}", own.run);
                    let cwd = std::env::temp_dir();
                    let [stdout, stderr] = ["stdout", "stderr"].map(|ext| cwd.join(format!("rlmflow-{}-{name}.{attempt}.{ext}", own.run)));
                    let job = self.submit(&name, own.args(&self.launch, &transcript), &cwd, [&stdout, &stderr], Some(&own.request))?;
                    let reason = self.wait(job, || {})?;
                    let (exit, outcome) = own.finish(&reason, &transcript, &stderr, reports, log)?;
                    (job, exit, outcome)
                }
            };
            let exit = match (exit, self.launch.timeout) {
                (Exit::Code(TIMED_OUT), Some(limit)) => Exit::TimedOut(limit.as_secs_f64()),
                (exit, _) => exit,
            };
            // A task stopped at its time limit was not lost: the stage's `retries` decide.
            let lost = !outcome && !matches!(exit, Exit::Code(0) | Exit::TimedOut(_));
            if !lost || attempt >= self.retries {
                return Ok(exit);
            }
            attempt += 1;
            let data = json!({"job": job, "attempt": attempt, "retries": self.retries, "reason": exit.describe()});
            reports(Report::Message(Message::Event { name: "hyperqueue_retry".into(), data }));
            let _ =
                writeln!(log.lock().unwrap(), "rlmflow: HyperQueue job {job} ended without an outcome ({}); submitting it again", exit.describe());
        }
    }

    fn submit(&self, name: &str, args: Vec<String>, cwd: &Path, [stdout, stderr]: [&Path; 2], stdin: Option<&[u8]>) -> anyhow::Result<u64> {
        let l = &self.launch;
        // The stage's time limit, on the worker: the Python client cannot set HyperQueue's
        // `--time-limit`, so coreutils' `timeout` stops the task (exit status 124), then kills it
        // if it has not ended 10 s later.
        let mut command: Vec<String> = match l.timeout {
            Some(limit) => vec!["timeout".into(), "--kill-after=10".into(), format!("{}s", limit.as_secs_f64())],
            None => Vec::new(),
        };
        command.push(l.exe.to_string_lossy().into_owned());
        command.extend(args);
        let gpus = self.gpu_share;
        let [cwd, stdout, stderr] = [cwd, stdout, stderr].map(|p| p.to_string_lossy().into_owned());
        let stdin = stdin.map(|bytes| bytes.to_vec());
        let client = self.client.lock().unwrap();
        client
            .call("submit", |py| {
                Ok(vec![
                    name.into_pyobject(py)?.into_any(),
                    command.into_pyobject(py)?.into_any(),
                    cwd.into_pyobject(py)?.into_any(),
                    stdout.into_pyobject(py)?.into_any(),
                    stderr.into_pyobject(py)?.into_any(),
                    l.threads.into_pyobject(py)?.into_any(),
                    gpus.into_pyobject(py)?.into_any(),
                    stdin.map(|b| pyo3::types::PyBytes::new(py, &b).into_any()).unwrap_or_else(|| py.None().into_bound(py)),
                ])
            })
            .with_context(|| format!("submitting {}", l.label))
    }

    /// Waits for the job to end, calling `between` after each look at its state; returns
    /// HyperQueue's reason it failed ("" when it did not).
    fn wait(&self, job: u64, mut between: impl FnMut()) -> anyhow::Result<String> {
        loop {
            let state: Option<String> = self.client.lock().unwrap().call("status", |py| Ok(vec![job.into_pyobject(py)?.into_any()]))?;
            between();
            match state {
                Some(reason) => return Ok(reason),
                None => std::thread::sleep(POLL),
            }
        }
    }

    /// Follows the task's stdout until the job ends; returns how it ended and whether the
    /// process reported an outcome (done, reused, failed, corrupt input).
    fn follow(&self, job: u64, stdout: &Path, reports: &Reports, log: &Mutex<File>) -> anyhow::Result<(Exit, bool)> {
        let mut tail = Tail::default();
        let mut outcome = false;
        let mut forward = |line: &str| {
            outcome |= outcome_of(line).is_some();
            forward_line(line, reports, log);
        };
        let reason = self.wait(job, || tail.read(stdout, &mut forward))?;
        tail.read(stdout, &mut forward);
        tail.finish(&mut forward);
        let exit = if reason.is_empty() { Exit::Code(0) } else { exit_of(&reason) };
        Ok((exit, outcome))
    }
}

/// One action as a task with a store of its own: its request, and a client of the remote cache
/// for the task's thread.
struct OwnTask {
    store: WorkerStore,
    remote: rlmflow_remote::Remote,
    /// The engine's store: the inputs come from it, the result goes into it.
    engine: rlmflow_cache::Store,
    key: rlmflow_cache::Digest,
    /// The request, as JSON, for the task's stdin.
    request: Vec<u8>,
    /// The run's id, under which the transcripts go.
    run: String,
}

impl OwnTask {
    /// Pushes the action's inputs to the remote cache, where the workers fetch them; an exit
    /// when that cannot be done.
    fn prepare(own: &OwnStores, launch: &Launch) -> anyhow::Result<Result<OwnTask, Exit>> {
        let remote = own.remote.open_transport()?;
        let engine =
            rlmflow_cache::Store::open_existing(&launch.store)?.with_context(|| format!("no rlmflow store at {}", launch.store.display()))?;
        let request = engine.request(&launch.key)?.with_context(|| format!("the store has no request for action {}", launch.key))?;
        for input in &request.preimage.inputs {
            if let Err(why) = remote.push_object(&engine, &input.digest, false, &mut |_, _| {})? {
                return Ok(Err(Exit::Lost(format!("could not hand input {} to the workers through the remote cache: {why}", input.digest.short()))));
            }
        }
        let request = serde_json::to_vec(&request)?;
        Ok(Ok(OwnTask { store: own.store.clone(), remote, engine, key: launch.key, request, run: own.run.clone() }))
    }

    /// `exec KEY --remote URL ...`: the task's command line after the executable.
    fn args(&self, launch: &Launch, transcript: &str) -> Vec<String> {
        let timeout = self.remote.timeout().as_secs_f64();
        let mut args = vec!["exec".to_owned(), launch.key.to_string(), "--remote".into(), self.remote.url().to_owned()];
        args.extend(["--remote-timeout".into(), timeout.to_string(), "--transcript".into(), transcript.to_owned()]);
        args.extend(["--threads".into(), launch.threads.to_string(), "--device".into(), launch.device.to_string()]);
        if let WorkerStore::Own(dir) = &self.store {
            args.extend(["--store".into(), dir.to_string_lossy().into_owned()]);
        }
        if launch.replace_remote {
            args.push("--replace".into());
        }
        args
    }

    /// After the job ended (HyperQueue's `reason` it failed, "" if it did not): forwards the
    /// transcript, and pulls the result into the engine's store. Returns how the task ended
    /// and whether it reported an outcome.
    fn finish(&self, reason: &str, transcript: &str, stderr: &Path, reports: &Reports, log: &Mutex<File>) -> anyhow::Result<(Exit, bool)> {
        let mut exit = if reason.is_empty() { Exit::Code(0) } else { exit_of(reason) };
        let mut outcome = None;
        match self.remote.transcript(transcript) {
            Some(text) => {
                for line in text.lines() {
                    outcome = outcome_of(line).or(outcome);
                    forward_line(line, reports, log);
                }
                self.remote.remove_transcript(transcript);
            }
            None => {
                let why = self.remote.down().map(|d| format!(" ({d})")).unwrap_or_default();
                let _ = writeln!(
                    log.lock().unwrap(),
                    "rlmflow: the task left no transcript on the remote cache{why}; its worker keeps its output in {}",
                    stderr.with_extension("stdout").display()
                );
            }
        }
        if outcome == Some(true) && exit == Exit::Code(0) {
            // The engine's own task's result: its type is the operator's own business here.
            let why = match self.remote.pull(&self.engine, &self.key, &|_| Ok(()), &mut |_, _| {})? {
                rlmflow_remote::Pulled::Hit { .. } => None,
                rlmflow_remote::Pulled::Miss => Some("the remote cache does not have it".into()),
                rlmflow_remote::Pulled::Unreachable(e) => Some(e.to_string()),
                rlmflow_remote::Pulled::Corrupt { why } | rlmflow_remote::Pulled::Untrusted { why } => Some(why),
            };
            if let Some(why) = why {
                let message = format!("the task finished, but its result could not be fetched from the remote cache: {why}");
                reports(Report::Message(Message::Failed { message, setting: None }));
                exit = Exit::Code(1);
            }
        }
        Ok((exit, outcome.is_some()))
    }
}

/// Whether a line of a task's output reports how the action ended: `Some(true)` when it is done
/// or was reused, `Some(false)` when it failed or found an input corrupt; `None` for anything
/// else (progress, events, other output).
fn outcome_of(line: &str) -> Option<bool> {
    match line.strip_prefix(crate::protocol::PREFIX).map(serde_json::from_str::<Message>)? {
        Ok(Message::Progress { .. } | Message::Event { .. } | Message::Live { .. } | Message::Waiting) | Err(_) => None,
        Ok(message) => Some(matches!(message, Message::Done { .. } | Message::Reused)),
    }
}

/// Points this process's stdout (fd 1) at a file until dropped.
struct StdoutTo {
    saved: i32,
}

impl StdoutTo {
    fn file(path: &Path) -> anyhow::Result<StdoutTo> {
        use std::os::fd::AsRawFd;
        let file = File::create(path).with_context(|| format!("creating {}", path.display()))?;
        std::io::stdout().flush()?;
        // SAFETY: plain descriptor calls; fd 1 is restored on drop.
        let saved = unsafe { libc::dup(1) };
        if saved < 0 || unsafe { libc::dup2(file.as_raw_fd(), 1) } < 0 {
            anyhow::bail!("redirecting stdout: {}", std::io::Error::last_os_error());
        }
        Ok(StdoutTo { saved })
    }
}

impl Drop for StdoutTo {
    fn drop(&mut self) {
        // SAFETY: `saved` is the descriptor `dup` returned.
        unsafe {
            libc::dup2(self.saved, 1);
            libc::close(self.saved);
        }
    }
}

/// HyperQueue's errors end in a Rust backtrace; the reason comes before it.
fn first_paragraph(text: &str) -> String {
    text.split("Stack backtrace:").next().unwrap_or(text).split_whitespace().collect::<Vec<_>>().join(" ")
}

/// Reads whole lines appended to a file since the last read.
#[derive(Default)]
struct Tail {
    offset: u64,
    partial: String,
}

impl Tail {
    fn read(&mut self, path: &Path, forward: &mut impl FnMut(&str)) {
        let Ok(mut file) = File::open(path) else { return };
        let mut bytes = Vec::new();
        if file.seek(SeekFrom::Start(self.offset)).is_err() || file.read_to_end(&mut bytes).is_err() {
            return;
        }
        self.offset += bytes.len() as u64;
        self.partial.push_str(&String::from_utf8_lossy(&bytes));
        while let Some(end) = self.partial.find('\n') {
            let line: String = self.partial.drain(..=end).collect();
            forward(line.trim_end_matches('\n'));
        }
    }

    fn finish(&mut self, forward: &mut impl FnMut(&str)) {
        if !self.partial.is_empty() {
            forward(&std::mem::take(&mut self.partial));
        }
    }
}

/// HyperQueue's failure text as an exit: "Program terminated with exit code 3." or "... Received
/// signal 9 (SIGKILL).".
fn exit_of(reason: &str) -> Exit {
    let number_after = |marker: &str| {
        reason.find(marker).and_then(|at| reason[at + marker.len()..].trim_start().split(|c: char| !c.is_ascii_digit()).next()?.parse().ok())
    };
    if let Some(signal) = number_after("signal") {
        return Exit::Signal(signal);
    }
    if let Some(code) = number_after("exit code") {
        return Exit::Code(code);
    }
    Exit::Lost(format!("HyperQueue: {reason}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hyperqueue_failures_become_exits() {
        assert_eq!(exit_of("Program terminated with exit code 3."), Exit::Code(3));
        assert_eq!(exit_of("Program terminated with exit code -1. Received signal 9 (SIGKILL)."), Exit::Signal(9));
        assert_eq!(exit_of("Worker lost"), Exit::Lost("HyperQueue: Worker lost".into()));
    }

    #[test]
    fn the_tail_forwards_whole_lines_as_they_arrive() {
        let path = std::env::temp_dir().join(format!("rlmflow-tail-{}", std::process::id()));
        std::fs::write(&path, "one\ntw").unwrap();
        let (mut tail, mut seen) = (Tail::default(), Vec::new());
        tail.read(&path, &mut |l| seen.push(l.to_owned()));
        assert_eq!(seen, ["one"]);
        std::fs::OpenOptions::new().append(true).open(&path).unwrap().write_all(b"o\nthr").unwrap();
        tail.read(&path, &mut |l| seen.push(l.to_owned()));
        tail.finish(&mut |l| seen.push(l.to_owned()));
        assert_eq!(seen, ["one", "two", "thr"]);
    }
}
