// Ray marching through an occupancy grid into packed samples, for the CPU.
//
// Same arithmetic as the PyTorch reference nerf/marching.py (float32, one rounding per
// operation: built with -ffp-contract=off so no multiply-add is fused), so both keep exactly
// the same samples. Ray r has candidates t_k = t_near + (k + offset_r) * step for
// k < min(ceil((t_far - t_near) / step), max_samples); a candidate is kept when t_k < t_far
// and the cell of o + d t_k is occupied (cells: x-major index (i res + j) res + k of the
// point's position in the AABB, truncated and clamped to the grid; NaN -> cell 0).
// With max_kept > 0 a ray stops at its max_kept-th kept sample. t_resume = t_near + e * step,
// e the candidates examined, is where a next call continues the ray (>= t_far: it is done).
// Each thread owns a contiguous run of rays and collects its samples in a private buffer; the
// buffers are then copied out in ray order.
//
// Also here: compositing packed samples into ray colours and its backward (nerf/volrend.py's
// `composite`), one pass over the samples in ray order; and the rays and target colours of a
// training step's random pixels (nerf/batch.py's `draw_rays`), one pass over the rays; and the
// SH encoding of the rays' directions (nerf/sh.py's `sh_encode`); and the training loss
// (nerf/losses.py's `huber_loss_and_grad`); and the random cells and points of an occupancy-grid
// update (nerf/occupancy.py).
#include <torch/extension.h>

#include <ATen/Parallel.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <vector>

namespace {

// 16 candidates at a time (one AVX-512 register, or what the target has): their grid cells
// cost three divisions each, the marcher's largest cost when done one candidate at a time.
constexpr int kLanes = 16;
typedef float vf16 __attribute__((vector_size(4 * kLanes)));
typedef int32_t vi16 __attribute__((vector_size(4 * kLanes)));

// The cell index along one axis of positions p: truncated, clamped to [0, res - 1], NaN -> 0
// (the reference's rule, the same float32 operations lane by lane).
inline vi16 axis_cells(vf16 p, float lo, float extent, float res_f) {
  const vf16 zero = {}, top = zero + (res_f - 1.0f);
  const vf16 v = ((p - lo) / extent) * res_f;
  const vf16 in = v >= zero ? v : zero;  // negative or NaN -> 0
  return __builtin_convertvector(in >= res_f ? top : in, vi16);
}

}  // namespace

