//! What `run --check-determinism` and `verify --recompute` find as they go ([`crate::determinism`]):
//! data, which `ui` puts into words.

use std::path::PathBuf;

use rlmflow_cache::Digest;

/// What a check or a recomputation finds, as it goes: data, put into words by `ui`.
pub enum Finding<'a> {
    /// An instance's check begins.
    Checking { label: &'a str, key: Digest },
    /// One attempt in a fresh process, with `env` asking for other kernels where not empty.
    Attempt { number: usize, threads: usize, env: &'a [(&'a str, &'a str)], output: Digest, seconds: f64 },
    /// Both attempts gave the same bytes; `stored`: the stored output, where it is other bytes.
    Same { stored: Option<Digest> },
    /// The attempts differ: the files that do, of how many, where the first differs, and where
    /// the two outputs are kept.
    Differs { files: Vec<String>, of: u64, first: Option<String>, kept: [PathBuf; 2] },
    /// A recomputed action's output is the one its record names.
    Agrees { label: &'a str, output: Digest },
    /// It is not: what the record names and who signed it, what was recomputed, and where.
    Disagrees { label: &'a str, recorded: Digest, signers: String, recomputed: Digest, kept: PathBuf },
}
