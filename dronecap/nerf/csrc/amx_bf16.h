// bf16 products on Intel's AMX tiles (Xeon 4th generation and later), the building blocks of
// mlp.cpp's bf16 path.
//
// TDPBF16PS multiplies a 16 x 32 bf16 block by a 32 x 16 one and sums into 16 x 16 floats: 8192
// multiply-adds per instruction, ~16x the AVX-512 float32 rate. Every tile register here is 16
// rows of 64 bytes, in one of three roles:
//   result  16 x 16 floats;
//   input   16 x 32 bf16: 16 rows (samples, or weight rows), 32 reduction columns;
//   weight  16 x 32 bf16: 32 reduction rows by 16 columns, rows paired (row r holds reduction
//           rows 2r and 2r + 1 side by side for each column: the "VNNI" layout).
// Activations live as bf16 rows [32 samples, pad32(width)], zero-padded: a layer's input block is
// a direct tile load. Sums, outputs and weight gradients are float32.
//
// Without AMX at build time (or with DRONECAP_NO_SIMD) only the layout helpers and
// amx_available() == false exist; mlp.cpp then runs float32 products only.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <vector>

#if defined(__AMX_BF16__) && defined(__AMX_TILE__) && defined(__AVX512BF16__) && \
    !defined(DRONECAP_NO_SIMD)
#define DRONECAP_AMX 1
#include <immintrin.h>
#include <sys/syscall.h>
#include <unistd.h>
#endif

