//! The tar format an artifact crosses the link in: packed deterministically, unpacked entry by
//! entry within bounds its record declares.

use std::path::Path;

use anyhow::{Context as _, bail};

/// An artifact directory as a tar file at `to` (its files with their modes, in sorted order);
/// returns its size.
pub(crate) fn pack(dir: &Path, to: &Path) -> anyhow::Result<u64> {
    let file = std::io::BufWriter::new(std::fs::File::create(to).with_context(|| format!("creating {}", to.display()))?);
    let mut builder = tar::Builder::new(file);
    builder.mode(tar::HeaderMode::Deterministic);
    builder.follow_symlinks(false);
    builder.append_dir_all(".", dir).with_context(|| format!("packing {}", dir.display()))?;
    let mut file = builder.into_inner()?;
    std::io::Write::flush(&mut file)?;
    Ok(std::fs::metadata(to)?.len())
}

/// The largest tar [`pack`] makes of `files` files holding `bytes` bytes: each file's data
/// padded to 512-byte blocks with a header block, and as many again for its folders and long
/// names, plus the end of the archive and the writer's padding.
pub(crate) fn largest_tar(files: u64, bytes: u64) -> u64 {
    bytes.saturating_add(files.saturating_mul(4 * 512)).saturating_add(64 << 10)
}

/// Unpacks the tar at `path` into `dir`, entry by entry, each checked before any of its bytes
/// are written: only regular files and folders (no links, devices or sparse files), within
/// `dir`, at most `files` files declaring at most `bytes` bytes in all. Memory stays bounded
/// whatever the tar declares.
pub(crate) fn unpack_bounded(path: &Path, dir: &Path, files: u64, bytes: u64) -> anyhow::Result<()> {
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

pub(crate) fn remove_dir(dir: &Path) {
    let _ = std::fs::remove_dir_all(dir);
}
