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

mod link;
pub mod signing;

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use link::{Watch, WatchedConnector};
use object_store::aws::{AmazonS3Builder, AmazonS3ConfigKey};
use object_store::path::Path as Key;
use object_store::{ClientOptions, ObjectStore, ObjectStoreExt, PutPayload, RetryConfig};
use rlmflow_cache::{ActionRecord, Digest, PulledFrom, SIGNED_FORMAT, Store, hash_tree};
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

/// `Ok` for a remote URL this client can use, else what is wrong with it and what is valid:
/// checked before any client is built (a malformed endpoint would otherwise panic inside the S3
/// client), for `[pipeline] remote` at validation and for `--remote` before a run.
pub fn check_url(url: &str) -> Result<(), BadRemote> {
    const VALID: &str = "valid: s3://bucket/prefix, https://host/path (WebDAV), file:///path";
    let bad = |problem: String| Err(BadRemote { variable: None, problem });
    if let Some(rest) = url.strip_prefix("s3://") {
        if rest.split('/').next().is_none_or(str::is_empty) {
            return bad(format!("`{url}` names no bucket; {VALID}"));
        }
        // Every variable the S3 client reads, and the endpoint it names.
        s3_from_env()?;
        for var in ["AWS_ENDPOINT_URL", "AWS_ENDPOINT"] {
            if let Ok(endpoint) = std::env::var(var) {
                let in_variable = |problem| BadRemote { variable: Some(var.to_owned()), problem };
                check_endpoint(&format!("the environment variable {var}"), &aws_value(var, &endpoint)?).map_err(in_variable)?;
            }
        }
        Ok(())
    } else if url.starts_with("http://") || url.starts_with("https://") {
        check_endpoint("the remote", url).or_else(bad)
    } else if let Some(path) = url.strip_prefix("file://") {
        match path {
            "" => bad(format!("`{url}` names no directory; {VALID}")),
            p if !Path::new(p).is_absolute() => bad(format!("`{url}` is not an absolute path; {VALID}")),
            _ => Ok(()),
        }
    } else {
        bad(format!("`{url}`: unknown scheme; {VALID}"))
    }
}

/// A remote URL, or an `AWS_*` variable the S3 client reads, that this client cannot use:
/// [`check_url`]'s answer, before any client is built.
#[derive(Clone, Debug, PartialEq)]
pub struct BadRemote {
    /// The environment variable at fault; `None`: the URL.
    pub variable: Option<String>,
    /// What is wrong, and what would be valid (it names the variable, never its value).
    pub problem: String,
}

impl std::fmt::Display for BadRemote {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.problem)
    }
}

impl std::error::Error for BadRemote {}

/// The S3 client's settings from the standard `AWS_*` variables, read as
/// `AmazonS3Builder::from_env` reads them, but each value without surrounding whitespace (a value
/// from a secrets file ends with a newline more often than not) and a control character inside a
/// value refused by the variable's name: the client panics on either.
fn s3_from_env() -> Result<AmazonS3Builder, BadRemote> {
    let mut builder = AmazonS3Builder::new();
    for (name, value) in std::env::vars_os().filter_map(|(k, v)| Some((k.into_string().ok()?, v.into_string().ok()?))) {
        if let Some(key) = name.starts_with("AWS_").then(|| name.to_ascii_lowercase().parse::<AmazonS3ConfigKey>().ok()).flatten() {
            builder = builder.with_config(key, aws_value(&name, &value)?);
        }
    }
    Ok(builder)
}

/// The value of the environment variable `name` without surrounding whitespace; an error naming
/// the variable (never its value: it may be a secret) for a control character inside it.
fn aws_value(name: &str, value: &str) -> Result<String, BadRemote> {
    let trimmed = value.trim();
    match trimmed.char_indices().find(|(_, c)| c.is_control()) {
        Some((at, c)) => Err(BadRemote {
            variable: Some(name.to_owned()),
            problem: format!(
                "the environment variable {name} holds the control character {c:?} at byte {at} of its value; valid: a value without control characters (surrounding whitespace is dropped)"
            ),
        }),
        None => Ok(trimmed.to_owned()),
    }
}

