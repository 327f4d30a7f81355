//! The windowed range-angle response of one radar: exact (ADC cube and FFTs) or fast (closed
//! form per scatterer, truncated).

use std::f64::consts::PI;

use rand::RngExt;
use rand_chacha::ChaCha8Rng;
use rustfft::FftPlannerScalar;
use rustfft::num_complex::Complex64;

use crate::RadarConfig;
use crate::scatter::Scatterer;

/// Which way to compute the response.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Path {
    /// Synthesise the ADC cube, Hann-window it, range FFT, zero-padded angle FFT.
    Exact,
    /// Sum each scatterer's closed-form windowed response over nearby bins only.
    Fast,
}

/// Power on a grid of `range_samples` range bins by `angle_bins` angle bins (row-major by
/// range). Angle bin m holds u = sin(theta) = 2m / angle_bins, wrapped to [-1, 1).
#[derive(Clone, Debug)]
pub struct RangeAngle {
    pub ranges: usize,
    pub angles: usize,
    pub power: Vec<f64>,
}

/// The Dirichlet kernel sum_{k<L} exp(-j 2 pi k delta / L).
fn dirichlet(delta: f64, len: usize) -> Complex64 {
    let l = len as f64;
    let denom = (PI * delta / l).sin();
    let magnitude = if denom.abs() < 1e-12 {
        // delta is a multiple of L: every term is exp(-j 2 pi k n) = 1 (times the sign below).
        l * (PI * delta).cos() / (PI * delta / l).cos()
    } else {
        (PI * delta).sin() / denom
    };
    Complex64::from_polar(1.0, -PI * delta * (l - 1.0) / l) * magnitude
}

/// The DTFT of a periodic Hann window of length L at offset `delta` bins.
fn hann_response(delta: f64, len: usize) -> Complex64 {
    dirichlet(delta, len) * 0.5 - (dirichlet(delta - 1.0, len) + dirichlet(delta + 1.0, len)) * 0.25
}

fn hann(len: usize) -> Vec<f64> {
    (0..len).map(|n| 0.5 - 0.5 * (2.0 * PI * n as f64 / len as f64).cos()).collect()
}

fn gaussian(rng: &mut ChaCha8Rng) -> (f64, f64) {
    // Box-Muller: two independent standard normals.
    let u1: f64 = 1.0 - rng.random::<f64>();
    let u2: f64 = rng.random::<f64>();
    let r = (-2.0 * u1.ln()).sqrt();
    let (s, c) = (2.0 * PI * u2).sin_cos();
    (r * c, r * s)
}

/// The response of one radar to `scatterers`, with receiver noise drawn from `rng` (none when
/// `noise` is false).
pub fn range_angle(cfg: &RadarConfig, scatterers: &[Scatterer], path: Path, noise: bool, rng: &mut ChaCha8Rng) -> RangeAngle {
    match path {
        Path::Exact => exact(cfg, scatterers, noise, rng),
        Path::Fast => fast(cfg, scatterers, noise, rng),
    }
}

fn fast(cfg: &RadarConfig, scatterers: &[Scatterer], noise: bool, rng: &mut ChaCha8Rng) -> RangeAngle {
    let (n, k, m) = (cfg.range_samples, cfg.antennas, cfg.angle_bins);
    let mut grid = vec![Complex64::new(0.0, 0.0); n * m];
    let dr = cfg.range_resolution();
    let tr = cfg.truncation_bins as i64;
    let ta = (cfg.truncation_bins as f64 * m as f64 / k as f64).ceil() as i64;
    let mut range_taps = Vec::with_capacity(2 * tr as usize + 2);
    let mut angle_taps = Vec::with_capacity(2 * ta as usize + 1);
    for s in scatterers {
        let rho = s.range / dr;
        let r0 = rho.floor() as i64;
        range_taps.clear();
        for b in (r0 - tr)..=(r0 + tr + 1) {
            range_taps.push((b.rem_euclid(n as i64) as usize, hann_response(b as f64 - rho, n)));
        }
        let centre = s.u * m as f64 / 2.0;
        let a0 = centre.round() as i64;
        angle_taps.clear();
        for b in (a0 - ta)..=(a0 + ta) {
            let delta = k as f64 * (b as f64 / m as f64 - s.u / 2.0);
            angle_taps.push((b.rem_euclid(m as i64) as usize, hann_response(delta, k)));
        }
        let amp = Complex64::from_polar(s.amplitude, s.phase);
        for &(ri, rv) in &range_taps {
            let row = &mut grid[ri * m..(ri + 1) * m];
            let rv = amp * rv;
            for &(ai, av) in &angle_taps {
                row[ai] += rv * av;
            }
        }
    }
    let mut power: Vec<f64> = grid.iter().map(|c| c.norm_sqr()).collect();
    if noise {
        // Noise per ADC sample, through both windows: variance sigma^2 sum w_n^2 sum w_k^2.
        let gain = (3.0 * n as f64 / 8.0) * (3.0 * k as f64 / 8.0);
        let sigma = (10f64.powf(cfg.noise_db / 10.0) * gain / 2.0).sqrt();
        for (p, c) in power.iter_mut().zip(&grid) {
            let (a, b) = gaussian(rng);
            *p = (c + Complex64::new(a * sigma, b * sigma)).norm_sqr();
        }
    }
    RangeAngle { ranges: n, angles: m, power }
}

