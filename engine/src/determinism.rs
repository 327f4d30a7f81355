//! `rlmflow run PIPELINE --check-determinism STAGE`: same key, same bytes, checked.
//!
//! The cache trusts that an operator's output depends only on its settings, inputs and seed. A
//! hidden source (iteration over a hash-seeded map, a global RNG, thread or completion order, a
//! memory address, the clock) breaks that silently: a rerun gets another digest and everything
//! downstream reruns or, worse, two machines disagree. This check runs what the stage needs
//! through the normal executor, then runs each of the stage's actions twice, each in a fresh
//! `rlmflow exec` process (so hash seeds, allocator addresses and global RNGs differ; Python's
//! hash seed is randomised) with a different thread count, into scratch directories, and
//! compares the two output trees. The second process's environment asks every numeric library
//! for other kernels than both its pins and its own automatic choice (older instruction sets
//! than AVX2; `rlmflow_stages::numerics::other_kernels`), so an operator whose bytes follow the
//! CPU's kernels, unpinned, shows it here on one machine. A difference names the files and the first differing byte.
//! Nothing is committed; the scratch outputs of a failed check stay in the store's `tmp/` for
//! inspection (`gc` removes them).

use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

use anyhow::{Context as _, bail};
use rlmflow_cache::{Digest, Store, differing_files, hash_tree};
use rlmflow_stages::Registry;

pub use crate::finding::Finding;
use crate::plan::{Freshness, Plan, assess};
use crate::protocol::{Message, PREFIX};
use crate::run::{Admitted, RunOptions, run};

/// The instances `names` name (stages or labels, [`Plan::instances_named`]).
fn named(plan: &Plan, names: &[String]) -> anyhow::Result<Vec<bool>> {
    let mut named = vec![false; plan.instances.len()];
    for name in names {
        plan.instances_named(name)?.into_iter().for_each(|i| named[i] = true);
    }
    Ok(named)
}

/// Checks every instance `stages` names (stages or labels), telling `found` what each attempt
/// finds; returns whether all were deterministic.
pub fn check(
    plan: &Plan,
    registry: &Registry,
    store: &Store,
    stages: &[String],
    opts: &RunOptions,
    found: &mut dyn FnMut(Finding),
) -> anyhow::Result<bool> {
    let wanted = plan.select(stages)?;
    let targets = named(plan, stages)?;
    let upstream: Vec<bool> = wanted.iter().zip(&targets).map(|(w, t)| *w && !t).collect();
    if upstream.iter().any(|u| *u) {
        let admitted = upstream.iter().map(|&selected| Admitted { selected, ..Default::default() }).collect();
        let summary = run(plan, registry, store, admitted, opts)?;
        if summary.failed + summary.skipped > 0 {
            bail!("the stages {} need did not all finish; nothing was checked", stages.join(", "));
        }
    }
    let states = assess(plan, registry, Some(store))?;
    let threads = [opts.jobs, (opts.jobs / 2).max(1)];
    let other_kernels = rlmflow_stages::numerics::other_kernels();
    let environments: [&[(&str, &str)]; 2] = [&[], &other_kernels];
    let mut all_same = true;
    for (i, inst) in plan.instances.iter().enumerate().filter(|(i, _)| targets[*i]) {
        let (key, preimage, stored) = match &states[i] {
            Freshness::Cached(r) => (r.key, r.preimage.clone(), Some(r.output)),
            Freshness::Stale { key, preimage, .. } => (*key, (**preimage).clone(), None),
            Freshness::Pending(waiting) => bail!("{}: {waiting}", inst.label),
        };
        store.write_request(&plan.request(i, key, preimage))?;
        plan.snapshot_tracked(i, store)?;
        found(Finding::Checking { label: &inst.label, key });
        let exe = crate::exec::executable(registry.get(&inst.operator).expect("validated operator"))?;
        let mut attempts: Vec<(PathBuf, Digest)> = Vec::new();
        for (attempt, (&n, env)) in threads.iter().zip(environments).enumerate() {
            let scratch = store.root().join("tmp").join(format!("check-{}-{}-{attempt}", key.hex(), std::process::id()));
            let _ = std::fs::remove_dir_all(&scratch);
            std::fs::create_dir_all(&scratch)?;
            let clock = Instant::now();
            // The attempt reports its output's tree digest; manifests are read only to explain a difference.
            let digest = attempt_in_fresh_process(&exe, store, &key, n, env, opts, &scratch)
                .with_context(|| format!("{}: attempt {}", inst.label, attempt + 1))?;
            found(Finding::Attempt { number: attempt + 1, threads: n, env, output: digest, seconds: clock.elapsed().as_secs_f64() });
            attempts.push((scratch, digest));
        }
        let [(dir_a, a), (dir_b, b)] = <[_; 2]>::try_from(attempts).expect("two attempts");
        if a == b {
            found(Finding::Same { stored: stored.filter(|s| *s != a) });
            std::fs::remove_dir_all(&dir_a)?;
            std::fs::remove_dir_all(&dir_b)?;
            continue;
        }
        let (a, b) = (hash_tree(&dir_a.join("out"))?, hash_tree(&dir_b.join("out"))?);
        all_same = false;
        let files = differing_files(&b.manifest, &a.manifest);
        let first = files.first().map(|f| first_difference(&dir_a.join("out").join(f), &dir_b.join("out").join(f))).transpose()?;
        found(Finding::Differs { of: a.files.max(b.files), first, kept: [dir_a.join("out"), dir_b.join("out")], files });
    }
    Ok(all_same)
}

