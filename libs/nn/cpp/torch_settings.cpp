// What libtorch has and tch 0.24 does not expose: deterministic algorithms, TF32, autocast per
// device type with its dtype (tch's `autocast` reaches CUDA's only, in its default float16), and
// the multi-tensor optimiser kernels PyTorch's AdamW(fused=True) and clip_grad_norm_ run.
// Each call returns nullptr, or a message the caller frees with `rlmflow_free_message`; no C++
// exception crosses into Rust. Tensors arrive as tch's handles (`at::Tensor*`).
#include <ATen/Context.h>
#include <ATen/autocast_mode.h>
#include <ATen/ops/_foreach_mul.h>
#include <ATen/ops/_foreach_norm.h>
#include <ATen/ops/_fused_adamw.h>
#include <ATen/ops/full.h>
#include <ATen/ops/stack.h>
#include <c10/core/ScalarType.h>

#include <cstdlib>
#include <vector>

#include "guarded.h"

namespace {
at::DeviceType device_type(int cuda) { return cuda ? at::kCUDA : at::kCPU; }

std::vector<at::Tensor> tensors(at::Tensor** handles, int n) {
  std::vector<at::Tensor> out;
  out.reserve(n);
  for (int i = 0; i < n; i++) out.push_back(*handles[i]);
  return out;
}
}  // namespace

extern "C" {
void rlmflow_free_message(char* message) { free(message); }

// Deterministic algorithms (an op without a deterministic kernel raises), deterministic cuDNN,
// and no cuDNN autotuning.
char* rlmflow_set_deterministic(bool on) {
  return guarded([&] {
    at::globalContext().setDeterministicAlgorithms(on, false);
    at::globalContext().setDeterministicCuDNN(on);
    at::globalContext().setBenchmarkCuDNN(false);
  });
}

bool rlmflow_deterministic() { return at::globalContext().deterministicAlgorithms(); }

// TF32 in cuBLAS matmuls and cuDNN convolutions (libtorch allows it in cuDNN by default).
char* rlmflow_set_tf32(bool on) {
  return guarded([&] {
    at::globalContext().setAllowTF32CuBLAS(on);
    at::globalContext().setAllowTF32CuDNN(on);
  });
}

bool rlmflow_tf32_cublas() { return at::globalContext().allowTF32CuBLAS(); }

// Enters an autocast region on the CPU (cuda = 0) or CUDA (cuda = 1) in bfloat16, as
// `torch.autocast(device, torch.bfloat16)` does; `previous` receives whether it was on.
char* rlmflow_autocast_enter(int cuda, bool* previous) {
  return guarded([&] {
    auto type = device_type(cuda);
    *previous = at::autocast::is_autocast_enabled(type);
    at::autocast::set_autocast_enabled(type, true);
    at::autocast::set_autocast_dtype(type, at::kBFloat16);
    at::autocast::increment_nesting();
  });
}

// Leaves the region: restores `previous` and, at the outermost exit, drops the cached
// low-precision copies of the weights (an optimiser step changes them in place).
char* rlmflow_autocast_exit(int cuda, bool previous) {
  return guarded([&] {
    if (at::autocast::decrement_nesting() == 0) {
      at::autocast::clear_cache();
    }
    at::autocast::set_autocast_enabled(device_type(cuda), previous);
  });
}

bool rlmflow_autocast_enabled(int cuda) { return at::autocast::is_autocast_enabled(device_type(cuda)); }

// One AdamW step over `n` parameters in PyTorch's fused kernel (torch.optim.AdamW(fused=True)):
// decoupled weight decay, the moments updated in place, bias corrections for step number `step`.
char* rlmflow_fused_adamw(at::Tensor** params, at::Tensor** grads, at::Tensor** exp_avgs, at::Tensor** exp_avg_sqs, int n,
                          double step, double lr, double beta1, double beta2, double weight_decay, double eps) {
  return guarded([&] {
    if (n == 0) return;
    auto p = tensors(params, n);
    // The kernel reads each parameter's step count; one tensor serves them all.
    auto count = at::full({}, step, p[0].options().dtype(at::kFloat));
    std::vector<at::Tensor> steps(n, count);
    at::_fused_adamw_(p, tensors(grads, n), tensors(exp_avgs, n), tensors(exp_avg_sqs, n), {}, steps, lr, beta1, beta2,
                      weight_decay, eps, false, false);
  });
}

// Scales `grads` in place so their global L2 norm is at most `max`, as
// torch.nn.utils.clip_grad_norm_(foreach=True) does, with no wait for the device.
char* rlmflow_foreach_clip(at::Tensor** grads, int n, double max) {
  return guarded([&] {
    auto g = tensors(grads, n);
    auto norm = at::stack(at::_foreach_norm(g, 2)).norm();
    at::_foreach_mul_(g, (max / (norm + 1e-6)).clamp_max(1.0));
  });
}
}
