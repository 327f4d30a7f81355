//! `rlmflow verify`: re-hash the store and check its records' signatures; with `--recompute`,
//! compute actions again, and with `--against`, compare with another machine's digests.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use rlmflow_cache::Store;
use rlmflow_stages::{Device, Registry};

use super::{StoreArg, existing_store};
use crate::config;
use crate::preflight::planned;
use crate::run::RunOptions;
use crate::ui::Rejected;

#[derive(clap::Args)]
pub(crate) struct Args {
    pipeline: Option<PathBuf>,
    /// Also recompute cached actions in fresh processes and compare their outputs with their
    /// records' (needs the pipeline): an audit of a cache this store pulled from.
    #[arg(long)]
    recompute: bool,
    /// With --recompute: only these stages, or instances as a run prints them (repeatable).
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
}

pub(crate) fn exec(args: Args, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Args { pipeline, recompute, only, sample, against, store } = args;
    let store = existing_store(registry, pipeline.as_deref(), &store)?;
    let mut n = 0;
    let report = store.verify(|_| n += 1)?;
    let p = pipeline.as_deref().map(|file| config::load(file, registry)).transpose()?;
    let rejected = match &p {
        Some(p) => verify_signatures(&store, &p.remote)?,
        None => Vec::new(),
    };
    print!("{}", crate::ui::store_check(&report, n, &rejected));
    let disagree = match (recompute, &p) {
        (false, _) => 0,
        (true, None) => anyhow::bail!("--recompute needs the pipeline file"),
        (true, Some(p)) => {
            let plan = planned(p, Some(&store), Device::Cpu)?;
            let jobs = std::thread::available_parallelism().map_or(1, |n| n.get());
            let opts = RunOptions { jobs, json: false, device: Device::Cpu, verify_inputs: false, remote: None };
            let disagree = crate::determinism::recompute(&plan, registry, &store, &only, sample, &opts, &mut |found| {
                println!("{}", crate::ui::finding(&found))
            })?;
            println!("verify --recompute: {disagree} disagree");
            disagree
        }
    };
    let unlike = match against {
        Some(file) => verify_against(&store, &file)?,
        None => 0,
    };
    Ok(if report.is_clean() && rejected.is_empty() && disagree == 0 && unlike == 0 { ExitCode::SUCCESS } else { ExitCode::FAILURE })
}

/// Checks every signed record of `store` (pulled from a remote cache, the signatures kept)
/// against the pipeline's trusted keys: one whose signature does not match it, or that only
/// untrusted keys signed, is quarantined. Returns those.
fn verify_signatures(store: &Store, remote: &config::RemoteSettings) -> anyhow::Result<Vec<Rejected>> {
    let trusted = rlmflow_remote::signing::TrustedKeys::parse(&remote.trusted_keys)?;
    let mut rejected = Vec::new();
    if trusted.is_empty() {
        return Ok(rejected);
    }
    for key in store.record_keys()? {
        let Some(record) = store.record(&key)?.filter(|r| !r.signatures.is_empty()) else { continue };
        match trusted.check(&record) {
            rlmflow_remote::signing::Trust::Signed { .. } => {}
            trust => {
                let quarantined = store.quarantine_record(&key)?;
                rejected.push(Rejected { key, trust, quarantined });
            }
        }
    }
    Ok(rejected)
}

/// `verify --against FILE`: each row's verdict, a summary line; how many rows failed (each that
/// differs, or one when none was here to compare).
fn verify_against(store: &Store, file: &Path) -> anyhow::Result<usize> {
    let rows = crate::digests::read(file)?;
    let verdicts = crate::digests::compare(store, &rows)?;
    let (lines, nothing_compared) = crate::ui::against(file, &rows, &verdicts);
    print!("{lines}");
    if let Some(error) = nothing_compared {
        eprintln!("error: {error}");
        return Ok(1);
    }
    Ok(verdicts.iter().filter(|v| matches!(v, crate::digests::Verdict::Differs(_))).count())
}
