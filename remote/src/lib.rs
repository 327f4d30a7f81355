//! The remote cache: artifacts and action records shared between machines through object
//! storage, so a fresh CI runner, a laptop or a cluster worker reuses what was computed anywhere.
//!
//! # Layout and protocol
//!
//! ```text
//! <prefix>/cas/<digest>.tar   an artifact directory as one tar (one request per artifact)
//! <prefix>/ac/<key>.json      an action record (the local store's, byte for byte)
//! <prefix>/runs/<run>/<task>  a cluster task's transcript, until the engine that submitted it reads it
//! ```
//!
//! * **Objects first, the record last.** A push uploads the artifact, then the record; a push
//!   killed half-way leaves at most an object no record names, never a record whose object is
//!   missing.
//! * **A record is a hit only with its object.** A pull reads the record, then the object it
//!   names; either missing is a miss.
//! * **Nothing unverified enters the store.** A downloaded artifact is unpacked into the store's
//!   `tmp/`, re-hashed, and committed through the store's own protocol only when its digest is the
//!   one the record names; a flipped byte or a truncated tar is a miss that says so
//!   ([`Pulled::Corrupt`]), and when pushing, the recomputed artifact replaces it.
//! * **Create if absent.** Content-addressed objects are uploaded only when the remote lacks them
//!   (identical content makes a second upload harmless; an object known to be corrupt is
//!   overwritten); records are written once per key.
//! * **Never a single point of failure.** Every request is bounded by a timeout; the first failure
//!   marks the remote down for the rest of the process ([`Remote::down`]) and every later call
//!   answers at once, so an unreachable server costs one timeout and one warning.
//!
//! A remote is read-only unless made with `push`: pull requests and laptops read, trusted CI
//! writes.
//!
//! Here: the client, its requests bounded by the timeout, and what each call found. Beside it,
//! one job a module: `config` (the URL and `AWS_*` checks, opening a client), `pull` (record
//! and artifact into the store, verified), `push` (artifact, then record, signed), `archive`
//! (the tar an artifact travels as, unpacked within its record's bounds), `transcript` (a cluster
//! task's output handed back), `signing` (record signatures, trusted keys) and `link` (the HTTP
//! client whose bodies report their bytes).

mod archive;
mod config;
mod link;
mod pull;
mod push;
pub mod signing;
mod transcript;

pub use config::{BadRemote, check_url};

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use link::Watch;
use object_store::path::Path as Key;
use object_store::{ObjectStore, ObjectStoreExt};
use rlmflow_cache::{ActionRecord, Digest};
use signing::{SigningKey, Trust, TrustedKeys};

/// A remote cache at one URL. Shared by threads: pulls run beside the stages that compute.
pub struct Remote {
    url: String,
    objects: Arc<dyn ObjectStore>,
    runtime: tokio::runtime::Runtime,
    timeout: Duration,
    /// Whether this client uploads.
    pub push: bool,
    /// Why the remote stopped being used, once a request failed.
    down: Mutex<Option<RemoteError>>,
    /// Whether [`Remote::newly_down`] has told it.
    told: AtomicBool,
    /// The keys whose signatures make a record usable (none: every record is, unverified).
    trusted: TrustedKeys,
    /// The key this client signs the records it uploads with.
    signer: Option<SigningKey>,
    /// Whether the remote takes an upload in parts (S3 and a directory do; WebDAV does not).
    parts: bool,
}

/// Why a request to the remote failed: the first one marks the remote down for the process
/// ([`Remote::down`]), and every later request answers with it at once.
#[derive(Clone, Debug, PartialEq)]
pub enum RemoteError {
    /// Nothing crossed the link for `timeout` while `doing` it; `cut`: the kernel closed the
    /// connection (its unacknowledged bytes waited that long), else the wait ran out.
    Stalled { doing: String, timeout: Duration, cut: bool },
    /// The request failed while `doing` it; `message` is the client's or the server's.
    Failed { doing: String, message: String },
    /// An upload asked of a client not made with `push`.
    ReadOnly,
}

impl std::fmt::Display for RemoteError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RemoteError::Stalled { doing, timeout, cut } => {
                write!(
                    f,
                    "{doing}: nothing arrived or left for {:.0} s{}",
                    timeout.as_secs_f64(),
                    if *cut { " (the connection was cut)" } else { "" }
                )
            }
            RemoteError::Failed { doing, message } => write!(f, "{doing}: {message}"),
            RemoteError::ReadOnly => write!(f, "this client does not push"),
        }
    }
}

