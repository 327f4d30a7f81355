//! A 77 GHz FMCW MIMO automotive radar model, shared by the scene operators.
//!
//! Four radars (front, back, left, right) each see the scene through a uniform linear array of
//! virtual antennas at half-wavelength spacing (86 by default, like the TI cascade the paper
//! used). [`scatter`] turns scene geometry into point scatterers: points on each vehicle's
//! outline (corners stronger), faces pointing away from the radar removed, points shadowed by a
//! nearer vehicle removed, and weak clutter along road edges and guardrails. Each scatterer's
//! amplitude falls as 1/R^2 (power 1/R^4) and with the element pattern; its phase carries the
//! round trip and a random surface term, so coherent summation produces speckle.
//!
//! [`response`] computes the windowed range-angle response of one radar two ways: the exact
//! reference synthesises the ADC cube and runs the range and angle FFTs; the fast path adds each
//! scatterer's closed-form windowed response (a Hann-windowed Dirichlet kernel in range and in
//! angle), truncated where it is negligible. [`image`] resamples the four radars into a view (by
//! default one 360-degree range-azimuth image, merged by maximum where fields overlap; also a
//! Cartesian bird's-eye image and each radar's own map), log-scales and normalises it, and maps
//! actor positions to pixels.
//!
//! Every draw comes from a `ChaCha8Rng` (the project's seeded generator), named as such rather
//! than as any `Rng`: the rendering code is then compiled once, here, and not again inside each
//! crate that renders (generic, it cost a fresh test build 73 CPU-seconds more).

pub mod image;
pub mod response;
pub mod scatter;

use serde::{Deserialize, Serialize};

pub use image::{ImageMap, Projection, View, radar_grids};
pub use response::{Path, RangeAngle};
pub use scatter::{MOUNTS, Mount, Scatterer, Segment, VehicleBox};

/// Speed of light, m/s.
pub const C: f64 = 299_792_458.0;

/// How an image maps received power to pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Normalise {
    /// A fixed span of `dynamic_range_db` above the receiver noise floor, the same for every
    /// frame: a vehicle at a given range has the same brightness whatever else the frame holds.
    Calibrated,
    /// `dynamic_range_db` below the frame's own peak: one close vehicle darkens every other
    /// return in its frame (the earlier default, kept as an option).
    PerFrame,
}

/// The most memory [`RadarConfig::render_bytes`] may ask of one render thread.
pub const MAX_RENDER_MIB: u64 = 1024;

/// The radar's parameters; the defaults model the paper's 77 GHz TI cascade.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RadarConfig {
    /// Output image side in pixels (64 for the laptop pipeline, 224 for the paper's).
    pub image: usize,
    /// The image covers ranges 0..range_max_m around the ego.
    pub range_max_m: f64,
    /// Complex ADC samples per chirp (range FFT size), 16..=8192.
    pub range_samples: usize,
    /// Chirp bandwidth, 1e6..=1e10 Hz; sets the range resolution c / 2B.
    pub bandwidth_hz: f64,
    /// 1e9..=3e11 Hz.
    pub carrier_hz: f64,
    /// Virtual antennas of the uniform linear array, half a wavelength apart, 2..=1024.
    pub antennas: usize,
    /// Angle FFT size (the array is zero-padded to it), antennas..=8192; with range_samples at
    /// most [`MAX_RENDER_MIB`] per render thread.
    pub angle_bins: usize,
    /// Half the field of view of each radar, degrees.
    pub fov_deg: f64,
    /// How power becomes pixel brightness (see [`Normalise`]).
    pub normalise: Normalise,
    /// The span of dB the image shows (above the noise floor, or below the frame's peak),
    /// (0, 200].
    pub dynamic_range_db: f64,
    /// Receiver noise power per ADC sample, dB relative to a 1 m^2 target at 1 m, -200..=100.
    pub noise_db: f64,
    /// Fast path: range bins kept on each side of a scatterer (angle bins scale with the
    /// zero-padding). 6 keeps the truncation error far below the noise.
    pub truncation_bins: usize,
}

