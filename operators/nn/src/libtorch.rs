//! libtorch's global settings that tch 0.24 does not expose, through the few C++ functions of
//! `cpp/torch_settings.cpp` (compiled by `build.rs` against the same headers): deterministic
//! algorithms, TF32, and bfloat16 autocast on the CPU or CUDA (tch's `autocast` reaches CUDA's
//! alone, in float16).

use std::ffi::{CStr, c_char};

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

    #[test]
    fn determinism_and_tf32_are_switches_libtorch_reports() {
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
