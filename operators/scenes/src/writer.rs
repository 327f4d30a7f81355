//! Writes a Scenes artifact. Frames go in batches to plain part files in the checkpoint
//! directory, so a killed stage resumes after its last complete batch; `finish` then writes the
//! MCAP file, its index and the summary into the output.

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::fs::{self, File, OpenOptions};
use std::io::{BufRead, BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use foxglove::Encode;
use foxglove::bytes::Bytes;
use foxglove::messages::{RawImage, Timestamp};
use mcap::records::{MessageHeader, Record};
use rlmflow_stages::grid::{Cell, DISTANCE_BINS, Grid, GridRule, SECTORS};
use rlmflow_stages::scenes::{ACTORS_TOPIC, FORMAT, Frame, INDEX, Image, MCAP, SUMMARY, Summary};

use crate::render::Rendered;

pub struct SceneWriter {
    dir: PathBuf,
    images: Vec<Image>,
    done: u64,
    cursor: serde_json::Value,
}

/// Frames recorded complete, and the operator's own resume state, written atomically together.
#[derive(Default, serde::Serialize, serde::Deserialize)]
struct Progress {
    frames: u64,
    cursor: serde_json::Value,
}

const PROGRESS: &str = "progress.json";
const FRAMES: &str = "frames.jsonl.part";
/// Nominal time between frames in the MCAP timeline (10 Hz).
const FRAME_PERIOD_NS: u64 = 100_000_000;
/// JSON schema of the /actors channel, for readers that validate.
const FRAME_SCHEMA: &str = r#"{"type":"object","properties":{"index":{"type":"integer"},"id":{"type":"string"},"episode":{"type":"string"},"scenario":{"type":"string"},"actors":{"type":"array","items":{"type":"object","properties":{"id":{"type":"integer"},"class":{"type":"string"},"x":{"type":"number"},"y":{"type":"number"},"heading":{"type":"number"},"length":{"type":"number"},"width":{"type":"number"},"speed":{"type":"number"},"lane_heading":{"type":"number"},"row":{"type":"number"},"col":{"type":"number"}}}}}}"#;

impl SceneWriter {
    /// Opens the parts in `checkpoint`, cut back to the last complete batch.
    pub fn resume(checkpoint: &Path, images: Vec<Image>) -> anyhow::Result<SceneWriter> {
        let progress: Progress = fs::read(checkpoint.join(PROGRESS)).ok().and_then(|b| serde_json::from_slice(&b).ok()).unwrap_or_default();
        let done = progress.frames;
        let writer = SceneWriter { dir: checkpoint.to_path_buf(), images, done, cursor: progress.cursor };
        let frames = writer.dir.join(FRAMES);
        if done == 0 {
            File::create(&frames)?;
        } else {
            // A kill between writing a batch and recording it leaves extra bytes: drop them.
            let text = fs::read_to_string(&frames)?;
            let keep: String = text.lines().take(done as usize).map(|l| format!("{l}\n")).collect();
            fs::write(&frames, keep)?;
        }
        for (k, image) in writer.images.iter().enumerate() {
            let part = writer.image_part(k);
            if done == 0 {
                File::create(&part)?;
            } else {
                OpenOptions::new().write(true).open(&part)?.set_len(done * (image.size * image.size) as u64)?;
            }
        }
        Ok(writer)
    }

    fn image_part(&self, k: usize) -> PathBuf {
        self.dir.join(format!("image-{k}.u8.part"))
    }

    pub fn done(&self) -> u64 {
        self.done
    }

    /// The resume state recorded with the last complete batch (null if none).
    pub fn cursor(&self) -> &serde_json::Value {
        &self.cursor
    }

    /// Appends a batch of rendered frames and records it as complete.
    pub fn append(&mut self, batch: &[Rendered]) -> anyhow::Result<()> {
        self.append_with_cursor(batch, serde_json::Value::Null)
    }

    /// Appends a batch and records it as complete together with the operator's resume state.
    pub fn append_with_cursor(&mut self, batch: &[Rendered], cursor: serde_json::Value) -> anyhow::Result<()> {
        let mut frames = OpenOptions::new().append(true).open(self.dir.join(FRAMES))?;
        let mut parts: Vec<File> =
            (0..self.images.len()).map(|k| OpenOptions::new().append(true).open(self.image_part(k))).collect::<Result<_, _>>()?;
        for (frame, images) in batch {
            assert_eq!(images.len(), self.images.len(), "one image per view");
            for ((part, pixels), info) in parts.iter_mut().zip(images).zip(&self.images) {
                assert_eq!(pixels.len(), info.size * info.size, "image size");
                part.write_all(pixels)?;
            }
            writeln!(frames, "{}", serde_json::to_string(frame)?)?;
        }
        for part in &parts {
            part.sync_data()?;
        }
        frames.sync_data()?;
        self.done += batch.len() as u64;
        self.cursor = cursor;
        let tmp = self.dir.join(format!("{PROGRESS}.tmp"));
        fs::write(&tmp, serde_json::to_vec(&Progress { frames: self.done, cursor: self.cursor.clone() })?)?;
        fs::rename(tmp, self.dir.join(PROGRESS))?;
        Ok(())
    }

    /// Writes `scenes.mcap`, `scenes.index` and `scenes.json` into `output`.
    pub fn finish(self, output: &Path, range_max_m: f64, generator: serde_json::Value) -> anyhow::Result<Summary> {
        let mcap_path = output.join(MCAP);
        let stats = self.write_mcap(&mcap_path).with_context(|| format!("writing {}", mcap_path.display()))?;
        let index = index(&mcap_path, &self.images, self.done).with_context(|| format!("indexing {}", mcap_path.display()))?;
        fs::write(output.join(INDEX), index.iter().flat_map(|o| o.to_le_bytes()).collect::<Vec<u8>>())?;
        let summary = Summary {
            format: FORMAT,
            frames: self.done,
            images: self.images,
            range_max_m,
            generator,
            vehicles_per_scene: stats.vehicles_per_scene(),
            frames_per_scenario: stats.per_scenario,
            cells: stats.cells,
            frames_without_positions: stats.without_positions,
        };
        fs::write(output.join(SUMMARY), serde_json::to_vec_pretty(&summary)?)?;
        Ok(summary)
    }

    /// Streams the parts into an MCAP file; returns the dataset statistics.
    fn write_mcap(&self, path: &Path) -> anyhow::Result<Statistics> {
        let mut stats = Statistics::new();
        let options = mcap::WriteOptions::new().use_chunks(false).compression(None).library(concat!("rlmflow ", env!("CARGO_PKG_VERSION")));
        let mut out = options.create(BufWriter::new(File::create(path)?))?;
        let schema = RawImage::get_schema().expect("RawImage has a schema");
        let image_schema = out.add_schema(&schema.name, &schema.encoding, &schema.data)?;
        let frame_schema = out.add_schema("rlmflow.Frame", "jsonschema", FRAME_SCHEMA.as_bytes())?;
        let actors = out.add_channel(frame_schema, ACTORS_TOPIC, "json", &BTreeMap::new())?;
        let channels: Vec<u16> =
            self.images.iter().map(|i| out.add_channel(image_schema, &i.topic, "protobuf", &BTreeMap::new())).collect::<Result<_, _>>()?;
        let mut frames = BufReader::new(File::open(self.dir.join(FRAMES))?).lines();
        let mut parts: Vec<BufReader<File>> =
            (0..self.images.len()).map(|k| File::open(self.image_part(k)).map(BufReader::new)).collect::<Result<_, _>>()?;
        let mut message = Vec::new();
        for i in 0..self.done {
            let line = frames.next().context("the frames part is shorter than its record")??;
            let frame: Frame = serde_json::from_str(&line).context("reading back frames")?;
            stats.add(&frame)?;
            let time = i * FRAME_PERIOD_NS;
            let header = |channel_id| MessageHeader { channel_id, sequence: i as u32, log_time: time, publish_time: time };
            out.write_to_known_channel(&header(actors), line.as_bytes())?;
            let stamp = Timestamp::new((time / 1_000_000_000) as u32, (time % 1_000_000_000) as u32);
            for ((part, info), &channel) in parts.iter_mut().zip(&self.images).zip(&channels) {
                let mut pixels = vec![0u8; info.size * info.size];
                part.read_exact(&mut pixels)?;
                let side = info.size as u32;
                // `frame_id` stays empty so the pixels are the message's last bytes (see `index`).
                let image = RawImage {
                    timestamp: Some(stamp),
                    frame_id: String::new(),
                    width: side,
                    height: side,
                    encoding: "mono8".into(),
                    step: side,
                    data: Bytes::from(pixels),
                };
                message.clear();
                image.encode(&mut message)?;
                if !message.ends_with(&image.data) {
                    bail!("the RawImage encoding does not end with its pixels; scenes.index would be wrong");
                }
                out.write_to_known_channel(&header(channel), &message)?;
            }
        }
        out.finish()?;
        out.into_inner().into_inner().map_err(|e| e.into_error())?.sync_all()?;
        Ok(stats)
    }
}

/// Reads the finished MCAP once and records, per frame, where the actors message and each
/// image's pixels lie in the file (the layout `scenes.index` documents).
fn index(path: &Path, images: &[Image], frames: u64) -> anyhow::Result<Vec<u64>> {
    let file = File::open(path)?;
    // SAFETY: the file was just written by this process and is not modified while mapped.
    let map = unsafe { memmap2::Mmap::map(&file)? };
    let base = map.as_ptr() as usize;
    let stride = 2 + images.len();
    let mut index = vec![u64::MAX; frames as usize * stride];
    let mut channels = BTreeMap::new();
    // Walk the records (opcode, u64 length, body) so that message bodies stay slices of the map.
    let mut pos = mcap::MAGIC.len();
    while pos + 9 <= map.len() && map[pos] != mcap::records::op::FOOTER {
        let len = u64::from_le_bytes(map[pos + 1..pos + 9].try_into().expect("8 bytes")) as usize;
        let body = map.get(pos + 9..pos + 9 + len).context("truncated record")?;
        match mcap::parse_record(map[pos], body)? {
            Record::Channel(c) => {
                let slot = if c.topic == ACTORS_TOPIC { 0 } else { 2 + images.iter().position(|i| i.topic == c.topic).context("unknown topic")? };
                channels.insert(c.id, slot);
            }
            Record::Message { header, data } => {
                let Cow::Borrowed(data) = data else { bail!("message {} was not read in place", header.sequence) };
                let offset = (data.as_ptr() as usize - base) as u64;
                let row = header.sequence as usize * stride;
                match channels[&header.channel_id] {
                    0 => {
                        index[row] = offset;
                        index[row + 1] = data.len() as u64;
                    }
                    slot => {
                        let size = images[slot - 2].size;
                        index[row + slot] = offset + (data.len() - size * size) as u64;
                    }
                }
            }
            _ => {}
        }
        pos += 9 + len;
    }
    if let Some(missing) = index.iter().position(|&o| o == u64::MAX) {
        bail!("frame {} has no message in slot {}", missing / stride, missing % stride);
    }
    Ok(index)
}

/// The dataset figures: frames per scenario, vehicles per scene, vehicles per cell.
struct Statistics {
    per_scenario: BTreeMap<String, u64>,
    per_scene: Vec<u64>,
    cells: BTreeMap<String, u64>,
    rule: GridRule,
    without_positions: u64,
}

impl Statistics {
    fn new() -> Statistics {
        let cells = DISTANCE_BINS.iter().flat_map(|bin| SECTORS.iter().map(move |sector| (format!("{bin}/{sector}"), 0))).collect();
        Statistics { per_scenario: BTreeMap::new(), per_scene: vec![0; 21], cells, rule: GridRule::default(), without_positions: 0 }
    }

    fn add(&mut self, frame: &Frame) -> anyhow::Result<()> {
        *self.per_scenario.entry(frame.scenario.clone()).or_default() += 1;
        if let Some(given) = &frame.grid {
            let grid = Grid::from_json(given).map_err(|e| anyhow::anyhow!("frame {}: its grid: {e}", frame.index))?;
            let n = (grid.vehicles() as usize).min(self.per_scene.len() - 1);
            self.per_scene[n] += 1;
            for (i, &n) in grid.counts.iter().enumerate().filter(|(_, n)| **n > 0) {
                *self.cells.get_mut(&Cell::from_index(i).name()).expect("every cell is listed") += n as u64;
            }
            self.without_positions += 1;
            return Ok(());
        }
        let vehicles: Vec<_> = frame.actors.iter().filter(|a| a.is_vehicle()).collect();
        let n = vehicles.len().min(self.per_scene.len() - 1);
        self.per_scene[n] += 1;
        for v in vehicles {
            if let Some(cell) = self.rule.classify(v.x, v.y, v.heading) {
                *self.cells.get_mut(&cell.name()).expect("every cell is listed") += 1;
            }
        }
        Ok(())
    }

    /// Frames per vehicle count, without trailing empty counts.
    fn vehicles_per_scene(&self) -> Vec<u64> {
        let used = self.per_scene.iter().rposition(|&n| n > 0).map_or(1, |last| last + 1);
        self.per_scene[..used].to_vec()
    }
}
