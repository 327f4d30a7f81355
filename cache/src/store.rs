use std::collections::BTreeMap;
use std::fs;
use std::io::{self, Write};
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::SystemTime;

use anyhow::{Context, bail};
use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::digest::Digest;
use crate::instance::InstanceRef;
use crate::lock::Lock;
use crate::preimage::Preimage;
use crate::tree::{TreeInfo, hash_tree};

const STORE_FORMAT: &str = "rlmflow-store 1\n";

/// What a finished action left: written last, so it exists only if its output does.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ActionRecord {
    pub key: Digest,
    pub preimage: Preimage,
    pub output: Digest,
    pub files: u64,
    pub bytes: u64,
    /// RFC 3339, UTC.
    pub started: String,
    pub duration_s: f64,
    pub metrics: Value,
    pub summary: String,
    /// The numeric platform it ran on (CPU, kernel pins, threads, libraries, GPU), for an action
    /// whose bytes depend on it: provenance, outside the key (the key holds its class).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub platform: Option<Value>,
    /// Signatures of the pushers that vouched for it on a remote cache (see `rlmflow_remote`):
    /// outside the key, over [`ActionRecord::signed_message`].
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub signatures: Vec<RecordSignature>,
    /// Where this store got it, when it was pulled from a remote cache rather than computed
    /// here: local provenance, outside the key and the signatures, never pushed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pulled: Option<PulledFrom>,
}

/// The remote cache a record was pulled from, and the trusted key that vouched for it, by name
/// and fingerprint (`None`: used unverified, the remote having no trusted keys set, so its
/// numbers are the remote's word).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PulledFrom {
    pub remote: String,
    pub signed_by: Option<String>,
}

/// One signer's signature of a record: the signer's key name, its ed25519 signature (base64),
/// and the format of the message it signed.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct RecordSignature {
    pub key: String,
    pub signature: String,
    /// [`SIGNED_FORMAT`] for a signature of [`ActionRecord::signed_message`]; 1 (absent) for the
    /// first format, which covered the key, operator and output only.
    #[serde(default = "first_signed_format")]
    pub format: u32,
}

/// The format of the message a signature made now signs.
pub const SIGNED_FORMAT: u32 = 2;

fn first_signed_format() -> u32 {
    1
}

impl ActionRecord {
    /// Where a person reading its numbers should know they were not checked here: pulled from a
    /// remote cache with no trusted keys (`None` when it was computed here or a trusted key
    /// signed it).
    pub fn unverified_origin(&self) -> Option<&str> {
        self.pulled.as_ref().filter(|p| p.signed_by.is_none()).map(|p| p.remote.as_str())
    }

    /// What a signature vouches for: every field of the record but the signatures themselves
    /// (the action key and preimage, the output, its times, metrics, summary and platform: all a
    /// command shows or a decision reads), as the record's canonical JSON, under the format's name.
    pub fn signed_message(&self) -> Vec<u8> {
        let unsigned = ActionRecord { signatures: Vec::new(), pulled: None, ..self.clone() };
        let json = serde_json::to_value(&unsigned).expect("a record is JSON");
        format!("rlmflow action record v{SIGNED_FORMAT}\n{}", crate::preimage::canonical_json(&json)).into_bytes()
    }
}

/// Everything `rlmflow exec` needs to run an action, stored before it runs so that the same
/// entry point works in a child process here or on another machine.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ActionRequest {
    pub key: Digest,
    /// The stage instance that asked, e.g. `pretrain[alpha4]` (for messages only).
    pub stage: String,
    pub preimage: Preimage,
    /// Every setting, including those left out of the key (`threads`, `log_every`).
    pub settings: Value,
    /// The producing instance of each single-artifact input, by slot (for messages only: those
    /// labels stay out of the key, so renaming a stage reruns nothing).
    #[serde(default)]
    pub input_labels: BTreeMap<String, String>,
    /// Every input's producing instance as data (its stage and variant), by label: what an
    /// operator that gathers instances (the report) groups them by, so it never parses labels.
    /// Out of the key, like the labels.
    #[serde(default)]
    pub input_instances: BTreeMap<String, Value>,
}

