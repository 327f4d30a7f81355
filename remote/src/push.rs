//! Pushes: an artifact (as one tar, in parts where the remote takes parts) and then its record,
//! so no record names a missing object.

use std::path::Path;

use anyhow::Context as _;
use object_store::path::Path as Key;
use object_store::{ObjectStoreExt, PutPayload};
use rlmflow_cache::{ActionRecord, Digest, SIGNED_FORMAT, Store};

use crate::archive::{pack, remove_dir};
use crate::link::{self, Watch};
use crate::{MAX_RECORD_BYTES, Pushed, Remote, RemoteError, signing};

/// The largest piece of an artifact one upload request carries (S3 takes parts of 5 MiB and
/// more, up to 10,000 of them).
const PART: usize = 8 << 20;

impl Remote {
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
}
