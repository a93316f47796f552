"""The far field (nerf.far_field): what a ray sees past the box, learned per direction; its
numerics, resolve choice, checkpoints, federated weights, GAP9 price, and that it learns a
background that lies at infinity."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from dronecap.datasets.format import Dataset
from dronecap.gap9 import arch
from dronecap.gap9.model import cost_report
from dronecap.nerf.config import preset, problems
from dronecap.nerf.far_field import FarField, equirect_coords
from dronecap.nerf.render import render_rays
from dronecap.nerf.resolve import choice_lines, resolve
from dronecap.nerf.trainer import Trainer
from dronecap.nerf.volrend import render_packed

KINDS = ("sh", "grid")


def _cfg(far: str = "sh", **kw):
    return preset("test").replace(
        batch_samples=4096, grid_res=16, march_steps=64, lr_schedule="constant", far_field=far,
        learn_exposure="off", learn_vignetting="off", **kw,
    )  # fmt: skip


def _unit(n: int, seed: int = 0) -> torch.Tensor:
    d = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed))
    return d / d.norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("kind", KINDS)
def test_starts_grey_and_stays_in_range_for_any_parameters(kind):
    far = FarField(kind, 3)
    d = _unit(500)
    torch.testing.assert_close(far(d), torch.full((500, 3), 0.5))
    assert far(d[:0]).shape == (0, 3)
    with torch.no_grad():
        for p in far.parameters():
            p.copy_(torch.randn(p.shape) * 1e30)  # huge logits: the sigmoid saturates
    out = far(d)
    assert torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
    half = far(d.half())  # fp16 directions (GAP9 storage) are taken in fp32
    assert half.dtype == torch.float32 and torch.isfinite(half).all()


def test_grid_wraps_around_the_azimuth_and_covers_the_poles():
    far = FarField("grid", 1)
    with torch.no_grad():
        far.logits.copy_(torch.randn(far.logits.shape))
    eps = 1e-6
    across = torch.tensor([[-1.0, eps, 0.3], [-1.0, -eps, 0.3]])
    across = across / across.norm(dim=-1, keepdim=True)
    a, b = far(across)
    torch.testing.assert_close(a, b, atol=1e-4, rtol=0)  # no seam at azimuth +-pi
    poles = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    az, el = equirect_coords(poles)
    assert el.tolist() == [-1.0, 1.0] and torch.isfinite(far(poles)).all()


def test_gradients_reach_the_far_field():
    far = FarField("grid", 2)
    far(_unit(64)).sum().backward()
    assert far.logits.grad.abs().sum() > 0


def test_composite_is_box_plus_exit_transmittance_times_far():
    """C = C_box + T_exit far(d): empty box -> far(d), opaque box -> the box colour."""
    far = FarField("sh", 1)
    with torch.no_grad():
        far.coeffs.copy_(torch.randn(far.coeffs.shape))
    d = _unit(2)
    behind = far(d)
    t0 = torch.tensor([0.0, 0.1, 0.0, 0.1])
    t1 = t0 + 0.1
    ri = torch.tensor([0, 0, 1, 1])
    box = torch.full((4, 1), 0.25)
    for sigma, want in [(0.0, behind), (1e30, torch.full((2, 1), 0.25))]:
        sig = torch.full((4,), sigma)
        color = render_packed(t0, t1, ri, 2, lambda *_: (box, sig), behind).color  # noqa: B023
        torch.testing.assert_close(color, want)


def test_rays_that_miss_the_box_render_the_far_field(cube_rgb):
    tr = Trainer(_cfg("grid"), dataclasses.replace(cube_rgb, alpha=None))
    with torch.no_grad():
        tr.field.far.logits.copy_(torch.randn(tr.field.far.logits.shape))
    origins = torch.tensor([[5.0, 5.0, 5.0]]).expand(16, 3)
    dirs = torch.cat([_unit(32)[_unit(32)[:, 0] > 0][:16].abs()], 0)  # away from the box
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    got = render_rays(tr.volume(), origins, dirs, torch.zeros(3))
    torch.testing.assert_close(got, tr.field.far(dirs))


@pytest.mark.parametrize("kind", KINDS)
def test_the_far_field_starts_at_far_init(cube_rgb, kind):
    """``far_init`` is the colour of every direction before training; (0, 1) only."""
    tr = Trainer(_cfg(kind, far_init=0.1), dataclasses.replace(cube_rgb, alpha=None))
    origins = torch.tensor([[5.0, 5.0, 5.0]]).expand(8, 3)
    dirs = _unit(8).abs()  # away from the box: the far field alone
    got = render_rays(tr.volume(), origins, dirs / dirs.norm(dim=-1, keepdim=True), torch.zeros(3))
    torch.testing.assert_close(got, torch.full((8, 3), 0.1))
    for bad in (0.0, 1.0, float("nan")):
        assert any("far_init" in line for line in problems(_cfg(kind, far_init=bad)))


def test_resolver_chooses_from_the_data(cube_rgb):
    with_alpha = resolve(_cfg("auto"), cube_rgb)
    assert with_alpha.config.far_field == "none"
    assert "alpha" in with_alpha.reasons["far_field"]
    footage = resolve(_cfg("auto"), dataclasses.replace(cube_rgb, alpha=None, background=None))
    assert footage.config.far_field in KINDS
    assert "camera footage" in footage.reasons["far_field"]
    assert any(line.startswith("far_field = ") for line in choice_lines(footage, False))
    declared = resolve(
        _cfg("auto"), dataclasses.replace(cube_rgb, alpha=None, background=(0.6,) * 3)
    )
    assert declared.config.far_field == "none" and "declares" in declared.reasons["far_field"]
    forced = resolve(_cfg("none"), dataclasses.replace(cube_rgb, alpha=None, background=None))
    assert forced.config.far_field == "none"
    assert forced.reasons["far_field"] == "set by the configuration"
    assert problems(_cfg("sky"))  # an unknown kind is refused


def test_old_checkpoints_load_without_a_far_field(cube_rgb, tmp_path):
    data = dataclasses.replace(cube_rgb, alpha=None)
    tr = Trainer(_cfg("none"), data)
    tr.train(2)
    tr.save(tmp_path / "ck.pt")
    ck = torch.load(tmp_path / "ck.pt", weights_only=False)
    del ck["resolved"]["config"]["far_field"]  # written before the far field existed
    torch.save(ck, tmp_path / "old.pt")
    old = Trainer.load(tmp_path / "old.pt", data)
    assert old.cfg.far_field == "none" and old.field.far is None
    assert not old.train(2)[-1]["skipped"]


@pytest.mark.parametrize("kind", KINDS)
def test_checkpoint_and_federated_weights_carry_the_far_field(cube_rgb, tmp_path, kind):
    data = dataclasses.replace(cube_rgb, alpha=None)
    tr = Trainer(_cfg(kind), data)
    tr.train(5)
    tr.save(tmp_path / "ck.pt")
    back = Trainer.load(tmp_path / "ck.pt", data)
    for p, q in zip(tr.field.far.parameters(), back.field.far.parameters(), strict=True):
        torch.testing.assert_close(p, q, rtol=0, atol=0)
        assert p.abs().sum() > 0  # it trained
    w = tr.model_weights()  # what FedAvg averages: the far field travels with the model
    assert any(k.startswith("far.") for k in w)
    other = Trainer(_cfg(kind, seed=1), data)
    other.load_model_weights(w)
    torch.testing.assert_close(other.field.far(_unit(8)), tr.field.far(_unit(8)))
    assert back.parameter_count() == tr.field.parameter_count()


def test_gap9_prices_the_far_field():
    base = preset("tiny-dronerf").replace(channels=1)
    assert arch.counts(base.replace(far_field="none")).far_field_params == 0
    assert arch.counts(base.replace(far_field="sh")).far_field_params == 16
    assert arch.counts(base.replace(far_field="grid")).far_field_params == 512
    off, on = cost_report(base.replace(far_field="none")), cost_report(base.replace(far_field="sh"))
    assert on["counts"]["params"] == off["counts"]["params"] + 16
    assert on["ops"]["step"]["loss"] > off["ops"]["step"]["loss"]
    assert on["link"] != off["link"]  # the far field travels in federated updates
    assert (
        0
        < on["ops"]["step"]["total"] - off["ops"]["step"]["total"]
        < 1e-3 * off["ops"]["step"]["total"]
    )


def _sky(ds: Dataset) -> Dataset:
    """``ds`` with nothing in the box: every pixel the colour of its ray's direction (a
    gradient at infinity), no alpha."""
    k = ds.intrinsics
    v, u = np.mgrid[0 : k.height, 0 : k.width]
    images = []
    for c2w in ds.poses:
        d = np.stack([(u + 0.5 - k.cx) / k.fx, (v + 0.5 - k.cy) / k.fy, np.ones(u.shape)], -1)
        d = d @ c2w[:3, :3].T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        rgb = np.stack([0.5 + 0.4 * d[..., 2], 0.5 + 0.4 * d[..., 0], 0.3 + 0.2 * d[..., 1]], -1)
        images.append(np.round(rgb * 255).astype(np.uint8))
    return dataclasses.replace(ds, images=np.stack(images), alpha=None, background=None)


@pytest.mark.parametrize("kind", KINDS)
def test_a_background_at_infinity_is_learned(make_cube, kind):
    """Frames that see only a direction-dependent gradient (nothing in the box): with a far
    field the test PSNR rises well above the fixed-background run's."""
    data = _sky(make_cube(n=16, size=24, fov=1.4))
    scores = {}
    for far in ("none", kind):
        tr = Trainer(_cfg(far, lr=2e-2), data)
        tr.train(60)
        scores[far] = tr.evaluate(data)["psnr"]
    assert math.isfinite(scores["none"])
    assert scores[kind] > scores["none"] + 8, scores
    assert scores[kind] > 18, scores  # 60 steps: ~21.8 dB (sh) against 8.6 dB


