//! `rlmflow exec KEY --store DIR`: runs one action. The engine starts it as a child process, so
//! an operator crash cannot take a run down; a remote executor can call it the same way.
//!
//! It talks to its parent through the wire protocol of [`crate::protocol`]; other output goes to
//! the stage's log.

use std::collections::BTreeMap;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::Context as _;
use rlmflow_cache::{ActionRecord, ActionRequest, Digest, Store, hash_tree, now_rfc3339};
use rlmflow_stages::numerics::{PlatformRecord, Target};
use rlmflow_stages::{Context, Device, DynOperator, Input, Outcome, Parsed, Registry, Reporter, SettingError};
use serde_json::Value;

use crate::platform::cuda_present;
use crate::protocol::{EXIT_CORRUPT_INPUT, Message, send};

/// Why an operator failed: its message, and the setting it is about, if any.
#[derive(Debug)]
struct Failure {
    message: String,
    setting: Option<String>,
}

impl std::fmt::Display for Failure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.setting {
            Some(key) => write!(f, "{key}: {}", self.message),
            None => f.write_str(&self.message),
        }
    }
}

impl From<String> for Failure {
    fn from(message: String) -> Failure {
        Failure { message, setting: None }
    }
}

struct StdoutReporter;

impl Reporter for StdoutReporter {
    fn progress(&self, position: u64, length: u64, message: &str) {
        send(&Message::Progress { position, length, message: message.to_owned() });
    }
    fn event(&self, name: &str, data: Value) {
        send(&Message::Event { name: name.to_owned(), data });
    }
    fn live(&self, dir: &std::path::Path) {
        send(&Message::Live { dir: dir.to_path_buf() });
    }
}

/// The binary that runs `op`'s actions: this one, or the worker it names, beside this one.
pub fn executable(op: &dyn DynOperator) -> anyhow::Result<std::path::PathBuf> {
    let exe = std::env::current_exe().context("locating the rlmflow executable")?;
    let Some(worker) = op.worker() else { return Ok(exe) };
    let path = exe.with_file_name(worker);
    if !path.is_file() {
        anyhow::bail!(
            "operator `{}` runs in `{worker}`, which is not beside {} (`cargo xtask build --release` builds both)",
            op.spec().name,
            exe.display()
        );
    }
    Ok(path)
}

/// Runs action `key` from `store`; returns the process exit status.
pub fn exec(registry: &Registry, store: &Path, key: Digest, threads: usize, device: Device) -> anyhow::Result<i32> {
    let store = Store::open_existing(store)?.with_context(|| format!("no rlmflow store at {}", store.display()))?;
    let _shared = store.lock_shared()?;
    let request = store.request(&key)?.with_context(|| format!("the store has no request for action {key}; `rlmflow run` writes it"))?;
    let _lock = match store.try_lock_action(&key)? {
        Some(lock) => lock,
        None => {
            send(&Message::Waiting);
            store.lock_action(&key)?
        }
    };
    let fresh = store.fresh(&key)?.is_some();
    // Into the stage's log: a damaged record read here is a miss, and the action runs again.
    if fresh {
        send(&Message::Reused);
        return Ok(0);
    }
    store.sweep_tmp(Some(&key))?;
    let op = registry.get(&request.preimage.operator).with_context(|| format!("this rlmflow has no operator `{}`", request.preimage.operator))?;
    // Parsed once: the platform check and the operator read the typed settings.
    let settings = match op.settings(request.settings.clone()) {
        Ok(settings) => settings,
        Err(wrong) => return Ok(fail(Failure { message: wrong.message, setting: Some(wrong.key) })),
    };
    let inputs = match inputs(&store, &request)? {
        Ok(inputs) => inputs,
        Err(code) => return Ok(code),
    };
    let work = store.work_dir(&key)?;
    let output_dir = work.join("out");
    let checkpoint_dir = store.checkpoint_dir(&key);
    let (device, platform) = match pin_platform(registry, op, &request, &settings, device) {
        Ok(pinned) => pinned,
        Err(message) => return Ok(fail(message.into())),
    };
    let started = now_rfc3339();
    let clock = Instant::now();
    let dirs = Dirs { output: output_dir.clone(), checkpoint: checkpoint_dir.clone(), responses: store.responses_dir(&request.preimage.operator) };
    let outcome = match run_operator(op, &request, &settings, inputs, dirs, threads, device)? {
        Ok(outcome) => outcome,
        Err(failure) => {
            store.write_failure(&key, &failure.to_string())?;
            clean_checkpoint(&checkpoint_dir);
            return Ok(fail(failure));
        }
    };
    let duration_s = clock.elapsed().as_secs_f64();
    let tree = store.commit_tree(&output_dir)?;
    store.write_record(&ActionRecord {
        key,
        preimage: request.preimage.clone(),
        output: tree.digest,
        files: tree.files,
        bytes: tree.bytes,
        started,
        duration_s,
        metrics: outcome.metrics,
        summary: outcome.summary,
        platform: platform.map(|p| serde_json::to_value(p).expect("a platform record serialises")),
        signatures: Vec::new(),
        pulled: None,
    })?;
    let _ = std::fs::remove_dir_all(&checkpoint_dir);
    let _ = std::fs::remove_dir_all(&work);
    send(&Message::Done { output: tree.digest });
    Ok(0)
}