impl std::error::Error for RemoteError {}

/// Whether [`Remote::fetch_object`] found an artifact.
pub enum Fetched {
    /// The local store had it already.
    Present,
    /// Downloaded (this many bytes), verified and committed.
    Downloaded(u64),
    Missing,
    /// The remote is down (this request failed, or an earlier one did).
    Unreachable(RemoteError),
    /// The remote's copy is not that digest's (`why`); nothing entered the store.
    Corrupt(String),
}

/// What a push did.
pub struct Pushed {
    /// Bytes uploaded (0: the remote had both).
    pub bytes: u64,
    /// The remote already held a record of this key naming another output: what it says (left
    /// as it was: a disagreement is an alarm for a person, not something to overwrite).
    pub disagrees: Option<String>,
    /// Why nothing was pushed though the remote is up: the record is larger than a reader takes
    /// ([`MAX_RECORD_BYTES`]; a setting holding megabytes of text makes one).
    pub refused: Option<String>,
}

/// What a pull found.
pub enum Pulled {
    /// The record and its artifact, now in the local store.
    Hit {
        record: Box<ActionRecord>,
        bytes: u64,
        seconds: f64,
    },
    Miss,
    /// The remote is down (this request failed, or an earlier one did).
    Unreachable(RemoteError),
    /// The remote's artifact is not the one its record names (`why`); nothing entered the store.
    Corrupt {
        why: String,
    },
    /// The record is not signed by a trusted key (`why`: unsigned, untrusted signers, forged);
    /// nothing entered the store.
    Untrusted {
        why: String,
    },
}

impl Remote {
    /// This client with trusted keys (a record is used only if one of them signed it) and the
    /// key it signs its uploads with.
    pub fn with_trust(mut self, trusted: TrustedKeys, signer: Option<SigningKey>) -> Remote {
        self.trusted = trusted;
        self.signer = signer;
        self
    }

    /// Whether records are checked against trusted keys; without, every record is used unverified.
    pub fn verified(&self) -> bool {
        !self.trusted.is_empty()
    }

    /// Whether a record may be used here, and the trusted key that signed it (`None`: no trusted
    /// keys are set, so it is used unverified); `Err(why)` when trusted keys are set and none
    /// signed it.
    fn trusts(&self, record: &ActionRecord) -> Result<Option<String>, String> {
        if self.trusted.is_empty() {
            return Ok(None);
        }
        match self.trusted.check(record) {
            Trust::Signed { name, fingerprint } => Ok(Some(format!("`{name}` (key {fingerprint})"))),
            other => Err(format!("its record is {other}")),
        }
    }

    pub fn url(&self) -> &str {
        &self.url
    }

    /// The longest a transfer may wait for its next bytes.
    pub fn timeout(&self) -> Duration {
        self.timeout
    }

    /// Why the remote is no longer asked, if a request failed.
    pub fn down(&self) -> Option<RemoteError> {
        self.down.lock().unwrap().clone()
    }

    /// Whether the remote is down and no caller was told yet (this one is now): a caller warns
    /// once, though every request after the first failure answers with it.
    pub fn newly_down(&self) -> bool {
        self.down().is_some() && !self.told.swap(true, Ordering::Relaxed)
    }

    /// Runs one request until it ends or waits for its next bytes longer than the timeout; the
    /// first failure marks the remote down.
    fn call<T>(&self, what: &str, request: impl Future<Output = object_store::Result<T>>) -> Result<Option<T>, RemoteError> {
        self.watched(what, &Watch::new(), request, &mut |_| {})
    }

    /// [`Remote::call`] as one step of the transfer `watch` follows; `tick` hears it every
    /// fraction of a second while the request runs.
    fn watched<T>(
        &self,
        what: &str,
        watch: &Arc<Watch>,
        request: impl Future<Output = object_store::Result<T>>,
        tick: &mut dyn FnMut(&Watch),
    ) -> Result<Option<T>, RemoteError> {
        if let Some(down) = self.down() {
            return Err(down);
        }
        let (doing, timeout) = (what.to_owned(), self.timeout);
        let why = match self.runtime.block_on(link::bounded(watch, self.timeout, request, tick)) {
            Some(Ok(value)) => return Ok(Some(value)),
            Some(Err(object_store::Error::NotFound { .. })) => return Ok(None),
            Some(Err(e)) if link::cut_by_the_kernel(&e) => RemoteError::Stalled { doing, timeout, cut: true },
            Some(Err(e)) => RemoteError::Failed { doing, message: e.to_string() },
            None => RemoteError::Stalled { doing, timeout, cut: false },
        };
        Err(self.down.lock().unwrap().get_or_insert(why).clone())
    }

