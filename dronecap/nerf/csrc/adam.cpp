// The trainer's optimizer step on the CPU (nerf/adam_step.py): a check that every gradient is
// finite, and one Adam update of every parameter, in two calls over all tensors at once.
//
// torch's fused Adam runs one parallel loop per tensor, and its finiteness check (the mixed-
// precision unscale pass) another per tensor; a step of the default model spends ~0.4 ms in
// them at two threads, mostly waiting on memory (~13 MB move through the caches). Here the
// tensors are laid end to end and cut into pieces that the threads take as they come free:
// no small tensor pays for a parallel loop of its own.
//
// The update is torch's (torch.optim.Adam, L2 weight decay, no AMSGrad), with the operations
// in the order of torch's vectorised CPU kernel as torch 2.13's x86 build compiles it: built
// with -ffp-contract=off, the fused multiply-adds are where that build has them (the first
// moment's lerp, the second moment's sum), and the results are torch's bit for bit there
// (tests/nerf/test_adam_step.py; another build may differ in the last bit).
#include <torch/extension.h>

#include <ATen/Parallel.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

namespace {

constexpr int64_t kSerialBelow = 1 << 15;  // elements below which one thread does it all

// The tensors' offsets in their end-to-end layout: start[i] .. start[i + 1] is tensor i.
std::vector<int64_t> layout(const std::vector<torch::Tensor>& ts) {
  std::vector<int64_t> start(ts.size() + 1, 0);
  for (size_t i = 0; i < ts.size(); ++i) {
    TORCH_CHECK(ts[i].device().is_cpu() && ts[i].scalar_type() == torch::kFloat32 &&
                    ts[i].is_contiguous(),
                "contiguous float32 CPU tensors expected");
    start[i + 1] = start[i] + ts[i].numel();
  }
  return start;
}

constexpr int64_t kPiece = 1 << 14;  // elements per piece handed to a thread

// Calls fn(i, a, b) for the parts [a, b) of tensors i (element offsets within it) of the pieces
// of the layout `start` that this thread takes: pieces go to whichever thread is free, so that
// one that starts late (woken from sleep after Python ran between kernels) does not hold the
// other up at the end (-0.1 ms of a 5.2 ms lego step at two threads against an even split).
template <typename F>
void for_my_parts(const std::vector<int64_t>& start, F fn) {
  const int64_t total = start.back(), pieces = (total + kPiece - 1) / kPiece;
#pragma omp for schedule(dynamic, 1)
  for (int64_t q = 0; q < pieces; ++q) {
    const int64_t lo = q * kPiece, hi = std::min(total, lo + kPiece);
    for (size_t i = 0; i + 1 < start.size(); ++i) {
      const int64_t a = std::max(lo, start[i]), b = std::min(hi, start[i + 1]);
      if (a < b) fn(i, a - start[i], b - start[i]);
    }
  }
}

int threads_for(int64_t total) {
  return total < kSerialBelow ? 1 : std::max(1, at::get_num_threads());
}

}  // namespace

// Whether every element of `tensors` (float32) is finite: an inf or NaN has all exponent bits
// set, which an integer mask finds in vector registers.
bool all_finite(std::vector<torch::Tensor> tensors) {
  const auto start = layout(tensors);
  int bad = 0;
#pragma omp parallel num_threads(threads_for(start.back())) reduction(| : bad)
  for_my_parts(start, [&](size_t i, int64_t a, int64_t b) {
    const uint32_t* bits = reinterpret_cast<const uint32_t*>(tensors[i].data_ptr<float>());
    uint32_t any = 0;
#pragma omp simd reduction(| : any)
    for (int64_t j = a; j < b; ++j) any |= uint32_t((bits[j] & 0x7f800000u) == 0x7f800000u);
    bad |= int(any);
  });
  return bad == 0;
}

