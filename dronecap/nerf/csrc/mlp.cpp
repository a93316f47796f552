// The radiance field's two MLPs fused on the CPU, forward and backward, for the training pass.
//
// Layers (bias-free, as nerf/field.py builds them; every preset has this shape):
//   h1 = relu(W1 e)            e: the hash encoding [E]           W1 [H, E]
//   g  = W2 h1                 g[0]: density logit, g: geometry   W2 [G, H]
//   h2 = relu(W3 [g, d])       d: SH of the ray's direction [S]   W3 [H, G + S]
//   h3 = relu(W4 h2)                                              W4 [H, H]
//   c  = W5 h3                 colour logits [C]                  W5 [C, H]
// Forward returns the colour sigmoid(c) [N, C], the density exp(clamp(g[0], -lim, lim)) [N] and
// the logit g[0] [N] (which the backward's clamp gradient needs). Backward takes the gradients
// of colour and density, recomputes the forward of a tile and returns the gradients of e and
// of W1..W5.
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
//
// With `bf16` (a CPU with AMX-BF16 tiles) the same layers multiply bf16-rounded inputs on the
// AMX tile unit, summing in float32 (amx_bf16.h): ~4x fewer cycles per step for the MLPs.
#include <torch/extension.h>

#include <ATen/Parallel.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <type_traits>
#include <vector>

#include "amx_bf16.h"

namespace {

using amx::bf16;

typedef float v16 __attribute__((vector_size(64)));
constexpr int kW = 16;     // floats per vector
constexpr int kTile = 32;  // samples per tile (a multiple of 8)

inline v16 vload(const float* p) {
  v16 v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}
inline void vstore(float* p, v16 v) { std::memcpy(p, &v, sizeof(v)); }

// exp of 16 floats to ~1 ulp: x = n ln2 + r with |r| <= ln2 / 2, exp(r) by its Taylor series to
// r^7 (relative error < 6e-9), times 2^n through the exponent bits. Above ln(FLT_MAX) the result
// is inf (as std::exp overflows: a sigmoid then saturates to exactly 0), between 88.3 and that
// exp(88.3), below -87.3 exp(-87.3) (no denormals); NaN stays NaN.
inline v16 vexp(v16 x0) {
  typedef int32_t i16 __attribute__((vector_size(64)));
  const v16 zero = {};
  v16 x = x0 > 88.3f ? zero + 88.3f : x0;
  x = x < -87.3f ? zero - 87.3f : x;
  const v16 magic = zero + 12582912.0f;  // 1.5 * 2^23: adding it rounds to an integer
  const v16 n = (x * 1.44269504f + magic) - magic;
  const v16 r = (x - n * 0.693359375f) - n * -2.12194440e-4f;
  v16 p = zero + 1.0f / 5040;
  for (const float k : {1.0f / 720, 1.0f / 120, 1.0f / 24, 1.0f / 6, 0.5f, 1.0f, 1.0f}) p = p * r + k;
  const i16 bits = (__builtin_convertvector(n, i16) + 127) << 23;
  v16 scale;
  std::memcpy(&scale, &bits, sizeof(scale));
  return x0 > 88.7228f ? zero + INFINITY : p * scale;
}
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
// transposed first (plain loops over its strides: no torch op per weight and call).
std::vector<float> padded(const torch::Tensor& w, bool transpose, int rows_to, int cols_to) {
  const int64_t s0 = w.stride(0), s1 = w.stride(1);
  const int r = int(w.size(transpose ? 1 : 0)), c = int(w.size(transpose ? 0 : 1));
  const int64_t sr = transpose ? s1 : s0, sc = transpose ? s0 : s1;  // strides of out's rows, cols
  std::vector<float> out(size_t(rows_to) * cols_to, 0.0f);
  const float* s = w.data_ptr<float>();
  for (int i = 0; i < r; ++i)
    for (int j = 0; j < c; ++j) out[size_t(i) * cols_to + j] = s[i * sr + j * sc];
  return out;
}

// One product's weights: M [n_in, n_out] float32 (n_out a multiple of 16) and, for bf16
// products, M packed for the AMX tiles (amx::pack).
struct Layer {
  std::vector<float> m;
  int n_in, n_out;
  std::vector<bf16> packed;
};

Layer layer(const torch::Tensor& w, bool transpose, int rows_to, int cols_to, int n_in, bool bf16) {
  Layer l{padded(w, transpose, rows_to, cols_to), n_in, cols_to, {}};
  if (bf16) l.packed = amx::pack(l.m, n_in, cols_to);
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
           layer(w5, false, d.C, d.H, d.C, bf16)}};
}

