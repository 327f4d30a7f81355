//! The numeric platform: which kernels compute an action whose bytes depend on them.
//!
//! libtorch picks its CPU kernels at run time (ATen's capability, oneDNN's instruction set, MKL's
//! code path), so the same model action gives other bytes on another CPU unless they are pinned.
//! An operator that computes with such kernels says so ([`crate::operator::Resources::kernels`]); then:
//!
//! - its process runs with the kernel choices of [`pins`], set by [`apply`] before the operator
//!   starts, whatever the caller's environment says;
//! - its key carries the [`class`] of machines that compute the same bytes under those choices,
//!   so two machines share a cache entry exactly when they compute the same bytes.
//!
//! `portable` (the default) pins one path for every x86-64 machine of one vendor with AVX2 and
//! FMA (`cpu/x86-64-v3/intel/portable`, `cpu/x86-64-v3/amd/portable`): ATen's AVX2 kernels,
//! oneDNN capped at AVX2, float32 matrix products by the FMA-chain GEMM (`RLMFLOW_GEMM`, whose
//! bits do not depend on the vector width, so an AVX-512 machine keeps its width) and MKL's
//! conditional numerical reproducibility for what still calls MKL, on its AVX2 branch on
//! Intel and its compatible branch elsewhere. The vendor is in the class because MKL parts them:
//! it honours its AVX2 branch on Intel CPUs only, and its compatible branch computed other bytes
//! on an AVX-512 Intel than on AVX-512 and AVX2 AMD machines, which agreed (docs/numerics.md).
//! Older x86-64 machines and other architectures get their own pins and classes. `native` sets
//! nothing, so each library takes the fastest kernels the machine has; its class names the CPU
//! model and vector extensions. On a CUDA device the class
//! names the GPU, its compute capability and driver.

use std::collections::BTreeMap;
use std::fmt;

use serde::{Deserialize, Serialize};

use crate::context::Device;

/// How a model action picks its kernels (the `numerics` setting).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Numerics {
    /// One kernel path on every machine of a class: results shared across CPU models.
    #[default]
    Portable,
    /// The fastest kernels this machine has: results shared only with the same CPU model.
    Native,
}

impl fmt::Display for Numerics {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Numerics::Portable => "portable",
            Numerics::Native => "native",
        })
    }
}

/// The arithmetic a model trains and evaluates in (the `precision` setting). Weights, the loss
/// and the optimiser stay in float32 whatever it says (as open_clip's `amp`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// `bf16` on a CUDA device, `fp32` on the CPU: what measured fastest on each
    /// (docs/benchmarks.md, "Precision").
    #[default]
    Auto,
    /// Float32 throughout; on CUDA with TF32 off in cuBLAS and cuDNN.
    Fp32,
    /// Float32 with TF32 matmuls and convolutions: a CUDA mode (Ampere and newer).
    Tf32,
    /// bfloat16 autocast over the models' forward passes (matmuls, convolutions and attention
    /// in bfloat16; softmax, norms and losses in float32).
    Bf16,
}

impl Precision {
    /// What `self` computes in on `target`: `auto` resolved.
    pub fn on(self, target: Target) -> Precision {
        match (self, target) {
            (Precision::Auto, Target::Cuda(_)) => Precision::Bf16,
            (Precision::Auto, Target::Cpu) => Precision::Fp32,
            (chosen, _) => chosen,
        }
    }
}

impl fmt::Display for Precision {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Precision::Auto => "auto",
            Precision::Fp32 => "fp32",
            Precision::Tf32 => "tf32",
            Precision::Bf16 => "bf16",
        })
    }
}

/// What a platform-dependent operator's settings say of its kernels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Kernels {
    pub numerics: Numerics,
    /// Its `device` setting.
    pub device: Device,
}

/// Where an action computes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Target {
    Cpu,
    Cuda(usize),
}

