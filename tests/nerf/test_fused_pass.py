"""A training tile without an autograd graph through the field: autograd's loss and gradients."""

import pytest
import torch

from dronecap.nerf import fused_pass
from dronecap.nerf.backend import kernel
from dronecap.nerf.batch import RayBatch
from dronecap.nerf.compaction import visible
from dronecap.nerf.config import preset
from dronecap.nerf.mlp_kernel import amx
from dronecap.nerf.train_pass import autograd_tile
from dronecap.nerf.trainer import Trainer

pytestmark = pytest.mark.skipif(
    any(kernel(k, "auto") is None for k in ("hashgrid", "mlp", "march")),
    reason="the C++ kernels are unavailable (no compiler)",
)


def _batch(tr: Trainer):
    """A step's rays and their samples with the pre-pass's encodings."""
    rays, s = tr._march_batch()
    return rays, visible(s, rays.origins, rays.dirs, tr.field, 1e-4)


def _loss_and_grads(tr: Trainer, rays, s, fused: bool):
    params = [*tr.field.parameters(), *tr.photometric.parameters()]
    for p in params:
        p.grad = None
    n = rays.origins.shape[0] + 7  # the batch's count, not the tile's, scales the loss
    if fused:
        loss = fused_pass.train_tile(tr.field, tr.photometric, rays, s, n)
    else:
        loss = autograd_tile(tr.field, tr.photometric, rays, s, n, 0.0, tr.aabb)
    return loss, [None if p.grad is None else p.grad.clone() for p in params]


@pytest.mark.parametrize(
    "changes",
    [
        dict(mlp_dtype="fp32"),
        dict(mlp_dtype="bf16"),
        dict(mlp_dtype="fp32", far_field="sh"),  # the far field's gradient
        dict(mlp_dtype="fp32", learn_exposure="on", learn_vignetting="on"),
    ],
)
def test_the_fused_tile_gives_autograds_loss_and_gradients_bit_for_bit(cube_rgb, changes):
    if changes["mlp_dtype"] == "bf16" and not amx():
        pytest.skip("bf16 products need AMX-BF16 tiles")
    cfg = preset("test").replace(batch_samples=2048, grid_res=16, **changes)
    tr = Trainer(cfg, cube_rgb)
    tr.train(20)
    rays, s = _batch(tr)
    assert s.n > 200 and s.encoded is not None
    a, ga = _loss_and_grads(tr, rays, s, fused=True)
    b, gb = _loss_and_grads(tr, rays, s, fused=False)
    assert a == b and a > 0
    assert [g is None for g in ga] == [g is None for g in gb]
    for x, y in zip(ga, gb, strict=True):
        assert x is None or torch.equal(x, y)
    assert sum(g is not None for g in ga) >= 6  # table and five weights, at least
    if "far_field" in changes or "learn_exposure" in changes:  # theirs too
        assert sum(g is not None for g in ga) > 6


def test_the_fused_tile_adds_to_gradients_already_there(cube_rgb):
    tr = Trainer(preset("test").replace(batch_samples=2048, grid_res=16), cube_rgb)
    tr.train(20)
    rays, s = _batch(tr)
    _, once = _loss_and_grads(tr, rays, s, fused=True)
    fused_pass.train_tile(tr.field, tr.photometric, rays, s, rays.origins.shape[0] + 7)
    twice = [p.grad for p in tr.field.parameters()]
    for x, y in zip(once, twice, strict=True):
        if x is not None:
            torch.testing.assert_close(y, 2 * x)


def test_the_fused_tile_steps_aside_where_a_part_has_no_kernel(cube_rgb):
    tr = Trainer(preset("test").replace(batch_samples=1024, grid_res=16), cube_rgb)
    rays, s = _batch(tr)
    bare = type(s)(s.ray_indices, s.t_starts, s.t_ends, s.counts)  # no pre-pass encodings
    assert fused_pass.train_tile(tr.field, tr.photometric, rays, bare, 100) is None
    plain = Trainer(preset("test").replace(batch_samples=1024, grid_res=16), cube_rgb,
                    backend="torch")  # fmt: skip
    assert fused_pass.train_tile(plain.field, plain.photometric, rays, s, 100) is None
    assert all(p.grad is None for p in [*tr.field.parameters(), *plain.field.parameters()])
    assert isinstance(rays, RayBatch)
