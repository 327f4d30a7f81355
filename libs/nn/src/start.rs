//! Published start weights copied onto our models: one loader ([`load`]), and a name map per
//! source ([`CLIP_VISION`], [`GPT2`]). A tensor whose shape does not fit is an error naming it,
//! except where the source's map says it may be left out (a vocabulary that is not ours).

use std::collections::HashMap;
use std::path::Path;

use anyhow::{Context as _, bail};
use tch::{Tensor, nn};

/// Looks a tensor up by its name in a weights file.
pub type FileTensor<'a> = &'a dyn Fn(&str) -> Option<Tensor>;

/// A family of published weights: how its file names our variables' tensors.
pub struct Source {
    /// For messages: `CLIP`, `GPT-2`.
    pub what: &'static str,
    /// The names it holds, for the error when the file holds none of them.
    pub names: &'static str,
    /// The file's tensor for our variable `rest` (its name after the model's prefix), in our
    /// layout; `None` where the file has none. `file` looks a name up in the file.
    pub map: fn(file: FileTensor<'_>, rest: &str) -> Option<Tensor>,
    /// Variables left as they are when the file's tensor does not fit.
    pub optional: &'static [&'static str],
}

/// Copies the tensors of the safetensors file at `path` onto the variables of `vs` named
/// `prefix` + a name `source` maps; returns how many it copied.
pub fn load(vs: &nn::VarStore, prefix: &str, path: &Path, source: &Source) -> anyhow::Result<usize> {
    let tensors: HashMap<String, Tensor> =
        Tensor::read_safetensors(path).with_context(|| format!("reading {} weights from {}", source.what, path.display()))?.into_iter().collect();
    let file = |name: &str| tensors.get(name).map(Tensor::shallow_clone);
    let mut loaded = 0;
    tch::no_grad(|| -> anyhow::Result<()> {
        for (name, mut var) in vs.variables() {
            let Some(rest) = name.strip_prefix(prefix) else { continue };
            let Some(found) = (source.map)(&file, rest) else { continue };
            if found.size() != var.size() {
                if source.optional.contains(&rest) {
                    continue;
                }
                bail!("{}: the tensor for `{name}` has shape {:?}, the model needs {:?}", path.display(), found.size(), var.size());
            }
            var.copy_(&found.to_kind(var.kind()));
            loaded += 1;
        }
        Ok(())
    })?;
    if loaded == 0 {
        bail!("{}: no tensor with {} names ({})", path.display(), source.what, source.names);
    }
    Ok(loaded)
}

/// A CLIP ViT-B/16 vision tower onto our radar tower (prefix `visual.`), from open_clip names
/// (`visual.conv1.weight`, `visual.transformer.resblocks.N...`) or Hugging Face names
/// (`vision_model.embeddings.patch_embedding.weight`, `vision_model.encoder.layers.N...`). The
/// RGB patch kernel is summed over its colour channels for the one radar channel; the
/// projection is kept only where its shape fits.
pub const CLIP_VISION: Source = Source {
    what: "CLIP",
    names: "open_clip visual.* or Hugging Face vision_model.*",
    map: |file, rest| {
        let found = clip_vision(file, rest)?;
        Some(if rest == "conv1.weight" && found.size().get(1) == Some(&3) {
            found.sum_dim_intlist([1].as_slice(), true, found.kind())
        } else {
            found
        })
    },
    optional: &["proj"],
};

