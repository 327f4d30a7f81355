// Float32 matrix products whose bits do not depend on the machine's vector width or vendor: every
// output is one fused multiply-add chain over k in order, c = fma(a[i][k], b[k][j], c) from
// c = 0, vectorised across columns only. 16 lanes (AVX-512), 8 (AVX2 and FMA) and a scalar
// `std::fma` loop give the same bits, so an AVX-512 machine keeps its width and computes what an
// AVX2 machine of either vendor computes (MKL's kernels, which ATen's matrix products otherwise
// call, choose their reduction order by CPU and vendor). Registered over ATen's CPU kernels for
// `mm`, `addmm`, `bmm` and `baddbmm` (their out and in-place forms too) when the portable numerics
// ask for it (`src/libtorch.rs`, `install_chain_gemm`); other dtypes go to ATen's own kernels.
// The kernel: B is packed per block of KC rows into panels of NR columns, each tile of MR rows
// by one panel keeps its accumulators in registers over the block, and the next block continues
// the chain from C (a float accumulator stored and loaded: the same bits). docs/numerics.md
// has the measurements.
#include <ATen/core/Tensor.h>
#include <ATen/Parallel.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/addmm_cpu_dispatch.h>
#include <ATen/ops/baddbmm_cpu_dispatch.h>
#include <ATen/ops/bmm_cpu_dispatch.h>
#include <ATen/ops/mm_cpu_dispatch.h>
#include <ATen/native/Resize.h>
#include <c10/util/Exception.h>
#include <torch/library.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstring>
#include <memory>
#include <mutex>
#include <vector>

#include "guarded.h"

#if defined(__x86_64__)
#include <immintrin.h>
#endif