// Per-thread weight gradients, laid out [out (padded to 16), in_padded] as the backward weights.
struct Grads {
  float* w[5];
};

// Copies the colour-logit gradients of rows [n0, n0 + m) into dc [kTile, Cp] (zeros beyond).
void colour_grads(const Dims& d, const float* gp, int64_t n0, int m, float* dc) {
  std::fill(dc, dc + kTile * d.Cp, 0.0f);
  for (int p = 0; p < m; ++p) std::memcpy(dc + p * d.Cp, gp + (n0 + p) * (1 + d.C) + 1, d.C * 4);
}

// dg [kTile, Gp] = the geometry part of dcin [kTile, Cinp], plus the density logit's gradient
// on g[0] (rows below m).
void geometry_grads(const Dims& d, const float* gp, int64_t n0, int m, const float* dcin,
                    float* dg) {
  for (int p = 0; p < kTile; ++p) {
    float* row = dg + p * d.Gp;
    std::memcpy(row, dcin + p * d.Cinp, d.G * 4);
    std::fill(row + d.G, row + d.Gp, 0.0f);
    if (p < m) row[0] += gp[(n0 + p) * (1 + d.C)];
  }
}

// ---- float32 products ----

// One tile's inputs and activations (rows beyond the batch are zeros).
struct Tile {
  alignas(64) float e[kTile * 128];
  alignas(64) float cin[kTile * 128];
  alignas(64) float h1[kTile * 128];
  alignas(64) float g[kTile * 128];
  alignas(64) float h2[kTile * 128];
  alignas(64) float h3[kTile * 128];
  alignas(64) float c[kTile * 16];
};

// A thread's working set: the activations (t) and their gradients (dt).
struct Fp32Work {
  Tile t, dt;
};

// Loads rows [n0, n0 + m) of e and the SH rows of their rays into the tile (zeros beyond),
// then runs the forward; without `colour` it stops before the last layer (the backward needs
// the activations, not the colour logits). Keeping the activations for the backward instead
// of computing them again measured no faster (lego steady step, 1 and 2 threads).
void forward_tile(const Dims& d, const Weights& w, const float* e, const float* sh,
                  const int64_t* ri, int64_t n0, int m, Fp32Work& k, bool colour) {
  Tile& t = k.t;
  std::fill(t.e, t.e + kTile * d.Ep, 0.0f);
  std::fill(t.cin, t.cin + kTile * d.Cinp, 0.0f);
  for (int p = 0; p < m; ++p) {
    std::memcpy(t.e + p * d.Ep, e + (n0 + p) * d.E, d.E * 4);
    std::memcpy(t.cin + p * d.Cinp + d.G, sh + ri[n0 + p] * d.S, d.S * 4);
  }
  tile_product(t.e, d.Ep, d.E, w.fwd[0].m.data(), d.H, t.h1, d.H, kRelu, nullptr);
  tile_product(t.h1, d.H, d.H, w.fwd[1].m.data(), d.Gp, t.g, d.Gp, kPlain, nullptr);
  for (int p = 0; p < kTile; ++p) std::memcpy(t.cin + p * d.Cinp, t.g + p * d.Gp, d.G * 4);
  tile_product(t.cin, d.Cinp, d.G + d.S, w.fwd[2].m.data(), d.H, t.h2, d.H, kRelu, nullptr);
  tile_product(t.h2, d.H, d.H, w.fwd[3].m.data(), d.H, t.h3, d.H, kRelu, nullptr);
  if (colour) tile_product(t.h3, d.H, d.H, w.fwd[4].m.data(), d.Cp, t.c, d.Cp, kPlain, nullptr);
}