/// `Ok` for an http(s) URL with a host (and a valid port).
fn check_endpoint(what: &str, endpoint: &str) -> Result<(), String> {
    let valid = "valid: http(s)://host[:port][/path]";
    let url = reqwest::Url::parse(endpoint).map_err(|e| format!("{what} `{endpoint}` is not a URL ({e}); {valid}"))?;
    if !matches!(url.scheme(), "http" | "https") || url.host_str().is_none_or(str::is_empty) {
        return Err(format!("{what} `{endpoint}` is not an http(s) URL with a host; {valid}"));
    }
    Ok(())
}

impl Remote {
    /// `s3://bucket/prefix` (endpoint and credentials from the standard `AWS_*` variables,
    /// `AWS_ENDPOINT_URL` for a non-AWS server), `http(s)://host/path` (WebDAV, a Bazel-style
    /// HTTP cache) or `file:///path`. A bad URL or endpoint is an error ([`check_url`]).
    pub fn open(url: &str, push: bool, timeout: Duration) -> anyhow::Result<Remote> {
        check_url(url).map_err(|problem| anyhow::anyhow!("remote {problem}"))?;
        // TLS on ring; an error only says a provider is installed already.
        let _ = rustls::crypto::ring::default_provider().install_default();
        // No whole-request timeout: it would cut off a large transfer that is still moving. The
        // link's client bounds the wait to connect; `call` bounds the wait for the next bytes
        // either way.
        let client = ClientOptions::new().with_timeout_disabled().with_allow_http(true);
        let retry = RetryConfig { max_retries: 1, retry_timeout: timeout, ..RetryConfig::default() };
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
        let objects: Arc<dyn ObjectStore> = if let Some(rest) = url.strip_prefix("s3://") {
            let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
            let store = s3_from_env()
                .map_err(|problem| anyhow::anyhow!("remote {problem}"))?
                .with_bucket_name(bucket)
                .with_client_options(client)
                .with_http_connector(WatchedConnector { timeout })
                .with_retry(retry)
                .build()
                .with_context(|| format!("remote `{url}`"))?;
            // A bucket that does not exist would read as an empty cache: asked once here. A
            // server that does not answer is not an error yet (the first request marks it down).
            let listed = runtime.block_on(link::bounded(&Watch::new(), timeout, store.list_with_delimiter(None), &mut |_| {}));
            if let Some(Err(e)) = listed
                && (matches!(e, object_store::Error::NotFound { .. }) || e.to_string().contains("NoSuchBucket"))
            {
                let endpoint = std::env::var("AWS_ENDPOINT_URL")
                    .or_else(|_| std::env::var("AWS_ENDPOINT"))
                    .map_or_else(|_| "AWS".into(), |e| e.trim().to_owned());
                bail!("remote `{url}`: bucket `{bucket}` does not exist at {endpoint}");
            }
            Arc::new(object_store::prefix::PrefixStore::new(store, prefix))
        } else if url.starts_with("http://") || url.starts_with("https://") {
            Arc::new(
                object_store::http::HttpBuilder::new()
                    .with_url(url)
                    .with_client_options(client)
                    .with_http_connector(WatchedConnector { timeout })
                    .with_retry(retry)
                    .build()
                    .with_context(|| format!("remote `{url}`"))?,
            )
        } else if let Some(path) = url.strip_prefix("file://") {
            std::fs::create_dir_all(path).with_context(|| format!("remote `{url}`: creating {path}"))?;
            Arc::new(object_store::local::LocalFileSystem::new_with_prefix(path).with_context(|| format!("remote `{url}`"))?)
        } else {
            bail!("remote `{url}`: unknown scheme; valid: s3://bucket/prefix, https://host/path (WebDAV), file:///path");
        };
        Ok(Remote {
            url: url.to_owned(),
            objects,
            runtime,
            timeout,
            push,
            down: Mutex::new(None),
            told: Default::default(),
            trusted: TrustedKeys::default(),
            signer: None,
            parts: !url.starts_with("http"),
        })
    }

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

