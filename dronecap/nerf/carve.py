"""The visual hull of a dataset with alpha masks: which occupancy cells any training view sees
as background.

A synthetic composite (NeRF Synthetic, an alpha channel per image) says where the object is
not: a cell whose centre projects onto background pixels of any training view cannot hold
anything the images show. The occupancy grid starts from the hull and never marks a cell outside
it occupied (:func:`dronecap.nerf.occupancy.restrict`), so the first steps march only rays
through the object's silhouette cone instead of the whole AABB. Datasets without alpha
(camera footage) are not carved.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from dronecap.camera import Camera

# An alpha below this (of 255) is background.
BACKGROUND_ALPHA = 8
# Views the hull is carved from (evenly spread over the training frames; fewer views give a
# larger, still valid hull: with a fixed 3-px margin lego kept 37.0 % of its 64^3 cells from 32
# of its 100 views, 33.6 % from all 100).
MAX_VIEWS = 32
# Background pixels this many pixels beyond the projected radius of a cell still count as
# object (a cell is tested at its centre; its corners project up to that radius away).
MARGIN_PX = 1


def cell_centres(res: int, aabb: Tensor) -> Tensor:
    """Centres [res^3, 3] of the cells of a ``res``^3 grid over ``aabb`` [2, 3], x-major (the
    order of :func:`dronecap.nerf.occupancy.cell_index`)."""
    axis = (torch.arange(res, dtype=torch.float32) + 0.5) / res
    ijk = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    return aabb[0].cpu() + ijk * (aabb[1] - aabb[0]).cpu()


def _pixels(points: Tensor, camera: Camera) -> Tensor:
    """Integer pixel (column, row) [N, 2] int64 of camera-frame points [N, 3] with z > 0."""
    if camera.is_pinhole:
        k = torch.as_tensor(camera.matrix(), dtype=points.dtype)
        uv = points[:, :2] / points[:, 2:3] * k[[0, 1], [0, 1]] + k[[0, 1], [2, 2]]
    else:
        uv = torch.from_numpy(camera.project(points.numpy()))
    return uv.floor().long()


def hull(
    res: int,
    aabb: Tensor,
    alpha: Tensor,
    poses: Tensor,
    cameras: tuple[Camera, ...],
    camera_index: Tensor,
) -> Tensor:
    """bool [res^3]: cells no training view sees as background (the visual hull).

    Args:
        res: cells per axis; aabb: [2, 3] grid bounds (scene units).
        alpha: uint8 [N, H, W] coverage of the N training frames (255 = opaque).
        poses: [N, 4, 4] camera-to-world, OpenCV axes (z forward).
        cameras, camera_index: the camera table and each frame's camera in it (int64 [N]).
    A cell is removed when, in one of :data:`MAX_VIEWS` views spread over the frames, its centre
    lies in front of the camera, projects inside the image, and no pixel is foreground within
    the cell's projected radius (its half-diagonal at the nearest cell's depth, in the view's
    largest focal length) + :data:`MARGIN_PX`.
    """
    centres = cell_centres(res, aabb)
    half_diagonal = 0.5 * float((aabb[1] - aabb[0]).norm()) / res
    keep = torch.arange(len(centres))  # cells still in the hull: each view tests only those
    views = torch.linspace(0, len(poses) - 1, min(MAX_VIEWS, len(poses))).long().unique()
    fg = (alpha[views, None].cpu() >= BACKGROUND_ALPHA).float()
    h, w = fg.shape[2:]
    c2w = poses[views].float().cpu()
    for j, i in enumerate(views.tolist()):
        camera = cameras[int(camera_index[i])]
        cam = (centres[keep] - c2w[j, :3, 3]) @ c2w[j, :3, :3]  # world -> camera (orthonormal)
        front = torch.nonzero(cam[:, 2] > 1e-6).squeeze(1)
        if front.numel() == 0:
            continue
        radius = max(camera.fx, camera.fy) * half_diagonal / float(cam[front, 2].min())
        r = min(math.ceil(radius) + MARGIN_PX, max(h, w))
        near_fg = torch.nn.functional.max_pool2d(fg[j : j + 1], 2 * r + 1, 1, r)[0, 0] > 0
        uv = _pixels(cam[front], camera)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        seen, uv = front[inside], uv[inside]
        drop = torch.zeros(len(keep), dtype=torch.bool)
        drop[seen[~near_fg[uv[:, 1], uv[:, 0]]]] = True
        keep = keep[~drop]
    out = torch.zeros(len(centres), dtype=torch.bool)
    out[keep] = True
    return out