// Returns (ray_indices int64 [S], t_starts float32 [S], t_ends float32 [S], counts int64 [R],
// t_resume float32 [R]).
std::vector<torch::Tensor> march(torch::Tensor origins, torch::Tensor dirs, torch::Tensor t_near,
                                 torch::Tensor t_far, double step, torch::Tensor occupied,
                                 torch::Tensor aabb, int64_t max_samples, torch::Tensor offsets,
                                 int64_t max_kept) {
  const int64_t r = origins.size(0);
  for (const auto& t : {origins, dirs, aabb}) {
    TORCH_CHECK(t.scalar_type() == torch::kFloat32 && t.is_contiguous() && t.dim() == 2 &&
                    t.size(1) == 3, "origins, dirs, aabb must be contiguous float32 [*, 3]");
  }
  for (const auto& t : {t_near, t_far, offsets}) {
    TORCH_CHECK(t.scalar_type() == torch::kFloat32 && t.is_contiguous() && t.numel() == r,
                "t_near, t_far, offsets must be contiguous float32 [R]");
  }
  TORCH_CHECK(dirs.size(0) == r && aabb.size(0) == 2, "dirs must be [R, 3] and aabb [2, 3]");
  TORCH_CHECK(step > 0.0, "marching step must be positive");
  const bool use_grid = occupied.numel() > 0;
  int64_t res = 0;
  if (use_grid) {
    TORCH_CHECK(occupied.scalar_type() == torch::kBool && occupied.is_contiguous(),
                "occupied must be a contiguous bool tensor");
    res = int64_t(std::llround(std::cbrt(double(occupied.numel()))));
    TORCH_CHECK(res * res * res == occupied.numel(), "occupied must have res^3 cells");
    TORCH_CHECK(res <= 1024, "occupancy grids above 1024^3 cells are not supported");
  }
  const float* o = origins.data_ptr<float>();
  const float* d = dirs.data_ptr<float>();
  const float* tn = t_near.data_ptr<float>();
  const float* tf = t_far.data_ptr<float>();
  const float* off = offsets.data_ptr<float>();
  const float* box = aabb.data_ptr<float>();
  const bool* occ = use_grid ? occupied.data_ptr<bool>() : nullptr;
  const float step_f = float(step), half = float(0.5 * step), res_f = float(res);
  const float lo[3] = {box[0], box[1], box[2]};
  const float extent[3] = {box[3] - box[0], box[4] - box[1], box[5] - box[2]};

  auto counts = torch::zeros({r}, torch::dtype(torch::kInt64));
  int64_t* cnt = counts.data_ptr<int64_t>();
  auto t_resume = torch::empty({r}, torch::dtype(torch::kFloat32));
  float* resume = t_resume.data_ptr<float>();
  const int nt = at::get_num_threads();
  std::vector<std::vector<float>> kept(nt);  // per run of rays: t of kept candidates, in order
  std::vector<int64_t> first_ray(nt + 1);
  for (int b = 0; b <= nt; ++b) first_ray[b] = r * b / nt;
#pragma omp parallel for schedule(static, 1) num_threads(nt)
  for (int b = 0; b < nt; ++b) {
    std::vector<float>& out = kept[b];
    out.reserve(size_t(first_ray[b + 1] - first_ray[b]) * 16);
    for (int64_t i = first_ray[b]; i < first_ray[b + 1]; ++i) {
      const float len = std::max(tf[i] - tn[i], 0.0f);
      const float n_f = std::ceil(len / step_f);  // NaN-safe: only n_f >= 1 gives samples
      const int64_t n = n_f >= 1.0f ? int64_t(std::min(n_f, float(max_samples))) : 0;
      int64_t c = 0, examined = n;
      for (int64_t k0 = 0; k0 < n && examined == n; k0 += kLanes) {
        vf16 t;
        for (int j = 0; j < kLanes; ++j) t[j] = float(k0 + j);
        t = tn[i] + (t + off[i]) * step_f;
        vi16 cell = {};
        if (use_grid)
          for (int a = 0; a < 3; ++a)
            cell = cell * int32_t(res) + axis_cells(o[3 * i + a] + d[3 * i + a] * t, lo[a],
                                                     extent[a], res_f);
        for (int j = 0; j < kLanes && k0 + j < n; ++j) {
          if (!(t[j] < tf[i]) || (use_grid && !occ[cell[j]])) continue;
          out.push_back(t[j]);
          if (++c == max_kept) {
            examined = k0 + j + 1;
            break;
          }
        }
      }
      cnt[i] = c;
      resume[i] = tn[i] + float(examined) * step_f;
    }
  }
  std::vector<int64_t> start(nt + 1, 0);
  for (int b = 0; b < nt; ++b) start[b + 1] = start[b] + int64_t(kept[b].size());
  const int64_t total = start[nt];
  auto ray_indices = torch::empty({total}, torch::dtype(torch::kInt64));
  auto t_starts = torch::empty({total}, torch::dtype(torch::kFloat32));
  auto t_ends = torch::empty({total}, torch::dtype(torch::kFloat32));
  int64_t* ri = ray_indices.data_ptr<int64_t>();
  float* ts = t_starts.data_ptr<float>();
  float* te = t_ends.data_ptr<float>();
#pragma omp parallel for schedule(static, 1) num_threads(nt)
  for (int b = 0; b < nt; ++b) {
    if (kept[b].empty()) continue;
    int64_t s = start[b];
    for (int64_t i = first_ray[b]; i < first_ray[b + 1]; ++i) {
      for (int64_t c = 0; c < cnt[i]; ++c, ++s) {
        const float t = kept[b][size_t(s - start[b])];
        ri[s] = i;
        ts[s] = std::max(t - half, tn[i]);
        te[s] = std::min(t + half, tf[i]);
      }
    }
  }
  return {ray_indices, t_starts, t_ends, counts, t_resume};
}