impl Target {
    /// Where a stage whose setting is `setting` computes in a run given `run` (`--device`), on a
    /// machine where CUDA is `available`: a setting naming a device wins, then a run naming a
    /// CUDA device, then (`auto`) CUDA device 0 where there is one. The engine keys an action by
    /// it and the worker computes on it, so both read this one rule.
    pub fn of(setting: Device, run: Device, available: bool) -> Target {
        match (setting, run) {
            (Device::Cpu, _) => Target::Cpu,
            (Device::Cuda(n), _) | (Device::Auto, Device::Cuda(n)) => Target::Cuda(n),
            (Device::Auto, _) if available => Target::Cuda(0),
            (Device::Auto, _) => Target::Cpu,
        }
    }

    /// As a device setting.
    pub fn device(self) -> Device {
        match self {
            Target::Cpu => Device::Cpu,
            Target::Cuda(n) => Device::Cuda(n),
        }
    }
}

/// Every environment variable through which a caller could choose a library's kernels. [`apply`]
/// sets each to its pin or removes it, so none of the caller's choices reaches a pinned action.
pub const KERNEL_VARIABLES: &[&str] = &[
    GEMM_VARIABLE,
    ATTENTION_VARIABLE,
    "ATEN_CPU_CAPABILITY",
    "ONEDNN_MAX_CPU_ISA",
    "DNNL_MAX_CPU_ISA",
    "MKL_CBWR",
    "MKL_ENABLE_INSTRUCTIONS",
    "MKL_DEBUG_CPU_TYPE",
    "MKL_DYNAMIC",
    "CUBLAS_WORKSPACE_CONFIG",
];

/// Which kernels compute ATen's float32 CPU matrix products: [`CHAIN_GEMM`] (the worker's
/// `rlmflow_nn::libtorch::pin_gemm` replaces MKL's by it), or unset for ATen's own.
pub const GEMM_VARIABLE: &str = "RLMFLOW_GEMM";
/// The FMA-chain GEMM: every output one fused multiply-add chain over k in order, the same bits
/// at 16, 8 or 1 float lanes.
pub const CHAIN_GEMM: &str = "fma-chain";
/// The chain GEMM's vector width in float lanes (1, 8 or 16); unset: the widest this CPU has. It
/// changes the speed and not the bits, so no pin sets it: a check sets it to compare widths.
pub const GEMM_LANES_VARIABLE: &str = "RLMFLOW_GEMM_LANES";

/// How the transformers' attention computes on the CPU: [`ATTENTION_BY_PRODUCTS`], or unset for
/// ATen's fused kernel (`scaled_dot_product_attention`), whose blocks call MKL's `sgemm`
/// directly, past the chain GEMM.
pub const ATTENTION_VARIABLE: &str = "RLMFLOW_ATTENTION";
/// Attention as its two matrix products and a softmax, so the products are the chain GEMM's: the
/// portable pin where MKL's pinned branch is its SSE2 one (every vendor but Intel), which made the
/// fused kernel's blocks the slowest part of a step. On Intel, MKL's pinned AVX2 branch keeps the
/// fused kernel as fast (docs/numerics.md).
pub const ATTENTION_BY_PRODUCTS: &str = "products";

/// This machine's CPU, as far as kernel choice goes.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Cpu {
    /// `x86_64`, `aarch64`.
    pub arch: String,
    /// The model name the kernel reports (`AMD EPYC 7B13`), or `unknown`.
    pub model: String,
    /// The vector extensions that change a library's kernel choice, in a fixed order.
    pub extensions: Vec<String>,
    /// The vendor the CPU names itself by (`GenuineIntel`, `AuthenticAMD`; empty off x86).
    #[serde(default)]
    pub vendor: String,
}

impl Cpu {
    /// This machine's.
    pub fn detect() -> Cpu {
        Cpu {
            arch: std::env::consts::ARCH.to_owned(),
            model: cpuinfo(&["model name", "Model", "CPU part"]),
            extensions: extensions(),
            vendor: vendor(),
        }
    }

    fn has(&self, extension: &str) -> bool {
        self.extensions.iter().any(|e| e == extension)
    }