    /// Whether the remote holds `key`'s record and the object it names (a miss when it is down).
    pub fn holds(&self, key: &Digest) -> bool {
        let Some(Ok(record)) = self.record(key) else { return false };
        self.trusts(&record).is_ok() && matches!(self.call("checking an object", self.objects.head(&Self::object_key(&record.output))), Ok(Some(_)))
    }

    /// Fetches `key`'s record and artifact into `store`, verified, the artifact also by
    /// `accept` (its type, before it is committed); a miss when the remote lacks either or is
    /// down. `progress` hears the artifact's bytes as they arrive.
    pub fn pull(
        &self,
        store: &Store,
        key: &Digest,
        accept: &dyn Fn(&Path) -> Result<(), String>,
        progress: &mut dyn FnMut(u64, u64),
    ) -> anyhow::Result<Pulled> {
        let clock = Instant::now();
        let mut record = match self.record(key) {
            None => return Ok(self.down().map_or(Pulled::Miss, Pulled::Unreachable)),
            Some(Ok(r)) if r.key == *key && r.preimage.key() == *key => r,
            Some(Ok(_)) => return Ok(Pulled::Corrupt { why: format!("the record of {} is not that key's", key.short()) }),
            Some(Err(why)) => return Ok(Pulled::Corrupt { why }),
        };
        let signed_by = match self.trusts(&record) {
            Ok(signed_by) => signed_by,
            Err(why) => return Ok(Pulled::Untrusted { why }),
        };
        record.pulled = Some(PulledFrom { remote: self.url.clone(), signed_by });
        let bytes = match self.fetch_accepted(store, &record.output, Some((record.files, record.bytes)), accept, progress)? {
            Fetched::Present => 0,
            Fetched::Downloaded(bytes) => bytes,
            Fetched::Missing => return Ok(Pulled::Miss),
            Fetched::Unreachable(e) => return Ok(Pulled::Unreachable(e)),
            Fetched::Corrupt(why) => return Ok(Pulled::Corrupt { why }),
        };
        store.write_record(&record)?;
        Ok(Pulled::Hit { record: Box::new(record), bytes, seconds: clock.elapsed().as_secs_f64() })
    }

    /// Fetches the artifact `digest` into `store`, verified, unless the store has it: what a
    /// cluster task does for each input it lacks.
    pub fn fetch_object(&self, store: &Store, digest: &Digest, progress: &mut dyn FnMut(u64, u64)) -> anyhow::Result<Fetched> {
        self.fetch_accepted(store, digest, None, &|_| Ok(()), progress)
    }