namespace {

// A sample's optical thickness by the reference's rules (nerf/volrend.packed_weights): NaN -> 0,
// clamped to [0, 1e4]; `live` is whether its gradient passes (not NaN, not clamped).
inline float thickness(float sigma, float length, bool& live) {
  const float tau = sigma * length;
  live = tau >= 0.0f && tau <= 1e4f;
  if (std::isnan(tau)) return 0.0f;
  return std::fmin(std::fmax(tau, 0.0f), 1e4f);
}

void check_composite(const torch::Tensor& sigma, const torch::Tensor& rgb, const torch::Tensor& t0,
                     const torch::Tensor& t1, const torch::Tensor& ri, const torch::Tensor& bg) {
  const int64_t s = sigma.numel();
  TORCH_CHECK(sigma.scalar_type() == torch::kFloat32 && rgb.scalar_type() == torch::kFloat32 &&
                  t0.scalar_type() == torch::kFloat32 && t1.scalar_type() == torch::kFloat32 &&
                  bg.scalar_type() == torch::kFloat32 && ri.scalar_type() == torch::kInt64,
              "float32 samples, int64 ray indices expected");
  TORCH_CHECK(rgb.dim() == 2 && rgb.size(0) == s && t0.numel() == s && t1.numel() == s &&
                  ri.numel() == s && bg.dim() == 2 && bg.size(1) == rgb.size(1),
              "sample and background shapes do not match");
  for (const auto* t : {&sigma, &rgb, &t0, &t1, &ri, &bg}) {
    TORCH_CHECK(t->is_contiguous() && t->device().is_cpu(), "contiguous CPU tensors expected");
  }
}

// Checks that ray indices ri [s] are non-decreasing indices of r rays, and splits the samples
// into `parts` runs of whole rays (bounds [parts + 1]), so that threads own disjoint rays.
std::vector<int64_t> ray_runs(const int64_t* ri, int64_t s, int64_t r, int parts) {
  for (int64_t i = 0; i < s; ++i)
    TORCH_CHECK(ri[i] >= 0 && ri[i] < r && (i == 0 || ri[i] >= ri[i - 1]),
                "ray indices must be non-decreasing and in range");
  std::vector<int64_t> bounds(parts + 1, s);
  for (int b = 0; b < parts; ++b) {
    int64_t i = s * b / parts;
    while (i > 0 && i < s && ri[i] == ri[i - 1]) ++i;  // to the start of the next ray
    bounds[b] = std::max(i, b > 0 ? bounds[b - 1] : int64_t(0));
  }
  return bounds;
}

// Walks the samples of each run of rays (ray_runs), one thread per run, in order along each
// ray: f(i, w_i, before) with w_i = T_i (1 - exp(-tau_i)) and `before` the optical thickness
// of the ray up to and including sample i (summed in double).
template <class F>
void walk_rays(const float* sigma, const float* t0, const float* t1, const int64_t* ri,
               const std::vector<int64_t>& runs, F&& f) {
  const int nt = int(runs.size()) - 1;
#pragma omp parallel for schedule(static, 1) num_threads(nt)
  for (int b = 0; b < nt; ++b) {
    double before = 0.0;
    for (int64_t i = runs[b]; i < runs[b + 1]; ++i) {
      if (i == runs[b] || ri[i] != ri[i - 1]) before = 0.0;
      bool live;
      const float tau = thickness(sigma[i], t1[i] - t0[i], live);
      const float w = std::exp(-float(before)) * -std::expm1(-tau);
      before += double(tau);
      f(i, w, before);
    }
  }
}

// Threads for compositing s samples: one below 4096 (a parallel region costs more).
inline int composite_threads(int64_t s) { return s > 4096 ? at::get_num_threads() : 1; }

}  // namespace

// Ray colours [R, C] = sum_i w_i rgb_i + (1 - sum_i w_i) bg of packed samples (sigma [S],
// rgb [S, C], intervals t0, t1 [S], ray_indices [S] non-decreasing, bg [R, C]); w_i = T_i
// (1 - exp(-tau_i)), T_i = exp(-sum of the ray's earlier tau, summed in double).
torch::Tensor composite_forward(torch::Tensor sigma, torch::Tensor rgb, torch::Tensor t0,
                                torch::Tensor t1, torch::Tensor ri, torch::Tensor bg) {
  check_composite(sigma, rgb, t0, t1, ri, bg);
  const int64_t s = sigma.numel(), r = bg.size(0), c = bg.size(1);
  auto acc = torch::zeros({r, c}, bg.options());
  std::vector<float> opacity(r, 0.0f);
  const float *sp = sigma.data_ptr<float>(), *cp = rgb.data_ptr<float>();
  const float *ap = t0.data_ptr<float>(), *bp = t1.data_ptr<float>(), *gp = bg.data_ptr<float>();
  const int64_t* rp = ri.data_ptr<int64_t>();
  float* out = acc.data_ptr<float>();
  walk_rays(sp, ap, bp, rp, ray_runs(rp, s, r, composite_threads(s)),
            [&](int64_t i, float w, double) {
              for (int64_t k = 0; k < c; ++k) out[rp[i] * c + k] += w * cp[i * c + k];
              opacity[rp[i]] += w;
            });
  for (int64_t j = 0; j < r; ++j)
    for (int64_t k = 0; k < c; ++k) out[j * c + k] += (1.0f - opacity[j]) * gp[j * c + k];
  return acc;
}

