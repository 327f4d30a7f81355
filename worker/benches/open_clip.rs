//! Weights a PyTorch user loads into open_clip: an encoder of the paper's shapes (`vit-b16` at
//! 224 px, the `paper` text tower at context 400), with random weights written as the `clip`
//! operator writes them (`model.safetensors`, `open_clip.json`), embeds a few frames and
//! captions here and in open_clip 3.3 (`open_clip_reference.py`, which loads them the way the
//! README shows); the largest difference between the two is printed, for GELU and for QuickGELU
//! radar towers.
//!
//! The reference needs an interpreter with torch 2.11 and open_clip_torch 3.3: point
//! `RLMFLOW_TORCH_PYTHON` at it. CI never runs this.
//!
//! ```sh
//! RLMFLOW_TORCH_PYTHON=/path/to/venv/bin/python cargo xtask bench -p rlmflow-torch --bench open_clip
//! ```

use rlmflow_nn::clip::{Clip, images_from_u8};
use rlmflow_nn::tch::{self, Kind, Tensor, nn};
use rlmflow_nn::train::write_weights;
use rlmflow_pretrain::{ClipSettings, model_config};

const BATCH: i64 = 4;

fn main() {
    tch::set_num_threads(2);
    let Some(python) = std::env::var_os("RLMFLOW_TORCH_PYTHON") else {
        println!("set RLMFLOW_TORCH_PYTHON to an interpreter with torch 2.11 and open_clip_torch 3.3");
        return;
    };
    for quick_gelu in [false, true] {
        let settings = ClipSettings { encoder: "vit-b16".into(), text: "paper".into(), quick_gelu, ..ClipSettings::default() };
        let config = model_config(&settings, 224, 400, 2048, 1).expect("a valid config");
        let dir = std::env::temp_dir().join(format!("rlmflow-open-clip-{}-{quick_gelu}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        tch::manual_seed(7);
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let model = Clip::new(&vs.root(), &config, 0.07, false);
        write_weights(&vs, &dir.join(rlmflow_stages::encoder::WEIGHTS)).unwrap();
        let open_clip = config.open_clip().expect("open_clip expresses vit-b16 + paper with linear heads");
        std::fs::write(dir.join(rlmflow_stages::encoder::OPEN_CLIP), serde_json::to_vec_pretty(&open_clip).unwrap()).unwrap();

        // Frames as u8 pixels; captions as <start>, ids, <end>, padding, ends at varied places.
        let pixels: Vec<u8> = (0..BATCH * 224 * 224).map(|i| (i * 2_654_435_761 % 251) as u8).collect();
        let images = images_from_u8(&pixels, BATCH, 224, tch::Device::Cpu);
        let tokens = Tensor::randint_low(3, 2048, [BATCH, 400], (Kind::Int64, tch::Device::Cpu));
        for (row, end) in [37, 120, 250, 399].into_iter().enumerate() {
            let _ = tokens.get(row as i64).narrow(0, 0, 1).fill_(0);
            let _ = tokens.get(row as i64).narrow(0, end, 1).fill_(1);
            let _ = tokens.get(row as i64).narrow(0, end + 1, 399 - end).fill_(2);
        }
        let (image, text) = tch::no_grad(|| (model.encode_image(&images, false).embedding, model.encode_text(&tokens)));
        let inputs = [("images", images), ("tokens", tokens), ("image_embedding", image), ("text_embedding", text)];
        Tensor::write_safetensors(&inputs, dir.join("inputs.safetensors")).unwrap();

        let script = concat!(env!("CARGO_MANIFEST_DIR"), "/benches/open_clip_reference.py");
        let out = std::process::Command::new(&python).args([script, dir.to_str().unwrap()]).output().expect("running the open_clip reference");
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let radar = if quick_gelu { "QuickGELU" } else { "GELU" };
        println!("vit-b16 ({radar}) + paper text, batch {BATCH}: {}", String::from_utf8_lossy(&out.stdout).trim());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
