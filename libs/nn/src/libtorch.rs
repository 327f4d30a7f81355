//! What libtorch has and tch 0.24 does not expose, through the few C++ functions of
//! `cpp/torch_settings.cpp` (compiled by `build.rs` against the same headers): deterministic
//! algorithms, TF32, bfloat16 autocast on the CPU or CUDA (tch's `autocast` reaches CUDA's
//! alone, in float16), and the multi-tensor kernels of PyTorch's fused AdamW and gradient
//! clipping; and the portable numerics' matrix products (`cpp/chain_gemm.cpp`).

use std::ffi::{CStr, c_char, c_void};
use std::sync::Mutex;

use tch::Tensor;

use anyhow::bail;
use rlmflow_stages::numerics::{CHAIN_GEMM, GEMM_LANES_VARIABLE, GEMM_VARIABLE};

unsafe extern "C" {
    fn rlmflow_free_message(message: *mut c_char);
    fn rlmflow_set_deterministic(on: bool) -> *mut c_char;
    fn rlmflow_deterministic() -> bool;
    fn rlmflow_set_tf32(on: bool) -> *mut c_char;
    fn rlmflow_tf32_cublas() -> bool;
    fn rlmflow_autocast_enter(cuda: i32, previous: *mut bool) -> *mut c_char;
    fn rlmflow_autocast_exit(cuda: i32, previous: bool) -> *mut c_char;
    fn rlmflow_autocast_enabled(cuda: i32) -> bool;
    fn rlmflow_fused_adamw(
        params: *const *mut c_void,
        grads: *const *mut c_void,
        exp_avgs: *const *mut c_void,
        exp_avg_sqs: *const *mut c_void,
        n: i32,
        step: f64,
        lr: f64,
        beta1: f64,
        beta2: f64,
        weight_decay: f64,
        eps: f64,
    ) -> *mut c_char;
    fn rlmflow_foreach_clip(grads: *const *mut c_void, n: i32, max: f64) -> *mut c_char;
    fn rlmflow_chain_gemm_widest() -> i32;
    fn rlmflow_chain_gemm_install(lanes: i32) -> *mut c_char;
    fn rlmflow_chain_mm(a: *const c_void, b: *const c_void, lanes: i32, out: *mut *mut c_void) -> *mut c_char;
}

/// `Ok`, or the C++ exception's message a shim function returned.
fn checked(message: *mut c_char, what: &str) -> anyhow::Result<()> {
    if message.is_null() {
        return Ok(());
    }
    // SAFETY: a non-null return is a NUL-terminated string the shim allocated with strdup.
    let text = unsafe { CStr::from_ptr(message) }.to_string_lossy().into_owned();
    unsafe { rlmflow_free_message(message) };
    bail!("libtorch refused to {what}: {text}")
}

/// Deterministic algorithms everywhere (an op with no deterministic kernel then raises, naming
/// itself), deterministic cuDNN, and no cuDNN autotuning.
pub fn set_deterministic(on: bool) -> anyhow::Result<()> {
    checked(unsafe { rlmflow_set_deterministic(on) }, "set deterministic algorithms")
}

pub fn deterministic() -> bool {
    unsafe { rlmflow_deterministic() }
}

/// TF32 in cuBLAS matmuls and cuDNN convolutions (libtorch allows it in cuDNN unless told).
pub fn set_tf32(on: bool) -> anyhow::Result<()> {
    checked(unsafe { rlmflow_set_tf32(on) }, "set TF32")
}

pub fn tf32() -> bool {
    unsafe { rlmflow_tf32_cublas() }
}

fn is_cuda(device: tch::Device) -> i32 {
    i32::from(device.is_cuda())
}

/// tch's handles of `tensors` (each an `at::Tensor*`), for a shim function.
fn handles(tensors: &[&Tensor]) -> Vec<*mut c_void> {
    tensors.iter().map(|t| t.as_ptr() as *mut c_void).collect()
}

/// The settings of one AdamW step.
#[derive(Clone, Copy, Debug)]
pub struct AdamWStep {
    /// The step's number, from 1 (for the bias corrections).
    pub step: i64,
    pub lr: f64,
    pub betas: (f64, f64),
    pub weight_decay: f64,
    pub eps: f64,
}

