"""The training pass as one autograd node: the separate Functions' colours and gradients."""

import pytest
import torch

from dronecap.nerf import fused_pass
from dronecap.nerf.backend import kernel
from dronecap.nerf.compaction import visible
from dronecap.nerf.config import preset
from dronecap.nerf.mlp_kernel import amx
from dronecap.nerf.trainer import Trainer
from dronecap.nerf.volrend import composite

pytestmark = pytest.mark.skipif(
    any(kernel(k, "auto") is None for k in ("hashgrid", "mlp", "march")),
    reason="the C++ kernels are unavailable (no compiler)",
)


def _batch(tr: Trainer):
    """A step's rays and their samples with the pre-pass's encodings."""
    rays, s = tr._march_batch()
    return rays, visible(s, rays.origins, rays.dirs, tr.field, 1e-4)


def _colour_and_grads(tr: Trainer, rays, s, fused: bool):
    field = tr.field
    for p in field.parameters():
        p.grad = None
    dir_enc = field.dir_encoding(rays.dirs)
    behind = field.behind(rays.dirs, rays.bg)
    n = rays.origins.shape[0]
    if fused:
        color = fused_pass.colors(field, s, dir_enc, behind)
    else:

        def color_sigma(t0, t1, ri):
            return field.color_sigma(s.unit, dir_enc, ri, s.encoded)

        color = composite(s.t_starts, s.t_ends, s.ray_indices, n, color_sigma, behind)
    weights = torch.linspace(-1.0, 2.0, color.numel()).reshape(color.shape)  # any loss
    (color * weights).sum().backward()
    grads = {k: p.grad.clone() for k, p in field.named_parameters() if p.grad is not None}
    return color.detach(), grads


@pytest.mark.parametrize("far_field", ["none", "sh"])
@pytest.mark.parametrize("mlp_dtype", ["fp32", "bf16"])
def test_the_fused_pass_gives_the_separate_functions_values_bit_for_bit(
    cube_rgb, far_field, mlp_dtype
):
    if mlp_dtype == "bf16" and not amx():
        pytest.skip("bf16 products need AMX-BF16 tiles")
    cfg = preset("test").replace(batch_samples=2048, grid_res=16, far_field=far_field,
                                 mlp_dtype=mlp_dtype)  # fmt: skip
    tr = Trainer(cfg, cube_rgb)
    tr.train(20)
    rays, s = _batch(tr)
    assert s.n > 200 and s.encoded is not None
    a, ga = _colour_and_grads(tr, rays, s, fused=True)
    b, gb = _colour_and_grads(tr, rays, s, fused=False)
    assert torch.equal(a, b)
    assert ga.keys() == gb.keys() and "encoding.table" in ga
    assert (far_field == "sh") == any(k.startswith("far") for k in ga)  # reaches the far field
    for k in ga:
        assert torch.equal(ga[k], gb[k]), k
    assert all(g.abs().sum() > 0 for g in ga.values())


def test_the_fused_pass_steps_aside_where_a_part_has_no_kernel(cube_rgb):
    tr = Trainer(preset("test").replace(batch_samples=1024, grid_res=16), cube_rgb)
    rays, s = _batch(tr)
    field = tr.field
    dir_enc, behind = field.dir_encoding(rays.dirs), field.behind(rays.dirs, rays.bg)
    assert fused_pass.colors(field, s, dir_enc, behind) is not None
    bare = type(s)(s.ray_indices, s.t_starts, s.t_ends, s.counts)  # no pre-pass encodings
    assert fused_pass.colors(field, bare, dir_enc, behind) is None
    torch_field = Trainer(preset("test").replace(batch_samples=1024, grid_res=16), cube_rgb,
                          backend="torch").field  # fmt: skip
    assert fused_pass.colors(torch_field, s, dir_enc, behind) is None
