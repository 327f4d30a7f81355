//! One file per command, as cargo's `commands/`: each holds its arguments and its body; what
//! several share (the store, `--set` and remote arguments, the helpers below) is here.

pub(crate) mod claims;
pub(crate) mod compare;
pub(crate) mod dag;
pub(crate) mod digests;
pub(crate) mod exec;
pub(crate) mod explain;
pub(crate) mod gc;
pub(crate) mod key;
pub(crate) mod operators;
pub(crate) mod pin;
pub(crate) mod pull;
pub(crate) mod push;
pub(crate) mod run;
pub(crate) mod runs;
pub(crate) mod setup;
pub(crate) mod show;
pub(crate) mod status;
pub(crate) mod verify;

use std::path::{Path, PathBuf};

use anyhow::Context as _;
use rlmflow_cache::Store;
use rlmflow_stages::Registry;

use crate::config::{self, Pipeline};

#[derive(clap::Args)]
pub(crate) struct StoreArg {
    /// The store directory; default: `[pipeline] cache`, beside the pipeline file.
    #[arg(long, value_name = "DIR")]
    pub(crate) cache: Option<PathBuf>,
}

/// `--set STAGE.KEY=VALUE`, repeatable.
#[derive(clap::Args)]
pub(crate) struct SetArg {
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

impl SetArg {
    /// The pipeline file with these overrides over it, validated.
    pub(crate) fn load(&self, pipeline: &Path, registry: &Registry) -> anyhow::Result<Pipeline> {
        config::load_with(pipeline, &self.set, &self.set_new, registry)
    }

    /// [`SetArg::load`] at the look its store has reached ([`at_look`]).
    pub(crate) fn load_at_look(&self, pipeline: &Path, registry: &Registry, store: &StoreArg) -> anyhow::Result<Pipeline> {
        at_look(self.load(pipeline, registry)?, registry, store)
    }
}

/// A pipeline whose seeds a rule adds, at the look its store has reached (the seeds its last
/// run ended with), so a command that reads the store plans what the run did; others as they are.
pub(crate) fn at_look(mut p: Pipeline, registry: &Registry, store: &StoreArg) -> anyhow::Result<Pipeline> {
    if p.seed_rule.is_some() {
        let store = Store::open_existing(&store_root(&p, store))?;
        crate::claims::reached(&mut p, registry, store.as_ref(), rlmflow_stages::Device::Cpu)?;
    }
    Ok(p)
}

#[derive(clap::Args)]
pub(crate) struct RemoteArg {
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
    /// The remote these flags and the pipeline name, opened; `None` without one.
    pub(crate) fn open(&self, p: &Pipeline) -> anyhow::Result<Option<rlmflow_remote::Remote>> {
        self.settings(p)?.map(|r| open_remote(&r)).transpose()
    }

    /// The pipeline's remote settings with the flags over them; `None` without a URL. A bad
    /// `--remote` is a usage error (exit 2), before anything runs.
    pub(crate) fn settings(&self, p: &Pipeline) -> anyhow::Result<Option<config::RemoteSettings>> {
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
pub(crate) struct Transfer {
    pub(crate) pipeline: PathBuf,
    #[arg(long, value_name = "STAGE")]
    pub(crate) only: Vec<String>,
    #[command(flatten)]
    pub(crate) store: StoreArg,
    #[command(flatten)]
    pub(crate) remote: RemoteArg,
}

/// A command-line argument that cannot work (exit 2, like a config error).
#[derive(Debug)]
pub(crate) struct UsageError(pub(crate) String);

impl std::fmt::Display for UsageError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for UsageError {}

/// The remote `settings` name; one that cannot be used (a bad URL or endpoint, a bucket that
/// does not exist) is a usage error (exit 2).
pub(crate) fn open_remote(settings: &config::RemoteSettings) -> anyhow::Result<rlmflow_remote::Remote> {
    settings.open().map_err(|e| UsageError(format!("{e:#}")).into())
}

pub(crate) fn store_root(pipeline: &Pipeline, arg: &StoreArg) -> PathBuf {
    arg.cache.clone().unwrap_or_else(|| pipeline.cache.clone())
}

/// The store `pipeline` has run into; an error saying `nothing` (what there is not to do) where
/// it has not run yet.
pub(crate) fn ran_store(pipeline: &Pipeline, arg: &StoreArg, nothing: &str) -> anyhow::Result<Store> {
    Store::open_existing(&store_root(pipeline, arg))?.with_context(|| format!("{} has not run yet; {nothing}", pipeline.file.display()))
}

pub(crate) fn existing_store(registry: &Registry, pipeline: Option<&Path>, arg: &StoreArg) -> anyhow::Result<Store> {
    let root = match (pipeline, &arg.cache) {
        (_, Some(dir)) => dir.clone(),
        (Some(file), None) => config::load(file, registry)?.cache,
        (None, None) => PathBuf::from(".rlmflow"),
    };
    Store::open_existing(&root)?.with_context(|| format!("no rlmflow store at {}", root.display()))
}

/// Says, for a command that only asks the remote (`status`, `dag`), that it went down meanwhile
/// and what it holds was not asked.
pub(crate) fn warn_unasked(remote: Option<&rlmflow_remote::Remote>) {
    if let Some((remote, why)) = remote.and_then(|r| Some((r, r.down()?))) {
        eprintln!("warning: remote cache {} not asked: {why}", remote.url());
    }
}
