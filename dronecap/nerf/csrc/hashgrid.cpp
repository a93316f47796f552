// Multiresolution hash encoding (Instant-NGP) forward and backward kernels for the CPU.
//
// Follows nerf/hashgrid.py's conventions exactly (see its module docstring): positions clamped
// to [0,1] (NaN -> 0), p = x * res with no +0.5 offset, cell = min(floor(p), res - 1), dense
// index c0 + c1 (res+1) + c2 (res+1)^2 when (res+1)^3 <= T, otherwise the xor-of-primes hash in
// uint32 arithmetic masked to T - 1 (equal to the int64 reference because T is a power of two).
// Output [N, L*F] level-major. Table and gradients are float32.
//
// Parallelism: forward splits (block of points, level) pairs over OpenMP threads, taking a
// block's levels in turn so its output rows stay in cache, and reads a row of F = 2 floats as
// one 64-bit gather lane. Backward scatters into the table; the default splits the work by
// level, so each thread owns whole disjoint slices of the gradient table and no two threads
// ever write the same row (race-free without atomics). With F = 2 both directions process 8
// (AVX2+FMA) or 16 (AVX-512) points per instruction; other F use the scalar loops. Two alternatives, kept for the
// benchmark that chose the default, split by points instead and resolve races with atomics or
// with per-thread partial tables.
//
// Fused queries without autograd (`density`, `visible`): the encoding of a block of points
// goes straight through the density MLP's hidden layer and density row while it is in cache,
// and `visible` adds compaction's per-ray transmittance cut (docs/hashgrid.md).
#include <torch/extension.h>

#include <ATen/Parallel.h>
#include <omp.h>
// SIMD paths for F = 2: AVX-512 (16 points), else AVX2 (8 points), else scalar. Building with
// -DDRONECAP_NO_SIMD keeps the scalar path only (benchmarks/train_speed.py compares them).
#if defined(__AVX512F__) && !defined(DRONECAP_NO_SIMD)
#define HG_AVX512 1
#elif defined(__AVX2__) && defined(__FMA__) && !defined(DRONECAP_NO_SIMD)
#define HG_AVX2 1
#endif
#if defined(HG_AVX512) || defined(HG_AVX2)
#include <immintrin.h>
#endif

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <tuple>
#include <vector>

#include "amx_bf16.h"

namespace {

constexpr uint32_t kPrime1 = 2654435761u;
constexpr uint32_t kPrime2 = 805459861u;
constexpr int64_t kBlock = 1024;  // points per forward work item

struct Level {
  float scale;       // res, as float
  float max_cell;    // res - 1
  uint32_t stride;   // res + 1 (dense levels)
  uint32_t mask;     // rows - 1 (hashed levels; rows is a power of two)
  bool dense;
  int64_t offset;    // first table row of the level
};

std::vector<Level> make_levels(const std::vector<int64_t>& resolutions,
                               const std::vector<int64_t>& offsets, int64_t log2_hashmap) {
  TORCH_CHECK(offsets.size() == resolutions.size() + 1, "offsets must have levels + 1 entries");
  const int64_t max_rows = int64_t(1) << log2_hashmap;
  std::vector<Level> levels;
  for (size_t l = 0; l < resolutions.size(); ++l) {
    const int64_t res = resolutions[l];
    const int64_t rows = offsets[l + 1] - offsets[l];
    const bool dense = (res + 1) * (res + 1) * (res + 1) <= max_rows;
    TORCH_CHECK(res >= 1, "resolutions must be >= 1");
    TORCH_CHECK(dense ? rows == (res + 1) * (res + 1) * (res + 1) : rows == max_rows,
                "level ", l, " has ", rows, " rows, inconsistent with its resolution");
    levels.push_back({float(res), float(res - 1), uint32_t(res + 1), uint32_t(rows - 1), dense,
                      offsets[l]});
  }
  return levels;
}

// The 8 corner rows (relative to the level's offset) and trilinear weights of one point.
inline void corners(const float* p, const Level& lv, uint32_t idx[8], float w[8]) {
  uint32_t c[3];
  float f[3];
  for (int k = 0; k < 3; ++k) {
    const float x = std::fmin(std::fmax(p[k], 0.0f), 1.0f);  // fmax(NaN, 0) = 0
    const float pos = x * lv.scale;
    const float cell = std::fmin(std::floor(pos), lv.max_cell);
    f[k] = pos - cell;
    c[k] = uint32_t(cell);
  }
  for (int i = 0; i < 8; ++i) {
    const uint32_t a = c[0] + (i & 1), b = c[1] + ((i >> 1) & 1), d = c[2] + ((i >> 2) & 1);
    idx[i] = lv.dense ? a + lv.stride * (b + lv.stride * d)
                      : (a ^ (b * kPrime1) ^ (d * kPrime2)) & lv.mask;
    const float wx = (i & 1) ? f[0] : 1.0f - f[0];
    const float wy = (i & 2) ? f[1] : 1.0f - f[1];
    const float wz = (i & 4) ? f[2] : 1.0f - f[2];
    w[i] = wx * wy * wz;
  }
}

#ifdef HG_AVX512
// 16 points at a time with AVX-512, for F = 2 (the configuration every preset uses). Same
// arithmetic as `corners` (multiply, floor, subtract: no fused multiply-add), so the fractions
// are bit-identical to the scalar path and to the reference.
struct Lanes {
  __m512i c[3];  // lower corner per axis
  __m512 f[3];   // fraction per axis
};

inline Lanes locate16(const float* x, const Level& lv) {
  const __m512i idx3 = _mm512_mullo_epi32(
      _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15), _mm512_set1_epi32(3));
  const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.0f);
  const __m512 scale = _mm512_set1_ps(lv.scale), max_cell = _mm512_set1_ps(lv.max_cell);
  Lanes p;
  for (int k = 0; k < 3; ++k) {
    __m512 v = _mm512_i32gather_ps(_mm512_add_epi32(idx3, _mm512_set1_epi32(k)), x, 4);
    v = _mm512_min_ps(_mm512_max_ps(v, zero), one);  // max(NaN, 0) returns 0
    const __m512 pos = _mm512_mul_ps(v, scale);
    const __m512 cell = _mm512_min_ps(
        _mm512_roundscale_ps(pos, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC), max_cell);
    p.f[k] = _mm512_sub_ps(pos, cell);
    p.c[k] = _mm512_cvttps_epi32(cell);
  }
  return p;
}

