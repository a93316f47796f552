"""Fixtures of the camera tests: chessboard images rendered through a known lens."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.interpolate import RegularGridInterpolator

from dronecap.camera import Camera

SUPERSAMPLE = 3  # rays per pixel side: anti-aliased edges, so corners refine to sub-pixel


def board_images(
    cam: Camera, poses: list[tuple[np.ndarray, np.ndarray]], cols: int = 9, rows: int = 6
) -> list[np.ndarray]:
    """uint8 [H, W] images of a chessboard with ``cols x rows`` inner corners (corner (i, j)
    at board point (i, j), z = 0), one per pose (rvec, tvec: board -> camera, OpenCV), seen
    through ``cam`` with its distortion, in dronecap's pixel convention (centre of pixel (u, v)
    at (u + .5, v + .5)). Each sub-pixel ray is undistorted (OpenCV on a 1-px lattice,
    interpolated between) and intersected with the board plane. White margin of one square,
    gray background."""
    n = SUPERSAMPLE
    gu, gv = np.arange(cam.width + 1.0), np.arange(cam.height + 1.0)
    lattice = cam.undistort_points(np.stack(np.meshgrid(gu, gv), -1).reshape(-1, 2))
    lattice = lattice.reshape(len(gv), len(gu), 2)
    v, u = np.mgrid[0 : cam.height * n, 0 : cam.width * n]
    pts = np.stack([(v.ravel() + 0.5) / n, (u.ravel() + 0.5) / n], 1)
    xy = np.stack([RegularGridInterpolator((gv, gu), lattice[..., c])(pts) for c in range(2)], 1)
    rays = np.c_[xy, np.ones(len(xy))]
    out = []
    for rvec, tvec in poses:
        r, _ = cv2.Rodrigues(np.asarray(rvec, float))
        d = rays @ r  # ray directions in board axes (R^T d, row form)
        o = -r.T @ np.asarray(tvec, float).ravel()  # camera centre in board axes
        lam = -o[2] / d[:, 2]
        i, j = np.floor(o[0] + lam * d[:, 0]), np.floor(o[1] + lam * d[:, 1])
        front = lam > 0
        inside = front & (i >= -1) & (i <= cols - 1) & (j >= -1) & (j <= rows - 1)
        margin = front & (i >= -2) & (i <= cols) & (j >= -2) & (j <= rows)
        img = np.where(inside & ((i + j) % 2 == 0), 20.0, np.where(margin, 235.0, 128.0))
        img = img.reshape(cam.height, n, cam.width, n).mean((1, 3))
        out.append(np.round(img).astype(np.uint8))
    return out


def board_poses(
    k: int, seed: int = 0, distance: float = 15.0
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``k`` varied poses of a 9x6 board (unit squares) about ``distance`` units in front of
    the camera, tilted up to ~30 degrees and moved around the image so corners reach its
    borders."""
    rng = np.random.default_rng(seed)
    poses = []
    for a in range(k):
        ang = 2 * np.pi * a / k
        rvec = np.array([0.5 * np.cos(ang), 0.5 * np.sin(ang), rng.uniform(-0.3, 0.3)])
        s = distance / 15.0
        centre = np.array(
            [
                2.6 * s * np.cos(ang + 0.4),
                1.4 * s * np.sin(ang + 0.4),
                distance + rng.uniform(-1, 1),
            ]
        )
        r, _ = cv2.Rodrigues(rvec)
        tvec = centre - r @ np.array([4.0, 2.5, 0.0])  # the board's middle lands at ``centre``
        poses.append((rvec, tvec))
    return poses
