"""The radiance field: activations, SH encoding, automatic n_max, low precision."""

import math

import numpy as np
import pytest
import torch

from dronecap.nerf.backend import kernel
from dronecap.nerf.config import preset
from dronecap.nerf.field import Field, trunc_exp
from dronecap.nerf.mlp_kernel import amx
from dronecap.nerf.resolve import auto_n_max
from dronecap.nerf.sh import sh_encode

AABB = np.array([[-1.0, -1, -1], [1, 1, 1]])


def test_trunc_exp_never_overflows_and_keeps_gradients():
    x = torch.tensor([-1e9, -3.0, 0.0, 3.0, 1e9], requires_grad=True)
    y = trunc_exp(x)
    y.sum().backward()
    assert torch.isfinite(y).all() and torch.isfinite(x.grad).all()
    assert math.isclose(y[3].item(), math.exp(3.0), rel_tol=1e-6)
    # e^15 = 3.3e6 would overflow float16: the field applies it in float32 (see below)


def test_sh_values_on_z_axis():
    sh = sh_encode(torch.tensor([[0.0, 0.0, 1.0]]))[0]
    assert sh.shape == (16,)
    assert math.isclose(sh[0].item(), 0.28209479, rel_tol=1e-6)
    assert math.isclose(sh[2].item(), 0.48860251, rel_tol=1e-6)  # Y_1^0 = c z
    assert math.isclose(sh[6].item(), 0.94617470 - 0.31539157, rel_tol=1e-6)
    assert math.isclose(sh[12].item(), 0.37317633 * 2, rel_tol=1e-6)  # z (5 z^2 - 3)
    assert torch.count_nonzero(sh).item() == 4  # only m = 0 terms survive on the axis


def test_sh_is_orthonormal_on_the_sphere():
    g = torch.Generator().manual_seed(0)
    d = torch.randn(200_000, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True)
    y = sh_encode(d)
    gram = 4 * math.pi * (y.T @ y) / len(d)
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=0.02)


def test_auto_n_max_by_hand():
    # extent 2, near 4, focal 200 px: a pixel covers 4/200 = 0.02 units -> 100 cells
    assert auto_n_max(AABB, 4.0, 200.0) == 100
    assert auto_n_max(AABB, 1e3, 1.0) == 16  # never below the coarsest useful level


def test_field_shapes_channels_and_extreme_points():
    cfg = preset("test")
    for c in (1, 3):
        f = Field(cfg.replace(n_max=64), c, AABB, backend="torch")
        pts = torch.tensor([[-1.0, -1, -1], [1, 1, 1], [5, -7, 0.2], [0, 0, 0]], requires_grad=True)
        d = torch.nn.functional.normalize(torch.randn(4, 3), dim=-1)
        col, sig = f(pts, d)
        assert col.shape == (4, c) and sig.shape == (4,)
        (col.sum() + sig.sum()).backward()
        assert torch.isfinite(col).all() and torch.isfinite(sig).all()
        assert all(torch.isfinite(p.grad).all() for p in f.parameters())


def test_fp16_field_rounds_activations():
    cfg = preset("test").replace(precision="fp16")
    f = Field(cfg.replace(n_max=64), 3, AABB, backend="torch")
    with torch.no_grad():
        f.encoding.table.normal_(0, 1)
    _, geo = f.geometry(torch.rand(32, 3) * 2 - 1)
    assert torch.equal(geo, geo.half().float())


def _twins(n_max: int = 64, **changes) -> tuple[Field, Field]:
    """Two fields with the same weights, multiplying in fp32 and in bf16."""
    cfg = preset("test").replace(n_max=n_max, **changes)
    exact = Field(cfg.replace(mlp_dtype="fp32"), 3, AABB, backend="torch")
    fast = Field(cfg.replace(mlp_dtype="bf16"), 3, AABB, backend="torch")
    with torch.no_grad():
        exact.encoding.table.normal_(0, 0.5)
    fast.load_state_dict(exact.state_dict())
    return exact, fast


def test_bf16_products_follow_fp32_in_values_and_gradients():
    exact, fast = _twins()
    g = torch.Generator().manual_seed(1)
    pts = torch.rand(1000, 3, generator=g) * 2 - 1  # not a multiple of the row quantum
    dirs = torch.nn.functional.normalize(torch.randn(1000, 3, generator=g), dim=-1)
    outs = []
    for f in (exact, fast):
        col, sig = f(pts, dirs)
        assert col.dtype == sig.dtype == torch.float32 and col.shape == (1000, 3)
        (col.sum() + sig.log().sum()).backward()
        outs.append((col.detach(), sig.detach().log()))
    assert fast.product_dtype == torch.bfloat16
    (c0, s0), (c1, s1) = outs
    assert (c1 - c0).abs().max() < 0.02 and (s1 - s0).abs().max() < 0.1
    assert not torch.equal(c0, c1)  # the bf16 path really multiplied in bf16
    for p0, p1 in zip(exact.parameters(), fast.parameters(), strict=True):
        assert p1.grad.dtype == torch.float32
        cos = torch.nn.functional.cosine_similarity(p0.grad.flatten(), p1.grad.flatten(), 0)
        assert cos > 0.99


