//! Every tensor the model code builds from host data is placed on a device in the same
//! expression. A tensor made from a slice lives on the CPU; on a CUDA stage it then meets the
//! model's tensors and libtorch stops ("Expected all tensors to be on the same device"), a bug
//! no CPU run can show (the `clipcap` beam search's parent rows were one). So this reads the
//! model code (`rlmflow-nn` and the torch operators, tests left out) and requires each
//! `Tensor::from_slice(..)`/`Tensor::from(..)` to be followed by `.to_device(..)` in its method
//! chain, or its line to say why it stays on the CPU (`// host: ...`).

use std::path::{Path, PathBuf};

/// Constructors that copy host data into a CPU tensor.
const HOST_CONSTRUCTORS: &[&str] = &["Tensor::from_slice(", "Tensor::from(", "Tensor::f_from_slice(", "Tensor::try_from(", "Tensor::from_data_size("];

/// The model code's source files, each with its text up to its `#[cfg(test)]` module.
fn model_sources() -> Vec<(PathBuf, String)> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let roots = ["libs/nn/src", "operators/pretrain/torch/src", "operators/probe/torch/src", "operators/segment/torch/src"].map(|r| root.join(r));
    let mut files = Vec::new();
    let mut pending: Vec<PathBuf> = roots.to_vec();
    while let Some(dir) = pending.pop() {
        for entry in std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
            let path = entry.unwrap().path();
            if path.is_dir() {
                pending.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                let text = std::fs::read_to_string(&path).unwrap();
                let code = text.split("\n#[cfg(test)]").next().unwrap_or_default().to_owned();
                files.push((path, code));
            }
        }
    }
    files.sort();
    files
}

/// The index just past the parenthesis that closes the one before `open`.
fn closing(text: &[u8], open: usize) -> usize {
    let mut depth = 0;
    for (i, &c) in text.iter().enumerate().skip(open) {
        match c {
            b'(' | b'[' => depth += 1,
            b')' | b']' => {
                depth -= 1;
                if depth == 0 {
                    return i + 1;
                }
            }
            _ => {}
        }
    }
    text.len()
}

/// The methods chained onto the expression that ends at `at`: `.view([..]).to_device(d)` gives
/// `view`, `to_device`.
fn chain(text: &[u8], mut at: usize) -> Vec<String> {
    let mut methods = Vec::new();
    loop {
        while at < text.len() && text[at].is_ascii_whitespace() {
            at += 1;
        }
        if text.get(at) != Some(&b'.') {
            return methods;
        }
        let start = at + 1;
        at = start;
        while at < text.len() && (text[at].is_ascii_alphanumeric() || text[at] == b'_') {
            at += 1;
        }
        methods.push(String::from_utf8_lossy(&text[start..at]).into_owned());
        if text.get(at) == Some(&b'(') {
            at = closing(text, at);
        } else if text.get(at) == Some(&b'?') {
            at += 1;
        }
    }
}

/// `line: code` of each host-built tensor in `code` that is neither placed nor marked.
fn unplaced(code: &str) -> Vec<String> {
    let bytes = code.as_bytes();
    let mut found = Vec::new();
    for constructor in HOST_CONSTRUCTORS {
        for (at, _) in code.match_indices(constructor) {
            let line_start = code[..at].rfind('\n').map_or(0, |i| i + 1);
            let line_end = code[at..].find('\n').map_or(code.len(), |i| at + i);
            let line = &code[line_start..line_end];
            if line.trim_start().starts_with("//") || line.contains("// host:") {
                continue;
            }
            let end = closing(bytes, at + constructor.len() - 1);
            if !chain(bytes, end).iter().any(|m| m == "to_device" || m == "to") {
                found.push(format!("{}: {}", code[..at].matches('\n').count() + 1, line.trim()));
            }
        }
    }
    found
}

#[test]
fn every_tensor_built_from_host_data_is_placed_on_a_device() {
    let sources = model_sources();
    assert!(sources.len() > 15, "the model code is where it was: {} files", sources.len());
    let mut problems = Vec::new();
    for (path, code) in &sources {
        problems.extend(unplaced(code).into_iter().map(|p| format!("{}:{p}", path.display())));
    }
    assert!(problems.is_empty(), "tensors built on the CPU and never placed (add `.to_device(..)`, or `// host: why`):\n{}", problems.join("\n"));
}

#[test]
fn the_check_catches_the_beam_search_parents_built_on_the_cpu() {
    // decode.rs before the fix: the parent rows and tokens went to a CUDA model from the CPU.
    let before = "        let logp = model.next(Some(&Tensor::from_slice(&parents)), &Tensor::from_slice(&last).unsqueeze(1));\n";
    assert_eq!(unplaced(before).len(), 2, "{:?}", unplaced(before));
    let after = "        let logp = model.next(Some(&Tensor::from_slice(&parents).to_device(device)), &Tensor::from_slice(&last).to_device(device).unsqueeze(1));\n";
    assert!(unplaced(after).is_empty(), "{:?}", unplaced(after));
    let rustfmt = "    Tensor::from_slice(&counts)\n        .view([n, 48])\n        .to_device(device)\n";
    assert!(unplaced(rustfmt).is_empty(), "a chain over lines");
    assert_eq!(unplaced("let t = Tensor::from(1f32);\n").len(), 1);
    assert!(unplaced("let t = Tensor::from(1f32); // host: a counter\n").is_empty());
}
