//! NumPy `.npy` arrays (format 1.0, C order), the on-disk form of the dense per-frame arrays
//! (segmentation masks, token ids): `numpy.load` reads them as they are, and a reader here maps
//! a row to a byte range without parsing anything else.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};

const MAGIC: &[u8] = b"\x93NUMPY\x01\x00";

/// Element types used by rlmflow's artifacts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dtype {
    U8,
    U32,
    F32,
}

impl Dtype {
    fn descr(self) -> &'static str {
        match self {
            Dtype::U8 => "|u1",
            Dtype::U32 => "<u4",
            Dtype::F32 => "<f4",
        }
    }

    pub fn size(self) -> usize {
        match self {
            Dtype::U8 => 1,
            Dtype::U32 | Dtype::F32 => 4,
        }
    }
}

fn header(dtype: Dtype, shape: &[usize]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(usize::to_string).collect();
    let shape = if dims.len() == 1 { format!("({},)", dims[0]) } else { format!("({})", dims.join(", ")) };
    let mut dict = format!("{{'descr': '{}', 'fortran_order': False, 'shape': {shape}, }}", dtype.descr());
    // Magic, version and length take 10 bytes; the header ends in a newline at a multiple of 64.
    let total = (10 + dict.len() + 1).div_ceil(64) * 64;
    dict.push_str(&" ".repeat(total - 10 - dict.len() - 1));
    dict.push('\n');
    let mut out = MAGIC.to_vec();
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    out
}

/// Writes an array row by row; `finish` checks that every row came.
pub struct NpyWriter {
    path: PathBuf,
    out: BufWriter<File>,
    dtype: Dtype,
    row_len: usize,
    rows: usize,
    written: usize,
}

impl NpyWriter {
    /// An array of `rows` rows of shape `row_shape`.
    pub fn create(path: &Path, dtype: Dtype, rows: usize, row_shape: &[usize]) -> anyhow::Result<NpyWriter> {
        let mut out = BufWriter::new(File::create(path).with_context(|| format!("creating {}", path.display()))?);
        let shape: Vec<usize> = std::iter::once(rows).chain(row_shape.iter().copied()).collect();
        out.write_all(&header(dtype, &shape))?;
        Ok(NpyWriter { path: path.to_owned(), out, dtype, row_len: row_shape.iter().product(), rows, written: 0 })
    }

    pub fn write_u8(&mut self, row: &[u8]) -> anyhow::Result<()> {
        assert_eq!(self.dtype, Dtype::U8, "{} holds {:?}", self.path.display(), self.dtype);
        self.write_bytes(row.len(), row)
    }

    pub fn write_u32(&mut self, row: &[u32]) -> anyhow::Result<()> {
        assert_eq!(self.dtype, Dtype::U32, "{} holds {:?}", self.path.display(), self.dtype);
        let bytes: Vec<u8> = row.iter().flat_map(|v| v.to_le_bytes()).collect();
        self.write_bytes(row.len(), &bytes)
    }

    pub fn write_f32(&mut self, row: &[f32]) -> anyhow::Result<()> {
        assert_eq!(self.dtype, Dtype::F32, "{} holds {:?}", self.path.display(), self.dtype);
        let bytes: Vec<u8> = row.iter().flat_map(|v| v.to_le_bytes()).collect();
        self.write_bytes(row.len(), &bytes)
    }

    fn write_bytes(&mut self, len: usize, bytes: &[u8]) -> anyhow::Result<()> {
        assert_eq!(len, self.row_len, "row of {len} elements for {}", self.path.display());
        self.written += 1;
        self.out.write_all(bytes).with_context(|| format!("writing {}", self.path.display()))
    }

    pub fn finish(mut self) -> anyhow::Result<()> {
        if self.written != self.rows {
            bail!("{}: wrote {} rows of {}", self.path.display(), self.written, self.rows);
        }
        self.out.flush().with_context(|| format!("writing {}", self.path.display()))
    }
}

/// Reads rows of an array in place.
pub struct Npy {
    path: PathBuf,
    file: File,
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    data_offset: u64,
}

impl Npy {
    pub fn open(path: &Path) -> anyhow::Result<Npy> {
        Npy::open_as(path, path)
    }