// The backward of composite_forward for the colour gradient g [R, C]: {d sigma [S], d rgb [S, C],
// d bg [R, C]}. With e_i = (rgb_i - bg) . g: d tau_i = T_{i+1} e_i - sum_{j > i} w_j e_j.
std::vector<torch::Tensor> composite_backward(torch::Tensor g, torch::Tensor sigma,
                                              torch::Tensor rgb, torch::Tensor t0,
                                              torch::Tensor t1, torch::Tensor ri,
                                              torch::Tensor bg) {
  check_composite(sigma, rgb, t0, t1, ri, bg);
  TORCH_CHECK(g.sizes() == bg.sizes() && g.is_contiguous() && g.scalar_type() == torch::kFloat32,
              "the gradient must be float32 [R, C]");
  const int64_t s = sigma.numel(), r = bg.size(0), c = bg.size(1);
  auto d_sigma = torch::empty({s}, sigma.options());
  auto d_rgb = torch::empty({s, c}, rgb.options());
  auto d_bg = torch::empty({r, c}, bg.options());
  const float *sp = sigma.data_ptr<float>(), *cp = rgb.data_ptr<float>(), *gp = g.data_ptr<float>();
  const float *ap = t0.data_ptr<float>(), *bp = t1.data_ptr<float>(), *bgp = bg.data_ptr<float>();
  const int64_t* rp = ri.data_ptr<int64_t>();
  float *dsp = d_sigma.data_ptr<float>(), *dcp = d_rgb.data_ptr<float>();
  std::vector<float> w(s), after(s), e(s);  // weight, transmittance behind, (rgb - bg) . g
  std::vector<double> rest(r, 0.0);          // sum of w e over the ray
  std::vector<float> opacity(r, 0.0f);
  const std::vector<int64_t> runs = ray_runs(rp, s, r, composite_threads(s));
  walk_rays(sp, ap, bp, rp, runs, [&](int64_t i, float wi, double before) {
    w[i] = wi;
    after[i] = std::exp(-float(before));
    float dot = 0.0f;
    for (int64_t k = 0; k < c; ++k) {
      dot += (cp[i * c + k] - bgp[rp[i] * c + k]) * gp[rp[i] * c + k];
      dcp[i * c + k] = wi * gp[rp[i] * c + k];
    }
    e[i] = dot;
    rest[rp[i]] += double(wi) * dot;
    opacity[rp[i]] += wi;
  });
  // rest becomes the sum over the ray's later samples (each ray's samples in order: any
  // order of the rays, so one pass over all samples)
  for (int64_t i = 0; i < s; ++i) {
    rest[rp[i]] -= double(w[i]) * e[i];
    bool live;
    thickness(sp[i], bp[i] - ap[i], live);
    const float d_tau = after[i] * e[i] - float(rest[rp[i]]);
    dsp[i] = live ? d_tau * (bp[i] - ap[i]) : 0.0f;
  }
  float* dbp = d_bg.data_ptr<float>();
  for (int64_t j = 0; j < r; ++j)
    for (int64_t k = 0; k < c; ++k) dbp[j * c + k] = (1.0f - opacity[j]) * gp[j * c + k];
  return {d_sigma, d_rgb, d_bg};
}

namespace {

// splitmix64: the random number of index i of a stream (seed), so that a draw does not depend
// on which thread makes it.
inline uint64_t mix(uint64_t seed, uint64_t i) {
  uint64_t z = seed + (i + 1) * 0x9e3779b97f4a7c15ull;
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}

// Uniform in [0, k) for k < 2^31 from the high 32 bits (bias below k / 2^32): what torch's int64
// ops reproduce (nerf/draws.py).
inline int64_t below32(uint64_t r, int64_t k) { return int64_t(((r >> 32) * uint64_t(k)) >> 32); }

// Uniform in [0, 1) on the 2^-24 grid (float32 exact).
inline float unit24(uint64_t r) { return float(uint32_t(r >> 40)) * 0x1p-24f; }

}  // namespace