template <bool Dense>
inline void corner16(const Lanes& p, int i, const Level& lv, __m512i& row, __m512& w) {
  const __m512i one = _mm512_set1_epi32(1);
  const __m512i a = (i & 1) ? _mm512_add_epi32(p.c[0], one) : p.c[0];
  const __m512i b = (i & 2) ? _mm512_add_epi32(p.c[1], one) : p.c[1];
  const __m512i d = (i & 4) ? _mm512_add_epi32(p.c[2], one) : p.c[2];
  if (Dense) {
    const __m512i s = _mm512_set1_epi32(int(lv.stride));
    row = _mm512_add_epi32(a, _mm512_mullo_epi32(s, _mm512_add_epi32(b, _mm512_mullo_epi32(s, d))));
  } else {
    const __m512i h = _mm512_xor_si512(
        a, _mm512_xor_si512(_mm512_mullo_epi32(b, _mm512_set1_epi32(int(kPrime1))),
                            _mm512_mullo_epi32(d, _mm512_set1_epi32(int(kPrime2)))));
    row = _mm512_and_si512(h, _mm512_set1_epi32(int(lv.mask)));
  }
  const __m512 one_f = _mm512_set1_ps(1.0f);
  const __m512 wx = (i & 1) ? p.f[0] : _mm512_sub_ps(one_f, p.f[0]);
  const __m512 wy = (i & 2) ? p.f[1] : _mm512_sub_ps(one_f, p.f[1]);
  const __m512 wz = (i & 4) ? p.f[2] : _mm512_sub_ps(one_f, p.f[2]);
  w = _mm512_mul_ps(_mm512_mul_ps(wx, wy), wz);
}

// Forward of points [n0, n0 + 16k) of one level; returns the first point left for the scalar tail.
template <bool Dense>
int64_t forward16(const float* x, const float* tl, float* out, int64_t n0, int64_t n1,
                  const Level& lv, int64_t l, int64_t out_dim) {
  const __m512i out_idx = _mm512_mullo_epi32(
      _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15),
      _mm512_set1_epi32(int(out_dim)));
  // Rows of F = 2 floats are read as one 64-bit lane: two 8-lane gathers per corner, and the
  // interleaved (f0, f1) accumulators match the output layout.
  const __m256i out_idx8 = _mm512_castsi512_si256(out_idx);
  const __m512i dup_lo = _mm512_setr_epi32(0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5, 6, 6, 7, 7);
  const __m512i dup_hi = _mm512_add_epi32(dup_lo, _mm512_set1_epi32(8));
  const double* td = reinterpret_cast<const double*>(tl);
  int64_t s = n0;
  for (; s + 16 <= n1; s += 16) {
    const Lanes p = locate16(x + 3 * s, lv);
    __m512 acc_lo = _mm512_setzero_ps(), acc_hi = _mm512_setzero_ps();
    for (int i = 0; i < 8; ++i) {
      __m512i row;
      __m512 w;
      corner16<Dense>(p, i, lv, row, w);
      const __m512 lo = _mm512_castpd_ps(_mm512_i32gather_pd(_mm512_castsi512_si256(row), td, 8));
      const __m512 hi =
          _mm512_castpd_ps(_mm512_i32gather_pd(_mm512_extracti64x4_epi64(row, 1), td, 8));
      acc_lo = _mm512_fmadd_ps(_mm512_permutexvar_ps(dup_lo, w), lo, acc_lo);
      acc_hi = _mm512_fmadd_ps(_mm512_permutexvar_ps(dup_hi, w), hi, acc_hi);
    }
    double* o = reinterpret_cast<double*>(out + s * out_dim + l * 2);
    _mm512_i32scatter_pd(o, out_idx8, _mm512_castps_pd(acc_lo), 4);
    _mm512_i32scatter_pd(o + 8 * out_dim / 2, out_idx8, _mm512_castps_pd(acc_hi), 4);
  }
  return s;
}

// Backward of points [n0, n0 + 16k) of one level (rows and products in SIMD, scatter scalar).
template <bool Dense>
int64_t backward16(const float* x, const float* grad_out, float* gl, int64_t n0, int64_t n1,
                   const Level& lv, int64_t l, int64_t out_dim) {
  const __m512i out_idx = _mm512_mullo_epi32(
      _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15),
      _mm512_set1_epi32(int(out_dim)));
  alignas(64) int32_t rows[8][16];
  alignas(64) float v0[8][16], v1[8][16];
  int64_t s = n0;
  for (; s + 16 <= n1; s += 16) {
    const Lanes p = locate16(x + 3 * s, lv);
    const float* g = grad_out + s * out_dim + l * 2;
    const __m512 g0 = _mm512_i32gather_ps(out_idx, g, 4), g1 = _mm512_i32gather_ps(out_idx, g + 1, 4);
    for (int i = 0; i < 8; ++i) {
      __m512i row;
      __m512 w;
      corner16<Dense>(p, i, lv, row, w);
      _mm512_store_si512(rows[i], row);
      _mm512_store_ps(v0[i], _mm512_mul_ps(w, g0));
      _mm512_store_ps(v1[i], _mm512_mul_ps(w, g1));
    }
    for (int j = 0; j < 16; ++j) {
      for (int i = 0; i < 8; ++i) {
        float* r = gl + 2 * int64_t(rows[i][j]);
        r[0] += v0[i][j];
        r[1] += v1[i][j];
      }
    }
  }
  return s;
}
#endif

#ifdef HG_AVX2
// 8 points at a time with AVX2 + FMA (CPUs without AVX-512, e.g. AMD Zen 2/3), for F = 2: the
// same scheme as the AVX-512 path at half the width. Same arithmetic as `corners` (multiply,
// floor, subtract), so the fractions and rows are bit-identical to the scalar path.
struct Lanes8 {
  __m256i c[3];  // lower corner per axis
  __m256 f[3];   // fraction per axis
};

inline Lanes8 locate8(const float* x, const Level& lv) {
  const __m256i idx3 = _mm256_setr_epi32(0, 3, 6, 9, 12, 15, 18, 21);
  const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f);
  const __m256 scale = _mm256_set1_ps(lv.scale), max_cell = _mm256_set1_ps(lv.max_cell);
  Lanes8 p;
  for (int k = 0; k < 3; ++k) {
    __m256 v = _mm256_i32gather_ps(x + k, idx3, 4);
    v = _mm256_min_ps(_mm256_max_ps(v, zero), one);  // max(NaN, 0) returns 0
    const __m256 pos = _mm256_mul_ps(v, scale);
    const __m256 cell = _mm256_min_ps(_mm256_floor_ps(pos), max_cell);
    p.f[k] = _mm256_sub_ps(pos, cell);
    p.c[k] = _mm256_cvttps_epi32(cell);
  }
  return p;
}

template <bool Dense>
inline void corner8(const Lanes8& p, int i, const Level& lv, __m256i& row, __m256& w) {
  const __m256i one = _mm256_set1_epi32(1);
  const __m256i a = (i & 1) ? _mm256_add_epi32(p.c[0], one) : p.c[0];
  const __m256i b = (i & 2) ? _mm256_add_epi32(p.c[1], one) : p.c[1];
  const __m256i d = (i & 4) ? _mm256_add_epi32(p.c[2], one) : p.c[2];
  if (Dense) {
    const __m256i s = _mm256_set1_epi32(int(lv.stride));
    row = _mm256_add_epi32(a, _mm256_mullo_epi32(s, _mm256_add_epi32(b, _mm256_mullo_epi32(s, d))));
  } else {
    const __m256i h = _mm256_xor_si256(
        a, _mm256_xor_si256(_mm256_mullo_epi32(b, _mm256_set1_epi32(int(kPrime1))),
                            _mm256_mullo_epi32(d, _mm256_set1_epi32(int(kPrime2)))));
    row = _mm256_and_si256(h, _mm256_set1_epi32(int(lv.mask)));
  }
  const __m256 one_f = _mm256_set1_ps(1.0f);
  const __m256 wx = (i & 1) ? p.f[0] : _mm256_sub_ps(one_f, p.f[0]);
  const __m256 wy = (i & 2) ? p.f[1] : _mm256_sub_ps(one_f, p.f[1]);
  const __m256 wz = (i & 4) ? p.f[2] : _mm256_sub_ps(one_f, p.f[2]);
  w = _mm256_mul_ps(_mm256_mul_ps(wx, wy), wz);
}