namespace amx {

typedef uint16_t bf16;      // bfloat16 bits
constexpr int kRows = 32;   // samples per tile of mlp.cpp: two 16-row groups, one reduction block
inline int pad32(int n) { return (n + 31) / 32 * 32; }

// float32 -> bfloat16, rounded to nearest even (as the AVX-512 conversion instructions do).
inline bf16 to_bf16(float f) {
  uint32_t u;
  std::memcpy(&u, &f, 4);
  return bf16((u + 0x7fffu + ((u >> 16) & 1u)) >> 16);
}

// M [n_in, n_out] float32 (n_out a multiple of 16) as weight blocks: block (kc, nb) holds rows
// 32 kc .. 32 kc + 31 and columns 16 nb .. 16 nb + 15, 512 bf16 each, kc-major. Rows beyond n_in
// are zeros.
inline std::vector<bf16> pack(const std::vector<float>& m, int n_in, int n_out) {
  const int nbt = n_out / 16;
  std::vector<bf16> out(size_t(pad32(n_in)) * n_out, 0);
  for (int k = 0; k < n_in; ++k)
    for (int c = 0; c < n_out; ++c) {
      const size_t block = size_t(k / 32) * nbt + c / 16;
      out[block * 512 + (k % 32) / 2 * 32 + (c % 16) * 2 + k % 2] = to_bf16(m[size_t(k) * n_out + c]);
    }
  return out;
}

// Whether this process can run the AMX products: built for a CPU with AMX-BF16 (-march=native)
// and granted the tile state by Linux (asked once per process).
inline bool available() {
#ifdef DRONECAP_AMX
  static const bool ok = syscall(SYS_arch_prctl, 0x1023 /* ARCH_REQ_XCOMP_PERM */,
                                 18 /* XFEATURE_XTILEDATA */) == 0;
  return ok;
#else
  return false;
#endif
}

#ifdef DRONECAP_AMX

// Loads the tile configuration (8 registers of 16 x 64 bytes) for the calling thread.
inline void begin() {
  struct {
    uint8_t palette, start_row, reserved[14];
    uint16_t colsb[16];
    uint8_t rows[16];
  } cfg{};
  cfg.palette = 1;
  for (int i = 0; i < 8; ++i) cfg.colsb[i] = 64, cfg.rows[i] = 16;
  _tile_loadconfig(&cfg);
}
inline void end() { _tile_release(); }

// float32 rows x [rows, n] (row stride ldx) -> bf16 rows o [kRows, ldo] (ldo a multiple of 32),
// zeros beyond n columns and beyond `rows` rows.
inline void rows_to_bf16(const float* x, int ldx, int rows, int n, bf16* o, int ldo) {
  for (int p = 0; p < kRows; ++p)
    for (int c = 0; c < ldo; c += 32) {
      const int lo = p < rows ? std::clamp(n - c, 0, 16) : 0;
      const int hi = p < rows ? std::clamp(n - c - 16, 0, 16) : 0;
      const __m512 a = _mm512_maskz_loadu_ps(__mmask16((1u << lo) - 1), x + p * ldx + c);
      const __m512 b = _mm512_maskz_loadu_ps(__mmask16((1u << hi) - 1), x + p * ldx + c + 16);
      _mm512_storeu_si512(o + p * ldo + c, (__m512i)_mm512_cvtne2ps_pbh(b, a));
    }
}

// NB result tiles 0..NB-1 += (the input block in tile 4) (NB weight blocks at b, 512 apart,
// loaded into tiles 6 and 7 in turn). Tile numbers are immediates, hence the unrolled steps.
template <int NB>
inline void sum_blocks(const bf16* b) {
  _tile_loadd(6, b, 64);
  _tile_dpbf16ps(0, 4, 6);
  if (NB > 1) { _tile_loadd(7, b + 512, 64); _tile_dpbf16ps(1, 4, 7); }
  if (NB > 2) { _tile_loadd(6, b + 1024, 64); _tile_dpbf16ps(2, 4, 6); }
  if (NB > 3) { _tile_loadd(7, b + 1536, 64); _tile_dpbf16ps(3, 4, 7); }
}

// Result tiles 0..NB-1 loaded from / stored to C [16, NB x 16] floats, row stride ldc.
template <int NB>
inline void load_results(const float* c, int ldc) {
  _tile_loadd(0, c, ldc * 4);
  if (NB > 1) _tile_loadd(1, c + 16, ldc * 4);
  if (NB > 2) _tile_loadd(2, c + 32, ldc * 4);
  if (NB > 3) _tile_loadd(3, c + 48, ldc * 4);
}
template <int NB>
inline void store_results(float* c, int ldc) {
  _tile_stored(0, c, ldc * 4);
  if (NB > 1) _tile_stored(1, c + 16, ldc * 4);
  if (NB > 2) _tile_stored(2, c + 32, ldc * 4);
  if (NB > 3) _tile_stored(3, c + 48, ldc * 4);
}

// Y[16 rows, NB x 16 columns from block nb0] = X[16, kp] M for one 16-row group: results in
// tiles 0..3, the input block in 4, weight blocks in 6 and 7.
template <int NB>
inline void rows16(const bf16* x, int kp, const bf16* m, int nbt, int nb0, float* y, int ldy) {
  _tile_zero(0);
  if (NB > 1) _tile_zero(1);
  if (NB > 2) _tile_zero(2);
  if (NB > 3) _tile_zero(3);
  for (int kc = 0; kc < kp / 32; ++kc) {
    _tile_loadd(4, x + kc * 32, kp * 2);
    sum_blocks<NB>(m + (size_t(kc) * nbt + nb0) * 512);
  }
  store_results<NB>(y, ldy);
}

// The same for both 16-row groups at once (NB = 1 or 2 column blocks; results in tiles
// 0..2 NB - 1), so that narrow layers still have independent sums in flight.
template <int NB>
inline void rows32(const bf16* x, int kp, const bf16* m, int nbt, float* y, int ldy) {
  _tile_zero(0);
  _tile_zero(1);
  if (NB > 1) { _tile_zero(2); _tile_zero(3); }
  for (int kc = 0; kc < kp / 32; ++kc) {
    _tile_loadd(4, x + kc * 32, kp * 2);
    _tile_loadd(5, x + 16 * kp + kc * 32, kp * 2);
    _tile_loadd(6, m + size_t(kc) * nbt * 512, 64);
    _tile_dpbf16ps(0, 4, 6);
    _tile_dpbf16ps(1, 5, 6);
    if (NB > 1) {
      _tile_loadd(7, m + (size_t(kc) * nbt + 1) * 512, 64);
      _tile_dpbf16ps(2, 4, 7);
      _tile_dpbf16ps(3, 5, 7);
    }
  }
  _tile_stored(0, y, ldy * 4);
  _tile_stored(1, y + 16 * ldy, ldy * 4);
  if (NB > 1) { _tile_stored(2, y + 16, ldy * 4); _tile_stored(3, y + 16 * ldy + 16, ldy * 4); }
}

// Y [kRows, n_out] float32 = X M for bf16 rows X [kRows, kp] and packed weights M (pack(); n_out
// a multiple of 16, kp = pad32 of M's rows).
inline void product(const bf16* x, int kp, const bf16* m, int n_out, float* y, int ldy) {
  const int nbt = n_out / 16;
  if (nbt == 1) return rows32<1>(x, kp, m, nbt, y, ldy);
  if (nbt == 2) return rows32<2>(x, kp, m, nbt, y, ldy);
  for (int r = 0; r < kRows; r += 16)
    for (int nb = 0; nb < nbt; nb += 4) {
      const bf16* xr = x + r * kp;
      float* yr = y + r * ldy + nb * 16;
      switch (std::min(4, nbt - nb)) {
        case 4: rows16<4>(xr, kp, m, nbt, nb, yr, ldy); break;
        case 3: rows16<3>(xr, kp, m, nbt, nb, yr, ldy); break;
        case 2: rows16<2>(xr, kp, m, nbt, nb, yr, ldy); break;
        default: rows16<1>(xr, kp, m, nbt, nb, yr, ldy); break;
      }
    }
}

// After a product: Y [kRows, n_out] float32 through a ReLU (`relu`) or the ReLU's backward (zero
// where the layer's bf16 activation `gate` [kRows, pad32(n_out)] is zero; none: null), in place,
// and rounded to bf16 rows o [kRows, pad32(n_out)] (zero-padded) for the next product.
inline void finish(float* y, int ldy, int n_out, bool relu, const bf16* gate, bf16* o) {
  const int ldo = pad32(n_out);
  const __m512 zero = _mm512_setzero_ps();
  for (int p = 0; p < kRows; ++p)
    for (int c = 0; c < ldo; c += 32) {
      float* yp = y + p * ldy + c;
      const bool two = c + 16 < n_out;
      __m512 a = _mm512_loadu_ps(yp), b = two ? _mm512_loadu_ps(yp + 16) : zero;
      if (relu) a = _mm512_max_ps(a, zero), b = _mm512_max_ps(b, zero);
      if (gate) {  // a ReLU'd activation is nonzero where its bf16 bits are
        const __mmask32 on = _mm512_test_epi16_mask(_mm512_loadu_si512(gate + p * ldo + c),
                                                    _mm512_set1_epi16(-1));
        a = _mm512_maskz_mov_ps(__mmask16(on), a), b = _mm512_maskz_mov_ps(__mmask16(on >> 16), b);
      }
      _mm512_storeu_ps(yp, a);
      if (two) _mm512_storeu_ps(yp + 16, b);
      _mm512_storeu_si512(o + p * ldo + c, (__m512i)_mm512_cvtne2ps_pbh(b, a));
    }
}

// The 16 x 16 floats at src (row stride lds) transposed into out[16] (out[j] = column j):
// 4 x 4 transposes within each 128-bit lane, then a 4 x 4 transpose of the lanes.
inline void transpose16(const float* src, int lds, __m512 out[16]) {
  __m512 r[16], t[16];
  for (int i = 0; i < 16; ++i) r[i] = _mm512_loadu_ps(src + i * lds);
  for (int i = 0; i < 16; i += 2) {
    t[i] = _mm512_unpacklo_ps(r[i], r[i + 1]);
    t[i + 1] = _mm512_unpackhi_ps(r[i], r[i + 1]);
  }
  for (int i = 0; i < 16; i += 4) {
    const __m512d a = _mm512_castps_pd(t[i]), b = _mm512_castps_pd(t[i + 1]);
    const __m512d c = _mm512_castps_pd(t[i + 2]), d = _mm512_castps_pd(t[i + 3]);
    r[i] = _mm512_castpd_ps(_mm512_unpacklo_pd(a, c));
    r[i + 1] = _mm512_castpd_ps(_mm512_unpackhi_pd(a, c));
    r[i + 2] = _mm512_castpd_ps(_mm512_unpacklo_pd(b, d));
    r[i + 3] = _mm512_castpd_ps(_mm512_unpackhi_pd(b, d));
  }
  // r[4i + c] holds, in lane L, column 4L + c of rows 4i .. 4i + 3
  for (int c = 0; c < 4; ++c) {
    const __m512 u0 = _mm512_shuffle_f32x4(r[c], r[4 + c], 0x44);
    const __m512 u1 = _mm512_shuffle_f32x4(r[c], r[4 + c], 0xEE);
    const __m512 u2 = _mm512_shuffle_f32x4(r[8 + c], r[12 + c], 0x44);
    const __m512 u3 = _mm512_shuffle_f32x4(r[8 + c], r[12 + c], 0xEE);
    out[c] = _mm512_shuffle_f32x4(u0, u2, 0x88);
    out[4 + c] = _mm512_shuffle_f32x4(u0, u2, 0xDD);
    out[8 + c] = _mm512_shuffle_f32x4(u1, u3, 0x88);
    out[12 + c] = _mm512_shuffle_f32x4(u1, u3, 0xDD);
  }
}

// C [16, NB x 16] (row stride ldc floats) += sum over q < blocks of (input block a + 512 q nbr,
// loaded into tile 4) (weight blocks at b + 512 q nbw, 512 apart): NB result tiles in flight,
// loaded and stored once for all the blocks.
template <int NB>
inline void sum_into(const bf16* a, int nbr, const bf16* b, int nbw, int blocks, float* c,
                     int ldc) {
  load_results<NB>(c, ldc);
  for (int q = 0; q < blocks; ++q) {
    _tile_loadd(4, a + size_t(q) * nbr * 512, 64);
    sum_blocks<NB>(b + size_t(q) * nbw * 512);
  }
  store_results<NB>(c, ldc);
}

// The weight-gradient sums of one layer: dW [n_rows, width] += dY^T X over the samples of the
// tiles added, with dY [kRows, ldd] float32 (n_rows and width multiples of 16, at most 128) and
// X the layer's bf16 input rows [kRows, pad32(width)]. Each tile is kept as blocks (dY transposed
// and rounded: 16 rows of dW by the 32 samples; X with its sample pairs interleaved) and kBlocks
// tiles are summed into dW at a time, so dW's tiles are loaded and stored once per kBlocks x 32
// samples rather than once per 32 (a fifth of the bf16 backward's time). flush() sums what is
// kept; call it before dW is read.
struct OuterSums {
  static constexpr int kBlocks = 4;
  int n_rows = 0, width = 0, used = 0;
  float* dw = nullptr;
  alignas(64) bf16 ys[kBlocks * 128 * 32];  // per tile: n_rows / 16 input blocks of 512
  alignas(64) bf16 xs[kBlocks * 128 * 32];  // per tile: width / 16 weight blocks of 512

