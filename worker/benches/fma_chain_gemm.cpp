// Whether float32 matrix products can give the same bits on AVX-512 and AVX2 machines at native
// speed (docs/numerics.md, "A GEMM whose bits do not depend on the vector width"): a kernel in
// which every C[i][j] is one fused multiply-add chain over k in order, vectorised across columns
// only, 16 lanes (AVX-512) or 8 (AVX2 and FMA), against libtorch's `at::mm` (MKL), one thread,
// on the laptop step's shapes (the towers' linears forward and backward, the caption decoder's
// logits). It checks the two kernels' bits against each other and against a scalar `fmaf`
// chain. It needs a CPU with AVX-512 (for `mkl` alone, any), g++ and libtorch's headers, and is
// not part of any build:
//
//   LT=$(cargo xtask libtorch)
//   g++ -O2 -std=c++17 -mavx2 -mfma -D_GLIBCXX_USE_CXX11_ABI=1 -I$LT/include \
//     -I$LT/include/torch/csrc/api/include worker/benches/fma_chain_gemm.cpp -o /tmp/fma_chain_gemm \
//     -L$LT/lib -Wl,-rpath,$LT/lib -Wl,--no-as-needed -ltorch_cpu -lc10
//   /tmp/fma_chain_gemm                       # MKL unpinned (native) and both chain kernels
//   MKL_CBWR=AVX2 /tmp/fma_chain_gemm mkl     # MKL on the portable pin's branch alone
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <immintrin.h>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <vector>

// C (M x N) = A (M x K, row-major) * B (K x N, row-major), B packed in panels of NR columns.
static void pack_b(const float* B, int K, int N, int NR, std::vector<float>& P) {
  int panels = (N + NR - 1) / NR;
  P.assign((size_t)panels * K * NR, 0.f);
  for (int p = 0; p < panels; p++)
    for (int k = 0; k < K; k++)
      for (int j = 0; j < NR && p * NR + j < N; j++) P[((size_t)p * K + k) * NR + j] = B[(size_t)k * N + p * NR + j];
}

__attribute__((target("avx512f"))) static void gemm512(const float* A, const float* P, float* C, int M, int K, int N) {
  const int NR = 32, MR = 14;
  int panels = (N + NR - 1) / NR;
  for (int p = 0; p < panels; p++) {
    const float* bp = P + (size_t)p * K * NR;
    int cols = std::min(NR, N - p * NR);
    __mmask16 m0 = cols >= 16 ? 0xFFFF : (__mmask16)((1u << cols) - 1);
    __mmask16 m1 = cols >= 32 ? 0xFFFF : cols > 16 ? (__mmask16)((1u << (cols - 16)) - 1) : 0;
    int i = 0;
    for (; i + MR <= M; i += MR) {
      __m512 acc[MR][2];
      for (int r = 0; r < MR; r++) acc[r][0] = acc[r][1] = _mm512_setzero_ps();
      const float* a = A + (size_t)i * K;
      for (int k = 0; k < K; k++) {
        __m512 b0 = _mm512_loadu_ps(bp + (size_t)k * NR), b1 = _mm512_loadu_ps(bp + (size_t)k * NR + 16);
#pragma GCC unroll 14
        for (int r = 0; r < MR; r++) {
          __m512 av = _mm512_set1_ps(a[(size_t)r * K + k]);
          acc[r][0] = _mm512_fmadd_ps(av, b0, acc[r][0]);
          acc[r][1] = _mm512_fmadd_ps(av, b1, acc[r][1]);
        }
      }
      for (int r = 0; r < MR; r++) {
        _mm512_mask_storeu_ps(C + (size_t)(i + r) * N + p * NR, m0, acc[r][0]);
        _mm512_mask_storeu_ps(C + (size_t)(i + r) * N + p * NR + 16, m1, acc[r][1]);
      }
    }
    for (; i < M; i++) {
      __m512 a0 = _mm512_setzero_ps(), a1 = _mm512_setzero_ps();
      for (int k = 0; k < K; k++) {
        __m512 av = _mm512_set1_ps(A[(size_t)i * K + k]);
        a0 = _mm512_fmadd_ps(av, _mm512_loadu_ps(bp + (size_t)k * NR), a0);
        a1 = _mm512_fmadd_ps(av, _mm512_loadu_ps(bp + (size_t)k * NR + 16), a1);
      }
      _mm512_mask_storeu_ps(C + (size_t)i * N + p * NR, m0, a0);
      _mm512_mask_storeu_ps(C + (size_t)i * N + p * NR + 16, m1, a1);
    }
  }
}

