//! A recorded range-azimuth map and the sensor geometry that says where each of its bins lies,
//! resampled into rlmflow's 360-degree range-azimuth image so an object's return lands on the
//! pixel the simulators would draw it on. Bins are exact: spaced evenly (in metres or degrees),
//! evenly in the sine of the angle (the angle bins of an FMCW radar's FFT), or at listed centres.

use std::f64::consts::PI;

use rlmflow_radar::{Projection, View};

/// Where the bins of one axis lie: range in metres, azimuth in radians counter-clockwise from
/// straight ahead (the ego's left positive); bin `i`'s centre sits at coordinate `i + 0.5`.
#[derive(Clone, Debug, PartialEq)]
pub enum Bins {
    /// Edges evenly spaced: the first bin begins at `from`, the last ends at `to` (either way round).
    Even { from: f64, to: f64 },
    /// Centres evenly spaced in the sine of the angle, from the first bin's angle to the last's.
    Sine { first: f64, last: f64 },
    /// Each bin's centre, increasing or decreasing.
    Centres(Vec<f64>),
}

impl Bins {
    /// The continuous coordinate of `value` on an axis of `n` bins (`0..=n`); `None` outside it.
    pub fn coordinate(&self, value: f64, n: usize) -> Option<f64> {
        let at = match self {
            Bins::Even { from, to } => (value - from) / (to - from) * n as f64,
            Bins::Sine { first, last } => {
                if value.abs() > PI / 2.0 {
                    return None;
                }
                let (u0, u1) = (first.sin(), last.sin());
                (value.sin() - u0) / (u1 - u0) * (n as f64 - 1.0) + 0.5
            }
            Bins::Centres(centres) => between(centres, value)?,
        };
        (0.0..=n as f64).contains(&at).then_some(at)
    }

    /// `Ok` when the axis can place values on `n` bins; else what is wrong.
    pub fn check(&self, n: usize) -> Result<(), String> {
        match self {
            Bins::Even { from, to } if !(from.is_finite() && to.is_finite() && from != to) => {
                Err(format!("the bins span {from}..{to}: an empty span"))
            }
            Bins::Sine { first, last } if first.sin() == last.sin() || first.abs() > PI / 2.0 || last.abs() > PI / 2.0 => {
                Err("bins even in sine need a first and a last angle within [-90, 90] degrees and apart".into())
            }
            Bins::Centres(c) if c.len() != n => Err(format!("{} bin centres listed for an axis of {n} bins", c.len())),
            Bins::Centres(c) if c.len() >= 2 && !(c.windows(2).all(|w| w[0] < w[1]) || c.windows(2).all(|w| w[0] > w[1])) => {
                Err("the bin centres must increase or decrease throughout".into())
            }
            _ => Ok(()),
        }
    }
}

/// The coordinate of `value` among bin `centres` (linear between neighbours, half a bin beyond
/// the ends); `None` outside.
fn between(centres: &[f64], value: f64) -> Option<f64> {
    let n = centres.len();
    if n < 2 {
        return None;
    }
    let rising = centres[1] > centres[0];
    let key = |v: f64| if rising { v } else { -v };
    let k = centres.partition_point(|&c| key(c) <= key(value)).clamp(1, n - 1) - 1;
    let (a, b) = (centres[k], centres[k + 1]);
    Some(k as f64 + (value - a) / (b - a) + 0.5)
}

/// A recorded map: `rows` range bins by `cols` azimuth bins of values in [0, 1].
pub struct RangeAzimuthMap {
    pub values: Vec<f32>,
    pub rows: usize,
    pub cols: usize,
    pub range: Bins,
    pub azimuth: Bins,
    /// The azimuth bins go all the way round (a scanning radar): angles are taken modulo 360
    /// degrees from the first bin's start.
    pub wraps: bool,
}

impl RangeAzimuthMap {
    /// rlmflow's range-azimuth image of `side` pixels out to `range_max_m`: each pixel's range
    /// and azimuth looked up in the map's bins (bilinear); outside them, black.
    pub fn resample(&self, side: usize, range_max_m: f64) -> Vec<f32> {
        let projection = Projection { view: View::RangeAzimuth, size: side, range_max_m, half_fov: 0.0 };
        (0..side * side)
            .map(|p| {
                let (x, y) = projection.point((p / side) as f64 + 0.5, (p % side) as f64 + 0.5);
                self.at(x, y)
            })
            .collect()
    }

