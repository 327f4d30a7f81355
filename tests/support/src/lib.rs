//! What rlmflow's test suites and benchmarks share: a self-removing scratch directory
//! ([`scratch`]), running the binaries and finding their outputs ([`cli`]), a fake OpenAI
//! endpoint ([`openai`]), real servers started from PyPI ([`servers`]), TensorBoard's event reader
//! ([`tensorboard`]), both in scratch Python environments ([`venv`]), fixtures of published radar datasets ([`datasets`]), the module-cycle
//! check ([`modules`]), the crates' layers ([`layers`]) and the tests ARCHITECTURE.md's invariants
//! name ([`invariants`]).

pub mod cli;
pub mod datasets;
pub mod invariants;
pub mod layers;
pub mod modules;
pub mod openai;
pub mod scratch;
pub mod servers;
pub mod tensorboard;
pub mod venv;

pub use scratch::Scratch;