// Forward of points [n0, n0 + 8k) of one level; returns the first point left for the scalar tail.
template <bool Dense>
int64_t forward8(const float* x, const float* tl, float* out, int64_t n0, int64_t n1,
                 const Level& lv, int64_t l, int64_t out_dim) {
  // Rows of F = 2 floats are read as one 64-bit lane: two 4-lane gathers per corner, and the
  // interleaved (f0, f1) accumulators match the output layout.
  const __m256i dup_lo = _mm256_setr_epi32(0, 0, 1, 1, 2, 2, 3, 3);
  const __m256i dup_hi = _mm256_setr_epi32(4, 4, 5, 5, 6, 6, 7, 7);
  const double* td = reinterpret_cast<const double*>(tl);
  int64_t s = n0;
  for (; s + 8 <= n1; s += 8) {
    const Lanes8 p = locate8(x + 3 * s, lv);
    __m256 acc_lo = _mm256_setzero_ps(), acc_hi = _mm256_setzero_ps();
    for (int i = 0; i < 8; ++i) {
      __m256i row;
      __m256 w;
      corner8<Dense>(p, i, lv, row, w);
      const __m256 lo = _mm256_castpd_ps(_mm256_i32gather_pd(td, _mm256_castsi256_si128(row), 8));
      const __m256 hi =
          _mm256_castpd_ps(_mm256_i32gather_pd(td, _mm256_extracti128_si256(row, 1), 8));
      acc_lo = _mm256_fmadd_ps(_mm256_permutevar8x32_ps(w, dup_lo), lo, acc_lo);
      acc_hi = _mm256_fmadd_ps(_mm256_permutevar8x32_ps(w, dup_hi), hi, acc_hi);
    }
    alignas(32) double pairs[8];  // (f0, f1) of the 8 points, one 64-bit lane each
    _mm256_store_pd(pairs, _mm256_castps_pd(acc_lo));
    _mm256_store_pd(pairs + 4, _mm256_castps_pd(acc_hi));
    for (int j = 0; j < 8; ++j) {
      std::memcpy(out + (s + j) * out_dim + l * 2, pairs + j, sizeof(double));
    }
  }
  return s;
}

// Backward of points [n0, n0 + 8k) of one level (rows and products in SIMD, scatter scalar).
template <bool Dense>
int64_t backward8(const float* x, const float* grad_out, float* gl, int64_t n0, int64_t n1,
                  const Level& lv, int64_t l, int64_t out_dim) {
  const __m256i out_idx =
      _mm256_mullo_epi32(_mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7), _mm256_set1_epi32(int(out_dim)));
  alignas(32) int32_t rows[8][8];
  alignas(32) float v0[8][8], v1[8][8];
  int64_t s = n0;
  for (; s + 8 <= n1; s += 8) {
    const Lanes8 p = locate8(x + 3 * s, lv);
    const float* g = grad_out + s * out_dim + l * 2;
    const __m256 g0 = _mm256_i32gather_ps(g, out_idx, 4), g1 = _mm256_i32gather_ps(g + 1, out_idx, 4);
    for (int i = 0; i < 8; ++i) {
      __m256i row;
      __m256 w;
      corner8<Dense>(p, i, lv, row, w);
      _mm256_store_si256(reinterpret_cast<__m256i*>(rows[i]), row);
      _mm256_store_ps(v0[i], _mm256_mul_ps(w, g0));
      _mm256_store_ps(v1[i], _mm256_mul_ps(w, g1));
    }
    for (int j = 0; j < 8; ++j) {
      for (int i = 0; i < 8; ++i) {
        float* r = gl + 2 * int64_t(rows[i][j]);
        r[0] += v0[i][j];
        r[1] += v1[i][j];
      }
    }
  }
  return s;
}
#endif

template <int F>
void forward_range(const float* x, const float* table, float* out, int64_t n0, int64_t n1,
                   const Level& lv, int64_t l, int64_t out_dim, int64_t f_rt) {
  const int64_t nf = F > 0 ? F : f_rt;
  const float* tl = table + lv.offset * nf;
#ifdef HG_AVX512
  if (F == 2) {
    n0 = lv.dense ? forward16<true>(x, tl, out, n0, n1, lv, l, out_dim)
                  : forward16<false>(x, tl, out, n0, n1, lv, l, out_dim);
  }
#elif defined(HG_AVX2)
  if (F == 2) {
    n0 = lv.dense ? forward8<true>(x, tl, out, n0, n1, lv, l, out_dim)
                  : forward8<false>(x, tl, out, n0, n1, lv, l, out_dim);
  }
#endif
  uint32_t idx[8];
  float w[8];
  for (int64_t n = n0; n < n1; ++n) {
    corners(x + 3 * n, lv, idx, w);
    float* o = out + n * out_dim + l * nf;
    for (int64_t f = 0; f < nf; ++f) {
      float acc = 0.0f;
      for (int i = 0; i < 8; ++i) acc += w[i] * tl[int64_t(idx[i]) * nf + f];
      o[f] = acc;
    }
  }
}

template <int F>
void backward_range(const float* x, const float* grad_out, float* grad, int64_t n0, int64_t n1,
                    const Level& lv, int64_t l, int64_t out_dim, int64_t f_rt, bool atomic) {
  const int64_t nf = F > 0 ? F : f_rt;
  float* gl = grad + lv.offset * nf;
#ifdef HG_AVX512
  if (F == 2 && !atomic) {
    n0 = lv.dense ? backward16<true>(x, grad_out, gl, n0, n1, lv, l, out_dim)
                  : backward16<false>(x, grad_out, gl, n0, n1, lv, l, out_dim);
  }
#elif defined(HG_AVX2)
  if (F == 2 && !atomic) {
    n0 = lv.dense ? backward8<true>(x, grad_out, gl, n0, n1, lv, l, out_dim)
                  : backward8<false>(x, grad_out, gl, n0, n1, lv, l, out_dim);
  }
#endif
  uint32_t idx[8];
  float w[8];
  for (int64_t n = n0; n < n1; ++n) {
    corners(x + 3 * n, lv, idx, w);
    const float* g = grad_out + n * out_dim + l * nf;
    for (int i = 0; i < 8; ++i) {
      float* row = gl + int64_t(idx[i]) * nf;
      for (int64_t f = 0; f < nf; ++f) {
        const float v = w[i] * g[f];
        if (atomic) {
#pragma omp atomic
          row[f] += v;
        } else {
          row[f] += v;
        }
      }
    }
  }
}

