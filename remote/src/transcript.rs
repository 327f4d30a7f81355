//! A cluster task's transcript on the remote (`runs/<name>`): how a task with a store of its own
//! hands its output back to the engine that submitted it.

use object_store::path::Path as Key;
use object_store::{ObjectStoreExt, PutPayload};

use crate::Remote;

/// The most bytes a cluster task's transcript (its protocol lines and output) may have.
const MAX_TRANSCRIPT_BYTES: u64 = 64 << 20;

impl Remote {
    /// Writes a cluster task's transcript (its protocol lines and other output) under
    /// `runs/<name>`, where the engine that submitted it reads it back. `false` when the remote
    /// is down or this client does not push.
    pub fn put_transcript(&self, name: &str, text: String) -> bool {
        self.push && self.call("uploading a transcript", self.objects.put(&Self::transcript_key(name), PutPayload::from(text))).is_ok()
    }

    /// A transcript [`Remote::put_transcript`] wrote, if the remote has it.
    pub fn transcript(&self, name: &str) -> Option<String> {
        let bytes = self.get("reading a transcript", &Self::transcript_key(name), MAX_TRANSCRIPT_BYTES)?.ok()?;
        Some(String::from_utf8_lossy(&bytes).into_owned())
    }

    /// Removes a transcript its engine has read (and kept in the stage's log).
    pub fn remove_transcript(&self, name: &str) {
        let _ = self.call("removing a transcript", self.objects.delete(&Self::transcript_key(name)));
    }

    fn transcript_key(name: &str) -> Key {
        Key::from(format!("runs/{name}"))
    }
}