@pytest.mark.parametrize("kind", KINDS)
def test_fp16_storage_trains_with_a_far_field(cube_rgb, kind):
    tr = Trainer(
        _cfg(kind, precision="fp16", mlp_dtype="fp32"), dataclasses.replace(cube_rgb, alpha=None)
    )
    assert not any(log["skipped"] for log in tr.train(5))
    assert tr.weights_finite() and torch.isfinite(tr.field.far(_unit(16))).all()


def test_the_geometry_export_carries_the_far_field(tmp_path):
    """far_field.json gives back the model's colour per direction; far_field.png is its map
    (azimuth -180..180 across): a grid bright for y > 0, dark for y < 0 shows so."""
    import cv2

    from dronecap.nerf.far_field import environment_map, far_field_record
    from dronecap.nerf.geometry import FAR_JSON, FAR_PNG, Geometry, write_geometry
    from dronecap.nerf.sh import sh_encode

    pytest.importorskip("open3d")
    sh = FarField("sh", 3)
    with torch.no_grad():
        sh.coeffs.copy_(torch.randn(sh.coeffs.shape, generator=torch.Generator().manual_seed(1)))
    rec = json.loads(json.dumps(far_field_record(sh)))  # what a reader of the file gets
    d = _unit(200)
    back = torch.sigmoid(sh_encode(d, rec["sh_degree"]) @ torch.tensor(rec["parameters"]).t())
    torch.testing.assert_close(back, sh(d))
    grid = FarField("grid", 1)
    with torch.no_grad():
        grid.logits[..., : grid.logits.shape[-1] // 2] = -6.0  # azimuth < 0: y < 0, dark
        grid.logits[..., grid.logits.shape[-1] // 2 :] = 6.0
    tri, up = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.tile([0.0, 0, 1], (3, 1))
    faces, grey = np.array([[0, 1, 2]], np.int32), np.full((3, 3), 0.5)
    geo = Geometry(tri, faces, up, grey, 1.0, far_field_record(grid), environment_map(grid))
    out = write_geometry(geo, tmp_path / "g")
    assert json.loads((out / FAR_JSON).read_text())["kind"] == "grid"
    png = cv2.imread(str(out / FAR_PNG), cv2.IMREAD_UNCHANGED)
    rows = png.shape[0]
    assert png.shape == (rows, 2 * rows)
    assert png[:, rows // 4].max() < 5 and png[:, 3 * rows // 2].min() > 250