/// One AdamW step over `params` in PyTorch's fused kernel (`torch.optim.AdamW(fused=True)`):
/// the parameters and the moments `exp_avgs`, `exp_avg_sqs` are updated in place; all four lists
/// are parallel, on one device, in float32.
pub fn fused_adamw(params: &[&Tensor], grads: &[&Tensor], exp_avgs: &[&Tensor], exp_avg_sqs: &[&Tensor], s: AdamWStep) -> anyhow::Result<()> {
    let n = params.len();
    assert!(grads.len() == n && exp_avgs.len() == n && exp_avg_sqs.len() == n, "parallel lists");
    let (p, g, m, v) = (handles(params), handles(grads), handles(exp_avgs), handles(exp_avg_sqs));
    // SAFETY: four arrays of n live tensor handles, borrowed for the call.
    let message = tch::no_grad(|| unsafe {
        rlmflow_fused_adamw(
            p.as_ptr(),
            g.as_ptr(),
            m.as_ptr(),
            v.as_ptr(),
            n as i32,
            s.step as f64,
            s.lr,
            s.betas.0,
            s.betas.1,
            s.weight_decay,
            s.eps,
        )
    });
    checked(message, "take a fused AdamW step")
}

/// Scales `grads` (at least one) in place so their global L2 norm is at most `max`, as
/// `torch.nn.utils.clip_grad_norm_(foreach=True)`, without waiting for the device.
pub fn foreach_clip(grads: &[&Tensor], max: f64) -> anyhow::Result<()> {
    let g = handles(grads);
    // SAFETY: an array of live tensor handles, borrowed for the call.
    let message = tch::no_grad(|| unsafe { rlmflow_foreach_clip(g.as_ptr(), g.len() as i32, max) });
    checked(message, "clip the gradients")
}

/// The widest chain GEMM kernel this CPU runs, in float32 lanes: 16 (AVX-512), 8 (AVX2 and FMA)
/// or 1 (scalar `fma`). Every width computes the same bits.
pub fn chain_lanes_widest() -> usize {
    unsafe { rlmflow_chain_gemm_widest() as usize }
}

/// `a` (m x k) times `b` (k x n), float32 on the CPU, by the chain GEMM at `lanes` (1, 8 or 16,
/// at most [`chain_lanes_widest`]), whether or not it is installed.
pub fn chain_mm(a: &Tensor, b: &Tensor, lanes: usize) -> anyhow::Result<Tensor> {
    check_lanes(lanes)?;
    let mut out: *mut c_void = std::ptr::null_mut();
    // SAFETY: two live tensor handles borrowed for the call; on success `out` is a new handle
    // this function owns.
    checked(unsafe { rlmflow_chain_mm(a.as_ptr() as *const c_void, b.as_ptr() as *const c_void, lanes as i32, &mut out) }, "multiply")?;
    Ok(unsafe { Tensor::from_ptr(out.cast()) })
}

fn check_lanes(lanes: usize) -> anyhow::Result<()> {
    let widest = chain_lanes_widest();
    if ![1, 8, 16].contains(&lanes) || lanes > widest {
        bail!("{GEMM_LANES_VARIABLE}={lanes}: the chain GEMM runs at 1, 8 or 16 lanes, and this CPU at most {widest}");
    }
    Ok(())
}

/// The lanes the chain GEMM is installed at in this process; 0: ATen's own kernels.
static CHAIN_LANES: Mutex<usize> = Mutex::new(0);

/// Makes ATen's float32 CPU matrix products (`mm`, `addmm`, `bmm`, `baddbmm`) what
/// `RLMFLOW_GEMM` asks: `fma-chain` (the portable pin, `rlmflow_stages::numerics::pins`)
/// replaces MKL's kernels by the chain GEMM at this CPU's widest lanes, or at
/// `RLMFLOW_GEMM_LANES` (what a check asks for to compare widths); unset leaves ATen's own.
/// Returns the lanes installed (0: none). `rlmflow-torch exec` installs it once, after the pins
/// are set and before the operator makes a tensor (its registry's kernel pin); every model
/// stage calls it again before it computes (a no-op then), as do `rlmflow-torch step` and the
/// tests. Asking for other lanes re-registers the kernels, which only the width test does,
/// between computations; the C++ side serialises registrations and reads the lanes atomically.
pub fn pin_gemm() -> anyhow::Result<usize> {
    let lanes = match std::env::var(GEMM_VARIABLE).ok().as_deref() {
        None | Some("") => 0,
        Some(CHAIN_GEMM) => match std::env::var(GEMM_LANES_VARIABLE).ok().filter(|v| !v.is_empty()) {
            None => chain_lanes_widest(),
            Some(asked) => {
                let lanes = asked.parse().map_err(|_| anyhow::anyhow!("{GEMM_LANES_VARIABLE}={asked}: 1, 8 or 16"))?;
                check_lanes(lanes)?;
                lanes
            }
        },
        Some(other) => bail!("{GEMM_VARIABLE}={other}: `{CHAIN_GEMM}`, or unset for ATen's own kernels"),
    };
    let mut installed = CHAIN_LANES.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    if *installed != lanes {
        checked(unsafe { rlmflow_chain_gemm_install(lanes as i32) }, "register the chain GEMM")?;
        *installed = lanes;
    }
    Ok(lanes)
}

