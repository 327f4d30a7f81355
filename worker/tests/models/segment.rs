//! The segmenters end to end through the real binaries: on small data the test makes through
//! the pipeline, `pup` on a trained and on an untrained encoder and the `unet` baseline each
//! learn (the loss falls; AP beats a constant predictor's, which equals the positive rate), the
//! U-Net runs once rather than per encoder variant, the artifact holds the sample masks and
//! the rollout maps. (Fresh processes give the stored bytes: `numerics.rs`.)

use crate::common::rlmflow;
use rlmflow_stages::npy::Npy;
use rlmflow_stages::segment::{self, read_summary};

const SEGMENTERS: &str = r#"
[stages.pup]
kind = "segment"
operator = "pup"
device = "cpu"
numerics = "native"
epochs = 6
batch = 32
channels = [64, 32, 16]

[stages.unet]
kind = "segment"
operator = "unet"
device = "cpu"
numerics = "native"
epochs = 6
batch = 32
channels = [8, 16, 32]
"#;

fn pipeline() -> String {
    format!("{}{}{SEGMENTERS}", crate::common::data_stages("segment"), crate::common::encoders(true))
}

#[test]
fn pup_and_unet_learn_and_keep_samples_and_rollouts() {
    let _turn = crate::common::one_at_a_time();
    let dir = crate::common::scratch("segment", &pipeline());
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--json"]);
    assert!(ok, "{out}");
    let unet_runs = out.lines().filter(|l| l.contains("\"stage_finished\"") && l.contains("\"stage\":\"unet")).count();
    assert_eq!(unet_runs, 1, "the U-Net reads no encoder, so it runs once, not per encoder variant");

    for (label, rollout) in [("pup[clip]", true), ("pup[random]", true), ("unet", false)] {
        let object = crate::common::output(&dir, "segment", label);
        let summary = read_summary(&object).unwrap();
        let m = &summary.metrics;
        let (first, last) = (&summary.log[0], &summary.log[summary.log.len() - 1]);
        assert!(last["loss"].as_f64() < first["loss"].as_f64(), "{label}: the training loss falls: {:?}", summary.log);
        crate::common::assert_curves_hold(&object, &summary.log);
        assert!(m.ap > 2.0 * m.positive_rate, "{label}: AP {} vs a constant predictor's {}", m.ap, m.positive_rate);
        assert!(m.iou > 0.0 && m.peak_iou >= m.iou, "{label}: IoU {} peak {}", m.iou, m.peak_iou);
        assert_eq!((m.iou_curve.len(), m.dice_curve.len()), (segment::THRESHOLDS, segment::THRESHOLDS));

        assert_eq!(summary.sample_frames.len(), 8);
        let samples = Npy::open(&object.join(segment::SAMPLES)).unwrap();
        assert_eq!(samples.shape, [8, 32, 32], "{label}");
        assert_eq!(object.join(segment::ROLLOUT).is_file(), rollout, "{label}");
        if rollout {
            // conv-tiny: two blocks, a 4 x 4 grid; the default asks for the last three blocks.
            assert_eq!(summary.rollout_blocks, [0, 1]);
            let maps = Npy::open(&object.join(segment::ROLLOUT)).unwrap();
            assert_eq!(maps.shape, [8, 4, 4]);
            for i in 0..8 {
                assert_eq!(maps.row_u8(i).unwrap().into_iter().max(), Some(255), "{label}: each map scaled to its peak");
            }
        }
    }
}
