//! From four range-angle maps to images, and from ego-frame positions to pixels. Three views:
//! the default 360-degree range-azimuth image (the four radars merged by maximum), a Cartesian
//! bird's-eye image, and each radar's own range-angle map.

use std::f64::consts::PI;

use rand_chacha::ChaCha8Rng;

use crate::RadarConfig;
use crate::response::{Path, range_angle};
use crate::scatter::{MOUNTS, Segment, VehicleBox, scatterers};

/// What an image shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum View {
    /// Rows range from the ego (row 0 at the ego), columns azimuth over the full circle: column
    /// 0 straight behind (via the left), the centre column straight ahead, left of centre the
    /// ego's left.
    RangeAzimuth,
    /// Cartesian, ego at the centre, ahead up, the ego's left on the left; the image spans
    /// +-range_max_m both ways.
    Bev,
    /// One radar's own map (index into [`MOUNTS`]): rows range from the radar, columns angle
    /// across its field of view, its left on the left.
    Radar(usize),
}

impl View {
    /// Every view's name, as settings spell them.
    pub const NAMES: [&'static str; 6] = ["range-azimuth", "bev", "radar-front", "radar-left", "radar-back", "radar-right"];

    pub fn parse(name: &str) -> Option<View> {
        match name {
            "range-azimuth" => Some(View::RangeAzimuth),
            "bev" => Some(View::Bev),
            _ => MOUNTS.iter().position(|m| name.strip_prefix("radar-") == Some(m.name)).map(View::Radar),
        }
    }

    pub fn name(&self) -> String {
        match self {
            View::RangeAzimuth => "range-azimuth".into(),
            View::Bev => "bev".into(),
            View::Radar(i) => format!("radar-{}", MOUNTS[*i].name),
        }
    }
}

/// How ego-frame points map to a view's pixels.
#[derive(Clone, Copy, Debug)]
pub struct Projection {
    pub view: View,
    pub size: usize,
    pub range_max_m: f64,
    /// Half the field of view of one radar, radians (the per-radar views span it).
    pub half_fov: f64,
}

impl Projection {
    pub fn new(view: View, cfg: &RadarConfig) -> Projection {
        Projection { view, size: cfg.image, range_max_m: cfg.range_max_m, half_fov: cfg.fov_deg.to_radians() }
    }

    /// Continuous pixel coordinates (row, col) of an ego-frame point; pixel centres are at
    /// integer + 0.5. Points outside the view map outside [0, size).
    pub fn pixel(&self, x: f64, y: f64) -> (f64, f64) {
        let s = self.size as f64;
        match self.view {
            View::RangeAzimuth => {
                let azimuth = y.atan2(x); // counter-clockwise from ahead
                (x.hypot(y) / self.range_max_m * s, (PI - azimuth) / (2.0 * PI) * s)
            }
            View::Bev => ((self.range_max_m - x) / (2.0 * self.range_max_m) * s, (self.range_max_m - y) / (2.0 * self.range_max_m) * s),
            View::Radar(i) => {
                let m = &MOUNTS[i];
                let (sin, cos) = m.yaw.sin_cos();
                let (dx, dy) = (x - m.x, y - m.y);
                let (lx, ly) = (dx * cos + dy * sin, -dx * sin + dy * cos);
                (lx.hypot(ly) / self.range_max_m * s, (self.half_fov - ly.atan2(lx)) / (2.0 * self.half_fov) * s)
            }
        }
    }

