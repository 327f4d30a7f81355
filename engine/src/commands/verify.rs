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
    Ok(if report.is_clean() && forged == 0 && disagree == 0 && unlike == 0 { ExitCode::SUCCESS } else { ExitCode::FAILURE })
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
            rlmflow_remote::signing::Trust::Signed { .. } => {}
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