// The forward of a tile again, then its backward: grad_e rows into ge, weight gradients
// summed into a.
void backward_tile(const Dims& d, const Weights& w, const float* e, const float* sh,
                   const int64_t* ri, const float* gp, int64_t n0, int m, Fp32Work& k,
                   const Grads& a, float* ge) {
  forward_tile(d, w, e, sh, ri, n0, m, k, false);
  Tile &t = k.t, &dt = k.dt;
  colour_grads(d, gp, n0, m, dt.c);
  tile_product(dt.c, d.Cp, d.C, w.bwd[4].m.data(), d.H, dt.h3, d.H, kMask, t.h3);
  tile_outer(dt.c, d.Cp, d.C, t.h3, d.H, d.H, a.w[4]);
  tile_product(dt.h3, d.H, d.H, w.bwd[3].m.data(), d.H, dt.h2, d.H, kMask, t.h2);
  tile_outer(dt.h3, d.H, d.H, t.h2, d.H, d.H, a.w[3]);
  tile_product(dt.h2, d.H, d.H, w.bwd[2].m.data(), d.Cinp, dt.cin, d.Cinp, kPlain, nullptr);
  tile_outer(dt.h2, d.H, d.H, t.cin, d.Cinp, d.Cinp, a.w[2]);
  geometry_grads(d, gp, n0, m, dt.cin, dt.g);
  tile_product(dt.g, d.Gp, d.G, w.bwd[1].m.data(), d.H, dt.h1, d.H, kMask, t.h1);
  tile_outer(dt.g, d.Gp, d.G, t.h1, d.H, d.H, a.w[1]);
  tile_product(dt.h1, d.H, d.H, w.bwd[0].m.data(), d.Ep, dt.e, d.Ep, kPlain, nullptr);
  tile_outer(dt.h1, d.H, d.H, t.e, d.Ep, d.Ep, a.w[0]);
  for (int p = 0; p < m; ++p) std::memcpy(ge + (n0 + p) * d.E, dt.e + p * d.Ep, d.E * 4);
}

void start(Fp32Work&) {}
void stop(Fp32Work&) {}

// ---- bf16 products on the AMX tiles (amx_bf16.h) ----
//
// The inputs of every product are rounded to bf16 and multiplied on the AMX tiles, which sum
// in float32; outputs, the ReLUs' gates and the weight gradients are float32. Activations are
// kept as the bf16 rows the next product reads.

#ifdef DRONECAP_AMX
struct Bf16Work {
  alignas(64) bf16 e[kTile * 128];    // [kTile, pad32(widths)] bf16 rows
  alignas(64) bf16 h1[kTile * 128];
  alignas(64) bf16 cin[kTile * 128];
  alignas(64) bf16 h2[kTile * 128];
  alignas(64) bf16 h3[kTile * 128];
  alignas(64) float g[kTile * 128];   // geometry outputs [kTile, Gp]
  alignas(64) float c[kTile * 16];    // colour logits [kTile, Cp]
  alignas(64) float fa[kTile * 128], fb[kTile * 128];  // float32 results and gradients
  alignas(64) bf16 ba[kTile * 128], bb[kTile * 128];   // the same rounded, for the next product
  amx::OuterSums sums[5];                              // the five layers' weight gradients
};

void forward_tile(const Dims& d, const Weights& w, const float* e, const float* sh,
                  const int64_t* ri, int64_t n0, int m, Bf16Work& t, bool colour) {
  using amx::pad32;
  const int h32 = pad32(d.H), cin32 = pad32(d.G + d.S);
  amx::rows_to_bf16(e + n0 * d.E, d.E, m, d.E, t.e, pad32(d.E));
  amx::product(t.e, pad32(d.E), w.fwd[0].packed.data(), d.H, t.fa, d.H);
  amx::finish(t.fa, d.H, d.H, true, nullptr, t.h1);
  amx::product(t.h1, h32, w.fwd[1].packed.data(), d.Gp, t.g, d.Gp);
  // cin = [g, SH of the ray] staged in float32 (zeros beyond m)
  std::fill(t.fb, t.fb + kTile * d.Cinp, 0.0f);
  for (int p = 0; p < kTile; ++p) std::memcpy(t.fb + p * d.Cinp, t.g + p * d.Gp, d.G * 4);
  for (int p = 0; p < m; ++p) std::memcpy(t.fb + p * d.Cinp + d.G, sh + ri[n0 + p] * d.S, d.S * 4);
  amx::rows_to_bf16(t.fb, d.Cinp, kTile, d.G + d.S, t.cin, cin32);
  amx::product(t.cin, cin32, w.fwd[2].packed.data(), d.H, t.fa, d.H);
  amx::finish(t.fa, d.H, d.H, true, nullptr, t.h2);
  amx::product(t.h2, h32, w.fwd[3].packed.data(), d.H, t.fa, d.H);
  amx::finish(t.fa, d.H, d.H, true, nullptr, t.h3);
  if (colour) amx::product(t.h3, h32, w.fwd[4].packed.data(), d.Cp, t.c, d.Cp);
}

