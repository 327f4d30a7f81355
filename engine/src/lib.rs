//! The rlmflow engine: pipeline files ([`config`]), plans and freshness ([`plan`]), the executor
//! ([`run`]), the memory check before it ([`footprint`]), the numeric platform class a model
//! action's key carries ([`platform`]), how it starts actions ([`dispatch`]: child processes or HyperQueue tasks), the
//! child-process entry point ([`exec`]), the determinism check ([`determinism`]) and the command
//! line ([`cli`]).
//! It knows no machine learning and depends on no operator: operators come from the registry a
//! binary passes to [`cli::main`] (`rlmflow` registers the shipped ones, `rlmflow-torch` the
//! libtorch ones, the end-to-end tests their own).

pub mod cli;
pub mod config;
pub mod determinism;
pub mod dispatch;
pub mod exec;
pub mod footprint;
pub mod plan;
pub mod platform;
pub mod run;
mod ui;