impl Default for RadarConfig {
    fn default() -> Self {
        RadarConfig {
            image: 64,
            range_max_m: 44.0,
            range_samples: 256,
            bandwidth_hz: 800e6,
            carrier_hz: 77e9,
            antennas: 86,
            angle_bins: 128,
            fov_deg: 75.0,
            normalise: Normalise::Calibrated,
            dynamic_range_db: 60.0,
            noise_db: -34.0,
            truncation_bins: 6,
        }
    }
}

impl RadarConfig {
    /// Memory one render thread holds: the four radars' range-angle power maps (f64) and one
    /// complex grid being summed.
    pub fn render_bytes(&self) -> u64 {
        (4 * 8 + 16) * self.range_samples as u64 * self.angle_bins as u64
    }

    /// The mean noise power of one range-angle bin, in dB: the noise per ADC sample through the
    /// Hann windows of both FFTs (sum of squared weights 3n/8 each).
    pub fn noise_floor_db(&self) -> f64 {
        self.noise_db + 10.0 * ((3.0 * self.range_samples as f64 / 8.0) * (3.0 * self.antennas as f64 / 8.0)).log10()
    }

    pub fn range_resolution(&self) -> f64 {
        C / (2.0 * self.bandwidth_hz)
    }

    pub fn wavelength(&self) -> f64 {
        C / self.carrier_hz
    }

    /// Checks the settings; the error names the key and what would be valid.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        if !(8..=1024).contains(&self.image) {
            return Err(("image", format!("must be 8..=1024 pixels, not {}", self.image)));
        }
        if !(1e6..=1e10).contains(&self.bandwidth_hz) {
            return Err(("bandwidth_hz", format!("must be in 1e6..=1e10 Hz, not {}", self.bandwidth_hz)));
        }
        if !(1e9..=3e11).contains(&self.carrier_hz) {
            return Err(("carrier_hz", format!("must be in 1e9..=3e11 Hz, not {}", self.carrier_hz)));
        }
        let unambiguous = self.range_samples as f64 * self.range_resolution();
        if self.range_max_m <= 1.0 || self.range_max_m >= unambiguous {
            return Err(("range_max_m", format!("must be in (1, {unambiguous:.1}) m, the unambiguous range of range_samples and bandwidth_hz")));
        }
        if !(16..=8192).contains(&self.range_samples) {
            return Err(("range_samples", format!("must be in 16..=8192, not {}", self.range_samples)));
        }
        if !(2..=1024).contains(&self.antennas) {
            return Err(("antennas", format!("must be in 2..=1024, not {}", self.antennas)));
        }
        if !(self.antennas..=8192).contains(&self.angle_bins) {
            return Err(("angle_bins", format!("must be in antennas ({})..=8192, not {}", self.antennas, self.angle_bins)));
        }
        let mib = self.render_bytes() >> 20;
        if mib > MAX_RENDER_MIB {
            let message = format!("range_samples x angle_bins needs {mib} MiB per render thread; at most {MAX_RENDER_MIB} MiB");
            return Err(("angle_bins", message));
        }
        if !(self.fov_deg > 0.0 && self.fov_deg < 90.0) {
            return Err(("fov_deg", "must be in (0, 90) degrees".into()));
        }
        if !(self.dynamic_range_db > 0.0 && self.dynamic_range_db <= 200.0) {
            return Err(("dynamic_range_db", format!("must be in (0, 200] dB, not {}", self.dynamic_range_db)));
        }
        if !(-200.0..=100.0).contains(&self.noise_db) {
            return Err(("noise_db", format!("must be in -200..=100 dB, not {}", self.noise_db)));
        }
        if self.truncation_bins == 0 || self.truncation_bins * 2 >= self.range_samples {
            return Err(("truncation_bins", "must be at least 1 and well below range_samples / 2".into()));
        }
        Ok(())
    }
}
