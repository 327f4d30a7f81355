//! The paper's own results (CARLA, ViT-B/16, 4xA100), printed beside ours so a reader compares
//! direction, not equality. Source: the captioning and segmentation tables of Section 5, and the
//! supplementary "Real-World Data Analysis" (RADIATE: the decoder alone fine-tuned on an 80/20
//! split, the sim-pretrained encoders frozen).

/// A pretraining method as the paper names it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Method {
    VanillaClip,
    SgClip(f64),
    UNet,
}

impl Method {
    pub fn name(self) -> String {
        match self {
            Method::VanillaClip => "Vanilla CLIP".into(),
            Method::SgClip(alpha) => format!("SG-CLIP (α={alpha})"),
            Method::UNet => "U-Net".into(),
        }
    }
}

/// Precision, recall, F1 per distance bin (0-10, 10-20, 20-30, 30-40 m).
const CAPTIONING: &[(Method, [[f64; 3]; 4])] = &[
    (Method::VanillaClip, [[0.961, 0.926, 0.943], [0.900, 0.817, 0.844], [0.742, 0.669, 0.693], [0.673, 0.529, 0.577]]),
    (Method::SgClip(16.0), [[0.983, 0.981, 0.982], [0.929, 0.916, 0.922], [0.849, 0.816, 0.829], [0.870, 0.844, 0.856]]),
    (Method::SgClip(4.0), [[0.985, 0.981, 0.983], [0.927, 0.918, 0.922], [0.875, 0.834, 0.852], [0.888, 0.848, 0.867]]),
    (Method::SgClip(1.0), [[0.986, 0.985, 0.985], [0.938, 0.930, 0.934], [0.863, 0.858, 0.861], [0.887, 0.848, 0.867]]),
];

/// Precision, recall, IoU, Dice at 0.5, Peak IoU, AP.
const SEGMENTATION: &[(Method, [f64; 6])] = &[
    (Method::UNet, [0.519, 0.927, 0.489, 0.657, 0.489, 0.442]),
    (Method::VanillaClip, [0.820, 0.699, 0.606, 0.755, 0.615, 0.522]),
    (Method::SgClip(1.0), [0.826, 0.717, 0.623, 0.768, 0.631, 0.628]),
    (Method::SgClip(16.0), [0.833, 0.724, 0.625, 0.769, 0.634, 0.631]),
    (Method::SgClip(4.0), [0.848, 0.719, 0.637, 0.778, 0.649, 0.634]),
];

/// The same columns on RADIATE (the supplementary's sim-to-real table; no U-Net row).
const SEGMENTATION_RADIATE: &[(Method, [f64; 6])] =
    &[(Method::VanillaClip, [0.352, 0.323, 0.202, 0.337, 0.207, 0.217]), (Method::SgClip(4.0), [0.468, 0.380, 0.265, 0.419, 0.271, 0.306])];

/// Which of the paper's segmentation tables a report quotes: its simulated test set, or
/// RADIATE's.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Table {
    #[default]
    Carla,
    Radiate,
}

/// The paper's captioning (precision, recall, F1) per bin for a method, when it reports one.
pub fn captioning(method: Method) -> Option<[[f64; 3]; 4]> {
    CAPTIONING.iter().find(|(m, _)| *m == method).map(|(_, v)| *v)
}

/// The paper's segmentation row (P, R, IoU, Dice at 0.5, Peak IoU, AP) for a method in `table`.
pub fn segmentation(method: Method, table: Table) -> Option<[f64; 6]> {
    let rows = match table {
        Table::Carla => SEGMENTATION,
        Table::Radiate => SEGMENTATION_RADIATE,
    };
    rows.iter().find(|(m, _)| *m == method).map(|(_, v)| *v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_papers_headline_numbers_are_where_the_text_says() {
        // "At 30-40 m, SG-CLIP (alpha=1.0) achieves 0.867 F1 versus vanilla CLIP's 0.577."
        assert_eq!(captioning(Method::SgClip(1.0)).unwrap()[3][2], 0.867);
        assert_eq!(captioning(Method::VanillaClip).unwrap()[3][2], 0.577);
        // "SG-CLIP (alpha=4.0) achieves ... 0.637 IoU@0.5 and 0.634 AP"; U-Net 0.489 IoU.
        assert_eq!(segmentation(Method::SgClip(4.0), Table::Carla).unwrap()[2], 0.637);
        assert_eq!(segmentation(Method::SgClip(4.0), Table::Carla).unwrap()[5], 0.634);
        assert_eq!(segmentation(Method::UNet, Table::Carla).unwrap()[2], 0.489);
        // RADIATE: "vanilla CLIP 0.352/0.323/0.202/0.337, 0.207, 0.217; SG-CLIP alpha 4
        // 0.468/0.380/0.265/0.419, 0.271, 0.306"; no U-Net row.
        assert_eq!(segmentation(Method::VanillaClip, Table::Radiate), Some([0.352, 0.323, 0.202, 0.337, 0.207, 0.217]));
        assert_eq!(segmentation(Method::SgClip(4.0), Table::Radiate).unwrap()[5], 0.306);
        assert_eq!(segmentation(Method::UNet, Table::Radiate), None);
        assert_eq!(captioning(Method::SgClip(2.0)), None);
    }
}
