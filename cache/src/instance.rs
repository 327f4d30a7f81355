//! An instance as the store names it (in refs and run plans): by what it is, not by how its
//! label renders.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// A stage instance as data: its stage, its variant per dimension (the stage that declared the
/// variants), its seed where it runs per seed, and which part it is of a sharded stage.
#[derive(Clone, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct InstanceRef {
    pub stage: String,
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty", rename = "assignment")]
    pub variants: BTreeMap<String, String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shard: Option<usize>,
}
