//! Dispatch: how an action's process is started and watched. The scheduler (`run/`) decides
//! what runs, when, and what its outcome means; a dispatcher only starts `rlmflow exec KEY
//! --store DIR` (or the worker binary's) somewhere and reports back, through the [`Reports`] it
//! is given, the protocol messages the process prints and how it ended. Planning, keys, locks, the commit
//! protocol and records are the same whichever dispatcher runs the action.
//!
//! `local.rs` starts child processes; `hyperqueue.rs` submits HyperQueue tasks. Another backend
//! (Slurm directly, Kubernetes) is one more file implementing [`Dispatch`].

use std::path::PathBuf;
use std::sync::Arc;

use crate::gpus::Gpu;
use crate::protocol::Message;

#[cfg(feature = "python")]
mod hyperqueue;
mod local;

#[cfg(feature = "python")]
pub use hyperqueue::HyperQueue;
pub use local::Local;

/// One action to start.
#[derive(Clone, Debug)]
pub struct Launch {
    /// `rlmflow` or the worker binary that runs the operator.
    pub exe: PathBuf,
    /// The arguments after the executable (`exec KEY --store DIR ...`).
    pub args: Vec<String>,
    pub key: rlmflow_cache::Digest,
    /// The engine's store, which holds the action's request and inputs.
    pub store: PathBuf,
    pub device: rlmflow_stages::Device,
    /// The remote cache's copy of this action's result is corrupt: a push replaces it.
    pub replace_remote: bool,
    /// The instance's label, for names and messages.
    pub label: String,
    pub threads: usize,
    pub gpu: bool,
    /// The GPU the scheduler placed it on, where it places them.
    pub placed: Option<Gpu>,
    /// Its peak memory estimate, where its operator makes one (a cluster asks for a GPU's share).
    pub estimate: Option<u64>,
    /// Where the process's output that is not protocol goes (`runs/<id>/logs/<label>.log`).
    pub log: PathBuf,
    /// The stage's `timeout`: the process is stopped once it has run this long.
    pub timeout: Option<std::time::Duration>,
}

/// What a dispatcher tells the scheduler about a started action.
pub enum Report {
    Message(Message),
    Exited(Exit),
}

/// Where a dispatcher tells what it hears of one action, from any of its threads.
pub type Reports = Arc<dyn Fn(Report) + Send + Sync>;

/// How an action's process ended.
#[derive(Clone, Debug, PartialEq)]
pub enum Exit {
    Code(i32),
    Signal(i32),
    /// It could not be started or watched, or the cluster lost it.
    Lost(String),
    /// It was stopped at its stage's `timeout` (seconds).
    TimedOut(f64),
}

impl Exit {
    pub fn code(&self) -> Option<i32> {
        match self {
            Exit::Code(c) => Some(*c),
            _ => None,
        }
    }

    pub fn describe(&self) -> String {
        match self {
            Exit::Code(c) => format!("the stage process exited with status {c}"),
            Exit::Signal(s) => format!("the stage process was killed by signal {s}"),
            Exit::Lost(why) => why.clone(),
            Exit::TimedOut(s) => format!("stopped at its timeout of {s} s"),
        }
    }
}

/// Starts actions and reports on them.
pub trait Dispatch {
    /// Starts `launch`; its messages, then exactly one `Exited`, go to `reports`.
    fn start(&mut self, launch: Launch, reports: Reports) -> anyhow::Result<()>;

    /// The most CPU threads one action may be given (a worker's cores), if the backend has a cap.
    fn max_threads(&self) -> Option<usize> {
        None
    }

    /// The GPUs the scheduler places GPU stages on (locally: the machine's inventory, empty
    /// where it has none); `None` where the backend places them itself (a cluster, by resource
    /// request).
    fn gpus(&self) -> Option<Vec<Gpu>> {
        None
    }

    /// Whether an action may find a CUDA device where it runs. `false` only where it surely
    /// will not (locally, without the driver's device nodes or `--device cuda`): a stage that
    /// needs one is then refused before anything runs.
    fn cuda_possible(&self) -> bool {
        true
    }

    /// For the run's header and first event, e.g. `local` or `hyperqueue (local cluster, 2 workers x 1 cores)`.
    fn describe(&self) -> String;
}

/// Reads protocol lines from `reader` into `reports`; other lines go to `log`.
pub(crate) fn forward_lines(reader: impl std::io::BufRead, reports: &Reports, log: &std::sync::Mutex<std::fs::File>) {
    for line in reader.lines().map_while(Result::ok) {
        forward_line(&line, reports, log);
    }
}

/// One line of a stage's stdout: a protocol message to `reports`, anything else to `log`.
pub(crate) fn forward_line(line: &str, reports: &Reports, log: &std::sync::Mutex<std::fs::File>) {
    use std::io::Write;
    match line.strip_prefix(crate::protocol::PREFIX).map(serde_json::from_str::<Message>) {
        Some(Ok(message)) => reports(Report::Message(message)),
        _ => {
            let _ = writeln!(log.lock().unwrap(), "{line}");
        }
    }
}