// The levels of a table [rows, F], checked against it.
std::vector<Level> table_levels(const torch::Tensor& table, const std::vector<int64_t>& resolutions,
                                const std::vector<int64_t>& offsets, int64_t log2_hashmap) {
  TORCH_CHECK(table.device().is_cpu() && table.dim() == 2 &&
                  table.scalar_type() == torch::kFloat32 && table.is_contiguous(),
              "table must be a contiguous float32 [rows, F] CPU tensor");
  auto levels = make_levels(resolutions, offsets, log2_hashmap);
  TORCH_CHECK(table.size(0) == offsets.back(), "table has ", table.size(0), " rows, expected ",
              offsets.back());
  return levels;
}

// The levels of a forward call, after checking x [N, 3] and table [rows, F] against them.
std::vector<Level> checked_levels(const torch::Tensor& x, const torch::Tensor& table,
                                  const std::vector<int64_t>& resolutions,
                                  const std::vector<int64_t>& offsets, int64_t log2_hashmap) {
  TORCH_CHECK(x.device().is_cpu() && x.dim() == 2 && x.size(1) == 3 &&
                  x.scalar_type() == torch::kFloat32 && x.is_contiguous(),
              "x must be a contiguous float32 [N, 3] CPU tensor");
  return table_levels(table, resolutions, offsets, log2_hashmap);
}

#define DISPATCH_F(nf, FN, ...)     \
  switch (nf) {                     \
    case 1: FN<1>(__VA_ARGS__); break; \
    case 2: FN<2>(__VA_ARGS__); break; \
    case 4: FN<4>(__VA_ARGS__); break; \
    case 8: FN<8>(__VA_ARGS__); break; \
    default: FN<0>(__VA_ARGS__); break; \
  }

}  // namespace

torch::Tensor hash_forward(torch::Tensor x, torch::Tensor table, std::vector<int64_t> resolutions,
                           std::vector<int64_t> offsets, int64_t log2_hashmap) {
  const auto levels = checked_levels(x, table, resolutions, offsets, log2_hashmap);
  const int64_t n = x.size(0), nf = table.size(1), nl = int64_t(levels.size());
  const int64_t out_dim = nl * nf;
  auto out = torch::empty({n, out_dim}, x.options());
  const float* xp = x.data_ptr<float>();
  const float* tp = table.data_ptr<float>();
  float* op = out.data_ptr<float>();
  const int64_t blocks = (n + kBlock - 1) / kBlock;
  const int64_t items = blocks * nl;
#pragma omp parallel for schedule(static) num_threads(at::get_num_threads())
  for (int64_t item = 0; item < items; ++item) {
    const int64_t b = item / nl, l = item % nl;  // a block's levels in turn: its output stays cached
    const int64_t n0 = b * kBlock, n1 = std::min(n, n0 + kBlock);
    DISPATCH_F(nf, forward_range, xp, tp, op, n0, n1, levels[l], l, out_dim, nf);
  }
  return out;
}

// mode 0: split by level (default, race-free); 1: split by points with atomics;
// 2: split by points into per-thread partial tables, summed at the end.
// `into`: empty, or a float32 [rows, F] gradient that receives the result added in place
// (mode 0 only; no full-size temporary). Returns the gradient tensor written.
torch::Tensor hash_backward(torch::Tensor grad_out, torch::Tensor x, torch::Tensor into,
                            int64_t rows, int64_t nf, std::vector<int64_t> resolutions,
                            std::vector<int64_t> offsets, int64_t log2_hashmap, int64_t mode) {
  TORCH_CHECK(x.dim() == 2 && x.size(1) == 3 && x.scalar_type() == torch::kFloat32 &&
                  x.is_contiguous(), "x must be a contiguous float32 [N, 3] tensor");
  const auto levels = make_levels(resolutions, offsets, log2_hashmap);
  const int64_t n = x.size(0), nl = int64_t(levels.size()), out_dim = nl * nf;
  TORCH_CHECK(grad_out.scalar_type() == torch::kFloat32 && grad_out.is_contiguous() &&
                  grad_out.size(0) == n && grad_out.size(1) == out_dim,
              "grad_out must be a contiguous float32 [N, L*F] tensor");
  TORCH_CHECK(rows == offsets.back(), "rows inconsistent with offsets");
  const float* xp = x.data_ptr<float>();
  const float* gp = grad_out.data_ptr<float>();
  const int nt = at::get_num_threads();
  const bool accumulate = into.numel() > 0;
  if (accumulate) {
    TORCH_CHECK(mode == 0, "in-place accumulation needs backward mode 0");
    TORCH_CHECK(into.scalar_type() == torch::kFloat32 && into.is_contiguous() &&
                    into.dim() == 2 && into.size(0) == rows && into.size(1) == nf,
                "into must be a contiguous float32 [rows, F] tensor");
  }
  // Mode 0 zeroes each level's slice in the thread that then scatters into it (one pass less).
  auto grad = accumulate ? into
              : mode == 0 ? torch::empty({rows, nf}, x.options())
                          : torch::zeros({rows, nf}, x.options());
  float* grad_p = grad.data_ptr<float>();
  if (mode == 0) {
#pragma omp parallel for schedule(static, 1) num_threads(nt)
    for (int64_t l = 0; l < nl; ++l) {
      if (!accumulate) std::fill(grad_p + offsets[l] * nf, grad_p + offsets[l + 1] * nf, 0.0f);
      DISPATCH_F(nf, backward_range, xp, gp, grad_p, 0, n, levels[l], l, out_dim, nf, false);
    }
  } else if (mode == 1) {
#pragma omp parallel for schedule(static) num_threads(nt)
    for (int64_t b = 0; b < nt; ++b) {
      const int64_t n0 = n * b / nt, n1 = n * (b + 1) / nt;
      for (int64_t l = 0; l < nl; ++l) {
        DISPATCH_F(nf, backward_range, xp, gp, grad_p, n0, n1, levels[l], l, out_dim, nf, true);
      }
    }
  } else {
    TORCH_CHECK(mode == 2, "unknown backward mode ", mode);
    auto partial = torch::zeros({nt - 1, rows, nf}, x.options());
    float* pp = partial.data_ptr<float>();
#pragma omp parallel for schedule(static) num_threads(nt)
    for (int64_t b = 0; b < nt; ++b) {
      const int64_t n0 = n * b / nt, n1 = n * (b + 1) / nt;
      float* dst = b == 0 ? grad_p : pp + (b - 1) * rows * nf;
      for (int64_t l = 0; l < nl; ++l) {
        DISPATCH_F(nf, backward_range, xp, gp, dst, n0, n1, levels[l], l, out_dim, nf, false);
      }
    }
    if (nt > 1) grad += partial.sum(0);
  }
  return grad;
}

