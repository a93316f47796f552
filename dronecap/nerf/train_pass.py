"""One tile of a training step: its rays rendered, their loss, and the gradients it adds.

The rendered colour passes through the photometric model (exposure, vignetting; the identity
when both are off) before the Huber loss, scaled by one over the batch's ray and channel counts
(not the tile's), so that the tiles' gradients sum to the full batch's. Where every part of the
pass has its C++ kernel, :mod:`.fused_pass` runs it without an autograd graph through the field
(the same values and gradients); else :func:`autograd_tile` does, through the field's autograd
Functions (any configuration, the distortion loss included).
"""

from __future__ import annotations

import torch
from torch import Tensor

from . import fused_pass
from .backend import kernel
from .batch import RayBatch
from .field import Field
from .losses import huber_loss
from .marching import Samples
from .photometric import Photometric
from .volrend import composite, distortion, render_packed


def tile_loss(
    field: Field, photometric: Photometric, rays: RayBatch, s: Samples, n_rays: int,
    distortion_weight: float, aabb: Tensor,
) -> float:  # fmt: skip
    """Forward and backward of one tile: its gradients added into the ``.grad`` of the field's
    and the photometric model's parameters; returns the tile's share of the batch loss.

    Args:
        rays: the tile's R rays; ``s`` their samples (ray indices from 0).
        n_rays: the batch's ray count (the loss's scale).
        distortion_weight: the distortion loss's weight per ray (0: none).
        aabb: [2, 3] the scene box (the distortion's unit: its diagonal).
    """
    if distortion_weight <= 0:
        loss = fused_pass.train_tile(field, photometric, rays, s, n_rays)
        if loss is not None:
            return loss
    return autograd_tile(field, photometric, rays, s, n_rays, distortion_weight, aabb)


def autograd_tile(
    field: Field, photometric: Photometric, rays: RayBatch, s: Samples, n_rays: int,
    distortion_weight: float, aabb: Tensor,
) -> float:  # fmt: skip
    """:func:`tile_loss` through autograd (any configuration)."""
    color, spread = render_rays(field, rays.origins, rays.dirs, s, rays.bg, distortion_weight, aabb)
    seen = photometric(color, rays.frame, rays.radius)
    ext = kernel("march", field.encoding.backend)  # the loss as the graph-free tile has it
    loss = huber_loss(seen, rays.target, n_rays * rays.target.shape[1], ext)
    if spread is not None:
        loss = loss + distortion_weight * spread.sum() / n_rays
    loss.backward()
    return float(loss.detach())


def render_rays(
    field: Field, origins: Tensor, dirs: Tensor, s: Samples, bg: Tensor,
    distortion_weight: float, aabb: Tensor,
) -> tuple[Tensor, Tensor | None]:  # fmt: skip
    """Colour [R, C] of rays ``origins``, ``dirs`` [R, 3] through ``field`` (with autograd)
    from their samples ``s``, composited on ``bg`` (or the far field), and each ray's
    distortion [R] in units of the diagonal of ``aabb`` (None when ``distortion_weight`` is 0).
    """
    dir_enc = field.dir_encoding(dirs)  # once per ray, gathered per sample

    def color_sigma(t0, t1, ri):  # the samples of ``s``, in order
        unit = field.unit(s.midpoints(origins, dirs)) if s.unit is None else s.unit
        return field.color_sigma(unit, dir_enc, ri, s.encoded)

    behind = field.behind(dirs, bg)  # the far field or the fixed background
    n = origins.shape[0]
    if distortion_weight <= 0:  # the colour alone
        backend = field.encoding.backend
        return composite(s.t_starts, s.t_ends, s.ray_indices, n, color_sigma, behind, backend), None
    out = render_packed(s.t_starts, s.t_ends, s.ray_indices, n, color_sigma, behind)
    diag = float(torch.linalg.norm(aabb[1] - aabb[0]))  # t in AABB diagonals
    t0, t1 = s.t_starts / diag, s.t_ends / diag
    return out.color, distortion(out.weights, t0, t1, s.ray_indices, n)