__attribute__((target("avx2,fma"))) static void gemm256(const float* A, const float* P, float* C, int M, int K, int N) {
  const int NR = 16, MR = 6;
  int panels = (N + NR - 1) / NR;
  float tmp[16];
  for (int p = 0; p < panels; p++) {
    const float* bp = P + (size_t)p * K * NR;
    int cols = std::min(NR, N - p * NR);
    auto store = [&](float* dst, __m256 v0, __m256 v1) {
      if (cols == NR) { _mm256_storeu_ps(dst, v0); _mm256_storeu_ps(dst + 8, v1); return; }
      _mm256_storeu_ps(tmp, v0); _mm256_storeu_ps(tmp + 8, v1); memcpy(dst, tmp, cols * sizeof(float));
    };
    int i = 0;
    for (; i + MR <= M; i += MR) {
      __m256 acc[MR][2];
      for (int r = 0; r < MR; r++) acc[r][0] = acc[r][1] = _mm256_setzero_ps();
      const float* a = A + (size_t)i * K;
      for (int k = 0; k < K; k++) {
        __m256 b0 = _mm256_loadu_ps(bp + (size_t)k * NR), b1 = _mm256_loadu_ps(bp + (size_t)k * NR + 8);
#pragma GCC unroll 6
        for (int r = 0; r < MR; r++) {
          __m256 av = _mm256_broadcast_ss(a + (size_t)r * K + k);
          acc[r][0] = _mm256_fmadd_ps(av, b0, acc[r][0]);
          acc[r][1] = _mm256_fmadd_ps(av, b1, acc[r][1]);
        }
      }
      for (int r = 0; r < MR; r++) store(C + (size_t)(i + r) * N + p * NR, acc[r][0], acc[r][1]);
    }
    for (; i < M; i++) {
      __m256 a0 = _mm256_setzero_ps(), a1 = _mm256_setzero_ps();
      for (int k = 0; k < K; k++) {
        __m256 av = _mm256_broadcast_ss(A + (size_t)i * K + k);
        a0 = _mm256_fmadd_ps(av, _mm256_loadu_ps(bp + (size_t)k * NR), a0);
        a1 = _mm256_fmadd_ps(av, _mm256_loadu_ps(bp + (size_t)k * NR + 8), a1);
      }
      store(C + (size_t)i * N + p * NR, a0, a1);
    }
  }
}

template <class F> static double best_ms(F f, int reps) {
  double best = 1e30;
  for (int r = 0; r < reps; r++) {
    auto t0 = std::chrono::steady_clock::now();
    f();
    best = std::min(best, std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
  }
  return best;
}

int main(int argc, char** argv) {
  at::set_num_threads(1);
  bool mkl_only = argc > 1 && !strcmp(argv[1], "mkl");
  if (!mkl_only && !__builtin_cpu_supports("avx512f")) {
    fprintf(stderr, "this CPU has no AVX-512: the 16-lane kernel cannot run here (`mkl` times MKL alone)\n");
    return 2;
  }
  int shapes[][3] = {{8320, 128, 384}, {8320, 128, 128}, {8320, 128, 512}, {8320, 512, 128}, {8320, 384, 128},
                     {128, 8320, 384}, {128, 8320, 128}, {128, 8320, 512}, {512, 8320, 128}, {4096, 128, 384}, {2240, 128, 629}};
  double tot_mkl = 0, tot_512 = 0, tot_256 = 0;
  bool all_same = true;
  for (auto& s : shapes) {
    int M = s[0], K = s[1], N = s[2];
    at::manual_seed(M + K + N);
    auto A = at::randn({M, K}), B = at::randn({K, N});
    double gflop = 2.0 * M * K * N / 1e9;
    at::Tensor Cm;
    double tm = best_ms([&] { Cm = at::mm(A, B); }, 5);
    tot_mkl += tm;
    if (mkl_only) { printf("%5d %5d %5d  mkl %7.2f ms %6.1f GF/s\n", M, K, N, tm, gflop / tm * 1e3); continue; }
    // B's packing is timed with each kernel: a product of ATen's would pack on every call.
    std::vector<float> P16, P32;
    std::vector<float> C16((size_t)M * N), C32((size_t)M * N);
    double t512 = best_ms([&] { pack_b(B.data_ptr<float>(), K, N, 32, P32); gemm512(A.data_ptr<float>(), P32.data(), C32.data(), M, K, N); }, 5);
    double t256 = best_ms([&] { pack_b(B.data_ptr<float>(), K, N, 16, P16); gemm256(A.data_ptr<float>(), P16.data(), C16.data(), M, K, N); }, 5);
    tot_512 += t512; tot_256 += t256;
    // The same bits at both widths, and at 200 sampled outputs a scalar fmaf chain's.
    bool same = !memcmp(C16.data(), C32.data(), C16.size() * 4);
    for (int t = 0; t < 200; t++) {
      int i = (t * 7919) % M, j = (t * 104729) % N;
      float c = 0.f;
      for (int k = 0; k < K; k++) c = std::fma(A.data_ptr<float>()[(size_t)i * K + k], B.data_ptr<float>()[(size_t)k * N + j], c);
      uint32_t x, y; memcpy(&x, &c, 4); memcpy(&y, &C32[(size_t)i * N + j], 4);
      same = same && x == y;
    }
    all_same = all_same && same;
    double err = (at::from_blob(C32.data(), {M, N}) - Cm).abs().max().item<double>();
    printf("%5d %5d %5d  mkl %7.2f ms %6.1f GF/s | avx512 chain %7.2f ms %6.1f | avx2 chain %7.2f ms %6.1f | same bits %s | max |diff| vs mkl %.2e\n", M, K, N, tm,
           gflop / tm * 1e3, t512, gflop / t512 * 1e3, t256, gflop / t256 * 1e3, same ? "yes" : "NO", err);
  }
  if (mkl_only) printf("total mkl %.1f ms\n", tot_mkl);
  else printf("total mkl %.1f ms, avx512 chain %.1f ms, avx2 chain %.1f ms, all same bits: %s\n", tot_mkl, tot_512, tot_256, all_same ? "yes" : "NO");
}