    /// The whole body of `key` if it is at most `limit` bytes: `None` when it is absent or the
    /// remote is down, `Some(Err(size))` when it is larger (refused by its declared size before
    /// its bytes are read, or by what arrived).
    fn get(&self, what: &str, key: &Key, limit: u64) -> Option<Result<Vec<u8>, u64>> {
        let mut body = Vec::new();
        let mut sink = |chunk: &[u8]| {
            body.extend_from_slice(chunk);
            Ok(())
        };
        match self.stream(what, key, limit, &mut sink, &mut |_, _| {}).ok()?? {
            Streamed::Whole(_) => Some(Ok(body)),
            Streamed::TooLarge(size) => Some(Err(size)),
        }
    }

    /// The body of `key`, chunk by chunk into `sink` as it arrives (so nothing holds all of a
    /// large artifact), if it is at most `limit` bytes; `Ok(None)` when it is absent or the remote
    /// is down. The timeout bounds the wait for each chunk.
    fn stream(
        &self,
        what: &str,
        key: &Key,
        limit: u64,
        sink: &mut dyn FnMut(&[u8]) -> std::io::Result<()>,
        progress: &mut dyn FnMut(u64, u64),
    ) -> std::io::Result<Option<Streamed>> {
        use futures_util::StreamExt as _;
        let watch = Watch::new();
        let Ok(Some(found)) = self.watched(what, &watch, self.objects.get(key), &mut |_| {}) else { return Ok(None) };
        let total = found.meta.size;
        if total > limit {
            return Ok(Some(Streamed::TooLarge(total)));
        }
        let mut stream = found.into_stream();
        let mut received = 0u64;
        loop {
            match self.watched(what, &watch, async { stream.next().await.transpose() }, &mut |_| {}) {
                Ok(Some(Some(chunk))) => {
                    received += chunk.len() as u64;
                    if received > limit {
                        return Ok(Some(Streamed::TooLarge(received)));
                    }
                    sink(&chunk)?;
                    progress(received, total);
                }
                Ok(Some(None)) => return Ok(Some(Streamed::Whole(received))),
                _ => return Ok(None),
            }
        }
    }

    /// `key`'s record on the remote: `None` when it is absent or the remote is down,
    /// `Some(Err(why))` when it is larger than [`MAX_RECORD_BYTES`] or is no record.
    fn record(&self, key: &Digest) -> Option<Result<ActionRecord, String>> {
        Some(match self.get("reading a record", &Self::record_key(key), MAX_RECORD_BYTES)? {
            Ok(bytes) => serde_json::from_slice::<ActionRecord>(&bytes).map_err(|e| format!("the record of {} is not a record ({e})", key.short())),
            Err(size) => Err(format!("the record of {} has {size} bytes; a record has at most {MAX_RECORD_BYTES}", key.short())),
        })
    }

    fn record_key(key: &Digest) -> Key {
        Key::from(format!("ac/{}.json", key.hex()))
    }

    fn object_key(digest: &Digest) -> Key {
        Key::from(format!("cas/{}.tar", digest.hex()))
    }
}

/// The most bytes an action record may have on the remote, checked before it is read: the
/// shipped pipelines' largest is under 4 kB, and a report gathering a thousand inputs stays
/// under 200 kB.
pub const MAX_RECORD_BYTES: u64 = 256 << 10;

/// How a body with a size limit was read.
enum Streamed {
    /// All of it, this many bytes.
    Whole(u64),
    /// Not read on: it has (or had sent) this many bytes, more than the limit.
    TooLarge(u64),
}

#[cfg(test)]
mod tests {
    use super::*;
    use rlmflow_cache::Store;