    /// [`Remote::fetch_object`], the unpacked artifact also checked by `accept` before it is
    /// committed. With `expected` (its record's files and bytes), the object is refused when its
    /// size could not be such a tar's, and its entries when they declare more.
    fn fetch_accepted(
        &self,
        store: &Store,
        digest: &Digest,
        expected: Option<(u64, u64)>,
        accept: &dyn Fn(&Path) -> Result<(), String>,
        progress: &mut dyn FnMut(u64, u64),
    ) -> anyhow::Result<Fetched> {
        if store.has_object(digest) {
            return Ok(match accept(&store.object_dir(digest)) {
                Ok(()) => Fetched::Present,
                Err(why) => Fetched::Corrupt(why),
            });
        }
        // Streamed to a file in one work directory, then unpacked into another; the digest's lock
        // keeps another process's sweep of `tmp/` off both meanwhile.
        let _held = store.lock_action(digest)?;
        let scratch = store.work_dir(digest)?;
        let dir = store.work_dir(digest)?;
        let tar_path = scratch.join("artifact.tar");
        let mut file = std::io::BufWriter::new(std::fs::File::create(&tar_path).with_context(|| format!("creating {}", tar_path.display()))?);
        let limit = expected.map_or(u64::MAX, |(files, bytes)| largest_tar(files, bytes));
        let received =
            self.stream("reading an object", &Self::object_key(digest), limit, &mut |chunk| std::io::Write::write_all(&mut file, chunk), progress);
        let received = received.and_then(|r| std::io::Write::flush(&mut file).map(|()| r));
        drop(file);
        let tar_bytes = match received.with_context(|| format!("writing {}", tar_path.display()))? {
            Some(Streamed::Whole(bytes)) => bytes,
            outcome => {
                remove_dir(&scratch);
                remove_dir(&dir);
                return Ok(match outcome {
                    Some(Streamed::TooLarge(size)) => {
                        Fetched::Corrupt(format!("its artifact's tar has {size} bytes, more than its record's files could take ({limit})"))
                    }
                    _ => self.down().map_or(Fetched::Missing, Fetched::Unreachable),
                });
            }
        };
        let (files, bytes) = expected.unwrap_or((u64::MAX, tar_bytes));
        let unpacked = unpack_bounded(&tar_path, &dir, files, bytes);
        remove_dir(&scratch);
        match unpacked.and_then(|()| Ok(hash_tree(&dir)?.digest)) {
            Ok(found)
                if found == *digest
                    && let Err(why) = accept(&dir) =>
            {
                remove_dir(&dir);
                Ok(Fetched::Corrupt(why))
            }
            Ok(found) if found == *digest => {
                store.commit_tree(&dir)?;
                Ok(Fetched::Downloaded(tar_bytes))
            }
            other => {
                remove_dir(&dir);
                Ok(Fetched::Corrupt(match other {
                    Ok(found) => format!("its artifact hashes to {}, not {}", found.short(), digest.short()),
                    Err(e) => format!("its artifact does not unpack ({e:#})"),
                }))
            }
        }
    }

    /// Uploads `record` and its artifact from `store`: the object unless the remote has it (or
    /// `replace`: it is known corrupt or untrusted), then the record unless the remote has one.
    /// A record already there that names another output is reported, not overwritten; one that
    /// agrees but lacks this client's signature gets it. The inner error when the remote is down
    /// or this client does not push. `progress` hears the artifact's bytes as they leave.
    pub fn push(
        &self,
        store: &Store,
        record: &ActionRecord,
        replace: bool,
        progress: &mut dyn FnMut(u64, u64),
    ) -> anyhow::Result<Result<Pushed, RemoteError>> {
        // Where this store got it is this store's business, not the remote's readers'.
        let record = &ActionRecord { pulled: None, ..record.clone() };
        let signed = self.signer.as_ref().map(|key| key.sign(record));
        let body = serde_json::to_vec_pretty(signed.as_ref().unwrap_or(record))?;
        if body.len() as u64 > MAX_RECORD_BYTES {
            let why = format!("its record has {} bytes; readers take records of at most {MAX_RECORD_BYTES}, so it is not pushed", body.len());
            return Ok(Ok(Pushed { bytes: 0, disagrees: None, refused: Some(why) }));
        }
        let mut bytes = match self.push_object(store, &record.output, replace, progress)? {
            Ok(bytes) => bytes,
            Err(e) => return Ok(Err(e)),
        };
        let key = Self::record_key(&record.key);
        let present = match self.call("checking a record", self.objects.head(&key)) {
            Ok(present) => present,
            Err(e) => return Ok(Err(e)),
        };
        let mut write = present.is_none() || replace;
        let mut disagrees = None;
        if !write {
            let theirs = self.record(&record.key).and_then(Result::ok);
            match theirs {
                Some(theirs) if theirs.output != record.output => {
                    let signers = signing::signers(&theirs);
                    disagrees = Some(format!(
                        "the remote's record of {} names output {} ({signers}), but this run computed {}; the remote's is left as it was",
                        record.key.short(),
                        theirs.output.short(),
                        record.output.short()
                    ));
                }
                Some(theirs) => {
                    write = self.signer.as_ref().is_some_and(|s| !theirs.signatures.iter().any(|t| t.key == s.name() && t.format == SIGNED_FORMAT))
                }
                None => {}
            }
        }
        if write {
            bytes += body.len() as u64;
            if let Err(e) = self.call("uploading a record", self.objects.put(&key, PutPayload::from(body))) {
                return Ok(Err(e));
            }
        }
        Ok(Ok(Pushed { bytes, disagrees, refused: None }))
    }