// The backward of a layer whose input x (bf16 rows [kTile, pad32(H)]) is a hidden ReLU's
// output: dW [pad16(n_out), H] += dY^T x, then dX = (dY W) where x > 0, into dx (float32 [kTile, H])
// and dxb (its bf16 rows). dY: float32 dy [kTile, pad16(n_out)] and its bf16 rows dyb; `l` is
// the layer as the backward reads it (its n_in is the forward's n_out).
void hidden_backward(const Dims& d, const Layer& l, const float* dy, const bf16* dyb,
                     const bf16* x, float* dw, float* dx, bf16* dxb, amx::OuterSums& sums) {
  const int n_out = pad16(l.n_in);
  sums.add(dy, n_out, n_out, x, d.H, dw);
  amx::product(dyb, amx::pad32(l.n_in), l.packed.data(), d.H, dx, d.H);
  amx::finish(dx, d.H, d.H, false, x, dxb);
}

void backward_tile(const Dims& d, const Weights& w, const float* e, const float* sh,
                   const int64_t* ri, const float* gp, int64_t n0, int m, Bf16Work& t,
                   const Grads& a, float* ge) {
  using amx::pad32;
  forward_tile(d, w, e, sh, ri, n0, m, t, false);
  colour_grads(d, gp, n0, m, t.fa);
  amx::rows_to_bf16(t.fa, d.Cp, kTile, d.C, t.ba, pad32(d.C));
  hidden_backward(d, w.bwd[4], t.fa, t.ba, t.h3, a.w[4], t.fb, t.bb, t.sums[4]);  // dh3
  hidden_backward(d, w.bwd[3], t.fb, t.bb, t.h2, a.w[3], t.fa, t.ba, t.sums[3]);  // dh2
  t.sums[2].add(t.fa, d.H, d.H, t.cin, d.Cinp, a.w[2]);
  amx::product(t.ba, pad32(d.H), w.bwd[2].packed.data(), d.Cinp, t.fb, d.Cinp);  // dcin
  geometry_grads(d, gp, n0, m, t.fb, t.fa);
  amx::rows_to_bf16(t.fa, d.Gp, kTile, d.G, t.ba, pad32(d.G));
  hidden_backward(d, w.bwd[1], t.fa, t.ba, t.h1, a.w[1], t.fb, t.bb, t.sums[1]);  // dh1
  t.sums[0].add(t.fb, d.H, d.H, t.e, d.Ep, a.w[0]);
  amx::product(t.bb, pad32(d.H), w.bwd[0].packed.data(), d.Ep, t.fa, d.Ep);  // de
  for (int p = 0; p < m; ++p) std::memcpy(ge + (n0 + p) * d.E, t.fa + p * d.Ep, d.E * 4);
}

void start(Bf16Work&) { amx::begin(); }
void stop(Bf16Work& t) {
  for (auto& s : t.sums) s.flush();  // the weight-gradient sums still kept
  amx::end();
}
#endif

// The activations of the outputs: colour = sigmoid of its logits, density = exp of its logit
// clamped to [-lim, lim] (nerf/field.py's trunc_exp).
struct Outputs {
  float *rgb, *sigma, *logit;  // [N, C], [N], [N]
  float lim;

  // Rows [n0, n0 + m) from a tile's density logits g[p * ldg] and colour logits c [kTile, Cp].
  void put(const Dims& d, int64_t n0, int m, const float* g, int ldg, const float* c) const {
    for (int p0 = 0; p0 < m; p0 += kW) {
      v16 x = {};
      for (int p = p0; p < std::min(m, p0 + kW); ++p) logit[n0 + p] = x[p - p0] = g[p * ldg];
      x = x > lim ? v16{} + lim : x;  // NaN stays NaN
      const v16 y = vexp(x < -lim ? v16{} - lim : x);
      std::memcpy(sigma + n0 + p0, &y, std::min(m - p0, kW) * 4);
    }
    for (int p = 0; p < m; ++p) {
      const v16 y = 1.0f / (1.0f + vexp(-vload(c + p * d.Cp)));
      std::memcpy(rgb + (n0 + p) * d.C, &y, d.C * 4);
    }
  }
};

