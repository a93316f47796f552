"""The visual hull from alpha masks (nerf/carve.py) and the occupancy grid restricted to it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from dronecap.nerf import carve, occupancy
from dronecap.nerf.config import preset
from dronecap.nerf.rays import frame_cameras
from dronecap.nerf.trainer import Trainer

RES = 16  # cells per axis over the cube scenes' AABB [-1, 1]^3: 0.125 per cell


def _hull(ds) -> torch.Tensor:
    idx = np.arange(len(ds.poses))
    cameras, index = frame_cameras(ds, idx)
    aabb = torch.as_tensor(ds.aabb, dtype=torch.float32)
    return carve.hull(
        RES, aabb, torch.as_tensor(ds.alpha), torch.as_tensor(ds.poses), cameras, index
    )


@pytest.mark.parametrize(("model", "distortion"), [("PINHOLE", ()), ("SIMPLE_RADIAL", (-0.2,))])
def test_hull_keeps_the_object_and_carves_the_empty_corners(make_cube, model, distortion):
    ds = make_cube(n=12, size=48, model=model, distortion=distortion)
    kept = _hull(ds)
    centres = carve.cell_centres(RES, torch.as_tensor(ds.aabb, dtype=torch.float32))
    inside = (centres.abs() <= 0.5).all(1)  # the cube [-0.5, 0.5]^3
    assert kept[inside].all()  # never carves what the images show
    # the cameras circle above the cube: cells below its bottom face, off its vertical
    # silhouette, are background in every view that sees them
    below = (centres[:, 2] < -0.7) & (centres[:, :2].abs().max(1).values > 0.7)
    assert not kept[below].any()
    assert 0.05 < kept.float().mean() < 0.5


def test_update_never_occupies_a_carved_cell():
    cfg = occupancy.GridConfig(res=4, warmup=2)
    allowed = torch.zeros(64, dtype=torch.bool)
    allowed[:10] = True
    state = occupancy.restrict(occupancy.init_state(cfg), allowed)
    assert state.occupied.sum() == 10
    aabb = torch.tensor([[0.0, 0, 0], [1, 1, 1]])
    gen = torch.Generator().manual_seed(0)
    dense = lambda p: torch.full((len(p),), 100.0)  # noqa: E731  (dense everywhere)
    for step in (0, 5):  # a warm-up update (all allowed cells) and a later one
        state = occupancy.update(cfg, state, step, dense, aabb, 0.1, gen)
        assert state.occupied[:10].all() and not state.occupied[10:].any()
        assert state.density[10:].eq(0).all()  # carved cells are never even queried


def test_trainer_carves_datasets_with_alpha_only(make_cube):
    cfg = preset("test")
    ds = make_cube(n=8, size=24)
    tr = Trainer(cfg, ds)
    assert tr.grid.allowed is not None and not tr.grid.allowed.all()
    assert torch.equal(tr.grid.occupied, tr.grid.allowed)  # the fresh grid is the hull
    tr.train(3)
    assert not (tr.grid.occupied & ~tr.grid.allowed).any()
    before = tr.grid.allowed.clone()
    tr.load_grid_state({k: np.ones_like(v) for k, v in tr.grid_state().items()})
    assert torch.equal(tr.grid.occupied, before)  # a loaded grid stays within the hull
    assert Trainer(cfg.replace(grid_carve=False), ds).grid.allowed is None
    assert Trainer(cfg, dataclasses.replace(ds, alpha=None)).grid.allowed is None
