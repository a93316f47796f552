"""Training losses and the batch PSNR estimate."""

from __future__ import annotations

import math

import torch.nn.functional as F
from torch import Tensor

HUBER_DELTA = 0.1  # Instant-NGP's Huber transition (colour units in [0, 1])


def huber_sum(pred: Tensor, target: Tensor, delta: float = HUBER_DELTA) -> Tensor:
    """Sum over rays and channels of the Huber loss ``d^2 / (2 delta)`` (|d| < delta) or
    ``|d| - delta / 2``; ``pred``/``target`` [R, C]. Divide by the batch's ray count (not the
    tile's) so that accumulating tiles gives exactly the full-batch loss and gradient."""
    return F.smooth_l1_loss(pred, target, reduction="sum", beta=delta)


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB of a mean squared error of values in [0, 1] (inf for 0)."""
    return math.inf if mse <= 0 else -10.0 * math.log10(mse)