/// One stage instance in a run's plan.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PlanEntry {
    pub label: String,
    /// What it is: how `compare` groups seeds and sets variants side by side.
    #[serde(flatten)]
    pub instance: InstanceRef,
    /// Unknown until its inputs exist; filled in as the run goes.
    pub key: Option<Digest>,
}

impl PlanEntry {
    /// An entry of a plan written while seeds were a variant named `seed` (`"assignment":
    /// {"seed": "2"}`) gets its seed field (variant names are not numbers there: no stage was
    /// named `seed` beside seeds).
    fn with_seed_field(mut self) -> PlanEntry {
        if self.instance.seed.is_none()
            && let Some(seed) = self.instance.variants.get("seed").and_then(|s| s.parse().ok())
        {
            self.instance.variants.remove("seed");
            self.instance.seed = Some(seed);
        }
        self
    }
}

/// The git commit a run's pipeline file was at, and whether tracked files had changed since.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GitState {
    pub commit: String,
    pub dirty: bool,
}

/// `runs/<id>/plan.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RunPlan {
    pub run: String,
    pub pipeline: String,
    pub started: String,
    /// The command line's overrides the run was started with, each as given (`--set
    /// STAGE.KEY=VALUE`, `--set-new ...`; a run recorded before the flag was kept: the text
    /// alone, a `--set`), so it can be repeated (absent when there were none).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub overrides: Vec<String>,
    /// Absent where the pipeline file is not in a git work tree (or git is not installed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub git: Option<GitState>,
    pub instances: Vec<PlanEntry>,
}

/// The store's directory of outside answers (see [`Store::responses_dir`]).
pub(crate) const RESPONSES: &str = "responses";

/// A content-addressed store rooted at one directory. See the crate docs for the layout.
#[derive(Clone, Debug)]
pub struct Store {
    root: PathBuf,
    /// Damage met while reading (a record, request, plan or ref treated as absent), kept for the
    /// caller to show: the store itself never prints. Shared by every `Store` of this root in the
    /// process ([`take_all_warnings`]).
    warnings: Arc<Mutex<Vec<String>>>,
}

/// The warnings of each store root this process opened: every `Store` of one root adds to one
/// list, so a command line can print them once, after whatever command met them.
static WARNINGS: Mutex<BTreeMap<PathBuf, Arc<Mutex<Vec<String>>>>> = Mutex::new(BTreeMap::new());

/// The warnings every store of this process met since the last call, each once, by store then
/// oldest first.
pub fn take_all_warnings() -> Vec<String> {
    let stores = WARNINGS.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    let mut all = Vec::new();
    for list in stores.values() {
        for warning in std::mem::take(&mut *list.lock().unwrap_or_else(|poisoned| poisoned.into_inner())) {
            if !all.contains(&warning) {
                all.push(warning);
            }
        }
    }
    all
}

/// A new run id: UTC time to the millisecond and the process id, so ids sort by start time.
pub fn run_id() -> String {
    let t = humantime::format_rfc3339_millis(SystemTime::now()).to_string();
    let compact: String = t.chars().filter(|c| c.is_ascii_alphanumeric()).collect();
    format!("{compact}-{}", std::process::id())
}

pub fn now_rfc3339() -> String {
    humantime::format_rfc3339_seconds(SystemTime::now()).to_string()
}

impl Store {
    /// Opens the store at `root`, creating it if needed.
    pub fn open(root: &Path) -> anyhow::Result<Store> {
        let warnings = WARNINGS.lock().unwrap_or_else(|poisoned| poisoned.into_inner()).entry(root.to_path_buf()).or_default().clone();
        let store = Store { root: root.to_path_buf(), warnings };
        let version = root.join("VERSION");
        match fs::read_to_string(&version) {
            Ok(v) if v == STORE_FORMAT => {}
            Ok(v) => bail!("{} holds a store of format `{}`; this rlmflow reads `{}`", root.display(), v.trim(), STORE_FORMAT.trim()),
            Err(e) if e.kind() == io::ErrorKind::NotFound => {
                for dir in ["objects", "actions", "requests", "checkpoints", "runs", "refs/pipelines", "refs/pins", "locks", "tmp", "quarantine"] {
                    fs::create_dir_all(root.join(dir)).with_context(|| format!("creating the store at {}", root.display()))?;
                }
                atomic_write(&store, &version, STORE_FORMAT.as_bytes())?;
            }
            Err(e) => return Err(e).with_context(|| format!("reading {}", version.display())),
        }
        Ok(store)
    }

