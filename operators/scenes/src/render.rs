//! One scene (vehicle boxes and road edges in the ego frame) to a Scenes frame: the radar
//! images of every configured view and the actors with their primary-image pixels. Shared by
//! both scene operators.

use rand::{Rng, RngExt};
use rand_chacha::ChaCha8Rng;
use rlmflow_radar::{ImageMap, Path, RadarConfig, Segment, VehicleBox, View, radar_grids};
use rlmflow_stages::SettingError;
pub use rlmflow_stages::parallel_map;
use rlmflow_stages::scenes::{Actor, Frame, Image};

/// A vehicle as a scene source describes it.
#[derive(Clone, Debug)]
pub struct Vehicle {
    pub id: u32,
    pub class: &'static str,
    pub body: VehicleBox,
    pub speed: f64,
    /// The heading of its lane relative to the ego's lane, where the source knows lanes.
    pub lane_heading: Option<f64>,
}

/// One frame's content before rendering.
#[derive(Clone, Debug)]
pub struct Scene {
    pub scenario: String,
    pub vehicles: Vec<Vehicle>,
    pub edges: Vec<Segment>,
}

/// A rendered frame: actors and one image (size x size bytes) per view.
pub type Rendered = (Frame, Vec<Vec<u8>>);

pub struct Renderer {
    cfg: RadarConfig,
    maps: Vec<ImageMap>,
    path: Path,
}

/// Checks an `images` setting: known view names, at least one, no repeats.
/// The most frames a scenes stage writes in one action (the paper generated 800,000).
pub const MAX_FRAMES: u64 = 10_000_000;

pub fn check_views(images: &[String]) -> Result<Vec<View>, SettingError> {
    if images.is_empty() {
        return Err(SettingError::new("images", format!("must name at least one view of {}", View::NAMES.join(", "))));
    }
    let mut views = Vec::new();
    for name in images {
        let view =
            View::parse(name).ok_or_else(|| SettingError::new("images", format!("unknown view `{name}`; valid: {}", View::NAMES.join(", "))))?;
        if views.contains(&view) {
            return Err(SettingError::new("images", format!("`{name}` is listed twice")));
        }
        views.push(view);
    }
    Ok(views)
}

impl Renderer {
    pub fn new(cfg: &RadarConfig, views: &[View], exact: bool) -> Renderer {
        let maps = views.iter().map(|&v| ImageMap::new(cfg, v)).collect();
        Renderer { cfg: cfg.clone(), maps, path: if exact { Path::Exact } else { Path::Fast } }
    }

    /// The image channels, in order; the first is the primary.
    pub fn images(&self) -> Vec<Image> {
        self.maps
            .iter()
            .map(|m| {
                let view = m.projection.view.name();
                Image { topic: format!("/radar/{view}"), view, size: self.cfg.image }
            })
            .collect()
    }

    pub fn render(&self, index: u64, scene: &Scene, rng: &mut ChaCha8Rng) -> Rendered {
        let bodies: Vec<VehicleBox> = scene.vehicles.iter().map(|v| v.body).collect();
        let grids = radar_grids(&self.cfg, &bodies, &scene.edges, self.path, rng);
        let images: Vec<Vec<u8>> = self.maps.iter().map(|m| m.merge(&grids).iter().map(|&v| (v * 255.0).round() as u8).collect()).collect();
        let primary = &self.maps[0].projection;
        let actors = scene
            .vehicles
            .iter()
            .map(|v| {
                let (row, col) = primary.pixel(v.body.x, v.body.y);
                let b = v.body;
                Actor {
                    id: v.id,
                    class: v.class.into(),
                    x: b.x,
                    y: b.y,
                    heading: b.heading,
                    length: b.length,
                    width: b.width,
                    speed: v.speed,
                    lane_heading: v.lane_heading,
                    row,
                    col,
                }
            })
            .collect();
        (Frame::new(index, scene.scenario.clone(), actors, &images), images)
    }
}

/// An index drawn with probability proportional to `weights`.
pub fn weighted(weights: &[f64], rng: &mut impl Rng) -> usize {
    let total: f64 = weights.iter().sum();
    let mut x = rng.random::<f64>() * total;
    for (i, w) in weights.iter().enumerate() {
        if x < *w {
            return i;
        }
        x -= w;
    }
    weights.len() - 1
}
