//! The rlmflow engine: pipeline files ([`config`]), plans and freshness ([`plan`]), the executor
//! ([`run`]) and how it starts actions ([`dispatch`]: child processes or HyperQueue tasks), the
//! child-process entry point ([`exec`]), the determinism check ([`determinism`]) and the command
//! line ([`cli`]).
//! It knows no machine learning: operators come from the registry a binary passes to
//! [`cli::main`].

pub mod cli;
pub mod config;
pub mod determinism;
pub mod dispatch;
pub mod exec;
pub mod plan;
pub mod run;
