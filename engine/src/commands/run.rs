//! `rlmflow run`: run a pipeline (`--dry-run`, `--check-determinism`) through `crate::run`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context as _;
use rlmflow_cache::Store;
use rlmflow_stages::{Device, Registry};

use super::{RemoteArg, SetArg, StoreArg, UsageError, store_root};
use crate::config;
use crate::event::{Event, Logged};
use crate::preflight::Preflight;
use crate::run::{RunOptions, run};
use crate::ui::print_status;

#[derive(clap::Args)]
pub(crate) struct Args {
    pipeline: PathBuf,
    /// Print the plan (cached / will run / pending, with reasons) and change nothing.
    #[arg(long)]
    dry_run: bool,
    /// Run only these stages (or instances, as a run prints them: `pretrain[alpha4]`) and what
    /// they need (repeatable).
    #[arg(long, value_name = "STAGE")]
    only: Vec<String>,
    /// CPU threads shared by concurrently running stages; default: all cores (with
    /// HyperQueue, its workers times their cores).
    #[arg(long, short)]
    jobs: Option<usize>,
    /// Where actions run, overriding `[pipeline] executor`: local or hyperqueue.
    #[arg(long, value_name = "EXECUTOR")]
    executor: Option<String>,
    /// The GPUs a local run places model stages on, by the driver's index, overriding
    /// `[pipeline] gpus` (default: every GPU it sees).
    #[arg(long, value_name = "0,1", value_delimiter = ',')]
    gpus: Option<Vec<usize>>,
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
    let Args { pipeline, dry_run, only, jobs, executor, gpus, json, device, verify_inputs, check_determinism, set, store, remote } = args;
    let mut p = set.load(&pipeline, registry)?;
    if gpus.is_some() {
        p.gpus = gpus;
    }
    if let Some(name) = executor {
        p.executor = config::Executor::parse(&name)
            .with_context(|| format!("unknown executor `{name}` for --executor; valid: {}", config::Executor::NAMES.join(", ")))?;
    }
    let root = store_root(&p, &store);
    // Under a seed rule the plan is the store's look: a dry run, `--only` and a determinism
    // check plan at it and add no seed.
    if p.seed_rule.is_some() {
        crate::claims::reached(&mut p, registry, Store::open_existing(&root)?.as_ref(), device)?;
    }
    if dry_run {
        let pre = Preflight::new(&p, registry, &root, device, &only)?;
        print_status(&pre.plan, &pre.instances, None, json);
        let inventory = crate::gpus::inventory(p.gpus.as_deref())?;
        if !json && p.executor == config::Executor::Local && !inventory.gpus.is_empty() {
            print!("{}", inventory.lines());
        }
        if let (Some(rule), false) = (p.seed_rule, json) {
            println!("  claims    at {} seeds now; a run adds seeds one at a time, up to {}, until every claim is decided", p.seeds.len(), rule.max);
        }
        pre.refuse_oversized()?;
        return Ok(ExitCode::SUCCESS);
    }
    let jobs = jobs
        .unwrap_or_else(|| match p.executor {
            config::Executor::Local => std::thread::available_parallelism().map_or(1, |n| n.get()),
            config::Executor::HyperQueue => p.hyperqueue.workers * p.hyperqueue.cores(),
        })
        .max(1);
    let opts = RunOptions { jobs, json, device, verify_inputs, remote: remote.settings(&p)? };
    // A pushing run that cannot sign stops before anything runs, as `push` does.
    if let Some(settings) = &opts.remote {
        settings.signing_key().map_err(|e| UsageError(format!("{e:#}")))?;
    }
    if !check_determinism.is_empty() {
        let pre = Preflight::new(&p, registry, &root, device, &only)?;
        pre.refuse_cuda_stages(registry)?;
        pre.refuse_oversized()?;
        let store = Store::open(&root)?;
        let same = crate::determinism::check(&pre.plan, registry, &store, &check_determinism, &opts, &mut |found| {
            println!("{}", crate::ui::finding(&found))
        })?;
        return Ok(if same { ExitCode::SUCCESS } else { ExitCode::FAILURE });
    }
    // Seeds until decided: each look computes what its claims read, and the next is asked.
    if p.seed_rule.is_some() && only.is_empty() {
        let mut computed = None;
        loop {
            let look = crate::claims::reached(&mut p, registry, Store::open_existing(&root)?.as_ref(), device)?;
            if look.missing.is_empty() {
                break;
            }
            // A look computed and still missing its instances would loop for ever.
            if computed.replace(look.seeds) == Some(look.seeds) {
                anyhow::bail!(
                    "the claims' instances at {} seeds are still not in the store after computing them: {}",
                    look.seeds,
                    look.missing.join(", ")
                );
            }
            if !json {
                println!("claims: computing their instances at {} seeds ({} missing)", look.seeds, look.missing.len());
            }
            if !run_selected(&p, registry, &root, &crate::claims::claim_stages(&p), &opts)? {
                return Ok(ExitCode::FAILURE);
            }
        }
    }
    let mut ok = run_selected(&p, registry, &root, &only, &opts)?;
    if p.claims.is_some() && only.is_empty() && ok {
        let store = Store::open(&root)?;
        let look = crate::claims::reached(&mut p, registry, Some(&store), device)?;
        match json {
            true => println!(
                "{}",
                serde_json::to_string(&Logged { event: Event::Claims { seeds: look.seeds, verdicts: look.verdicts.clone() }, t: 0.0 })?
            ),
            false => print!("{}", crate::ui::claims(&look, p.claims.as_ref().map_or(0.0, |s| s.level))),
        }
        for v in look.required_fails() {
            eprintln!("error: required claim `{}` fails", v.claim);
            ok = false;
        }
    }
    Ok(if ok { ExitCode::SUCCESS } else { ExitCode::FAILURE })
}

/// Runs the instances of `only` (all when empty) and what they need; whether none failed.
fn run_selected(p: &config::Pipeline, registry: &Registry, root: &std::path::Path, only: &[String], opts: &RunOptions) -> anyhow::Result<bool> {
    let pre = Preflight::new(p, registry, root, opts.device, only)?;
    pre.refuse_cuda_stages(registry)?;
    pre.refuse_oversized()?;
    let store = Store::open(root)?;
    let summary = run(&pre.plan, registry, &store, pre.instances.into_iter().map(Into::into).collect(), opts)?;
    Ok(summary.failed == 0)
}
