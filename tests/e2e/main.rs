//! End-to-end tests of the engine through the `rlmflow-test` binary (the real CLI with the test
//! operators of this crate).

mod bad_input;
mod bounds;
mod claims;
mod config_errors;
mod digests;
mod engine;
mod gpus;
mod harness;
mod history;
mod hyperqueue;
mod numerics;
mod overrides;
mod remote;
mod shards;
mod store_repair;
