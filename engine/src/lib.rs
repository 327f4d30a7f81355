//! The rlmflow engine: pipeline files ([`config`]), plans ([`plan`]), why an instance runs
//! ([`reason`]), what a run establishes before it starts ([`preflight`], with the memory check,
//! [`footprint`]), the scheduler ([`run`], with its budget, remote exchange, results links and
//! provenance), the numeric
//! platform class a model action's key carries ([`platform`]), how it starts actions
//! ([`dispatch`]: child processes or HyperQueue tasks) and talks to them ([`protocol`]), the
//! child-process entry point ([`exec`]) and the cluster task with a store of its own ([`task`]),
//! the determinism check ([`determinism`]), the plan drawn ([`dag`]), past runs ([`history`]) and
//! their comparison ([`compare`]), what a person sees (`ui`)
//! and the command line ([`cli`]).
//! It knows no machine learning and depends on no operator: operators come from the registry a
//! binary passes to [`cli::main`] (`rlmflow` registers the shipped ones, `rlmflow-torch` the
//! libtorch ones, the end-to-end tests their own).

pub mod claims;
pub mod cli;
mod commands;
pub mod compare;
pub mod config;
pub mod dag;
pub mod determinism;
pub mod digests;
pub mod dispatch;
pub mod event;
pub mod exec;
mod finding;
pub mod footprint;
pub mod gpus;
pub mod history;
pub mod plan;
pub mod platform;
pub mod preflight;
pub mod protocol;
pub mod reason;
pub mod run;
pub mod task;
mod ui;
