//! Training curves as TensorBoard event files: what `tensorboard --logdir` reads, written as
//! training goes.
//!
//! The file is TensorFlow's record format (each record: its length as u64 little-endian, the
//! masked CRC-32C of the length, the bytes, their masked CRC-32C), each record one `Event`
//! protobuf (`tensorflow/core/util/event.proto`) holding a `Summary` of simple scalar values.
//! Only the fields a scalar needs are declared, with their numbers from the upstream protos.
//!
//! An artifact's bytes depend only on its key, so the file is named without the host and time
//! upstream writers put in the name, and every event's `wall_time` is 0: the run's event log
//! (`runs/<id>/events.jsonl`) has the real times. A resumed training cuts the file back to the
//! last checkpointed step ([`EventWriter::resume`]) and goes on, so it ends with the bytes of an
//! uninterrupted one.

use std::fs::{File, OpenOptions};
use std::io::{BufReader, Read, Write};
use std::path::{Path, PathBuf};

use anyhow::Context as _;
use prost::Message;

/// The file's name: TensorBoard reads any file whose name holds `tfevents`.
pub const FILE: &str = "events.out.tfevents.rlmflow";

#[derive(Clone, PartialEq, Message)]
struct Event {
    #[prost(double, tag = "1")]
    wall_time: f64,
    #[prost(int64, tag = "2")]
    step: i64,
    #[prost(string, optional, tag = "3")]
    file_version: Option<String>,
    #[prost(message, optional, tag = "5")]
    summary: Option<Summary>,
}

#[derive(Clone, PartialEq, Message)]
struct Summary {
    #[prost(message, repeated, tag = "1")]
    value: Vec<SummaryValue>,
}

#[derive(Clone, PartialEq, Message)]
struct SummaryValue {
    #[prost(string, tag = "1")]
    tag: String,
    #[prost(float, optional, tag = "2")]
    simple_value: Option<f32>,
}

/// TensorFlow's masked CRC-32C: rotated and offset, so a CRC stored inside checksummed data
/// does not checksum to a constant.
fn masked_crc(bytes: &[u8]) -> u32 {
    let crc = crc32c::crc32c(bytes);
    crc.rotate_right(15).wrapping_add(0xa282_ead8)
}

/// One event as a record.
fn record(event: &Event) -> Vec<u8> {
    let data = event.encode_to_vec();
    let length = (data.len() as u64).to_le_bytes();
    let mut out = Vec::with_capacity(data.len() + 16);
    out.extend_from_slice(&length);
    out.extend_from_slice(&masked_crc(&length).to_le_bytes());
    out.extend_from_slice(&data);
    out.extend_from_slice(&masked_crc(&data).to_le_bytes());
    out
}

/// Appends scalar events to one event file, flushing each, so TensorBoard shows them as they
/// come.
pub struct EventWriter {
    file: File,
    path: PathBuf,
}

impl EventWriter {
    /// The event file in `dir` for a training that has finished the steps up to `step` (0: none):
    /// a new file for 0, else the existing one cut back after its records of `step`, so the
    /// events of an epoch that was not checkpointed are written again. `None` when the file
    /// does not reach `step` (a checkpoint without its events): the training starts over.
    pub fn resume(dir: &Path, step: u64) -> anyhow::Result<Option<EventWriter>> {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let path = dir.join(FILE);
        if step == 0 {
            let mut writer = EventWriter { file: File::create(&path).with_context(|| format!("creating {}", path.display()))?, path };
            writer.write(&Event { file_version: Some("brain.Event:2".into()), ..Default::default() })?;
            return Ok(Some(writer));
        }
        let (keep, last) = end_of_step(&path, step)?;
        if last != Some(step) {
            return Ok(None);
        }
        let mut file = OpenOptions::new().write(true).open(&path)?;
        file.set_len(keep)?;
        std::io::Seek::seek(&mut file, std::io::SeekFrom::End(0))?;
        Ok(Some(EventWriter { file, path }))
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Scalars `tags` at `step`, as one event.
    pub fn scalars(&mut self, step: u64, values: &[(String, f64)]) -> anyhow::Result<()> {
        let value = values.iter().map(|(tag, v)| SummaryValue { tag: tag.clone(), simple_value: Some(*v as f32) }).collect();
        self.write(&Event { step: step as i64, summary: Some(Summary { value }), ..Default::default() })
    }

    fn write(&mut self, event: &Event) -> anyhow::Result<()> {
        self.file.write_all(&record(event)).and_then(|()| self.file.flush()).with_context(|| format!("writing {}", self.path.display()))
    }
}

/// The byte length of `path`'s whole records up to the last one whose step is at most `step`,
/// and that record's step (none without a file or a record). A record cut short or failing its
/// checksums ends the reading.
fn end_of_step(path: &Path, step: u64) -> anyhow::Result<(u64, Option<u64>)> {
    let file = match File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok((0, None)),
        Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
    };
    let mut reader = BufReader::new(file);
    let (mut keep, mut last) = (0u64, None);
    loop {
        let mut head = [0u8; 12];
        if reader.read_exact(&mut head).is_err() {
            break;
        }
        let length = u64::from_le_bytes(head[..8].try_into().unwrap());
        if masked_crc(&head[..8]) != u32::from_le_bytes(head[8..].try_into().unwrap()) || length > 1 << 30 {
            break;
        }
        let mut data = vec![0u8; length as usize + 4];
        if reader.read_exact(&mut data).is_err() {
            break;
        }
        let (body, crc) = data.split_at(length as usize);
        if masked_crc(body) != u32::from_le_bytes(crc.try_into().unwrap()) {
            break;
        }
        let Ok(event) = Event::decode(body) else { break };
        if event.step as u64 > step {
            break;
        }
        keep += 12 + length + 4;
        last = Some(event.step as u64);
    }
    Ok((keep, last))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// TensorFlow's own test vector for the masked CRC of the empty string and of "a" (CRC-32C
    /// 0 and 0xc1d04330).
    #[test]
    fn the_masked_crc_is_tensorflows() {
        assert_eq!(crc32c::crc32c(b"a"), 0xc1d0_4330);
        assert_eq!(masked_crc(b""), 0xa282_ead8);
        assert_eq!(masked_crc(b"a"), 0xc1d0_4330u32.rotate_right(15).wrapping_add(0xa282_ead8));
    }

    #[test]
    fn a_resumed_writer_cuts_back_to_the_step_and_ends_with_the_same_bytes() {
        let dir = std::env::temp_dir().join(format!("rlmflow-tensorboard-{}", std::process::id()));
        let write = |from: u64, to: u64| {
            let mut w = EventWriter::resume(&dir, from).unwrap().unwrap();
            for step in from + 1..=to {
                w.scalars(step, &[("train/loss".into(), 1.0 / step as f64)]).unwrap();
            }
        };
        write(0, 6);
        let whole = std::fs::read(dir.join(FILE)).unwrap();
        // Killed after step 6 with step 4 checkpointed, and a record cut short: resumed from 4.
        let mut cut = whole.clone();
        cut.extend_from_slice(&whole[whole.len() - 10..]);
        std::fs::write(dir.join(FILE), &cut).unwrap();
        write(4, 6);
        assert_eq!(std::fs::read(dir.join(FILE)).unwrap(), whole);
        // A file that stops short of the checkpoint cannot be resumed.
        std::fs::write(dir.join(FILE), &whole[..whole.len() / 2]).unwrap();
        assert!(EventWriter::resume(&dir, 6).unwrap().is_none());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