    /// The ego-frame point at continuous pixel coordinates.
    pub fn point(&self, row: f64, col: f64) -> (f64, f64) {
        let s = self.size as f64;
        match self.view {
            View::RangeAzimuth => {
                let range = row / s * self.range_max_m;
                let azimuth = PI - col / s * 2.0 * PI;
                (range * azimuth.cos(), range * azimuth.sin())
            }
            View::Bev => (self.range_max_m - row / s * 2.0 * self.range_max_m, self.range_max_m - col / s * 2.0 * self.range_max_m),
            View::Radar(i) => {
                let m = &MOUNTS[i];
                let range = row / s * self.range_max_m;
                let angle = self.half_fov - col / s * 2.0 * self.half_fov + m.yaw;
                (m.x + range * angle.cos(), m.y + range * angle.sin())
            }
        }
    }
}

/// The four radars' range-angle power grids for one scene (index as [`MOUNTS`]).
pub fn radar_grids(cfg: &RadarConfig, vehicles: &[VehicleBox], edges: &[Segment], path: Path, rng: &mut ChaCha8Rng) -> Vec<Vec<f64>> {
    MOUNTS
        .iter()
        .map(|mount| {
            let s = scatterers(cfg, mount, vehicles, edges, rng);
            range_angle(cfg, &s, path, true, rng).power
        })
        .collect()
}

/// One bilinear sample of one radar's range-angle grid.
#[derive(Clone, Copy, Debug)]
struct Tap {
    radar: u8,
    index: [u32; 4],
    weight: [f32; 4],
}

/// Precomputed resampling from the radars' range-angle grids to one view: each pixel averages
/// a few bilinear samples per radar (enough to cover its footprint), and takes the maximum over
/// the radars that see it (only its own radar in a per-radar view).
pub struct ImageMap {
    cfg: RadarConfig,
    pub projection: Projection,
    /// Per pixel, its taps; `starts[p]..starts[p + 1]` index `taps`.
    starts: Vec<u32>,
    taps: Vec<Tap>,
}

impl ImageMap {
    pub fn new(cfg: &RadarConfig, view: View) -> ImageMap {
        let size = cfg.image;
        let projection = Projection::new(view, cfg);
        let dr = cfg.range_resolution();
        let (n, m) = (cfg.range_samples, cfg.angle_bins);
        // Sub-samples per pixel side: enough that neighbouring samples are about a bin apart.
        let range_sub = ((cfg.range_max_m / size as f64 / dr).ceil() as usize).clamp(1, 8);
        let angle_sub = ((2.0 * PI / size as f64) / (2.0 / m as f64)).ceil().clamp(1.0, 8.0) as usize;
        let cos_fov = cfg.fov_deg.to_radians().cos();
        let mut starts = Vec::with_capacity(size * size + 1);
        let mut taps = Vec::new();
        for row in 0..size {
            for col in 0..size {
                starts.push(taps.len() as u32);
                for (radar, mount) in MOUNTS.iter().enumerate() {
                    if matches!(view, View::Radar(only) if only != radar) {
                        continue;
                    }
                    let (sin_yaw, cos_yaw) = mount.yaw.sin_cos();
                    let mut pixel_taps = Vec::new();
                    for i in 0..range_sub {
                        for j in 0..angle_sub {
                            let (x, y) =
                                projection.point(row as f64 + (i as f64 + 0.5) / range_sub as f64, col as f64 + (j as f64 + 0.5) / angle_sub as f64);
                            let (dx, dy) = (x - mount.x, y - mount.y);
                            let (lx, ly) = (dx * cos_yaw + dy * sin_yaw, -dx * sin_yaw + dy * cos_yaw);
                            let r = (lx * lx + ly * ly).sqrt();
                            if r < 0.5 || lx / r < cos_fov {
                                continue;
                            }
                            let rho = r / dr;
                            let alpha = (ly / r) * m as f64 / 2.0;
                            let (r0, a0) = (rho.floor(), alpha.floor());
                            let (fr, fa) = ((rho - r0) as f32, (alpha - a0) as f32);
                            let (r0, a0) = (r0 as usize, a0 as i64);
                            if r0 + 1 >= n {
                                continue;
                            }
                            let a0w = a0.rem_euclid(m as i64) as usize;
                            let a1w = (a0 + 1).rem_euclid(m as i64) as usize;
                            pixel_taps.push(Tap {
                                radar: radar as u8,
                                index: [(r0 * m + a0w) as u32, (r0 * m + a1w) as u32, ((r0 + 1) * m + a0w) as u32, ((r0 + 1) * m + a1w) as u32],
                                weight: [(1.0 - fr) * (1.0 - fa), (1.0 - fr) * fa, fr * (1.0 - fa), fr * fa],
                            });
                        }
                    }
                    // A radar contributes to a pixel only if it sees all of it.
                    if pixel_taps.len() == range_sub * angle_sub {
                        taps.extend(pixel_taps);
                    }
                }
            }
        }
        starts.push(taps.len() as u32);
        ImageMap { cfg: cfg.clone(), projection, starts, taps }
    }

