"""A camera per frame: each frame's rays go through its own camera (two drones' cameras)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from dronecap.datasets.format import Dataset
from dronecap.nerf.backend import kernel
from dronecap.nerf.batch import RayBatch, draw_rays
from dronecap.nerf.config import preset
from dronecap.nerf.draws import pixel_draws
from dronecap.nerf.rays import camera_rays, direction_tables, frame_cameras, frame_rays
from dronecap.nerf.trainer import Trainer


def two_camera_cube(make_cube) -> Dataset:
    """Views of the cube alternately through two cameras of different field of view, each
    rendered through its own camera."""
    a, b = make_cube(fov=0.8), make_cube(fov=1.0)
    which = np.arange(a.n) % 2  # 0: camera a, 1: camera b
    pick = lambda x, y: np.where(which.reshape(-1, *[1] * (x.ndim - 1)) == 0, x, y)  # noqa: E731
    ds = dataclasses.replace(
        a,
        images=pick(a.images, b.images),
        alpha=pick(a.alpha, b.alpha),
        drone=which.astype(np.int16),
        drone_names=["a", "b"],
    )
    ds.set_cameras([a.intrinsics, b.intrinsics], which)
    return ds


def test_frame_rays_match_each_cameras_own_rays(make_cube) -> None:
    ds = two_camera_cube(make_cube)
    cams = tuple(ds.cameras)
    g = torch.Generator().manual_seed(0)
    which = torch.tensor([0, 1, 1, 0, 1])
    u, v = torch.randint(24, (5,), generator=g), torch.randint(24, (5,), generator=g)
    c2w = torch.as_tensor(ds.poses[:5])
    o, d = frame_rays(c2w, cams, which, u, v)
    for r in range(5):
        o1, d1 = camera_rays(c2w[r], cams[int(which[r])], u[r : r + 1], v[r : r + 1])
        torch.testing.assert_close(d[r], d1[0])
        torch.testing.assert_close(o[r], o1[0])
    assert not torch.allclose(d, camera_rays(c2w, cams[0], u, v)[1])  # the cameras differ


def test_trainer_casts_every_frames_rays_through_its_own_camera(make_cube) -> None:
    ds = two_camera_cube(make_cube)
    tr = Trainer(preset("test").replace(batch_samples=1024, grid_res=16), ds)
    assert len(tr.cameras) == 2
    batch = tr._draw_rays(512)
    train = np.flatnonzero(ds.split == 0)
    frame = train[batch.frame.cpu().numpy()]
    poses = ds.poses[frame]
    d_cam = np.einsum("nji,nj->ni", poses[:, :3, :3], batch.dirs.cpu().numpy().astype(float))
    for own in (True, False):
        cam = [ds.cameras[int(ds.camera_index[f]) ^ (not own)] for f in frame]
        fx, cx = np.array([k.fx for k in cam]), np.array([k.cx for k in cam])
        u = fx * d_cam[:, 0] / d_cam[:, 2] + cx - 0.5  # an integer column through its own camera
        off = np.abs(u - np.round(u)).max()
        assert off < 1e-3 if own else off > 0.1
    logs = tr.train(5)
    assert len(logs) == 5 and all(np.isfinite(x["loss"]) for x in logs)
    assert np.isfinite(tr.evaluate(ds, np.flatnonzero(ds.split == 2))["psnr"])


@pytest.mark.parametrize("with_alpha", [True, False])
def test_kernel_draws_the_rays_and_targets_of_the_torch_reference(make_cube, with_alpha) -> None:
    if kernel("march", "auto") is None:
        pytest.skip("the C++ marching kernel does not build here")
    ds = two_camera_cube(make_cube)
    cams, index = frame_cameras(ds, np.arange(ds.n))
    alpha = torch.as_tensor(ds.alpha) if with_alpha else None
    args = (torch.as_tensor(ds.images), alpha, torch.as_tensor(ds.poses), cams, index, (0.2,) * 3)
    draws = [
        draw_rays(*args, 8, 700, torch.Generator().manual_seed(3), backend)
        for backend in ("torch", "cpp")
    ]
    for name, want, got in zip(RayBatch._fields, *draws, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6, msg=name)
    with pytest.raises(RuntimeError, match="out of range"):
        frame, zero = torch.tensor([ds.n + 1]), torch.tensor([0])  # a frame beyond the images
        no_alpha, tables = torch.zeros(0, dtype=torch.uint8), direction_tables(cams)
        kernel("march", "cpp").draw(
            args[0], no_alpha, args[2].float(), tables, index, frame, zero, zero,
            torch.zeros(1, 3), 1.0, 1.0, 2.0,
        )  # fmt: skip


def test_pixel_draws_are_uniform_and_follow_the_seed() -> None:
    which, u, v, bg = pixel_draws(12345, 100, 8, 200_000, (120, 160, 3), True)
    frames = which.unique()
    assert len(frames) <= 8 and int(frames.min()) >= 0 and int(frames.max()) < 100
    for draws, size in ((u, 160), (v, 120)):
        counts = torch.bincount(draws, minlength=size).float()
        assert counts.numel() == size and counts.min() > 0.85 * counts.mean()  # ~1250 each
    assert 0.0 <= float(bg.min()) and float(bg.max()) < 1.0 and abs(float(bg.mean()) - 0.5) < 0.01
    again = pixel_draws(12345, 100, 8, 200_000, (120, 160, 3), True)
    other = pixel_draws(12346, 100, 8, 200_000, (120, 160, 3), True)
    assert all(torch.equal(a, b) for a, b in zip((which, u, v, bg), again, strict=True))
    assert not torch.equal(u, other[1])
    assert pixel_draws(1, 100, 8, 10, (120, 160, 3), False)[3] is None
