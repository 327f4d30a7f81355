//! Devices and arithmetic through the real binaries: `rlmflow doctor` says which devices the
//! worker can compute on and why not CUDA, naming the first cause it meets; `precision` is a
//! keyed setting whose `bf16` trains through the worker (bfloat16 autocast on the CPU) and gives
//! the same bytes in a fresh process and store.

use std::path::Path;

use crate::common::{output, rlmflow, scratch, scratch_alone};

#[test]
fn the_doctor_says_which_devices_the_worker_can_use_and_why_not_cuda() {
    let dir = scratch_alone("doctor", "");
    let (ok, out) = rlmflow(&dir, &["doctor"]);
    assert!(ok, "{out}");
    assert!(out.contains("devices        cpu"), "{out}");
    let libtorch = out.lines().find_map(|l| l.strip_prefix("libtorch       ")).unwrap_or_else(|| panic!("{out}"));
    let lib = Path::new(libtorch.split(" (").next().unwrap()).join("lib");
    assert!(lib.join("libtorch_cpu.so").is_file(), "the libtorch the worker runs with: {out}");
    if out.contains("CUDA           usable") {
        return; // a machine with a GPU: nothing is out of reach
    }
    assert!(out.contains("CUDA           not usable: "), "{out}");
    if !Path::new("/dev/nvidiactl").exists() {
        assert!(out.contains("NVIDIA driver  none: libcuda.so.1 cannot be loaded"), "{out}");
    }
    if lib.join("libtorch_cuda.so").is_file() {
        // The worker tried to load libtorch's CUDA half: either it loaded (the CUDA packages are
        // installed) or the error names a library the tree does not hold.
        let line = out.lines().find(|l| l.starts_with("libtorch_cuda  ")).unwrap();
        if line != "libtorch_cuda  loaded" {
            let missing = line.split("not loaded: ").nth(1).and_then(|r| r.split(':').next()).unwrap_or_else(|| panic!("{line}"));
            assert!(missing.starts_with("lib") && missing.contains(".so"), "{line}");
            let tree = lib.parent().unwrap().parent().unwrap();
            let found = std::process::Command::new("find").arg(tree).arg("-name").arg(missing).output().unwrap();
            assert!(found.stdout.is_empty(), "{missing} is in {}, yet the worker says it is missing: {line}", tree.display());
        }
    } else {
        assert!(out.contains("is a CPU build"), "{out}");
    }
}

/// A CPU-size encoder, one epoch, in the given arithmetic (native kernels: bfloat16 under the
/// portable pins is five times slower, and `numerics.rs` checks the pins).
fn pipeline(name: &str, precision: &str) -> String {
    format!(
        "{}\n[stages.pretrain]\noperator = \"clip\"\ndevice = \"cpu\"\n{}\nbatch = 64\nepochs = 1\nwarmup_epochs = 0.0\n{precision}\n",
        crate::common::data_stages(name),
        crate::common::NATIVE
    )
}

#[test]
fn precision_is_keyed_and_bf16_trains_to_the_same_bytes_in_a_fresh_store() {
    let _turn = crate::common::one_at_a_time();
    let dir = scratch("precision", &pipeline("precision", ""));
    let (ok, out) = rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    let fp32 = output(&dir, "precision", "pretrain");
    let (ok, status) = rlmflow(&dir, &["status", "p.toml", "--set", "pretrain.precision=\"bf16\""]);
    assert!(ok && status.contains(r#"pretrain.precision "auto" -> "bf16""#), "{status}");
    let (ok, explain) = rlmflow(&dir, &["explain", "p.toml", "pretrain", "--set", "pretrain.precision=\"bf16\""]);
    assert!(ok && explain.contains("precision") && explain.contains("bf16"), "{explain}");
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--set", "pretrain.precision=\"bf16\""]);
    assert!(ok && out.contains("ran      pretrain"), "{out}");
    let bf16 = output(&dir, "precision", "pretrain");
    assert_ne!(fp32, bf16, "bf16 is another result under another key");
    let weights = |dir: &Path| std::fs::read(dir.join("model.safetensors")).unwrap();
    assert_ne!(weights(&fp32), weights(&bf16));

    // The same key in a fresh store, computed in fresh processes: the same bytes.
    let fresh = scratch_alone("precision-fresh", &pipeline("precision", "precision = \"bf16\""));
    let (ok, out) = rlmflow(&fresh, &["run", "p.toml"]);
    assert!(ok, "{out}");
    assert_eq!(output(&fresh, "precision", "pretrain").file_name(), bf16.file_name(), "same key, same bytes: {out}");

    // A CUDA-only arithmetic on the CPU is refused before anything runs, naming the key.
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--set", "pretrain.precision=\"tf32\""]);
    assert!(!ok && out.contains("precision") && out.contains("`tf32` is a CUDA matmul mode"), "{out}");
}

/// The GPU check (`xtask/device-check.py`) on a machine without a GPU: it checks what it needs
/// (the binaries run, examples/paper-smoke.toml with every model stage on CUDA validates, the
/// PyTorch reference is there), says it measured nothing and why, and exits 0; a missing binary
/// is named. So the check a GPU loan runs cannot rot between loans.
#[test]
fn the_device_check_runs_dry_without_a_gpu_and_names_what_is_missing() {
    let dir = scratch_alone("device-check", "");
    let bin = dir.join("bin");
    std::fs::create_dir_all(&bin).unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../xtask/device-check.py");
    let check = |extra: &[&str]| {
        let out = std::process::Command::new("python3").arg(&script).arg("--bin").arg(&bin).args(extra).output().unwrap();
        (out.status.success(), String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr))
    };
    let (ok, out) = check(&[]);
    assert!(!ok && out.contains("rlmflow") && out.contains("is missing"), "{out}");
    std::os::unix::fs::symlink(crate::common::rlmflow_exe(), bin.join("rlmflow")).unwrap();
    std::os::unix::fs::symlink(env!("CARGO_BIN_EXE_rlmflow-torch"), bin.join("rlmflow-torch")).unwrap();
    let (ok, out) = check(&[]);
    assert!(ok, "{out}");
    if !out.contains("CUDA           usable") {
        assert!(out.contains("device-check: dry mode, no CUDA device") && out.contains("inputs checked"), "{out}");
    }
    let (ok, out) = check(&["--dry"]);
    assert!(ok && out.contains("device-check: dry mode, --dry"), "{out}");
}