/// A bfloat16 autocast region on `device`'s type, as `torch.autocast(device, torch.bfloat16)`:
/// open while the value lives. Leaving the outermost region drops autocast's low-precision copies
/// of the weights, so open one per forward pass (an optimiser step changes the weights in place).
pub struct Autocast {
    cuda: i32,
    previous: bool,
}

impl Autocast {
    pub fn enter(device: tch::Device) -> anyhow::Result<Autocast> {
        let cuda = is_cuda(device);
        let mut previous = false;
        checked(unsafe { rlmflow_autocast_enter(cuda, &mut previous) }, "enter autocast")?;
        Ok(Autocast { cuda, previous })
    }

    /// Whether a region is open on `device`'s type.
    pub fn enabled(device: tch::Device) -> bool {
        unsafe { rlmflow_autocast_enabled(is_cuda(device)) }
    }
}

impl Drop for Autocast {
    fn drop(&mut self) {
        // Leaving restores a flag and clears a cache: nothing in it can fail but allocation.
        let _ = checked(unsafe { rlmflow_autocast_exit(self.cuda, self.previous) }, "leave autocast");
    }
}

#[cfg(test)]
mod tests {
    use tch::{Device, Kind, Tensor};

    use super::*;

    #[test]
    fn autocast_computes_matmuls_in_bfloat16_inside_its_region_only() {
        let _generator = crate::generator();
        let a = Tensor::randn([4, 8], (Kind::Float, Device::Cpu));
        let b = Tensor::randn([8, 3], (Kind::Float, Device::Cpu));
        assert!(!Autocast::enabled(Device::Cpu));
        {
            let _region = Autocast::enter(Device::Cpu).unwrap();
            assert!(Autocast::enabled(Device::Cpu));
            assert_eq!(a.matmul(&b).kind(), Kind::BFloat16, "a matmul is on autocast's lower-precision list");
            assert_eq!(a.log_softmax(-1, Kind::Float).kind(), Kind::Float, "log_softmax stays in float32");
            {
                let _inner = Autocast::enter(Device::Cpu).unwrap();
            }
            assert!(Autocast::enabled(Device::Cpu), "leaving an inner region keeps the outer one");
        }
        assert!(!Autocast::enabled(Device::Cpu));
        assert_eq!(a.matmul(&b).kind(), Kind::Float);
    }

    fn refs(ts: &[Tensor]) -> Vec<&Tensor> {
        ts.iter().collect()
    }

    /// PyTorch's AdamW update and clip_grad_norm_, written out per parameter.
    fn by_hand(params: &[Tensor], grads: &[Tensor], lr: f64, wd: f64, max: f64) -> Vec<Tensor> {
        let total = grads.iter().map(|g| g.square().sum(Kind::Double)).fold(Tensor::zeros([], (Kind::Double, Device::Cpu)), |a, b| a + b).sqrt();
        let scale = (max / (total.double_value(&[]) + 1e-6)).min(1.0);
        let (b1, b2, eps) = (0.9f64, 0.999f64, 1e-8);
        params
            .iter()
            .zip(grads)
            .map(|(p, g)| {
                let g = g * scale;
                let m = &g * (1.0 - b1);
                let v = g.square() * (1.0 - b2);
                let (c1, c2) = (1.0 - b1, 1.0 - b2);
                p * (1.0 - lr * wd) - (m / c1) * lr / ((v / c2).sqrt() + eps)
            })
            .collect()
    }