// The forward of all N rows, tile by tile on each thread, into out.
template <class Work>
void forward_rows(const Dims& d, const Weights& w, const float* e, const float* sh,
                  const int64_t* ri, int64_t n, const Outputs& out) {
  const int64_t tiles = (n + kTile - 1) / kTile;
#pragma omp parallel num_threads(at::get_num_threads())
  {
    std::unique_ptr<Work> k(new Work);
    start(*k);
#pragma omp for schedule(static)
    for (int64_t b = 0; b < tiles; ++b) {
      const int64_t n0 = b * kTile;
      const int m = int(std::min<int64_t>(kTile, n - n0));
      forward_tile(d, w, e, sh, ri, n0, m, *k, true);
      const auto& t = [&]() -> const auto& {
        if constexpr (std::is_same_v<Work, Fp32Work>) return k->t;
        else return *k;
      }();
      out.put(d, n0, m, t.g, d.Gp, t.c);
    }
    stop(*k);
  }
}

// The backward of all N rows: grad_e rows into ge, each thread's weight gradients into its
// slice of acc (per_thread floats each, the five matrices one after the other).
template <class Work>
void backward_rows(const Dims& d, const Weights& w, const float* e, const float* sh,
                   const int64_t* ri, const float* gp, int64_t n, float* ge, float* acc,
                   size_t per_thread) {
  const int64_t tiles = (n + kTile - 1) / kTile;
  const size_t sizes[5] = {size_t(d.H) * d.Ep, size_t(d.Gp) * d.H, size_t(d.H) * d.Cinp,
                           size_t(d.H) * d.H, size_t(d.Cp) * d.H};
#pragma omp parallel num_threads(at::get_num_threads())
  {
    std::unique_ptr<Work> k(new Work);
    Grads a;
    a.w[0] = acc + size_t(omp_get_thread_num()) * per_thread;
    for (int i = 1; i < 5; ++i) a.w[i] = a.w[i - 1] + sizes[i - 1];
    start(*k);
#pragma omp for schedule(static)
    for (int64_t b = 0; b < tiles; ++b) {
      const int64_t n0 = b * kTile;
      backward_tile(d, w, e, sh, ri, gp, n0, int(std::min<int64_t>(kTile, n - n0)), *k, a, ge);
    }
    stop(*k);
  }
}

