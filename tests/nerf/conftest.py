"""Tiny synthetic scenes for the trainer tests: a face-coloured cube rendered analytically."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dronecap.datasets.format import Dataset, Intrinsics, write_dataset

FACE_COLOURS = np.array(
    [
        [0.9, 0.1, 0.1],
        [0.1, 0.8, 0.2],
        [0.1, 0.2, 0.9],
        [0.9, 0.8, 0.1],
        [0.1, 0.8, 0.8],
        [0.8, 0.2, 0.8],
    ]
)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Camera-to-world [4, 4], OpenCV axes (z towards target, y down)."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, y, z], 1)
    m[:3, 3] = eye
    return m


def render_cube(c2w: np.ndarray, k: Intrinsics, half: float = 0.5):
    """RGB [H, W, 3] float and alpha [H, W] of the cube [-half, half]^3 (face colours), seen
    through the camera's lens model (OpenCV undoes the distortion of each pixel centre)."""
    v, u = np.mgrid[0 : k.height, 0 : k.width]
    xy = k.undistort_points(np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1))
    d = np.concatenate([xy, np.ones((xy.shape[0], 1))], 1).reshape(k.height, k.width, 3)
    d = d @ c2w[:3, :3].T
    o = np.broadcast_to(c2w[:3, 3], d.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (-half - o) / d
        t1 = (half - o) / d
    tn = np.minimum(t0, t1).max(-1)
    tf = np.maximum(t0, t1).min(-1)
    hit = (tf > tn) & (tf > 0)
    axis = np.argmax(np.minimum(t0, t1), -1)
    p = o + d * tn[..., None]
    sign = np.take_along_axis(p, axis[..., None], -1)[..., 0] > 0
    face = axis * 2 + sign
    rgb = np.where(hit[..., None], FACE_COLOURS[face], 1.0)
    return rgb, hit.astype(float)


def cube_dataset(
    n: int = 12,
    size: int = 24,
    channels: int = 3,
    test_every: int = 4,
    model: str = "PINHOLE",
    distortion: tuple[float, ...] = (),
    radius: float = 3.0,
    fov: float = 0.8,
    aim_offset: float = 0.0,
) -> Dataset:
    """``n`` views on a circle (``radius``, slightly above) of the coloured cube through a
    camera of field of view ``fov`` (radians) and the given lens ``model``/``distortion``;
    every ``test_every``-th view is a test view. AABB [-1, 1]^3, white background.

    ``aim_offset`` > 0 aims view ``i`` that far beside the cube, in a direction that turns by
    2.4 rad from view to view, so the cube crosses every part of the frame (where a lens
    distorts most) instead of sitting at the centre."""
    f = size / (2 * np.tan(0.5 * fov))
    k = Intrinsics(f, f, size / 2, size / 2, size, size, model, tuple(distortion))
    poses, imgs, alphas = [], [], []
    for i in range(n):
        th = 2 * np.pi * i / n
        eye = np.array([radius * np.cos(th), radius * np.sin(th), 0.4 * radius])
        side = np.array([-np.sin(th), np.cos(th), 0.0])  # horizontal, across the view
        target = aim_offset * (np.cos(2.4 * i) * side + np.sin(2.4 * i) * np.array([0, 0, 1.0]))
        c2w = look_at(eye, target, np.array([0.0, 0.0, 1.0]))
        rgb, a = render_cube(c2w, k)
        if channels == 1:
            rgb = rgb @ np.array([0.299, 0.587, 0.114])[:, None]
        poses.append(c2w)
        imgs.append(np.round(rgb * 255).astype(np.uint8))
        alphas.append(np.round(a * 255).astype(np.uint8))
    split = np.array([2 if i % test_every == 0 else 0 for i in range(n)], np.int8)
    return Dataset(
        images=np.stack(imgs),
        alpha=np.stack(alphas),
        poses=np.stack(poses),
        intrinsics=k,
        split=split,
        near_far=np.tile([radius - 1.5, radius + 1.5], (n, 1)),
        aabb=np.array([[-1.0, -1, -1], [1, 1, 1]]),
        background=(1.0,) * channels,
    )


@pytest.fixture(scope="session")
def cube_rgb() -> Dataset:
    """12 RGB views of the cube, 24x24."""
    return cube_dataset()


@pytest.fixture(scope="session")
def cube_h5(tmp_path_factory) -> Path:
    """The RGB cube written as dataset.h5."""
    return write_dataset(tmp_path_factory.mktemp("cube") / "dataset.h5", cube_dataset())


@pytest.fixture(scope="session")
def cube_gray_h5(tmp_path_factory) -> Path:
    """The gray cube written as dataset.h5."""
    return write_dataset(
        tmp_path_factory.mktemp("cube_gray") / "dataset.h5", cube_dataset(channels=1)
    )


@pytest.fixture(scope="session")
def make_cube():
    """:func:`cube_dataset` itself, for tests that need other sizes or lenses."""
    return cube_dataset