  void add(const float* dy, int ldd, int rows, const bf16* x, int cols, float* grad) {
    static_assert(kRows == 32, "a tile's samples are one reduction block");
    n_rows = rows, width = cols, dw = grad;
    const int ldx = pad32(width);
    bf16* xq = xs + size_t(used) * width * 32;
    bf16* yq = ys + size_t(used) * n_rows * 32;
    alignas(64) static const uint16_t pairs[32] = {0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21,
                                                   6, 22, 7, 23, 8, 24, 9, 25, 10, 26, 11, 27,
                                                   12, 28, 13, 29, 14, 30, 15, 31};
    const __m512i interleave = _mm512_load_si512(pairs);
    for (int kb = 0; kb < width / 16; ++kb)
      for (int r = 0; r < 16; ++r) {
        const __m256i a = _mm256_loadu_si256((const __m256i*)(x + (2 * r) * ldx + kb * 16));
        const __m256i b = _mm256_loadu_si256((const __m256i*)(x + (2 * r + 1) * ldx + kb * 16));
        const __m512i v = _mm512_inserti64x4(_mm512_castsi256_si512(a), b, 1);
        _mm512_storeu_si512(xq + kb * 512 + r * 32, _mm512_permutexvar_epi16(interleave, v));
      }
    for (int jb = 0; jb < n_rows / 16; ++jb) {
      __m512 lo[16], hi[16];
      transpose16(dy + jb * 16, ldd, lo);
      transpose16(dy + 16 * ldd + jb * 16, ldd, hi);
      for (int j = 0; j < 16; ++j)
        _mm512_storeu_si512(yq + jb * 512 + j * 32, (__m512i)_mm512_cvtne2ps_pbh(hi[j], lo[j]));
    }
    if (++used == kBlocks) flush();
  }

  void flush() {
    const int nbr = n_rows / 16, nbw = width / 16;
    for (int jb = 0; jb < nbr && used > 0; ++jb)
      for (int kb = 0; kb < nbw; kb += 4) {
        const bf16 *a = ys + jb * 512, *b = xs + kb * 512;
        float* c = dw + size_t(jb) * 16 * width + kb * 16;
        switch (std::min(4, nbw - kb)) {
          case 4: sum_into<4>(a, nbr, b, nbw, used, c, width); break;
          case 3: sum_into<3>(a, nbr, b, nbw, used, c, width); break;
          case 2: sum_into<2>(a, nbr, b, nbw, used, c, width); break;
          default: sum_into<1>(a, nbr, b, nbw, used, c, width); break;
        }
      }
    used = 0;
  }
};

#endif  // DRONECAP_AMX

}  // namespace amx
