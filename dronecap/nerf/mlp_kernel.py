"""The field's two MLPs in one C++ pass for the training step (``csrc/mlp.cpp``).

With torch, each layer of the density and colour MLPs is a matrix product over the whole batch
followed by a ReLU pass, and every [N, 64] activation (2 MB at 8k samples) leaves the core's L2
cache between one op and the next. The kernel takes 32 samples at a time through every layer,
and their backward, while they sit in L1. It returns each sample's colour (sigmoid of the colour
logits) and density (``trunc_exp`` of the density logit), and its backward takes their
gradients: the activations cost no torch ops either way. Its forward and backward match the
torch layers up to float32 summation order (tests/nerf/test_mlp_kernel.py).

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
from .kernel_args import f32, i64

MAX_HIDDEN = 128  # the kernel's tiles hold rows of at most this many floats
MAX_COLOR = 16  # colour channels the kernel's output tile holds


def usable(density_mlp: nn.Sequential, color_mlp: nn.Sequential, backend: str) -> bool:
    """Whether :func:`field_outputs` can run these MLPs (bias-free ``Linear``/``ReLU`` stacks as
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


def field_outputs(
    encoded: Tensor,
    dir_enc: Tensor,
    ray_indices: Tensor,
    weights: list[Tensor],
    bf16: bool,
    max_log_density: float,
) -> tuple[Tensor, Tensor]:
    """Colour and density of samples through both MLPs and their activations, with autograd.

    Args:
        encoded: [N, E] the samples' hash encodings (gradient flows back to them).
        dir_enc: [R, S] SH encoding of each ray's direction (no gradient).
        ray_indices: [N] int64, each sample's ray.
        weights: the five weights of MLPs :func:`usable` accepts (:func:`mlp_weights`); they
            get gradients.
        bf16: multiply bf16-rounded inputs on the AMX tiles (float32 sums, outputs and weight
            gradients); only where :func:`amx` is true.
        max_log_density: the density logit's clamp (``nerf.field.trunc_exp``).

    Returns:
        colour [N, C] in (0, 1) (sigmoid of the colour MLP's outputs) and density [N] per
        scene unit (exp of the density MLP's first output clamped to +-``max_log_density``),
        float32.
    """
    lim = float(max_log_density)
    return _FusedMLP.apply(encoded, dir_enc.detach(), ray_indices, bf16, lim, *weights)


def mlp_weights(density_mlp: nn.Sequential, color_mlp: nn.Sequential) -> list[Tensor]:
    """The five weights the kernel takes, in its order."""
    return [m.weight for m in (*density_mlp, *color_mlp) if isinstance(m, nn.Linear)]


def forward(encoded, dir_enc, ray_indices, weights, bf16: bool, lim: float) -> tuple:
    """The kernel's forward, without autograd: (rgb [N, C], sigma [N], logit) and the
    arguments :func:`backward` takes again (the inputs as the kernel saw them)."""
    args = (f32(encoded), f32(dir_enc), i64(ray_indices))
    rgb, sigma, logit = backend_load("mlp").forward(*args, *(f32(w) for w in weights), bf16, lim)
    return (rgb, sigma, logit), args


def backward(g_rgb, g_sigma, outputs, args, weights, bf16: bool, lim: float) -> list[Tensor]:
    """The kernel's backward: [grad of the encodings, grads of the five weights], given the
    gradients of colour and density (None: zero) and :func:`forward`'s outputs and args."""
    rgb, sigma, _ = outputs
    g_rgb = torch.zeros_like(rgb) if g_rgb is None else f32(g_rgb)
    g_sigma = torch.zeros_like(sigma) if g_sigma is None else f32(g_sigma)
    ws = [f32(w) for w in weights]
    return backend_load("mlp").backward(g_rgb, g_sigma, *outputs, *args, *ws, bf16, lim)


@functools.cache
def amx() -> bool:
    """Whether the fused kernel can multiply in bf16 on this CPU's AMX tiles (built for a CPU
    with AMX-BF16, and the tile state granted to this process)."""
    k = kernel("mlp")
    return k is not None and bool(k.amx())


class _FusedMLP(torch.autograd.Function):
    """Autograd wrapper of the kernel: gradients for the encodings and the five weights."""

    @staticmethod
    def forward(ctx, encoded, dir_enc, ray_indices, bf16, lim, *weights):  # noqa: D102
        outputs, args = forward(encoded, dir_enc, ray_indices, weights, bf16, lim)
        ctx.save_for_backward(*outputs, *args, *weights)
        ctx.bf16, ctx.lim = bf16, lim
        ctx.mark_non_differentiable(outputs[2])
        return outputs[0], outputs[1]

    @staticmethod
    def backward(ctx, g_rgb, g_sigma):  # noqa: D102
        saved = ctx.saved_tensors
        grads = backward(g_rgb, g_sigma, saved[:3], saved[3:6], saved[6:], ctx.bf16, ctx.lim)
        grad_e = grads[0] if ctx.needs_input_grad[0] else None
        return grad_e, None, None, None, None, *grads[1:]
