"""A plain backdrop read from the frames (datasets.background): object captures without alpha
on white or black declare it as the dataset background, camera footage does not."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dronecap.datasets.background import plain_background
from dronecap.datasets.format import open_dataset
from dronecap.datasets.import_transforms import import_transforms
from dronecap.nerf.config import preset
from dronecap.nerf.resolve import resolve

from .test_import_transforms import write_nerfstudio_scene


def _object_frames(backdrop: int, channels: int, n: int = 6, seed: int = 0) -> np.ndarray:
    """uint8 [n, 40, 40, C]: a textured object in the middle of a ``backdrop`` frame, JPEG-like
    noise of +-6 levels on the backdrop, one object corner touching the left edge."""
    rng = np.random.default_rng(seed)
    im = np.full((n, 40, 40, channels), backdrop, np.int16)
    im += rng.integers(-6, 7, im.shape, dtype=np.int16)
    im[:, 10:30, 8:32] = rng.integers(0, 256, (n, 20, 24, channels))
    im[:, 18:22, :8] = rng.integers(0, 256, (n, 4, 8, channels))
    return im.clip(0, 255).astype(np.uint8)


def test_a_plain_backdrop_is_found_and_footage_has_none() -> None:
    white, why = plain_background(_object_frames(255, 3))
    assert white == (1.0, 1.0, 1.0) and "backdrop" in why
    black, _ = plain_background(_object_frames(0, 1))
    assert black == (0.0,)
    rng = np.random.default_rng(1)
    footage = rng.integers(0, 256, (6, 40, 40, 1), dtype=np.uint8)  # texture to the edges
    assert plain_background(footage)[0] is None
    half = _object_frames(255, 3)
    half[:3] = footage.repeat(3, -1)[:3]  # half the frames on a backdrop: not a backdrop
    assert plain_background(half)[0] is None


def test_an_rgb_object_capture_on_white_trains_against_white(tmp_path: Path) -> None:
    """The nerfstudio cube (RGB on white, no alpha, no background key) imports with a white
    background, which the trainer composites on: the resolver keeps the box only."""
    scene = write_nerfstudio_scene(tmp_path / "scene")
    ds = open_dataset(import_transforms(scene, tmp_path / "d.h5", size=48, progress=False))
    assert ds.alpha is None and ds.background == (1.0, 1.0, 1.0)
    assert "backdrop" in ds.attrs["background_from"]
    r = resolve(preset("test"), ds)
    assert r.scene.background == (1.0, 1.0, 1.0) and r.config.far_field == "none"
