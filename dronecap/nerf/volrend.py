"""Volume rendering of packed samples (takes a callable, never the model).

For sample i of a ray with optical thickness ``tau_i = sigma_i * (t_end - t_start)``:
``alpha_i = 1 - exp(-tau_i)``, transmittance ``T_i = exp(-sum_{j<i} tau_j)`` and weight
``w_i = T_i * alpha_i``. The ray colour is ``sum_i w_i c_i + (1 - sum_i w_i) * background``.
The per-ray exclusive prefix sum is done in float64 so that opaque samples (tau up to ~1e4)
on earlier rays do not wipe out the precision of later rays' sums.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from .backend import kernel
from .backend import load as backend_load

# (t_starts [S], t_ends [S], ray_indices [S]) -> (colors [S, C], sigmas [S])
ColorSigmaFn = Callable[[Tensor, Tensor, Tensor], tuple[Tensor, Tensor]]


class Rendered(NamedTuple):
    """What :func:`render_packed` returns for R rays of S packed samples."""

    color: Tensor  # [R, C] composited on the background
    opacity: Tensor  # [R] sum of the weights
    depth: Tensor  # [R] expected distance (0 for empty rays)
    weights: Tensor  # [S] rendering weight of each sample


def packed_weights(tau: Tensor, ray_indices: Tensor, n_rays: int) -> tuple[Tensor, Tensor]:
    """Rendering weights of packed samples.

    Args:
        tau: [S] optical thickness of each sample (>= 0; sigma * step length).
        ray_indices: [S] int64 ray of each sample, non-decreasing.
        n_rays: number of rays R.

    Returns:
        weights [S] and transmittance before each sample [S], both float32 in [0, 1].
    """
    tau = torch.nan_to_num(tau.float(), nan=0.0, posinf=1e4).clamp(0.0, 1e4)
    csum = torch.cumsum(tau.double(), 0)
    ray_total = torch.zeros(n_rays + 1, dtype=torch.float64, device=tau.device)
    ray_total.index_add_(0, ray_indices + 1, tau.double())
    start = torch.cumsum(ray_total, 0)[:-1]  # sum of tau over all earlier rays
    excl = (csum - tau.double() - start[ray_indices]).clamp_min(0.0).float()
    trans = torch.exp(-excl)
    alpha = -torch.expm1(-tau)
    return trans * alpha, trans


def accumulate(values: Tensor, ray_indices: Tensor, n_rays: int) -> Tensor:
    """Per-ray sum of packed ``values`` [S, ...] -> [n_rays, ...]."""
    out = torch.zeros((n_rays, *values.shape[1:]), dtype=values.dtype, device=values.device)
    return out.index_add(0, ray_indices, values)


def render_packed(
    t_starts: Tensor,
    t_ends: Tensor,
    ray_indices: Tensor,
    n_rays: int,
    color_sigma_fn: ColorSigmaFn,
    background: Tensor,
) -> Rendered:
    """Render packed samples.

    Args:
        t_starts, t_ends: [S] sample intervals along each ray (scene units).
        ray_indices: [S] ray of each sample (non-decreasing).
        n_rays: R.
        color_sigma_fn: returns colours [S, C] and densities [S] of the samples.
        background: [R, C] or [C] colour behind each ray.

    Returns:
        :class:`Rendered` (colour, opacity, depth per ray; weight per sample).
    """
    colors, sigmas = color_sigma_fn(t_starts, t_ends, ray_indices)
    weights, _ = packed_weights(sigmas * (t_ends - t_starts), ray_indices, n_rays)
    rgb = accumulate(weights.unsqueeze(-1) * colors, ray_indices, n_rays)
    opacity = accumulate(weights, ray_indices, n_rays)
    depth = accumulate(weights * 0.5 * (t_starts + t_ends), ray_indices, n_rays)
    bg = background.expand(n_rays, -1) if background.ndim == 1 else background
    return Rendered(rgb + (1.0 - opacity).unsqueeze(-1) * bg, opacity, depth, weights)


def composite(
    t_starts: Tensor,
    t_ends: Tensor,
    ray_indices: Tensor,
    n_rays: int,
    color_sigma_fn: ColorSigmaFn,
    background: Tensor,
    backend: str = "auto",
) -> Tensor:
    """Colour [R, C] of :func:`render_packed` alone (the training pass needs nothing else).

    With the C++ kernel (``csrc/march.cpp``; :func:`nerf.backend.kernel` of ``backend``) the
    weights, the sums per ray and their backward are one pass over the samples each, instead
    of ~15 tensor ops each way; the same values and gradients up to float32 summation order.
    """
    if kernel("march", backend) is None or t_starts.device.type != "cpu":
        out = render_packed(t_starts, t_ends, ray_indices, n_rays, color_sigma_fn, background)
        return out.color
    colors, sigmas = color_sigma_fn(t_starts, t_ends, ray_indices)
    bg = background.expand(n_rays, colors.shape[1]).float().contiguous()
    return _Composite.apply(sigmas.float().contiguous(), colors.float().contiguous(),
                            t_starts.float().contiguous(), t_ends.float().contiguous(),
                            ray_indices.long().contiguous(), bg)  # fmt: skip


class _Composite(torch.autograd.Function):
    """Autograd wrapper of the C++ compositing: gradients for densities, colours, background."""

    @staticmethod
    def forward(ctx, sigmas, colors, t_starts, t_ends, ray_indices, bg):  # noqa: D102
        ctx.save_for_backward(sigmas, colors, t_starts, t_ends, ray_indices, bg)
        return backend_load("march").composite(sigmas, colors, t_starts, t_ends, ray_indices, bg)

    @staticmethod
    def backward(ctx, grad):  # noqa: D102
        d_sigma, d_rgb, d_bg = backend_load("march").composite_backward(
            grad.float().contiguous(), *ctx.saved_tensors
        )
        return d_sigma, d_rgb, None, None, None, d_bg


def distortion(
    weights: Tensor, t_starts: Tensor, t_ends: Tensor, ray_indices: Tensor, n_rays: int
) -> Tensor:
    """Per-ray distortion (Mip-NeRF 360, Barron et al. 2022) of packed samples -> [R].

    ``sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 d_i`` with ``m`` the interval midpoints
    and ``d`` their lengths (the units of ``t``): small when a ray's weight sits in one short
    stretch (a surface), large when it is spread along the ray (fog). The double sum is
    ``2 sum_i w_i (m_i W_i - S_i)`` with ``W_i``, ``S_i`` the sums of ``w_j`` and ``w_j m_j``
    over the ray's earlier samples (samples ordered along each ray), so it costs O(S).

    Args:
        weights: [S] rendering weights (:func:`packed_weights`).
        t_starts, t_ends: [S] sample intervals.
        ray_indices: [S] ray of each sample, non-decreasing.
        n_rays: R.
    """
    mid = 0.5 * (t_starts + t_ends)
    w = weights.double()
    wm = w * mid.double()

    def earlier(x: Tensor) -> Tensor:  # sum over the same ray's earlier samples, [S]
        total = torch.zeros(n_rays + 1, dtype=x.dtype, device=x.device)
        total.index_add_(0, ray_indices + 1, x)
        return torch.cumsum(x, 0) - x - torch.cumsum(total, 0)[:-1][ray_indices]

    pairs = 2.0 * w * (mid.double() * earlier(w) - earlier(wm))
    own = w * w * (t_ends - t_starts).double() / 3.0
    return accumulate((pairs + own).float(), ray_indices, n_rays)
