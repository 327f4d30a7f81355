//! The report's figures, drawn with plotters as SVG text: line charts (training curves,
//! metric-versus-threshold sweeps), bar charts (histograms) and the 4 x 12 cell grid.

use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use rlmflow_stages::grid::{DISTANCE_BINS, SECTORS};

const SIZE: (u32, u32) = (640, 360);
const FONT: &str = "sans-serif";

/// One named line of a chart.
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

fn range(values: impl Iterator<Item = f64>, floor_zero: bool) -> std::ops::Range<f64> {
    let (mut lo, mut hi) = values.filter(|v| v.is_finite()).fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    if !lo.is_finite() {
        (lo, hi) = (0.0, 1.0);
    }
    if floor_zero {
        lo = lo.min(0.0);
    }
    if hi - lo < 1e-12 {
        hi = lo + 1.0;
    }
    let pad = (hi - lo) * 0.05;
    (if floor_zero && lo >= 0.0 { lo } else { lo - pad })..hi + pad
}

/// A line chart; `y_unit` fixes the y axis to [0, 1] (rates and scores).
pub fn lines(title: &str, x_desc: &str, y_desc: &str, series: &[Series], y_unit: bool) -> anyhow::Result<String> {
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, SIZE).into_drawing_area();
        root.fill(&WHITE).map_err(draw_error)?;
        let xs = range(series.iter().flat_map(|s| s.points.iter().map(|p| p.0)), false);
        let ys = if y_unit { 0.0..1.0 } else { range(series.iter().flat_map(|s| s.points.iter().map(|p| p.1)), false) };
        let mut chart = ChartBuilder::on(&root)
            .caption(title, (FONT, 18))
            .margin(12)
            .x_label_area_size(36)
            .y_label_area_size(56)
            .build_cartesian_2d(xs, ys)
            .map_err(draw_error)?;
        chart.configure_mesh().x_desc(x_desc).y_desc(y_desc).light_line_style(WHITE).draw().map_err(draw_error)?;
        for (i, s) in series.iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            chart
                .draw_series(LineSeries::new(s.points.iter().copied().filter(|p| p.1.is_finite()), color.stroke_width(2)))
                .map_err(draw_error)?
                .label(s.name.as_str())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2)));
        }
        if series.len() > 1 || series.first().is_some_and(|s| !s.name.is_empty()) {
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperRight)
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK.mix(0.3))
                .label_font((FONT, 12))
                .draw()
                .map_err(draw_error)?;
        }
        root.present().map_err(draw_error)?;
    }
    Ok(svg)
}

/// A bar chart over labelled categories.
pub fn bars(title: &str, x_desc: &str, y_desc: &str, bars: &[(String, f64)]) -> anyhow::Result<String> {
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, SIZE).into_drawing_area();
        root.fill(&WHITE).map_err(draw_error)?;
        let ys = range(bars.iter().map(|b| b.1), true);
        let n = bars.len().max(1);
        let mut chart = ChartBuilder::on(&root)
            .caption(title, (FONT, 18))
            .margin(12)
            .x_label_area_size(36)
            .y_label_area_size(56)
            .build_cartesian_2d(0.0..n as f64, ys)
            .map_err(draw_error)?;
        let labels: Vec<String> = bars.iter().map(|b| b.0.clone()).collect();
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_desc(x_desc)
            .y_desc(y_desc)
            .x_labels(n.min(24))
            .x_label_formatter(&|x| labels.get(x.floor() as usize).cloned().unwrap_or_default())
            .light_line_style(WHITE)
            .draw()
            .map_err(draw_error)?;
        let color = Palette99::pick(0).to_rgba();
        chart
            .draw_series(bars.iter().enumerate().map(|(i, b)| Rectangle::new([(i as f64 + 0.1, 0.0), (i as f64 + 0.9, b.1)], color.filled())))
            .map_err(draw_error)?;
        root.present().map_err(draw_error)?;
    }
    Ok(svg)
}

