"""Volume rendering of packed samples (takes a callable, never the model).

For sample i of a ray with optical thickness ``tau_i = sigma_i * (t_end - t_start)``:
``alpha_i = 1 - exp(-tau_i)``, transmittance ``T_i = exp(-sum_{j<i} tau_j)`` and weight
``w_i = T_i * alpha_i``. The ray colour is ``sum_i w_i c_i + (1 - sum_i w_i) * background``.
The per-ray exclusive prefix sum is done in float64 so that opaque samples (tau up to ~1e4)
on earlier rays do not wipe out the precision of later rays' sums.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

# (t_starts [S], t_ends [S], ray_indices [S]) -> (colors [S, C], sigmas [S])
ColorSigmaFn = Callable[[Tensor, Tensor, Tensor], tuple[Tensor, Tensor]]


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
) -> tuple[Tensor, Tensor, Tensor]:
    """Render packed samples.

    Args:
        t_starts, t_ends: [S] sample intervals along each ray (scene units).
        ray_indices: [S] ray of each sample (non-decreasing).
        n_rays: R.
        color_sigma_fn: returns colours [S, C] and densities [S] of the samples.
        background: [R, C] or [C] colour behind each ray.

    Returns:
        color [R, C], opacity [R], depth [R] (expected distance; 0 for empty rays).
    """
    colors, sigmas = color_sigma_fn(t_starts, t_ends, ray_indices)
    weights, _ = packed_weights(sigmas * (t_ends - t_starts), ray_indices, n_rays)
    rgb = accumulate(weights.unsqueeze(-1) * colors, ray_indices, n_rays)
    opacity = accumulate(weights, ray_indices, n_rays)
    depth = accumulate(weights * 0.5 * (t_starts + t_ends), ray_indices, n_rays)
    bg = background.expand(n_rays, -1) if background.ndim == 1 else background
    return rgb + (1.0 - opacity).unsqueeze(-1) * bg, opacity, depth
