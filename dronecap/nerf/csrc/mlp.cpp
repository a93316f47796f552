// The radiance field's two MLPs fused on the CPU, forward and backward, for the training pass.
//
// Layers (bias-free, as nerf/field.py builds them; every preset has this shape):
//   h1 = relu(W1 e)            e: the hash encoding [E]           W1 [H, E]
//   g  = W2 h1                 g[0]: density logit, g: geometry   W2 [G, H]
//   h2 = relu(W3 [g, d])       d: SH of the ray's direction [S]   W3 [H, G + S]
//   h3 = relu(W4 h2)                                              W4 [H, H]
//   c  = W5 h3                 colour logits [C]                  W5 [C, H]
// Forward returns [N, 1 + C]: g[0] and c (the density and colour activations stay in torch).
// Backward recomputes the forward of a tile and returns the gradients of e and of W1..W5.
//
// Why: with torch each layer is a matrix product over the whole batch followed by a ReLU pass,
// and every [N, 64] activation (2 MB at 8k samples) leaves the 2 MB L2 cache between ops; here
// a tile of 32 samples goes through all layers (and their backward) while it sits in L1, and
// each product is a register-blocked loop of broadcast multiply-adds.
//
// Vectors are GCC vector extensions of 16 floats: one AVX-512 register, two AVX2 registers, or
// whatever the target has, so the one code path builds everywhere. Widths that are not a
// multiple of 16 (C = 1 or 3, any E, G, S) are zero-padded in the transposed copies and tiles;
// padded rows and columns contribute nothing.
#include <torch/extension.h>

#include <ATen/Parallel.h>
#include <omp.h>

#if defined(__AMX_BF16__) && defined(__AMX_TILE__) && defined(__AVX512BF16__)
#define DRONECAP_AMX 1
#include <immintrin.h>
#include <sys/syscall.h>
#include <unistd.h>
#endif

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <memory>
#include <vector>