def test_bf16_rows_do_not_depend_on_the_batch_around_them():
    # zero padding to the row quantum must not leak into real rows or their gradients
    _, fast = _twins()
    pts = torch.rand(300, 3) * 2 - 1
    alone = fast.density(pts[:7])
    together = fast.density(pts)[:7]
    assert torch.equal(alone, together)


def test_bf16_products_keep_huge_and_zero_densities_finite():
    _, fast = _twins()
    with torch.no_grad():
        fast.density_mlp[-1].weight.mul_(1e4)  # log-densities far past the clamp
    sig = fast.density(torch.rand(50, 3) * 2 - 1)
    assert torch.isfinite(sig).all() and (sig >= 0).all()
    with torch.no_grad():
        fast.density_mlp[-1].weight.zero_()
    assert torch.equal(fast.density(torch.rand(5, 3)), torch.ones(5))  # exp(0)


def _hashgrid_amx() -> bool:
    k = kernel("hashgrid", "auto")
    return amx() and k is not None and bool(k.amx())


@pytest.mark.skipif(
    not _hashgrid_amx(), reason="bf16 products need AMX-BF16 tiles (Intel Xeon 4th gen+)"
)
def test_fused_density_query_in_bf16_products_follows_the_bf16_layers():
    # under bf16 products the fused query's hidden layer multiplies on the AMX tiles
    g = torch.Generator().manual_seed(4)
    cfg = preset("scene-sized").replace(n_max=223, mlp_dtype="bf16")
    f = Field(cfg, 3, AABB)
    with torch.no_grad():
        f.encoding.table.uniform_(-1, 1, generator=g)
        f.density_mlp[-1].weight.mul_(4)  # log-densities of a few units
        pts = torch.rand(1003, 3, generator=g) * 2 - 1
        sig, enc = f.density_and_encoding(pts)
        want = f.density_from_encoding(enc)  # torch's bf16 layers (bf16 activations)
        f.product_dtype = torch.float32
        exact, _ = f.density_and_encoding(pts)
    assert torch.allclose(sig.log(), want.log(), rtol=2**-6, atol=2**-6)
    assert not torch.equal(sig, exact) and torch.allclose(sig.log(), exact.log(), atol=0.05)


def test_density_alone_is_the_geometry_pass_density_in_every_product_dtype():
    # the pre-pass and grid updates compute only the density column of the last layer
    pts = torch.rand(700, 3) * 2 - 1
    for f in (*_twins(), *_twins(precision="fp16")[:1]):
        sig, geo = f.geometry(pts)
        assert geo.shape[1] > 1
        # a one-column product may round differently from the 16-column one: by a few float32
        # ulps, or to the neighbouring bf16 value of the raw density (2^-8 relative) in bf16
        if f.product_dtype == torch.float32:
            assert torch.allclose(f.density(pts), sig, rtol=1e-5, atol=0)
        else:
            assert torch.allclose(f.density(pts).log(), sig.log(), rtol=2**-7, atol=2**-7)
        assert torch.equal(f.density_from_encoding(f.encode(pts)), f.density(pts))


def test_fused_density_query_matches_encoding_then_mlp():
    # compaction's pre-pass and the occupancy updates: encoding and density MLP in one C++ pass
    # (4-point AVX path at width 64, the scalar loop at other widths and for the tail rows)
    g = torch.Generator().manual_seed(3)
    for hidden, backend in ((64, "auto"), (32, "auto"), (48, "auto"), (64, "torch")):
        # fp32 products: the torch layers then multiply as the fused query does
        cfg = preset("scene-sized").replace(n_max=223, hidden=hidden, mlp_dtype="fp32")
        f = Field(cfg, 3, AABB, backend=backend)
        with torch.no_grad():
            f.encoding.table.uniform_(-1, 1, generator=g)
        for n in (0, 1, 17, 1003):
            pts = torch.rand(n, 3, generator=g) * 2.4 - 1.2  # some outside the box
            if n > 5:
                pts[5] = float("nan")
            with torch.no_grad():
                want_enc = f.encode(pts)
                want = f.density_from_encoding(want_enc)
                sig, enc = f.density_and_encoding(pts)
                alone = f.density(pts)  # no autograd: the query without the encoding
            assert sig.shape == (n,) and enc.shape == (n, f.encoding.out_dim)
            assert torch.equal(enc, want_enc)
            assert torch.allclose(sig, want, rtol=1e-5, atol=1e-7)
            assert torch.equal(alone, sig)
    with torch.no_grad():  # log-densities far past the clamp stay finite
        f = Field(preset("scene-sized").replace(n_max=223), 3, AABB)
        f.density_mlp[-1].weight.mul_(1e6)
        f.encoding.table.uniform_(-1, 1, generator=g)
        sig = f.density(torch.rand(64, 3, generator=g) * 2 - 1)
    assert torch.isfinite(sig).all() and (sig >= 0).all() and sig.max() > 1e5
