use std::fs::{File, OpenOptions, TryLockError};
use std::io;
use std::path::Path;

/// An OS advisory lock on a file, released when dropped or when the process dies.
#[derive(Debug)]
pub struct Lock {
    _file: File,
}

fn open(path: &Path) -> io::Result<File> {
    OpenOptions::new().create(true).truncate(false).write(true).open(path)
}

impl Lock {
    pub fn exclusive(path: &Path) -> io::Result<Lock> {
        let file = open(path)?;
        file.lock()?;
        Ok(Lock { _file: file })
    }

    pub fn shared(path: &Path) -> io::Result<Lock> {
        let file = open(path)?;
        file.lock_shared()?;
        Ok(Lock { _file: file })
    }

    /// `Ok(None)` when another process holds the lock.
    pub fn try_exclusive(path: &Path) -> io::Result<Option<Lock>> {
        let file = open(path)?;
        match file.try_lock() {
            Ok(()) => Ok(Some(Lock { _file: file })),
            Err(TryLockError::WouldBlock) => Ok(None),
            Err(TryLockError::Error(e)) => Err(e),
        }
    }
}
