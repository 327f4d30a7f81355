//! What an operator is given when it runs.

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::Arc;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use serde_json::Value;

/// A device, as a torch operator's `device` setting and the run's `--device` name it: `auto`,
/// `cpu`, `cuda` (device 0) or `cuda:N`, parsed once here. `auto` leaves the choice to the
/// operator: the engine's GPU, else CUDA when libtorch has one, else the CPU.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum Device {
    Auto,
    #[default]
    Cpu,
    Cuda(usize),
}

impl FromStr for Device {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> anyhow::Result<Device> {
        match s {
            "auto" => Ok(Device::Auto),
            "cpu" => Ok(Device::Cpu),
            "cuda" => Ok(Device::Cuda(0)),
            _ => match s.strip_prefix("cuda:").map(str::parse) {
                Some(Ok(n)) => Ok(Device::Cuda(n)),
                _ => bail!("unknown device `{s}`; valid: cpu, cuda, cuda:N, auto"),
            },
        }
    }
}

impl TryFrom<String> for Device {
    type Error = anyhow::Error;
    fn try_from(s: String) -> anyhow::Result<Device> {
        s.parse()
    }
}

impl From<Device> for String {
    fn from(d: Device) -> String {
        d.to_string()
    }
}

impl fmt::Display for Device {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Device::Auto => write!(f, "auto"),
            Device::Cpu => write!(f, "cpu"),
            Device::Cuda(n) => write!(f, "cuda:{n}"),
        }
    }
}

/// Receives an operator's progress and events; the engine decides where they go (a progress bar
/// in the parent process, the run's JSON event log).
pub trait Reporter: Send + Sync {
    fn progress(&self, position: u64, length: u64, message: &str);
    fn event(&self, name: &str, data: Value);
    /// `dir` shows the action's work as it goes ([`Context::live`]).
    fn live(&self, dir: &Path);
}

/// A reporter that drops everything (unit tests of operators).
pub struct Silent;
impl Reporter for Silent {
    fn progress(&self, _: u64, _: u64, _: &str) {}
    fn event(&self, _: &str, _: Value) {}
    fn live(&self, _: &Path) {}
}

/// One upstream artifact: the producing instance, by label (e.g. `pretrain[alpha4]`, for
/// messages) and as data, and its directory. Artifact directories are read-only.
#[derive(Clone, Debug)]
pub struct Input {
    pub label: String,
    pub instance: InstanceId,
    pub path: PathBuf,
}

impl Input {
    /// An input whose producer is known by label only (an operator run on its own): the label
    /// is its stage, with no variant.
    pub fn new(label: impl Into<String>, path: impl Into<PathBuf>) -> Input {
        let label = label.into();
        Input { instance: InstanceId { stage: label.clone(), ..Default::default() }, label, path: path.into() }
    }
}

/// A stage instance as data: its stage, per variant dimension (the stage that declared the
/// variants) the variant it takes, and its seed where it runs per seed.
#[derive(Clone, Debug, Default, PartialEq, Eq, PartialOrd, Ord, serde::Serialize, serde::Deserialize)]
pub struct InstanceId {
    pub stage: String,
    pub variant: BTreeMap<String, String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
}

/// The operator's view of one run of one stage instance.
pub struct Context {
    /// The stage instance, e.g. `pretrain[alpha4]`, for messages.
    pub stage: String,
    inputs: BTreeMap<String, Vec<Input>>,
    /// Empty on entry; everything written here becomes the stage's output artifact.
    pub output_dir: PathBuf,
    /// Survives a crash or kill of this action and is handed to the next attempt of the same
    /// action key; removed once the action commits.
    pub checkpoint_dir: PathBuf,
    pub seed: u64,
    /// The store's directory for this operator's answers from outside services (an LLM
    /// endpoint), kept across actions and runs; `None` when it runs outside a store.
    pub responses: Option<PathBuf>,
    /// Threads the scheduler granted; use no more.
    pub threads: usize,
    pub device: Device,
    reporter: Arc<dyn Reporter>,
}