    /// Opens `path`, naming it `shown` in every message (the user's file, not a snapshot's path
    /// in the store).
    pub fn open_as(path: &Path, shown: &Path) -> anyhow::Result<Npy> {
        let file = File::open(path).with_context(|| format!("reading {}", shown.display()))?;
        let path = shown;
        let mut start = [0u8; 10];
        file.read_exact_at(&mut start, 0).with_context(|| format!("{}: too short for a .npy file", path.display()))?;
        if &start[..8] != MAGIC {
            bail!("{}: not a version 1.0 .npy file", path.display());
        }
        let len = u16::from_le_bytes([start[8], start[9]]) as usize;
        let mut dict = vec![0u8; len];
        file.read_exact_at(&mut dict, 10).with_context(|| format!("{}: header cut short", path.display()))?;
        let dict = String::from_utf8_lossy(&dict);
        let dtype = [Dtype::U8, Dtype::U32, Dtype::F32]
            .into_iter()
            .find(|d| dict.contains(&format!("'descr': '{}'", d.descr())))
            .with_context(|| format!("{}: element type is not one of |u1 (uint8), <u4 (uint32), <f4 (float32): {}", path.display(), dict.trim()))?;
        if !dict.contains("'fortran_order': False") {
            bail!("{}: only C-ordered arrays are read", path.display());
        }
        let shape = dict
            .split_once("'shape': (")
            .and_then(|(_, rest)| rest.split_once(')'))
            .map(|(dims, _)| dims.split(',').map(str::trim).filter(|d| !d.is_empty()).map(str::parse).collect::<Result<Vec<usize>, _>>())
            .with_context(|| format!("{}: no shape in the header", path.display()))?
            .with_context(|| format!("{}: bad shape in the header", path.display()))?;
        let data_offset = 10 + len as u64;
        let data = shape.iter().try_fold(dtype.size() as u64, |n, &d| n.checked_mul(d as u64));
        let Some(expected) = data.and_then(|d| d.checked_add(data_offset)) else {
            bail!("{}: its header's shape {shape:?} is larger than any file", path.display());
        };
        let actual = file.metadata()?.len();
        if actual != expected {
            bail!("{}: {actual} bytes, but its header says {shape:?} {dtype:?} ({expected} bytes)", path.display());
        }
        Ok(Npy { path: path.to_owned(), file, dtype, shape, data_offset })
    }

    pub fn rows(&self) -> usize {
        self.shape.first().copied().unwrap_or(0)
    }

    fn row_len(&self) -> usize {
        self.shape.iter().skip(1).product()
    }

    fn row_bytes(&self, row: usize, dtype: Dtype) -> anyhow::Result<Vec<u8>> {
        if dtype != self.dtype {
            bail!("{} holds {:?}, not {dtype:?}", self.path.display(), self.dtype);
        }
        if row >= self.rows() {
            bail!("row {row} is past the end of {} ({} rows)", self.path.display(), self.rows());
        }
        let len = self.row_len() * dtype.size();
        let mut out = vec![0u8; len];
        self.file.read_exact_at(&mut out, self.data_offset + (row * len) as u64).with_context(|| format!("reading {}", self.path.display()))?;
        Ok(out)
    }

    pub fn row_u8(&self, row: usize) -> anyhow::Result<Vec<u8>> {
        self.row_bytes(row, Dtype::U8)
    }

    pub fn row_u32(&self, row: usize) -> anyhow::Result<Vec<u32>> {
        Ok(u32s(&self.row_bytes(row, Dtype::U32)?))
    }

    /// The whole array, flat, as f32 (a uint8 or float32 array; values as stored).
    pub fn all_f32(&self) -> anyhow::Result<Vec<f32>> {
        let mut out = vec![0u8; self.shape.iter().product::<usize>() * self.dtype.size()];
        self.file.read_exact_at(&mut out, self.data_offset).with_context(|| format!("reading {}", self.path.display()))?;
        match self.dtype {
            Dtype::U8 => Ok(out.into_iter().map(f32::from).collect()),
            Dtype::F32 => Ok(out.chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().expect("chunks of 4"))).collect()),
            Dtype::U32 => bail!("{} holds uint32; valid here: uint8 or float32", self.path.display()),
        }
    }

    /// The whole array, flat.
    pub fn all_u32(&self) -> anyhow::Result<Vec<u32>> {
        if self.dtype != Dtype::U32 {
            bail!("{} holds {:?}, not U32", self.path.display(), self.dtype);
        }
        let mut out = vec![0u8; self.shape.iter().product::<usize>() * 4];
        self.file.read_exact_at(&mut out, self.data_offset).with_context(|| format!("reading {}", self.path.display()))?;
        Ok(u32s(&out))
    }
}

fn u32s(bytes: &[u8]) -> Vec<u32> {
    bytes.chunks_exact(4).map(|b| u32::from_le_bytes(b.try_into().expect("chunks of 4"))).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arrays_round_trip_with_aligned_headers() {
        let dir = std::env::temp_dir().join(format!("rlmflow-npy-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("a.npy");
        let mut w = NpyWriter::create(&path, Dtype::U32, 3, &[2]).unwrap();
        for r in 0..3u32 {
            w.write_u32(&[r, r * 1000]).unwrap();
        }
        w.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!((bytes.len() - 24) % 64, 0, "data starts on a 64-byte boundary");
        let npy = Npy::open(&path).unwrap();
        assert_eq!((npy.dtype, npy.shape.clone()), (Dtype::U32, vec![3, 2]));
        assert_eq!(npy.row_u32(2).unwrap(), vec![2, 2000]);
        assert_eq!(npy.all_u32().unwrap(), vec![0, 0, 1, 1000, 2, 2000]);
        assert!(npy.row_u8(0).unwrap_err().to_string().contains("not U8"));
        assert!(npy.row_u32(3).unwrap_err().to_string().contains("past the end"));
        std::fs::write(&path, &bytes[..bytes.len() - 1]).unwrap();
        assert!(Npy::open(&path).err().unwrap().to_string().contains("but its header says [3, 2]"));
        let w = NpyWriter::create(&path, Dtype::U8, 2, &[4]).unwrap();
        assert!(w.finish().unwrap_err().to_string().contains("wrote 0 rows of 2"));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
