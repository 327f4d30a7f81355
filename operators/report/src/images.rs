//! Sample frames as PNG: heatmaps, masks, and attention rollout laid over a heatmap.

use base64::Engine as _;

/// A square single-channel image, row-major.
pub struct Gray<'a> {
    pub side: usize,
    pub pixels: &'a [u8],
}

/// PNG bytes of a grayscale image.
pub fn gray_png(image: &Gray) -> anyhow::Result<Vec<u8>> {
    encode(image.pixels, image.side, png::ColorType::Grayscale)
}

/// PNG bytes of `map` (any square grid) upsampled to the heatmap's side and laid over it in red,
/// opacity following the map's value.
pub fn overlay_png(heatmap: &Gray, map: &Gray) -> anyhow::Result<Vec<u8>> {
    let side = heatmap.side;
    let mut rgb = Vec::with_capacity(side * side * 3);
    for row in 0..side {
        for col in 0..side {
            let base = heatmap.pixels[row * side + col] as f64;
            let a = 0.8 * map.pixels[(row * map.side / side) * map.side + col * map.side / side] as f64 / 255.0;
            rgb.extend([base * (1.0 - a) + 255.0 * a, base * (1.0 - a) + 40.0 * a, base * (1.0 - a) + 40.0 * a].map(|v| v.round() as u8));
        }
    }
    encode(&rgb, side, png::ColorType::Rgb)
}

fn encode(data: &[u8], side: usize, color: png::ColorType) -> anyhow::Result<Vec<u8>> {
    let mut out = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut out, side as u32, side as u32);
        encoder.set_color(color);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header()?;
        writer.write_image_data(data)?;
        writer.finish()?;
    }
    Ok(out)
}

/// A `data:` URI, so the HTML report needs no other file.
pub fn data_uri(png: &[u8]) -> String {
    format!("data:image/png;base64,{}", base64::engine::general_purpose::STANDARD.encode(png))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pngs_decode_to_what_was_drawn() {
        let pixels: Vec<u8> = (0..16).map(|i| i * 16).collect();
        let bytes = gray_png(&Gray { side: 4, pixels: &pixels }).unwrap();
        let mut reader = png::Decoder::new(std::io::Cursor::new(bytes)).read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        reader.next_frame(&mut buf).unwrap();
        assert_eq!(buf, pixels);

        // A full map turns the pixel red; an empty one leaves the heatmap as it was.
        let heat = [100u8; 4];
        let map = [255u8, 0, 0, 0];
        let bytes = overlay_png(&Gray { side: 2, pixels: &heat }, &Gray { side: 2, pixels: &map }).unwrap();
        let mut reader = png::Decoder::new(std::io::Cursor::new(bytes)).read_info().unwrap();
        let mut rgb = vec![0; reader.output_buffer_size().unwrap()];
        reader.next_frame(&mut rgb).unwrap();
        assert_eq!(&rgb[..3], &[224, 52, 52]);
        assert_eq!(&rgb[3..6], &[100, 100, 100]);
        assert!(data_uri(&[1, 2]).starts_with("data:image/png;base64,"));
    }
}
