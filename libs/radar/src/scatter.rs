//! Scene geometry to point scatterers, as one radar sees them.

use rand::RngExt;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::RadarConfig;

/// A radar's position and boresight in the ego frame (x forward, y left, yaw counter-clockwise).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Mount {
    pub name: &'static str,
    pub x: f64,
    pub y: f64,
    pub yaw: f64,
}

/// Front, back, left and right radars: together 360 degrees, overlapping at the corners.
pub const MOUNTS: [Mount; 4] = [
    Mount { name: "front", x: 2.0, y: 0.0, yaw: 0.0 },
    Mount { name: "left", x: 0.0, y: 0.9, yaw: std::f64::consts::FRAC_PI_2 },
    Mount { name: "back", x: -2.0, y: 0.0, yaw: std::f64::consts::PI },
    Mount { name: "right", x: 0.0, y: -0.9, yaw: -std::f64::consts::FRAC_PI_2 },
];

/// A vehicle's footprint: centre, heading (radians, ego frame), length and width in metres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct VehicleBox {
    pub x: f64,
    pub y: f64,
    pub heading: f64,
    pub length: f64,
    pub width: f64,
}

impl VehicleBox {
    /// Corners counter-clockwise: front-left, rear-left, rear-right, front-right.
    pub fn corners(&self) -> [(f64, f64); 4] {
        let (s, c) = self.heading.sin_cos();
        let (hl, hw) = (self.length / 2.0, self.width / 2.0);
        [(hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw)].map(|(a, b)| (self.x + a * c - b * s, self.y + a * s + b * c))
    }

    /// Whether the open segment p-q crosses this box's outline.
    fn blocks(&self, p: (f64, f64), q: (f64, f64)) -> bool {
        let k = self.corners();
        (0..4).any(|i| segments_cross(p, q, k[i], k[(i + 1) % 4]))
    }
}

/// A road edge or guardrail: a line of weak clutter.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Segment {
    pub a: (f64, f64),
    pub b: (f64, f64),
}

/// One point scatterer in a radar's own frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Scatterer {
    /// Range from the radar, metres.
    pub range: f64,
    /// sin of the angle off boresight (positive to the radar's left).
    pub u: f64,
    /// Linear amplitude: sqrt(RCS) x element pattern / R^2.
    pub amplitude: f64,
    /// Round trip and surface phase, radians.
    pub phase: f64,
}

const CORNER_RCS: f64 = 10.0;
const EDGE_RCS: f64 = 1.0;
const EDGE_SPACING: f64 = 0.4;
const CLUTTER_RCS: f64 = 0.05;
const CLUTTER_SPACING: f64 = 1.0;

/// The scatterers `mount` sees. `rng` draws surface phases and RCS fluctuation (speckle).
pub fn scatterers(cfg: &RadarConfig, mount: &Mount, vehicles: &[VehicleBox], edges: &[Segment], rng: &mut ChaCha8Rng) -> Vec<Scatterer> {
    let origin = (mount.x, mount.y);
    // (position, RCS, the vehicle it lies on: its own outline cannot shadow it)
    let mut points: Vec<((f64, f64), f64, Option<usize>)> = Vec::new();
    for (i, v) in vehicles.iter().enumerate() {
        let k = v.corners();
        let visible: Vec<bool> = (0..4)
            .map(|e| {
                let (a, b) = (k[e], k[(e + 1) % 4]);
                // Outward normal of a counter-clockwise polygon edge is (dy, -dx).
                let normal = (b.1 - a.1, a.0 - b.0);
                let mid = ((a.0 + b.0) / 2.0 - origin.0, (a.1 + b.1) / 2.0 - origin.1);
                normal.0 * mid.0 + normal.1 * mid.1 < 0.0
            })
            .collect();
        for e in 0..4 {
            if visible[e] || visible[(e + 3) % 4] {
                points.push((k[e], CORNER_RCS, Some(i)));
            }
            if visible[e] {
                let (a, b) = (k[e], k[(e + 1) % 4]);
                let len = ((b.0 - a.0).powi(2) + (b.1 - a.1).powi(2)).sqrt();
                let n = (len / EDGE_SPACING).floor() as usize;
                for j in 1..n {
                    let t = j as f64 / n as f64;
                    let p = (a.0 + t * (b.0 - a.0), a.1 + t * (b.1 - a.1));
                    points.push((p, EDGE_RCS * rng.random_range(0.5..1.5), Some(i)));
                }
            }
        }
    }
    for s in edges {
        let len = ((s.b.0 - s.a.0).powi(2) + (s.b.1 - s.a.1).powi(2)).sqrt();
        let n = (len / CLUTTER_SPACING).ceil().max(1.0) as usize;
        for j in 0..=n {
            let t = j as f64 / n as f64;
            let rcs = CLUTTER_RCS * -(1.0 - rng.random::<f64>()).ln();
            points.push(((s.a.0 + t * (s.b.0 - s.a.0), s.a.1 + t * (s.b.1 - s.a.1)), rcs, None));
        }
    }

    let (sin_yaw, cos_yaw) = mount.yaw.sin_cos();
    let max_range = cfg.range_max_m + 4.0 * cfg.range_resolution();
    let cos_fov = cfg.fov_deg.to_radians().cos();
    let k4 = 4.0 * std::f64::consts::PI / cfg.wavelength();
    let mut out = Vec::with_capacity(points.len());
    for &(p, rcs, own) in &points {
        let (dx, dy) = (p.0 - origin.0, p.1 - origin.1);
        // Into the radar frame: x along boresight, y to its left.
        let (lx, ly) = (dx * cos_yaw + dy * sin_yaw, -dx * sin_yaw + dy * cos_yaw);
        let range = (lx * lx + ly * ly).sqrt();
        if range < 0.5 || range > max_range || lx / range < cos_fov {
            continue;
        }
        let shadowed = vehicles.iter().enumerate().any(|(j, v)| Some(j) != own && v.blocks(origin, p));
        if shadowed {
            continue;
        }
        let cos_theta = lx / range;
        out.push(Scatterer {
            range,
            u: ly / range,
            amplitude: rcs.sqrt() * cos_theta / (range * range),
            phase: (k4 * range + rng.random::<f64>() * std::f64::consts::TAU) % std::f64::consts::TAU,
        });
    }
    out
}

fn cross(o: (f64, f64), a: (f64, f64), b: (f64, f64)) -> f64 {
    (a.0 - o.0) * (b.1 - o.1) - (a.1 - o.1) * (b.0 - o.0)
}

/// Proper intersection of segments p-q and a-b (touching endpoints do not count).
fn segments_cross(p: (f64, f64), q: (f64, f64), a: (f64, f64), b: (f64, f64)) -> bool {
    let d1 = cross(a, b, p);
    let d2 = cross(a, b, q);
    let d3 = cross(p, q, a);
    let d4 = cross(p, q, b);
    const EPS: f64 = 1e-9;
    ((d1 > EPS && d2 < -EPS) || (d1 < -EPS && d2 > EPS)) && ((d3 > EPS && d4 < -EPS) || (d3 < -EPS && d4 > EPS))
}