    /// Opens an existing store without creating anything (`--dry-run`, `status`); `None` if
    /// there is none yet.
    pub fn open_existing(root: &Path) -> anyhow::Result<Option<Store>> {
        if root.join("VERSION").exists() { Store::open(root).map(Some) } else { Ok(None) }
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    fn warn(&self, warning: String) {
        let mut warnings = self.warnings.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        if !warnings.contains(&warning) {
            warnings.push(warning);
        }
    }

    /// Reads a record, request, plan or ref. A damaged one is treated as absent, with a warning:
    /// each can be recomputed or rewritten, so a run always makes progress, and `verify`
    /// quarantines it.
    pub(crate) fn read_json<T: serde::de::DeserializeOwned>(&self, path: &Path) -> anyhow::Result<Option<T>> {
        Ok(match read_json_checked(path)? {
            Read::Intact(value) => Some(value),
            Read::Absent => None,
            Read::Damaged(why) => {
                self.warn(format!("{} is damaged ({why}); treated as absent (`rlmflow verify` quarantines it)", path.display()));
                None
            }
        })
    }

    // ---- objects ----

    pub fn object_dir(&self, digest: &Digest) -> PathBuf {
        self.root.join("objects").join(digest.shard()).join(digest.hex())
    }

    pub(crate) fn manifest_path(&self, digest: &Digest) -> PathBuf {
        self.root.join("objects").join(digest.shard()).join(format!("{}.tree", digest.hex()))
    }

    pub fn has_object(&self, digest: &Digest) -> bool {
        self.manifest_path(digest).is_file() && self.object_dir(digest).is_dir()
    }

    /// Moves a finished output directory into `objects/` (files made read-only). If an equal
    /// object exists already, the new copy is dropped.
    pub fn commit_tree(&self, dir: &Path) -> anyhow::Result<TreeInfo> {
        let info = hash_tree(dir)?;
        if self.has_object(&info.digest) {
            remove_tree(dir)?;
            return Ok(info);
        }
        make_read_only(dir)?;
        let target = self.object_dir(&info.digest);
        fs::create_dir_all(target.parent().unwrap())?;
        if target.exists() {
            // A manifest-less leftover of an interrupted commit: it was never served.
            remove_tree(&target)?;
        }
        fs::rename(dir, &target).with_context(|| format!("moving output to {}", target.display()))?;
        atomic_write(self, &self.manifest_path(&info.digest), info.manifest.as_bytes())?;
        Ok(info)
    }

    /// Every object digest in the store.
    pub fn objects(&self) -> anyhow::Result<Vec<Digest>> {
        let mut out = Vec::new();
        for shard in read_dir_sorted(&self.root.join("objects"))? {
            for entry in read_dir_sorted(&shard)? {
                let name = entry.file_name().unwrap().to_string_lossy().into_owned();
                if let Some(hex) = name.strip_suffix(".tree")
                    && let Ok(d) = hex.parse()
                {
                    out.push(d);
                }
            }
        }
        Ok(out)
    }

    // ---- actions ----

    pub(crate) fn record_path(&self, key: &Digest) -> PathBuf {
        self.root.join("actions").join(key.shard()).join(format!("{}.json", key.hex()))
    }

    pub(crate) fn request_path(&self, key: &Digest) -> PathBuf {
        self.root.join("requests").join(key.shard()).join(format!("{}.json", key.hex()))
    }

    /// The record of `key`; a damaged record (unreadable, or not the record of `key`) is a miss.
    pub fn record(&self, key: &Digest) -> anyhow::Result<Option<ActionRecord>> {
        let path = self.record_path(key);
        Ok(self.read_json::<ActionRecord>(&path)?.filter(|r| {
            let intact = r.key == *key && r.preimage.key() == *key;
            if !intact {
                self.warn(format!("{} is not the record of its key; treated as absent (`rlmflow verify` quarantines it)", path.display()));
            }
            intact
        }))
    }

    /// The record of `key` if its output is present: a cache hit.
    pub fn fresh(&self, key: &Digest) -> anyhow::Result<Option<ActionRecord>> {
        Ok(self.record(key)?.filter(|r| self.has_object(&r.output)))
    }

    /// Publishes a finished action. Call only after its output is committed.
    pub fn write_record(&self, record: &ActionRecord) -> anyhow::Result<()> {
        assert!(self.has_object(&record.output), "record written before its output");
        atomic_write(self, &self.record_path(&record.key), &serde_json::to_vec_pretty(record)?)?;
        let _ = fs::remove_file(self.failure_path(&record.key));
        Ok(())
    }

    /// Keeps why the last attempt at action `key` failed (its operator's error) until an attempt
    /// succeeds, so `status` can tell a failed action from an interrupted one.
    pub fn write_failure(&self, key: &Digest, message: &str) -> anyhow::Result<()> {
        atomic_write(self, &self.failure_path(key), message.as_bytes())
    }

    /// Why the last attempt at action `key` failed, if it failed.
    pub fn failure(&self, key: &Digest) -> Option<String> {
        fs::read_to_string(self.failure_path(key)).ok()
    }

    fn failure_path(&self, key: &Digest) -> PathBuf {
        self.root.join("failures").join(format!("{}.txt", key.hex()))
    }

    pub fn write_request(&self, request: &ActionRequest) -> anyhow::Result<()> {
        atomic_write(self, &self.request_path(&request.key), &serde_json::to_vec_pretty(request)?)
    }

    pub fn request(&self, key: &Digest) -> anyhow::Result<Option<ActionRequest>> {
        self.read_json(&self.request_path(key))
    }

    /// Every action record's key.
    pub fn record_keys(&self) -> anyhow::Result<Vec<Digest>> {
        keys_in(&self.root.join("actions"))
    }

    pub fn request_keys(&self) -> anyhow::Result<Vec<Digest>> {
        keys_in(&self.root.join("requests"))
    }

    // ---- checkpoints, work directories and locks ----

    pub fn checkpoint_dir(&self, key: &Digest) -> PathBuf {
        self.root.join("checkpoints").join(key.hex())
    }

    /// Where operator `operator` keeps the answers of an outside service (an LLM endpoint), one
    /// JSON file per request digest: shared by every action of the store, so a resumed or
    /// repeated one asks nothing twice. `verify` checks them; `gc --responses` removes them.
    pub fn responses_dir(&self, operator: &str) -> PathBuf {
        self.root.join(RESPONSES).join(file_safe(operator))
    }

    /// A fresh work directory for one attempt at `key`. Its name starts with the key, so the
    /// sweep can tell whether its owner is still alive (it holds the key's lock).
    pub fn work_dir(&self, key: &Digest) -> anyhow::Result<PathBuf> {
        static COUNTER: AtomicU64 = AtomicU64::new(0);
        let n = COUNTER.fetch_add(1, Ordering::Relaxed);
        let dir = self.root.join("tmp").join(format!("{}.{}.{n}", key.hex(), std::process::id()));
        fs::create_dir_all(&dir)?;
        Ok(dir)
    }

    /// Blocks until this process alone may compute `key`.
    pub fn lock_action(&self, key: &Digest) -> io::Result<Lock> {
        Lock::exclusive(&self.lock_path(key))
    }

    pub fn try_lock_action(&self, key: &Digest) -> io::Result<Option<Lock>> {
        Lock::try_exclusive(&self.lock_path(key))
    }

    fn lock_path(&self, key: &Digest) -> PathBuf {
        self.root.join("locks").join(format!("{}.lock", key.hex()))
    }

    /// Held (shared) by every run and exec; held exclusively by `gc`.
    pub fn lock_shared(&self) -> io::Result<Lock> {
        Lock::shared(&self.root.join("locks/store.lock"))
    }

    pub fn lock_exclusive(&self) -> io::Result<Lock> {
        Lock::exclusive(&self.root.join("locks/store.lock"))
    }

    /// Removes work directories whose owner died (their key is not locked), and the work
    /// directories of `key` itself when the caller holds its lock. Returns how many.
    pub fn sweep_tmp(&self, held: Option<&Digest>) -> anyhow::Result<usize> {
        let mut swept = 0;
        for dir in read_dir_sorted(&self.root.join("tmp"))? {
            let name = dir.file_name().unwrap().to_string_lossy().into_owned();
            if let Some(writer) = name.strip_prefix("write-") {
                // atomic_write's scratch files: left only by a writer killed mid-write.
                if abandoned_write(&dir, writer) {
                    let _ = fs::remove_file(&dir);
                    swept += 1;
                }
                continue;
            }
            let Some(key) = name.split('.').next().and_then(|k| k.parse::<Digest>().ok()) else {
                continue;
            };
            let dead = if held == Some(&key) { true } else { self.try_lock_action(&key)?.is_some() };
            if dead {
                remove_tree(&dir)?;
                swept += 1;
            }
        }
        Ok(swept)
    }

    // ---- runs and refs ----

    pub fn run_dir(&self, run: &str) -> PathBuf {
        self.root.join("runs").join(run)
    }

    /// Run ids, oldest first.
    pub fn runs(&self) -> anyhow::Result<Vec<String>> {
        Ok(read_dir_sorted(&self.root.join("runs"))?.into_iter().filter_map(|p| p.file_name().map(|n| n.to_string_lossy().into_owned())).collect())
    }

    pub fn write_plan(&self, plan: &RunPlan) -> anyhow::Result<()> {
        let dir = self.run_dir(&plan.run);
        fs::create_dir_all(dir.join("logs"))?;
        atomic_write_unsynced(self, &dir.join("plan.json"), &serde_json::to_vec_pretty(plan)?)
    }

    pub fn plan(&self, run: &str) -> anyhow::Result<Option<RunPlan>> {
        let plan: Option<RunPlan> = self.read_json(&self.run_dir(run).join("plan.json"))?;
        Ok(plan.map(|mut p| {
            p.instances = p.instances.into_iter().map(PlanEntry::with_seed_field).collect();
            p
        }))
    }
}

/// `name` with every character but ASCII letters, digits, `-`, `_` and `.` replaced by `_`,
/// for file names derived from pipeline, pin and stage names.
pub fn file_safe(name: &str) -> String {
    name.chars().map(|c| if c.is_ascii_alphanumeric() || "-_.".contains(c) { c } else { '_' }).collect()
}

fn keys_in(dir: &Path) -> anyhow::Result<Vec<Digest>> {
    let mut out = Vec::new();
    for shard in read_dir_sorted(dir)? {
        for file in read_dir_sorted(&shard)? {
            let name = file.file_name().unwrap().to_string_lossy().into_owned();
            if let Some(key) = name.strip_suffix(".json").and_then(|h| h.parse().ok()) {
                out.push(key);
            }
        }
    }
    Ok(out)
}

pub(crate) fn read_dir_sorted(dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let mut out = match fs::read_dir(dir) {
        Ok(rd) => rd.map(|e| e.map(|e| e.path())).collect::<io::Result<Vec<_>>>()?,
        Err(e) if e.kind() == io::ErrorKind::NotFound => Vec::new(),
        Err(e) => return Err(e).with_context(|| format!("reading {}", dir.display())),
    };
    out.sort();
    Ok(out)
}

/// A JSON file of the store as read: absent, intact, or damaged (truncated, empty, not the
/// expected shape).
pub(crate) enum Read<T> {
    Absent,
    Intact(T),
    Damaged(String),
}

pub(crate) fn read_json_checked<T: serde::de::DeserializeOwned>(path: &Path) -> anyhow::Result<Read<T>> {
    match fs::read(path) {
        Ok(bytes) => Ok(serde_json::from_slice(&bytes).map_or_else(|e| Read::Damaged(e.to_string()), Read::Intact)),
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(Read::Absent),
        Err(e) => Err(e).with_context(|| format!("reading {}", path.display())),
    }
}

/// Whether an atomic write's scratch file (`write-<pid>-<n>`) was abandoned: its process is gone,
/// or it is older than any write takes (a store shared between machines cannot see the
/// writer's process, and a pid can be reused).
fn abandoned_write(path: &Path, writer: &str) -> bool {
    const OLDEST_WRITE: std::time::Duration = std::time::Duration::from_secs(3600);
    let pid = writer.split('-').next().and_then(|p| p.parse::<i32>().ok());
    // SAFETY: kill with signal 0 only checks that the process exists.
    let gone = pid.is_some_and(|pid| pid > 0 && unsafe { libc::kill(pid, 0) } != 0 && io::Error::last_os_error().raw_os_error() == Some(libc::ESRCH));
    let age = fs::metadata(path).and_then(|m| m.modified()).ok().and_then(|t| t.elapsed().ok());
    gone || age.is_some_and(|a| a > OLDEST_WRITE)
}

/// Writes `bytes` to a temporary file in the store's `tmp/`, synced, and renames it over `path`:
/// after a crash of the machine, `path` holds the old bytes or the new, whole.
pub(crate) fn atomic_write(store: &Store, path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    replace(store, path, bytes, true)
}

/// [`atomic_write`] without the sync, for what a run rewrites as it goes and a crash of the
/// machine may lose (`runs/<id>/plan.json`): readers still see the old bytes or the new, whole.
fn atomic_write_unsynced(store: &Store, path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    replace(store, path, bytes, false)
}

fn replace(store: &Store, path: &Path, bytes: &[u8], sync: bool) -> anyhow::Result<()> {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    let tmp = store.root.join("tmp").join(format!("write-{}-{n}", std::process::id()));
    fs::create_dir_all(tmp.parent().unwrap())?;
    let mut f = fs::File::create(&tmp).with_context(|| format!("writing {}", tmp.display()))?;
    f.write_all(bytes)?;
    if sync {
        f.sync_data()?;
    }
    drop(f);
    fs::create_dir_all(path.parent().unwrap())?;
    fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

fn make_read_only(dir: &Path) -> io::Result<()> {
    for entry in fs::read_dir(dir)? {
        let entry = entry?;
        if entry.file_type()?.is_dir() {
            make_read_only(&entry.path())?;
        } else {
            let mut perms = entry.metadata()?.permissions();
            perms.set_mode(perms.mode() & !0o222);
            fs::set_permissions(entry.path(), perms)?;
        }
    }
    Ok(())
}

pub(crate) fn remove_tree(path: &Path) -> io::Result<()> {
    match fs::remove_dir_all(path) {
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(()),
        other => other,
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::preimage::InputDigest;
    use crate::tree::tests::tempdir;

    pub(crate) fn record_for(store: &Store, seed: u64, content: &[u8]) -> ActionRecord {
        let preimage = Preimage {
            operator: "op".into(),
            operator_version: 1,
            config: serde_json::json!({}),
            seed,
            inputs: Vec::<InputDigest>::new(),
            platform: None,
        };
        let key = preimage.key();
        let work = store.work_dir(&key).unwrap();
        fs::create_dir_all(work.join("out")).unwrap();
        fs::write(work.join("out/data.txt"), content).unwrap();
        let info = store.commit_tree(&work.join("out")).unwrap();
        let record = ActionRecord {
            key,
            preimage,
            output: info.digest,
            files: info.files,
            bytes: info.bytes,
            started: now_rfc3339(),
            duration_s: 0.1,
            metrics: Value::Null,
            summary: String::new(),
            platform: None,
            signatures: Vec::new(),
            pulled: None,
        };
        store.write_record(&record).unwrap();
        record
    }

    #[test]
    fn a_plan_written_while_seeds_were_a_variant_reads_with_its_seed_field() {
        let store = Store::open(&tempdir("old-plan")).unwrap();
        let entry = |assignment: Value| serde_json::json!({"label": "l", "stage": "c", "assignment": assignment, "key": null});
        let old = serde_json::json!({
            "run": "r1", "pipeline": "p", "started": "2026-01-01T00:00:00Z",
            "instances": [entry(serde_json::json!({"pretrain": "alpha4", "seed": "2"})), entry(serde_json::json!({"pretrain": "x"}))],
        });
        fs::create_dir_all(store.run_dir("r1")).unwrap();
        fs::write(store.run_dir("r1").join("plan.json"), serde_json::to_vec(&old).unwrap()).unwrap();
        let plan = store.plan("r1").unwrap().unwrap();
        let seeded = &plan.instances[0].instance;
        assert_eq!((seeded.seed, seeded.variants.len(), &seeded.variants["pretrain"]), (Some(2), 1, &"alpha4".to_owned()));
        assert_eq!(plan.instances[1].instance.seed, None);
        // Written again, the seed is its own field.
        store.write_plan(&plan).unwrap();
        let text: Value = serde_json::from_slice(&fs::read(store.run_dir("r1").join("plan.json")).unwrap()).unwrap();
        assert_eq!(text["instances"][0], serde_json::json!({"label": "l", "stage": "c", "assignment": {"pretrain": "alpha4"}, "seed": 2, "key": null}));
    }

    #[test]
    fn committed_actions_are_fresh_until_their_object_is_damaged() {
        let store = Store::open(&tempdir("store-commit")).unwrap();
        let record = record_for(&store, 1, b"payload");
        assert!(store.fresh(&record.key).unwrap().is_some());
        let file = store.object_dir(&record.output).join("data.txt");
        assert!(fs::metadata(&file).unwrap().permissions().readonly());
        assert!(store.check_object(&record.output).unwrap().is_none());

        // Flip a byte behind the store's back.
        fs::set_permissions(&file, fs::Permissions::from_mode(0o644)).unwrap();
        fs::write(&file, b"pAyload").unwrap();
        let damaged = store.verify(|_| {}).unwrap();
        assert_eq!(damaged.objects.len(), 1);
        assert_eq!(damaged.objects[0].files, ["data.txt"]);
        assert!(store.fresh(&record.key).unwrap().is_none(), "a damaged object is never served");
        assert!(!store.quarantine_is_empty());
    }

    #[test]
    fn equal_outputs_share_one_object() {
        let store = Store::open(&tempdir("store-dedup")).unwrap();
        let a = record_for(&store, 1, b"same");
        let b = record_for(&store, 2, b"same");
        assert_ne!(a.key, b.key);
        assert_eq!(a.output, b.output);
        assert_eq!(store.objects().unwrap(), [a.output]);
    }

    #[test]
    fn sweep_removes_only_dead_work_dirs() {
        let store = Store::open(&tempdir("store-sweep")).unwrap();
        let (live, dead) = (Digest::of(b"live"), Digest::of(b"dead"));
        let _held = store.lock_action(&live).unwrap();
        let live_dir = store.work_dir(&live).unwrap();
        let dead_dir = store.work_dir(&dead).unwrap();
        // Our own lock is per open file: take it on another descriptor to simulate another process.
        assert_eq!(store.sweep_tmp(None).unwrap(), 1);
        assert!(live_dir.exists() && !dead_dir.exists());
    }

    #[test]
    fn a_store_of_another_format_is_refused() {
        let dir = tempdir("store-format");
        fs::write(dir.join("VERSION"), "rlmflow-store 99\n").unwrap();
        let err = Store::open(&dir).unwrap_err().to_string();
        assert!(err.contains("rlmflow-store 99"), "{err}");
    }

    impl Store {
        fn quarantine_is_empty(&self) -> bool {
            read_dir_sorted(&self.root.join("quarantine")).unwrap().is_empty()
        }
    }
}