// The rays and targets of R drawn pixels (pixel p of frame which[p] at column u[p], row v[p]):
// origins [R, 3] = the frame's camera centre, dirs [R, 3] = its rotation times the camera's
// undistorted direction through the pixel (tables [K, H, W, 3], camera_index [N] -> K),
// normalised; target [R, C] = the pixel's colour / 255, composited on bg [R, C] by its alpha
// (uint8 [N, H, W], or an empty tensor: no alpha, target = colour); radius [R] = the pixel
// centre's distance from (cx, cy) over `corner` (the farthest corner's distance).
std::vector<torch::Tensor> draw(torch::Tensor images, torch::Tensor alpha, torch::Tensor poses,
                                torch::Tensor tables, torch::Tensor camera_index,
                                torch::Tensor which, torch::Tensor u, torch::Tensor v,
                                torch::Tensor bg, double cx, double cy, double corner) {
  TORCH_CHECK(images.scalar_type() == torch::kUInt8 && images.dim() == 4 && images.is_contiguous(),
              "images must be contiguous uint8 [N, H, W, C]");
  const int64_t n = images.size(0), h = images.size(1), w = images.size(2), c = images.size(3);
  const bool has_alpha = alpha.numel() > 0;
  TORCH_CHECK(!has_alpha || (alpha.scalar_type() == torch::kUInt8 && alpha.is_contiguous() &&
                             alpha.numel() == n * h * w), "alpha must be contiguous uint8 [N, H, W]");
  TORCH_CHECK(poses.scalar_type() == torch::kFloat32 && poses.is_contiguous() &&
                  poses.numel() == n * 16, "poses must be contiguous float32 [N, 4, 4]");
  TORCH_CHECK(tables.scalar_type() == torch::kFloat32 && tables.is_contiguous() &&
                  tables.dim() == 4 && tables.size(1) == h && tables.size(2) == w &&
                  tables.size(3) == 3, "direction tables must be contiguous float32 [K, H, W, 3]");
  const int64_t r = which.numel(), k_cams = tables.size(0);
  for (const auto& t : {camera_index, which, u, v}) {
    TORCH_CHECK(t.scalar_type() == torch::kInt64 && t.is_contiguous() && t.dim() == 1,
                "indices must be contiguous int64 [*]");
  }
  TORCH_CHECK(camera_index.numel() == n && u.numel() == r && v.numel() == r,
              "camera_index must be [N] and u, v [R]");
  TORCH_CHECK(bg.scalar_type() == torch::kFloat32 && bg.is_contiguous() && bg.dim() == 2 &&
                  bg.size(0) == r && bg.size(1) == c, "bg must be contiguous float32 [R, C]");
  const auto f32 = images.options().dtype(torch::kFloat32);
  auto origins = torch::empty({r, 3}, f32), dirs = torch::empty({r, 3}, f32);
  auto target = torch::empty({r, c}, f32), radius = torch::empty({r}, f32);
  const uint8_t *im = images.data_ptr<uint8_t>(), *al = has_alpha ? alpha.data_ptr<uint8_t>() : nullptr;
  const float *ps = poses.data_ptr<float>(), *tb = tables.data_ptr<float>(), *bp = bg.data_ptr<float>();
  const int64_t *ci = camera_index.data_ptr<int64_t>(), *wp = which.data_ptr<int64_t>();
  const int64_t *up = u.data_ptr<int64_t>(), *vp = v.data_ptr<int64_t>();
  float *op = origins.data_ptr<float>(), *dp = dirs.data_ptr<float>();
  float *tp = target.data_ptr<float>(), *rp = radius.data_ptr<float>();
  bool bad = false;
  const float fcx = float(cx), fcy = float(cy), fcorner = float(std::max(corner, 1e-12));
#pragma omp parallel for schedule(static) num_threads(at::get_num_threads()) reduction(|| : bad)
  for (int64_t p = 0; p < r; ++p) {
    const int64_t f = wp[p], x = up[p], y = vp[p];
    if (f < 0 || f >= n || x < 0 || x >= w || y < 0 || y >= h || ci[f] < 0 || ci[f] >= k_cams) {
      bad = true;
      continue;
    }
    const float* m = ps + f * 16;  // row-major [4, 4] camera-to-world
    const float* d = tb + ((ci[f] * h + y) * w + x) * 3;
    float out[3], norm2 = 0.0f;
    for (int i = 0; i < 3; ++i) {
      out[i] = m[i * 4] * d[0] + m[i * 4 + 1] * d[1] + m[i * 4 + 2] * d[2];
      norm2 += out[i] * out[i];
    }
    const float norm = std::sqrt(norm2);
    for (int i = 0; i < 3; ++i) {
      op[p * 3 + i] = m[i * 4 + 3];
      dp[p * 3 + i] = out[i] / norm;
    }
    const int64_t pixel = (f * h + y) * w + x;
    const float a = has_alpha ? float(al[pixel]) / 255.0f : 1.0f;
    for (int64_t k = 0; k < c; ++k) {
      const float rgb = float(im[pixel * c + k]) / 255.0f;
      tp[p * c + k] = has_alpha ? rgb * a + bp[p * c + k] * (1.0f - a) : rgb;
    }
    const float du = float(x) + 0.5f - fcx, dv = float(y) + 0.5f - fcy;
    rp[p] = std::sqrt((du * du + dv * dv) / fcorner);
  }
  TORCH_CHECK(!bad, "a drawn pixel, frame or camera index is out of range");
  return {origins, dirs, target, radius};
}

