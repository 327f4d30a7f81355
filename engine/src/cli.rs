//! The `rlmflow` command line. A binary builds its operator registry and calls [`main`].

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context as _, bail};
use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};
use rlmflow_cache::{Digest, Store, canonical_json};
use rlmflow_stages::{Device, ItemCount, Registry};

use crate::config::{self, ConfigError, Pipeline};
use crate::plan::{Freshness, assess};
use crate::preflight::{Preflight, planned};
use crate::run::{RunOptions, run};
use crate::ui::{Ui, print_status, print_store_warnings};

#[derive(Parser)]
#[command(name = "rlmflow", version, about = "Declarative data-and-training pipelines for radar-language research")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(clap::Args)]
struct StoreArg {
    /// The store directory; default: `[pipeline] cache`, beside the pipeline file.
    #[arg(long, value_name = "DIR")]
    cache: Option<PathBuf>,
}

/// `--set STAGE.KEY=VALUE`, repeatable.
#[derive(clap::Args)]
struct SetArg {
    /// Override a setting of the pipeline file (repeatable): STAGE.KEY=VALUE, the value in TOML,
    /// dotted keys into tables and variants (pretrain.alpha=2,
    /// pretrain.variants.alpha4.epochs=20); checked exactly as the file is.
    #[arg(long = "set", value_name = "STAGE.KEY=VALUE")]
    set: Vec<String>,
    /// As --set, and may make a variant the file does not declare
    /// (pretrain.variants.alpha8.alpha=8.0); --set refuses one, naming the nearest.
    #[arg(long = "set-new", value_name = "STAGE.variants.NAME.KEY=VALUE")]
    set_new: Vec<String>,
}

#[derive(clap::Args)]
struct RemoteArg {
    /// The remote cache, overriding `[pipeline] remote`: s3://bucket/prefix (the standard AWS_*
    /// variables, AWS_ENDPOINT_URL for a non-AWS server), https://host/path (WebDAV) or
    /// file:///path.
    #[arg(long, value_name = "URL")]
    remote: Option<String>,
    /// Upload computed results to the remote cache (`[pipeline] remote_push = true`): for
    /// trusted writers only, such as CI on the main branch.
    #[arg(long)]
    push: bool,
}

impl RemoteArg {
    /// The pipeline's remote settings with the flags over them; `None` without a URL. A bad
    /// `--remote` is a usage error (exit 2), before anything runs.
    fn settings(&self, p: &Pipeline) -> anyhow::Result<Option<config::RemoteSettings>> {
        let mut settings = p.remote.clone();
        if let Some(url) = &self.remote {
            let resolved = config::resolve_remote(url, Path::new("."));
            rlmflow_remote::check_url(&resolved).map_err(|problem| UsageError(format!("--remote: {problem}")))?;
            settings.url = Some(resolved);
        }
        settings.push |= self.push;
        Ok(settings.url.is_some().then_some(settings))
    }
}

/// What `push` and `pull` move: a pipeline's results, or those of `--only` stages.
#[derive(clap::Args)]
struct Transfer {
    pipeline: PathBuf,
    #[arg(long, value_name = "STAGE")]
    only: Vec<String>,
    #[command(flatten)]
    store: StoreArg,
    #[command(flatten)]
    remote: RemoteArg,
}

