"""The fused C++ MLPs of the training pass: the torch layers' values and gradients."""

import math

import numpy as np
import pytest
import torch

from dronecap.nerf.backend import kernel
from dronecap.nerf.config import preset
from dronecap.nerf.field import MAX_LOG_DENSITY, Field, trunc_exp
from dronecap.nerf.mlp_kernel import amx, field_outputs, mlp_weights, usable

AABB = np.array([[-1.0, -1, -1], [1, 1, 1]])
needs_kernel = pytest.mark.skipif(
    kernel("mlp", "auto") is None, reason="C++ MLP kernel unavailable"
)


def _field(channels: int = 3, **changes) -> Field:
    torch.manual_seed(0)
    changes = {"mlp_dtype": "fp32", **changes}  # exact products unless a test asks for bf16
    f = Field(preset("scene-sized").replace(n_max=64, **changes), channels, AABB)
    with torch.no_grad():
        for p in f.parameters():
            p.mul_(3)  # weights large enough that many ReLUs are on and logits are O(1)
    return f


def _torch_outputs(f: Field, enc: torch.Tensor, dir_enc: torch.Tensor, ri: torch.Tensor):
    h = f._run(f.density_mlp, enc)
    return _activated(h, f._run(f.color_mlp, torch.cat([h, dir_enc[ri]], -1)))


