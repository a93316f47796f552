"""Shared by the GAP9 model tests: a toy configuration small enough to count by hand, and the
platform."""

import pytest

from dronecap.gap9.model import load_platform
from dronecap.gap9.platform import Platform
from dronecap.nerf.config import TrainConfig

# A 2-level toy: T = 2^5 = 32, levels at res 2 and 4 (n_min 2, n_max 4), F = 2; MLPs 4 wide with
# one hidden layer each; 3 geometry features; SH degree 1 (1 coefficient); gray (C = 1);
# a 4^3 grid; 8 samples per step in tiles of 4; 10 x 10 images.
TOY = TrainConfig(
    levels=2, features=2, log2_hashmap=5, n_min=2, n_max=4, hidden=4, density_layers=1,
    color_layers=1, geo_features=3, sh_degree=1, channels=1, grid_res=4, batch_samples=8,
    tile_samples=4, resolution=10, images_per_step=1, train_images=3, steps=10, grid_warmup=2,
    grid_every=4, march_steps=16,
)  # fmt: skip


@pytest.fixture(scope="module")
def gap9() -> Platform:
    return load_platform()