    /// x86-64 with AVX2 and FMA (the x86-64-v3 level as far as kernels go).
    fn is_x86_64_v3(&self) -> bool {
        self.arch == "x86_64" && self.has("avx2") && self.has("fma")
    }

    fn is_intel(&self) -> bool {
        self.vendor == "GenuineIntel"
    }

    /// The vendor as a class names it: `intel`, `amd`, else its own name in lower case.
    fn vendor_class(&self) -> String {
        match self.vendor.as_str() {
            "GenuineIntel" => "intel".to_owned(),
            "AuthenticAMD" => "amd".to_owned(),
            "" => "unknown".to_owned(),
            other => other.chars().filter(char::is_ascii_alphanumeric).collect::<String>().to_lowercase(),
        }
    }
}

/// The first of `/proc/cpuinfo`'s lines named by `keys`, its value; `unknown` if none.
fn cpuinfo(keys: &[&str]) -> String {
    let info = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let line = info.lines().find(|l| keys.iter().any(|k| l.starts_with(k)));
    line.and_then(|l| l.split_once(':')).map_or("unknown".to_owned(), |(_, v)| v.split_whitespace().collect::<Vec<_>>().join(" "))
}

/// CPUID's vendor string: what MKL reads to choose its branch.
#[cfg(target_arch = "x86_64")]
fn vendor() -> String {
    // SAFETY: leaf 0 of CPUID exists on every x86-64 CPU.
    #[allow(unused_unsafe)]
    let id = unsafe { std::arch::x86_64::__cpuid(0) };
    let bytes: Vec<u8> = [id.ebx, id.edx, id.ecx].iter().flat_map(|r| r.to_le_bytes()).collect();
    String::from_utf8_lossy(&bytes).into_owned()
}

#[cfg(not(target_arch = "x86_64"))]
fn vendor() -> String {
    String::new()
}

#[cfg(target_arch = "x86_64")]
fn extensions() -> Vec<String> {
    macro_rules! present {
        ($($f:tt),*) => { [$((($f), std::arch::is_x86_feature_detected!($f))),*] };
    }
    let all = present!("sse4.2", "avx", "avx2", "fma", "avx512f", "avx512bw", "avx512vl", "avx512dq", "avx512vnni", "avx512bf16", "avx512fp16");
    all.iter().filter(|(_, on)| *on).map(|(name, _)| (*name).to_owned()).collect()
}

#[cfg(target_arch = "aarch64")]
fn extensions() -> Vec<String> {
    macro_rules! present {
        ($($f:tt),*) => { [$((($f), std::arch::is_aarch64_feature_detected!($f))),*] };
    }
    let all = present!("neon", "fp16", "dotprod", "bf16", "i8mm", "sve", "sve2");
    all.iter().filter(|(_, on)| *on).map(|(name, _)| (*name).to_owned()).collect()
}

#[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
fn extensions() -> Vec<String> {
    Vec::new()
}

/// The environment a platform-dependent action runs with on `cpu`: each of
/// [`KERNEL_VARIABLES`] with its value, or `None` where it is removed.
pub fn pins(numerics: Numerics, cpu: &Cpu, target: Target) -> BTreeMap<&'static str, Option<&'static str>> {
    let mut env: BTreeMap<&'static str, Option<&'static str>> = KERNEL_VARIABLES.iter().map(|v| (*v, None)).collect();
    if numerics == Numerics::Portable {
        // MKL runs its AVX2 branch on Intel CPUs only.
        let mkl = if cpu.is_intel() { "AVX2" } else { "COMPATIBLE" };
        let chosen: &[(&str, &str)] = if cpu.is_x86_64_v3() {
            &[
                (GEMM_VARIABLE, CHAIN_GEMM),
                ("ATEN_CPU_CAPABILITY", "avx2"),
                ("ONEDNN_MAX_CPU_ISA", "AVX2"),
                ("MKL_CBWR", mkl),
                ("MKL_DYNAMIC", "FALSE"),
            ]
        } else if cpu.arch == "x86_64" {
            &[("ATEN_CPU_CAPABILITY", "default"), ("ONEDNN_MAX_CPU_ISA", "SSE41"), ("MKL_CBWR", "COMPATIBLE"), ("MKL_DYNAMIC", "FALSE")]
        } else {
            &[("ATEN_CPU_CAPABILITY", "default")]
        };
        for (var, value) in chosen {
            env.insert(var, Some(value));
        }
        // Off Intel that branch is SSE2 code, so attention leaves MKL for the chain GEMM too.
        if cpu.is_x86_64_v3() && !cpu.is_intel() {
            env.insert(ATTENTION_VARIABLE, Some(ATTENTION_BY_PRODUCTS));
        }
    }
    if let Target::Cuda(_) = target {
        // cuBLAS's deterministic workspace, as PyTorch's reproducibility notes ask.
        env.insert("CUBLAS_WORKSPACE_CONFIG", Some(":4096:8"));
    }
    env
}

