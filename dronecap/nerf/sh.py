"""Real spherical-harmonics encoding of view directions (Instant-NGP's direction encoding)."""

from __future__ import annotations

import torch
from torch import Tensor

from .backend import kernel


def sh_dim(degree: int) -> int:
    """Number of coefficients of an encoding of ``degree`` bands (degree 4 -> 16)."""
    if not 1 <= degree <= 4:
        raise ValueError(f"sh_degree must be 1..4, got {degree}")
    return degree * degree


def sh_encode(dirs: Tensor, degree: int = 4, backend: str = "torch") -> Tensor:
    """Real SH basis (bands 0..degree-1) evaluated at unit directions.

    Args:
        dirs: [N, 3] unit vectors (x, y, z), any float dtype.
        degree: number of bands, 1..4.
        backend: ``nerf.backend``'s rule for the marching kernel, whose ``sh_encode`` takes
            float32 CPU directions without autograd in one call (the same values; ~45 tensor
            ops here); the default is this PyTorch code (the field passes its own backend).

    Returns:
        [N, degree**2] coefficients, same dtype as ``dirs``.
    """
    n = sh_dim(degree)
    plain = dirs.dtype == torch.float32 and dirs.device.type == "cpu" and not dirs.requires_grad
    ext = kernel("march", backend) if plain else None
    if ext is not None:
        return ext.sh_encode(dirs, degree)
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if degree > 1:
        out += [-0.48860251190291987 * y, 0.48860251190291987 * z, -0.48860251190291987 * x]
    if degree > 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            1.0925484305920792 * x * y,
            -1.0925484305920792 * y * z,
            0.94617469575755997 * zz - 0.31539156525251999,
            -1.0925484305920792 * x * z,
            0.54627421529603959 * (xx - yy),
        ]
    if degree > 3:
        out += [
            0.59004358992664352 * y * (3 * xx - yy),
            2.8906114426405538 * x * y * z,
            0.45704579946446572 * y * (1 - 5 * zz),
            0.3731763325901154 * z * (5 * zz - 3),
            0.45704579946446572 * x * (1 - 5 * zz),
            1.4453057213202769 * z * (xx - yy),
            0.59004358992664352 * x * (xx - 3 * yy),
        ]
    res = torch.stack(out, -1)
    assert res.shape[-1] == n
    return res
