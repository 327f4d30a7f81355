//! What rlmflow's test suites and benchmarks share: fixtures of published radar datasets
//! ([`datasets`]) and the module-cycle check ([`modules`]).

pub mod datasets;
pub mod modules;
