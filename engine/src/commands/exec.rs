//! `rlmflow exec`: one action in this process, the engine's child-process entry point
//! (`crate::exec`; a cluster task's, `crate::task`).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::bail;
use rlmflow_cache::Digest;
use rlmflow_stages::{Device, Registry};

#[derive(clap::Args)]
pub(crate) struct Args {
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
}

pub(crate) fn exec(args: Args, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Args { key, store, threads, device, scratch, remote, remote_timeout, transcript, replace } = args;
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