    /// A download reports its bytes as they arrive, chunk by chunk, up to the whole.
    #[test]
    fn a_pull_reports_its_progress_in_chunks() {
        let root = std::env::temp_dir().join(format!("rlmflow-remote-progress-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let (a, b) = (Store::open(&root.join("a")).unwrap(), Store::open(&root.join("b")).unwrap());
        let dir = a.work_dir(&Digest::of(b"x")).unwrap();
        std::fs::write(dir.join("data.bin"), vec![7u8; 100_000]).unwrap();
        let digest = a.commit_tree(&dir).unwrap().digest;
        let remote = Remote::open(&format!("file://{}", root.join("remote").display()), true, Duration::from_secs(5)).unwrap();
        assert!(remote.push_object(&a, &digest, false, &mut |_, _| {}).unwrap().is_ok());
        let mut heard = Vec::new();
        assert!(matches!(remote.fetch_object(&b, &digest, &mut |done, total| heard.push((done, total))).unwrap(), Fetched::Downloaded(_)));
        assert!(heard.len() > 1, "more than one chunk: {heard:?}");
        let (done, total) = *heard.last().unwrap();
        assert_eq!(done, total);
        assert!(heard.windows(2).all(|w| w[0].0 < w[1].0));
        assert!(b.has_object(&digest));
        std::fs::remove_dir_all(&root).unwrap();
    }

    /// What the remote declares is checked before its bytes are taken: a tar whose entries
    /// declare more than its record's files and bytes, a sparse file, a link, a tar larger than
    /// those files could make, a record past the cap. Nothing enters the store.
    #[test]
    fn a_remote_object_or_record_is_refused_by_what_it_declares_before_its_bytes() {
        let root = std::env::temp_dir().join(format!("rlmflow-remote-bounds-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let (a, b) = (Store::open(&root.join("a")).unwrap(), Store::open(&root.join("b")).unwrap());
        let dir = a.work_dir(&Digest::of(b"y")).unwrap();
        std::fs::write(dir.join("data.bin"), vec![1u8; 1000]).unwrap();
        let digest = a.commit_tree(&dir).unwrap().digest;
        let remote = Remote::open(&format!("file://{}", root.join("remote").display()), true, Duration::from_secs(5)).unwrap();
        assert!(remote.push_object(&a, &digest, false, &mut |_, _| {}).unwrap().is_ok());
        let object = root.join("remote").join(format!("cas/{}.tar", digest.hex()));
        let refused = |tar: Vec<u8>| -> String {
            std::fs::write(&object, tar).unwrap();
            match remote.fetch_accepted(&b, &digest, Some((1, 1000)), &|_| Ok(()), &mut |_, _| {}).unwrap() {
                Fetched::Corrupt(why) => why,
                _ => panic!("a crafted tar was used"),
            }
        };
        let entry = |kind: tar::EntryType, size: u64| -> Vec<u8> {
            let mut header = tar::Header::new_gnu();
            header.set_path("data.bin").unwrap();
            header.set_entry_type(kind);
            header.set_size(size);
            header.set_mode(0o644);
            if kind == tar::EntryType::GNUSparse {
                // 4 GiB as its GNU header declares it, from one block of data at its end.
                let gnu = header.as_gnu_mut().unwrap();
                gnu.set_real_size(4 << 30);
                gnu.sparse[0].set_offset((4 << 30) - 512);
                gnu.sparse[0].set_length(512);
            }
            header.set_cksum();
            let mut bytes = header.as_bytes().to_vec();
            bytes.extend(vec![0u8; 1024]);
            bytes
        };
        let why = refused(entry(tar::EntryType::Regular, 4 << 30));
        assert!(why.contains("`data.bin` takes it past its record's 1 files and 1000 bytes"), "{why}");
        let why = refused(entry(tar::EntryType::GNUSparse, 512));
        assert!(why.contains("`data.bin` is a GNUSparse entry"), "{why}");
        let why = refused(entry(tar::EntryType::Symlink, 0));
        assert!(why.contains("`data.bin` is a Symlink entry"), "{why}");
        let why = refused(vec![0u8; 2 << 20]);
        assert!(why.contains("its artifact's tar has 2097152 bytes, more than its record's files could take"), "{why}");
        assert!(!b.has_object(&digest));
        // A record past the cap is refused by its size.
        let key = Digest::of(b"a key");
        std::fs::create_dir_all(root.join("remote/ac")).unwrap();
        std::fs::write(root.join(format!("remote/ac/{}.json", key.hex())), vec![b' '; 300_000]).unwrap();
        let why = remote.record(&key).unwrap().unwrap_err();
        assert!(why.contains("has 300000 bytes; a record has at most 262144"), "{why}");
        std::fs::remove_dir_all(&root).unwrap();
    }
}