namespace {

typedef float v16 __attribute__((vector_size(64)));
constexpr int kW = 16;     // floats per vector
constexpr int kTile = 32;  // samples per tile (a multiple of 8)

inline v16 vload(const float* p) {
  v16 v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}
inline void vstore(float* p, v16 v) { std::memcpy(p, &v, sizeof(v)); }
inline int pad16(int n) { return (n + kW - 1) / kW * kW; }

// What a product does with its result before storing it.
enum Out { kPlain, kRelu, kMask };

// Y[p, :] = sum_k X[p, k] * M[k, :] for P rows p, with NV vectors of output per row.
// X [P, ldx] (n_in used), M [n_in, NV*16], Y [P, ldy]; kRelu stores max(y, 0), kMask stores y
// where mask[p, :] > 0 and 0 elsewhere (the ReLU's backward; mask has Y's layout).
template <int P, int NV>
inline void rows(const float* x, int ldx, int n_in, const float* m, float* y, int ldy, Out out,
                 const float* mask) {
  v16 acc[P][NV];
  for (int p = 0; p < P; ++p)
    for (int q = 0; q < NV; ++q) acc[p][q] = v16{};
  for (int k = 0; k < n_in; ++k) {
    v16 w[NV];
    for (int q = 0; q < NV; ++q) w[q] = vload(m + k * NV * kW + q * kW);
    for (int p = 0; p < P; ++p) {
      const float s = x[p * ldx + k];
      for (int q = 0; q < NV; ++q) acc[p][q] += s * w[q];
    }
  }
  for (int p = 0; p < P; ++p) {
    for (int q = 0; q < NV; ++q) {
      v16 v = acc[p][q];
      if (out == kRelu) v = v > v16{} ? v : v16{};
      if (out == kMask) v = vload(mask + p * ldy + q * kW) > v16{} ? v : v16{};
      vstore(y + p * ldy + q * kW, v);
    }
  }
}

// The product above for a whole tile (kTile rows), output width n_out (a multiple of 16,
// at most 128); picks row and vector blocking that keep ~16 accumulators in registers.
void tile_product(const float* x, int ldx, int n_in, const float* m, int n_out, float* y, int ldy,
                  Out out, const float* mask) {
  for (int q0 = 0; q0 < n_out; q0 += 4 * kW) {
    const int nv = std::min(4, (n_out - q0) / kW);
    const float* mq = m + q0;
    // M's rows are n_out wide: copy the block's columns contiguously when they are not all
    float block[128 * 4 * kW];
    if (nv * kW != n_out) {
      for (int k = 0; k < n_in; ++k) std::memcpy(block + k * nv * kW, mq + k * n_out, nv * kW * 4);
      mq = block;
    }
    const float* mk = mask ? mask + q0 : nullptr;
    for (int p = 0; p < kTile; p += (nv >= 2 ? 4 : 8)) {
      const float* xp = x + p * ldx;
      float* yp = y + p * ldy + q0;
      const float* mp = mk ? mk + p * ldy : nullptr;
      switch (nv) {
        case 4: rows<4, 4>(xp, ldx, n_in, mq, yp, ldy, out, mp); break;
        case 3: rows<4, 3>(xp, ldx, n_in, mq, yp, ldy, out, mp); break;
        case 2: rows<4, 2>(xp, ldx, n_in, mq, yp, ldy, out, mp); break;
        default: rows<8, 1>(xp, ldx, n_in, mq, yp, ldy, out, mp); break;
      }
    }
  }
}

// dW[j, :] += sum_p dY[p, j] * X[p, :] over the tile's rows: dW [n_rows, ldw] (ldw a multiple of
// 16, the X width used), dY [kTile, ldd], X [kTile, ldx]. J rows of dW at a time in registers.
template <int J, int NV>
inline void outer_rows(const float* dy, int ldd, const float* x, int ldx, float* dw, int ldw) {
  v16 acc[J][NV];
  for (int j = 0; j < J; ++j)
    for (int q = 0; q < NV; ++q) acc[j][q] = vload(dw + j * ldw + q * kW);
  for (int p = 0; p < kTile; ++p) {
    v16 xv[NV];
    for (int q = 0; q < NV; ++q) xv[q] = vload(x + p * ldx + q * kW);
    for (int j = 0; j < J; ++j) {
      const float s = dy[p * ldd + j];
      for (int q = 0; q < NV; ++q) acc[j][q] += s * xv[q];
    }
  }
  for (int j = 0; j < J; ++j)
    for (int q = 0; q < NV; ++q) vstore(dw + j * ldw + q * kW, acc[j][q]);
}

void tile_outer(const float* dy, int ldd, int n_rows, const float* x, int ldx, int width,
                float* dw) {
  for (int q0 = 0; q0 < width; q0 += 4 * kW) {
    const int nv = std::min(4, (width - q0) / kW);
    int j = 0;
    for (; j + 4 <= n_rows && nv >= 3; j += 4) {
      if (nv == 4) outer_rows<4, 4>(dy + j, ldd, x + q0, ldx, dw + j * width + q0, width);
      else outer_rows<4, 3>(dy + j, ldd, x + q0, ldx, dw + j * width + q0, width);
    }
    for (; j + 8 <= n_rows && nv <= 2; j += 8) {
      if (nv == 2) outer_rows<8, 2>(dy + j, ldd, x + q0, ldx, dw + j * width + q0, width);
      else outer_rows<8, 1>(dy + j, ldd, x + q0, ldx, dw + j * width + q0, width);
    }
    for (; j < n_rows; ++j) {
      switch (nv) {
        case 4: outer_rows<1, 4>(dy + j, ldd, x + q0, ldx, dw + j * width + q0, width); break;
        case 3: outer_rows<1, 3>(dy + j, ldd, x + q0, ldx, dw + j * width + q0, width); break;
        case 2: outer_rows<1, 2>(dy + j, ldd, x + q0, ldx, dw + j * width + q0, width); break;
        default: outer_rows<1, 1>(dy + j, ldd, x + q0, ldx, dw + j * width + q0, width); break;
      }
    }
  }
}

// A [rows, cols] float32 matrix copied into [rows_to, cols_to] zero-padded storage, optionally
// transposed first.
std::vector<float> padded(const torch::Tensor& w, bool transpose, int rows_to, int cols_to) {
  const auto src = (transpose ? w.t() : w).contiguous();
  const int r = int(src.size(0)), c = int(src.size(1));
  std::vector<float> out(size_t(rows_to) * cols_to, 0.0f);
  const float* s = src.data_ptr<float>();
  for (int i = 0; i < r; ++i) std::memcpy(out.data() + size_t(i) * cols_to, s + size_t(i) * c, c * 4);
  return out;
}

// ---- bf16 products on AMX tiles (Intel Sapphire Rapids and later) ----
//
// With `bf16` the products' inputs are rounded to bfloat16 and multiplied on the AMX tile unit,
// which sums in float32 (TDPBF16PS: a 16 x 32 by 32 x 16 product per instruction, ~16x the
// AVX-512 float32 rate); outputs, ReLUs and the weight gradients (the outer products) stay
// float32. A tile register here is always 16 rows of 64 bytes: 16 x 16 floats (a result),
// 16 x 32 bf16 (an input block: 16 samples, 32 reduction columns), or 16 pairs of weight rows
// interleaved (a weight block: 32 reduction rows, 16 output columns).

typedef uint16_t bf16;  // bfloat16 bits
inline int pad32(int n) { return (n + 31) / 32 * 32; }

// float32 -> bfloat16, rounded to nearest even (as the AVX-512 conversion instructions do).
inline bf16 to_bf16(float f) {
  uint32_t u;
  std::memcpy(&u, &f, 4);
  return bf16((u + 0x7fffu + ((u >> 16) & 1u)) >> 16);
}

// M [n_in, n_out] (n_out a multiple of 16) as AMX weight blocks: block (kc, nb) covers rows
// 32 kc .. 32 kc + 31 and columns 16 nb .. 16 nb + 15; its row r holds M[32 kc + 2r][c] and
// M[32 kc + 2r + 1][c] side by side for each of the 16 columns c. Rows beyond n_in are zeros.
std::vector<bf16> pack_bf16(const std::vector<float>& m, int n_in, int n_out) {
  const int kp = pad32(n_in), nbt = n_out / kW;
  std::vector<bf16> out(size_t(kp) * n_out, 0);
  for (int k = 0; k < n_in; ++k)
    for (int c = 0; c < n_out; ++c) {
      const size_t block = size_t(k / 32) * nbt + c / kW;
      out[block * 512 + (k % 32) / 2 * 32 + (c % kW) * 2 + k % 2] = to_bf16(m[size_t(k) * n_out + c]);
    }
  return out;
}

// Whether this process can run the AMX products: built for a CPU with AMX-BF16 (-march=native)
// and granted the tile state by Linux (asked once per process).
bool amx_available() {
#ifdef DRONECAP_AMX
  static const bool ok = syscall(SYS_arch_prctl, 0x1023 /* ARCH_REQ_XCOMP_PERM */,
                                 18 /* XFEATURE_XTILEDATA */) == 0;
  return ok;
#else
  return false;
#endif
}

#ifdef DRONECAP_AMX
// Loads the one tile configuration (8 registers of 16 x 64 bytes) for this thread.
void amx_begin() {
  struct {
    uint8_t palette, start_row, reserved[14];
    uint16_t colsb[16];
    uint8_t rows[16];
  } cfg{};
  cfg.palette = 1;
  for (int i = 0; i < 8; ++i) cfg.colsb[i] = 64, cfg.rows[i] = 16;
  _tile_loadconfig(&cfg);
}
void amx_end() { _tile_release(); }

// X [kTile, n] float32 rows -> bf16 rows of ldo (a multiple of 32) columns, zeros beyond n.
void rows_to_bf16(const float* x, int ldx, int n, bf16* o, int ldo) {
  for (int p = 0; p < kTile; ++p)
    for (int c = 0; c < ldo; c += 32) {
      const int lo = std::clamp(n - c, 0, 16), hi = std::clamp(n - c - 16, 0, 16);
      const __m512 a = _mm512_maskz_loadu_ps(__mmask16((1u << lo) - 1), x + p * ldx + c);
      const __m512 b = _mm512_maskz_loadu_ps(__mmask16((1u << hi) - 1), x + p * ldx + c + 16);
      _mm512_storeu_si512(o + p * ldo + c, (__m512i)_mm512_cvtne2ps_pbh(b, a));
    }
}

// Y[16 rows, NB x 16 columns from 16 nb0] = X[16, kp] M for one 16-row group; tiles 0..3 hold
// the results, 4 the input block, 6 and 7 the weight blocks. (Tile numbers are immediates.)
template <int NB>
inline void amx_rows(const bf16* x, int kp, const bf16* m, int nbt, int nb0, float* y, int ldy) {
  _tile_zero(0);
  if (NB > 1) _tile_zero(1);
  if (NB > 2) _tile_zero(2);
  if (NB > 3) _tile_zero(3);
  for (int kc = 0; kc < kp / 32; ++kc) {
    _tile_loadd(4, x + kc * 32, kp * 2);
    const bf16* b = m + (size_t(kc) * nbt + nb0) * 512;
    _tile_loadd(6, b, 64);
    _tile_dpbf16ps(0, 4, 6);
    if (NB > 1) { _tile_loadd(7, b + 512, 64); _tile_dpbf16ps(1, 4, 7); }
    if (NB > 2) { _tile_loadd(6, b + 1024, 64); _tile_dpbf16ps(2, 4, 6); }
    if (NB > 3) { _tile_loadd(7, b + 1536, 64); _tile_dpbf16ps(3, 4, 7); }
  }
  _tile_stored(0, y, ldy * 4);
  if (NB > 1) _tile_stored(1, y + 16, ldy * 4);
  if (NB > 2) _tile_stored(2, y + 32, ldy * 4);
  if (NB > 3) _tile_stored(3, y + 48, ldy * 4);
}

// amx_rows for both 16-row groups of the tile at once (NB = 1 or 2 column blocks): results in
// tiles 0..2 NB - 1, so that narrow layers still have independent sums in flight.
template <int NB>
inline void amx_rows2(const bf16* x, int kp, const bf16* m, int nbt, int nb0, float* y, int ldy) {
  _tile_zero(0);
  _tile_zero(1);
  if (NB > 1) { _tile_zero(2); _tile_zero(3); }
  for (int kc = 0; kc < kp / 32; ++kc) {
    _tile_loadd(4, x + kc * 32, kp * 2);
    _tile_loadd(5, x + 16 * kp + kc * 32, kp * 2);
    const bf16* b = m + (size_t(kc) * nbt + nb0) * 512;
    _tile_loadd(6, b, 64);
    _tile_dpbf16ps(0, 4, 6);
    _tile_dpbf16ps(1, 5, 6);
    if (NB > 1) {
      _tile_loadd(7, b + 512, 64);
      _tile_dpbf16ps(2, 4, 7);
      _tile_dpbf16ps(3, 5, 7);
    }
  }
  _tile_stored(0, y, ldy * 4);
  _tile_stored(1, y + 16 * ldy, ldy * 4);
  if (NB > 1) { _tile_stored(2, y + 16, ldy * 4); _tile_stored(3, y + 16 * ldy + 16, ldy * 4); }
}

// tile_product's result from bf16 inputs X [kTile, kp] and packed weights (pack_bf16).
void amx_product(const bf16* x, int kp, const bf16* m, int n_out, float* y, int ldy, Out out,
                 const float* mask) {
  const int nbt = n_out / kW;
  static_assert(kTile == 32, "a tile is two 16-row groups");
  if (nbt <= 2) {
    if (nbt == 2) amx_rows2<2>(x, kp, m, nbt, 0, y, ldy);
    else amx_rows2<1>(x, kp, m, nbt, 0, y, ldy);
  } else for (int r = 0; r < kTile; r += 16)
    for (int nb = 0; nb < nbt; nb += 4) {
      const bf16* xr = x + r * kp;
      float* yr = y + r * ldy + nb * kW;
      switch (std::min(4, nbt - nb)) {
        case 4: amx_rows<4>(xr, kp, m, nbt, nb, yr, ldy); break;
        case 3: amx_rows<3>(xr, kp, m, nbt, nb, yr, ldy); break;
        case 2: amx_rows<2>(xr, kp, m, nbt, nb, yr, ldy); break;
        default: amx_rows<1>(xr, kp, m, nbt, nb, yr, ldy); break;
      }
    }
  if (out == kPlain) return;
  for (int p = 0; p < kTile; ++p)
    for (int q = 0; q < n_out; q += kW) {
      const v16 v = vload(y + p * ldy + q);
      const v16 gate = out == kRelu ? v : vload(mask + p * ldy + q);
      vstore(y + p * ldy + q, gate > v16{} ? v : v16{});
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

// C [16, NB x 16] (row stride ldc floats) += (input block in tile 4) (weight blocks at b, each
// 512 apart): NB result tiles in flight, so that their loads, sums and stores overlap.
template <int NB>
inline void amx_sum_into(const bf16* b, float* c, int ldc) {
  _tile_loadd(0, c, ldc * 4);
  if (NB > 1) _tile_loadd(1, c + 16, ldc * 4);
  if (NB > 2) _tile_loadd(2, c + 32, ldc * 4);
  if (NB > 3) _tile_loadd(3, c + 48, ldc * 4);
  _tile_loadd(6, b, 64);
  _tile_dpbf16ps(0, 4, 6);
  if (NB > 1) { _tile_loadd(7, b + 512, 64); _tile_dpbf16ps(1, 4, 7); }
  if (NB > 2) { _tile_loadd(6, b + 1024, 64); _tile_dpbf16ps(2, 4, 6); }
  if (NB > 3) { _tile_loadd(7, b + 1536, 64); _tile_dpbf16ps(3, 4, 7); }
  _tile_stored(0, c, ldc * 4);
  if (NB > 1) _tile_stored(1, c + 16, ldc * 4);
  if (NB > 2) _tile_stored(2, c + 32, ldc * 4);
  if (NB > 3) _tile_stored(3, c + 48, ldc * 4);
}

// tile_outer on the AMX tiles: dW [n_rows (a multiple of 16), width] += dY^T X over the tile's
// kTile = 32 samples, with dY [kTile, ldd] and X [kTile, ldx] rounded to bf16. The input
// blocks are dY transposed (16 rows of dW by the 32 samples) and the weight blocks X with its
// sample pairs interleaved; dW's 16 x 16 blocks are loaded, summed into and stored.
void amx_outer(const float* dy, int ldd, int n_rows, const float* x, int ldx, int width, float* dw,
               bf16* scratch) {
  static_assert(kTile == 32, "a tile's samples are one AMX reduction block");
  bf16* xs = scratch;                    // width / 16 weight blocks of 512
  bf16* ys = scratch + size_t(width) * 32;  // n_rows / 16 input blocks of 512
  alignas(64) static const uint16_t pairs[32] = {0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21,
                                                 6, 22, 7, 23, 8, 24, 9, 25, 10, 26, 11, 27,
                                                 12, 28, 13, 29, 14, 30, 15, 31};
  const __m512i interleave = _mm512_load_si512(pairs);
  for (int kb = 0; kb < width / 16; ++kb)
    for (int r = 0; r < 16; ++r) {
      const __m512 a = _mm512_loadu_ps(x + (2 * r) * ldx + kb * 16);
      const __m512 b = _mm512_loadu_ps(x + (2 * r + 1) * ldx + kb * 16);
      const __m512i v = (__m512i)_mm512_cvtne2ps_pbh(b, a);
      _mm512_storeu_si512(xs + kb * 512 + r * 32, _mm512_permutexvar_epi16(interleave, v));
    }
  for (int jb = 0; jb < n_rows / 16; ++jb) {
    __m512 lo[16], hi[16];
    transpose16(dy + jb * 16, ldd, lo);
    transpose16(dy + 16 * ldd + jb * 16, ldd, hi);
    for (int j = 0; j < 16; ++j)
      _mm512_storeu_si512(ys + jb * 512 + j * 32, (__m512i)_mm512_cvtne2ps_pbh(hi[j], lo[j]));
  }
  for (int jb = 0; jb < n_rows / 16; ++jb) {
    _tile_loadd(4, ys + jb * 512, 64);
    for (int kb = 0; kb < width / 16; kb += 4) {
      float* c = dw + size_t(jb) * 16 * width + kb * 16;
      switch (std::min(4, width / 16 - kb)) {
        case 4: amx_sum_into<4>(xs + kb * 512, c, width); break;
        case 3: amx_sum_into<3>(xs + kb * 512, c, width); break;
        case 2: amx_sum_into<2>(xs + kb * 512, c, width); break;
        default: amx_sum_into<1>(xs + kb * 512, c, width); break;
      }
    }
  }
}
#else
void amx_begin() {}
void amx_end() {}
void rows_to_bf16(const float*, int, int, bf16*, int) {}
void amx_product(const bf16*, int, const bf16*, int, float*, int, Out, const float*) {}
void amx_outer(const float*, int, int, const float*, int, int, float*, bf16*) {}
#endif

// One product's weights: M [n_in, n_out] float32 (n_out a multiple of 16) and, for bf16
// products, M packed for the AMX tiles.
struct Layer {
  std::vector<float> m;
  int n_in, n_out;
  std::vector<bf16> packed;
};

Layer layer(const torch::Tensor& w, bool transpose, int rows_to, int cols_to, int n_in, bool bf16) {
  Layer l{padded(w, transpose, rows_to, cols_to), n_in, cols_to, {}};
  if (bf16) l.packed = pack_bf16(l.m, n_in, cols_to);
  return l;
}

struct Dims {
  int E, H, G, S, C;          // encoding, hidden, geometry, SH, colour widths
  int Ep, Gp, Cinp, Cp;       // padded to multiples of 16 (Cin = G + S)
};

// The five layers as the forward reads them (fwd: M = W^T [in, out_padded]) and as the
// backward's input gradients read them (bwd: M = W [out, in_padded]).
struct Weights {
  Layer fwd[5], bwd[5];
  bool bf16;
};

Weights prepare(const Dims& d, const torch::Tensor& w1, const torch::Tensor& w2,
                const torch::Tensor& w3, const torch::Tensor& w4, const torch::Tensor& w5,
                bool bf16) {
  const int cin = d.G + d.S;
  return {{layer(w1, true, d.E, d.H, d.E, bf16), layer(w2, true, d.H, d.Gp, d.H, bf16),
           layer(w3, true, cin, d.H, cin, bf16), layer(w4, true, d.H, d.H, d.H, bf16),
           layer(w5, true, d.H, d.Cp, d.H, bf16)},
          {layer(w1, false, d.H, d.Ep, d.H, bf16), layer(w2, false, d.G, d.H, d.G, bf16),
           layer(w3, false, d.H, d.Cinp, d.H, bf16), layer(w4, false, d.H, d.H, d.H, bf16),
           layer(w5, false, d.C, d.H, d.C, bf16)},
          bf16};
}

// One tile's inputs and activations (rows beyond the batch are zeros).
struct Tile {
  alignas(64) float e[kTile * 128];
  alignas(64) float cin[kTile * 128];
  alignas(64) float h1[kTile * 128];
  alignas(64) float g[kTile * 128];
  alignas(64) float h2[kTile * 128];
  alignas(64) float h3[kTile * 128];
  alignas(64) float c[kTile * 16];
  alignas(64) bf16 x[kTile * 256];  // bf16 products: rounded inputs, or amx_outer's blocks
};

// Y = X M for a tile with layer `l`: tile_product in float32, or on the AMX tiles with bf16
// inputs (X rounded into t.x first).
void apply(const Weights& w, const Layer& l, const float* x, int ldx, float* y, int ldy, Out out,
           const float* mask, Tile& t) {
  if (w.bf16) {
    rows_to_bf16(x, ldx, l.n_in, t.x, pad32(l.n_in));
    amx_product(t.x, pad32(l.n_in), l.packed.data(), l.n_out, y, ldy, out, mask);
  } else {
    tile_product(x, ldx, l.n_in, l.m.data(), l.n_out, y, ldy, out, mask);
  }
}

// dW [pad16(n_rows), width] += dY^T X over the tile (tile_outer, or on the AMX tiles).
void outer(const Weights& w, const float* dy, int ldd, int n_rows, const float* x, int ldx,
           int width, float* dw, Tile& t) {
  if (w.bf16) amx_outer(dy, ldd, pad16(n_rows), x, ldx, width, dw, t.x);
  else tile_outer(dy, ldd, n_rows, x, ldx, width, dw);
}

// Loads rows [n0, n0 + m) of e and the SH rows of their rays into the tile (zeros beyond),
// then runs the forward; without `colour` it stops before the last layer (the backward needs
// the activations, not the colour logits). Keeping the activations for the backward instead
// of computing them again measured no faster (lego steady step, 1 and 2 threads).
void forward_tile(const Dims& d, const Weights& w, const float* e, const float* sh,
                  const int64_t* ri, int64_t n0, int m, Tile& t, bool colour) {
  std::fill(t.e, t.e + kTile * d.Ep, 0.0f);
  std::fill(t.cin, t.cin + kTile * d.Cinp, 0.0f);
  for (int p = 0; p < m; ++p) {
    std::memcpy(t.e + p * d.Ep, e + (n0 + p) * d.E, d.E * 4);
    std::memcpy(t.cin + p * d.Cinp + d.G, sh + ri[n0 + p] * d.S, d.S * 4);
  }
  apply(w, w.fwd[0], t.e, d.Ep, t.h1, d.H, kRelu, nullptr, t);
  apply(w, w.fwd[1], t.h1, d.H, t.g, d.Gp, kPlain, nullptr, t);
  for (int p = 0; p < kTile; ++p) std::memcpy(t.cin + p * d.Cinp, t.g + p * d.Gp, d.G * 4);
  apply(w, w.fwd[2], t.cin, d.Cinp, t.h2, d.H, kRelu, nullptr, t);
  apply(w, w.fwd[3], t.h2, d.H, t.h3, d.H, kRelu, nullptr, t);
  if (colour) apply(w, w.fwd[4], t.h3, d.H, t.c, d.Cp, kPlain, nullptr, t);
}

Dims dims_of(const torch::Tensor& e, const torch::Tensor& sh, const torch::Tensor& ri,
             const torch::Tensor& w1, const torch::Tensor& w2, const torch::Tensor& w3,
             const torch::Tensor& w4, const torch::Tensor& w5, bool bf16) {
  TORCH_CHECK(!bf16 || amx_available(), "bf16 products need AMX-BF16 tiles, which this CPU or process lacks");
  for (const auto* t : {&e, &sh, &w1, &w2, &w3, &w4, &w5}) {
    TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == torch::kFloat32 && t->dim() == 2,
                "float32 CPU matrices expected");
  }
  TORCH_CHECK(ri.scalar_type() == torch::kInt64 && ri.dim() == 1 && ri.size(0) == e.size(0),
              "ray_indices must be int64 [N]");
  Dims d;
  d.E = int(e.size(1)), d.H = int(w1.size(0)), d.G = int(w2.size(0)), d.S = int(sh.size(1));
  d.C = int(w5.size(0));
  TORCH_CHECK(d.H % kW == 0 && d.H <= 128, "hidden width must be a multiple of 16, at most 128");
  TORCH_CHECK(d.E <= 128 && d.G + d.S <= 128 && d.C <= 16, "layer widths out of range");
  TORCH_CHECK(w1.size(1) == d.E && w2.size(1) == d.H && w3.size(0) == d.H &&
                  w3.size(1) == d.G + d.S && w4.size(0) == d.H && w4.size(1) == d.H &&
                  w5.size(1) == d.H,
              "weight shapes do not chain");
  d.Ep = pad16(d.E), d.Gp = pad16(d.G), d.Cinp = pad16(d.G + d.S), d.Cp = pad16(d.C);
  return d;
}

}  // namespace

// e [N, E] encodings, sh [R, S] SH of each ray's direction, ri [N] each sample's ray.
// Returns [N, 1 + C]: the density logit and the colour logits.
torch::Tensor mlp_forward(torch::Tensor e, torch::Tensor sh, torch::Tensor ri, torch::Tensor w1,
                          torch::Tensor w2, torch::Tensor w3, torch::Tensor w4, torch::Tensor w5,
                          bool bf16) {
  e = e.contiguous(), sh = sh.contiguous(), ri = ri.contiguous();
  const Dims d = dims_of(e, sh, ri, w1, w2, w3, w4, w5, bf16);
  const Weights w = prepare(d, w1, w2, w3, w4, w5, bf16);
  const int64_t n = e.size(0);
  auto out = torch::empty({n, 1 + d.C}, e.options());
  const float *ep = e.data_ptr<float>(), *sp = sh.data_ptr<float>();
  const int64_t* rp = ri.data_ptr<int64_t>();
  float* op = out.data_ptr<float>();
  const int64_t tiles = (n + kTile - 1) / kTile;
#pragma omp parallel num_threads(at::get_num_threads())
  {
    std::unique_ptr<Tile> t(new Tile);
    if (bf16) amx_begin();
#pragma omp for schedule(static)
    for (int64_t b = 0; b < tiles; ++b) {
      const int64_t n0 = b * kTile;
      const int m = int(std::min<int64_t>(kTile, n - n0));
      forward_tile(d, w, ep, sp, rp, n0, m, *t, true);
      for (int p = 0; p < m; ++p) {
        float* o = op + (n0 + p) * (1 + d.C);
        o[0] = t->g[p * d.Gp];
        std::memcpy(o + 1, t->c + p * d.Cp, d.C * 4);
      }
    }
    if (bf16) amx_end();
  }
  return out;
}

// grad [N, 1 + C] of the forward's output; returns {grad_e [N, E], grad_w1, ..., grad_w5}.
std::vector<torch::Tensor> mlp_backward(torch::Tensor grad, torch::Tensor e, torch::Tensor sh,
                                        torch::Tensor ri, torch::Tensor w1, torch::Tensor w2,
                                        torch::Tensor w3, torch::Tensor w4, torch::Tensor w5,
                                        bool bf16) {
  e = e.contiguous(), sh = sh.contiguous(), ri = ri.contiguous(), grad = grad.contiguous();
  const Dims d = dims_of(e, sh, ri, w1, w2, w3, w4, w5, bf16);
  TORCH_CHECK(grad.scalar_type() == torch::kFloat32 && grad.size(0) == e.size(0) &&
                  grad.size(1) == 1 + d.C, "grad must be float32 [N, 1 + C]");
  const Weights w = prepare(d, w1, w2, w3, w4, w5, bf16);
  const int64_t n = e.size(0);
  const int cin = d.G + d.S;
  // per-thread weight gradients, laid out [out, in_padded] as the backward weights
  // (rows padded to 16: the AMX sums write whole 16-row blocks)
  const size_t s1 = size_t(d.H) * d.Ep, s2 = size_t(d.Gp) * d.H, s3 = size_t(d.H) * d.Cinp;
  const size_t s4 = size_t(d.H) * d.H, s5 = size_t(d.Cp) * d.H, all = s1 + s2 + s3 + s4 + s5;
  const int nt = at::get_num_threads();
  std::vector<float> acc(size_t(nt) * all, 0.0f);
  auto grad_e = torch::empty({n, d.E}, e.options());
  const float *ep = e.data_ptr<float>(), *sp = sh.data_ptr<float>(), *gp = grad.data_ptr<float>();
  const int64_t* rp = ri.data_ptr<int64_t>();
  float* gep = grad_e.data_ptr<float>();
  const int64_t tiles = (n + kTile - 1) / kTile;
#pragma omp parallel num_threads(nt)
  {
    std::unique_ptr<Tile> t(new Tile), dt(new Tile);  // activations and their gradients
    float* a = acc.data() + size_t(omp_get_thread_num()) * all;
    float *a1 = a, *a2 = a1 + s1, *a3 = a2 + s2, *a4 = a3 + s3, *a5 = a4 + s4;
    if (bf16) amx_begin();
#pragma omp for schedule(static)
    for (int64_t b = 0; b < tiles; ++b) {
      const int64_t n0 = b * kTile;
      const int m = int(std::min<int64_t>(kTile, n - n0));
      forward_tile(d, w, ep, sp, rp, n0, m, *t, false);
      // dc: colour-logit gradients (padded to Cp); rows beyond m are zero
      std::fill(dt->c, dt->c + kTile * d.Cp, 0.0f);
      for (int p = 0; p < m; ++p) std::memcpy(dt->c + p * d.Cp, gp + (n0 + p) * (1 + d.C) + 1, d.C * 4);
      apply(w, w.bwd[4], dt->c, d.Cp, dt->h3, d.H, kMask, t->h3, *dt);
      outer(w, dt->c, d.Cp, d.C, t->h3, d.H, d.H, a5, *dt);
      apply(w, w.bwd[3], dt->h3, d.H, dt->h2, d.H, kMask, t->h2, *dt);
      outer(w, dt->h3, d.H, d.H, t->h2, d.H, d.H, a4, *dt);
      apply(w, w.bwd[2], dt->h2, d.H, dt->cin, d.Cinp, kPlain, nullptr, *dt);
      outer(w, dt->h2, d.H, d.H, t->cin, d.Cinp, d.Cinp, a3, *dt);
      // dg: the geometry part of dcin, plus the density logit's gradient on g[0]
      for (int p = 0; p < kTile; ++p) {
        float* dg = dt->g + p * d.Gp;
        std::memcpy(dg, dt->cin + p * d.Cinp, d.G * 4);
        std::fill(dg + d.G, dg + d.Gp, 0.0f);
        if (p < m) dg[0] += gp[(n0 + p) * (1 + d.C)];
      }
      apply(w, w.bwd[1], dt->g, d.Gp, dt->h1, d.H, kMask, t->h1, *dt);
      outer(w, dt->g, d.Gp, d.G, t->h1, d.H, d.H, a2, *dt);
      apply(w, w.bwd[0], dt->h1, d.H, dt->e, d.Ep, kPlain, nullptr, *dt);
      outer(w, dt->h1, d.H, d.H, t->e, d.Ep, d.Ep, a1, *dt);
      for (int p = 0; p < m; ++p) std::memcpy(gep + (n0 + p) * d.E, dt->e + p * d.Ep, d.E * 4);
    }
    if (bf16) amx_end();
  }
  // sum the threads' gradients and drop the padding
  for (int k = 1; k < nt; ++k)
    for (size_t i = 0; i < all; ++i) acc[i] += acc[size_t(k) * all + i];
  auto unpad = [&](const float* src, int rows_, int ld, int cols) {
    auto out = torch::empty({rows_, cols}, e.options());
    float* o = out.data_ptr<float>();
    for (int i = 0; i < rows_; ++i) std::memcpy(o + size_t(i) * cols, src + size_t(i) * ld, cols * 4);
    return out;
  };
  const float* a = acc.data();
  return {grad_e,
          unpad(a, d.H, d.Ep, d.E),
          unpad(a + s1, d.G, d.H, d.H),
          unpad(a + s1 + s2, d.H, d.Cinp, cin),
          unpad(a + s1 + s2 + s3, d.H, d.H, d.H),
          unpad(a + s1 + s2 + s3 + s4, d.C, d.H, d.H)};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &mlp_forward, "fused field MLPs: (e, sh, ri, w1..w5) -> [N, 1 + C] logits",
        py::call_guard<py::gil_scoped_release>());
  m.def("amx", &amx_available, "whether bf16 products can run on this CPU's AMX tiles");
  m.def("backward", &mlp_backward, "fused field MLPs' backward: -> grad_e, grad_w1..grad_w5",
        py::call_guard<py::gil_scoped_release>());
}