#[derive(Subcommand)]
enum Command {
    /// Run a pipeline, reusing every stage whose inputs and settings are unchanged.
    Run {
        pipeline: PathBuf,
        /// Print the plan (cached / will run / pending, with reasons) and change nothing.
        #[arg(long)]
        dry_run: bool,
        /// Run only these stages and what they need (repeatable).
        #[arg(long, value_name = "STAGE")]
        only: Vec<String>,
        /// CPU threads shared by concurrently running stages; default: all cores (with
        /// HyperQueue, its workers times their cores).
        #[arg(long, short)]
        jobs: Option<usize>,
        /// Where actions run, overriding `[pipeline] executor`: local or hyperqueue.
        #[arg(long, value_name = "EXECUTOR")]
        executor: Option<String>,
        /// Print the JSON event log on stdout instead of progress.
        #[arg(long)]
        json: bool,
        /// Device for operators that use one: cpu, cuda, cuda:N.
        #[arg(long, default_value = "cpu")]
        device: Device,
        /// Re-hash every reused output before using it; a damaged one is quarantined and
        /// recomputed (by default only stages that run re-hash their inputs; `verify` checks all).
        #[arg(long)]
        verify_inputs: bool,
        /// Run what this stage needs, then run each of its actions twice in fresh processes
        /// with different thread counts, the second asking every numeric library for other
        /// kernels, into scratch, and compare the outputs byte for byte (repeatable). Exits 1 and names the first differing file if they differ.
        #[arg(long, value_name = "STAGE")]
        check_determinism: Vec<String>,
        #[command(flatten)]
        set: SetArg,
        #[command(flatten)]
        store: StoreArg,
        #[command(flatten)]
        remote: RemoteArg,
    },
    /// Show each stage as cached, will run (and why) or pending, and which ones the remote cache
    /// holds.
    Status {
        pipeline: PathBuf,
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        set: SetArg,
        #[command(flatten)]
        store: StoreArg,
        #[command(flatten)]
        remote: RemoteArg,
    },
    /// Draw the plan: each stage instance coloured by its state (cached, will run, will be pulled
    /// from the remote cache, pending) with the reason in its tooltip, and the artifacts between
    /// them; Mermaid (GitHub renders it) or Graphviz DOT.
    Dag {
        pipeline: PathBuf,
        #[arg(long, value_enum, default_value = "mermaid")]
        format: crate::dag::Format,
        #[command(flatten)]
        set: SetArg,
        #[command(flatten)]
        store: StoreArg,
        #[command(flatten)]
        remote: RemoteArg,
    },
    /// Upload every cached result of a pipeline (or of `--only` stages) to the remote cache.
    Push(Transfer),
    /// Download from the remote cache every result of a pipeline (or of `--only` stages and
    /// what they need) that the local store lacks and the remote holds.
    Pull(Transfer),
    /// Show what changed in a stage's preimage since its last run.
    Explain {
        pipeline: PathBuf,
        stage: String,
        #[command(flatten)]
        set: SetArg,
        #[command(flatten)]
        store: StoreArg,
    },
    /// List a pipeline's runs, newest first: when, the git commit (and whether the tree was
    /// dirty), overrides, how many stages ran, were reused or pulled, and the headline of each
    /// stage it computed.
    Runs {
        pipeline: PathBuf,
        /// The headline of every stage instance, reused ones too.
        #[arg(long)]
        all: bool,
        /// At most N runs.
        #[arg(long, value_name = "N")]
        last: Option<usize>,
        /// One JSON object per run and line: its plan, how each instance ended, the counts,
        /// whether it finished.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        store: StoreArg,
    },
    /// Settings and metrics side by side: two runs (default: the pipeline's last two; one RUN:
    /// that run against the latest), or with --variants the variants of one run, seeds pooled
    /// into mean ± sd. Shows only what differs unless --all.
    Compare {
        pipeline: PathBuf,
        /// Run ids, or unique beginnings of them (`rlmflow runs` lists them).
        #[arg(value_name = "RUN", num_args = 0..=2)]
        runs: Vec<String>,
        /// Compare the variants of each stage of one run (default: the latest).
        #[arg(long)]
        variants: bool,
        /// Every instance, setting and metric, not only those that differ.
        #[arg(long)]
        all: bool,
        #[arg(long, conflicts_with = "markdown")]
        json: bool,
        /// Markdown tables, for pasting into a note or an issue.
        #[arg(long)]
        markdown: bool,
        #[command(flatten)]
        store: StoreArg,
    },
    /// Show where a stage's outputs, record and metrics are.
    Show {
        pipeline: PathBuf,
        stage: String,
        #[command(flatten)]
        store: StoreArg,
    },
    /// Remove what no root reaches: runs beyond the newest N, and the actions and objects only they used.
    Gc {
        /// A pipeline whose store to collect (else --cache, else ./.rlmflow).
        pipeline: Option<PathBuf>,
        #[arg(long)]
        dry_run: bool,
        #[arg(long, default_value_t = 10)]
        keep_runs: usize,
        /// Also remove the stored answers of outside services (an `llm` stage then asks its
        /// endpoint again).
        #[arg(long)]
        responses: bool,
        #[command(flatten)]
        store: StoreArg,
    },
    /// Re-hash every object; quarantine and report the damaged ones.
    Verify {
        pipeline: Option<PathBuf>,
        /// Also recompute cached actions in fresh processes and compare their outputs with their
        /// records' (needs the pipeline): an audit of a cache this store pulled from.
        #[arg(long)]
        recompute: bool,
        /// With --recompute: only these stages (repeatable).
        #[arg(long, value_name = "STAGE")]
        only: Vec<String>,
        /// With --recompute: at most N actions, chosen by key.
        #[arg(long, value_name = "N")]
        sample: Option<usize>,
        /// Also compare this store with another machine's digests file (`rlmflow digests`): each
        /// of its keys that this store holds must have the same output. Exits 1 if one differs
        /// or none is here to compare.
        #[arg(long, value_name = "FILE")]
        against: Option<PathBuf>,
        #[command(flatten)]
        store: StoreArg,
    },
    /// Print every instance's action key and output digest, with this machine's CPU and numeric
    /// classes, for another machine to compare with (`rlmflow verify --against FILE`). Every
    /// instance must be computed in the store.
    Digests {
        pipeline: PathBuf,
        #[command(flatten)]
        set: SetArg,
        #[command(flatten)]
        store: StoreArg,
    },
    /// Pin the current results of a pipeline under a name, so gc keeps them.
    Pin {
        pipeline: PathBuf,
        name: String,
        #[command(flatten)]
        store: StoreArg,
    },
    /// List stage kinds and operators with their default settings, and the settings that cannot
    /// change a result (left out of the key).
    Operators {
        /// One JSON object per line, per operator: name, kind, version, summary, inputs, produces,
        /// merge (the operator joining its shards, or null), defaults, non_result, tracked.
        #[arg(long)]
        json: bool,
    },
    /// Make an ed25519 key pair for signing remote cache records: writes NAME.secret (for the
    /// pusher's RLMFLOW_SIGNING_KEY; keep it secret) and NAME.public, and prints the public key
    /// for readers' `remote_trusted_keys`.
    Key {
        #[command(subcommand)]
        action: KeyAction,
    },
    /// Create the managed Python environment (pinned packages from the lock compiled into this
    /// binary) if it is missing, and print where it is. Stages that need it also create it on
    /// first use.
    Setup,
    /// Run one action from the store (the engine's child-process entry point).
    #[command(hide = true)]
    Exec {
        key: Digest,
        /// The store (with `--remote`, the worker's own; none: a temporary one).
        #[arg(long)]
        store: Option<PathBuf>,
        #[arg(long, default_value_t = 1)]
        threads: usize,
        #[arg(long, default_value = "cpu")]
        device: Device,
        /// Run into this directory without committing (`run --check-determinism`).
        #[arg(long, value_name = "DIR")]
        scratch: Option<PathBuf>,
        /// Run as a cluster task with a store of its own: the request on stdin, inputs fetched
        /// from this remote cache, the result and a transcript pushed to it.
        #[arg(long, value_name = "URL", requires = "transcript", conflicts_with = "scratch")]
        remote: Option<String>,
        #[arg(long, value_name = "SECONDS", default_value_t = 10.0)]
        remote_timeout: f64,
        /// Where under the remote's `runs/` the task's transcript goes.
        #[arg(long, value_name = "NAME")]
        transcript: Option<String>,
        /// Upload the result even over an object of the same digest (the remote's copy is corrupt).
        #[arg(long)]
        replace: bool,
    },
}