// One Adam update of params[i] from grads[i] with its moments exp_avgs[i], exp_avg_sqs[i]
// (all float32, the same shape) at step count steps[i] (a float32 scalar tensor, counted up
// by one here first; tensors shared between parameters once), learning rate lrs[i], betas
// (beta1s[i], beta2s[i]), L2 weight decay
// wds[i] and eps[i].
void adam_step(std::vector<torch::Tensor> params, std::vector<torch::Tensor> grads,
               std::vector<torch::Tensor> exp_avgs, std::vector<torch::Tensor> exp_avg_sqs,
               std::vector<torch::Tensor> steps, std::vector<double> lrs,
               std::vector<double> beta1s, std::vector<double> beta2s, std::vector<double> wds,
               std::vector<double> eps) {
  const size_t n = params.size();
  TORCH_CHECK(grads.size() == n && exp_avgs.size() == n && exp_avg_sqs.size() == n &&
                  steps.size() == n && lrs.size() == n && beta1s.size() == n &&
                  beta2s.size() == n && wds.size() == n && eps.size() == n,
              "one gradient, pair of moments, step count and option set per parameter");
  const auto start = layout(params);
  for (const auto* list : {&grads, &exp_avgs, &exp_avg_sqs})
    TORCH_CHECK(layout(*list) == start, "gradients and moments must match their parameters");
  // per tensor, in float32 from double as torch rounds them: step size lr / (1 - beta1^t),
  // sqrt(1 - beta2^t), 1 - beta1, 1 - beta2
  std::vector<float> size(n), root(n), c1(n), c2(n), b2(n), e(n), wd(n);
  for (size_t i = 0; i < n; ++i) {
    TORCH_CHECK(steps[i].numel() == 1 && steps[i].device().is_cpu() &&
                    steps[i].scalar_type() == torch::kFloat32,
                "a step count is a float32 scalar CPU tensor (torch's)");
    float* count = steps[i].data_ptr<float>();  // no dispatched op to read or count it
    bool seen = false;
    for (size_t j = 0; j < i; ++j) seen = seen || steps[j].data_ptr<float>() == count;
    if (!seen) *count += 1.0f;
    const double t = double(*count);
    size[i] = float(lrs[i] / (1 - std::pow(beta1s[i], t)));
    root[i] = float(std::sqrt(1 - std::pow(beta2s[i], t)));
    c1[i] = float(1 - beta1s[i]), c2[i] = float(1 - beta2s[i]), b2[i] = float(beta2s[i]);
    e[i] = float(eps[i]), wd[i] = float(wds[i]);
    TORCH_CHECK(std::abs(c1[i]) < 0.5f, "beta1 must be above 0.5");
  }
#pragma omp parallel num_threads(threads_for(start.back()))
  for_my_parts(start, [&](size_t i, int64_t a, int64_t b) {
    float* p = params[i].data_ptr<float>();
    float* m = exp_avgs[i].data_ptr<float>();
    float* v = exp_avg_sqs[i].data_ptr<float>();
    const float* g = grads[i].data_ptr<float>();
    const float step = -size[i], r = root[i], k1 = c1[i], k2 = c2[i], beta2 = b2[i];
    const float eps_i = e[i], decay = wd[i];
    const bool decays = decay != 0.0f;
#pragma omp simd
    for (int64_t j = a; j < b; ++j) {
      const float gj = decays ? g[j] + p[j] * decay : g[j];
      const float mj = std::fma(k1, gj - m[j], m[j]);  // m + (1 - beta1) (g - m)
      const float vj = std::fma(k2 * gj, gj, v[j] * beta2);  // beta2 v + (1 - beta2) g^2
      m[j] = mj, v[j] = vj;
      p[j] = p[j] + step * mj / (std::sqrt(vj) / r + eps_i);
    }
  });
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("all_finite", &all_finite, "whether every element of float32 tensors is finite",
        py::call_guard<py::gil_scoped_release>());
  m.def("adam_step", &adam_step,
        "one Adam update: (params, grads, exp_avgs, exp_avg_sqs, steps, lrs, beta1s, beta2s, "
        "weight_decays, eps)",
        py::call_guard<py::gil_scoped_release>());
}
