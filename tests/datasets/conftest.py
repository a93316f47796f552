"""Fixtures for the datasets tests: a tiny Blender-layout scene of a known box (rendered here by
ray casting, OpenGL camera axes), and the real lego scene imported once."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dronecap.datasets.blender import import_blender, opengl_to_opencv

BOX = np.array([[-0.3, -0.2, -0.1], [0.3, 0.2, 0.4]])  # the synthetic scene's object (world units)
BOX_RGB = (200, 30, 60)


def gl_lookat(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world 4x4 in the OpenGL/Blender convention (x right, y up, z backwards)."""
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, -fwd, eye
    return m


def render_box_alpha(c2w_gl: np.ndarray, size: int, angle_x: float) -> np.ndarray:
    """bool [size, size]: pixels whose centre ray (OpenGL camera) hits BOX."""
    f = size / (2 * np.tan(angle_x / 2))
    j, i = np.mgrid[0:size, 0:size] + 0.5
    d_cam = np.stack([(i - size / 2) / f, -(j - size / 2) / f, -np.ones_like(i)], -1)
    d = d_cam @ c2w_gl[:3, :3].T
    o = c2w_gl[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (BOX[0] - o) / d
        t1 = (BOX[1] - o) / d
    tmin = np.nanmax(np.minimum(t0, t1), -1)
    tmax = np.nanmin(np.maximum(t0, t1), -1)
    return (tmax >= tmin) & (tmax > 0)


def make_box_scene(root: Path, size: int = 48, n_train: int = 24, n_test: int = 6) -> Path:
    """A Blender-layout scene of BOX seen from a sphere of cameras (radius 3, no val split).

    Object pixels are BOX_RGB with alpha 255; the rest is black with alpha 0.
    """
    angle_x = 0.8
    n = n_train + n_test
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n  # Fibonacci sphere, all elevations
    phi = np.pi * (1 + 5**0.5) * k
    rho = np.sqrt(1 - z**2)
    eyes = 3 * np.stack([rho * np.cos(phi), rho * np.sin(phi), z], -1)
    for split, idx in (("train", range(n_train)), ("test", range(n_train, n))):
        (root / split).mkdir(parents=True, exist_ok=True)
        frames = []
        for i, g in enumerate(idx):
            c2w = gl_lookat(eyes[g], np.zeros(3))
            a = render_box_alpha(c2w, size, angle_x)
            bgra = np.zeros((size, size, 4), np.uint8)
            bgra[a] = (BOX_RGB[2], BOX_RGB[1], BOX_RGB[0], 255)
            cv2.imwrite(str(root / split / f"r_{i}.png"), bgra)
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()})
        data = {"camera_angle_x": angle_x, "frames": frames}
        (root / f"transforms_{split}.json").write_text(json.dumps(data))
    return root


@pytest.fixture(scope="session")
def cv_lookat():
    """cv_lookat(eye [3], target [3]) -> camera-to-world 4x4 in OpenCV axes, world up +z."""
    return lambda eye, target: opengl_to_opencv(gl_lookat(np.asarray(eye, float), target))


@pytest.fixture(scope="session")
def box_truth() -> tuple[np.ndarray, tuple[int, int, int]]:
    """The synthetic scene's object: its box [2, 3] (min, max) and its RGB colour."""
    return BOX, BOX_RGB


@pytest.fixture(scope="session")
def scene_maker():
    """make_box_scene(root, size, n_train, n_test) -> Path, for tests that damage a scene."""
    return make_box_scene


@pytest.fixture(scope="module")
def box_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny rendered Blender-layout scene of a known box (48 px, 24 train + 6 test views)."""
    return make_box_scene(tmp_path_factory.mktemp("box_scene"))


@pytest.fixture(scope="session")
def lego_h5(lego_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The real lego scene imported once at 160 px RGB."""
    return import_blender(lego_dir, tmp_path_factory.mktemp("lego") / "dataset.h5", progress=False)