/// Runs action `key` into `scratch/out` (checkpoints in `scratch/checkpoint`) and reports the
/// output's digest, committing nothing and taking no lock: one attempt of `run
/// --check-determinism`.
pub fn exec_scratch(registry: &Registry, store: &Path, key: Digest, threads: usize, device: Device, scratch: &Path) -> anyhow::Result<i32> {
    let store = Store::open_existing(store)?.with_context(|| format!("no rlmflow store at {}", store.display()))?;
    let _shared = store.lock_shared()?;
    let request = store.request(&key)?.with_context(|| format!("the store has no request for action {key}"))?;
    let op = registry.get(&request.preimage.operator).with_context(|| format!("this rlmflow has no operator `{}`", request.preimage.operator))?;
    // Parsed once: the platform check and the operator read the typed settings.
    let settings = match op.settings(request.settings.clone()) {
        Ok(settings) => settings,
        Err(wrong) => return Ok(fail(Failure { message: wrong.message, setting: Some(wrong.key) })),
    };
    let inputs = match inputs(&store, &request)? {
        Ok(inputs) => inputs,
        Err(code) => return Ok(code),
    };
    let device = match pin_platform(registry, op, &request, &settings, device) {
        Ok((device, _)) => device,
        Err(message) => return Ok(fail(message.into())),
    };
    let output_dir = scratch.join("out");
    let dirs =
        Dirs { output: output_dir.clone(), checkpoint: scratch.join("checkpoint"), responses: store.responses_dir(&request.preimage.operator) };
    match run_operator(op, &request, &settings, inputs, dirs, threads, device)? {
        Ok(_) => {
            send(&Message::Done { output: hash_tree(&output_dir)?.digest });
            Ok(0)
        }
        Err(failure) => Ok(fail(failure)),
    }
}

/// The action's inputs by slot, each re-hashed first; `Err(exit status)` when one is damaged or
/// missing (quarantined and reported, so the engine recomputes its producer).
fn inputs(store: &Store, request: &ActionRequest) -> anyhow::Result<Result<BTreeMap<String, Vec<Input>>, i32>> {
    let mut inputs: BTreeMap<String, Vec<Input>> = BTreeMap::new();
    for input in &request.preimage.inputs {
        let damaged = if store.has_object(&input.digest) { store.check_object(&input.digest)? } else { None };
        if let Some(corruption) = damaged {
            store.quarantine(&input.digest)?;
            send(&Message::CorruptInput { digest: input.digest, files: corruption.files });
            return Ok(Err(EXIT_CORRUPT_INPUT));
        }
        if !store.has_object(&input.digest) {
            send(&Message::CorruptInput { digest: input.digest, files: Vec::new() });
            return Ok(Err(EXIT_CORRUPT_INPUT));
        }
        let path = store.object_dir(&input.digest);
        // A single input's label is not in the preimage; the request names it for messages.
        let label = match (input.label.is_empty(), request.input_labels.get(&input.slot)) {
            (true, Some(label)) => label.clone(),
            _ => input.label.clone(),
        };
        let mut one = Input::new(label, path);
        if let Some(id) = request.input_instances.get(&one.label) {
            one.instance = serde_json::from_value(id.clone()).with_context(|| format!("the request's instance of input `{}`", one.label))?;
        }
        inputs.entry(input.slot.clone()).or_default().push(one);
    }
    Ok(Ok(inputs))
}

