//! Running the program: what it is told, how it is watched, and what it may not touch.
//!
//! It runs in the snapshot of its sources (the pipeline's tree, holding only the files its key
//! covers), with `$RLMFLOW_STAGE` naming a JSON file of its context (inputs by slot, each
//! artifact's directory, read-only; its output directory, empty; a checkpoint directory that
//! survives a kill; seed, settings, device, threads) and the same as `RLMFLOW_*` variables. Its
//! stderr and its stdout's own lines go to the stage's log; it dies with the stage's process
//! (a timeout or a kill stops both). Writing into an input (its sources included) is found
//! afterwards by the files' sizes and times, and fails the stage.

use std::collections::{BTreeMap, VecDeque};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{Context as _, bail};
use rlmflow_stages::{Context, Device, Progress};
use serde_json::{Map, Value, json};

use crate::ScriptSettings;
use crate::protocol::{self, Message};

/// Lines of stderr an error shows.
const TAIL: usize = 20;

/// What the program reported besides its files.
#[derive(Default)]
pub struct Reported {
    pub metrics: Map<String, Value>,
    pub summary: String,
}

pub fn run(s: &ScriptSettings, ctx: &mut Context) -> anyhow::Result<Reported> {
    let stage = ctx.stage.clone();
    let sources = ctx.optional_input("sources").map(Path::to_path_buf);
    let cwd = sources.clone().unwrap_or_else(|| ctx.output_dir.clone());
    let program = resolve(s, ctx, sources.as_deref())?;
    let work = ctx.output_dir.parent().context("the output directory has a parent")?.to_path_buf();
    std::fs::create_dir_all(&ctx.checkpoint_dir).with_context(|| format!("creating {}", ctx.checkpoint_dir.display()))?;
    let scratch = work.join("scratch");
    std::fs::create_dir_all(&scratch)?;
    let context_file = work.join("stage.json");
    std::fs::write(&context_file, serde_json::to_vec_pretty(&describe(s, ctx))?)?;

    let before = inputs_state(ctx)?;
    let mut command = Command::new(&program);
    command.args(&s.run[1..]).current_dir(&cwd).stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped());
    environment(&mut command, s, ctx, &context_file, &scratch);
    die_with_parent(&mut command);
    let shown = s.run.join(" ");
    let mut child = command.spawn().with_context(|| format!("{stage}: cannot start `{shown}` ({})", program.display()))?;

    let stderr = child.stderr.take().expect("stderr is piped");
    let tail = std::thread::spawn(move || {
        let mut tail = VecDeque::new();
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            eprintln!("{line}");
            if tail.len() == TAIL {
                tail.pop_front();
            }
            tail.push_back(line);
        }
        tail
    });
    let mut reported = Reported::default();
    let mut bar: Option<(u64, Progress)> = None;
    let mut bad_line = None;
    let stdout = child.stdout.take().expect("stdout is piped");
    for (n, line) in BufReader::new(stdout).lines().enumerate() {
        let line = line.with_context(|| format!("{stage}: reading the program's output"))?;
        let Some(text) = line.strip_prefix(protocol::PREFIX) else {
            eprintln!("{line}");
            continue;
        };
        match protocol::parse(text) {
            Ok(Message::Progress { position, length, message }) => {
                if bar.as_ref().is_none_or(|(l, _)| *l != length) {
                    bar = Some((length, ctx.progress(length, &message)));
                }
                let (_, progress) = bar.as_ref().expect("a bar was made");
                progress.set_message(message);
                progress.set_position(position);
            }
            Ok(Message::Event { name, data }) => ctx.event(&name, data),
            Ok(Message::Metrics(metrics)) => reported.metrics.extend(metrics),
            Ok(Message::Summary(summary)) => reported.summary = summary,
            Ok(Message::Live(dir)) => ctx.live(&ctx.checkpoint_dir.join(dir)),
            Err(why) => {
                bad_line = Some(format!("{stage}: line {} of `{shown}`'s output is a malformed protocol message: {why}\n  the line: {line}", n + 1));
                let _ = child.kill();
                break;
            }
        }
    }
    if let Some((_, progress)) = &bar {
        progress.finish();
    }
    let status = child.wait().with_context(|| format!("{stage}: waiting for `{shown}`"))?;
    let tail = tail.join().unwrap_or_default();
    let _ = std::io::stderr().flush();
    if let Some(message) = bad_line {
        bail!("{message}");
    }
    if !status.success() {
        let how = match status.code() {
            Some(code) => format!("exited with status {code}"),
            None => format!("was stopped by a signal ({status})"),
        };
        let tail: Vec<String> = tail.into_iter().collect();
        let tail = if tail.is_empty() {
            "  (it wrote nothing to stderr)".to_owned()
        } else {
            tail.iter().map(|l| format!("  | {l}")).collect::<Vec<_>>().join("\n")
        };
        bail!("{stage}: `{shown}` {how}; the end of its stderr (the stage's log holds it all):\n{tail}");
    }
    let after = inputs_state(ctx)?;
    if let Some(changed) = wrote_into(&before, &after) {
        bail!("{stage}: `{shown}` wrote into its input {changed}: a program writes only into $RLMFLOW_OUTPUT, $RLMFLOW_CHECKPOINT and $TMPDIR");
    }
    let _ = std::fs::remove_dir_all(&scratch);
    let _ = std::fs::remove_file(&context_file);
    Ok(reported)
}