def _activated(h: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """[colour | density] [N, C + 1] from the density MLP's outputs h and the colour logits c."""
    return torch.cat([torch.sigmoid(c), trunc_exp(h[:, :1])], 1)


def _fused(f: Field, enc, dir_enc, ri, bf16: bool = False) -> torch.Tensor:
    weights = mlp_weights(f.density_mlp, f.color_mlp)
    rgb, sigma = field_outputs(enc, dir_enc, ri, weights, bf16, MAX_LOG_DENSITY)
    return torch.cat([rgb, sigma[:, None]], 1)


def _seed(n: int) -> torch.Generator:
    return torch.Generator().manual_seed(n)


def _samples(f: Field, n: int, rays: int, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    enc = torch.randn(n, f.encoding.out_dim, generator=g) * 0.3
    dirs = torch.nn.functional.normalize(torch.randn(rays, 3, generator=g), dim=-1)
    ri = torch.sort(torch.randint(0, rays, (n,), generator=g)).values
    return enc, f.dir_encoding(dirs), ri


@needs_kernel
@pytest.mark.parametrize(
    "channels, changes",
    [(3, {}), (1, {}), (3, {"hidden": 32}), (3, {"hidden": 48, "geo_features": 15}),
     (3, {"levels": 5, "features": 3})],
)  # fmt: skip
def test_fused_outputs_and_gradients_match_the_torch_layers(channels, changes):
    f = _field(channels, **changes)
    assert usable(f.density_mlp, f.color_mlp, "auto")
    weights = [m.weight for m in (*f.density_mlp, *f.color_mlp) if isinstance(m, torch.nn.Linear)]
    for n in (0, 1, 33, 1000):  # empty, a partial tile, several tiles
        enc, dir_enc, ri = _samples(f, n, rays=max(n // 7, 1))
        e1, e2 = enc.clone().requires_grad_(), enc.clone().requires_grad_()
        want = _torch_outputs(f, e1, dir_enc, ri)
        got = _fused(f, e2, dir_enc, ri)
        assert got.shape == (n, 1 + channels)
        assert torch.allclose(got, want, rtol=1e-5, atol=1e-5)
        if n == 0:
            continue
        g = torch.randn(want.shape, generator=torch.Generator().manual_seed(n))
        grads_want = torch.autograd.grad(want, [e1, *weights], g)
        grads_got = torch.autograd.grad(got, [e2, *weights], g)
        for a, b in zip(grads_want, grads_got, strict=True):
            assert a.shape == b.shape
            assert torch.allclose(b, a, rtol=1e-4, atol=1e-4 * float(a.abs().max()))


def _bf16(x: torch.Tensor) -> torch.Tensor:
    return x.to(torch.bfloat16).float()


class _RoundedLinear(torch.autograd.Function):
    """A bias-free layer whose every product rounds its two inputs to bf16 and sums in float32,
    forward and backward: what the kernel's AMX products compute."""

    @staticmethod
    def forward(ctx, x, w):  # noqa: D102
        ctx.save_for_backward(x, w)
        return _bf16(x) @ _bf16(w).T

    @staticmethod
    def backward(ctx, g):  # noqa: D102
        x, w = ctx.saved_tensors
        return _bf16(g) @ _bf16(w), _bf16(g).T @ _bf16(x)


def _rounded_outputs(f: Field, enc, dir_enc, ri):
    def run(mlp, x):
        for m in mlp:
            x = torch.relu(x) if isinstance(m, torch.nn.ReLU) else _RoundedLinear.apply(x, m.weight)
        return x

    h = run(f.density_mlp, enc)
    return _activated(h, run(f.color_mlp, torch.cat([h, dir_enc[ri]], -1)))


@pytest.mark.skipif(not amx(), reason="bf16 products need AMX-BF16 tiles (Intel Xeon 4th gen+)")
@pytest.mark.parametrize(
    "channels, changes", [(3, {}), (1, {}), (3, {"hidden": 32, "geo_features": 15})]
)
def test_bf16_products_are_the_rounded_products_summed_in_float32(channels, changes):
    f = _field(channels, **changes)
    weights = [m.weight for m in (*f.density_mlp, *f.color_mlp) if isinstance(m, torch.nn.Linear)]
    for n in (1, 33, 1000):
        enc, dir_enc, ri = _samples(f, n, rays=max(n // 7, 1))
        e1, e2, e3 = (enc.clone().requires_grad_() for _ in range(3))
        want = _rounded_outputs(f, e1, dir_enc, ri)
        got = _fused(f, e2, dir_enc, ri, bf16=True)
        exact = _fused(f, e3, dir_enc, ri)
        # float32 sums in another order may round an activation to the next bf16 (2^-8 apart)
        top = float(want.detach().abs().max())
        assert torch.allclose(got, want, rtol=1e-3, atol=2e-3 * top)
        assert not torch.allclose(got, exact, rtol=1e-5, atol=1e-5)  # the products did round
        assert torch.allclose(got, exact, rtol=0.05, atol=0.05 * top)
        g = torch.randn(want.shape, generator=torch.Generator().manual_seed(n))
        grads_want = torch.autograd.grad(want, [e1, *weights], g)
        grads_got = torch.autograd.grad(got, [e2, *weights], g)
        for a, b in zip(grads_want, grads_got, strict=True):
            assert torch.allclose(b, a, rtol=1e-3, atol=5e-3 * float(a.abs().max()))


@needs_kernel
def test_field_colour_and_density_of_samples_follow_the_torch_path():
    fused, plain = _field(), _field()
    plain._fused_mlp = False  # the torch layers
    pts = torch.rand(500, 3) * 2 - 1
    _, dir_enc, ri = _samples(fused, 500, rays=60)
    c1, s1 = fused.color_sigma(fused.unit(pts), dir_enc, ri)
    c2, s2 = plain.color_sigma(plain.unit(pts), dir_enc, ri)
    assert fused._fused_mlp and torch.allclose(c1, c2, atol=1e-6)
    assert torch.allclose(s1, s2, rtol=1e-5)
    (c1.sum() + s1.sum()).backward()
    (c2.sum() + s2.sum()).backward()
    for a, b in zip(fused.parameters(), plain.parameters(), strict=True):
        assert torch.allclose(a.grad, b.grad, rtol=1e-4, atol=1e-4 * float(b.grad.abs().max()))


@needs_kernel
def test_huge_and_zero_weights_stay_finite():
    f, plain = _field(), _field()
    plain._fused_mlp = False  # the torch layers
    enc, dir_enc, ri = _samples(f, 64, rays=8)
    for m in (f, plain):
        with torch.no_grad():  # logits of ~1e3: the clamp and the sigmoid saturate
            m.encoding.table.copy_(torch.randn(m.encoding.table.shape, generator=_seed(5)))
            m.density_mlp[-1].weight.mul_(1e3)
            m.color_mlp[-1].weight.mul_(1e3)
    pts = torch.rand(64, 3) * 2 - 1
    c, s = f.color_sigma(f.unit(pts), dir_enc, ri)
    assert torch.isfinite(c).all() and torch.isfinite(s).all() and (s >= 0).all()
    lo, hi = float(s.detach().min()), float(s.detach().max())
    assert (lo, hi) == pytest.approx(math.exp(MAX_LOG_DENSITY) ** np.array([-1, 1]), rel=1e-5)
    c2, s2 = plain.color_sigma(plain.unit(pts), dir_enc, ri)
    assert torch.allclose(c, c2, atol=1e-6) and torch.allclose(s, s2, rtol=1e-5)
    (c.sum() + s.sum()).backward()
    (c2.sum() + s2.sum()).backward()  # no gradient through a clamped logit, on both paths
    for a, b in zip(f.parameters(), plain.parameters(), strict=True):
        assert torch.isfinite(a.grad).all()
        assert torch.allclose(a.grad, b.grad, rtol=1e-4, atol=1e-4 * float(b.grad.abs().max()))
    with torch.no_grad():
        for p in f.parameters():
            p.zero_()
    c, s = f.color_sigma(f.unit(pts), dir_enc, ri)
    assert torch.equal(c, torch.full_like(c, 0.5)) and torch.equal(s, torch.ones_like(s))


def test_other_shapes_and_precisions_use_the_torch_layers():
    assert not usable(_field(density_layers=2).density_mlp, _field().color_mlp, "auto")
    assert not usable(_field().density_mlp, _field(color_layers=1).color_mlp, "auto")
    assert not usable(_field(hidden=40).density_mlp, _field(hidden=40).color_mlp, "auto")
    assert not usable(_field().density_mlp, _field().color_mlp, "torch")
    for changes, fused in (({"precision": "fp16"}, False), ({"mlp_dtype": "bf16"}, amx())):
        f = _field(**changes)
        _, dir_enc, ri = _samples(f, 10, rays=2)
        f.color_sigma(torch.rand(10, 3), dir_enc, ri)
        assert f.prepare_kernels() is fused
