//! HyperQueue tasks: each action is one task running the same `exec` command line, with a
//! resource request from what its operator declares (threads -> cpus, a GPU -> `gpus/nvidia`
//! when `gpus = true`). The client API and the local cluster come from the `hyperqueue` package
//! in the managed Python environment (`hyperqueue.py`).
//!
//! A task's stdout and stderr go to files under the run directory (the store must be on a
//! filesystem every worker sees); stdout is followed as it grows, so progress and events arrive
//! as from a local child, and the rest of both files joins the stage's log. A task that ends
//! without an outcome (its process killed, its worker lost) is submitted again up to `retries`
//! times; the action resumes from its checkpoint. An operator's own error is not retried.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::mpsc::Sender;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::Context as _;
use rlmflow_python::embed::{self, pyo3};
use serde_json::json;

use pyo3::conversion::FromPyObjectOwned;
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use super::{Dispatch, Exit, HyperQueueSettings, Launch, Report, forward_line};
use crate::exec::Message;

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
    pub fn connect(settings: HyperQueueSettings, dir: &Path, note: Box<dyn FnMut(&str) + Send>) -> anyhow::Result<HyperQueue> {
        let mut hq = HyperQueue { settings, note, helper: None, client: None, cluster: None, dir: dir.to_path_buf() };
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
    gpus: bool,
}

impl Dispatch for HyperQueue {
    fn start(&mut self, id: usize, launch: Launch, tx: Sender<(usize, Report)>) -> anyhow::Result<()> {
        let client = self.client()?;
        let task = Task { client, dir: self.dir.clone(), launch, retries: self.settings.retries, gpus: self.settings.gpus };
        let log = Arc::new(Mutex::new(File::create(&task.launch.log).with_context(|| format!("creating {}", task.launch.log.display()))?));
        std::thread::spawn(move || {
            let exit = task.run(id, &tx, &log).unwrap_or_else(|e| Exit::Lost(format!("{e:#}")));
            let _ = tx.send((id, Report::Exited(exit)));
        });
        Ok(())
    }

    fn max_threads(&self) -> Option<usize> {
        Some(self.settings.cores())
    }

    fn serialises_gpu(&self) -> bool {
        false
    }

    fn describe(&self) -> String {
        let HyperQueueSettings { workers, server_dir, .. } = &self.settings;
        match server_dir {
            Some(dir) => format!("hyperqueue (server {})", dir.display()),
            None => format!("hyperqueue (local cluster, {workers} workers x {} cores)", self.settings.cores()),
        }
    }
}

/// How often a running task's state and output are looked at.
const POLL: Duration = Duration::from_millis(100);

impl Task {
    fn run(&self, id: usize, tx: &Sender<(usize, Report)>, log: &Mutex<File>) -> anyhow::Result<Exit> {
        let name = rlmflow_cache::file_safe(&self.launch.label);
        let mut attempt = 0;
        loop {
            let stdout = self.dir.join(format!("{name}.{attempt}.stdout"));
            let stderr = self.dir.join(format!("{name}.{attempt}.stderr"));
            let job = self.submit(&name, &stdout, &stderr)?;
            let (exit, outcome) = self.follow(job, &stdout, id, tx, log)?;
            if let Ok(mut text) = std::fs::read_to_string(&stderr) {
                if !text.is_empty() && !text.ends_with('\n') {
                    text.push('\n');
                }
                let _ = log.lock().unwrap().write_all(text.as_bytes());
            }
            let lost = !outcome && !matches!(exit, Exit::Code(0));
            if !lost || attempt >= self.retries {
                return Ok(exit);
            }
            attempt += 1;
            let data = json!({"job": job, "attempt": attempt, "retries": self.retries, "reason": exit.describe()});
            let _ = tx.send((id, Report::Message(Message::Event { name: "hyperqueue_retry".into(), data })));
            let _ =
                writeln!(log.lock().unwrap(), "rlmflow: HyperQueue job {job} ended without an outcome ({}); submitting it again", exit.describe());
        }
    }

    fn submit(&self, name: &str, stdout: &Path, stderr: &Path) -> anyhow::Result<u64> {
        let l = &self.launch;
        let mut args = vec![l.exe.to_string_lossy().into_owned()];
        args.extend(l.args.iter().cloned());
        let gpus = u32::from(self.gpus && l.gpu);
        let [cwd, stdout, stderr] = [&self.dir, stdout, stderr].map(|p| p.to_string_lossy().into_owned());
        let client = self.client.lock().unwrap();
        client
            .call("submit", |py| {
                Ok(vec![
                    name.into_pyobject(py)?.into_any(),
                    args.into_pyobject(py)?.into_any(),
                    cwd.into_pyobject(py)?.into_any(),
                    stdout.into_pyobject(py)?.into_any(),
                    stderr.into_pyobject(py)?.into_any(),
                    l.threads.into_pyobject(py)?.into_any(),
                    gpus.into_pyobject(py)?.into_any(),
                ])
            })
            .with_context(|| format!("submitting {}", l.label))
    }

    /// Follows the task's stdout until the job ends; returns how it ended and whether the
    /// process reported an outcome (done, reused, failed, corrupt input).
    fn follow(&self, job: u64, stdout: &Path, id: usize, tx: &Sender<(usize, Report)>, log: &Mutex<File>) -> anyhow::Result<(Exit, bool)> {
        let mut tail = Tail::default();
        let mut outcome = false;
        let mut forward = |line: &str| {
            if let Some(Ok(message)) = line.strip_prefix(crate::exec::PREFIX).map(serde_json::from_str::<Message>) {
                outcome |= !matches!(message, Message::Progress { .. } | Message::Event { .. } | Message::Waiting);
            }
            forward_line(line, id, tx, log);
        };
        let reason = loop {
            let state: Option<String> = self.client.lock().unwrap().call("status", |py| Ok(vec![job.into_pyobject(py)?.into_any()]))?;
            tail.read(stdout, &mut forward);
            match state {
                Some(reason) => break reason,
                None => std::thread::sleep(POLL),
            }
        };
        tail.read(stdout, &mut forward);
        tail.finish(&mut forward);
        let exit = if reason.is_empty() { Exit::Code(0) } else { exit_of(&reason) };
        Ok((exit, outcome))
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
