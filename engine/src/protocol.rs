//! The wire protocol between the engine and the process running an action: lines on the
//! child's stdout that start with [`PREFIX`], each a JSON [`Message`], and the exit statuses
//! the engine reads ([`EXIT_CORRUPT_INPUT`]).

use std::io::Write;

use rlmflow_cache::Digest;
use serde::{Deserialize, Serialize};
use serde_json::Value;

pub const PREFIX: &str = "@rlmflow ";

/// Exit status of an exec whose input object failed verification (quarantined): the engine
/// recomputes the upstream action and tries again.
pub const EXIT_CORRUPT_INPUT: i32 = 3;

#[derive(Debug, Serialize, Deserialize)]
#[serde(tag = "t", rename_all = "snake_case")]
pub enum Message {
    /// Another process holds the action's lock.
    Waiting,
    /// The action was completed by another process meanwhile.
    Reused,
    Progress {
        position: u64,
        length: u64,
        message: String,
    },
    Event {
        name: String,
        data: Value,
    },
    /// The action's work in progress shows in `dir` (a training's curves in its checkpoint):
    /// the engine links its results entry there until the output is committed.
    Live {
        dir: std::path::PathBuf,
    },
    CorruptInput {
        digest: Digest,
        files: Vec<String>,
    },
    Done {
        output: Digest,
    },
    Failed {
        message: String,
        /// The setting the failure is about (dotted, relative to the stage table), when the
        /// operator said so ([`SettingError`]): the engine names its file and line.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        setting: Option<String>,
    },
}

/// Writes `message` to stdout as one protocol line.
pub fn send(message: &Message) {
    let line = format!("{PREFIX}{}\n", serde_json::to_string(message).expect("message serialises"));
    let mut out = std::io::stdout().lock();
    // A parent that died cannot read us; nothing else to do then.
    let _ = out.write_all(line.as_bytes()).and_then(|_| out.flush());
}
