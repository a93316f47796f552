"""Camera rays through the stored camera model (OpenCV axes) and their intersection with an AABB.

Rays go through pixel centres ``(u + 0.5, v + 0.5)`` *as the lens saw them*: the camera's
distortion model (:class:`dronecap.camera.Camera`: SIMPLE_RADIAL, OPENCV, fisheye, ...) is undone
once per camera by OpenCV (:meth:`Camera.pixel_directions`) and the resulting table of
camera-frame directions is cached, so training, rendering and evaluation all cast the rays the
images were actually taken along. A dataset with a camera per frame (several drones) casts each
frame's rays through its own camera (:func:`frame_rays`).
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from dronecap.camera import Camera

from .backend import kernel

if TYPE_CHECKING:
    from dronecap.datasets.format import Dataset

TINY = 1e-12  # direction components smaller than this count as parallel to a slab


@functools.lru_cache(maxsize=16)
def pixel_directions(camera: Camera) -> Tensor:
    """Camera-frame directions (x/z, y/z, 1) through every pixel centre of ``camera``,
    undistorted through its lens model: float32 [H, W, 3] CPU tensor, cached per camera."""
    return torch.from_numpy(camera.pixel_directions())


def camera_rays(c2w: Tensor, camera: Camera, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """Rays through pixels ``(u, v)`` of ``camera`` (through their centres, lens included).

    Args:
        c2w: [4, 4] or [N, 4, 4] camera-to-world, OpenCV axes (x right, y down, z forward).
        camera: intrinsics and distortion of the image the pixels belong to.
        u, v: [N] integer pixel column and row indices (0 <= u < width, 0 <= v < height).

    Returns:
        origins [N, 3] and unit directions [N, 3] in world (scene) units, float32, on the
        device of ``c2w``.
    """
    table = pixel_directions(camera).to(c2w.device)
    d = table[v.long(), u.long()]
    c2w = c2w.float()
    rot = c2w[..., :3, :3]
    dirs = (rot @ d.unsqueeze(-1)).squeeze(-1) if rot.ndim == 3 else d @ rot.T
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    origins = c2w[..., :3, 3].expand_as(dirs)
    return origins.contiguous(), dirs


@functools.lru_cache(maxsize=4)
def direction_tables(cameras: tuple[Camera, ...]) -> Tensor:
    """The direction tables of ``cameras`` stacked: float32 [K, H, W, 3] CPU tensor."""
    return torch.stack([pixel_directions(k) for k in cameras])


def frame_cameras(
    ds: Dataset, idx: np.ndarray, device: torch.device | str = "cpu"
) -> tuple[tuple[Camera, ...], Tensor]:
    """The camera table of ``ds`` and the camera of each frame ``idx`` [M] in it (int64 [M]
    tensor on ``device``); a single-camera dataset is a table of one."""
    if ds.cameras is None or ds.camera_index is None:
        return (ds.camera_of(0),), torch.zeros(len(idx), dtype=torch.int64, device=device)
    index = np.asarray(ds.camera_index, np.int64)[idx]
    return tuple(ds.cameras), torch.as_tensor(index, device=device)


def frame_rays(
    c2w: Tensor, cameras: tuple[Camera, ...], which: Tensor, u: Tensor, v: Tensor
) -> tuple[Tensor, Tensor]:
    """Rays through pixels ``(u, v)``, each of its own frame's camera (all cameras the same
    image size).

    Args:
        c2w: [N, 4, 4] camera-to-world of each ray's frame, OpenCV axes.
        cameras: the table of cameras [K].
        which: [N] index into ``cameras`` of each ray's camera.
        u, v: [N] integer pixel column and row indices.

    Returns:
        origins [N, 3] and unit directions [N, 3] (world units, float32, on ``c2w``'s device).
    """
    if len(cameras) == 1:
        return camera_rays(c2w, cameras[0], u, v)
    table = direction_tables(cameras).to(c2w.device)
    d = table[which.long(), v.long(), u.long()]
    c2w = c2w.float()
    dirs = (c2w[:, :3, :3] @ d.unsqueeze(-1)).squeeze(-1)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    return c2w[:, :3, 3].contiguous(), dirs


def ray_aabb(
    origins: Tensor, dirs: Tensor, aabb: Tensor, backend: str = "torch"
) -> tuple[Tensor, Tensor, Tensor]:
    """Slab intersection of rays with an axis-aligned box.

    Args:
        origins: [N, 3] scene units.
        dirs: [N, 3] directions (need not be unit; t is in units of |dir|).
        aabb: [2, 3] (min, max).
        backend: ``nerf.backend``'s rule for the marching kernel, whose ``ray_aabb`` takes
            float32 CPU rays without autograd in one call (the same values; ~15 tensor ops
            here); the default is this PyTorch code.

    Returns:
        t_near [N] (>= 0: a ray starting inside the box starts at 0), t_far [N], hit [N] bool
        (t_far > t_near). Never NaN, also for direction components of exactly 0.
    """
    plain = all(
        t.dtype == torch.float32 and t.device.type == "cpu" and not t.requires_grad
        for t in (origins, dirs, aabb)
    )
    ext = kernel("march", backend) if plain else None
    if ext is not None:
        return tuple(ext.ray_aabb(origins, dirs, aabb, TINY))
    safe = torch.where(dirs.abs() < TINY, torch.where(dirs < 0, -TINY, TINY), dirs)
    inv = 1.0 / safe
    t0 = (aabb[0] - origins) * inv
    t1 = (aabb[1] - origins) * inv
    t_near = torch.minimum(t0, t1).amax(-1).clamp_min(0.0)
    t_far = torch.maximum(t0, t1).amin(-1)
    hit = t_far > t_near
    return t_near, torch.where(hit, t_far, t_near), hit