/// For an operator whose bytes depend on its kernels: checks that this machine computes the
/// numeric platform class its key was planned for, pins this process's kernel choices (whatever
/// the caller's environment says), and returns the device it computes on with the platform
/// record for its provenance. Other operators run as asked, with no record. `Err` says why the
/// action must not run here.
fn pin_platform(
    registry: &Registry,
    op: &dyn DynOperator,
    request: &ActionRequest,
    settings: &Parsed,
    device: Device,
) -> Result<(Device, Option<PlatformRecord>), String> {
    let resources = op.resources(settings);
    let Some(kernels) = resources.kernels else { return Ok((device, None)) };
    let target = Target::of(kernels.device, device, cuda_present());
    // A model operator computes with its own `threads` setting (part of its key).
    let record = PlatformRecord::new(kernels.numerics, target, resources.threads, registry.libraries());
    if let Some(planned) = request.preimage.platform.as_ref().filter(|p| **p != record.class) {
        return Err(format!(
            "this action's key is for numeric platform `{planned}`, and this machine computes `{}`: it would store other bytes under the key. Run it on a machine of that class, or plan the run here",
            record.class
        ));
    }
    rlmflow_stages::numerics::apply(kernels.numerics, &record.cpu, target);
    registry.pin_kernels().map_err(|e| format!("{}: pinning the kernels: {e:#}", request.stage))?;
    Ok((target.device(), Some(record)))
}

/// Where one attempt at an action writes: its output, its checkpoints, and the store's
/// directory of its operator's outside answers.
struct Dirs {
    output: PathBuf,
    checkpoint: PathBuf,
    responses: PathBuf,
}

/// Runs the operator with its output and checkpoint directories; `Ok(Err(failure))` when it
/// fails or panics.
fn run_operator(
    op: &dyn DynOperator,
    request: &ActionRequest,
    settings: &Parsed,
    inputs: BTreeMap<String, Vec<Input>>,
    dirs: Dirs,
    threads: usize,
    device: Device,
) -> anyhow::Result<Result<Outcome, Failure>> {
    std::fs::create_dir_all(&dirs.output)?;
    std::fs::create_dir_all(&dirs.checkpoint)?;
    let mut ctx = Context::new(
        request.stage.clone(),
        inputs,
        dirs.output,
        dirs.checkpoint,
        request.preimage.seed,
        threads.max(1),
        device,
        Arc::new(StdoutReporter),
    );
    ctx.responses = Some(dirs.responses);
    Ok(match catch_unwind(AssertUnwindSafe(|| op.run(settings, &mut ctx))) {
        Ok(Ok(outcome)) => Ok(outcome),
        Ok(Err(e)) => Err(match e.chain().find_map(|cause| cause.downcast_ref::<SettingError>()) {
            Some(wrong) => Failure { message: wrong.message.clone(), setting: Some(wrong.key.clone()) },
            None => format!("{e:#}").into(),
        }),
        Err(panic) => {
            let text = panic
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "unknown panic".into());
            Err(format!("operator `{}` panicked: {text}", request.preimage.operator).into())
        }
    })
}

fn fail(failure: Failure) -> i32 {
    eprintln!("error: {failure}");
    send(&Message::Failed { message: failure.message, setting: failure.setting });
    1
}

/// After a failed attempt: removes what no rerun resumes from (files cut off mid-write, `.part`)
/// and the checkpoint folder if that leaves it empty, so only a resumable checkpoint stays.
fn clean_checkpoint(dir: &Path) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    for entry in entries.flatten() {
        if entry.path().extension().is_some_and(|e| e == "part") {
            let _ = std::fs::remove_file(entry.path());
        }
    }
    let _ = std::fs::remove_dir(dir); // only if empty
}
