//! Writes a Scenes artifact in batches through the checkpoint directory, so a killed stage
//! resumes after its last complete batch.

use std::collections::BTreeMap;
use std::fs::{self, File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

use anyhow::Context as _;
use rlmflow_stages::grid::{DISTANCE_BINS, GridRule, SECTORS};
use rlmflow_stages::scenes::{FORMAT, FRAMES, Frame, HEATMAPS, SUMMARY, Summary};

pub struct SceneWriter {
    dir: PathBuf,
    side: usize,
    done: u64,
}

const DONE: &str = "frames-done";

impl SceneWriter {
    /// Opens the parts in `checkpoint`, cut back to the last complete batch.
    pub fn resume(checkpoint: &Path, side: usize) -> anyhow::Result<SceneWriter> {
        let done: u64 = fs::read_to_string(checkpoint.join(DONE)).ok().and_then(|s| s.trim().parse().ok()).unwrap_or(0);
        let writer = SceneWriter { dir: checkpoint.to_path_buf(), side, done };
        let heatmaps = writer.part(HEATMAPS);
        let frames = writer.part(FRAMES);
        if done == 0 {
            File::create(&heatmaps)?;
            File::create(&frames)?;
        } else {
            // A kill between writing a batch and recording it leaves extra bytes: drop them.
            OpenOptions::new().write(true).open(&heatmaps)?.set_len(done * (side * side) as u64)?;
            let text = fs::read_to_string(&frames)?;
            let keep: String = text.lines().take(done as usize).map(|l| format!("{l}\n")).collect();
            fs::write(&frames, keep)?;
        }
        Ok(writer)
    }

    fn part(&self, name: &str) -> PathBuf {
        self.dir.join(format!("{name}.part"))
    }

    pub fn done(&self) -> u64 {
        self.done
    }

    /// Appends a batch of (frame, heatmap bytes) and records it as complete.
    pub fn append(&mut self, batch: &[(Frame, Vec<u8>)]) -> anyhow::Result<()> {
        let mut heatmaps = OpenOptions::new().append(true).open(self.part(HEATMAPS))?;
        let mut frames = OpenOptions::new().append(true).open(self.part(FRAMES))?;
        for (frame, pixels) in batch {
            assert_eq!(pixels.len(), self.side * self.side, "heatmap size");
            heatmaps.write_all(pixels)?;
            writeln!(frames, "{}", serde_json::to_string(frame)?)?;
        }
        heatmaps.sync_data()?;
        frames.sync_data()?;
        self.done += batch.len() as u64;
        let tmp = self.dir.join(format!("{DONE}.tmp"));
        fs::write(&tmp, self.done.to_string())?;
        fs::rename(tmp, self.dir.join(DONE))?;
        Ok(())
    }

    /// Moves the parts into `output` with the summary and dataset statistics.
    pub fn finish(self, output: &Path, range_max_m: f64, generator: serde_json::Value) -> anyhow::Result<Summary> {
        let mut per_scenario: BTreeMap<String, u64> = BTreeMap::new();
        let mut per_scene = vec![0u64; 21];
        let mut cells: BTreeMap<String, u64> = BTreeMap::new();
        for bin in DISTANCE_BINS {
            for sector in SECTORS {
                cells.insert(format!("{bin}/{sector}"), 0);
            }
        }
        let rule = GridRule::default();
        let file = File::open(self.part(FRAMES))?;
        for line in BufReader::new(file).lines() {
            let frame: Frame = serde_json::from_str(&line?).context("reading back frames")?;
            *per_scenario.entry(frame.scenario.clone()).or_default() += 1;
            let vehicles: Vec<_> = frame.actors.iter().filter(|a| a.class == "car" || a.class == "truck").collect();
            let n = vehicles.len().min(per_scene.len() - 1);
            per_scene[n] += 1;
            for v in vehicles {
                if let Some(cell) = rule.classify(v.x, v.y, v.heading) {
                    *cells.get_mut(&cell.name()).unwrap() += 1;
                }
            }
        }
        while per_scene.len() > 1 && per_scene.last() == Some(&0) {
            per_scene.pop();
        }
        let summary = Summary {
            format: FORMAT,
            frames: self.done,
            image: self.side,
            range_max_m,
            generator,
            frames_per_scenario: per_scenario,
            vehicles_per_scene: per_scene,
            cells,
        };
        for name in [HEATMAPS, FRAMES] {
            fs::rename(self.part(name), output.join(name)).with_context(|| format!("moving {name} into the output"))?;
        }
        fs::write(output.join(SUMMARY), serde_json::to_vec_pretty(&summary)?)?;
        Ok(summary)
    }
}