// `draw` of random pixels: n_rays pixels (uniform frame among `k_frames` frames drawn uniformly
// from the N, uniform column and row) and, with alpha, a uniform background colour per ray,
// else `background` [C]; from the splitmix64 stream `seed`: frame j from number j, ray p's
// frame, column and row from numbers k_frames + 3p + 0, 1, 2, its background channel ch from
// number k_frames + 3 n_rays + p C + ch (nerf/draws.py's `pixel_draws`, the same in torch).
// Returns draw's {origins, dirs, target, radius} and {frame int64 [R], background [R, C]}.
std::vector<torch::Tensor> draw_random(torch::Tensor images, torch::Tensor alpha,
                                       torch::Tensor poses, torch::Tensor tables,
                                       torch::Tensor camera_index, int64_t seed, int64_t n_rays,
                                       int64_t k_frames, torch::Tensor background, double cx,
                                       double cy, double corner) {
  TORCH_CHECK(images.dim() == 4 && n_rays >= 0 && k_frames >= 1, "images [N, H, W, C], k >= 1");
  const int64_t n = images.size(0), h = images.size(1), w = images.size(2), c = images.size(3);
  TORCH_CHECK(n >= 1 && h >= 1 && w >= 1, "no images to draw from");
  TORCH_CHECK(background.scalar_type() == torch::kFloat32 && background.numel() == c,
              "background must be float32 [C]");
  const uint64_t s = uint64_t(seed);
  const auto i64 = torch::dtype(torch::kInt64);
  auto which = torch::empty({n_rays}, i64), u = torch::empty({n_rays}, i64);
  auto v = torch::empty({n_rays}, i64);
  auto bg = torch::empty({n_rays, c}, torch::dtype(torch::kFloat32));
  std::vector<int64_t> frames(static_cast<size_t>(k_frames));
  for (int64_t j = 0; j < k_frames; ++j) frames[size_t(j)] = below32(mix(s, uint64_t(j)), n);
  int64_t *wp = which.data_ptr<int64_t>(), *up = u.data_ptr<int64_t>(), *vp = v.data_ptr<int64_t>();
  float* bp = bg.data_ptr<float>();
  const float* fixed = background.contiguous().data_ptr<float>();
  const bool random_bg = alpha.numel() > 0;
  const uint64_t base = uint64_t(k_frames), bg_base = base + 3 * uint64_t(n_rays);
  for (int64_t p = 0; p < n_rays; ++p) {
    const uint64_t i = base + 3 * uint64_t(p);
    wp[p] = frames[size_t(below32(mix(s, i), k_frames))];
    up[p] = below32(mix(s, i + 1), w);
    vp[p] = below32(mix(s, i + 2), h);
    for (int64_t ch = 0; ch < c; ++ch)
      bp[p * c + ch] = random_bg ? unit24(mix(s, bg_base + uint64_t(p * c + ch))) : fixed[ch];
  }
  auto out = draw(images, alpha, poses, tables, camera_index, which, u, v, bg, cx, cy, corner);
  out.push_back(which);
  out.push_back(bg);
  return out;
}

// Real SH basis of bands 0 .. degree - 1 at unit directions dirs [N, 3] -> [N, degree^2]: the
// coefficients and terms of nerf/sh.py's sh_encode, one row per direction.
torch::Tensor sh_encode(torch::Tensor dirs, int64_t degree) {
  TORCH_CHECK(dirs.scalar_type() == torch::kFloat32 && dirs.dim() == 2 && dirs.size(1) == 3,
              "directions must be float32 [N, 3]");
  TORCH_CHECK(degree >= 1 && degree <= 4, "sh degree must be 1..4");
  const auto d = dirs.contiguous();
  const int64_t n = d.size(0), k = degree * degree;
  auto out = torch::empty({n, k}, d.options());
  const float* dp = d.data_ptr<float>();
  float* op = out.data_ptr<float>();
  for (int64_t i = 0; i < n; ++i) {
    const float x = dp[3 * i], y = dp[3 * i + 1], z = dp[3 * i + 2];
    const float xx = x * x, yy = y * y, zz = z * z;
    const float v[16] = {
        0.28209479177387814f, -0.48860251190291987f * y, 0.48860251190291987f * z,
        -0.48860251190291987f * x, 1.0925484305920792f * x * y, -1.0925484305920792f * y * z,
        0.94617469575755997f * zz - 0.31539156525251999f, -1.0925484305920792f * x * z,
        0.54627421529603959f * (xx - yy), 0.59004358992664352f * y * (3 * xx - yy),
        2.8906114426405538f * x * y * z, 0.45704579946446572f * y * (1 - 5 * zz),
        0.3731763325901154f * z * (5 * zz - 3), 0.45704579946446572f * x * (1 - 5 * zz),
        1.4453057213202769f * z * (xx - yy), 0.59004358992664352f * x * (xx - 3 * yy)};
    std::memcpy(op + i * k, v, k * sizeof(float));
  }
  return out;
}

