"""Tensors as the C++ kernels take them, without a torch op where they already are so.

``t.float().contiguous()`` costs two dispatched torch ops (~1 us) even when ``t`` is already a
contiguous float32 tensor, and a training step passes ~40 such arguments to its kernels. The
kernels record no autograd history, so a tensor that requires grad is passed as it is.
"""

from __future__ import annotations

import torch
from torch import Tensor


def f32(t: Tensor) -> Tensor:
    """``t`` as a contiguous float32 tensor (``t`` itself when it is one)."""
    if t.dtype is torch.float32 and t.is_contiguous():
        return t
    return t.detach().float().contiguous()


def i64(t: Tensor) -> Tensor:
    """``t`` as a contiguous int64 tensor (``t`` itself when it is one)."""
    if t.dtype is torch.int64 and t.is_contiguous():
        return t
    return t.detach().long().contiguous()