    /// Uploads the artifact `digest` from `store` unless the remote has it (or `replace`): what
    /// the engine does for a cluster task's inputs. Returns the bytes uploaded, or the inner
    /// error when the remote is down or this client does not push. `progress` hears the bytes as
    /// they leave.
    pub fn push_object(
        &self,
        store: &Store,
        digest: &Digest,
        replace: bool,
        progress: &mut dyn FnMut(u64, u64),
    ) -> anyhow::Result<Result<u64, RemoteError>> {
        if !self.push {
            return Ok(Err(RemoteError::ReadOnly));
        }
        let object = Self::object_key(digest);
        match self.call("checking an object", self.objects.head(&object)) {
            Ok(Some(_)) if !replace => return Ok(Ok(0)),
            Err(e) => return Ok(Err(e)),
            Ok(_) => {}
        }
        // Packed into a file in a work directory of the store's `tmp/`, then sent from it; the
        // digest's lock keeps another process's sweep of `tmp/` off it meanwhile.
        let _held = store.lock_action(digest)?;
        let work = store.work_dir(digest)?;
        let tar_path = work.join("artifact.tar");
        let sent = pack(&store.object_dir(digest), &tar_path).and_then(|size| Ok((size, self.upload(&object, &tar_path, size, progress)?)));
        remove_dir(&work);
        let (size, uploaded) = sent?;
        Ok(uploaded.map(|()| size))
    }