// Slab intersection of rays origins [N, 3] + t dirs [N, 3] with the box aabb [2, 3] (min,
// max): {t_near [N] (>= 0), t_far [N] (t_near where the ray misses), hit bool [N]}, with
// nerf/rays.py's ray_aabb arithmetic operation by operation (NaN propagates as there);
// direction components below `tiny` in magnitude count as parallel to a slab (its TINY).
std::vector<torch::Tensor> ray_aabb(torch::Tensor origins, torch::Tensor dirs, torch::Tensor aabb,
                                    double tiny) {
  for (const auto* t : {&origins, &dirs, &aabb})
    TORCH_CHECK(t->scalar_type() == torch::kFloat32 && t->dim() == 2 && t->size(1) == 3,
                "origins, dirs [N, 3] and aabb [2, 3] must be float32");
  TORCH_CHECK(dirs.size(0) == origins.size(0) && aabb.size(0) == 2, "shapes differ");
  const auto o = origins.contiguous(), d = dirs.contiguous(), b = aabb.contiguous();
  const int64_t n = o.size(0);
  auto near = torch::empty({n}, o.options()), far = torch::empty({n}, o.options());
  auto hit = torch::empty({n}, o.options().dtype(torch::kBool));
  const float *op = o.data_ptr<float>(), *dp = d.data_ptr<float>(), *bp = b.data_ptr<float>();
  float *np = near.data_ptr<float>(), *fp = far.data_ptr<float>();
  bool* hp = hit.data_ptr<bool>();
  // torch.minimum / maximum / amax / amin / clamp_min: NaN wins
  auto lo = [](float a, float c) { return std::isnan(a) || std::isnan(c) ? NAN : (a < c ? a : c); };
  auto hi = [](float a, float c) { return std::isnan(a) || std::isnan(c) ? NAN : (a > c ? a : c); };
  const float kTiny = float(tiny);
  for (int64_t i = 0; i < n; ++i) {
    float t_near = -INFINITY, t_far = INFINITY;
    for (int k = 0; k < 3; ++k) {
      const float dk = dp[3 * i + k];
      const float safe = std::fabs(dk) < kTiny ? (dk < 0 ? -kTiny : kTiny) : dk;
      const float inv = 1.0f / safe;
      const float t0 = (bp[k] - op[3 * i + k]) * inv, t1 = (bp[3 + k] - op[3 * i + k]) * inv;
      t_near = hi(t_near, lo(t0, t1));
      t_far = lo(t_far, hi(t0, t1));
    }
    t_near = hi(t_near, 0.0f);
    hp[i] = t_far > t_near;
    np[i] = t_near, fp[i] = hp[i] ? t_far : t_near;
  }
  return {near, far, hit};
}

// The Huber loss of rendered colours (nerf/losses.py's huber_loss_and_grad) in one pass: of
// d = pred - target (float32 [R, C]), the sum of d^2 / (2 delta) where |d| < delta and of
// |d| - delta / 2 elsewhere (in double), over divisor; and its gradient d / delta or sign(d),
// over divisor, float32 operations in the reference's order. NaN and inf reach the loss.
// Returns {loss (a float32 scalar), gradient [R, C]}.
std::vector<torch::Tensor> huber(torch::Tensor pred, torch::Tensor target, int64_t divisor,
                                 double delta) {
  TORCH_CHECK(pred.scalar_type() == torch::kFloat32 && target.scalar_type() == torch::kFloat32 &&
                  pred.sizes() == target.sizes() && divisor > 0,
              "pred and target: float32 of one shape; divisor > 0");
  const auto p = pred.contiguous(), t = target.contiguous();
  auto grad = torch::empty_like(p);
  const float *pp = p.data_ptr<float>(), *tp = t.data_ptr<float>();
  float* gp = grad.data_ptr<float>();
  const float dl = float(delta), half = float(0.5 * delta), div = float(divisor);
  double sum = 0.0;
  for (int64_t i = 0; i < p.numel(); ++i) {
    const float d = pp[i] - tp[i], z = std::fabs(d);
    const bool inner = z < dl;
    sum += inner ? 0.5f * z * z / dl : z - half;
    const float sign = d > 0.0f ? 1.0f : d < 0.0f ? -1.0f : d;  // 0 and NaN stay themselves
    gp[i] = (inner ? d / dl : sign) / div;
  }
  return {torch::full({}, float(sum) / div, p.options()), grad};
}