namespace {

constexpr int64_t kFuseBlock = 256;  // points per fused work item: encodings stay in L1/L2

// Density MLP of one hidden layer on encoded rows e [n, in_dim]: out[i] = w2 . relu(W1 e_i),
// w1t = W1 transposed [in_dim, hidden] (scalar loops; any width).
void density_rows(const float* e, int64_t n, int64_t in_dim, const float* w1t, const float* w2,
                  int64_t hidden, float* out) {
  std::vector<float> hid(hidden);
  for (int64_t i = 0; i < n; ++i) {
    const float* row = e + i * in_dim;
    std::fill(hid.begin(), hid.end(), 0.0f);
    for (int64_t k = 0; k < in_dim; ++k) {
      const float v = row[k];
      const float* w = w1t + k * hidden;
      for (int64_t j = 0; j < hidden; ++j) hid[j] += v * w[j];
    }
    float acc = 0.0f;
    for (int64_t j = 0; j < hidden; ++j) acc += std::fmax(hid[j], 0.0f) * w2[j];
    out[i] = acc;
  }
}

#ifdef HG_AVX512
// The same for a hidden width of 64 (every preset), four points at a time: their 4 x 64 hidden
// values live in 16 registers and each row of w1t is loaded once for the four. Returns the
// number of rows done (a multiple of 4; the rest go through density_rows).
int64_t density_rows64(const float* e, int64_t n, int64_t in_dim, const float* w1t,
                       const float* w2, float* out) {
  const __m512 zero = _mm512_setzero_ps();
  __m512 v2[4];
  for (int q = 0; q < 4; ++q) v2[q] = _mm512_loadu_ps(w2 + 16 * q);
  int64_t i = 0;
  for (; i + 4 <= n; i += 4) {
    __m512 acc[4][4];
    for (int p = 0; p < 4; ++p)
      for (int q = 0; q < 4; ++q) acc[p][q] = zero;
    const float* row = e + i * in_dim;
    for (int64_t k = 0; k < in_dim; ++k) {
      const float* w = w1t + k * 64;
      const __m512 w0 = _mm512_loadu_ps(w), w1 = _mm512_loadu_ps(w + 16);
      const __m512 w2v = _mm512_loadu_ps(w + 32), w3 = _mm512_loadu_ps(w + 48);
      for (int p = 0; p < 4; ++p) {
        const __m512 v = _mm512_set1_ps(row[p * in_dim + k]);
        acc[p][0] = _mm512_fmadd_ps(v, w0, acc[p][0]);
        acc[p][1] = _mm512_fmadd_ps(v, w1, acc[p][1]);
        acc[p][2] = _mm512_fmadd_ps(v, w2v, acc[p][2]);
        acc[p][3] = _mm512_fmadd_ps(v, w3, acc[p][3]);
      }
    }
    for (int p = 0; p < 4; ++p) {
      __m512 t = _mm512_mul_ps(_mm512_max_ps(acc[p][0], zero), v2[0]);
      for (int q = 1; q < 4; ++q) t = _mm512_fmadd_ps(_mm512_max_ps(acc[p][q], zero), v2[q], t);
      out[i + p] = _mm512_reduce_add_ps(t);
    }
  }
  return i;
}
#elif defined(HG_AVX2)
// The same with AVX2 + FMA, one point at a time (its 64 hidden values in 8 registers).
int64_t density_rows64(const float* e, int64_t n, int64_t in_dim, const float* w1t,
                       const float* w2, float* out) {
  const __m256 zero = _mm256_setzero_ps();
  for (int64_t i = 0; i < n; ++i) {
    __m256 acc[8];
    for (int q = 0; q < 8; ++q) acc[q] = zero;
    const float* row = e + i * in_dim;
    for (int64_t k = 0; k < in_dim; ++k) {
      const __m256 v = _mm256_set1_ps(row[k]);
      const float* w = w1t + k * 64;
      for (int q = 0; q < 8; ++q) acc[q] = _mm256_fmadd_ps(v, _mm256_loadu_ps(w + 8 * q), acc[q]);
    }
    __m256 t = _mm256_mul_ps(_mm256_max_ps(acc[0], zero), _mm256_loadu_ps(w2));
    for (int q = 1; q < 8; ++q)
      t = _mm256_fmadd_ps(_mm256_max_ps(acc[q], zero), _mm256_loadu_ps(w2 + 8 * q), t);
    alignas(32) float lanes[8];
    _mm256_store_ps(lanes, t);
    float sum = 0.0f;
    for (int q = 0; q < 8; ++q) sum += lanes[q];
    out[i] = sum;
  }
  return n;
}
#endif

}  // namespace

#ifdef DRONECAP_AMX
// density_rows on the AMX tiles: the rows of e rounded to bf16 and the hidden layer summed in
// float32 (amx_bf16.h; w1 packed by amx::pack from W1 transposed), its ReLU and the output row
// in float32. hidden a multiple of 16 and in_dim at most 128.
void density_rows_amx(const float* e, int64_t n, int64_t in_dim, const amx::bf16* w1,
                      const float* w2, int64_t hidden, float* out) {
  alignas(64) amx::bf16 x[amx::kRows * 128];
  alignas(64) float y[amx::kRows * 128];
  const int kp = amx::pad32(int(in_dim)), h = int(hidden);
  for (int64_t r0 = 0; r0 < n; r0 += amx::kRows) {
    const int rows = int(std::min<int64_t>(amx::kRows, n - r0));
    amx::rows_to_bf16(e + r0 * in_dim, int(in_dim), rows, int(in_dim), x, kp);
    amx::product(x, kp, w1, h, y, h);
    for (int p = 0; p < rows; ++p) {
      __m512 acc = _mm512_setzero_ps();
      for (int j = 0; j < h; j += 16) {
        const __m512 v = _mm512_max_ps(_mm512_loadu_ps(y + p * h + j), _mm512_setzero_ps());
        acc = _mm512_fmadd_ps(v, _mm512_loadu_ps(w2 + j), acc);
      }
      out[r0 + p] = _mm512_reduce_add_ps(acc);
    }
  }
}
#endif

// The density MLP's first output (before its activation) at points, fused with their hash
// encoding: a block of points is encoded into a buffer that stays in cache and goes through the
// MLP (one hidden layer of ReLUs, bias-free) before the next block, so the [N, hidden]
// activations never reach memory. w1 [hidden, L*F] and w2 [hidden] (the last layer's first row).
// Checked and laid out once (the pre-pass queries in rounds), then run on any rows of points.
// With `bf16` the hidden layer multiplies on the AMX tiles where they can run it (the build has
// them, hidden a multiple of 16 up to 128, L*F at most 128), else in float32.
struct DensityQuery {
  std::vector<Level> levels;
  int64_t nf, out_dim, hidden;
  torch::Tensor table, w1t, w2c;  // kept alive for the pointers below
  const float *tp, *w1p, *w2p;
  std::vector<amx::bf16> w1_tiles;  // W1 transposed, packed for the AMX tiles (bf16 only)