/// The 48 cells as the paper lays them out: distance bins as rows (near at the bottom), lane
/// sectors as columns, each coloured by its value over `max` and labelled with `label(value)`.
pub fn cells(title: &str, values: &[f64], max: f64, label: &dyn Fn(f64) -> String) -> anyhow::Result<String> {
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (760, 340)).into_drawing_area();
        root.fill(&WHITE).map_err(draw_error)?;
        let sectors = SECTORS.len() as i32;
        let bins = DISTANCE_BINS.len() as i32;
        // Segmented axes put one label at the centre of each cell.
        let mut chart = ChartBuilder::on(&root)
            .caption(title, (FONT, 18))
            .margin(12)
            .x_label_area_size(110)
            .y_label_area_size(60)
            .build_cartesian_2d((0..sectors - 1).into_segmented(), (0..bins - 1).into_segmented())
            .map_err(draw_error)?;
        let name = |names: &[&str], v: &SegmentValue<i32>| match v {
            SegmentValue::CenterOf(i) => names.get(*i as usize).map(|s| s.replace('_', " ")).unwrap_or_default(),
            _ => String::new(),
        };
        chart
            .configure_mesh()
            .disable_mesh()
            .x_labels(SECTORS.len())
            .y_labels(DISTANCE_BINS.len())
            .x_label_formatter(&|_| String::new())
            .y_label_formatter(&|v| name(&DISTANCE_BINS, v))
            .draw()
            .map_err(draw_error)?;
        // The mesh centres every axis label on its tick, so a rotated sector name would run up
        // into the grid; these hang down from the axis instead.
        let (_, axis) = chart.backend_coord(&(SegmentValue::Exact(0), SegmentValue::Exact(0)));
        for (i, sector) in SECTORS.iter().enumerate() {
            let (x, _) = chart.backend_coord(&(SegmentValue::CenterOf(i as i32), SegmentValue::Exact(0)));
            let style = (FONT, 10).into_font().transform(FontTransform::Rotate90).color(&BLACK).pos(Pos::new(HPos::Left, VPos::Center));
            root.draw(&Text::new(sector.replace('_', " "), (x, axis + 8), style)).map_err(draw_error)?;
        }
        let max = if max > 0.0 { max } else { 1.0 };
        let corner = |c: usize, dx: i32, dy: i32| {
            let (bin, sector) = ((c / SECTORS.len()) as i32, (c % SECTORS.len()) as i32);
            (SegmentValue::Exact(sector + dx), SegmentValue::Exact(bin + dy))
        };
        chart
            .draw_series(values.iter().enumerate().map(|(c, &v)| Rectangle::new([corner(c, 0, 0), corner(c, 1, 1)], heat(v / max).filled())))
            .map_err(draw_error)?;
        chart
            .draw_series(
                values
                    .iter()
                    .enumerate()
                    .map(|(c, &v)| Text::new(label(v), corner(c, 0, 1), (FONT, 11).into_font().color(&BLACK).pos(text_anchor()))),
            )
            .map_err(draw_error)?;
        root.present().map_err(draw_error)?;
    }
    Ok(svg)
}

/// Cell labels hang from the cell's top-left corner, inset a little.
fn text_anchor() -> Pos {
    Pos::new(HPos::Left, VPos::Top)
}

/// White to deep blue.
fn heat(t: f64) -> RGBColor {
    let t = t.clamp(0.0, 1.0);
    let mix = |a: f64, b: f64| (a + (b - a) * t).round() as u8;
    RGBColor(mix(255.0, 33.0), mix(255.0, 102.0), mix(255.0, 172.0))
}

fn draw_error<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow::anyhow!("drawing a figure: {e:?}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn charts_are_svg_with_their_titles_and_legends() {
        let series = [
            Series { name: "vanilla".into(), points: vec![(1.0, 3.0), (2.0, 2.0)] },
            Series { name: "alpha4".into(), points: vec![(1.0, 2.5), (2.0, f64::NAN)] },
        ];
        let svg = lines("loss", "epoch", "loss", &series, false).unwrap();
        assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
        for text in ["loss", "vanilla", "alpha4", "epoch"] {
            assert!(svg.contains(text), "no `{text}`");
        }
        let svg = bars("vehicles", "n", "frames", &[("0".into(), 3.0), ("1".into(), 5.0)]).unwrap();
        assert!(svg.contains("vehicles") && svg.contains("<rect"));
        let values: Vec<f64> = (0..48).map(|c| c as f64).collect();
        let svg = cells("F1", &values, 47.0, &|v| format!("{v:.0}")).unwrap();
        assert!(svg.contains("\n47\n") && svg.contains("\n30-40m\n"), "cell labels and bins are text");
    }

    /// The value of `name="..."` in one SVG element's text.
    fn attribute(element: &str, name: &str) -> f64 {
        let start = element.find(&format!(" {name}=\"")).unwrap_or_else(|| panic!("no {name} in {element}")) + name.len() + 3;
        element[start..].split('"').next().unwrap().parse().unwrap()
    }

    #[test]
    fn sector_names_hang_below_the_cell_grid_inside_the_figure() {
        let values: Vec<f64> = (0..48).map(|c| c as f64).collect();
        let svg = cells("F1", &values, 47.0, &|v| format!("{v:.0}")).unwrap();
        let cells: Vec<&str> = svg.split("<rect").skip(2).collect();
        assert_eq!(cells.len(), 48, "one rectangle per cell after the background");
        let bottom = cells.iter().map(|r| attribute(r, "y") + attribute(r, "height")).fold(0.0, f64::max);
        for (i, sector) in SECTORS.iter().enumerate() {
            let name = sector.replace('_', " ");
            let element = svg.split("<text").find(|t| t.contains(&format!(">\n{name}\n<"))).unwrap_or_else(|| panic!("no `{name}`"));
            let (x, y, size) = (attribute(element, "x"), attribute(element, "y"), attribute(element, "font-size"));
            assert!(element.contains(&format!("rotate(90, {x}, {y})")), "`{name}` reads downwards: {element}");
            assert!(y > bottom, "`{name}` starts at y {y}, inside the grid (bottom {bottom})");
            // Its column: the bottom row's i-th cell.
            let column = cells[i];
            assert!((attribute(column, "x")..attribute(column, "x") + attribute(column, "width")).contains(&x), "`{name}` under its column");
            // Glyphs are narrower than 0.6 em in any sans-serif font.
            assert!(y + 0.6 * size * name.len() as f64 <= 340.0, "`{name}` runs off the figure");
        }
    }

    #[test]
    fn the_same_data_draws_the_same_bytes() {
        let series = [Series { name: "a".into(), points: vec![(0.0, 0.1), (1.0, 0.9)] }];
        assert_eq!(lines("t", "x", "y", &series, true).unwrap(), lines("t", "x", "y", &series, true).unwrap());
    }
}
