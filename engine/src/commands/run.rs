//! `rlmflow run`: run a pipeline (`--dry-run`, `--check-determinism`) through `crate::run`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context as _;
use rlmflow_cache::Store;
use rlmflow_stages::{Device, Registry};

use super::{RemoteArg, SetArg, StoreArg, UsageError, store_root};
use crate::config;
use crate::plan::Freshness;
use crate::preflight::Preflight;
use crate::run::{RunOptions, run};
use crate::ui::print_status;

#[derive(clap::Args)]
pub(crate) struct Args {
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
}

pub(crate) fn exec(args: Args, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Args { pipeline, dry_run, only, jobs, executor, json, device, verify_inputs, check_determinism, set, store, remote } = args;
    let mut p = set.load(&pipeline, registry)?;
    if let Some(name) = executor {
        p.executor = config::Executor::parse(&name)
            .with_context(|| format!("unknown executor `{name}` for --executor; valid: {}", config::Executor::NAMES.join(", ")))?;
    }
    let root = store_root(&p, &store);
    let pre = Preflight::new(&p, registry, &root, device, &only)?;
    if dry_run {
        print_status(&pre.plan, &pre.states, &pre.selected, &pre.fits, None, json);
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
    let known = pre.states.into_iter().map(|s| if let Freshness::Cached(record) = s { Some(record) } else { None }).collect();
    let (plan, selected) = (pre.plan, pre.selected);
    let opts = RunOptions { jobs, json, device, verify_inputs, remote: remote.settings(&p)? };
    // A pushing run that cannot sign stops before anything runs, as `push` does.
    if let Some(settings) = &opts.remote {
        settings.signing_key().map_err(|e| UsageError(format!("{e:#}")))?;
    }
    let store = Store::open(&root)?;
    if !check_determinism.is_empty() {
        let same = crate::determinism::check(&plan, registry, &store, &check_determinism, &opts)?;
        return Ok(if same { ExitCode::SUCCESS } else { ExitCode::FAILURE });
    }
    let summary = run(&plan, registry, &store, &selected, known, &opts)?;
    Ok(if summary.failed > 0 { ExitCode::FAILURE } else { ExitCode::SUCCESS })
}