  DensityQuery(const torch::Tensor& table_, const std::vector<int64_t>& resolutions,
               const std::vector<int64_t>& offsets, int64_t log2_hashmap, const torch::Tensor& w1,
               const torch::Tensor& w2, bool bf16)
      : levels(table_levels(table_, resolutions, offsets, log2_hashmap)),
        nf(table_.size(1)),
        out_dim(int64_t(levels.size()) * nf),
        hidden(w1.size(0)),
        table(table_) {
    TORCH_CHECK(w1.dim() == 2 && w1.size(1) == out_dim && w1.scalar_type() == torch::kFloat32,
                "w1 must be float32 [hidden, L*F]");
    TORCH_CHECK(hidden >= 1 && hidden <= 1024, "hidden width must be in [1, 1024]");
    TORCH_CHECK(w2.numel() == hidden && w2.scalar_type() == torch::kFloat32,
                "w2 must be float32 [hidden]");
    w1t = w1.t().contiguous();
    w2c = w2.reshape({hidden}).contiguous();
    tp = table.data_ptr<float>(), w1p = w1t.data_ptr<float>(), w2p = w2c.data_ptr<float>();
#ifdef DRONECAP_AMX
    if (bf16 && amx::available() && hidden % 16 == 0 && hidden <= 128 && out_dim <= 128)
      w1_tiles = amx::pack(std::vector<float>(w1p, w1p + out_dim * hidden), int(out_dim),
                           int(hidden));
#endif
  }

  // Raw densities rp [n] of the points xp [n, 3] and, when `ep` is not null, their encodings
  // ep [n, L*F]; blocks of points split over the threads.
  void operator()(const float* xp, int64_t n, float* rp, float* ep) const {
    const int64_t blocks = (n + kFuseBlock - 1) / kFuseBlock;
#pragma omp parallel num_threads(std::min<int64_t>(at::get_num_threads(), blocks))
    {
      std::vector<float> scratch(ep ? 0 : kFuseBlock * out_dim);
      begin();
#pragma omp for schedule(dynamic, 1)  // a thread woken late takes fewer blocks
      for (int64_t b = 0; b < blocks; ++b) {
        const int64_t n0 = b * kFuseBlock, m = std::min(n, n0 + kFuseBlock) - n0;
        block(xp + 3 * n0, m, rp + n0, ep ? ep + n0 * out_dim : scratch.data());
      }
      end();
    }
  }

  // The same on the calling thread alone, between its begin() and end(), into encodings ep.
  void serial(const float* xp, int64_t n, float* rp, float* ep) const {
    for (int64_t n0 = 0; n0 < n; n0 += kFuseBlock)
      block(xp + 3 * n0, std::min(n - n0, kFuseBlock), rp + n0, ep + n0 * out_dim);
  }

  // A thread's tile state for the AMX products (nothing without them).
  void begin() const {
#ifdef DRONECAP_AMX
    if (!w1_tiles.empty()) amx::begin();
#endif
  }
  void end() const {
#ifdef DRONECAP_AMX
    if (!w1_tiles.empty()) amx::end();
#endif
  }

 private:
  // At most kFuseBlock points: encoded into e, then through the MLP.
  void block(const float* xp, int64_t m, float* rp, float* e) const {
    for (int64_t l = 0; l < int64_t(levels.size()); ++l) {
      DISPATCH_F(nf, forward_range, xp, tp, e, 0, m, levels[l], l, out_dim, nf);
    }
#ifdef DRONECAP_AMX
    if (!w1_tiles.empty()) {
      density_rows_amx(e, m, out_dim, w1_tiles.data(), w2p, hidden, rp);
      return;
    }
#endif
    int64_t done = 0;
#if defined(HG_AVX512) || defined(HG_AVX2)
    if (hidden == 64) done = density_rows64(e, m, out_dim, w1p, w2p, rp);
#endif
    density_rows(e + done * out_dim, m - done, out_dim, w1p, w2p, hidden, rp + done);
  }
};

// Returns {raw [N], encoded [N, L*F] (empty unless keep_encoded)}.
std::vector<torch::Tensor> density_forward(torch::Tensor x, torch::Tensor table,
                                           std::vector<int64_t> resolutions,
                                           std::vector<int64_t> offsets, int64_t log2_hashmap,
                                           torch::Tensor w1, torch::Tensor w2, bool keep_encoded,
                                           bool bf16) {
  const int64_t n = x.size(0), out_dim = int64_t(resolutions.size()) * table.size(1);
  auto raw = torch::empty({n}, x.options());
  auto encoded = torch::empty({keep_encoded ? n : 0, out_dim}, x.options());
  checked_levels(x, table, resolutions, offsets, log2_hashmap);
  const DensityQuery query(table, resolutions, offsets, log2_hashmap, w1, w2, bf16);
  query(x.data_ptr<float>(), n, raw.data_ptr<float>(),
        keep_encoded ? encoded.data_ptr<float>() : nullptr);
  return {raw, encoded};
}

// Compaction's pre-pass in one call: the density of packed samples (intervals [t_start, t_end)
// in scene units along rays origins [R, 3] + t dirs [R, 3], ray_indices [S] non-decreasing),
// each ray's transmittance before each sample (exp of minus the optical thickness summed in
// double, as nerf/volrend.packed_weights), and the samples where it is above min_transmittance.
// A sample is queried at its midpoint mapped to the unit cube of the box (box [2, 3]: its min
// corner and size): (o + d (t_start + t_end) / 2 - min) / size. Density = exp(raw clamped to
// +-max_log_density); thickness = density * length, NaN -> 0, clamped to [0, 1e4] (the
// reference's rules). Returns the kept samples {ray indices int64 [K], t_starts [K], t_ends
// [K], the kept count of each ray int64 [R], encodings [K, L*F], unit-cube midpoints [K, 3]} (the training pass encodes exactly these coordinates).
// With max_kept > 0, only the first whole rays whose kept samples fit in it (at least one ray;
// nerf/batch.py's whole_rays, the training batch) are returned, R their count. Also returns
// the count of samples kept before that cut.
//
// The rays march front to back in rounds: each round queries the next samples of every ray
// still above the threshold (kVisibleRound in the first round, twice as many in each next one:
// a ray that is still clear is likely to stay clear), and a ray stops at its first sample below
// it. Samples behind a ray's cut (about 60 % of a step's marched samples on lego) are then mostly
// never encoded; what is kept is exactly what querying every sample would keep.
constexpr int64_t kVisibleRound = 4;
constexpr int64_t kVisibleChunk = 4096;  // samples per chunk of rays (a thread's work item)

