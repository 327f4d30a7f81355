//! The `import` operator (kind `scenes`): a researcher's own recordings as a Scenes artifact,
//! the one the simulators write, so labels, captions, pretraining and probes run on them.
//!
//! `path` (tracked by content: an edited image reruns the import and what depends on it) is
//! either a directory with a manifest, or an MCAP file:
//!
//! * **Manifest** (`manifest`, JSON lines, one frame per line): the image file (`.npy` of
//!   float32 or uint8, or a grayscale `.png`), optionally its `episode` (a sequence: its frames
//!   share a split), `time` (seconds, increasing within an episode) and `scenario`, and either
//!   its `actors` in the ego frame or the paper's `grid` JSON itself. The image's axes
//!   (`axes`) say how to read it: a range-azimuth map is resampled into rlmflow's 360-degree
//!   range-azimuth image of `image` pixels out to `range_max_m`, so actors land on the pixels
//!   the simulators would put them on; `layout = "as-given"` keeps the image (resized to
//!   `image`) and takes each actor's pixel `row` and `col` from the manifest.
//! * **MCAP** with `foxglove.RawImage` radar channels (`mono8`, square) and a JSON `/actors`
//!   channel of frames, matched by log time: at least the layout rlmflow itself writes, so the
//!   import of a Scenes artifact's `scenes.mcap` gives frames and images equal to the original's
//!   (identity, episode and actors kept).
//!
//! Every problem names the file, the line or frame, and what would be valid; the operator
//! writes its artifact only once every frame has been read.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use rlmflow_radar::{Projection, View};
use rlmflow_stages::grid::Grid;
use rlmflow_stages::scenes::{ACTORS_TOPIC, Actor, Frame, Image};
use rlmflow_stages::{Context, InputOutlines, Operator, OperatorSpec, Outcome, Outline, SettingError, Settings};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::datasets::{Opened, UnknownClasses, carrada, cruw, radiate};
use crate::geometry::{Bins, RangeAzimuthMap, sample};
use crate::raw::{Power, Raw, inside_recording, normalise, read_image};
use crate::render::Rendered;
use crate::writer::SceneWriter;