Dims dims_of(const torch::Tensor& e, const torch::Tensor& sh, const torch::Tensor& ri,
             const torch::Tensor& w1, const torch::Tensor& w2, const torch::Tensor& w3,
             const torch::Tensor& w4, const torch::Tensor& w5, bool bf16) {
  TORCH_CHECK(!bf16 || amx::available(), "bf16 products need AMX-BF16 tiles, which this CPU or process lacks");
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

// e [N, E] encodings, sh [R, S] SH of each ray's direction, ri [N] each sample's ray, lim the
// density logit's clamp. Returns {colour [N, C], density [N], density logit [N]}.
std::vector<torch::Tensor> mlp_forward(torch::Tensor e, torch::Tensor sh, torch::Tensor ri,
                                       torch::Tensor w1, torch::Tensor w2, torch::Tensor w3,
                                       torch::Tensor w4, torch::Tensor w5, bool bf16, double lim) {
  e = e.contiguous(), sh = sh.contiguous(), ri = ri.contiguous();
  const Dims d = dims_of(e, sh, ri, w1, w2, w3, w4, w5, bf16);
  const Weights w = prepare(d, w1, w2, w3, w4, w5, bf16);
  const int64_t n = e.size(0);
  auto rgb = torch::empty({n, d.C}, e.options());
  auto sigma = torch::empty({n}, e.options()), logit = torch::empty({n}, e.options());
  const Outputs out{rgb.data_ptr<float>(), sigma.data_ptr<float>(), logit.data_ptr<float>(),
                    float(lim)};
  const float *ep = e.data_ptr<float>(), *sp = sh.data_ptr<float>();
  const int64_t* rp = ri.data_ptr<int64_t>();
#ifdef DRONECAP_AMX
  if (bf16) {
    forward_rows<Bf16Work>(d, w, ep, sp, rp, n, out);
    return {rgb, sigma, logit};
  }
#endif
  forward_rows<Fp32Work>(d, w, ep, sp, rp, n, out);
  return {rgb, sigma, logit};
}

// The gradients of the logits [N, 1 + C] from those of the forward's outputs: the density's
// through exp (zero where the clamp held the logit), the colour's through the sigmoid.
torch::Tensor logit_grads(const torch::Tensor& g_rgb, const torch::Tensor& g_sigma,
                          const torch::Tensor& rgb, const torch::Tensor& sigma,
                          const torch::Tensor& logit, double lim) {
  const int64_t n = rgb.size(0), c = rgb.size(1);
  for (const auto* t : {&g_rgb, &g_sigma, &rgb, &sigma, &logit})
    TORCH_CHECK(t->scalar_type() == torch::kFloat32 && t->is_contiguous() && t->size(0) == n,
                "outputs and their gradients must be contiguous float32 with N rows");
  TORCH_CHECK(g_rgb.sizes() == rgb.sizes() && g_sigma.numel() == n && sigma.numel() == n &&
              logit.numel() == n, "colour [N, C] and density [N] (and their gradients) expected");
  auto grad = torch::empty({n, 1 + c}, rgb.options());
  const float *gr = g_rgb.data_ptr<float>(), *gs = g_sigma.data_ptr<float>();
  const float *r = rgb.data_ptr<float>(), *s = sigma.data_ptr<float>(), *x = logit.data_ptr<float>();
  float* o = grad.data_ptr<float>();
  const float l = float(lim);
  for (int64_t i = 0; i < n; ++i) {
    o[i * (1 + c)] = (x[i] >= -l && x[i] <= l) ? gs[i] * s[i] : 0.0f;
    for (int64_t k = 0; k < c; ++k)
      o[i * (1 + c) + 1 + k] = gr[i * c + k] * (1.0f - r[i * c + k]) * r[i * c + k];
  }
  return grad;
}

// The backward of mlp_forward for the gradients of its colour and density (and what it
// returned); returns {grad_e [N, E], grad_w1, ..., grad_w5}.
std::vector<torch::Tensor> mlp_backward(torch::Tensor g_rgb, torch::Tensor g_sigma,
                                        torch::Tensor rgb, torch::Tensor sigma,
                                        torch::Tensor logit, torch::Tensor e, torch::Tensor sh,
                                        torch::Tensor ri, torch::Tensor w1, torch::Tensor w2,
                                        torch::Tensor w3, torch::Tensor w4, torch::Tensor w5,
                                        bool bf16, double lim) {
  e = e.contiguous(), sh = sh.contiguous(), ri = ri.contiguous();
  const Dims d = dims_of(e, sh, ri, w1, w2, w3, w4, w5, bf16);
  TORCH_CHECK(rgb.size(0) == e.size(0) && rgb.dim() == 2 && rgb.size(1) == d.C,
              "colour must be [N, C]");
  const auto grad = logit_grads(g_rgb.contiguous(), g_sigma.contiguous(), rgb, sigma, logit, lim);
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
#ifdef DRONECAP_AMX
  if (bf16) backward_rows<Bf16Work>(d, w, ep, sp, rp, gp, n, gep, acc.data(), all);
  else
#endif
    backward_rows<Fp32Work>(d, w, ep, sp, rp, gp, n, gep, acc.data(), all);
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
  m.def("forward", &mlp_forward,
        "fused field MLPs: (e, sh, ri, w1..w5, bf16, lim) -> (colour [N, C], density [N], logit)",
        py::call_guard<py::gil_scoped_release>());
  m.def("amx", &amx::available, "whether bf16 products can run on this CPU's AMX tiles");
  m.def("backward", &mlp_backward, "fused field MLPs' backward: (g_rgb, g_sigma, rgb, sigma, logit, e, ...) -> grad_e, "
        "grad_w1..grad_w5",
        py::call_guard<py::gil_scoped_release>());
}
