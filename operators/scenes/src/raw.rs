//! A recording's image as stored (`.npy` or a grayscale PNG), read from inside the recording
//! only, and its values read as received power, decibels or an image: what the manifest import
//! and every dataset reader share.

use std::path::Path;

use anyhow::{Context as _, bail};
use rlmflow_stages::npy::Npy;
use serde::{Deserialize, Serialize};

/// A recording's image: its shape and values, as stored.
pub(crate) struct Raw {
    pub(crate) height: usize,
    pub(crate) width: usize,
    pub(crate) values: Vec<f32>,
    /// The largest value its type holds (255 for uint8, 65,535 for 16-bit PNG), for `normalised`.
    pub(crate) integer_max: Option<f32>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Power {
    /// Received power (non-negative), shown in dB.
    Linear,
    /// Power already in dB.
    Db,
    /// Already an image: uint8 as it is, floats in [0, 1].
    Normalised,
}

/// `Ok` for a path that names a file inside the recording: relative, without `..`; else what
/// is wrong with it. The recording is tracked by content, so a file outside it would be read
/// without entering the key.
pub(crate) fn inside_recording(name: &str) -> Result<(), &'static str> {
    use std::path::Component;
    let components: Vec<Component> = Path::new(name).components().collect();
    if components.iter().any(|c| matches!(c, Component::RootDir | Component::Prefix(_))) {
        return Err("is an absolute path, outside the recording");
    }
    if components.contains(&Component::ParentDir) {
        return Err("climbs out of the recording with `..`");
    }
    if !components.iter().any(|c| matches!(c, Component::Normal(_))) {
        return Err("names no file");
    }
    Ok(())
}

/// An image file of the recording in `dir` (its snapshot), named `name` by the manifest of the
/// user's recording `shown`: `.npy` (2-D, float32 or uint8) or `.png` (grayscale, 8 or 16
/// bits), at least one pixel.
pub(crate) fn read_image(dir: &Path, shown: &Path, name: &str) -> anyhow::Result<Raw> {
    if let Err(problem) = inside_recording(name) {
        bail!("{problem}; images are named relative to the recording's directory");
    }
    let path = dir.join(name);
    if !path.is_file() {
        bail!("no such file in the recording");
    }
    let raw = match path.extension().and_then(|e| e.to_str()) {
        Some("npy") => {
            let npy = Npy::open_as(&path, &shown.join(name))?;
            let [height, width] = npy.shape[..] else {
                bail!("shape {:?}; valid: a 2-D array (rows, columns)", npy.shape);
            };
            let integer_max = (npy.dtype == rlmflow_stages::npy::Dtype::U8).then_some(255.0);
            Raw { height, width, values: npy.all_f32()?, integer_max }
        }
        Some("png") => {
            let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path)?));
            let mut reader = decoder.read_info()?;
            let mut buf = vec![0u8; reader.output_buffer_size().context("the PNG is too large")?];
            let info = reader.next_frame(&mut buf)?;
            let (width, height) = (info.width as usize, info.height as usize);
            let (values, max) = match (info.color_type, info.bit_depth) {
                (png::ColorType::Grayscale, png::BitDepth::Eight) => (buf[..width * height].iter().map(|&v| f32::from(v)).collect(), 255.0),
                (png::ColorType::Grayscale, png::BitDepth::Sixteen) => {
                    (buf[..width * height * 2].chunks_exact(2).map(|b| f32::from(u16::from_be_bytes([b[0], b[1]]))).collect(), 65_535.0)
                }
                (color, depth) => bail!("a {color:?} PNG of {depth:?} bits; valid: grayscale, 8 or 16 bits"),
            };
            Raw { height, width, values, integer_max: Some(max) }
        }
        _ => bail!("unknown image type; valid: .npy (float32 or uint8) or .png (grayscale)"),
    };
    if raw.height == 0 || raw.width == 0 {
        bail!("an image of {}x{} pixels; an image needs at least one row and one column", raw.height, raw.width);
    }
    Ok(raw)
}

/// Values in [0, 1] as `power` says to read them, dB values shown over `dynamic_range_db` below
/// the image's peak.
pub(crate) fn normalise(raw: &Raw, power: Power, dynamic_range_db: f64) -> anyhow::Result<Vec<f32>> {
    let db: Vec<f32> = match power {
        Power::Normalised => {
            return match raw.integer_max {
                Some(max) => Ok(raw.values.iter().map(|v| v / max).collect()),
                None => {
                    let (lo, hi) = raw.values.iter().fold((f32::MAX, f32::MIN), |(lo, hi), &v| (lo.min(v), hi.max(v)));
                    if lo < 0.0 || hi > 1.0 {
                        bail!("its values span [{lo}, {hi}], but power = \"normalised\" needs floats in [0, 1]; say power = \"linear\" or \"db\"");
                    }
                    Ok(raw.values.clone())
                }
            };
        }
        Power::Linear => {
            if let Some(v) = raw.values.iter().find(|v| **v < 0.0) {
                bail!("it holds a negative power ({v}); power = \"linear\" needs received power >= 0 (say power = \"db\" for decibels)");
            }
            raw.values.iter().map(|&v| if v > 0.0 { 10.0 * v.log10() } else { f32::NEG_INFINITY }).collect()
        }
        Power::Db => raw.values.clone(),
    };
    let peak = db.iter().cloned().fold(f32::NEG_INFINITY, f32::max);
    let range = dynamic_range_db as f32;
    Ok(db.iter().map(|&v| if peak.is_finite() && v.is_finite() { ((v - (peak - range)) / range).clamp(0.0, 1.0) } else { 0.0 }).collect())
}
