//! The `rlmflow` command line: its commands, and what every command ends with (the exit status
//! of a usage or config error). Each command's arguments and body are in `commands/`. A binary
//! builds its operator registry and calls [`main`].

use std::process::ExitCode;

use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};
use rlmflow_stages::Registry;

use crate::commands::{self, UsageError};
use crate::config::ConfigError;

#[derive(Parser)]
#[command(name = "rlmflow", version, about = "Declarative data-and-training pipelines for radar-language research")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run a pipeline, reusing every stage whose inputs and settings are unchanged.
    Run(commands::run::Args),
    /// Show each stage as cached, will run (and why) or pending, and which ones the remote cache
    /// holds.
    Status(commands::status::Args),
    /// Draw the plan: each stage instance coloured by its state (cached, will run, will be pulled
    /// from the remote cache, pending) with the reason under its label, and the artifacts between
    /// them; Mermaid (GitHub renders it) or Graphviz DOT.
    Dag(commands::dag::Args),
    /// Upload every cached result of a pipeline (or of `--only` stages) to the remote cache.
    Push(commands::Transfer),
    /// Download from the remote cache every result of a pipeline (or of `--only` stages and
    /// what they need) that the local store lacks and the remote holds.
    Pull(commands::Transfer),
    /// Show what changed in a stage's preimage since its last run; for a claim, which change
    /// between two runs made its verdict flip.
    Explain(commands::explain::Args),
    /// Each claim of `[claims]` from what the store holds (computing nothing): its verdict
    /// (holds, fails, undecided), the seeds it used, and each comparison's mean paired
    /// difference with its interval. Exits 1 when a required claim fails.
    Claims(commands::claims::Args),
    /// List a pipeline's runs, newest first: when, the git commit (and whether the tree was
    /// dirty), overrides, how many stages ran, were reused or pulled, and the headline of each
    /// stage it computed.
    Runs(commands::runs::Args),
    /// Settings and metrics side by side: two runs (default: the pipeline's last two; one RUN:
    /// that run against the latest), or with --variants the variants of one run, seeds pooled
    /// into mean ± sd. Shows only what differs unless --all.
    Compare(commands::compare::Args),
    /// Show where a stage's outputs, record and metrics are.
    Show(commands::show::Args),
    /// Remove what no root reaches: runs beyond the newest N, and the actions and objects only they used.
    Gc(commands::gc::Args),
    /// Re-hash every object; quarantine and report the damaged ones.
    Verify(commands::verify::Args),
    /// Print every instance's action key and output digest, with this machine's CPU and numeric
    /// classes, for another machine to compare with (`rlmflow verify --against FILE`). Every
    /// instance must be computed in the store.
    Digests(commands::digests::Args),
    /// Pin the current results of a pipeline under a name, so gc keeps them.
    Pin(commands::pin::Args),
    /// List stage kinds and operators with their default settings, and the settings that cannot
    /// change a result (left out of the key).
    Operators(commands::operators::Args),
    /// Make an ed25519 key pair for signing remote cache records: writes NAME.secret (for the
    /// pusher's RLMFLOW_SIGNING_KEY; keep it secret) and NAME.public, and prints the public key
    /// for readers' `remote_trusted_keys`.
    Key(commands::key::Args),
    /// Create the managed Python environment (pinned packages from the lock compiled into this
    /// binary) if it is missing, and print where it is. Stages that need it also create it on
    /// first use.
    Setup,
    /// Run one action from the store (the engine's child-process entry point).
    #[command(hide = true)]
    Exec(commands::exec::Args),
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
    crate::ui::print_store_warnings();
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
            | Command::Claims { .. }
    ) {
        // These only read and print: a reader that stops early (`| head`) ends them quietly, as
        // it ends `ls`, where a failed write would panic. The others start processes or write
        // the store, and keep Rust's default (a closed pipe is an error where it is written).
        // SAFETY: before any thread is started; SIG_DFL is a valid disposition for SIGPIPE.
        unsafe { libc::signal(libc::SIGPIPE, libc::SIG_DFL) };
    }
    match command {
        Command::Run(args) => commands::run::exec(args, registry),
        Command::Status(args) => commands::status::exec(args, registry),
        Command::Dag(args) => commands::dag::exec(args, registry),
        Command::Push(args) => commands::push::exec(args, registry),
        Command::Pull(args) => commands::pull::exec(args, registry),
        Command::Explain(args) => commands::explain::exec(args, registry),
        Command::Claims(args) => commands::claims::exec(args, registry),
        Command::Runs(args) => commands::runs::exec(args, registry),
        Command::Compare(args) => commands::compare::exec(args, registry),
        Command::Show(args) => commands::show::exec(args, registry),
        Command::Gc(args) => commands::gc::exec(args, registry),
        Command::Verify(args) => commands::verify::exec(args, registry),
        Command::Digests(args) => commands::digests::exec(args, registry),
        Command::Pin(args) => commands::pin::exec(args, registry),
        Command::Operators(args) => commands::operators::exec(args, registry),
        Command::Key(args) => commands::key::exec(args),
        Command::Setup => commands::setup::exec(),
        Command::Exec(args) => commands::exec::exec(args, registry),
    }
}
