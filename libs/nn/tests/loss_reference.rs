//! CLIP and SG-CLIP losses and gradients against PyTorch's on a fixed batch
//! (`fixtures/loss_reference.json`, made by `fixtures/make_loss_reference.py` with torch 2.11).

use rlmflow_nn::clip::logits;
use rlmflow_nn::loss::{Distance, clip_loss, off_diagonal_mass, soft_clip_loss, soft_targets};
use rlmflow_nn::tch::{Kind, Tensor};
use serde_json::Value;

fn matrix(v: &Value) -> Tensor {
    let rows: Vec<Vec<f64>> = serde_json::from_value(v.clone()).unwrap();
    let (n, d) = (rows.len() as i64, rows[0].len() as i64);
    Tensor::from_slice(&rows.concat()).view([n, d])
}

fn assert_close(ours: &Tensor, theirs: &Tensor, what: &str) {
    let diff = (ours - theirs).abs().max().double_value(&[]);
    assert!(diff < 1e-9, "{what}: max difference {diff}");
}

#[test]
fn losses_and_gradients_match_pytorch() {
    let fixture: Value = serde_json::from_str(include_str!("fixtures/loss_reference.json")).unwrap();
    let counts = matrix(&fixture["counts"]);
    let scale = Tensor::from(1.0 / fixture["tau"].as_f64().unwrap()).to_kind(Kind::Double);
    let cases = fixture["cases"].as_array().unwrap();
    assert_eq!(cases.len(), 4);
    for case in cases {
        let image = matrix(&fixture["image"]).set_requires_grad(true);
        let text = matrix(&fixture["text"]).set_requires_grad(true);
        let l = logits(&image, &text, &scale);
        let (loss, off) = match case["alpha"].as_f64() {
            None => (clip_loss(&l), 0.0),
            Some(alpha) => {
                let distance = if case["pair_total"].as_bool().unwrap() { Distance::PairTotal } else { Distance::Raw };
                let targets = soft_targets(&counts, alpha, distance).to_kind(Kind::Double);
                (soft_clip_loss(&l, &targets), off_diagonal_mass(&targets))
            }
        };
        let what = format!("{} alpha {:?}", case["objective"], case["alpha"]);
        assert!(
            (loss.double_value(&[]) - case["loss"].as_f64().unwrap()).abs() < 1e-9,
            "{what}: loss {} vs {}",
            loss.double_value(&[]),
            case["loss"]
        );
        assert!((off - case["off_diagonal"].as_f64().unwrap()).abs() < 1e-6, "{what}: off-diagonal {off} vs {}", case["off_diagonal"]);
        loss.backward();
        assert_close(&image.grad(), &matrix(&case["grad_image"]), &format!("{what}: image gradient"));
        assert_close(&text.grad(), &matrix(&case["grad_text"]), &format!("{what}: text gradient"));
    }
}
