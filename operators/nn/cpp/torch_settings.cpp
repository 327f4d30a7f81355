// libtorch's global settings that tch 0.24 does not expose: deterministic algorithms, TF32,
// and autocast per device type with its dtype (tch's `autocast` reaches CUDA's only, in its
// default float16). Each call returns nullptr, or a message the caller frees with
// `rlmflow_free_message`; no C++ exception crosses into Rust.
#include <ATen/Context.h>
#include <ATen/autocast_mode.h>
#include <c10/core/ScalarType.h>

#include <cstdlib>
#include <cstring>
#include <exception>

namespace {
template <typename F>
char* guarded(F f) {
  try {
    f();
    return nullptr;
  } catch (const std::exception& e) {
    return strdup(e.what());
  } catch (...) {
    return strdup("an unknown C++ exception");
  }
}

at::DeviceType device_type(int cuda) { return cuda ? at::kCUDA : at::kCPU; }
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
}