// The cells an occupancy-grid update samples and a random point in each (nerf/draws.py's
// grid_draws, bit for bit, from the splitmix64 stream `seed`): in warm-up every cell of `pool`
// (int64 [A], the allowed cells; empty: every cell of the grid); after it, `quarter` cells
// uniformly from the pool (or the grid) and `quarter` uniformly from the occupied ones
// (occupied: bool [res^3]; none when no cell is). Returns {cells int64 [M], jitter float32
// [M, 3] uniform in [0, 1)}: the same for any thread count.
std::vector<torch::Tensor> grid_draws(torch::Tensor occupied, torch::Tensor pool, int64_t quarter,
                                      bool warm, int64_t seed) {
  TORCH_CHECK(occupied.scalar_type() == torch::kBool && occupied.is_contiguous() &&
                  occupied.dim() == 1, "occupied must be a contiguous bool [res^3] tensor");
  TORCH_CHECK(pool.numel() == 0 || (pool.scalar_type() == torch::kInt64 && pool.is_contiguous()),
              "pool must be contiguous int64 [A] or empty");
  TORCH_CHECK(quarter >= 0, "quarter must be >= 0");
  const int64_t n = occupied.numel(), a = pool.numel();
  const int64_t* pp = a ? pool.data_ptr<int64_t>() : nullptr;
  const uint64_t s = uint64_t(seed);
  const auto i64 = torch::dtype(torch::kInt64);
  torch::Tensor cells;
  if (warm) {
    cells = a ? pool.clone() : torch::arange(n, i64);
  } else {
    std::unique_ptr<int64_t[]> occ(new int64_t[n + 1]);  // the occupied cells, in order
    const bool* op = occupied.data_ptr<bool>();  // (written without branches, nor zeroed first)
    int64_t k = 0;
    for (int64_t i = 0; i < n; ++i) occ[size_t(k)] = i, k += op[i];
    const int64_t span = a ? a : n;
    cells = torch::empty({k ? 2 * quarter : quarter}, i64);
    int64_t* cp = cells.data_ptr<int64_t>();
#pragma omp parallel for schedule(static) num_threads(at::get_num_threads()) if (quarter > 8192)
    for (int64_t i = 0; i < quarter; ++i) {
      const int64_t u = below32(mix(s, uint64_t(i)), std::max<int64_t>(span, 1));
      cp[i] = a ? pp[u] : u;
      if (k) cp[quarter + i] = occ[below32(mix(s, uint64_t(quarter + i)), k)];
    }
  }
  const int64_t m = cells.numel();
  const int64_t pairs = (3 * m + 1) / 2;  // two 24-bit uniforms from each 64-bit number
  auto numbers = torch::empty({2 * pairs}, torch::dtype(torch::kFloat32));
  float* jp = numbers.data_ptr<float>();
  const uint64_t js = mix(s, ~uint64_t(0));  // the jitter's own stream
#pragma omp parallel for schedule(static) num_threads(at::get_num_threads()) if (m > 16384)
  for (int64_t i = 0; i < pairs; ++i) {
    const uint64_t r = mix(js, uint64_t(i));
    jp[2 * i] = unit24(r);
    jp[2 * i + 1] = float(uint32_t(r) >> 8) * 0x1p-24f;
  }
  return {cells, numbers.narrow(0, 0, 3 * m).view({m, 3})};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  // the GIL is released while the kernel runs: another Python thread can work meanwhile
  m.def("march", &march, "occupancy-grid ray marching into packed samples",
        py::call_guard<py::gil_scoped_release>());
  m.def("composite", &composite_forward, "ray colours of packed samples",
        py::call_guard<py::gil_scoped_release>());
  m.def("composite_backward", &composite_backward, "gradients of composite",
        py::call_guard<py::gil_scoped_release>());
  m.def("draw", &draw, "rays and target colours of drawn pixels",
        py::call_guard<py::gil_scoped_release>());
  m.def("draw_random", &draw_random, "rays and target colours of random pixels",
        py::call_guard<py::gil_scoped_release>());
  m.def("sh_encode", &sh_encode, "real SH basis of unit directions",
        py::call_guard<py::gil_scoped_release>());
  m.def("ray_aabb", &ray_aabb, "slab intersection of rays with a box",
        py::call_guard<py::gil_scoped_release>());
  m.def("huber", &huber, "Huber loss of colours and its gradient",
        py::call_guard<py::gil_scoped_release>());
  m.def("grid_draws", &grid_draws, "an occupancy-grid update's cells and points",
        py::call_guard<py::gil_scoped_release>());
}