std::tuple<std::vector<torch::Tensor>, int64_t> visible_forward(
    torch::Tensor origins, torch::Tensor dirs, torch::Tensor t_starts, torch::Tensor t_ends,
    torch::Tensor ray_indices, torch::Tensor box, torch::Tensor table,
    std::vector<int64_t> resolutions, std::vector<int64_t> offsets, int64_t log2_hashmap,
    torch::Tensor w1, torch::Tensor w2, double max_log_density, double min_transmittance,
    bool bf16, int64_t max_kept) {
  const int64_t n = t_starts.numel(), out_dim = int64_t(resolutions.size()) * table.size(1);
  for (const auto* t : {&origins, &dirs, &t_starts, &t_ends, &box})
    TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == torch::kFloat32,
                "float32 CPU tensors expected");
  TORCH_CHECK(origins.dim() == 2 && origins.size(1) == 3 && dirs.sizes() == origins.sizes() &&
                  box.numel() == 6 && t_ends.numel() == n && ray_indices.numel() == n &&
                  ray_indices.scalar_type() == torch::kInt64,
              "origins, dirs [R, 3], box [2, 3], t_starts, t_ends [S], ray_indices int64 [S]");
  const auto o = origins.contiguous(), d = dirs.contiguous(), b = box.contiguous();
  const auto t0 = t_starts.contiguous(), t1 = t_ends.contiguous(), ri = ray_indices.contiguous();
  const float *op = o.data_ptr<float>(), *dp = d.data_ptr<float>(), *bp = b.data_ptr<float>();
  const float *t0p = t0.data_ptr<float>(), *t1p = t1.data_ptr<float>();
  const int64_t* rip = ri.data_ptr<int64_t>();
  const int64_t n_rays = o.size(0);
  const float lo[3] = {bp[0], bp[1], bp[2]};
  const float size[3] = {bp[3], bp[4], bp[5]};
  // the rays' runs of samples [begin[r], begin[r + 1])
  std::vector<int64_t> begin;
  for (int64_t i = 0; i < n; ++i) {
    TORCH_CHECK(rip[i] >= 0 && rip[i] < n_rays && (i == 0 || rip[i] >= rip[i - 1]),
                "ray_indices must be non-decreasing indices of the rays");
    if (i == 0 || rip[i] != rip[i - 1]) begin.push_back(i);
  }
  const int64_t rays = int64_t(begin.size());
  begin.push_back(n);
  std::vector<int64_t> next(begin.begin(), begin.end() - 1);  // each ray's first unqueried sample
  const float lim = float(max_log_density);
  // transmittance exp(-before) > min_transmittance, as a bound on the thickness (no exp)
  const double most = min_transmittance > 0 ? -std::log(min_transmittance) : INFINITY;
  const DensityQuery query(table, resolutions, offsets, log2_hashmap, w1, w2, bf16);
  // The queried samples' unit-cube midpoints and encodings, and each sample's row there (a
  // sample of a chunk of rays is queried into the rows of that chunk's samples); kept per
  // calling thread from call to call, so that their pages are not faulted in anew.
  thread_local std::vector<float> xq, encoded;
  thread_local std::vector<int64_t> row;
  xq.resize(std::max(xq.size(), size_t(n) * 3));
  encoded.resize(std::max(encoded.size(), size_t(n) * out_dim));
  row.resize(std::max(row.size(), size_t(n)));
  // (other threads of the parallel loops below see these through plain pointers: a
  // thread_local name would be their own, empty, copy)
  float *xqp = xq.data(), *encp = encoded.data();
  int64_t* rowp = row.data();
  // Chunks of rays holding about kVisibleChunk samples each march their rounds on one thread,
  // independently of the others: no serial step and no barrier between rounds.
  std::vector<int64_t> chunk{0};
  for (int64_t r = 1; r < rays; ++r)
    if (begin[r] - begin[chunk.back()] >= kVisibleChunk) chunk.push_back(r);
  chunk.push_back(rays);
  const int64_t chunks = int64_t(chunk.size()) - 1;
#pragma omp parallel num_threads(std::min<int64_t>(at::get_num_threads(), chunks))
  {
    query.begin();
    std::vector<int64_t> active, queried;
    std::vector<float> tau;
#pragma omp for schedule(dynamic, 1)
    for (int64_t c = 0; c < chunks; ++c) {
      active.clear();
      for (int64_t r = chunk[c]; r < chunk[c + 1]; ++r) active.push_back(r);
      std::vector<double> before(active.size(), 0.0);  // optical thickness so far, per ray
      const int64_t r0 = chunk[c];
      for (int64_t round = kVisibleRound, base = begin[r0]; !active.empty(); round *= 2) {
        queried.clear();
        for (const int64_t r : active)
          for (int64_t i = next[r]; i < std::min(next[r] + round, begin[r + 1]); ++i)
            queried.push_back(i);
        const int64_t m = int64_t(queried.size());
        for (int64_t j = 0; j < m; ++j) {
          const int64_t i = queried[j], r = rip[i];
          const float mid = 0.5f * (t0p[i] + t1p[i]);
          float* x = xqp + 3 * (base + j);
          for (int k = 0; k < 3; ++k)
            x[k] = (op[3 * r + k] + dp[3 * r + k] * mid - lo[k]) / size[k];
          rowp[i] = base + j;
        }
        tau.resize(m);
        query.serial(xqp + 3 * base, m, tau.data(), encp + base * out_dim);
        base += m;
        int64_t j = 0, still = 0;
        for (const int64_t r : active) {
          const int64_t stop = std::min(next[r] + round, begin[r + 1]);
          double& b = before[r - r0];
          bool cut = false;
          for (int64_t i = next[r]; i < stop; ++i, ++j) {
            if (cut) continue;
            if (b >= most) { cut = true; continue; }
            // the sample's optical thickness from its raw density
            const float raw = tau[j];
            const float t = std::exp(std::fmin(std::fmax(raw, -lim), lim)) * (t1p[i] - t0p[i]);
            b += std::isnan(t) || std::isnan(raw) ? 0.0 : double(std::fmin(std::fmax(t, 0.0f), 1e4f));
            next[r] = i + 1;
          }
          if (!cut && b < most && next[r] < begin[r + 1]) active[still++] = r;
        }
        active.resize(still);
      }
    }
    query.end();
  }
  // kept: each ray's samples before its cut (next[r]), in order; out[r] its first kept row
  std::vector<int64_t> out(rays + 1, 0);
  for (int64_t r = 0; r < rays; ++r) out[r + 1] = out[r] + next[r] - begin[r];
  // the batch: the first whole rays whose kept samples fit in max_kept (at least one ray;
  // nerf/batch.py's whole_rays), `runs` of the runs of samples
  int64_t runs = rays, batch_rays = n_rays;
  if (max_kept > 0 && out[rays] > max_kept) {
    int64_t r = 0;
    while (out[r + 1] <= max_kept) ++r;  // the first run that does not fit
    const int64_t first = rip[begin[r]];  // its ray: the rays before it fit
    batch_rays = std::max<int64_t>(first, 1);
    runs = first >= 1 ? r : 1;  // (or that ray alone, the first of all)
  }
  const int64_t k = out[runs];
  auto kept_ri = torch::empty({k}, ray_indices.options());
  auto kept_t0 = torch::empty({k}, t0.options()), kept_t1 = torch::empty({k}, t0.options());
  auto counts = torch::zeros({batch_rays}, ray_indices.options());
  auto kept = torch::empty({k, out_dim}, t0.options());
  auto unit = torch::empty({k, 3}, t0.options());
  int64_t* kri = kept_ri.data_ptr<int64_t>();
  int64_t* cp = counts.data_ptr<int64_t>();
  float *kp = kept.data_ptr<float>(), *up = unit.data_ptr<float>();
  float *k0 = kept_t0.data_ptr<float>(), *k1 = kept_t1.data_ptr<float>();
