//! Weights a setting names (`init`, a tracked path: its content is in the key), checked when the
//! pipeline is validated rather than when the stage has run for an hour: the file exists, is a
//! whole safetensors file, and holds the model the setting expects.

use std::path::Path;

use safetensors::SafeTensors;

use crate::settings::SettingError;

/// The model an `init` setting must hold: any one of `names` marks it.
pub struct Expected<'a> {
    /// For messages: `CLIP ViT-B/16 (open_clip or Hugging Face names)`.
    pub model: &'a str,
    pub names: &'a [&'a str],
    /// Where such a file comes from, for the error: "docs/guide/paper-scale.md".
    pub source: &'a str,
}

/// Checks setting `key`'s file at `path` (a regular file: the engine has refused anything else
/// unopened) against `expected`; the error says what is wrong.
pub fn check_init(key: &str, path: &Path, expected: &Expected) -> Result<(), SettingError> {
    let wrong = |what: String| Err(SettingError::new(key, format!("{what}; give a {} safetensors file ({})", expected.model, expected.source)));
    let shown = path.display();
    if !path.is_file() {
        return wrong(format!("`{shown}` is not a file"));
    }
    let file = match std::fs::File::open(path) {
        Ok(file) => file,
        Err(e) => return wrong(format!("cannot open `{shown}` ({e})")),
    };
    // SAFETY: the map is read-only and dropped before this returns; a file changed meanwhile can
    // only make the check fail.
    let map = match unsafe { memmap2::Mmap::map(&file) } {
        Ok(map) => map,
        Err(e) => return wrong(format!("cannot read `{shown}` ({e})")),
    };
    let tensors = match SafeTensors::deserialize(&map) {
        Ok(tensors) => tensors,
        Err(e) => return wrong(format!("`{shown}` is not a whole safetensors file ({e:?}: truncated or of another format)")),
    };
    let names = tensors.names();
    if !expected.names.iter().any(|n| names.iter().any(|m| m == n)) {
        return wrong(format!("`{shown}` holds {} tensors, none of them {}", names.len(), expected.names.join(" or ")));
    }
    Ok(())
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A small safetensors file at `path` holding one 2x2 f32 tensor per name.
    pub fn write_weights(path: &Path, names: &[&str]) {
        let data = vec![0u8; 16];
        let views: Vec<(String, safetensors::tensor::TensorView)> = names
            .iter()
            .map(|n| (n.to_string(), safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![2, 2], &data).unwrap()))
            .collect();
        safetensors::serialize_to_file(views, &None, path).unwrap();
    }

    #[test]
    fn a_missing_truncated_or_other_models_file_names_the_setting_and_what_is_wrong() {
        let dir = std::env::temp_dir().join(format!("rlmflow-weights-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let expected =
            Expected { model: "GPT-2", names: &["h.0.attn.c_attn.weight", "transformer.h.0.attn.c_attn.weight"], source: "see the README" };
        let check = |path: &Path| check_init("init", path, &expected);

        let good = dir.join("gpt2.safetensors");
        write_weights(&good, &["transformer.h.0.attn.c_attn.weight", "transformer.wte.weight"]);
        assert!(check(&good).is_ok());

        let e = check(&dir.join("absent.safetensors")).unwrap_err();
        assert_eq!(e.key, "init");
        assert!(e.message.contains("is not a file") && e.message.ends_with("give a GPT-2 safetensors file (see the README)"), "{}", e.message);

        let bytes = std::fs::read(&good).unwrap();
        let truncated = dir.join("truncated.safetensors");
        std::fs::write(&truncated, &bytes[..bytes.len() - 4]).unwrap();
        assert!(check(&truncated).unwrap_err().message.contains("is not a whole safetensors file"));

        let other = dir.join("clip.safetensors");
        write_weights(&other, &["visual.conv1.weight"]);
        let e = check(&other).unwrap_err();
        assert!(e.message.contains("holds 1 tensors, none of them h.0.attn.c_attn.weight or transformer.h.0.attn.c_attn.weight"), "{}", e.message);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