    /// The map's value at the point `x` metres ahead and `y` to the left (bilinear between bins,
    /// across the seam of a map that wraps); outside its bins, 0.
    pub fn at(&self, x: f64, y: f64) -> f32 {
        let mut azimuth = y.atan2(x);
        if self.wraps {
            let start = match &self.azimuth {
                Bins::Even { from, to } => from.min(*to),
                _ => -PI,
            };
            azimuth = start + (azimuth - start).rem_euclid(2.0 * PI);
        }
        match (self.range.coordinate(x.hypot(y), self.rows), self.azimuth.coordinate(azimuth, self.cols)) {
            (Some(row), Some(col)) => bilinear(&self.values, self.rows, self.cols, row, col, self.wraps),
            _ => 0.0,
        }
    }
}

/// Bilinear sample of `values` (height x width) at continuous (row, col), pixel centres at
/// integer + 0.5; 0 outside.
pub fn sample(values: &[f32], height: usize, width: usize, row: f64, col: f64) -> f32 {
    bilinear(values, height, width, row, col, false)
}

/// [`sample`], where `wraps` makes the last column the first's neighbour (a full turn of
/// azimuth) instead of an edge.
fn bilinear(values: &[f32], height: usize, width: usize, row: f64, col: f64, wraps: bool) -> f32 {
    let (r, c) = (row - 0.5, col - 0.5);
    if r < -0.5 || r > height as f64 - 0.5 || (!wraps && (c < -0.5 || c > width as f64 - 0.5)) {
        return 0.0;
    }
    let r0 = r.floor().max(0.0) as usize;
    let (r1, fr) = ((r0 + 1).min(height - 1), (r - r0 as f64).clamp(0.0, 1.0) as f32);
    let (c0, c1, fc) = if wraps {
        let c = c.rem_euclid(width as f64);
        let c0 = c.floor() as usize % width;
        (c0, (c0 + 1) % width, (c - c.floor()) as f32)
    } else {
        let c0 = c.floor().max(0.0) as usize;
        (c0, (c0 + 1).min(width - 1), (c - c0 as f64).clamp(0.0, 1.0) as f32)
    };
    let at = |r: usize, c: usize| values[r * width + c];
    (at(r0, c0) * (1.0 - fc) + at(r0, c1) * fc) * (1.0 - fr) + (at(r1, c0) * (1.0 - fc) + at(r1, c1) * fc) * fr
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bins_place_values_at_their_centres() {
        let even = Bins::Even { from: 0.0, to: 50.0 };
        assert_eq!(even.coordinate(2.5, 10), Some(0.5));
        assert_eq!(even.coordinate(51.0, 10), None);
        // FFT angle bins: centres at arcsin of evenly spaced sines, the ends at +-90 degrees.
        let sine = Bins::Sine { first: PI / 2.0, last: -PI / 2.0 };
        for k in 0..128 {
            let centre = (1.0 - 2.0 * k as f64 / 127.0).asin();
            assert!((sine.coordinate(centre, 128).unwrap() - (k as f64 + 0.5)).abs() < 1e-9, "bin {k}");
        }
        let listed = Bins::Centres(vec![1.0, 2.0, 4.0]);
        assert_eq!(listed.coordinate(3.0, 3), Some(2.0));
        assert_eq!(listed.coordinate(4.5, 3), Some(2.75));
        assert_eq!(listed.coordinate(5.5, 3), None);
        assert!(Bins::Centres(vec![1.0, 3.0, 2.0]).check(3).is_err());
    }

    /// A scanning radar's turn has no edge: straight ahead, between the last column and the
    /// first, is interpolated across the seam, not clamped to either side.
    #[test]
    fn a_full_turn_interpolates_across_its_seam() {
        // Four columns clockwise from ahead (0-90, 90-180, ... degrees), one range bin.
        let map = RangeAzimuthMap {
            values: vec![1.0, 0.0, 0.0, 0.0],
            rows: 1,
            cols: 4,
            range: Bins::Even { from: 0.0, to: 10.0 },
            azimuth: Bins::Even { from: 0.0, to: -2.0 * PI },
            wraps: true,
        };
        let at = |degrees_left: f64| {
            let a = degrees_left.to_radians();
            map.at(5.0 * a.cos(), 5.0 * a.sin())
        };
        assert_eq!(at(-45.0), 1.0, "the first column's centre, 45 degrees to the right");
        assert!((at(0.0) - 0.5).abs() < 1e-6, "ahead: half the first column, half the last ({})", at(0.0));
        assert!((at(22.5) - 0.25).abs() < 1e-6, "{}", at(22.5));
        assert_eq!(at(45.0), 0.0, "the last column's centre");
    }
}