/// The program to start: the environment's interpreter for `python`, a file of the sources, or
/// a program on `PATH`.
fn resolve(s: &ScriptSettings, ctx: &Context, sources: Option<&Path>) -> anyhow::Result<PathBuf> {
    let program = &s.run[0];
    if program == "python" || program == "python3" {
        let mut note = |note: &str| ctx.event("python", json!({ "note": note }));
        let env = match ctx.tracked_file("environment")? {
            Some(lock) => {
                let text = std::fs::read_to_string(&lock).with_context(|| format!("reading the environment lock {}", lock.display()))?;
                rlmflow_python::ensure_lock(&text, "rlmflow", &mut note)
                    .with_context(|| format!("{}: the environment `{}` does not install", ctx.stage, s.environment))?
            }
            None => rlmflow_python::ensure(&mut note)?,
        };
        let minor = env.version.rsplitn(2, '.').last().unwrap_or_default();
        if !s.python.starts_with(&format!("{minor} ")) && rlmflow_python::PYTHON != "python3" {
            bail!("{}: the key was planned for Python {} but the environment's is {}", ctx.stage, s.python, env.version);
        }
        return Ok(env.python);
    }
    if let Some(file) = sources.map(|dir| dir.join(program)).filter(|f| f.is_file()) {
        return Ok(file);
    }
    if program.contains('/') {
        bail!(
            "{}: `{program}` is not a file below the pipeline's directory (a program there must be named by its path from the pipeline file)",
            ctx.stage
        );
    }
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path)
        .map(|dir| dir.join(program))
        .find(|candidate| candidate.is_file())
        .with_context(|| format!("{}: program `{program}` is neither a file of the pipeline's tree nor on PATH", ctx.stage))
}

/// `$RLMFLOW_STAGE`: everything the program is told.
fn describe(s: &ScriptSettings, ctx: &Context) -> Value {
    let inputs: Map<String, Value> = ctx
        .slots()
        .filter(|(slot, _)| !matches!(*slot, "sources" | "environment"))
        .map(|(slot, inputs)| (slot.to_owned(), inputs.iter().map(|i| json!({"label": i.label, "path": i.path})).collect()))
        .collect();
    json!({
        "stage": ctx.stage,
        "inputs": inputs,
        "output": ctx.output_dir,
        "checkpoint": ctx.checkpoint_dir,
        "seed": ctx.seed,
        "settings": s.settings,
        "device": device(s.device).0,
        "threads": ctx.threads,
    })
}

/// What the program sees as its device, and `CUDA_VISIBLE_DEVICES`.
fn device(device: Device) -> (&'static str, String) {
    match device {
        Device::Cuda(n) => ("cuda", n.to_string()),
        _ => ("cpu", String::new()),
    }
}

fn environment(command: &mut Command, s: &ScriptSettings, ctx: &Context, context_file: &Path, scratch: &Path) {
    let (name, visible) = device(s.device);
    let threads = ctx.threads.to_string();
    command
        .env("RLMFLOW_STAGE", context_file)
        .env("RLMFLOW_OUTPUT", &ctx.output_dir)
        .env("RLMFLOW_CHECKPOINT", &ctx.checkpoint_dir)
        .env("RLMFLOW_SEED", ctx.seed.to_string())
        .env("RLMFLOW_DEVICE", name)
        .env("RLMFLOW_THREADS", &threads)
        .env("CUDA_VISIBLE_DEVICES", visible)
        .env("TMPDIR", scratch)
        // A hash seed of its own per process would order a set differently in each run.
        .env("PYTHONHASHSEED", "0")
        // Bytecode written beside a source would change the snapshot the key names.
        .env("PYTHONDONTWRITEBYTECODE", "1");
    for var in ["OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"] {
        command.env(var, &threads);
    }
    for (slot, inputs) in ctx.slots() {
        if let Some(first) = inputs.first() {
            command.env(format!("RLMFLOW_INPUT_{}", slot.to_uppercase().replace('-', "_")), &first.path);
        }
    }
}

/// Each input file's size and modification time, by slot and path.
type State = BTreeMap<(String, PathBuf), (u64, std::time::SystemTime)>;

fn inputs_state(ctx: &Context) -> anyhow::Result<State> {
    let mut state = State::new();
    for (slot, inputs) in ctx.slots() {
        for input in inputs {
            walk(&input.path, &mut |path, meta| {
                state.insert((slot.to_owned(), path.to_path_buf()), (meta.len(), meta.modified().unwrap_or(std::time::UNIX_EPOCH)));
            })?;
        }
    }
    Ok(state)
}

fn walk(dir: &Path, seen: &mut dyn FnMut(&Path, &std::fs::Metadata)) -> anyhow::Result<()> {
    for entry in std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))? {
        let entry = entry?;
        let meta = entry.metadata()?;
        seen(&entry.path(), &meta);
        if meta.is_dir() {
            walk(&entry.path(), seen)?;
        }
    }
    Ok(())
}

/// The first input slot whose files changed, added or went, with the file.
fn wrote_into(before: &State, after: &State) -> Option<String> {
    let changed = after.iter().find(|(k, v)| before.get(*k) != Some(v)).map(|(k, _)| k).or_else(|| before.keys().find(|k| !after.contains_key(*k)));
    changed.map(|(slot, path)| format!("`{slot}` ({})", path.display()))
}

/// The program dies with the stage's process (Linux), so a timeout or a kill leaves nothing
/// computing alone.
fn die_with_parent(command: &mut Command) {
    #[cfg(target_os = "linux")]
    unsafe {
        use std::os::unix::process::CommandExt;
        command.pre_exec(|| {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
}