/// The FFTs of the exact path: rustfft's scalar planner on every machine. Its default planner
/// picks AVX, SSE or NEON code at run time, and those round differently, so the same key would
/// give other scenes on another CPU (the test below shows the difference).
fn exact(cfg: &RadarConfig, scatterers: &[Scatterer], noise: bool, rng: &mut ChaCha8Rng) -> RangeAngle {
    exact_with(&mut FftPlannerScalar::new(), cfg, scatterers, noise, rng)
}

/// A planner of forward FFTs.
trait Plan {
    fn forward(&mut self, len: usize) -> std::sync::Arc<dyn rustfft::Fft<f64>>;
}

impl Plan for FftPlannerScalar<f64> {
    fn forward(&mut self, len: usize) -> std::sync::Arc<dyn rustfft::Fft<f64>> {
        self.plan_fft_forward(len)
    }
}

fn exact_with(planner: &mut impl Plan, cfg: &RadarConfig, scatterers: &[Scatterer], noise: bool, rng: &mut ChaCha8Rng) -> RangeAngle {
    let (n, k, m) = (cfg.range_samples, cfg.antennas, cfg.angle_bins);
    let dr = cfg.range_resolution();
    // The ADC cube: k antennas by n fast-time samples.
    let mut cube = vec![Complex64::new(0.0, 0.0); k * n];
    let mut fast_time = vec![Complex64::new(0.0, 0.0); n];
    for s in scatterers {
        let step = Complex64::from_polar(1.0, 2.0 * PI * (s.range / dr) / n as f64);
        let mut ph = Complex64::from_polar(s.amplitude, s.phase);
        for v in fast_time.iter_mut() {
            *v = ph;
            ph *= step;
        }
        let spatial = Complex64::from_polar(1.0, PI * s.u);
        let mut sp = Complex64::new(1.0, 0.0);
        for ant in 0..k {
            let row = &mut cube[ant * n..(ant + 1) * n];
            for (c, f) in row.iter_mut().zip(&fast_time) {
                *c += f * sp;
            }
            sp *= spatial;
        }
    }
    if noise {
        let sigma = (10f64.powf(cfg.noise_db / 10.0) / 2.0).sqrt();
        for c in cube.iter_mut() {
            let (a, b) = gaussian(rng);
            *c += Complex64::new(a * sigma, b * sigma);
        }
    }
    let (wn, wk) = (hann(n), hann(k));
    let range_fft = planner.forward(n);
    for ant in 0..k {
        let row = &mut cube[ant * n..(ant + 1) * n];
        for (c, w) in row.iter_mut().zip(&wn) {
            *c *= w * wk[ant];
        }
        range_fft.process(row);
    }
    let angle_fft = planner.forward(m);
    let mut power = vec![0.0; n * m];
    let mut column = vec![Complex64::new(0.0, 0.0); m];
    for bin in 0..n {
        column.iter_mut().for_each(|c| *c = Complex64::new(0.0, 0.0));
        for ant in 0..k {
            column[ant] = cube[ant * n + bin];
        }
        angle_fft.process(&mut column);
        for (p, c) in power[bin * m..(bin + 1) * m].iter_mut().zip(&column) {
            *p = c.norm_sqr();
        }
    }
    RangeAngle { ranges: n, angles: m, power }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rustfft::FftPlanner;

    /// The planner that picks vector code at run time: only the test below compares with it.
    impl Plan for FftPlanner<f64> {
        fn forward(&mut self, len: usize) -> std::sync::Arc<dyn rustfft::Fft<f64>> {
            self.plan_fft_forward(len)
        }
    }

    fn scatterers() -> Vec<Scatterer> {
        // A handful at awkward fractional bins, some close enough to interfere coherently.
        [(5.3, 0.1, 1.0, 0.2), (12.71, -0.42, 0.3, 1.9), (12.9, -0.40, 0.5, 4.0), (30.05, 0.77, 0.05, 2.5), (39.9, -0.9, 0.02, 0.0)]
            .iter()
            .map(|&(range, u, a, phase)| Scatterer { range, u, amplitude: a, phase })
            .collect()
    }

    #[test]
    fn the_fast_path_agrees_with_the_exact_reference() {
        let cfg = RadarConfig::default();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let exact = range_angle(&cfg, &scatterers(), Path::Exact, false, &mut rng);
        let fast = range_angle(&cfg, &scatterers(), Path::Fast, false, &mut rng);
        let peak = exact.power.iter().cloned().fold(0.0, f64::max);
        // Within 0.5 dB wherever the exact map is within 40 dB of its peak (what the image's
        // dynamic range shows clearly), and the truncated sidelobes never err by more than
        // -45 dB of the peak anywhere.
        let mut compared = 0;
        for (e, f) in exact.power.iter().zip(&fast.power) {
            if *e > peak * 1e-4 {
                let db = 10.0 * (f / e).log10();
                assert!(db.abs() < 0.5, "fast {f:e} vs exact {e:e}: {db:.2} dB");
                compared += 1;
            }
            assert!((f - e).abs() < peak * 10f64.powf(-4.5), "fast {f:e} vs exact {e:e} (peak {peak:e})");
        }
        assert!(compared >= 5 * 12, "compared only {compared} cells");
    }

    /// The exact path's bytes are the scalar FFT's on every CPU. Where this machine's planner
    /// picks vector code, the test says whether that code rounds differently (the reason for the
    /// pin); it fails only if the exact path stops being the scalar one.
    #[test]
    fn the_exact_path_computes_with_the_scalar_fft_on_every_cpu() {
        let cfg = RadarConfig::default();
        let run = |planner: Option<&mut FftPlanner<f64>>| {
            let mut rng = ChaCha8Rng::seed_from_u64(9);
            match planner {
                Some(p) => exact_with(p, &cfg, &scatterers(), true, &mut rng).power,
                None => range_angle(&cfg, &scatterers(), Path::Exact, true, &mut rng).power,
            }
        };
        let pinned = run(None);
        let mut scalar = FftPlannerScalar::new();
        let by_scalar = exact_with(&mut scalar, &cfg, &scatterers(), true, &mut ChaCha8Rng::seed_from_u64(9)).power;
        assert!(pinned.iter().zip(&by_scalar).all(|(a, b)| a.to_bits() == b.to_bits()), "the exact path is not the scalar FFT's");
        let by_default = run(Some(&mut FftPlanner::new()));
        let differing = pinned.iter().zip(&by_default).filter(|(a, b)| a.to_bits() != b.to_bits()).count();
        println!("this CPU's default FFT planner differs from the scalar one in {differing} of {} cells", pinned.len());
    }

    #[test]
    fn a_scatterer_peaks_at_its_range_and_angle_bin() {
        let cfg = RadarConfig::default();
        let s = [Scatterer { range: 20.0 * cfg.range_resolution(), u: 0.5, amplitude: 1.0, phase: 0.0 }];
        for path in [Path::Exact, Path::Fast] {
            let ra = range_angle(&cfg, &s, path, false, &mut ChaCha8Rng::seed_from_u64(0));
            let best = (0..ra.power.len()).max_by(|&a, &b| ra.power[a].total_cmp(&ra.power[b])).unwrap();
            assert_eq!((best / ra.angles, best % ra.angles), (20, 32), "{path:?}");
            // Coherent gain of both Hann windows: (N/2 * K/2)^2.
            let gain = (cfg.range_samples as f64 / 2.0 * cfg.antennas as f64 / 2.0).powi(2);
            assert!((ra.power[best] / gain - 1.0).abs() < 1e-6, "{path:?}: {}", ra.power[best] / gain);
        }
    }

    #[test]
    fn noise_has_the_stated_power_on_both_paths() {
        let cfg = RadarConfig { range_samples: 64, antennas: 16, angle_bins: 32, ..RadarConfig::default() };
        let gain = (3.0 * 64.0 / 8.0) * (3.0 * 16.0 / 8.0) * 10f64.powf(cfg.noise_db / 10.0);
        for path in [Path::Exact, Path::Fast] {
            let mut rng = ChaCha8Rng::seed_from_u64(3);
            let mut total = 0.0;
            let mut cells = 0.0;
            for _ in 0..20 {
                let ra = range_angle(&cfg, &[], path, true, &mut rng);
                total += ra.power.iter().sum::<f64>();
                cells += ra.power.len() as f64;
            }
            let mean = total / cells;
            // Zero-padding the angle FFT does not change the per-bin noise variance.
            assert!((mean / gain - 1.0).abs() < 0.1, "{path:?}: mean {mean:e} vs {gain:e}");
        }
    }
}