    /// Sends the file at `path` (`size` bytes) as `key`: in parts of [`PART`] where the remote
    /// takes parts (S3, a directory) and the file is larger than one, so neither memory nor one
    /// request holds all of it. The timeout bounds the wait for the link to take the next bytes;
    /// `progress` hears the bytes sent. The inner error when the remote went down.
    fn upload(&self, key: &Key, path: &Path, size: u64, progress: &mut dyn FnMut(u64, u64)) -> anyhow::Result<Result<(), RemoteError>> {
        use std::io::Read as _;
        let mut file = std::fs::File::open(path).with_context(|| format!("reading {}", path.display()))?;
        let watch = Watch::new();
        // Over HTTP the link counts the bytes the connection took; a directory takes a part whole.
        if !self.parts || size <= PART as u64 {
            let mut body = Vec::with_capacity(size as usize);
            file.read_to_end(&mut body)?;
            let put = self.objects.put(key, PutPayload::from(body));
            let sent = self.watched("uploading an object", &watch, put, &mut |w| progress(w.sent().min(size), size)).map(|_| ());
            if sent.is_ok() {
                progress(size, size);
            }
            return Ok(sent);
        }
        let mut upload = match self.call("starting an upload", self.objects.put_multipart(key)) {
            Ok(Some(upload)) => upload,
            Ok(None) => return Ok(Err(RemoteError::Failed { doing: "starting an upload".into(), message: "the remote answered: not found".into() })),
            Err(e) => return Ok(Err(e)),
        };
        let mut part = vec![0u8; PART];
        let mut parts_done = 0u64;
        loop {
            let mut filled = 0;
            while filled < PART {
                match file.read(&mut part[filled..])? {
                    0 => break,
                    n => filled += n,
                }
            }
            if filled == 0 {
                break;
            }
            let put = upload.put_part(PutPayload::from(part[..filled].to_vec()));
            if let Err(e) = self.watched("uploading a part", &watch, put, &mut |w| progress(parts_done.max(w.sent()).min(size), size)) {
                let _ = self.runtime.block_on(link::bounded(&Watch::new(), self.timeout, upload.abort(), &mut |_| {}));
                return Ok(Err(e));
            }
            parts_done += filled as u64;
            progress(parts_done, size);
        }
        Ok(self.call("finishing an upload", upload.complete()).map(|_| ()))
    }

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

/// The largest piece of an artifact one upload request carries (S3 takes parts of 5 MiB and
/// more, up to 10,000 of them).
const PART: usize = 8 << 20;

/// An artifact directory as a tar file at `to` (its files with their modes, in sorted order);
/// returns its size.
fn pack(dir: &Path, to: &Path) -> anyhow::Result<u64> {
    let file = std::io::BufWriter::new(std::fs::File::create(to).with_context(|| format!("creating {}", to.display()))?);
    let mut builder = tar::Builder::new(file);
    builder.mode(tar::HeaderMode::Deterministic);
    builder.follow_symlinks(false);
    builder.append_dir_all(".", dir).with_context(|| format!("packing {}", dir.display()))?;
    let mut file = builder.into_inner()?;
    std::io::Write::flush(&mut file)?;
    Ok(std::fs::metadata(to)?.len())
}

/// The most bytes an action record may have on the remote, checked before it is read: the
/// shipped pipelines' largest is under 4 kB, and a report gathering a thousand inputs stays
/// under 200 kB.
pub const MAX_RECORD_BYTES: u64 = 256 << 10;

/// The most bytes a cluster task's transcript (its protocol lines and output) may have.
const MAX_TRANSCRIPT_BYTES: u64 = 64 << 20;

/// How a body with a size limit was read.
enum Streamed {
    /// All of it, this many bytes.
    Whole(u64),
    /// Not read on: it has (or had sent) this many bytes, more than the limit.
    TooLarge(u64),
}

/// The largest tar [`pack`] makes of `files` files holding `bytes` bytes: each file's data
/// padded to 512-byte blocks with a header block, and as many again for its folders and long
/// names, plus the end of the archive and the writer's padding.
fn largest_tar(files: u64, bytes: u64) -> u64 {
    bytes.saturating_add(files.saturating_mul(4 * 512)).saturating_add(64 << 10)
}

/// Unpacks the tar at `path` into `dir`, entry by entry, each checked before any of its bytes
/// are written: only regular files and folders (no links, devices or sparse files), within
/// `dir`, at most `files` files declaring at most `bytes` bytes in all. Memory stays bounded
/// whatever the tar declares.
fn unpack_bounded(path: &Path, dir: &Path, files: u64, bytes: u64) -> anyhow::Result<()> {
    let mut archive = tar::Archive::new(std::io::BufReader::new(std::fs::File::open(path)?));
    let (mut seen_files, mut seen_bytes) = (0u64, 0u64);
    for entry in archive.entries()? {
        let mut entry = entry?;
        let name = entry.path()?.display().to_string();
        match entry.header().entry_type() {
            tar::EntryType::Directory => {}
            tar::EntryType::Regular => {
                seen_files += 1;
                seen_bytes = seen_bytes.saturating_add(entry.header().size()?);
                if seen_files > files || seen_bytes > bytes {
                    bail!("`{name}` takes it past its record's {files} files and {bytes} bytes");
                }
            }
            other => bail!("`{name}` is a {other:?} entry; an artifact holds regular files and folders only"),
        }
        if !entry.unpack_in(dir)? {
            bail!("`{name}` would land outside the artifact");
        }
    }
    Ok(())
}

fn remove_dir(dir: &Path) {
    let _ = std::fs::remove_dir_all(dir);
}

#[cfg(test)]
mod tests {
    use super::*;

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
