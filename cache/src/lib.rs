//! rlmflow's content-addressed store.
//!
//! # Freshness is data
//!
//! Every stage run is an *action*. Its [`Preimage`] lists everything that can change its result:
//! the operator's name and hand-bumped version, the canonical settings (sorted keys, defaults
//! filled in, settings that cannot change the result left out), the seed, and the content
//! digests of its input artifacts. The action key is a BLAKE3 hash of a versioned,
//! length-prefixed encoding of that preimage. Nothing machine-specific (mtimes, absolute paths,
//! host names) enters it, so a restored store hits on any machine.
//!
//! An action is *fresh* when its record exists and the output object it names is present.
//! When it is not, the reason is computed by diffing preimages ([`Preimage::diff`]): each
//! [`Change`] names the field (`alpha 4.0 -> 1.0`, `operator version 2 -> 3`,
//! `input scenes changed`), so `rlmflow status` can say why a stage will run.
//!
//! Because inputs enter the key by *content* digest, a rerun that reproduces identical bytes
//! leaves every downstream key unchanged (early cutoff).
//!
//! # Layout and invariants
//!
//! ```text
//! objects/ab/<digest>/       an artifact directory, immutable (files read-only)
//! objects/ab/<digest>.tree   its manifest: one line per file (hash, size, mode, path)
//! actions/ab/<key>.json      the action record: preimage, output digest, timings, metrics
//! requests/ab/<key>.json     what `rlmflow exec` needs to run the action (written before it runs)
//! checkpoints/<key>/         resume state of an unfinished action
//! runs/<run-id>/             plan.json, events.jsonl and logs/ of one run
//! refs/pipelines/<name>.json the last key of every stage instance of a pipeline (a GC root)
//! refs/pins/<name>.json      keys pinned by hand (GC roots)
//! refs/links.json            the directories of links into the store (`results/`; see `links`)
//! locks/                     advisory locks: one per action key, one for the store
//! tmp/                       work directories of running actions; orphans are swept
//! quarantine/                objects and files that failed verification, kept for inspection
//! external/                  digests of external inputs' files, and their trees' manifests
//!                            (see [`external`])
//! ```
//!
//! * An action record exists only if its output object does: outputs are written in `tmp/`,
//!   hashed, renamed into `objects/`, and the record is renamed into `actions/` last.
//! * Objects are never modified in place. A corrupted object is moved to `quarantine/`, which
//!   turns every record naming it into a miss; it is never served.
//! * Locks are OS advisory locks, released by the kernel when their process dies: no lock ever
//!   needs removing by hand.

mod digest;
pub mod external;
mod gc;
mod instance;
mod links;
mod lock;
mod preimage;
mod refs;
mod store;
mod tree;
mod verify;

pub use digest::{Digest, NotADigest};
pub use gc::GcReport;
pub use links::Links;
pub use lock::Lock;
pub use instance::InstanceRef;
pub use refs::Refs;
pub use preimage::{Change, InputDigest, Preimage, canonical_json};
pub use store::{
    ActionRecord, ActionRequest, GitState, PlanEntry, PulledFrom, RecordSignature, RunPlan, SIGNED_FORMAT, Store, file_safe, now_rfc3339, run_id,
    take_all_warnings,
};
pub use tree::{TreeInfo, differing_files, hash_file, hash_tree};
pub use verify::{Corruption, DamagedFile, VerifyReport};