/// Sets this process's kernel choices to [`pins`]. Call before any library computes, while the
/// process has one thread (the engine does, before a platform-dependent operator runs).
pub fn apply(numerics: Numerics, cpu: &Cpu, target: Target) {
    for (var, value) in pins(numerics, cpu, target) {
        // SAFETY: called before the operator starts, while the process has one thread.
        unsafe {
            match value {
                Some(value) => std::env::set_var(var, value),
                None => std::env::remove_var(var),
            }
        }
    }
}

/// The GPU an action runs on, as its driver reports it.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Gpu {
    pub name: String,
    /// `9.0`.
    pub compute_capability: String,
    pub driver: String,
}

impl Gpu {
    /// CUDA device `index` through `nvidia-smi`; `None` where it cannot tell.
    pub fn detect(index: usize) -> Option<Gpu> {
        let line = query_gpu(index, "name,compute_cap,driver_version")?;
        let mut fields = line.split(',').map(|f| f.trim().to_owned());
        Some(Gpu { name: fields.next()?, compute_capability: fields.next()?, driver: fields.next()? })
    }
}

/// `nvidia-smi`'s line of `fields` (comma-separated query names, units left out) for CUDA
/// device `index`; `None` where there is no such device or no `nvidia-smi`.
pub fn query_gpu(index: usize, fields: &str) -> Option<String> {
    let out = std::process::Command::new("nvidia-smi")
        .args([format!("--query-gpu={fields}"), "--format=csv,noheader,nounits".into(), format!("--id={index}")])
        .stderr(std::process::Stdio::null())
        .output()
        .ok()
        .filter(|o| o.status.success())?;
    Some(String::from_utf8_lossy(&out.stdout).lines().next()?.trim().to_owned())
}

/// The class of machines that compute the same bytes for a platform-dependent action: a line of
/// its key. `gpu` is the target's when it is CUDA.
pub fn class(numerics: Numerics, cpu: &Cpu, target: Target, gpu: Option<&Gpu>) -> String {
    if let Target::Cuda(_) = target {
        let gpu = gpu.map_or("unknown GPU".to_owned(), |g| format!("{}/sm_{}/driver {}", g.name, g.compute_capability.replace('.', ""), g.driver));
        return format!("cuda/{gpu}/{numerics}");
    }
    match numerics {
        Numerics::Portable if cpu.is_x86_64_v3() => format!("cpu/x86-64-v3/{}/portable", cpu.vendor_class()),
        Numerics::Portable if cpu.arch == "x86_64" => format!("cpu/x86-64/{}/portable", cpu.vendor_class()),
        Numerics::Portable => format!("cpu/{}/portable", cpu.arch.replace('_', "-")),
        Numerics::Native => format!("cpu/{}/native/{}/{}", cpu.arch.replace('_', "-"), cpu.model, cpu.extensions.join("+")),
    }
}