    /// Renders one scene into this view alone (see [`radar_grids`] and [`ImageMap::merge`] to
    /// render several views of one scene).
    pub fn render(&self, vehicles: &[VehicleBox], edges: &[Segment], path: Path, rng: &mut ChaCha8Rng) -> Vec<f32> {
        self.merge(&radar_grids(&self.cfg, vehicles, edges, path, rng))
    }

    /// Resamples per-radar power grids into the image, in dB above the noise floor or below the
    /// image's peak ([`crate::Normalise`]), mapped to [0, 1] over the configured dynamic range.
    pub fn merge(&self, grids: &[Vec<f64>]) -> Vec<f32> {
        let size = self.cfg.image;
        let mut power = vec![0f32; size * size];
        for (p, out) in power.iter_mut().enumerate() {
            let taps = &self.taps[self.starts[p] as usize..self.starts[p + 1] as usize];
            let mut per_radar = [0f32; 4];
            let mut counts = [0u32; 4];
            for t in taps {
                let g = &grids[t.radar as usize];
                let v: f32 = (0..4).map(|q| g[t.index[q] as usize] as f32 * t.weight[q]).sum();
                per_radar[t.radar as usize] += v;
                counts[t.radar as usize] += 1;
            }
            *out = (0..4).filter(|&r| counts[r] > 0).map(|r| per_radar[r] / counts[r] as f32).fold(0.0, f32::max);
        }
        let range = self.cfg.dynamic_range_db as f32;
        let floor = match self.cfg.normalise {
            crate::Normalise::Calibrated => self.cfg.noise_floor_db() as f32,
            crate::Normalise::PerFrame => {
                let peak = power.iter().cloned().fold(0.0, f32::max);
                if peak <= 0.0 {
                    return power;
                }
                10.0 * peak.log10() - range
            }
        };
        power.iter().map(|&p| if p > 0.0 { ((10.0 * p.log10() - floor) / range).clamp(0.0, 1.0) } else { 0.0 }).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn pixels_and_points_invert() {
        let cfg = RadarConfig::default();
        for name in View::NAMES {
            let view = View::parse(name).unwrap();
            assert_eq!(view.name(), name);
            let p = Projection::new(view, &cfg);
            for (x, y) in [(10.0, 0.5), (-7.0, 3.0), (0.5, -30.0), (-20.0, -0.1)] {
                let (r, c) = p.pixel(x, y);
                let (x2, y2) = p.point(r, c);
                assert!((x - x2).abs() < 1e-9 && (y - y2).abs() < 1e-9, "{name}: ({x}, {y}) -> ({x2}, {y2})");
            }
        }
        // Ahead is the centre column, the left is left of centre; in the bird's-eye view ahead
        // is up.
        let p = Projection::new(View::RangeAzimuth, &cfg);
        assert_eq!(p.pixel(10.0, 0.0).1, 32.0);
        assert_eq!(p.pixel(0.0, 10.0).1, 16.0);
        let bev = Projection::new(View::Bev, &cfg);
        assert_eq!(bev.pixel(0.0, 0.0), (32.0, 32.0));
        assert!(bev.pixel(10.0, 5.0).0 < 32.0 && bev.pixel(10.0, 5.0).1 < 32.0);
        let left = Projection::new(View::Radar(1), &cfg);
        assert_eq!(left.pixel(0.0, 10.9).1, 32.0, "the left radar looks left");
    }

    #[test]
    fn a_vehicle_is_brightest_where_it_is_in_every_view() {
        let cfg = RadarConfig { noise_db: -60.0, ..RadarConfig::default() };
        let cases = [
            (View::RangeAzimuth, vec![(15.0, 0.0), (-12.0, 4.0), (3.0, -25.0), (24.0, 24.0)]),
            (View::Bev, vec![(15.0, 0.0), (-12.0, 4.0), (3.0, -25.0)]),
            (View::Radar(0), vec![(15.0, 0.0), (20.0, 8.0)]),
            (View::Radar(3), vec![(2.0, -18.0)]),
        ];
        for (view, positions) in cases {
            let map = ImageMap::new(&cfg, view);
            for (x, y) in positions {
                let v = VehicleBox { x, y, heading: 0.3, length: 4.5, width: 1.8 };
                let img = map.render(&[v], &[], Path::Fast, &mut ChaCha8Rng::seed_from_u64(5));
                let best = (0..img.len()).max_by(|&a, &b| img[a].total_cmp(&img[b])).unwrap();
                let (row, col) = ((best / cfg.image) as f64 + 0.5, (best % cfg.image) as f64 + 0.5);
                // The radars see the near face: the peak lies within the footprint's pixel extent.
                let pixels: Vec<(f64, f64)> = v.corners().iter().map(|&(cx, cy)| map.projection.pixel(cx, cy)).collect();
                let (rmin, rmax) = pixels.iter().fold((f64::MAX, f64::MIN), |a, p| (a.0.min(p.0), a.1.max(p.0)));
                let (cmin, cmax) = pixels.iter().fold((f64::MAX, f64::MIN), |a, p| (a.0.min(p.1), a.1.max(p.1)));
                assert!(
                    row >= rmin - 1.5 && row <= rmax + 1.5 && col >= cmin - 1.5 && col <= cmax + 1.5,
                    "{view:?}: vehicle at ({x},{y}): peak at ({row},{col}), footprint rows {rmin:.1}..{rmax:.1} cols {cmin:.1}..{cmax:.1}"
                );
            }
        }
    }

    #[test]
    fn calibrated_brightness_of_a_vehicle_does_not_depend_on_the_rest_of_the_frame() {
        let far = VehicleBox { x: 30.0, y: 1.0, heading: 0.0, length: 4.5, width: 1.8 };
        let near = VehicleBox { x: 4.0, y: -9.0, heading: 0.2, length: 4.5, width: 1.8 };
        // The same returns of the far vehicle, alone and with a close vehicle's added.
        let grids = |v: VehicleBox, seed| radar_grids(&RadarConfig::default(), &[v], &[], Path::Fast, &mut ChaCha8Rng::seed_from_u64(seed));
        let (alone, other) = (grids(far, 1), grids(near, 2));
        let both: Vec<Vec<f64>> = alone.iter().zip(&other).map(|(a, b)| a.iter().zip(b).map(|(x, y)| x + y).collect()).collect();
        let brightest = |cfg: &RadarConfig, grids: &[Vec<f64>]| {
            let map = ImageMap::new(cfg, View::RangeAzimuth);
            let img = map.merge(grids);
            let (row, col) = map.projection.pixel(far.x - far.length / 2.0, far.y);
            let at = |r: f64, c: f64| img[r as usize * cfg.image + c as usize];
            (-1..=1).flat_map(|dr| (-1..=1).map(move |dc| (dr as f64, dc as f64))).map(|(dr, dc)| at(row + dr, col + dc)).fold(0.0, f32::max)
        };
        let calibrated = RadarConfig::default();
        let (a, b) = (brightest(&calibrated, &alone), brightest(&calibrated, &both));
        assert!(a > 0.3, "the far vehicle stands out: {a}");
        assert!((a - b).abs() < 1.0 / 255.0, "calibrated: {a} alone, {b} with a close vehicle");
        // Per frame, the close vehicle's peak darkens it.
        let per_frame = RadarConfig { normalise: crate::Normalise::PerFrame, ..calibrated };
        let (a, b) = (brightest(&per_frame, &alone), brightest(&per_frame, &both));
        assert!(a - b > 0.1, "per frame: {a} alone, {b} with a close vehicle");
    }

    #[test]
    fn every_direction_is_covered() {
        let map = ImageMap::new(&RadarConfig::default(), View::RangeAzimuth);
        let size = map.cfg.image;
        // Beyond a few metres every column has taps from at least one radar.
        for col in 0..size {
            let p = 10 * size + col;
            assert!(map.starts[p + 1] > map.starts[p], "column {col} uncovered at row 10");
        }
    }
}
