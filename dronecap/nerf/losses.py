"""Training losses and the batch PSNR estimate."""

from __future__ import annotations

import math

import torch
from torch import Tensor

HUBER_DELTA = 0.1  # Instant-NGP's Huber transition (colour units in [0, 1])


def huber_loss(pred: Tensor, target: Tensor, divisor: int, ext=None) -> Tensor:
    """The sum over rays and channels of the Huber loss ``d^2 / (2 delta)`` (|d| < delta) or
    ``|d| - delta / 2`` of ``d = pred - target`` ([R, C]), divided by ``divisor``, with
    autograd to ``pred``. The trainer divides by the batch's ray and channel counts (not the
    tile's), so that accumulating tiles gives exactly the full-batch loss and gradient.
    ``ext``: as in :func:`huber_loss_and_grad`."""
    return _Huber.apply(pred, target, divisor, ext)


@torch.no_grad()
def huber_loss_and_grad(
    pred: Tensor, target: Tensor, divisor: int, ext=None
) -> tuple[Tensor, Tensor]:
    """:func:`huber_loss` and its gradient [R, C] w.r.t. ``pred``, without autograd (the values
    of torch's smooth L1 loss, ``beta`` = delta, up to float32 rounding). NaN and inf reach
    the loss. ``ext``: the marching kernel (``nerf.backend.kernel("march")``), whose ``huber``
    does it in one pass for float32 CPU tensors (~2 instead of ~65 us for a lego batch; the
    same gradient, the loss summed in double), or None (torch ops)."""
    cpu32 = pred.dtype == target.dtype == torch.float32 and pred.device.type == "cpu"
    if ext is not None and cpu32:
        loss, grad = ext.huber(pred, target, divisor, HUBER_DELTA)
        return loss, grad
    d = pred - target
    z = d.abs()
    loss = torch.where(z < HUBER_DELTA, 0.5 * z * z / HUBER_DELTA, z - 0.5 * HUBER_DELTA)
    grad = torch.where(z < HUBER_DELTA, d / HUBER_DELTA, d.sign()) / divisor
    return loss.sum() / divisor, grad


class _Huber(torch.autograd.Function):
    """:func:`huber_loss` as one node whose backward is :func:`huber_loss_and_grad`'s gradient
    (what the graph-free training tile hands back itself: the two agree bit for bit)."""

    @staticmethod
    def forward(ctx, pred, target, divisor, ext):  # noqa: D102
        loss, grad = huber_loss_and_grad(pred, target, divisor, ext)
        ctx.save_for_backward(grad)
        return loss

    @staticmethod
    def backward(ctx, g):  # noqa: D102
        (grad,) = ctx.saved_tensors
        return grad * g, None, None, None


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB of a mean squared error of values in [0, 1] (inf for 0)."""
    return math.inf if mse <= 0 else -10.0 * math.log10(mse)
