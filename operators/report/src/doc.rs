//! The report as a list of blocks, rendered twice: Markdown with its figures as files beside it,
//! and one self-contained HTML page with the same figures inline.

use std::fmt::Write as _;
use std::path::Path;

use crate::images;

pub enum Block {
    Heading(u8, String),
    Paragraph(String),
    Table {
        header: Vec<String>,
        rows: Vec<Vec<String>>,
    },
    /// An SVG chart, saved as `figures/<name>.svg`.
    Chart {
        name: String,
        svg: String,
    },
    /// A row of PNG images with captions, saved as `figures/<name>.png`.
    Images(Vec<Picture>),
    /// Text shown as it is (settings, captions).
    Code(String),
}

pub struct Picture {
    pub name: String,
    pub caption: String,
    pub png: Vec<u8>,
}

pub const FIGURES: &str = "figures";

/// Writes `report.md` (and the figures it links) and `report.html` into `dir`.
pub fn write(dir: &Path, title: &str, blocks: &[Block]) -> anyhow::Result<()> {
    let figures = dir.join(FIGURES);
    std::fs::create_dir_all(&figures)?;
    for block in blocks {
        match block {
            Block::Chart { name, svg } => std::fs::write(figures.join(format!("{name}.svg")), svg)?,
            Block::Images(pictures) => {
                for p in pictures {
                    std::fs::write(figures.join(format!("{}.png", p.name)), &p.png)?;
                }
            }
            _ => {}
        }
    }
    std::fs::write(dir.join("report.md"), markdown(title, blocks))?;
    std::fs::write(dir.join("report.html"), html(title, blocks))?;
    Ok(())
}

pub fn markdown(title: &str, blocks: &[Block]) -> String {
    let mut md = format!("# {title}\n");
    for block in blocks {
        md.push('\n');
        match block {
            Block::Heading(level, text) => writeln!(md, "{} {text}", "#".repeat(*level as usize + 1)).unwrap(),
            Block::Paragraph(text) => writeln!(md, "{text}").unwrap(),
            Block::Table { header, rows } => {
                let cell = |s: &String| s.replace('|', "\\|");
                writeln!(md, "| {} |", header.iter().map(cell).collect::<Vec<_>>().join(" | ")).unwrap();
                writeln!(md, "|{}", "---|".repeat(header.len())).unwrap();
                for row in rows {
                    writeln!(md, "| {} |", row.iter().map(cell).collect::<Vec<_>>().join(" | ")).unwrap();
                }
            }
            Block::Chart { name, .. } => writeln!(md, "![{name}]({FIGURES}/{name}.svg)").unwrap(),
            Block::Images(pictures) => {
                let cells: Vec<String> = pictures.iter().map(|p| format!("![{}]({FIGURES}/{}.png)<br>{}", p.name, p.name, p.caption)).collect();
                writeln!(md, "| {} |\n|{}", cells.join(" | "), "---|".repeat(cells.len())).unwrap();
            }
            Block::Code(text) => writeln!(md, "```text\n{}\n```", text.trim_end()).unwrap(),
        }
    }
    md
}

const STYLE: &str = "body{font-family:sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}\
table{border-collapse:collapse;margin:1em 0;font-size:13px}td,th{border:1px solid #ccc;padding:3px 7px;text-align:right}\
td:first-child,th:first-child{text-align:left}th{background:#f2f2f2}\
figure{display:inline-block;margin:4px;text-align:center;font-size:12px}\
figure img{width:160px;height:160px;image-rendering:pixelated;border:1px solid #ccc}\
pre{background:#f6f6f6;padding:8px;overflow-x:auto;font-size:12px;white-space:pre-wrap;overflow-wrap:anywhere}svg{max-width:100%;height:auto}";

pub fn html(title: &str, blocks: &[Block]) -> String {
    let mut out = format!(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{}</title><style>{STYLE}</style></head><body>\n<h1>{}</h1>\n",
        escape(title),
        escape(title)
    );
    for block in blocks {
        match block {
            Block::Heading(level, text) => writeln!(out, "<h{0}>{1}</h{0}>", level + 1, escape(text)).unwrap(),
            Block::Paragraph(text) => writeln!(out, "<p>{}</p>", inline(text)).unwrap(),
            Block::Table { header, rows } => {
                out.push_str("<table><tr>");
                header.iter().for_each(|h| write!(out, "<th>{}</th>", escape(h)).unwrap());
                out.push_str("</tr>\n");
                for row in rows {
                    out.push_str("<tr>");
                    row.iter().for_each(|c| write!(out, "<td>{}</td>", escape(c)).unwrap());
                    out.push_str("</tr>\n");
                }
                out.push_str("</table>\n");
            }
            // plotters writes a bare <svg> element, which HTML takes inline.
            Block::Chart { svg, .. } => writeln!(out, "<div>{svg}</div>").unwrap(),
            Block::Images(pictures) => {
                out.push_str("<div>");
                for p in pictures {
                    write!(
                        out,
                        "<figure><img alt=\"{}\" src=\"{}\"><figcaption>{}</figcaption></figure>",
                        escape(&p.name),
                        images::data_uri(&p.png),
                        escape(&p.caption)
                    )
                    .unwrap();
                }
                out.push_str("</div>\n");
            }
            Block::Code(text) => writeln!(out, "<pre>{}</pre>", escape(text.trim_end())).unwrap(),
        }
    }
    out.push_str("</body></html>\n");
    out
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// Paragraph text: escaped, with Markdown's `code` spans kept as code.
fn inline(s: &str) -> String {
    escape(s).split('`').enumerate().map(|(i, part)| if i % 2 == 1 { format!("<code>{part}</code>") } else { part.to_owned() }).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_renderings_hold_every_block() {
        let blocks = vec![
            Block::Heading(1, "Results".into()),
            Block::Paragraph("a `code` <b>".into()),
            Block::Table { header: vec!["row".into(), "F1".into()], rows: vec![vec!["a|b".into(), "0.5".into()]] },
            Block::Chart { name: "loss".into(), svg: "<svg></svg>".into() },
            Block::Images(vec![Picture { name: "f0".into(), caption: "frame 0".into(), png: vec![1] }]),
            Block::Code("x = 1".into()),
        ];
        let md = markdown("T", &blocks);
        assert!(md.starts_with("# T\n\n## Results\n"));
        assert!(md.contains("| a\\|b | 0.5 |") && md.contains("![loss](figures/loss.svg)") && md.contains("figures/f0.png"));
        let page = html("T", &blocks);
        assert!(page.contains("<h2>Results</h2>") && page.contains("a <code>code</code> &lt;b&gt;"));
        assert!(page.contains("<td>a|b</td>") && page.contains("<svg></svg>") && page.contains("data:image/png;base64,AQ=="));
        assert!(!page.contains("http"), "the page must load nothing from elsewhere");
    }
}
