"""C++/OpenMP ray marching through the occupancy grid: a drop-in for :func:`nerf.marching.march`.

Same arguments, same :class:`~nerf.marching.Samples` and the same samples as the PyTorch
reference (the kernel repeats its float32 arithmetic operation by operation), several times
faster because no candidate tensor is ever materialised. The kernel is compiled on first use
and cached by :mod:`nerf.backend`, whose fallback rule :func:`march_function` follows.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .backend import kernel
from .backend import load as backend_load
from .kernel_args import f32
from .marching import Samples
from .marching import march as march_reference
from .occupancy import GridState


def load_extension():
    """The marching kernel (``csrc/march.cpp``), built on first use without fused
    multiply-adds, so its float32 results match the reference's tensor arithmetic exactly."""
    return backend_load("march")


def march_function(backend: str = "auto"):
    """The marching function for ``backend``: :func:`march` (C++) or the PyTorch reference
    :func:`nerf.marching.march`, by the rule of :func:`nerf.backend.kernel`."""
    return march if kernel("march", backend) is not None else march_reference


def march(
    origins: Tensor,
    dirs: Tensor,
    t_near: Tensor,
    t_far: Tensor,
    step: float,
    grid: GridState | None,
    aabb: Tensor,
    max_samples: int,
    offsets: Tensor | None = None,
    max_kept: int = 0,
) -> Samples:
    """March rays and keep the samples in occupied cells (CPU tensors).

    Args:
        origins, dirs: [R, 3] rays (unit directions, scene units).
        t_near, t_far: [R] the ray's segment inside the AABB (t_far <= t_near: no samples).
        step: marching step in scene units (> 0).
        grid: occupancy state (``occupied`` bool [res^3], x-major), or None to keep every sample.
        aabb: [2, 3] bounds of the grid.
        max_samples: at most this many candidates per ray.
        offsets: [R] position of the first sample within its step, in [0, 1) (training
            jitter); None puts samples at step midpoints (0.5).
        max_kept: > 0: a ray stops at this many kept samples (0: no limit).

    Returns:
        :class:`Samples` (ray_indices int64 [S] non-decreasing, t_starts/t_ends float32 [S]
        clipped to [t_near, t_far], counts int64 [R], t_resume float32 [R]).
    """
    if not step > 0:
        raise ValueError(f"marching step must be positive, got {step}")
    r = origins.shape[0]
    if offsets is None:
        offsets = torch.full((r,), 0.5)
    occupied = torch.zeros(0, dtype=torch.bool) if grid is None else grid.occupied
    ray_indices, t_starts, t_ends, counts, t_resume = load_extension().march(
        *(f32(t) for t in (origins, dirs, t_near, t_far)),
        float(step),
        occupied.contiguous(),
        f32(aabb),
        int(max_samples),
        f32(offsets),
        int(max_kept),
    )
    return Samples(ray_indices, t_starts, t_ends, counts, t_resume)
