"""Camera rays of pinhole views (OpenCV axes) and their intersection with an AABB."""

from __future__ import annotations

import torch
from torch import Tensor

TINY = 1e-12  # direction components smaller than this count as parallel to a slab


def camera_rays(c2w: Tensor, fx: float, fy: float, cx: float, cy: float, u: Tensor, v: Tensor):
    """Rays through pixel indices ``(u, v)`` of a pinhole camera (pixel centres at +0.5).

    Args:
        c2w: [4, 4] or [N, 4, 4] camera-to-world, OpenCV axes (x right, y down, z forward).
        fx, fy, cx, cy: intrinsics in pixels.
        u, v: [N] pixel column and row indices (int or float).

    Returns:
        origins [N, 3] and unit directions [N, 3] in world (scene) units, float32.
    """
    d = torch.stack(
        [
            (u.float() + 0.5 - cx) / fx,
            (v.float() + 0.5 - cy) / fy,
            torch.ones_like(u, dtype=torch.float32),
        ],
        -1,
    )
    c2w = c2w.float()
    rot = c2w[..., :3, :3]
    dirs = (rot @ d.unsqueeze(-1)).squeeze(-1) if rot.ndim == 3 else d @ rot.T
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    origins = c2w[..., :3, 3].expand_as(dirs)
    return origins.contiguous(), dirs


def ray_aabb(origins: Tensor, dirs: Tensor, aabb: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Slab intersection of rays with an axis-aligned box.

    Args:
        origins: [N, 3] scene units.
        dirs: [N, 3] directions (need not be unit; t is in units of |dir|).
        aabb: [2, 3] (min, max).

    Returns:
        t_near [N] (>= 0: a ray starting inside the box starts at 0), t_far [N], hit [N] bool
        (t_far > t_near). Never NaN, also for direction components of exactly 0.
    """
    safe = torch.where(dirs.abs() < TINY, torch.where(dirs < 0, -TINY, TINY), dirs)
    inv = 1.0 / safe
    t0 = (aabb[0] - origins) * inv
    t1 = (aabb[1] - origins) * inv
    t_near = torch.minimum(t0, t1).amax(-1).clamp_min(0.0)
    t_far = torch.maximum(t0, t1).amin(-1)
    hit = t_far > t_near
    return t_near, torch.where(hit, t_far, t_near), hit
