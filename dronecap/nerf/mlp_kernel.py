"""The field's two MLPs in one C++ pass for the training step (``csrc/mlp.cpp``).

With torch, each layer of the density and colour MLPs is a matrix product over the whole batch
followed by a ReLU pass, and every [N, 64] activation (2 MB at 8k samples) leaves the core's L2
cache between one op and the next. The kernel takes 32 samples at a time through every layer,
and their backward, while they sit in L1. It computes the density logit and the colour logits
of each sample; the activations (``trunc_exp``, sigmoid) stay in torch. Its forward and
backward match the torch layers up to float32 summation order (tests/nerf/test_mlp_kernel.py).

It covers the shape every preset has: a density MLP of one hidden layer, a colour MLP of two,
float32 storage and products, a hidden width that is a multiple of 16 (at most 128). Other
configurations use the torch layers (:func:`usable`).
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor, nn

from .backend import kernel
from .backend import load as backend_load

MAX_HIDDEN = 128  # the kernel's tiles hold rows of at most this many floats
MAX_COLOR = 16  # colour channels the kernel's output tile holds


def usable(density_mlp: nn.Sequential, color_mlp: nn.Sequential, backend: str) -> bool:
    """Whether :func:`field_logits` can run these MLPs (bias-free ``Linear``/``ReLU`` stacks as
    :func:`nerf.field._mlp` builds them) under ``backend`` (:func:`nerf.backend.kernel`)."""
    dens = [m for m in density_mlp if isinstance(m, nn.Linear)]
    col = [m for m in color_mlp if isinstance(m, nn.Linear)]
    if len(dens) != 2 or len(col) != 3 or any(m.bias is not None for m in dens + col):
        return False
    hidden = dens[0].out_features
    widths_fit = (
        hidden % 16 == 0
        and hidden <= MAX_HIDDEN
        and dens[0].in_features <= MAX_HIDDEN
        and col[0].in_features <= MAX_HIDDEN
        and col[2].out_features <= MAX_COLOR
        and all(m.out_features == hidden for m in (col[0], col[1]))
    )
    return widths_fit and kernel("mlp", backend) is not None


def field_logits(
    encoded: Tensor,
    dir_enc: Tensor,
    ray_indices: Tensor,
    density_mlp: nn.Sequential,
    color_mlp: nn.Sequential,
    bf16: bool = False,
) -> Tensor:
    """Density and colour logits of samples through both MLPs, with autograd.

    Args:
        encoded: [N, E] the samples' hash encodings (gradient flows back to them).
        dir_enc: [R, S] SH encoding of each ray's direction (no gradient).
        ray_indices: [N] int64, each sample's ray.
        density_mlp, color_mlp: as :func:`usable` accepts; their weights get gradients.
        bf16: multiply bf16-rounded inputs on the AMX tiles (float32 sums, outputs and weight
            gradients); only where :func:`amx` is true.

    Returns:
        [N, 1 + C] float32: column 0 the density logit (the density MLP's first output),
        columns 1.. the colour logits.
    """
    weights = [m.weight for m in (*density_mlp, *color_mlp) if isinstance(m, nn.Linear)]
    return _FusedMLP.apply(encoded, dir_enc.detach(), ray_indices, bf16, *weights)


@functools.cache
def amx() -> bool:
    """Whether the fused kernel can multiply in bf16 on this CPU's AMX tiles (built for a CPU
    with AMX-BF16, and the tile state granted to this process)."""
    k = kernel("mlp")
    return k is not None and bool(k.amx())


class _FusedMLP(torch.autograd.Function):
    """Autograd wrapper of the kernel: gradients for the encodings and the five weights."""

    @staticmethod
    def forward(ctx, encoded, dir_enc, ray_indices, bf16, *weights):  # noqa: D102
        args = (encoded.float().contiguous(), dir_enc.float().contiguous(), ray_indices.long())
        ctx.save_for_backward(*args, *weights)
        ctx.bf16 = bf16
        return backend_load("mlp").forward(*args, *(w.float() for w in weights), bf16)

    @staticmethod
    def backward(ctx, grad):  # noqa: D102
        encoded, dir_enc, ray_indices, *weights = ctx.saved_tensors
        ws = [w.float() for w in weights]
        grads = backend_load("mlp").backward(
            grad.float().contiguous(), encoded, dir_enc, ray_indices, *ws, ctx.bf16
        )
        grad_e = grads[0] if ctx.needs_input_grad[0] else None
        return grad_e, None, None, None, *grads[1:]
