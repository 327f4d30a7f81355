//! Pulls: a record and its artifact from the remote into the local store, verified before
//! anything is committed.

use std::path::Path;
use std::time::Instant;

use anyhow::Context as _;
use object_store::ObjectStoreExt;
use rlmflow_cache::{Digest, PulledFrom, Store, hash_tree};

use crate::archive::{largest_tar, remove_dir, unpack_bounded};
use crate::{Fetched, Pulled, Remote, Streamed};

impl Remote {
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
    pub(crate) fn fetch_accepted(
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
}
