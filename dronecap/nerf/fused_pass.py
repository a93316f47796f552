"""A tile of the training pass without an autograd graph through the field, where every part
of it runs in C++.

A training step renders its rays from the samples compaction kept: their hash encodings
(computed by the pre-pass), both MLPs (:mod:`.mlp_kernel`) and the compositing along each ray
(:func:`.volrend.composite`). Through autograd each is a Function of its own, and the glue
between them (Function applications, their Python backward calls, the engine's work between
them) cost ~0.5 ms of a ~6 ms lego step at two threads. :func:`train_tile` calls the same
kernels in the same order, forward then backward, and hands each parameter its gradient. The
loss's gradient comes from :func:`.losses.huber_loss_and_grad` (the backward of
:func:`.losses.huber_loss`); only a learned photometric model and a far field (small torch
ops) go through autograd. The same values and gradients as :func:`.train_pass.autograd_tile`,
bit for bit (tests/nerf/test_fused_pass.py).
"""

from __future__ import annotations

import torch
from torch import Tensor

from . import mlp_kernel
from .backend import kernel
from .batch import RayBatch
from .field import Field
from .hashgrid import table_backward
from .kernel_args import f32, i64
from .losses import huber_loss, huber_loss_and_grad
from .marching import Samples
from .photometric import Photometric


def train_tile(
    field: Field, photometric: Photometric, rays: RayBatch, s: Samples, n_rays: int
) -> float | None:
    """Forward and backward of one tile (:func:`.train_pass.tile_loss` without the distortion
    loss): gradients added into the ``.grad`` of the hash table, the MLP weights, the far field
    and the photometric model; returns the tile's loss.

    Returns None, having done nothing, where a part has no kernel here: no cached encodings
    (``s.encoded``, ``s.unit``: compaction's pre-pass), the torch MLPs or encoding, a table
    stored below float32, tensors off the CPU.
    """
    mlp = field.mlp_kernel_args()
    layout = field.encoding.backward_args()
    march = kernel("march", field.encoding.backend)
    if s.encoded is None or s.unit is None or mlp is None or layout is None or march is None:
        return None
    if s.t_starts.device.type != "cpu":
        return None
    weights, bf16, lim = mlp
    t0, t1, ri = f32(s.t_starts), f32(s.t_ends), i64(s.ray_indices)
    behind = field.behind(rays.dirs, rays.bg)  # with autograd for a far field
    n_rays_tile = rays.dirs.shape[0]
    fixed = not behind.requires_grad and behind.shape == (n_rays_tile, rays.target.shape[1])
    bg = f32(behind if fixed else behind.detach().expand(n_rays_tile, -1))
    with torch.no_grad():
        dir_enc = field.dir_encoding(rays.dirs)
        outputs, args = mlp_kernel.forward(s.encoded, dir_enc, ri, weights, bf16, lim)
        rgb, sigma, _ = outputs
        color = march.composite(sigma, rgb, t0, t1, ri, bg)
    divisor = n_rays * rays.target.shape[1]
    if photometric.identity():  # the loss's gradient by hand: no autograd at all
        loss, g = huber_loss_and_grad(color, rays.target, divisor, march)
    else:  # the loss and the photometric model through autograd, from the colour on
        color.requires_grad_(True)
        seen = photometric(color, rays.frame, rays.radius)
        loss = huber_loss(seen, rays.target, divisor, march)
        loss.backward()
        g = color.grad
    with torch.no_grad():
        g = f32(g)
        d_sigma, d_rgb, d_bg = march.composite_backward(g, sigma, rgb, t0, t1, ri, bg)
        grads = mlp_kernel.backward(d_rgb, d_sigma, outputs, args, weights, bf16, lim)
        table = field.encoding.table
        leaf = table if field.encoding.inplace_grad else None  # its gradient added in place
        _add_grad(table, table_backward(grads[0], f32(s.unit), layout, leaf))
        for w, gw in zip(weights, grads[1:], strict=True):
            _add_grad(w, gw)
    if behind.requires_grad:  # the far field's colours
        behind.backward(d_bg if behind.ndim == 2 else d_bg.sum(0))
    return float(loss.detach() if loss.requires_grad else loss)


def _add_grad(p: Tensor, g: Tensor | None) -> None:
    """Add ``g`` (None: nothing, already added) into ``p.grad`` as autograd would."""
    if g is None:
        return
    if p.grad is None:
        p.grad = g
    else:
        p.grad.add_(g)