/// An environment that asks every library for other kernels than both the portable pins and its
/// own automatic choice: older instruction sets than AVX2 (ATen's default, oneDNN's SSE4.1,
/// MKL's SSE4.2 and automatic branch, OpenBLAS's Prescott kernels), every one of numpy's
/// loops, and the chain GEMM at AVX2's 8 lanes (its widest is 16 on an AVX-512 machine). `run --check-determinism` runs a second attempt under it: where a pin is missing the
/// first attempt (the library's own choice, AVX-512 on a machine that has it) and this one
/// differ, and where a pin does not win over the environment this one differs from the pin's.
pub fn other_kernels() -> Vec<(&'static str, &'static str)> {
    vec![
        ("ATEN_CPU_CAPABILITY", "default"),
        ("ONEDNN_MAX_CPU_ISA", "SSE41"),
        ("MKL_ENABLE_INSTRUCTIONS", "SSE4_2"),
        ("MKL_CBWR", "AUTO"),
        ("OPENBLAS_CORETYPE", "Prescott"),
        ("NPY_DISABLE_CPU_FEATURES", ""),
        (GEMM_LANES_VARIABLE, "8"),
    ]
}

/// What an action's provenance records of the platform it ran on.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PlatformRecord {
    /// The class in its key.
    pub class: String,
    pub numerics: Numerics,
    pub cpu: Cpu,
    /// The kernel choices it ran with (`unset` where removed).
    pub pins: BTreeMap<String, String>,
    pub threads: usize,
    /// The numeric libraries of the binary that ran it (`libtorch 2.11.0`).
    pub libraries: Vec<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gpu: Option<Gpu>,
}

impl PlatformRecord {
    pub fn new(numerics: Numerics, target: Target, threads: usize, libraries: &[&str]) -> PlatformRecord {
        let cpu = Cpu::detect();
        let gpu = match target {
            Target::Cuda(n) => Gpu::detect(n),
            Target::Cpu => None,
        };
        let pins = pins(numerics, &cpu, target).into_iter().map(|(k, v)| (k.to_owned(), v.unwrap_or("unset").to_owned())).collect();
        PlatformRecord {
            class: class(numerics, &cpu, target, gpu.as_ref()),
            numerics,
            cpu,
            pins,
            threads,
            libraries: libraries.iter().map(|l| (*l).to_owned()).collect(),
            gpu,
        }
    }
}

