//! CRUW's and CARRADA's map grids against their devkits' own numbers. Neither devkit publishes
//! sample data; their grids are defined by code and configuration, cited at each constant
//! (yizhou-wang/cruw-devkit at 7e9317d, valeoai/carrada_dataset at f3f9beb).

use super::{carrada, cruw};
use crate::geometry::Bins;

/// `scipy.constants.speed_of_light`, which `confmap2ra` uses.
const SPEED_OF_LIGHT: f64 = 299_792_458.0;

/// Asserts that the bin whose centre the devkit puts at `value` is bin `k` of ours, centred.
fn centred(bins: &Bins, n: usize, value: f64, k: usize, what: &str) {
    let at = bins.coordinate(value, n).unwrap_or_else(|| panic!("{what} {k}: {value} is off our grid"));
    assert!((at - (k as f64 + 0.5)).abs() < 1e-9, "{what} {k}: the devkit's {value} is at our coordinate {at}, not {}", k as f64 + 0.5);
}

#[test]
fn cruw_bins_are_the_devkits_confmap2ra_grid() {
    // cruw/dataset_configs/sensor_config_rod2021.json, "radar_cfg".
    let (ramap_rsize, ramap_asize, crop_num, sample_freq, sweep_slope, ra_min, ra_max) = (128, 128, 3, 4e6, 21.0017e12, -90.0_f64, 90.0_f64);
    assert_eq!((ramap_rsize, ramap_asize), (cruw::SIZE, cruw::SIZE));
    // cruw/mapping/generate_grids.py, confmap2ra(name='range'): FFT bins 0..fft_Rang at
    // Fs / fft_Rang each, times c / sweepSlope / 2, the first and last crop_num dropped.
    let fft_rang = ramap_rsize + 2 * crop_num;
    let range: Vec<f64> = (0..fft_rang)
        .map(|k| k as f64 * (sample_freq / fft_rang as f64) * SPEED_OF_LIGHT / sweep_slope / 2.0)
        .skip(crop_num)
        .take(ramap_rsize)
        .collect();
    // confmap2ra(name='angle'): arcsin of np.linspace(sin(ra_min), sin(ra_max), ramap_asize),
    // positive to the right (mapping/coor_transform.py, pol2cart_ramap: x = rho * sin(phi)).
    let (w0, w1) = (ra_min.to_radians().sin(), ra_max.to_radians().sin());
    let angle: Vec<f64> = (0..ramap_asize).map(|j| (w0 + (w1 - w0) * j as f64 / (ramap_asize - 1) as f64).asin()).collect();
    // The same grids as numpy prints them from the devkit's function.
    for (k, metres) in [(0, 0.6391645864631144), (1, 0.8522194486174858), (64, 14.274675764342886), (127, 27.697132080068286)] {
        assert!((range[k] - metres).abs() < 1e-12, "range {k}: {} against {metres}", range[k]);
    }
    for (j, degrees) in [(0, -90.0), (1, -79.81825161166375), (63, -0.45115253218247), (64, 0.45115253218247), (127, 90.0)] {
        assert!((angle[j].to_degrees() - degrees).abs() < 1e-9, "angle {j}: {} against {degrees}", angle[j].to_degrees());
    }
    let (ours_range, ours_azimuth) = cruw::bins();
    for (k, &r) in range.iter().enumerate() {
        centred(&ours_range, cruw::SIZE, r, k, "range bin");
    }
    // Ours are counter-clockwise (the left positive); the ends (+-90 degrees) are the bins' centres.
    for (j, &a) in angle.iter().enumerate() {
        centred(&ours_azimuth, cruw::SIZE, -a, j, "angle bin");
    }
}

#[test]
fn carrada_bins_hold_what_the_devkits_to_ra_puts_in_them() {
    // carrada_dataset/utils/transform_annotations.py, AnnotationTransformer: RANGE_RES and
    // ANGLE_RES; scripts/generate_annotation_files.py: RA_SHAPE = (256, 256).
    let (range_res, angle_res, ra_shape) = (0.1953125, 0.01227184630308513, (256_usize, 256_usize));
    assert_eq!(ra_shape, (carrada::SIZE, carrada::SIZE));
    assert_eq!((range_res, angle_res), (carrada::RANGE_RES, carrada::ANGLE_RES));
    // to_ra: range_coordinate = x_shape - int(range / RANGE_RES); angle_coordinate =
    // int(y_shape / 2) + int(arctan(x / y) / ANGLE_RES), x lateral (positive to the right), int
    // truncating towards zero.
    let to_ra = |range: f64, angle: f64| (ra_shape.0 as i64 - (range / range_res) as i64, (ra_shape.1 / 2) as i64 + (angle / angle_res) as i64);
    let (ours_range, ours_azimuth) = carrada::bins();
    // A point a quarter of a bin either side of each bin's middle falls in the devkit's bin and in ours.
    for k in 1..=ra_shape.0 {
        for quarter in [-0.25, 0.25] {
            let range = (k as f64 + 0.5 + quarter) * range_res;
            let (row, _) = to_ra(range, 0.0);
            let ours = ours_range.coordinate(range, carrada::SIZE).unwrap().floor() as i64;
            assert_eq!(ours, row, "{range} m: devkit row {row}, ours {ours}");
        }
    }
    for m in -128_i64..128 {
        // Column 128 spans (-1, 1) bins of angle (int truncates towards zero); each other column one bin.
        let middle = match m {
            0 => 0.0,
            m if m > 0 => (m as f64 + 0.5) * angle_res,
            m => (m as f64 - 0.5) * angle_res,
        };
        for quarter in [-0.25, 0.25] {
            let angle = middle + quarter * angle_res;
            let (_, col) = to_ra(1.0, angle);
            if !(0..ra_shape.1 as i64).contains(&col) {
                continue;
            }
            let ours = ours_azimuth.coordinate(-angle, carrada::SIZE).unwrap().floor() as i64;
            assert_eq!(ours, col, "{} degrees: devkit column {col}, ours {ours}", angle.to_degrees());
        }
    }
}