fn clip_vision(file: FileTensor<'_>, rest: &str) -> Option<Tensor> {
    if let Some(t) = file(&format!("visual.{rest}")) {
        return Some(t);
    }
    let hf = |k: &str| file(&format!("vision_model.{k}"));
    let layer = |i: &str, k: &str| format!("encoder.layers.{i}.{k}");
    match rest {
        "conv1.weight" => hf("embeddings.patch_embedding.weight"),
        "class_embedding" => hf("embeddings.class_embedding"),
        "positional_embedding" => hf("embeddings.position_embedding.weight"),
        "ln_pre.weight" => hf("pre_layrnorm.weight"),
        "ln_pre.bias" => hf("pre_layrnorm.bias"),
        "ln_post.weight" => hf("post_layernorm.weight"),
        "ln_post.bias" => hf("post_layernorm.bias"),
        "proj" => file("visual_projection.weight").map(|t| t.tr()),
        _ => {
            let (i, key) = rest.strip_prefix("transformer.resblocks.")?.split_once('.')?;
            let qkv = |suffix: &str| -> Option<Tensor> {
                let parts: Option<Vec<Tensor>> =
                    ["q_proj", "k_proj", "v_proj"].iter().map(|p| hf(&layer(i, &format!("self_attn.{p}.{suffix}")))).collect();
                parts.map(|p| Tensor::cat(&p, 0))
            };
            match key {
                "attn.in_proj_weight" => qkv("weight"),
                "attn.in_proj_bias" => qkv("bias"),
                "attn.out_proj.weight" => hf(&layer(i, "self_attn.out_proj.weight")),
                "attn.out_proj.bias" => hf(&layer(i, "self_attn.out_proj.bias")),
                "ln_1.weight" => hf(&layer(i, "layer_norm1.weight")),
                "ln_1.bias" => hf(&layer(i, "layer_norm1.bias")),
                "ln_2.weight" => hf(&layer(i, "layer_norm2.weight")),
                "ln_2.bias" => hf(&layer(i, "layer_norm2.bias")),
                "mlp.c_fc.weight" => hf(&layer(i, "mlp.fc1.weight")),
                "mlp.c_fc.bias" => hf(&layer(i, "mlp.fc1.bias")),
                "mlp.c_proj.weight" => hf(&layer(i, "mlp.fc2.weight")),
                "mlp.c_proj.bias" => hf(&layer(i, "mlp.fc2.bias")),
                _ => None,
            }
        }
    }
}

/// GPT-2 onto ClipCap's decoder (`crate::gpt::Gpt`), from Hugging Face `GPT2Model` or
/// `GPT2LMHeadModel` names, with or without the `transformer.` prefix. GPT-2's Conv1D kernels
/// are (in, out) and are transposed; the token and position tables are kept only where their
/// shapes fit (GPT-2's vocabulary is not ours).
pub const GPT2: Source = Source {
    what: "GPT-2",
    names: "h.N.attn.c_attn.weight, ln_f.weight, ...",
    map: |file, rest| {
        let get = |k: &str| file(k).or_else(|| file(&format!("transformer.{k}")));
        match rest {
            "wte.weight" | "wpe.weight" | "ln_f.weight" | "ln_f.bias" => get(rest),
            _ => {
                let (i, key) = rest.strip_prefix("transformer.resblocks.")?.split_once('.')?;
                let h = |k: &str| get(&format!("h.{i}.{k}"));
                match key {
                    "attn.in_proj_weight" => h("attn.c_attn.weight").map(|t| t.tr()),
                    "attn.in_proj_bias" => h("attn.c_attn.bias"),
                    "attn.out_proj.weight" => h("attn.c_proj.weight").map(|t| t.tr()),
                    "attn.out_proj.bias" => h("attn.c_proj.bias"),
                    "mlp.c_fc.weight" => h("mlp.c_fc.weight").map(|t| t.tr()),
                    "mlp.c_fc.bias" => h("mlp.c_fc.bias"),
                    "mlp.c_proj.weight" => h("mlp.c_proj.weight").map(|t| t.tr()),
                    "mlp.c_proj.bias" => h("mlp.c_proj.bias"),
                    "ln_1.weight" | "ln_1.bias" | "ln_2.weight" | "ln_2.bias" => h(key),
                    _ => None,
                }
            }
        }
        .map(|t| t.contiguous())
    },
    optional: &["wte.weight", "wpe.weight"],
};