#[derive(clap::Subcommand)]
enum KeyAction {
    /// A new key pair named NAME (letters, digits, `-`, `_`, `.`).
    Generate {
        name: String,
        /// Where to write NAME.secret and NAME.public.
        #[arg(long, default_value = ".")]
        dir: PathBuf,
    },
}

/// A command-line argument that cannot work (exit 2, like a config error).
#[derive(Debug)]
struct UsageError(String);

impl std::fmt::Display for UsageError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for UsageError {}

/// The remote `settings` name; one that cannot be used (a bad URL or endpoint, a bucket that
/// does not exist) is a usage error (exit 2).
fn open_remote(settings: &config::RemoteSettings) -> anyhow::Result<rlmflow_remote::Remote> {
    settings.open().map_err(|e| UsageError(format!("{e:#}")).into())
}

/// A command a binary adds beside the engine's own, such as `rlmflow parse` (the caption
/// parser's: the engine knows no machine learning).
pub struct ExtraCommand {
    /// Its name, help and arguments.
    pub command: clap::Command,
    pub run: fn(&clap::ArgMatches) -> anyhow::Result<ExitCode>,
}

/// The command line of a binary with `registry`'s operators and `extra` commands. Call it first
/// thing in `main`.
pub fn main(registry: Registry, extra: &[ExtraCommand]) -> ExitCode {
    #[cfg(feature = "python")]
    rlmflow_python::embed::pin_home();
    let matches = extra.iter().fold(Cli::command(), |cli, e| cli.subcommand(e.command.clone())).get_matches();
    let outcome = match matches.subcommand().and_then(|(name, args)| Some((extra.iter().find(|e| e.command.get_name() == name)?, args))) {
        Some((command, args)) => (command.run)(args),
        None => Cli::from_arg_matches(&matches).map_err(|e| -> anyhow::Error { e.exit() }).and_then(|cli| dispatch(cli.command, &registry)),
    };
    match outcome {
        Ok(code) => code,
        Err(e) => {
            if let Some(usage) = e.downcast_ref::<UsageError>() {
                eprintln!("error: {}", usage.0);
                return ExitCode::from(2);
            }
            if let Some(config) = e.downcast_ref::<ConfigError>() {
                eprintln!("{config}");
                let n = config.diagnostics.len();
                eprintln!(
                    "error: {} in {}; nothing was run",
                    if n == 1 { "1 problem".into() } else { format!("{n} problems") },
                    config.file.display()
                );
                return ExitCode::from(2);
            }
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// Downloads the selected instances' results the local store lacks, providers first: a
/// consumer's key is known once its inputs' outputs are. Returns the results and bytes pulled.
fn pull(
    plan: &crate::plan::Plan,
    registry: &Registry,
    store: &Store,
    remote: &rlmflow_remote::Remote,
    selected: &[bool],
) -> anyhow::Result<(usize, u64)> {
    let mut outputs: Vec<Option<Digest>> = vec![None; plan.instances.len()];
    let (mut pulled, mut bytes) = (0, 0);
    let ui = Ui::new(false);
    for (i, inst) in plan.instances.iter().enumerate() {
        let Some(key) = plan.preimage(i, registry, &outputs).map(|p| p.key()) else { continue };
        if let Some(record) = store.fresh(&key)? {
            outputs[i] = Some(record.output);
            continue;
        }
        if !selected[i] {
            continue;
        }
        let produces = plan.pipeline.stages[inst.stage].kind.produces;
        let mut bar = ui.transfer(&inst.label, "pulling");
        let found = remote.pull(store, &key, &|dir| registry.catalog.check_artifact(produces, dir), &mut |done, total| bar.moved(done, total))?;
        drop(bar);
        match found {
            rlmflow_remote::Pulled::Hit { record, bytes: b, .. } => {
                println!("  pulled   {}  {:.1} MB", inst.label, b as f64 / 1e6);
                outputs[i] = Some(record.output);
                pulled += 1;
                bytes += b;
            }
            rlmflow_remote::Pulled::Miss => println!("  missing  {}", inst.label),
            rlmflow_remote::Pulled::Corrupt { why } => println!("  corrupt  {}  the remote's copy is not used: {why}", inst.label),
            rlmflow_remote::Pulled::Untrusted { why } => println!("  untrusted {}  the remote's record is not used: {why}", inst.label),
        }
        if let Some(why) = remote.down() {
            bail!("remote cache {}: {why}", remote.url());
        }
    }
    Ok((pulled, bytes))
}

fn store_root(pipeline: &Pipeline, arg: &StoreArg) -> PathBuf {
    arg.cache.clone().unwrap_or_else(|| pipeline.cache.clone())
}

/// The store `pipeline` has run into; an error saying `nothing` (what there is not to do) where
/// it has not run yet.
fn ran_store(pipeline: &Pipeline, arg: &StoreArg, nothing: &str) -> anyhow::Result<Store> {
    Store::open_existing(&store_root(pipeline, arg))?.with_context(|| format!("{} has not run yet; {nothing}", pipeline.file.display()))
}

fn dispatch(command: Command, registry: &Registry) -> anyhow::Result<ExitCode> {
    if matches!(
        command,
        Command::Operators { .. }
            | Command::Status { .. }
            | Command::Digests { .. }
            | Command::Dag { .. }
            | Command::Explain { .. }
            | Command::Show { .. }
            | Command::Runs { .. }
            | Command::Compare { .. }
    ) {
        // These only read and print: a reader that stops early (`| head`) ends them quietly, as
        // it ends `ls`, where a failed write would panic. The others start processes or write
        // the store, and keep Rust's default (a closed pipe is an error where it is written).
        // SAFETY: before any thread is started; SIG_DFL is a valid disposition for SIGPIPE.
        unsafe { libc::signal(libc::SIGPIPE, libc::SIG_DFL) };
    }
    match command {
        Command::Run { pipeline, dry_run, only, jobs, executor, json, device, verify_inputs, check_determinism, set, store, remote } => {
            let mut p = config::load_with(&pipeline, &set.set, &set.set_new, registry)?;
            if let Some(name) = executor {
                p.executor = config::Executor::parse(&name)
                    .with_context(|| format!("unknown executor `{name}` for --executor; valid: {}", config::Executor::NAMES.join(", ")))?;
            }
            let root = store_root(&p, &store);
            let pre = Preflight::new(&p, registry, &root, device, &only)?;
            if dry_run {
                print_status(&pre.plan, &pre.states, &pre.selected, &pre.fits, None, json);
                print_store_warnings(pre.store.as_ref());
                pre.refuse_oversized()?;
                return Ok(ExitCode::SUCCESS);
            }
            let jobs = jobs
                .unwrap_or_else(|| match p.executor {
                    config::Executor::Local => std::thread::available_parallelism().map_or(1, |n| n.get()),
                    config::Executor::HyperQueue => p.hyperqueue.workers * p.hyperqueue.cores(),
                })
                .max(1);
            pre.refuse_cuda_stages(registry, device)?;
            pre.refuse_oversized()?;
            let (plan, selected) = (pre.plan, pre.selected);
            let opts = RunOptions { jobs, json, device, verify_inputs, remote: remote.settings(&p)? };
            // A pushing run that cannot sign stops before anything runs, as `push` does.
            if let Some(settings) = &opts.remote {
                settings.signing_key().map_err(|e| UsageError(format!("{e:#}")))?;
            }
            let store = Store::open(&root)?;
            if !check_determinism.is_empty() {
                let same = crate::determinism::check(&plan, registry, &store, &check_determinism, &opts)?;
                print_store_warnings(Some(&store));
                return Ok(if same { ExitCode::SUCCESS } else { ExitCode::FAILURE });
            }
            let summary = run(&plan, registry, &store, &selected, &opts)?;
            print_store_warnings(Some(&store));
            Ok(if summary.failed > 0 { ExitCode::FAILURE } else { ExitCode::SUCCESS })
        }
        Command::Status { pipeline, json, set, store, remote } => {
            let p = config::load_with(&pipeline, &set.set, &set.set_new, registry)?;
            let pre = Preflight::new(&p, registry, &store_root(&p, &store), Device::Cpu, &[])?;
            let remote = remote.settings(&p)?.map(|r| open_remote(&r)).transpose()?;
            print_status(&pre.plan, &pre.states, &pre.selected, &pre.fits, remote.as_ref(), json);
            if let Some(why) = remote.as_ref().and_then(|r| r.down()) {
                eprintln!("warning: remote cache {} not asked: {why}", remote.as_ref().map_or("", |r| r.url()));
            }
            print_store_warnings(pre.store.as_ref());
            Ok(ExitCode::SUCCESS)
        }
        Command::Dag { pipeline, format, set, store, remote } => {
            let p = config::load_with(&pipeline, &set.set, &set.set_new, registry)?;
            let pre = Preflight::new(&p, registry, &store_root(&p, &store), Device::Cpu, &[])?;
            let remote = remote.settings(&p)?.map(|r| open_remote(&r)).transpose()?;
            print!("{}", crate::dag::draw(&pre.plan, &pre.states, remote.as_ref(), format));
            if let Some(why) = remote.as_ref().and_then(|r| r.down()) {
                eprintln!("warning: remote cache {} not asked: {why}", remote.as_ref().map_or("", |r| r.url()));
            }
            Ok(ExitCode::SUCCESS)
        }
        Command::Push(Transfer { pipeline, only, store, remote }) => {
            let p = config::load(&pipeline, registry)?;
            let store = ran_store(&p, &store, "nothing to push")?;
            let plan = planned(&p, Some(&store), Device::Cpu)?;
            let selected = plan.select(&only)?;
            let settings = remote.settings(&p)?.context("no remote cache: set `[pipeline] remote` or give --remote")?;
            let remote = open_remote(&config::RemoteSettings { push: true, ..settings })?;
            let (mut pushed, mut bytes) = (0, 0);
            let ui = Ui::new(false);
            for (i, state) in assess(&plan, registry, Some(&store))?.iter().enumerate().filter(|(i, _)| selected[*i]) {
                let Freshness::Cached(record) = state else { continue };
                let mut bar = ui.transfer(&plan.instances[i].label, "pushing");
                let sent = remote.push(&store, record, false, &mut |done, total| bar.moved(done, total))?;
                drop(bar);
                if let Some(why) = remote.down() {
                    bail!("remote cache {}: {why}", remote.url());
                }
                if let Some(why) = sent.as_ref().and_then(|p| p.disagrees.as_ref()) {
                    println!("  WARNING  {}: {why}", plan.instances[i].label);
                }
                if let Some(why) = sent.as_ref().and_then(|p| p.refused.as_ref()) {
                    println!("  warning  {}: {why}", plan.instances[i].label);
                    continue;
                }
                let sent = sent.map_or(0, |p| p.bytes);
                println!("  {}  {}  {:.1} MB", if sent > 0 { "pushed" } else { "held  " }, plan.instances[i].label, sent as f64 / 1e6);
                pushed += usize::from(sent > 0);
                bytes += sent;
            }
            println!("push: {pushed} results uploaded ({:.1} MB) to {}", bytes as f64 / 1e6, remote.url());
            Ok(ExitCode::SUCCESS)
        }
        Command::Pull(Transfer { pipeline, only, store, remote }) => {
            let p = config::load(&pipeline, registry)?;
            let store = Store::open(&store_root(&p, &store))?;
            let plan = planned(&p, Some(&store), Device::Cpu)?;
            let selected = plan.select(&only)?;
            let settings = remote.settings(&p)?.context("no remote cache: set `[pipeline] remote` or give --remote")?;
            let remote = open_remote(&settings)?;
            let (pulled, bytes) = pull(&plan, registry, &store, &remote, &selected)?;
            println!("pull: {pulled} results downloaded ({:.1} MB) from {}", bytes as f64 / 1e6, remote.url());
            Ok(ExitCode::SUCCESS)
        }
        Command::Explain { pipeline, stage, set, store } => explain(registry, &pipeline, &set, &stage, &store),
        Command::Show { pipeline, stage, store } => show(registry, &pipeline, &stage, &store),
        Command::Runs { pipeline, all, last, json, store } => {
            let p = config::load(&pipeline, registry)?;
            let store = ran_store(&p, &store, "no runs to list")?;
            let mut runs = crate::history::runs_of(&store, &p.name)?;
            runs.truncate(last.unwrap_or(usize::MAX));
            if json {
                for run in &runs {
                    let mut line = serde_json::to_value(run)?;
                    line["counts"] = serde_json::to_value(run.counts())?;
                    println!("{line}");
                }
            } else if runs.is_empty() {
                println!("no runs of pipeline `{}` in {}", p.name, store.root().display());
            } else {
                print!("{}", crate::history::listing(&store, &runs, all)?);
            }
            print_store_warnings(Some(&store));
            Ok(ExitCode::SUCCESS)
        }
        Command::Compare { pipeline, runs: ids, variants, all, json, markdown, store } => {
            let p = config::load(&pipeline, registry)?;
            let store = ran_store(&p, &store, "nothing to compare")?;
            let runs = crate::history::runs_of(&store, &p.name)?;
            // Unnamed runs are the newest that are not plain reruns, in which nothing differs.
            let computing: Vec<&crate::history::PastRun> = runs.iter().filter(|r| !r.repeats).collect();
            let pick = |id: Option<&String>, newest: usize| -> anyhow::Result<&crate::history::PastRun> {
                match id {
                    Some(id) => crate::history::find(&runs, id, &p.name),
                    None => computing.get(newest).copied().with_context(|| {
                        format!(
                            "pipeline `{}` has {} run(s) in {} besides plain reruns ({} in all); compare needs {} (name runs to compare others)",
                            p.name,
                            computing.len(),
                            store.root().display(),
                            runs.len(),
                            newest + 1
                        )
                    }),
                }
            };
            let tables = if variants {
                if ids.len() > 1 {
                    return Err(UsageError("--variants compares the variants of one run: give at most one RUN".into()).into());
                }
                crate::compare::variants(&store, pick(ids.first(), 0)?, all)?
            } else {
                let (a, b) = match ids.as_slice() {
                    [] => (pick(None, 1)?, pick(None, 0)?),
                    [a] => (pick(Some(a), 0)?, pick(None, 0)?),
                    [a, b, ..] => (pick(Some(a), 0)?, pick(Some(b), 0)?),
                };
                vec![crate::compare::runs(&store, a, b, all)?]
            };
            for table in &tables {
                match (json, markdown) {
                    (true, _) => println!("{}", serde_json::to_string(table)?),
                    (_, true) => println!("{}", table.markdown()),
                    _ => print!("{}", table.terminal()),
                }
            }
            print_store_warnings(Some(&store));
            Ok(ExitCode::SUCCESS)
        }
        Command::Gc { pipeline, dry_run, keep_runs, responses, store } => {
            let store = existing_store(registry, pipeline.as_deref(), &store)?;
            let report = store.gc(keep_runs, dry_run, responses)?;
            let verb = if dry_run { "would remove" } else { "removed" };
            let mut counts: std::collections::BTreeMap<&str, usize> = Default::default();
            for (what, path, _) in &report.removed {
                *counts.entry(what).or_default() += 1;
                if dry_run {
                    println!("  {verb} {what} {}", path.display());
                }
            }
            let parts: Vec<String> = counts.iter().map(|(w, n)| format!("{n} {w}")).collect();
            println!(
                "gc: {verb} {} ({:.1} MB); kept {} objects",
                if parts.is_empty() { "nothing".into() } else { parts.join(", ") },
                report.bytes() as f64 / 1e6,
                report.kept_objects
            );
            print_store_warnings(Some(&store));
            Ok(ExitCode::SUCCESS)
        }
        Command::Digests { pipeline, set, store } => {
            let p = config::load_with(&pipeline, &set.set, &set.set_new, registry)?;
            let store = ran_store(&p, &store, "nothing to list")?;
            let plan = planned(&p, Some(&store), Device::Cpu)?;
            let states = assess(&plan, registry, Some(&store))?;
            print!("{}", crate::digests::render(&p, &plan, &states, &rlmflow_stages::numerics::Cpu::detect())?);
            print_store_warnings(Some(&store));
            Ok(ExitCode::SUCCESS)
        }
        Command::Verify { pipeline, recompute, only, sample, against, store } => {
            let store = existing_store(registry, pipeline.as_deref(), &store)?;
            let mut n = 0;
            let report = store.verify(|_| n += 1)?;
            for c in &report.objects {
                println!("  corrupt object {}: {} (quarantined; stages using it will recompute)", c.digest, c.files.join(", "));
            }
            for f in &report.files {
                println!("  damaged {}: {} (quarantined to {})", f.path.display(), f.problem, f.quarantined.display());
            }
            for (key, output) in &report.records_without_output {
                println!("  record {} needs object {}, which is gone: its action reruns when needed", key.short(), output.short());
            }
            let p = pipeline.as_deref().map(|file| config::load(file, registry)).transpose()?;
            let forged = match &p {
                Some(p) => verify_signatures(&store, &p.remote)?,
                None => 0,
            };
            println!(
                "verify: {n} objects, {} damaged; {} damaged store files; {forged} records with a bad signature",
                report.objects.len(),
                report.files.len()
            );
            let disagree = match (recompute, &p) {
                (false, _) => 0,
                (true, None) => anyhow::bail!("--recompute needs the pipeline file"),
                (true, Some(p)) => {
                    let plan = planned(p, Some(&store), Device::Cpu)?;
                    let jobs = std::thread::available_parallelism().map_or(1, |n| n.get());
                    let opts = RunOptions { jobs, json: false, device: Device::Cpu, verify_inputs: false, remote: None };
                    let disagree = crate::determinism::recompute(&plan, registry, &store, &only, sample, &opts)?;
                    println!("verify --recompute: {disagree} disagree");
                    disagree
                }
            };
            let unlike = match against {
                Some(file) => verify_against(&store, &file)?,
                None => 0,
            };
            Ok(if report.is_clean() && forged == 0 && disagree == 0 && unlike == 0 { ExitCode::SUCCESS } else { ExitCode::FAILURE })
        }
        Command::Pin { pipeline, name, store } => {
            config::check_name(&name).map_err(|problem| anyhow::anyhow!("the pin name {problem}"))?;
            let p = config::load(&pipeline, registry)?;
            let store = ran_store(&p, &store, "nothing to pin")?;
            let plan = planned(&p, Some(&store), Device::Cpu)?;
            let states = assess(&plan, registry, Some(&store))?;
            let keys: std::collections::BTreeMap<String, Digest> = states
                .iter()
                .enumerate()
                .filter_map(|(i, s)| match s {
                    Freshness::Cached(r) => Some((plan.instances[i].label.clone(), r.key)),
                    _ => None,
                })
                .collect();
            let path = store.pin(&name, &keys)?;
            println!("pinned {} cached stage instances in {}", keys.len(), path.display());
            print_store_warnings(Some(&store));
            Ok(ExitCode::SUCCESS)
        }
        Command::Key { action: KeyAction::Generate { name, dir } } => {
            let (secret, public) = rlmflow_remote::signing::generate(&name)?;
            let (secret_file, public_file) = (dir.join(format!("{name}.secret")), dir.join(format!("{name}.public")));
            if secret_file.exists() {
                anyhow::bail!("{} exists; a key is never overwritten", secret_file.display());
            }
            use std::os::unix::fs::OpenOptionsExt as _;
            let mut file = std::fs::OpenOptions::new().write(true).create_new(true).mode(0o600).open(&secret_file)?;
            std::io::Write::write_all(&mut file, format!("{secret}\n").as_bytes())?;
            std::fs::write(&public_file, format!("{public}\n"))?;
            println!("secret key: {} (for the pusher: {}={})", secret_file.display(), config::SIGNING_KEY_VARIABLE, secret_file.display());
            println!("public key: {public}");
            println!("readers trust it with: remote_trusted_keys = [\"{public}\"]");
            Ok(ExitCode::SUCCESS)
        }
        Command::Setup => {
            let env = rlmflow_python::ensure(&mut |note| eprintln!("{note}"))?;
            println!("Python {} environment: {}", env.version, env.root.display());
            println!("site-packages: {}", env.site_packages.display());
            Ok(ExitCode::SUCCESS)
        }
        Command::Operators { json: true } => {
            for kind in &registry.catalog.kinds {
                for op in registry.operators_of(kind.name) {
                    let spec = op.spec();
                    let defaults = op.defaults();
                    let reads = spec.inputs.map_or_else(|| kind.inputs.iter().map(|s| s.name).collect(), <[&str]>::to_vec);
                    let inputs: serde_json::Map<String, serde_json::Value> = kind
                        .inputs
                        .iter()
                        .filter(|slot| reads.contains(&slot.name))
                        .map(|slot| (slot.name.to_owned(), serde_json::json!(slot.artifact.to_string())))
                        .collect();
                    let line = serde_json::json!({
                        "name": spec.name, "kind": spec.kind, "version": spec.version, "summary": spec.summary,
                        "inputs": inputs, "produces": kind.produces.to_string(), "merge": op.merge(),
                        "defaults": defaults, "non_result": op.non_result_keys(), "tracked": op.tracked_keys()
                    });
                    println!("{line}");
                }
            }
            Ok(ExitCode::SUCCESS)
        }
        Command::Operators { json: false } => {
            for kind in &registry.catalog.kinds {
                let inputs: Vec<String> = kind.inputs.iter().map(|s| format!("{}: {}", s.name, s.artifact)).collect();
                println!("{} ({}) -> {}", kind.name, inputs.join(", "), kind.produces);
                for op in registry.operators_of(kind.name) {
                    let spec = op.spec();
                    let defaults = op.defaults();
                    println!("  {} v{}: {}\n    defaults: {}", spec.name, spec.version, spec.summary, canonical_json(&defaults));
                    if !op.tracked_keys().is_empty() {
                        println!("    paths tracked by content (their files' digests enter the key, not the path): {}", op.tracked_keys().join(", "));
                    }
                    if !op.non_result_keys().is_empty() {
                        println!("    not part of the result (left out of the key): {}", op.non_result_keys().join(", "));
                    }
                    match (op.merge(), op.items(&defaults)) {
                        (Some(merge), Some((ItemCount::Known(_), unit))) => {
                            println!("    shardable: `shards` or `shard_size` split its {unit} into parts, merged by `{merge}`")
                        }
                        (Some(merge), Some((ItemCount::OfInput(slot), unit))) => {
                            println!("    shardable: `shards = N` splits the {unit} of its `{slot}` input into N parts, merged by `{merge}`")
                        }
                        _ => {}
                    }
                }
            }
            Ok(ExitCode::SUCCESS)
        }
        Command::Exec { key, store, threads, device, scratch, remote, remote_timeout, transcript, replace } => {
            let code = match (remote, store, scratch) {
                (Some(url), store, _) => {
                    let timeout = std::time::Duration::from_secs_f64(remote_timeout);
                    let remote = crate::task::TaskRemote { url, timeout, transcript: transcript.expect("clap requires it"), replace };
                    crate::task::exec_task(store.as_deref(), key, threads, device, remote)?
                }
                (None, Some(store), Some(dir)) => crate::exec::exec_scratch(registry, &store, key, threads, device, &dir)?,
                (None, Some(store), None) => crate::exec::exec(registry, &store, key, threads, device)?,
                (None, None, _) => bail!("exec needs --store DIR (or --remote URL, for a cluster task with a store of its own)"),
            };
            Ok(ExitCode::from(code as u8))
        }
    }
}

/// Checks every signed record of `store` (pulled from a remote cache, the signatures kept)
/// against the pipeline's trusted keys: one whose signature does not match it, or that only
/// untrusted keys signed, is quarantined and named. Returns how many.
fn verify_signatures(store: &Store, remote: &config::RemoteSettings) -> anyhow::Result<usize> {
    let trusted = rlmflow_remote::signing::TrustedKeys::parse(&remote.trusted_keys)?;
    if trusted.is_empty() {
        return Ok(0);
    }
    let mut bad = 0;
    for key in store.record_keys()? {
        let Some(record) = store.record(&key)?.filter(|r| !r.signatures.is_empty()) else { continue };
        match trusted.check(&record) {
            rlmflow_remote::signing::Trust::Signed(_) => {}
            other => {
                let to = store.quarantine_record(&key)?;
                println!("  record {} is {other}: quarantined to {} (its action reruns when needed)", key.short(), to.display());
                bad += 1;
            }
        }
    }
    Ok(bad)
}

/// `verify --against FILE`: each row's verdict, a summary line; how many rows failed (each that
/// differs, or one when none was here to compare).
fn verify_against(store: &Store, file: &Path) -> anyhow::Result<usize> {
    use crate::digests::Verdict;
    let rows = crate::digests::read(file)?;
    let verdicts = crate::digests::compare(store, &rows)?;
    let width = rows.iter().map(|r| r.instance.len()).max().unwrap_or(0);
    for (row, verdict) in rows.iter().zip(&verdicts) {
        match verdict {
            Verdict::Same => println!("  same      {:width$}  key {}", row.instance, row.key.short()),
            Verdict::Differs(here) => {
                println!("  DIFFERS   {:width$}  key {}: there {}, here {}", row.instance, row.key.short(), row.output.short(), here.short())
            }
            Verdict::Absent => println!("  absent    {:width$}  key {} is not in this store", row.instance, row.key.short()),
        }
    }
    let count = |f: fn(&Verdict) -> bool| verdicts.iter().filter(|v| f(v)).count();
    let (same, differ, absent) = (count(|v| *v == Verdict::Same), count(|v| matches!(v, Verdict::Differs(_))), count(|v| *v == Verdict::Absent));
    println!(
        "verify --against {}: {same} the same, {differ} differ, {absent} not in this store (not computed here, or other settings or versions: other keys)",
        file.display()
    );
    if same + differ == 0 {
        eprintln!("error: none of the {} keys of {} is in this store: nothing was compared", rows.len(), file.display());
        return Ok(1);
    }
    Ok(differ)
}

fn existing_store(registry: &Registry, pipeline: Option<&Path>, arg: &StoreArg) -> anyhow::Result<Store> {
    let root = match (pipeline, &arg.cache) {
        (_, Some(dir)) => dir.clone(),
        (Some(file), None) => config::load(file, registry)?.cache,
        (None, None) => PathBuf::from(".rlmflow"),
    };
    Store::open_existing(&root)?.with_context(|| format!("no rlmflow store at {}", root.display()))
}

fn instances_of(plan: &crate::plan::Plan, stage: &str) -> anyhow::Result<Vec<usize>> {
    let Some(s) = plan.pipeline.stage(stage) else {
        let names = plan.pipeline.stage_names();
        bail!("no stage named `{stage}`; stages: {}{}", names.join(", "), config::suggest(stage, &names));
    };
    Ok((0..plan.instances.len()).filter(|&i| plan.instances[i].stage == s).collect())
}

fn explain(registry: &Registry, file: &Path, set: &SetArg, stage: &str, arg: &StoreArg) -> anyhow::Result<ExitCode> {
    let p = config::load_with(file, &set.set, &set.set_new, registry)?;
    let store = Store::open_existing(&store_root(&p, arg))?;
    let plan = planned(&p, store.as_ref(), Device::Cpu)?;
    let states = assess(&plan, registry, store.as_ref())?;
    let last = match &store {
        Some(s) => s.last_keys(&p.name)?,
        None => Default::default(),
    };
    for i in instances_of(&plan, stage)? {
        let label = &plan.instances[i].label;
        println!("{label}");
        match &states[i] {
            Freshness::Cached(r) => {
                println!("  cached: key {} (ran {:.1}s, {})", r.key, r.duration_s, r.started);
                if last.get(label) != Some(&r.key) {
                    println!("  (the last run used another key: {})", last.get(label).map_or("none".into(), |k| k.to_string()));
                }
                println!("  preimage:\n{}", indent(&serde_json::to_string_pretty(&r.preimage)?));
            }
            Freshness::Stale { key, reasons, preimage } => {
                println!("  will run: key {key}");
                println!("  last run: {}", last.get(label).map_or("none".into(), |k| k.to_string()));
                for r in reasons {
                    println!("    {r}");
                }
                println!("  preimage:\n{}", indent(&serde_json::to_string_pretty(preimage)?));
            }
            Freshness::Pending(waiting) => {
                println!("  pending: {waiting}; its key is known once that input is");
                if let (Some(s), Some(old)) = (&store, last.get(label))
                    && let Some(before) = crate::reason::previous_preimage(s, old)?
                {
                    let unknown = rlmflow_cache::Digest([0; 32]);
                    let outputs: Vec<Option<Digest>> =
                        states.iter().map(|st| Some(if let Freshness::Cached(r) = st { r.output } else { unknown })).collect();
                    let now = plan.preimage(i, registry, &outputs).unwrap();
                    for change in now.diff(&before) {
                        if !matches!(&change, rlmflow_cache::Change::InputChanged { .. }) {
                            println!("    {}", crate::ui::describe(&p.stages[plan.instances[i].stage].name, &change));
                        }
                    }
                }
            }
        }
    }
    print_store_warnings(store.as_ref());
    Ok(ExitCode::SUCCESS)
}

fn show(registry: &Registry, file: &Path, stage: &str, arg: &StoreArg) -> anyhow::Result<ExitCode> {
    let p = config::load(file, registry)?;
    let store = Store::open_existing(&store_root(&p, arg))?;
    let plan = planned(&p, store.as_ref(), Device::Cpu)?;
    let states = assess(&plan, registry, store.as_ref())?;
    for i in instances_of(&plan, stage)? {
        let label = &plan.instances[i].label;
        match (&states[i], &store) {
            (Freshness::Cached(r), Some(s)) => {
                println!("{label}: cached");
                println!("  output:  {}", s.object_dir(&r.output).display());
                println!("  files:   {} ({:.1} MB)", r.files, r.bytes as f64 / 1e6);
                println!("  key:     {}", r.key);
                println!("  ran:     {} for {:.1}s", r.started, r.duration_s);
                match &r.pulled {
                    None => println!("  origin:  computed here"),
                    Some(rlmflow_cache::PulledFrom { remote, signed_by: Some(key) }) => {
                        println!("  origin:  pulled from {remote}, signed by `{key}`")
                    }
                    Some(rlmflow_cache::PulledFrom { remote, signed_by: None }) => {
                        println!("  origin:  pulled from {remote} UNVERIFIED (no trusted keys): its summary and metrics are the remote's word")
                    }
                }
                let unverified = if r.unverified_origin().is_some() { " (unverified)" } else { "" };
                if !r.summary.is_empty() {
                    println!("  summary{unverified}: {}", r.summary);
                }
                if !r.metrics.is_null() {
                    println!("  metrics{unverified}: {}", canonical_json(&r.metrics));
                }
                // A record from before its operator kept one, or a damaged one, shows none.
                if let Some(platform) = r.platform.clone().and_then(|p| serde_json::from_value::<rlmflow_stages::numerics::PlatformRecord>(p).ok()) {
                    platform.to_string().lines().for_each(|line| println!("  {line}"));
                }
            }
            (Freshness::Stale { reasons, .. }, _) => println!("{label}: not computed yet ({})", crate::ui::words(reasons)),
            (Freshness::Pending(waiting), _) => println!("{label}: not computed yet ({waiting})"),
            (Freshness::Cached(_), None) => unreachable!("cached without a store"),
        }
    }
    print_store_warnings(store.as_ref());
    Ok(ExitCode::SUCCESS)
}

fn indent(text: &str) -> String {
    text.lines().map(|l| format!("    {l}")).collect::<Vec<_>>().join("\n")
}