pub struct Import;

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ImportSettings {
    /// A directory holding `manifest` and the images it names, or an `.mcap` file; relative to
    /// the pipeline file.
    pub path: String,
    /// The manifest's name inside `path`.
    pub manifest: String,
    /// The imported image's side in pixels, 8..=1,024 (0: as the recording has it, for square
    /// images kept as given and MCAP).
    pub image: usize,
    /// The range the imported range-azimuth image reaches, in metres (the simulators' `radar.range_max_m`).
    pub range_max_m: f64,
    /// What `path` holds: `auto` (a manifest, or an MCAP file), or a published dataset in its
    /// own layout: `radiate`, `cruw` (ROD2021), `carrada` (its maps' values read by `axes.power`).
    pub format: Format,
    /// The dataset's sequences to read, by folder name (empty: all).
    pub sequences: Vec<String>,
    /// An annotated object of a class the dataset's table does not map: `error` or `skip`
    /// (counted and named in the import's metrics).
    pub unknown_classes: UnknownClasses,
    /// How the manifest's images are laid out and scaled.
    pub axes: Axes,
    /// The scenario of frames whose line names none.
    pub scenario: String,
    /// Frames per checkpointed batch (does not change the result).
    pub batch: u64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Axes {
    pub layout: Layout,
    /// The ranges the rows cover, from 0 (the radar) to this, in metres.
    pub range_span_m: f64,
    /// The azimuths the columns cover, centred on straight ahead, in degrees, (0, 360].
    pub azimuth_span_deg: f64,
    pub rows: Rows,
    pub columns: Columns,
    /// How the columns divide the azimuth span: evenly in degrees, or evenly in its sine (the
    /// angle bins of an FMCW radar's FFT; the first and last columns' centres at the span's ends).
    pub azimuth_bins: AzimuthBins,
    /// Each column's azimuth centre in degrees, counter-clockwise (the left positive), in column
    /// order: exact axes for any sensor (overrides `azimuth_span_deg` and `azimuth_bins`).
    pub azimuth_centres_deg: Vec<f64>,
    /// Each row's range centre in metres, in row order (overrides `range_span_m` and `rows`).
    pub range_centres_m: Vec<f64>,
    pub power: Power,
    /// For `linear` and `db`: the span below each frame's peak mapped onto the pixel range.
    pub dynamic_range_db: f64,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Layout {
    /// Rows are range, columns azimuth: resampled into rlmflow's range-azimuth image.
    RangeAzimuth,
    /// Kept as it is (resized to `image`); actors need `row` and `col`.
    AsGiven,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Rows {
    /// The first row is at the radar.
    NearFirst,
    FarFirst,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Columns {
    /// The first column is the leftmost azimuth (the ego's left), as rlmflow draws it.
    LeftFirst,
    RightFirst,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AzimuthBins {
    Degrees,
    Sine,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Format {
    Auto,
    Radiate,
    Cruw,
    Carrada,
}

impl Default for ImportSettings {
    fn default() -> Self {
        ImportSettings {
            path: String::new(),
            manifest: "manifest.jsonl".into(),
            image: 64,
            range_max_m: 50.0,
            format: Format::Auto,
            sequences: Vec::new(),
            unknown_classes: UnknownClasses::Error,
            axes: Axes::default(),
            scenario: "imported".into(),
            batch: 256,
        }
    }
}

impl Default for Axes {
    fn default() -> Self {
        Axes {
            layout: Layout::RangeAzimuth,
            range_span_m: 50.0,
            azimuth_span_deg: 180.0,
            rows: Rows::NearFirst,
            columns: Columns::LeftFirst,
            azimuth_bins: AzimuthBins::Degrees,
            azimuth_centres_deg: Vec::new(),
            range_centres_m: Vec::new(),
            power: Power::Linear,
            dynamic_range_db: 40.0,
        }
    }
}

impl Settings for ImportSettings {
    const NON_RESULT: &'static [&'static str] = &["batch"];
    const TRACKED: &'static [&'static str] = &["path"];

    fn check(&self) -> Result<(), SettingError> {
        if self.path.is_empty() {
            return Err(SettingError::new(
                "path",
                "must be set: the recording's directory (with its manifest) or an .mcap file, relative to the pipeline file",
            ));
        }
        if let Err(problem) = inside_recording(&self.manifest) {
            return Err(SettingError::new("manifest", format!("`{}` {problem}; the manifest is named relative to `path`", self.manifest)));
        }
        if self.image != 0 {
            SettingError::check_range("image", self.image, 8..=1024)?;
        }
        SettingError::check_positive("range_max_m", self.range_max_m, 10_000.0)?;
        SettingError::check_positive("axes.range_span_m", self.axes.range_span_m, 10_000.0)?;
        if !(self.axes.azimuth_span_deg > 0.0 && self.axes.azimuth_span_deg <= 360.0) {
            return Err(SettingError::new(
                "axes.azimuth_span_deg",
                format!("must be in (0, 360] (the columns' azimuths, centred on straight ahead), not {}", self.axes.azimuth_span_deg),
            ));
        }
        if self.axes.azimuth_bins == AzimuthBins::Sine && self.axes.azimuth_span_deg > 180.0 {
            return Err(SettingError::new(
                "axes.azimuth_span_deg",
                format!(
                    "{} degrees cannot be spanned by bins even in sine; valid with azimuth_bins = \"sine\": (0, 180]",
                    self.axes.azimuth_span_deg
                ),
            ));
        }
        for (key, list) in [("axes.azimuth_centres_deg", &self.axes.azimuth_centres_deg), ("axes.range_centres_m", &self.axes.range_centres_m)] {
            let bins = Bins::Centres(list.clone());
            if let Some(bad) = list.iter().find(|v| !v.is_finite()) {
                return Err(SettingError::new(key, format!("holds {bad}; every bin centre must be a finite number")));
            }
            if !list.is_empty()
                && let Err(e) = bins.check(list.len())
            {
                return Err(SettingError::new(key, format!("{e}; list one centre per bin, in the image's order")));
            }
        }
        SettingError::check_positive("axes.dynamic_range_db", self.axes.dynamic_range_db, 200.0)?;
        if self.format != Format::Auto && self.image == 0 {
            return Err(SettingError::new("image", "must be set (8..=1024): a dataset's maps are resampled into rlmflow's range-azimuth image"));
        }
        if self.format == Format::Auto && !self.sequences.is_empty() {
            return Err(SettingError::new(
                "sequences",
                "names a dataset's sequences; set `format` to the dataset (\"radiate\", \"cruw\", \"carrada\")",
            ));
        }
        if self.axes.layout == Layout::RangeAzimuth && self.image == 0 && !self.path.ends_with(".mcap") {
            return Err(SettingError::new("image", "must be set (8..=1024) to resample a range-azimuth map; 0 keeps images as given only"));
        }
        SettingError::check_range("batch", self.batch, 1..=4_096)
    }
}

impl Operator for Import {
    type Settings = ImportSettings;

    fn spec(&self) -> OperatorSpec {
        OperatorSpec {
            name: "import",
            kind: "scenes",
            version: 2,
            inputs: None,
            summary: "your own recordings (a manifest of .npy/.png radar images with actors or grids, or an MCAP file) as a Scenes artifact",
        }
    }

    fn outline(&self, s: &ImportSettings, _: &InputOutlines) -> Result<Outline, SettingError> {
        Ok(Outline { image: (s.image > 0).then_some(s.image as u64), ..Outline::default() })
    }

    fn run(&self, s: &ImportSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let source = ctx.input("path")?.to_path_buf();
        let mcap = std::fs::read_dir(&source)?.flatten().map(|e| e.path()).find(|p| p.extension().is_some_and(|e| e == "mcap"));
        let mut sink = Sink { checkpoint: ctx.checkpoint_dir.clone(), batch: s.batch as usize, writer: None, pending: Vec::new(), seen: 0 };
        let (mut skipped, mut warnings) = (BTreeMap::new(), Vec::new());
        let from = match mcap {
            _ if s.format != Format::Auto => {
                let (shown, wanted, unknown) = (Path::new(&s.path), &s.sequences, s.unknown_classes);
                let (opened, name) = match s.format {
                    Format::Radiate => (radiate::open(&source, shown, wanted, unknown)?, "radiate"),
                    Format::Cruw => (cruw::open(&source, shown, wanted, unknown, s.axes.dynamic_range_db)?, "cruw"),
                    Format::Carrada => (carrada::open(&source, shown, wanted, unknown, s.axes.power, s.axes.dynamic_range_db)?, "carrada"),
                    Format::Auto => unreachable!("a dataset format"),
                };
                (skipped, warnings) = read_dataset(opened, s, ctx, &mut sink)?;
                name
            }
            Some(file) if !source.join(&s.manifest).exists() => {
                let shown =
                    if s.path.ends_with(".mcap") { PathBuf::from(&s.path) } else { Path::new(&s.path).join(file.file_name().unwrap_or_default()) };
                read_mcap(&file, &shown, s, &mut sink)?;
                "mcap"
            }
            _ => {
                read_manifest(&source, s, ctx, &mut sink)?;
                "manifest"
            }
        };
        let generator = json!({"operator": "import", "from": from, "settings": s.result_settings()});
        let summary = sink.finish(&ctx.output_dir, s.range_max_m, generator)?;
        let without = summary.frames_without_positions;
        let grids = if without > 0 { format!(", {without} labelled by their grid alone") } else { String::new() };
        let skips = if skipped.is_empty() {
            String::new()
        } else {
            let named: Vec<String> = skipped.iter().map(|(class, n)| format!("{n} {class}")).collect();
            format!("; skipped objects of unknown classes: {}", named.join(", "))
        };
        let warned: String = warnings.iter().map(|w| format!("; warning: {w}")).collect();
        Ok(Outcome {
            metrics: json!({
                "frames": summary.frames, "vehicles": summary.vehicles(), "frames_without_positions": without,
                "skipped_classes": skipped, "warnings": warnings,
            }),
            summary: format!("{} frames from {from}{grids}, {} vehicles{skips}{warned}", summary.frames, summary.vehicles()),
        })
    }
}

/// Where read frames go: into the checkpointed writer in batches, so a recording larger than
/// memory imports, and a killed import resumes after its last batch (frames before it are read
/// again, for the checks, but not written twice).
struct Sink {
    checkpoint: PathBuf,
    batch: usize,
    writer: Option<SceneWriter>,
    pending: Vec<Rendered>,
    /// Frames read so far.
    seen: u64,
}

impl Sink {
    /// Takes the next frame; `images` describes every frame's images.
    fn push(&mut self, images: &[Image], frame: Rendered) -> anyhow::Result<()> {
        if self.writer.is_none() {
            self.writer = Some(SceneWriter::resume(&self.checkpoint, images.to_vec()).context("opening the checkpoint")?);
        }
        let writer = self.writer.as_mut().expect("opened above");
        self.seen += 1;
        if self.seen > writer.done() {
            self.pending.push(frame);
            if self.pending.len() == self.batch {
                writer.append(&std::mem::take(&mut self.pending))?;
            }
        }
        Ok(())
    }

    fn finish(mut self, output: &Path, range_max_m: f64, generator: Value) -> anyhow::Result<rlmflow_stages::scenes::Summary> {
        let mut writer = self.writer.take().context("the recording has no frames")?;
        if !self.pending.is_empty() {
            writer.append(&self.pending)?;
        }
        writer.finish(output, range_max_m, generator)
    }
}

/// One manifest line.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Line {
    image: String,
    #[serde(default)]
    episode: Option<String>,
    #[serde(default)]
    time: Option<f64>,
    #[serde(default)]
    scenario: Option<String>,
    #[serde(default)]
    actors: Option<Vec<LineActor>>,
    #[serde(default)]
    grid: Option<Value>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct LineActor {
    class: String,
    x: f64,
    y: f64,
    heading: f64,
    length: f64,
    width: f64,
    #[serde(default)]
    speed: f64,
    #[serde(default)]
    lane_heading: Option<f64>,
    /// Pixel position in the given image (`layout = "as-given"`), pixel centres at integer + 0.5.
    #[serde(default)]
    row: Option<f64>,
    #[serde(default)]
    col: Option<f64>,
}

fn read_manifest(dir: &Path, s: &ImportSettings, ctx: &Context, sink: &mut Sink) -> anyhow::Result<()> {
    let shown = Path::new(&s.path).join(&s.manifest);
    let text = std::fs::read_to_string(dir.join(&s.manifest)).with_context(|| {
        format!("{}: no manifest `{}` in {} (set `manifest` to its name, or point `path` at an .mcap file)", shown.display(), s.manifest, s.path)
    })?;
    let view = match s.axes.layout {
        Layout::RangeAzimuth => View::RangeAzimuth.name(),
        Layout::AsGiven => "as-given".to_owned(),
    };
    let mut side = s.image;
    let mut shape: Option<(usize, usize, String)> = None;
    let mut last_time: BTreeMap<String, f64> = BTreeMap::new();
    let mut images: Vec<Image> = Vec::new();
    let lines: Vec<(usize, &str)> = text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()).collect();
    if lines.is_empty() {
        bail!("{}: no frames; a manifest has one JSON line per frame", shown.display());
    }
    let progress = ctx.progress(lines.len() as u64, "frames");
    for (index, (n, text)) in lines.into_iter().enumerate() {
        let at = format!("{}:{}", shown.display(), n + 1);
        let line: Line = serde_json::from_str(text).map_err(|e| {
            anyhow::anyhow!(
                "{at}: {e}; a line is {{\"image\": \"frames/0001.npy\", \"episode\": \"...\", \"time\": 0.1, \"actors\": [{{\"class\": \"car\", \"x\": 12.0, \"y\": -1.5, \"heading\": 0.0, \"length\": 4.5, \"width\": 1.8}}]}} or {{\"image\": ..., \"grid\": {{...}}}}"
            )
        })?;
        let raw = read_image(dir, Path::new(&s.path), &line.image).with_context(|| format!("{at}: image `{}`", line.image))?;
        match &shape {
            None => shape = Some((raw.height, raw.width, line.image.clone())),
            Some((h, w, first)) if (*h, *w) != (raw.height, raw.width) => {
                bail!(
                    "{at}: image `{}` is {}x{}, but `{first}` (the first frame's) is {h}x{w}; every image of a recording must have one shape",
                    line.image,
                    raw.height,
                    raw.width
                )
            }
            Some(_) => {}
        }
        if let Some((row, col)) = (0..raw.values.len()).find(|&i| !raw.values[i].is_finite()).map(|i| (i / raw.width, i % raw.width)) {
            bail!(
                "{at}: image `{}` holds {} at row {row}, column {col}; every value must be a finite number",
                line.image,
                raw.values[row * raw.width + col]
            );
        }
        if let (Some(time), Some(episode)) = (line.time, &line.episode) {
            if !time.is_finite() {
                bail!("{at}: `time` must be a finite number of seconds, not {time}");
            }
            if let Some(&before) = last_time.get(episode).filter(|&&before| time <= before) {
                bail!(
                    "{at}: `time` {time} does not follow the episode's previous frame ({before}); within an episode the lines must be in time order"
                );
            }
            last_time.insert(episode.clone(), time);
        }
        if s.axes.layout == Layout::AsGiven && side == 0 {
            if raw.height != raw.width {
                bail!(
                    "{at}: image `{}` is {}x{}; kept as given (image = 0) it must be square, or set `image` to resize it",
                    line.image,
                    raw.height,
                    raw.width
                );
            }
            side = raw.width;
        }
        let unit = normalise(&raw, s.axes.power, s.axes.dynamic_range_db).with_context(|| format!("{at}: image `{}`", line.image))?;
        let pixels = match s.axes.layout {
            Layout::RangeAzimuth => {
                let map = manifest_map(unit, raw.height, raw.width, &s.axes);
                for (bins, n, key) in [(&map.range, raw.height, "axes.range_centres_m"), (&map.azimuth, raw.width, "axes.azimuth_centres_deg")] {
                    bins.check(n).map_err(|e| anyhow::anyhow!("{at}: image `{}` against `{key}`: {e}", line.image))?;
                }
                map.resample(side, s.range_max_m)
            }
            Layout::AsGiven => resize(&unit, raw.height, raw.width, side),
        };
        let bytes = to_bytes(&pixels);
        let scenario = line.scenario.clone().unwrap_or_else(|| s.scenario.clone());
        let index = index as u64;
        let mut frame = match (line.actors, line.grid) {
            (Some(actors), None) => {
                let actors = actors
                    .into_iter()
                    .enumerate()
                    .map(|(k, a)| actor(k, a, &raw, side, s))
                    .collect::<Result<Vec<_>, String>>()
                    .map_err(|e| anyhow::anyhow!("{at}: {e}"))?;
                Frame::new(index, scenario, actors, std::slice::from_ref(&bytes))
            }
            (None, Some(grid)) => {
                Grid::from_json(&grid).map_err(|e| anyhow::anyhow!("{at}: `grid`: {e}"))?;
                Frame::with_grid(index, scenario, grid, std::slice::from_ref(&bytes))
            }
            (Some(_), Some(_)) => bail!("{at}: give either `actors` or `grid`, not both"),
            (None, None) => {
                bail!("{at}: no `actors` and no `grid`; give the frame's actors in the ego frame (an empty list for none) or the paper's grid JSON")
            }
        };
        frame.episode = line.episode;
        if images.is_empty() {
            images.push(Image { view: view.clone(), topic: format!("/radar/{view}"), size: side });
        }
        sink.push(&images, (frame, vec![bytes]))?;
        progress.inc(1);
    }
    progress.finish();
    Ok(())
}

/// A dataset's frames through the sink, each map resampled into rlmflow's range-azimuth image
/// and each object placed on its pixel; returns the objects skipped by class and the reader's
/// warnings (each also in the event log).
fn read_dataset(dataset: Opened, s: &ImportSettings, ctx: &Context, sink: &mut Sink) -> anyhow::Result<(BTreeMap<String, usize>, Vec<String>)> {
    if dataset.frames.is_empty() {
        bail!("{}: no frames", s.path);
    }
    let view = View::RangeAzimuth.name();
    let images = [Image { view: view.clone(), topic: format!("/radar/{view}"), size: s.image }];
    let projection = range_azimuth(s.image, s);
    let progress = ctx.progress(dataset.frames.len() as u64, "frames");
    for (i, read) in dataset.frames.into_iter().enumerate() {
        let recorded = read()?;
        let bytes = to_bytes(&recorded.map.resample(s.image, s.range_max_m));
        let actors = recorded
            .objects
            .iter()
            .enumerate()
            .map(|(k, o)| {
                let (row, col) = projection.pixel(o.x, o.y);
                let (x, y, heading, length, width) = (o.x, o.y, o.heading, o.length, o.width);
                Actor { id: k as u32, class: o.class.into(), x, y, heading, length, width, speed: 0.0, lane_heading: None, row, col }
            })
            .collect();
        let mut frame = Frame::new(i as u64, recorded.scenario, actors, std::slice::from_ref(&bytes));
        frame.episode = Some(recorded.episode);
        sink.push(&images, (frame, vec![bytes]))?;
        progress.inc(1);
    }
    progress.finish();
    for warning in &dataset.warnings {
        ctx.event("warning", json!({ "message": warning }));
    }
    Ok((dataset.skipped, dataset.warnings))
}

/// rlmflow's range-azimuth image of `side` pixels out to `range_max_m`, where actors are placed.
fn range_azimuth(side: usize, s: &ImportSettings) -> Projection {
    Projection { view: View::RangeAzimuth, size: side, range_max_m: s.range_max_m, half_fov: 0.0 }
}

/// A manifest image's map: its rows and columns placed by `axes`.
fn manifest_map(values: Vec<f32>, height: usize, width: usize, axes: &Axes) -> RangeAzimuthMap {
    let span = axes.range_span_m;
    let range = if !axes.range_centres_m.is_empty() {
        Bins::Centres(axes.range_centres_m.clone())
    } else {
        match axes.rows {
            Rows::NearFirst => Bins::Even { from: 0.0, to: span },
            Rows::FarFirst => Bins::Even { from: span, to: 0.0 },
        }
    };
    let half = axes.azimuth_span_deg.to_radians() / 2.0;
    // Counter-clockwise from ahead: the left is positive.
    let (first, last) = match axes.columns {
        Columns::LeftFirst => (half, -half),
        Columns::RightFirst => (-half, half),
    };
    let azimuth = if !axes.azimuth_centres_deg.is_empty() {
        Bins::Centres(axes.azimuth_centres_deg.iter().map(|d| d.to_radians()).collect())
    } else {
        match axes.azimuth_bins {
            AzimuthBins::Degrees => Bins::Even { from: first, to: last },
            AzimuthBins::Sine => Bins::Sine { first, last },
        }
    };
    RangeAzimuthMap { values, rows: height, cols: width, range, azimuth, wraps: false }
}

/// An image resized to `side` x `side` (bilinear; the same image when the sizes agree).
fn resize(values: &[f32], height: usize, width: usize, side: usize) -> Vec<f32> {
    if (height, width) == (side, side) {
        return values.to_vec();
    }
    let (sr, sc) = (height as f64 / side as f64, width as f64 / side as f64);
    (0..side * side).map(|p| sample(values, height, width, ((p / side) as f64 + 0.5) * sr, ((p % side) as f64 + 0.5) * sc)).collect()
}

const CLASSES: &str = "car, truck, walker, sign:<name> (e.g. sign:stop)";

fn actor(k: usize, a: LineActor, raw: &Raw, side: usize, s: &ImportSettings) -> Result<Actor, String> {
    let known = matches!(a.class.as_str(), "car" | "truck" | "walker") || a.class.strip_prefix("sign:").is_some_and(|n| !n.is_empty());
    if !known {
        return Err(format!("actor {k}: unknown class `{}`; valid: {CLASSES}", a.class));
    }
    for (name, v) in [("x", a.x), ("y", a.y), ("heading", a.heading), ("length", a.length), ("width", a.width), ("speed", a.speed)] {
        if !v.is_finite() {
            return Err(format!("actor {k}: `{name}` must be a finite number, not {v}"));
        }
    }
    let (row, col) = match (s.axes.layout, a.row, a.col) {
        (Layout::RangeAzimuth, None, None) => range_azimuth(side, s).pixel(a.x, a.y),
        (Layout::RangeAzimuth, _, _) => {
            return Err(format!("actor {k}: `row`/`col` are for layout = \"as-given\"; with a range-azimuth layout the position comes from x and y"));
        }
        (Layout::AsGiven, Some(row), Some(col)) => (row * side as f64 / raw.height as f64, col * side as f64 / raw.width as f64),
        (Layout::AsGiven, _, _) => {
            return Err(format!(
                "actor {k}: no `row` and `col`; with layout = \"as-given\" rlmflow cannot place it in the image: give its pixel position, or the image's axes (layout = \"range-azimuth\")"
            ));
        }
    };
    Ok(Actor {
        id: k as u32,
        class: a.class,
        x: a.x,
        y: a.y,
        heading: a.heading,
        length: a.length,
        width: a.width,
        speed: a.speed,
        lane_heading: a.lane_heading,
        row,
        col,
    })
}

/// An MCAP file's frames: the `/actors` message (a Frame, JSON) and the `foxglove.RawImage`
/// messages of each log time. A first pass finds the image channels (in the order they first
/// appear; the first is the primary image); the second hands each frame on once it is whole.
fn read_mcap(file: &Path, shown: &Path, s: &ImportSettings, sink: &mut Sink) -> anyhow::Result<()> {
    let opened = std::fs::File::open(file).with_context(|| format!("reading {}", shown.display()))?;
    // SAFETY: the file is a snapshot in the store, read-only and never modified in place.
    let bytes = unsafe { memmap2::Mmap::map(&opened) }.with_context(|| format!("reading {}", shown.display()))?;
    let messages = || mcap::MessageStream::new(&bytes).with_context(|| format!("{}: not an MCAP file", shown.display()));
    let mut channels: Vec<Image> = Vec::new();
    for (read, message) in messages()?.enumerate() {
        let message = message.with_context(|| damaged(shown, read))?;
        if is_raw_image(&message.channel) && !channels.iter().any(|c| c.topic == message.channel.topic) {
            let size = (raw_image(shown, &message)?.len() as f64).sqrt() as usize;
            let topic = message.channel.topic.clone();
            channels.push(Image { view: topic.strip_prefix("/radar/").unwrap_or(&topic).to_owned(), topic, size });
        }
    }
    if channels.is_empty() {
        bail!("{}: no foxglove.RawImage channel; the radar images must be RawImage messages (mono8)", shown.display());
    }
    let side = if s.image == 0 { channels[0].size } else { s.image };
    let images: Vec<Image> = channels.iter().map(|c| Image { size: side, ..c.clone() }).collect();

    // By log time: the frame's actors once seen, and its images by channel.
    let mut pending: BTreeMap<u64, Partial> = BTreeMap::new();
    let mut index = 0;
    for (read, message) in messages()?.enumerate() {
        let message = message.with_context(|| damaged(shown, read))?;
        let topic = &message.channel.topic;
        let entry = pending.entry(message.log_time).or_default();
        if topic == ACTORS_TOPIC {
            let frame: Frame = serde_json::from_slice(&message.data).with_context(|| {
                format!("{}: message {} on {topic}: not a frame (JSON with index, id, scenario, actors)", shown.display(), message.sequence)
            })?;
            entry.0 = Some(frame);
        } else if let Some(slot) = channels.iter().position(|c| &c.topic == topic) {
            let data = raw_image(shown, &message)?;
            if data.len() != channels[slot].size * channels[slot].size {
                bail!(
                    "{}: message {} on {topic}: an image of {} bytes, but the channel's first was {} pixels square",
                    shown.display(),
                    message.sequence,
                    data.len(),
                    channels[slot].size
                );
            }
            entry.1.insert(slot, data);
        }
        let whole = entry.0.is_some() && entry.1.len() == channels.len();
        if whole {
            let (frame, mut pixels) = pending.remove(&message.log_time).expect("the entry above");
            let mut frame = frame.expect("whole");
            let views: Vec<Vec<u8>> =
                (0..channels.len()).map(|slot| resize_bytes(pixels.remove(&slot).expect("whole"), channels[slot].size, side)).collect();
            if side != channels[0].size {
                let scale = side as f64 / channels[0].size as f64;
                frame.actors.iter_mut().for_each(|a| (a.row, a.col) = (a.row * scale, a.col * scale));
            }
            frame.index = index;
            index += 1;
            sink.push(&images, (frame, views))?;
        }
    }
    if let Some((time, (frame, pixels))) = pending.into_iter().next() {
        let missing = match frame {
            None => format!("no {ACTORS_TOPIC} message"),
            Some(_) => format!(
                "no image on {}",
                channels.iter().enumerate().find(|(slot, _)| !pixels.contains_key(slot)).map_or("", |(_, c)| c.topic.as_str())
            ),
        };
        bail!("{}: the frame at log time {time} ns has {missing}; every frame needs its actors and one image per radar channel", shown.display());
    }
    Ok(())
}

type Partial = (Option<Frame>, BTreeMap<usize, Vec<u8>>);

/// An MCAP file damaged after its first `read` messages, for the error.
fn damaged(shown: &Path, read: usize) -> String {
    format!("{}: a damaged record after message {read} (the first {read} messages read whole)", shown.display())
}

fn is_raw_image(channel: &mcap::Channel<'_>) -> bool {
    channel.schema.as_ref().is_some_and(|schema| schema.name == "foxglove.RawImage")
}

/// A `foxglove.RawImage` message's pixels: square, mono8, one byte per pixel.
fn raw_image(shown: &Path, message: &mcap::Message<'_>) -> anyhow::Result<Vec<u8>> {
    use prost::Message as _;
    let at = format!("{}: message {} on {}", shown.display(), message.sequence, message.channel.topic);
    let image = foxglove::messages::RawImage::decode(&message.data[..]).with_context(|| format!("{at}: not a foxglove.RawImage"))?;
    let side = image.width as usize;
    if image.encoding != "mono8" || image.height != image.width || image.step != image.width || image.data.len() != side * side {
        bail!("{at}: a {}x{} `{}` image; valid: square mono8 images, one byte per pixel", image.width, image.height, image.encoding);
    }
    Ok(image.data.to_vec())
}

/// Values in [0, 1] as an image's bytes (value / 255).
fn to_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect()
}

/// A mono8 image of `from` pixels square at `to` pixels square (the same bytes when equal).
fn resize_bytes(data: Vec<u8>, from: usize, to: usize) -> Vec<u8> {
    if from == to {
        return data;
    }
    let unit: Vec<f32> = data.iter().map(|&v| f32::from(v) / 255.0).collect();
    to_bytes(&resize(&unit, from, from, to))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A spot of power at (x, y) in a front-facing map lands on the pixel the simulators' image
    /// puts (x, y) on, whichever way the map's rows and columns run.
    #[test]
    fn a_range_azimuth_map_is_resampled_so_actors_sit_on_their_returns() {
        let (rows, cols) = (50, 90);
        let (x, y) = (20.0f64, 8.0f64);
        for (row_order, col_order) in [(Rows::NearFirst, Columns::LeftFirst), (Rows::FarFirst, Columns::RightFirst)] {
            let s = ImportSettings { image: 64, axes: Axes { rows: row_order, columns: col_order, ..Axes::default() }, ..ImportSettings::default() };
            let mut values = vec![1e-3f32; rows * cols];
            let (range, azimuth) = (x.hypot(y), y.atan2(x).to_degrees());
            let row = match row_order {
                Rows::NearFirst => range / 50.0 * rows as f64,
                Rows::FarFirst => (1.0 - range / 50.0) * rows as f64,
            } as usize;
            let col = match col_order {
                Columns::LeftFirst => (90.0 - azimuth) / 180.0 * cols as f64,
                Columns::RightFirst => (azimuth + 90.0) / 180.0 * cols as f64,
            } as usize;
            // A spot as wide as an output pixel (64 columns over 360 degrees are 2.8 map columns).
            for r in row - 2..=row + 2 {
                for c in col - 4..=col + 4 {
                    values[r * cols + c] = 1e3;
                }
            }
            let raw = Raw { height: rows, width: cols, values, integer_max: None };
            let unit = normalise(&raw, s.axes.power, s.axes.dynamic_range_db).unwrap();
            let image = manifest_map(unit, rows, cols, &s.axes).resample(64, s.range_max_m);
            let placed = actor(
                0,
                LineActor { class: "car".into(), x, y, heading: 0.0, length: 4.5, width: 1.8, speed: 0.0, lane_heading: None, row: None, col: None },
                &raw,
                64,
                &s,
            )
            .unwrap();
            let at = |r: f64, c: f64| image[r as usize * 64 + c as usize];
            assert!(at(placed.row, placed.col) > 0.9, "{row_order:?} {col_order:?}: {}", at(placed.row, placed.col));
            // Behind the ego, outside the map's 180 degrees: black.
            assert_eq!(at(placed.row, 2.0), 0.0);
        }
    }

    /// An FFT radar's map, its columns even in the sine of the angle (or listed bin by bin):
    /// read with those axes, a return far off axis lands under its actor; read as even in
    /// degrees, it does not.
    #[test]
    fn sine_and_listed_azimuth_bins_put_an_off_axis_return_under_its_actor() {
        let (rows, cols) = (64, 64);
        let (x, y) = (10.0f64, 14.0f64); // 54 degrees to the left
        let sine_col = |azimuth: f64| (1.0 - azimuth.sin()) / 2.0 * (cols - 1) as f64; // left first, centres at +-90
        let centres: Vec<f64> = (0..cols).map(|j| (1.0 - 2.0 * j as f64 / (cols - 1) as f64).asin().to_degrees()).collect();
        let mut values = vec![1e-3f32; rows * cols];
        let (row, col) = ((x.hypot(y) / 50.0 * rows as f64) as usize, sine_col(y.atan2(x)).round() as usize);
        for r in row - 1..=row + 1 {
            for c in col - 1..=col + 1 {
                values[r * cols + c] = 1e3;
            }
        }
        let raw = Raw { height: rows, width: cols, values, integer_max: None };
        let brightness = |axes: Axes| {
            let s = ImportSettings { image: 128, axes, ..ImportSettings::default() };
            let image =
                manifest_map(normalise(&raw, s.axes.power, s.axes.dynamic_range_db).unwrap(), rows, cols, &s.axes).resample(128, s.range_max_m);
            let (r, c) = range_azimuth(128, &s).pixel(x, y);
            image[r as usize * 128 + c as usize]
        };
        assert!(brightness(Axes { azimuth_bins: AzimuthBins::Sine, ..Axes::default() }) > 0.9);
        assert!(brightness(Axes { azimuth_centres_deg: centres, ..Axes::default() }) > 0.9);
        assert!(brightness(Axes::default()) < 0.5, "read as even in degrees the return is elsewhere");
    }
}
