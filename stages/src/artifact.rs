//! The artifact types, named once: the catalog's slots, markers and measures and each reader's
//! messages use these names.

pub const SCENES: &str = "Scenes";
pub const LABELS: &str = "Labels";
pub const CAPTIONS: &str = "Captions";
pub const TOKENS: &str = "Tokens";
pub const ENCODER: &str = "Encoder";
pub const EMBEDDINGS: &str = "Embeddings";
pub const PROBE_REPORT: &str = "ProbeReport";
pub const SEG_REPORT: &str = "SegReport";
pub const REPORT: &str = "Report";

/// The artifact type of a `files` stage: whatever files its program wrote, read by no built-in
/// stage.
pub const FILES: &str = "Files";