impl Context {
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        stage: String,
        inputs: BTreeMap<String, Vec<Input>>,
        output_dir: PathBuf,
        checkpoint_dir: PathBuf,
        seed: u64,
        threads: usize,
        device: Device,
        reporter: Arc<dyn Reporter>,
    ) -> Context {
        Context { stage, inputs, output_dir, checkpoint_dir, seed, responses: None, threads, device, reporter }
    }

    /// A context for running an operator on its own (tests, benchmarks): one artifact per named
    /// input slot, on the CPU, reporting nothing.
    pub fn standalone(stage: &str, inputs: &[(&str, &Path)], output_dir: &Path, checkpoint_dir: &Path, seed: u64, threads: usize) -> Context {
        let inputs = inputs.iter().map(|(slot, path)| (slot.to_string(), vec![Input::new(*slot, *path)])).collect();
        Context::new(stage.into(), inputs, output_dir.into(), checkpoint_dir.into(), seed, threads, Device::Cpu, Arc::new(Silent))
    }

    /// The directory of the single artifact bound to `slot`.
    pub fn input(&self, slot: &str) -> anyhow::Result<&Path> {
        self.optional_input(slot).with_context(|| format!("stage {} has no `{slot}` input", self.stage))
    }

    /// The producing instance of the single artifact bound to `slot` (e.g. `pretrain[alpha4]`),
    /// for messages only: it is not part of the action's key, so it never goes into the output.
    pub fn input_label(&self, slot: &str) -> Option<&str> {
        self.inputs.get(slot).and_then(|v| v.first()).map(|i| i.label.as_str())
    }

    pub fn optional_input(&self, slot: &str) -> Option<&Path> {
        self.inputs.get(slot).and_then(|v| v.first()).map(|i| i.path.as_path())
    }

    /// The file a tracked setting (`Settings::TRACKED`) names, in its snapshot (a file is
    /// tracked as a tree of one); `None` where the setting is empty.
    pub fn tracked_file(&self, slot: &str) -> anyhow::Result<Option<PathBuf>> {
        let Some(dir) = self.optional_input(slot) else { return Ok(None) };
        let entries: Vec<PathBuf> =
            std::fs::read_dir(dir).and_then(|d| d.map(|e| e.map(|e| e.path())).collect()).with_context(|| format!("reading {}", dir.display()))?;
        match &entries[..] {
            [file] if file.is_file() => Ok(Some(file.clone())),
            _ => anyhow::bail!("`{slot}` must name a file, but its snapshot ({}) holds {} entries", dir.display(), entries.len()),
        }
    }

    /// Every bound input slot with its artifacts, by slot name (tracked paths among them).
    pub fn slots(&self) -> impl Iterator<Item = (&str, &[Input])> {
        self.inputs.iter().map(|(slot, inputs)| (slot.as_str(), inputs.as_slice()))
    }

    /// Every artifact gathered into `slot` (for slots of arity `All`), in a stable order.
    pub fn gathered(&self, slot: &str) -> &[Input] {
        self.inputs.get(slot).map(Vec::as_slice).unwrap_or(&[])
    }

    /// A progress handle for `length` units of work.
    pub fn progress(&self, length: u64, message: &str) -> Progress {
        Progress { reporter: self.reporter.clone(), length, message: Mutex::new(message.to_owned()), state: Mutex::new((0, None)) }
    }

    /// Records a structured event in the run's JSON event log.
    pub fn event(&self, name: &str, data: Value) {
        self.reporter.event(name, data);
    }

    /// Says that `dir` shows this action's work as it goes (a training's curves in its
    /// checkpoint directory): the engine links the stage's results entry there until the
    /// output is committed.
    pub fn live(&self, dir: &Path) {
        self.reporter.live(dir);
    }
}

/// Reports the position of one piece of long work, at most ten times a second.
pub struct Progress {
    reporter: Arc<dyn Reporter>,
    length: u64,
    message: Mutex<String>,
    /// Position, and when it was last reported.
    state: Mutex<(u64, Option<Instant>)>,
}

impl Progress {
    const INTERVAL: Duration = Duration::from_millis(100);

    pub fn inc(&self, delta: u64) {
        let mut state = self.state.lock().unwrap();
        state.0 += delta;
        self.maybe_report(&mut state, false);
    }

    pub fn set_position(&self, position: u64) {
        let mut state = self.state.lock().unwrap();
        state.0 = position;
        self.maybe_report(&mut state, false);
    }

    /// Replaces the message shown beside the position (running totals, say).
    pub fn set_message(&self, message: String) {
        *self.message.lock().unwrap() = message;
    }

    pub fn finish(&self) {
        let mut state = self.state.lock().unwrap();
        self.maybe_report(&mut state, true);
    }

    fn maybe_report(&self, state: &mut (u64, Option<Instant>), force: bool) {
        let now = Instant::now();
        if force || state.1.is_none_or(|last| now - last >= Self::INTERVAL) {
            state.1 = Some(now);
            self.reporter.progress(state.0, self.length, &self.message.lock().unwrap());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn devices_parse_and_print() {
        for s in ["cpu", "cuda:0", "cuda:3"] {
            assert_eq!(s.parse::<Device>().unwrap().to_string(), s);
        }
        assert_eq!("cuda".parse::<Device>().unwrap(), Device::Cuda(0));
        assert!("tpu".parse::<Device>().unwrap_err().to_string().contains("valid: cpu"));
    }

    /// Records every (position, message) reported.
    struct Count(Mutex<Vec<(u64, String)>>);
    impl Reporter for Count {
        fn progress(&self, position: u64, _: u64, message: &str) {
            self.0.lock().unwrap().push((position, message.to_owned()));
        }
        fn event(&self, _: &str, _: Value) {}
        fn live(&self, _: &Path) {}
    }

    #[test]
    fn progress_is_throttled_but_finish_always_reports() {
        let reporter = Arc::new(Count(Mutex::new(Vec::new())));
        let ctx = Context::new("s".into(), BTreeMap::new(), "/o".into(), "/c".into(), 0, 1, Device::Cpu, reporter.clone());
        let p = ctx.progress(1000, "work");
        for _ in 0..1000 {
            p.inc(1);
        }
        p.finish();
        let seen: Vec<u64> = reporter.0.lock().unwrap().iter().map(|(p, _)| *p).collect();
        assert_eq!(seen.first(), Some(&1));
        assert_eq!(seen.last(), Some(&1000));
        assert!(seen.len() < 10, "reported {} times", seen.len());
    }

    #[test]
    fn a_new_message_shows_from_the_next_report() {
        let reporter = Arc::new(Count(Mutex::new(Vec::new())));
        let ctx = Context::new("s".into(), BTreeMap::new(), "/o".into(), "/c".into(), 0, 1, Device::Cpu, reporter.clone());
        let p = ctx.progress(10, "frames");
        p.inc(1);
        p.set_message("frames, 3 requests".into());
        p.finish();
        assert_eq!(*reporter.0.lock().unwrap(), [(1, "frames".to_string()), (1, "frames, 3 requests".to_string())]);
    }
}
