"""The SH direction encoding: an orthonormal basis, the same from the kernel and from torch."""

import math

import pytest
import torch

from dronecap.nerf.backend import kernel
from dronecap.nerf.sh import sh_dim, sh_encode


def _directions(n: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)


@pytest.mark.parametrize("degree", [1, 2, 3, 4])
def test_bands_are_orthonormal_over_the_sphere(degree):
    y = sh_encode(_directions(200_000).double(), degree)  # the torch path (float64)
    gram = 4 * math.pi * (y.T @ y) / y.shape[0]  # Monte Carlo integral of Y_i Y_j
    assert y.shape[1] == sh_dim(degree)
    assert torch.allclose(gram, torch.eye(sh_dim(degree), dtype=gram.dtype), atol=0.02)


@pytest.mark.parametrize("degree", [1, 2, 3, 4])
def test_kernel_encodes_as_the_torch_path(degree):
    if kernel("march", "auto") is None:
        pytest.skip("the C++ marching kernel does not build here")
    d = torch.cat([_directions(1000), torch.eye(3), torch.zeros(1, 3)])  # axes, a zero vector
    want, got = sh_encode(d, degree, "torch"), sh_encode(d, degree, "cpp")
    torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-7)
    with pytest.raises(RuntimeError, match="1..4"):
        kernel("march", "cpp").sh_encode(d, 5)


def test_directions_with_autograd_take_the_torch_path():
    d = _directions(8).requires_grad_()
    sh_encode(d, 4, "cpp").sum().backward()
    assert d.grad is not None and torch.isfinite(d.grad).all()