/// `rlmflow verify PIPELINE --recompute`: recomputes cached actions (of those `stages` names, or
/// all) in fresh processes and compares each output with the one its record names, so a team
/// can audit a cache it pulled from (a forged or foreign record shows as a disagreement).
/// `sample` keeps that many, chosen by key (a fixed, unbiased choice); `found` hears each.
/// Returns how many disagree.
pub fn recompute(
    plan: &Plan,
    registry: &Registry,
    store: &Store,
    stages: &[String],
    sample: Option<usize>,
    opts: &RunOptions,
    found: &mut dyn FnMut(Finding),
) -> anyhow::Result<usize> {
    let wanted = if stages.is_empty() { vec![true; plan.instances.len()] } else { named(plan, stages)? };
    let states = assess(plan, registry, Some(store))?;
    let mut cached: Vec<(usize, rlmflow_cache::ActionRecord)> = states
        .iter()
        .enumerate()
        .filter(|(i, _)| wanted[*i])
        .filter_map(|(i, state)| match state {
            Freshness::Cached(record) => Some((i, (**record).clone())),
            _ => None,
        })
        .collect();
    if let Some(n) = sample {
        cached.sort_by_key(|(_, r)| r.key);
        cached.truncate(n);
        cached.sort_by_key(|(i, _)| *i);
    }
    let mut disagree = 0;
    for (i, record) in cached {
        let inst = &plan.instances[i];
        store.write_request(&plan.request(i, record.key, record.preimage.clone()))?;
        plan.snapshot_tracked(i, store)?;
        let exe = crate::exec::executable(registry.get(&inst.operator).expect("validated operator"))?;
        let scratch = store.root().join("tmp").join(format!("recompute-{}-{}", record.key.hex(), std::process::id()));
        let _ = std::fs::remove_dir_all(&scratch);
        std::fs::create_dir_all(&scratch)?;
        let digest = attempt_in_fresh_process(&exe, store, &record.key, opts.jobs, &[], opts, &scratch)
            .with_context(|| format!("recomputing {}", inst.label))?;
        if digest == record.output {
            found(Finding::Agrees { label: &inst.label, output: digest });
            std::fs::remove_dir_all(&scratch)?;
            continue;
        }
        disagree += 1;
        let signers = rlmflow_remote::signing::signers(&record);
        found(Finding::Disagrees { label: &inst.label, recorded: record.output, signers, recomputed: digest, kept: scratch.join("out") });
    }
    Ok(disagree)
}

/// Runs `rlmflow exec KEY --scratch DIR` with `env` added to its environment and waits for its
/// output digest.
fn attempt_in_fresh_process(
    exe: &Path,
    store: &Store,
    key: &Digest,
    threads: usize,
    env: &[(&str, &str)],
    opts: &RunOptions,
    scratch: &Path,
) -> anyhow::Result<Digest> {
    let log = scratch.join("exec.log");
    let mut child = Command::new(exe)
        .arg("exec")
        .arg(key.to_string())
        .arg("--store")
        .arg(store.root())
        .arg("--threads")
        .arg(threads.to_string())
        .arg("--device")
        .arg(opts.device.to_string())
        .arg("--scratch")
        .arg(scratch)
        // Python's string hashes differ in every attempt, whatever the caller's environment says.
        .env("PYTHONHASHSEED", "random")
        .envs(env.iter().copied())
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(&log)?)
        .spawn()
        .context("starting `rlmflow exec`")?;
    let mut result = None;
    for line in BufReader::new(child.stdout.take().unwrap()).lines().map_while(Result::ok) {
        match line.strip_prefix(PREFIX).and_then(|m| serde_json::from_str::<Message>(m).ok()) {
            Some(Message::Done { output }) => result = Some(Ok(output)),
            Some(Message::Failed { message, .. }) => result = Some(Err(message)),
            Some(Message::CorruptInput { digest, .. }) => result = Some(Err(format!("input {} failed verification", digest.short()))),
            _ => {}
        }
    }
    let status = child.wait()?;
    match result {
        Some(Ok(output)) if status.success() => Ok(output),
        Some(Err(message)) => bail!("{message} (log: {})", log.display()),
        _ => bail!("the stage process ended with {status} (log: {})", log.display()),
    }
}

/// Where two files first differ, for the report.
fn first_difference(a: &Path, b: &Path) -> anyhow::Result<String> {
    let name = a.file_name().map_or(String::new(), |n| n.to_string_lossy().into_owned());
    let (Ok(fa), Ok(fb)) = (std::fs::File::open(a), std::fs::File::open(b)) else {
        return Ok(format!("{name} exists in only one attempt"));
    };
    let (la, lb) = (fa.metadata()?.len(), fb.metadata()?.len());
    let (mut ra, mut rb) = (BufReader::new(fa).bytes(), BufReader::new(fb).bytes());
    let mut offset = 0u64;
    loop {
        match (ra.next().transpose()?, rb.next().transpose()?) {
            (Some(x), Some(y)) if x == y => offset += 1,
            (None, None) => return Ok(format!("{name}: same bytes")),
            _ => return Ok(format!("{name} at byte {offset} (sizes {la} and {lb})")),
        }
    }
}