#pragma omp parallel for schedule(static) num_threads(at::get_num_threads()) if (k > 2048)
  for (int64_t r = 0; r < runs; ++r) {
    if (begin[r] < begin[r + 1]) cp[rip[begin[r]]] = next[r] - begin[r];
    for (int64_t i = begin[r], j = out[r]; i < next[r]; ++i, ++j) {
      kri[j] = rip[i], k0[j] = t0p[i], k1[j] = t1p[i];
      std::memcpy(kp + j * out_dim, encp + rowp[i] * out_dim, out_dim * 4);
      std::memcpy(up + 3 * j, xqp + 3 * rowp[i], 12);
    }
  }
  return {{kept_ri, kept_t0, kept_t1, counts, kept, unit}, out[rays]};
}

// One occupancy-grid update after its random draws (nerf/occupancy.py's update): the optical
// thickness density * step_size at a jittered point of each sampled cell (cells [M] flat
// x-major indices of a res^3 grid over grid_box [2, 3] (min, max), jitter [M, 3] in [0, 1)),
// the point encoded in the unit cube of the field's box (box [2, 3]: min corner and size);
// density = exp(raw clamped to +-max_log_density), NaN -> 0. Folded into the grid's EMA
// (density [res^3]): new = max(old * decay, 0, each sampled point's thickness in the cell).
// Returns {new density, occupied bool [res^3]: new > min(threshold, mean(new)), and allowed
// (bool [res^3], or empty for every cell)}.
std::vector<torch::Tensor> grid_refresh(torch::Tensor density, torch::Tensor allowed,
                                        torch::Tensor cells, torch::Tensor jitter,
                                        torch::Tensor grid_box, torch::Tensor box, int64_t res,
                                        double step_size, double decay, double threshold,
                                        torch::Tensor table, std::vector<int64_t> resolutions,
                                        std::vector<int64_t> offsets, int64_t log2_hashmap,
                                        torch::Tensor w1, torch::Tensor w2,
                                        double max_log_density, bool bf16) {
  const int64_t n = density.numel(), m = cells.numel();
  TORCH_CHECK(res >= 1 && res <= 1024 && n == res * res * res, "density must hold res^3 cells");
  TORCH_CHECK(density.scalar_type() == torch::kFloat32 && cells.scalar_type() == torch::kInt64 &&
                  jitter.scalar_type() == torch::kFloat32 && jitter.numel() == 3 * m &&
                  grid_box.numel() == 6 && box.numel() == 6,
              "density float32 [res^3], cells int64 [M], jitter float32 [M, 3], boxes [2, 3]");
  TORCH_CHECK(allowed.numel() == 0 || (allowed.numel() == n && allowed.scalar_type() == torch::kBool),
              "allowed must be bool [res^3] or empty");
  const auto old = density.contiguous(), c = cells.contiguous(), j = jitter.contiguous();
  const auto gb = grid_box.contiguous(), fb = box.contiguous(), ok = allowed.contiguous();
  const float *op = old.data_ptr<float>(), *jp = j.data_ptr<float>();
  const float *g = gb.data_ptr<float>(), *b = fb.data_ptr<float>();
  const int64_t* cp = c.data_ptr<int64_t>();
  std::vector<float> x(3 * m);
  bool bad = false;
  const int nt = at::get_num_threads();
#pragma omp parallel for schedule(static) num_threads(nt) reduction(|| : bad)
  for (int64_t i = 0; i < m; ++i) {
    const int64_t cell = cp[i];
    if (cell < 0 || cell >= n) { bad = true; continue; }
    const int64_t ijk[3] = {cell / (res * res), (cell / res) % res, cell % res};
    for (int k = 0; k < 3; ++k) {
      const float p = g[k] + (float(ijk[k]) + jp[3 * i + k]) / float(res) * (g[3 + k] - g[k]);
      x[3 * i + k] = (p - b[k]) / b[3 + k];
    }
  }
  TORCH_CHECK(!bad, "a cell index is out of the grid");
  std::vector<float> raw(m);
  const DensityQuery query(table, resolutions, offsets, log2_hashmap, w1, w2, bf16);
  query(x.data(), m, raw.data(), nullptr);
  auto fresh = torch::empty({n}, old.options());
  float* np = fresh.data_ptr<float>();
  const float d = float(decay), lim = float(max_log_density), step = float(step_size);
#pragma omp parallel num_threads(nt)
  {
#pragma omp for schedule(static) nowait
    for (int64_t i = 0; i < n; ++i) np[i] = std::max(op[i] * d, 0.0f);
#pragma omp for schedule(static)
    for (int64_t i = 0; i < m; ++i)  // the points' thicknesses, in place of their raw densities
      raw[i] = std::exp(std::fmin(std::fmax(raw[i], -lim), lim)) * step;
  }
  for (int64_t i = 0; i < m; ++i)  // the cells' maxima in order (cells repeat across points)
    if (!std::isnan(raw[i])) np[cp[i]] = std::max(np[cp[i]], raw[i]);
  double sum = 0.0;
#pragma omp parallel for schedule(static) num_threads(nt) reduction(+ : sum)
  for (int64_t i = 0; i < n; ++i) sum += np[i];
  const float cut = std::min(float(threshold), float(sum / double(n)));
  auto occupied = torch::empty({n}, old.options().dtype(torch::kBool));
  bool* qp = occupied.data_ptr<bool>();
  const bool* ap = ok.numel() ? ok.data_ptr<bool>() : nullptr;
#pragma omp parallel for schedule(static) num_threads(nt)
  for (int64_t i = 0; i < n; ++i) qp[i] = np[i] > cut && (!ap || ap[i]);
  return {fresh, occupied};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  // the GIL is released while a kernel runs: another Python thread can work meanwhile
  m.def("forward", &hash_forward, "hash encoding forward: (x [N,3], table [R,F], ...) -> [N, L*F]",
        py::call_guard<py::gil_scoped_release>());
  m.def("amx", &amx::available, "whether the density queries can multiply on AMX tiles");
  m.def("density", &density_forward,
        "density MLP's first output fused with the encoding: (x, table, ..., w1, w2, keep, bf16) "
        "-> "
        "(raw [N], encoded [N, L*F] or empty)",
        py::call_guard<py::gil_scoped_release>());
  m.def("visible", &visible_forward,
        "compaction's pre-pass: (origins, dirs, t_starts, t_ends, ray_indices, box, table, ..., "
        "w1, w2, max_log_density, min_transmittance, bf16, max_kept) -> the kept samples' (ray "
        "indices, t_starts, t_ends, counts per ray, encodings, unit points), and their count "
        "before the batch's cut",
        py::call_guard<py::gil_scoped_release>());
  m.def("backward", &hash_backward, "hash encoding backward: scatter-add of grad_out into the table",
        py::call_guard<py::gil_scoped_release>());
  m.def("grid_refresh", &grid_refresh,
        "an occupancy-grid update after its draws: (density, allowed, cells, jitter, grid_box, "
        "box, res, step_size, decay, threshold, table, ..., w1, w2, max_log_density, bf16) -> "
        "(new density, occupied)",
        py::call_guard<py::gil_scoped_release>());
}
