//! What libtorch has and tch 0.24 does not expose, through the few C++ functions of
//! `cpp/torch_settings.cpp` (compiled by `build.rs` against the same headers): deterministic
//! algorithms, TF32, bfloat16 autocast on the CPU or CUDA (tch's `autocast` reaches CUDA's
//! alone, in float16), and the multi-tensor kernels of PyTorch's fused AdamW and gradient
//! clipping.

use std::ffi::{CStr, c_char, c_void};

use tch::Tensor;

use anyhow::bail;

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