    #[test]
    fn the_fused_adamw_step_and_foreach_clipping_are_pytorchs_update() {
        let _generator = crate::generator();
        tch::manual_seed(9);
        let params: Vec<Tensor> = [[3, 4], [5, 1]].iter().map(|s| Tensor::randn(*s, (Kind::Float, Device::Cpu))).collect();
        let grads: Vec<Tensor> = params.iter().map(|p| p.randn_like() * 10.0).collect();
        let expected = by_hand(&params, &grads, 0.01, 0.1, 1.0);
        foreach_clip(&refs(&grads), 1.0).unwrap();
        let norm = grads.iter().map(|g| g.square().sum(Kind::Float).double_value(&[])).sum::<f64>().sqrt();
        assert!((norm - 1.0).abs() < 1e-4, "clipped to norm 1: {norm}");
        let m: Vec<Tensor> = params.iter().map(Tensor::zeros_like).collect();
        let v: Vec<Tensor> = params.iter().map(Tensor::zeros_like).collect();
        let s = AdamWStep { step: 1, lr: 0.01, betas: (0.9, 0.999), weight_decay: 0.1, eps: 1e-8 };
        fused_adamw(&refs(&params), &refs(&grads), &refs(&m), &refs(&v), s).unwrap();
        for (p, e) in params.iter().zip(&expected) {
            assert!(p.allclose(e, 1e-5, 1e-6, false), "{p} against {e}");
        }
    }

    fn bits(t: &Tensor) -> Vec<u32> {
        Vec::<f32>::try_from(t.contiguous().flatten(0, -1)).unwrap().iter().map(|v| v.to_bits()).collect()
    }

    /// Every output one fused multiply-add chain over k in order, from 0: what each width must give.
    fn fma_chain(a: &Tensor, b: &Tensor) -> Vec<u32> {
        let (m, k, n) = (a.size()[0], a.size()[1], b.size()[1]);
        let a = Vec::<f32>::try_from(a.contiguous().flatten(0, -1)).unwrap();
        let b = Vec::<f32>::try_from(b.contiguous().flatten(0, -1)).unwrap();
        let mut out = Vec::new();
        for i in 0..m {
            for j in 0..n {
                let c = (0..k).fold(0f32, |c, l| a[(i * k + l) as usize].mul_add(b[(l * n + j) as usize], c));
                out.push(c.to_bits());
            }
        }
        out
    }

    #[test]
    fn the_chain_gemm_gives_the_same_bits_at_every_width_this_cpu_runs() {
        let _generator = crate::generator();
        tch::manual_seed(4);
        let widths: Vec<usize> = [1, 8, 16].into_iter().filter(|&l| l <= chain_lanes_widest()).collect();
        if widths.len() < 3 {
            eprintln!("this CPU runs the chain GEMM at {widths:?} lanes only: the other widths are compared where a CPU has them");
        }
        // Edges of every blocking: rows past a tile, columns past a panel, k past a packed block,
        // k = 0; and the layouts a model's products take (transposed, expanded).
        for (m, k, n) in [(1, 1, 1), (13, 257, 33), (25, 600, 70), (7, 0, 5), (64, 256, 16), (3, 31, 129)] {
            let a = Tensor::randn([m, k], (Kind::Float, Device::Cpu));
            let b = Tensor::randn([k, n], (Kind::Float, Device::Cpu));
            let mut layouts = vec![(a.tr().contiguous().tr(), b.tr().contiguous().tr())];
            if k > 0 {
                layouts.push((a.select(1, 0).unsqueeze(1).expand([m, k], false), b.select(0, 0).unsqueeze(0).expand([k, n], false)));
            }
            layouts.push((a, b));
            for (a, b) in &layouts {
                let expected = fma_chain(a, b);
                for &lanes in &widths {
                    let c = chain_mm(a, b, lanes).unwrap();
                    assert_eq!(c.size(), [m, n]);
                    assert!(bits(&c) == expected, "{m}x{k}x{n} at {lanes} lanes differs from the fma chain");
                }
            }
        }
        assert!(chain_mm(&Tensor::ones([2, 3], (Kind::Double, Device::Cpu)), &Tensor::ones([3, 2], (Kind::Double, Device::Cpu)), 1).is_err());
        let wrong = chain_mm(&Tensor::ones([2, 3], (Kind::Float, Device::Cpu)), &Tensor::ones([3, 2], (Kind::Float, Device::Cpu)), 4).unwrap_err();
        assert!(format!("{wrong}").contains("RLMFLOW_GEMM_LANES=4"), "{wrong}");
    }

    #[test]
    fn determinism_and_tf32_are_switches_libtorch_reports() {
        let _generator = crate::generator();
        set_deterministic(true).unwrap();
        assert!(deterministic());
        set_deterministic(false).unwrap();
        assert!(!deterministic());
        set_tf32(true).unwrap();
        assert!(tf32());
        set_tf32(false).unwrap();
        assert!(!tf32());
    }
}