namespace {

// k rows of B per packed block: a block of 32-column panels stays in L2 while rows of A pass.
constexpr int64_t KC = 256;

// Lanes of the kernel in use: 1, 8 or 16. Written only by `rlmflow_chain_gemm_install` (before a
// stage computes), read by every product on any of ATen's threads.
std::atomic<int> chosen_lanes{1};

int lanes_in_use() { return chosen_lanes.load(std::memory_order_relaxed); }

// Element (r, c) of a strided float matrix is p[r * s0 + c * s1].
struct View {
  const float* p;
  int64_t s0, s1;
};

// B's rows [k0, k1) in panels of `nr` columns, k-major within a panel, zeros past N.
void pack_block(View b, int64_t k0, int64_t k1, int64_t n, int64_t nr, float* out) {
  const int64_t panels = (n + nr - 1) / nr;
  for (int64_t p = 0; p < panels; p++) {
    const int64_t cols = std::min(nr, n - p * nr);
    float* o = out + p * (k1 - k0) * nr;
    for (int64_t k = k0; k < k1; k++, o += nr) {
      const float* row = b.p + k * b.s0 + p * nr * b.s1;
      if (b.s1 == 1) {
        std::memcpy(o, row, cols * sizeof(float));
      } else {
        for (int64_t j = 0; j < cols; j++) o[j] = row[j * b.s1];
      }
      std::fill(o + cols, o + nr, 0.f);
    }
  }
}

// One tile: `rows` rows of A from `a` by `cols` columns of C from `c`, over the packed panel `b`
// of k in [k0, k1); when k0 > 0 the chain continues from C.
void tile_scalar(int rows, const float* a, View av, const float* b, int64_t nr, float* c, int64_t ldc, int64_t k0, int64_t k1,
                 int64_t cols) {
  for (int r = 0; r < rows; r++)
    for (int64_t j = 0; j < cols; j++) {
      float s = k0 ? c[r * ldc + j] : 0.f;
      for (int64_t k = k0; k < k1; k++) s = std::fma(a[r * av.s0 + k * av.s1], b[(k - k0) * nr + j], s);
      c[r * ldc + j] = s;
    }
}

#if defined(__x86_64__)
// Named accumulators: GCC keeps an array of vectors on the stack, storing it at every step.
#define ROWS6(X) X(0) X(1) X(2) X(3) X(4) X(5)
#define ROWS12(X) ROWS6(X) X(6) X(7) X(8) X(9) X(10) X(11)

template <int R>
__attribute__((target("avx512f"))) void tile512(const float* a, View av, const float* b, float* c, int64_t ldc, int64_t k0, int64_t k1,
                                                int64_t cols) {
  const __mmask16 m0 = cols >= 16 ? 0xFFFF : (__mmask16)((1u << cols) - 1);
  const __mmask16 m1 = cols >= 32 ? 0xFFFF : cols > 16 ? (__mmask16)((1u << (cols - 16)) - 1) : 0;
#define DECL(r)                                                        \
  __m512 x##r = _mm512_setzero_ps(), y##r = _mm512_setzero_ps();       \
  const float* a##r = a + (r)*av.s0;                                   \
  if ((r) < R && k0 && cols == 32) {                                   \
    x##r = _mm512_loadu_ps(c + (r)*ldc);                               \
    y##r = _mm512_loadu_ps(c + (r)*ldc + 16);                          \
  } else if ((r) < R && k0) {                                          \
    x##r = _mm512_maskz_loadu_ps(m0, c + (r)*ldc);                     \
    y##r = _mm512_maskz_loadu_ps(m1, c + (r)*ldc + 16);                \
  }
  ROWS12(DECL)
  for (int64_t k = k0; k < k1; k++, b += 32) {
    const __m512 b0 = _mm512_loadu_ps(b), b1 = _mm512_loadu_ps(b + 16);
#define STEP(r)                                          \
  if ((r) < R) {                                         \
    const __m512 s = _mm512_set1_ps(a##r[k * av.s1]);    \
    x##r = _mm512_fmadd_ps(s, b0, x##r);                 \
    y##r = _mm512_fmadd_ps(s, b1, y##r);                 \
  }
    ROWS12(STEP)
  }
  // Plain stores where the panel is full, masked ones at the edge only.
#define PUT(r)                                                \
  if ((r) < R && cols == 32) {                                \
    _mm512_storeu_ps(c + (r)*ldc, x##r);                      \
    _mm512_storeu_ps(c + (r)*ldc + 16, y##r);                 \
  } else if ((r) < R) {                                       \
    _mm512_mask_storeu_ps(c + (r)*ldc, m0, x##r);             \
    _mm512_mask_storeu_ps(c + (r)*ldc + 16, m1, y##r);        \
  }
  ROWS12(PUT)
#undef DECL
#undef STEP
#undef PUT
}

template <int R>
__attribute__((target("avx2,fma"))) void tile256(const float* a, View av, const float* b, float* c, int64_t ldc, int64_t k0, int64_t k1,
                                                 int64_t cols) {
  const __m256i l0 = _mm256_cmpgt_epi32(_mm256_set1_epi32((int)cols), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
  const __m256i l1 = _mm256_cmpgt_epi32(_mm256_set1_epi32((int)cols), _mm256_setr_epi32(8, 9, 10, 11, 12, 13, 14, 15));
#define DECL(r)                                                  \
  __m256 x##r = _mm256_setzero_ps(), y##r = _mm256_setzero_ps(); \
  const float* a##r = a + (r)*av.s0;                             \
  if ((r) < R && k0 && cols == 16) {                             \
    x##r = _mm256_loadu_ps(c + (r)*ldc);                         \
    y##r = _mm256_loadu_ps(c + (r)*ldc + 8);                     \
  } else if ((r) < R && k0) {                                    \
    x##r = _mm256_maskload_ps(c + (r)*ldc, l0);                  \
    y##r = _mm256_maskload_ps(c + (r)*ldc + 8, l1);              \
  }
  ROWS6(DECL)
  for (int64_t k = k0; k < k1; k++, b += 16) {
    const __m256 b0 = _mm256_loadu_ps(b), b1 = _mm256_loadu_ps(b + 8);
#define STEP(r)                                            \
  if ((r) < R) {                                           \
    const __m256 s = _mm256_broadcast_ss(a##r + k * av.s1); \
    x##r = _mm256_fmadd_ps(s, b0, x##r);                   \
    y##r = _mm256_fmadd_ps(s, b1, y##r);                   \
  }
    ROWS6(STEP)
  }
  // Plain stores where the panel is full: AVX2's masked store is slow on AMD.
#define PUT(r)                                         \
  if ((r) < R && cols == 16) {                         \
    _mm256_storeu_ps(c + (r)*ldc, x##r);               \
    _mm256_storeu_ps(c + (r)*ldc + 8, y##r);           \
  } else if ((r) < R) {                                \
    _mm256_maskstore_ps(c + (r)*ldc, l0, x##r);        \
    _mm256_maskstore_ps(c + (r)*ldc + 8, l1, y##r);    \
  }
  ROWS6(PUT)
#undef DECL
#undef STEP
#undef PUT
}

void tile16(int rows, const float* a, View av, const float* b, float* c, int64_t ldc, int64_t k0, int64_t k1, int64_t cols) {
  switch (rows) {
#define CASE(r)                                           \
  case (r) + 1:                                           \
    tile512<(r) + 1>(a, av, b, c, ldc, k0, k1, cols);     \
    break;
    ROWS12(CASE)
#undef CASE
  }
}

void tile8(int rows, const float* a, View av, const float* b, float* c, int64_t ldc, int64_t k0, int64_t k1, int64_t cols) {
  switch (rows) {
#define CASE(r)                                           \
  case (r) + 1:                                           \
    tile256<(r) + 1>(a, av, b, c, ldc, k0, k1, cols);     \
    break;
    ROWS6(CASE)
#undef CASE
  }
}
#endif

// C (m x n, row stride ldc) = A (m x k) B (k x n) on this thread.
void gemm_serial(View a, View b, float* c, int64_t ldc, int64_t m, int64_t k, int64_t n, int lanes) {
  if (k == 0) {
    for (int64_t i = 0; i < m; i++) std::fill(c + i * ldc, c + i * ldc + n, 0.f);
    return;
  }
  // Panel width and tile height: two vectors of columns by as many rows as the registers hold.
  const int64_t nr = lanes == 1 ? 16 : 2 * lanes, mr = lanes == 16 ? 12 : 6;
  const int64_t panels = (n + nr - 1) / nr;
  thread_local std::vector<float> packed;
  packed.resize(panels * std::min(k, KC) * nr);
  for (int64_t k0 = 0; k0 < k; k0 += KC) {
    const int64_t k1 = std::min(k, k0 + KC);
    pack_block(b, k0, k1, n, nr, packed.data());
    for (int64_t i = 0; i < m; i += mr) {
      const int rows = (int)std::min(mr, m - i);
      const float* ap = a.p + i * a.s0;
      for (int64_t p = 0; p < panels; p++) {
        const float* bp = packed.data() + p * (k1 - k0) * nr;
        float* cp = c + i * ldc + p * nr;
        const int64_t cols = std::min(nr, n - p * nr);
#if defined(__x86_64__)
        if (lanes == 16) {
          tile16(rows, ap, a, bp, cp, ldc, k0, k1, cols);
          continue;
        }
        if (lanes == 8) {
          tile8(rows, ap, a, bp, cp, ldc, k0, k1, cols);
          continue;
        }
#endif
        tile_scalar(rows, ap, a, bp, nr, cp, ldc, k0, k1, cols);
      }
    }
  }
}

// C = A B over ATen's threads, split by rows (each output's chain is the same however split).
void gemm(View a, View b, float* c, int64_t ldc, int64_t m, int64_t k, int64_t n, int lanes) {
  const int64_t grain = std::max<int64_t>(48, (m + at::get_num_threads() - 1) / std::max(1, at::get_num_threads()));
  at::parallel_for(0, m, grain, [&](int64_t begin, int64_t end) {
    gemm_serial({a.p + begin * a.s0, a.s0, a.s1}, b, c + begin * ldc, ldc, end - begin, k, n, lanes);
  });
}

bool is_float(const at::Tensor& t) { return t.scalar_type() == at::kFloat && t.layout() == at::kStrided; }

View view(const at::Tensor& t) { return {t.const_data_ptr<float>(), t.stride(0), t.stride(1)}; }

// a (m x k) times b (k x n), a new contiguous float tensor.
at::Tensor product(const at::Tensor& a, const at::Tensor& b, int lanes) {
  TORCH_CHECK(a.dim() == 2 && b.dim() == 2, "matrix product: both arguments must be 2-D, got ", a.dim(), "-D and ", b.dim(), "-D");
  TORCH_CHECK(a.size(1) == b.size(0), "mat1 and mat2 shapes cannot be multiplied (", a.size(0), "x", a.size(1), " and ", b.size(0), "x",
              b.size(1), ")");
  auto c = at::empty({a.size(0), b.size(1)}, a.options());
  if (c.numel() > 0) gemm(view(a), view(b), c.data_ptr<float>(), b.size(1), a.size(0), a.size(1), b.size(1), lanes);
  return c;
}

// Batched: a (batch x m x k) times b (batch x k x n).
at::Tensor batched(const at::Tensor& a, const at::Tensor& b, int lanes) {
  TORCH_CHECK(a.dim() == 3 && b.dim() == 3, "batch1 and batch2 must be 3-D tensors, got ", a.dim(), "-D and ", b.dim(), "-D");
  TORCH_CHECK(a.size(0) == b.size(0) && a.size(2) == b.size(1), "Expected size for first two dimensions of batch2 tensor to be: [",
              a.size(0), ", ", a.size(2), "] but got: [", b.size(0), ", ", b.size(1), "].");
  const int64_t batch = a.size(0), m = a.size(1), k = a.size(2), n = b.size(2);
  auto c = at::empty({batch, m, n}, a.options());
  if (c.numel() == 0) return c;
  const float *pa = a.const_data_ptr<float>(), *pb = b.const_data_ptr<float>();
  float* pc = c.data_ptr<float>();
  auto one = [&](int64_t t) {
    gemm_serial({pa + t * a.stride(0), a.stride(1), a.stride(2)}, {pb + t * b.stride(0), b.stride(1), b.stride(2)}, pc + t * m * n, n, m, k,
                n, lanes);
  };
  if (batch >= at::get_num_threads()) {
    at::parallel_for(0, batch, 1, [&](int64_t begin, int64_t end) {
      for (int64_t t = begin; t < end; t++) one(t);
    });
  } else {
    for (int64_t t = 0; t < batch; t++)
      gemm({pa + t * a.stride(0), a.stride(1), a.stride(2)}, {pb + t * b.stride(0), b.stride(1), b.stride(2)}, pc + t * m * n, n, m, k, n,
           lanes);
  }
  return c;
}

// beta * self + alpha * p, with ATen's elementwise kernels at alpha = 1 (the same bits at every
// vector width); self broadcasts to p's shape and is not read when beta is 0.
at::Tensor epilogue(at::Tensor p, const at::Tensor& self, const at::Scalar& beta, const at::Scalar& alpha) {
  if (alpha.toDouble() != 1.0) p.mul_(alpha);
  if (beta.toDouble() == 0.0) return p;
  return beta.toDouble() == 1.0 ? p.add_(self) : p.add_(self.mul(beta));
}

// An `out` form's result: `p` written into `out`, resized as ATen's kernels resize it.
at::Tensor& into(at::Tensor& out, const at::Tensor& p) {
  at::native::resize_output(out, p.sizes());
  return out.copy_(p);
}

at::Tensor mm(const at::Tensor& self, const at::Tensor& mat2) {
  if (!is_float(self) || !is_float(mat2)) return at::cpu::mm(self, mat2);
  return product(self, mat2, lanes_in_use());
}

at::Tensor& mm_out(const at::Tensor& self, const at::Tensor& mat2, at::Tensor& out) {
  if (!is_float(self) || !is_float(mat2) || !is_float(out)) return at::cpu::mm_outf(self, mat2, out);
  return into(out, product(self, mat2, lanes_in_use()));
}

at::Tensor addmm(const at::Tensor& self, const at::Tensor& mat1, const at::Tensor& mat2, const at::Scalar& beta, const at::Scalar& alpha) {
  if (!is_float(self) || !is_float(mat1) || !is_float(mat2)) return at::cpu::addmm(self, mat1, mat2, beta, alpha);
  return epilogue(product(mat1, mat2, lanes_in_use()), self, beta, alpha);
}

at::Tensor& addmm_out(const at::Tensor& self, const at::Tensor& mat1, const at::Tensor& mat2, const at::Scalar& beta, const at::Scalar& alpha,
                      at::Tensor& out) {
  if (!is_float(self) || !is_float(mat1) || !is_float(mat2) || !is_float(out)) return at::cpu::addmm_outf(self, mat1, mat2, beta, alpha, out);
  return into(out, epilogue(product(mat1, mat2, lanes_in_use()), self, beta, alpha));
}

at::Tensor& addmm_(at::Tensor& self, const at::Tensor& mat1, const at::Tensor& mat2, const at::Scalar& beta, const at::Scalar& alpha) {
  if (!is_float(self) || !is_float(mat1) || !is_float(mat2)) return at::cpu::addmm_(self, mat1, mat2, beta, alpha);
  return self.copy_(epilogue(product(mat1, mat2, lanes_in_use()), self, beta, alpha));
}

at::Tensor bmm(const at::Tensor& self, const at::Tensor& mat2) {
  if (!is_float(self) || !is_float(mat2)) return at::cpu::bmm(self, mat2);
  return batched(self, mat2, lanes_in_use());
}

at::Tensor& bmm_out(const at::Tensor& self, const at::Tensor& mat2, at::Tensor& out) {
  if (!is_float(self) || !is_float(mat2) || !is_float(out)) return at::cpu::bmm_outf(self, mat2, out);
  return into(out, batched(self, mat2, lanes_in_use()));
}

at::Tensor baddbmm(const at::Tensor& self, const at::Tensor& b1, const at::Tensor& b2, const at::Scalar& beta, const at::Scalar& alpha) {
  if (!is_float(self) || !is_float(b1) || !is_float(b2)) return at::cpu::baddbmm(self, b1, b2, beta, alpha);
  return epilogue(batched(b1, b2, lanes_in_use()), self, beta, alpha);
}

at::Tensor& baddbmm_out(const at::Tensor& self, const at::Tensor& b1, const at::Tensor& b2, const at::Scalar& beta, const at::Scalar& alpha,
                        at::Tensor& out) {
  if (!is_float(self) || !is_float(b1) || !is_float(b2) || !is_float(out)) return at::cpu::baddbmm_outf(self, b1, b2, beta, alpha, out);
  return into(out, epilogue(batched(b1, b2, lanes_in_use()), self, beta, alpha));
}

at::Tensor& baddbmm_(at::Tensor& self, const at::Tensor& b1, const at::Tensor& b2, const at::Scalar& beta, const at::Scalar& alpha) {
  if (!is_float(self) || !is_float(b1) || !is_float(b2)) return at::cpu::baddbmm_(self, b1, b2, beta, alpha);
  return self.copy_(epilogue(batched(b1, b2, lanes_in_use()), self, beta, alpha));
}

// The registration; dropping it restores ATen's kernels. `registration` serialises installs.
std::unique_ptr<torch::Library> registered;
std::mutex registration;

// Replacing ATen's kernels is the point, so the dispatcher's warning that it happened is not
// passed on.
struct Silent : c10::WarningHandler {
  void process(const c10::Warning&) override {}
};

int widest_lanes() {
#if defined(__x86_64__)
  if (__builtin_cpu_supports("avx512f")) return 16;
  if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma")) return 8;
#endif
  return 1;
}
}  // namespace

extern "C" {
// The widest kernel this CPU runs: 16, 8 or 1 lanes.
int rlmflow_chain_gemm_widest() { return widest_lanes(); }

// Registers the chain kernels over ATen's CPU matrix products at `lanes` (1, 8 or 16; at most
// the widest); lanes = 0 removes them. The caller checks `lanes` first.
char* rlmflow_chain_gemm_install(int lanes) {
  return guarded([&] {
    std::lock_guard<std::mutex> held(registration);
    registered.reset();
    if (lanes == 0) return;
    chosen_lanes.store(lanes, std::memory_order_relaxed);
    Silent silent;
    c10::WarningUtils::WarningHandlerGuard quiet(&silent);
    registered = std::make_unique<torch::Library>(torch::Library::IMPL, "aten", c10::DispatchKey::CPU, __FILE__, __LINE__);
    registered->impl("mm", TORCH_FN(mm));
    registered->impl("mm.out", TORCH_FN(mm_out));
    registered->impl("addmm", TORCH_FN(addmm));
    registered->impl("addmm.out", TORCH_FN(addmm_out));
    registered->impl("addmm_", TORCH_FN(addmm_));
    registered->impl("bmm", TORCH_FN(bmm));
    registered->impl("bmm.out", TORCH_FN(bmm_out));
    registered->impl("baddbmm", TORCH_FN(baddbmm));
    registered->impl("baddbmm.out", TORCH_FN(baddbmm_out));
    registered->impl("baddbmm_", TORCH_FN(baddbmm_));
  });
}

// The chain product of 2-D float tensors a and b at `lanes`, whether installed or not (for the
// tests that compare widths); *out receives a new tensor handle.
char* rlmflow_chain_mm(const at::Tensor* a, const at::Tensor* b, int lanes, at::Tensor** out) {
  return guarded([&] {
    TORCH_CHECK(is_float(*a) && is_float(*b), "the chain product takes float32 tensors");
    *out = new at::Tensor(product(*a, *b, lanes));
  });
}
}
