"""The training pass as one autograd node, when every part of it runs in C++.

A training step renders its rays from the samples compaction kept: their hash encodings
(computed by the pre-pass), both MLPs (:mod:`.mlp_kernel`) and the compositing along each ray
(:func:`.volrend.composite`). Each is an autograd Function of its own, and the glue between
them (three Function applications, three Python backward calls and the engine's work between
them) cost ~0.3 ms of a ~6 ms lego step at two threads. :func:`colors` calls the same kernels
in the same order under one Function: the same values and gradients, bit for bit
(tests/nerf/test_fused_pass.py), and the trainer falls back to the separate Functions wherever
a part has no kernel.
"""

from __future__ import annotations

import torch
from torch import Tensor

from . import mlp_kernel
from .backend import kernel
from .backend import load as backend_load
from .field import Field
from .hashgrid import table_backward
from .marching import Samples


def colors(field: Field, s: Samples, dir_enc: Tensor, behind: Tensor) -> Tensor | None:
    """Colour [R, C] of the rays of ``s`` through ``field``, composited on ``behind``, with
    autograd to the hash table, the MLP weights and ``behind``.

    Args:
        field: the model.
        s: packed samples of R rays with their encodings and unit-cube midpoints
            (``s.encoded``, ``s.unit``: compaction's pre-pass).
        dir_enc: [R, sh_degree^2] the rays' :meth:`Field.dir_encoding`.
        behind: [R, C] or [C] what each ray sees past its samples (``Field.behind``).

    Returns:
        the colours, or None where a part has no kernel here (no cached encodings, the torch
        MLPs or encoding, a table stored below float32, tensors off the CPU): then render with
        ``Field.color_sigma`` and ``volrend.composite``.
    """
    mlp = field.mlp_kernel_args()
    layout = field.encoding.backward_args()
    march = kernel("march", field.encoding.backend)
    if s.encoded is None or s.unit is None or mlp is None or layout is None or march is None:
        return None
    if s.t_starts.device.type != "cpu":
        return None
    weights, bf16, lim = mlp
    n_rays = dir_enc.shape[0]
    bg = behind.expand(n_rays, -1) if behind.ndim == 1 else behind
    table = field.encoding.table
    leaf = table if field.encoding.inplace_grad else None  # its gradient added in place
    return _Pass.apply(
        s.unit.float().contiguous(), s.encoded, dir_enc, s.t_starts.float().contiguous(),
        s.t_ends.float().contiguous(), s.ray_indices.long().contiguous(),
        bg.float().contiguous(), (leaf, layout, bf16, lim), table, *weights,
    )  # fmt: skip


class _Pass(torch.autograd.Function):
    """Both MLPs and the compositing forward; compositing, MLP and table backward."""

    @staticmethod
    def forward(ctx, unit, encoded, dir_enc, t0, t1, ri, bg, how, table, *weights):  # noqa: D102
        _, _, bf16, lim = how
        outputs, args = mlp_kernel.forward(encoded, dir_enc, ri, weights, bf16, lim)
        rgb, sigma, _ = outputs
        color = backend_load("march").composite(sigma, rgb, t0, t1, ri, bg)
        ctx.save_for_backward(unit, t0, t1, ri, bg, *outputs, *args, *weights)
        ctx.how = how
        return color

    @staticmethod
    def backward(ctx, grad):  # noqa: D102
        unit, t0, t1, ri, bg, *rest = ctx.saved_tensors
        outputs, args, weights = rest[:3], rest[3:6], rest[6:]
        leaf, layout, bf16, lim = ctx.how
        rgb, sigma, _ = outputs
        march = backend_load("march")
        d_sigma, d_rgb, d_bg = march.composite_backward(
            grad.float().contiguous(), sigma, rgb, t0, t1, ri, bg
        )
        grads = mlp_kernel.backward(d_rgb, d_sigma, outputs, args, weights, bf16, lim)
        g_table = table_backward(grads[0], unit, layout, leaf)  # None: added into leaf.grad
        return None, None, None, None, None, None, d_bg, None, g_table, *grads[1:]