impl fmt::Display for PlatformRecord {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "platform {}", self.class)?;
        writeln!(f, "  cpu {} ({}; {})", self.cpu.model, self.cpu.arch, self.cpu.extensions.join(" "))?;
        if let Some(gpu) = &self.gpu {
            writeln!(f, "  gpu {} (compute capability {}, driver {})", gpu.name, gpu.compute_capability, gpu.driver)?;
        }
        let pins: Vec<String> = self.pins.iter().map(|(k, v)| format!("{k}={v}")).collect();
        writeln!(f, "  kernels {} ({})", self.numerics, pins.join(" "))?;
        write!(
            f,
            "  threads {}; {}",
            self.threads,
            if self.libraries.is_empty() { "no numeric library named".to_owned() } else { self.libraries.join(", ") }
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cpu(arch: &str, extensions: &[&str]) -> Cpu {
        let vendor = if arch == "x86_64" { "AuthenticAMD" } else { "" };
        Cpu { arch: arch.into(), model: "Test CPU".into(), extensions: extensions.iter().map(|e| (*e).to_owned()).collect(), vendor: vendor.into() }
    }

    #[test]
    fn every_avx2_machine_of_a_vendor_is_one_portable_class_whatever_its_model() {
        let zen3 = cpu("x86_64", &["sse4.2", "avx", "avx2", "fma"]);
        let zen4 = Cpu { model: "Other CPU".into(), ..cpu("x86_64", &["sse4.2", "avx", "avx2", "fma", "avx512f", "avx512bw"]) };
        assert_eq!(class(Numerics::Portable, &zen3, Target::Cpu, None), "cpu/x86-64-v3/amd/portable");
        assert_eq!(class(Numerics::Portable, &zen4, Target::Cpu, None), class(Numerics::Portable, &zen3, Target::Cpu, None));
        assert_eq!(pins(Numerics::Portable, &zen3, Target::Cpu), pins(Numerics::Portable, &zen4, Target::Cpu));
        assert_ne!(class(Numerics::Native, &zen3, Target::Cpu, None), class(Numerics::Native, &zen4, Target::Cpu, None));
        assert!(class(Numerics::Native, &zen4, Target::Cpu, None).contains("Other CPU"));
        assert_eq!(class(Numerics::Portable, &cpu("aarch64", &["neon"]), Target::Cpu, None), "cpu/aarch64/portable");
        assert_eq!(class(Numerics::Portable, &cpu("x86_64", &["sse4.2"]), Target::Cpu, None), "cpu/x86-64/amd/portable");
        // Intel's AVX-512 and AVX2 machines share MKL's AVX2 branch, which MKL runs on Intel only.
        let intel = |extensions: &[&str]| Cpu { vendor: "GenuineIntel".into(), ..cpu("x86_64", extensions) };
        let (skylake_x, haswell) = (intel(&["avx2", "fma", "avx512f"]), intel(&["avx2", "fma"]));
        assert_eq!(class(Numerics::Portable, &skylake_x, Target::Cpu, None), "cpu/x86-64-v3/intel/portable");
        assert_eq!(pins(Numerics::Portable, &skylake_x, Target::Cpu), pins(Numerics::Portable, &haswell, Target::Cpu));
        assert_eq!(pins(Numerics::Portable, &haswell, Target::Cpu)["MKL_CBWR"], Some("AVX2"));
        assert_eq!(
            class(Numerics::Portable, &Cpu { vendor: "HygonGenuine".into(), ..zen3 }, Target::Cpu, None),
            "cpu/x86-64-v3/hygongenuine/portable"
        );
    }

    #[test]
    fn pins_name_every_kernel_variable_and_native_removes_them_all() {
        let zen3 = cpu("x86_64", &["avx2", "fma"]);
        let portable = pins(Numerics::Portable, &zen3, Target::Cpu);
        assert_eq!(portable.len(), KERNEL_VARIABLES.len());
        assert_eq!(portable["ATEN_CPU_CAPABILITY"], Some("avx2"));
        assert_eq!(portable[GEMM_VARIABLE], Some(CHAIN_GEMM));
        assert_eq!(portable["MKL_CBWR"], Some("COMPATIBLE"));
        assert_eq!(portable[ATTENTION_VARIABLE], Some(ATTENTION_BY_PRODUCTS), "off MKL's SSE2 branch");
        let intel = Cpu { vendor: "GenuineIntel".into(), ..zen3.clone() };
        assert_eq!(pins(Numerics::Portable, &intel, Target::Cpu)[ATTENTION_VARIABLE], None, "MKL's AVX2 branch keeps the fused kernel");
        assert_eq!(pins(Numerics::Portable, &intel, Target::Cpu)[GEMM_VARIABLE], Some(CHAIN_GEMM));
        assert_eq!(pins(Numerics::Portable, &cpu("aarch64", &["neon"]), Target::Cpu)[GEMM_VARIABLE], None, "no chain kernel off x86-64-v3");
        assert_eq!(pins(Numerics::Portable, &cpu("aarch64", &["neon"]), Target::Cpu)[ATTENTION_VARIABLE], None, "no chain kernel to take it");
        assert_eq!(portable["MKL_ENABLE_INSTRUCTIONS"], None);
        assert!(pins(Numerics::Native, &zen3, Target::Cpu).values().all(Option::is_none));
        assert_eq!(pins(Numerics::Native, &zen3, Target::Cuda(0))["CUBLAS_WORKSPACE_CONFIG"], Some(":4096:8"));
    }

    #[test]
    fn a_cuda_class_names_the_gpu() {
        let gpu = Gpu { name: "NVIDIA H100".into(), compute_capability: "9.0".into(), driver: "550.54".into() };
        let zen3 = cpu("x86_64", &["avx2", "fma"]);
        assert_eq!(class(Numerics::Portable, &zen3, Target::Cuda(0), Some(&gpu)), "cuda/NVIDIA H100/sm_90/driver 550.54/portable");
    }
}
