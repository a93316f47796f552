"""Ray casting of a scene through the simulated drone's lens: diffuse shading, motion blur.

One ray per pixel centre (u + 0.5, v + 0.5), cast through the lens model
(:meth:`dronecap.camera.Camera.undistort_points`, OpenCV axes), so a distorted or off-centre
lens is rendered exactly as the camera model projects. A frame is the average of K sub-frame
renders at poses spread over the exposure time (K grows with how far the image moves during the
exposure); :mod:`dronecap.simulator.sensor` turns that radiance into an 8-bit frame.
"""

from __future__ import annotations

import numpy as np

from dronecap.camera import Camera
from dronecap.simulator.scenes import Scene


def ray_directions(lens: Camera) -> np.ndarray:
    """Unit ray directions in camera axes through every pixel centre, row-major: float32
    [H*W, 3] (through the lens distortion)."""
    v, u = np.mgrid[0 : lens.height, 0 : lens.width].astype(np.float64)
    xy = lens.undistort_points(np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1))
    d = np.concatenate([xy, np.ones((len(xy), 1))], 1)
    return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


class Renderer:
    """Renders a :class:`Scene` through a lens (:class:`dronecap.camera.Camera`)."""

    def __init__(self, scene: Scene, lens: Camera) -> None:
        self.scene, self.lens = scene, lens
        self._dirs = ray_directions(lens)

    def radiance(self, c2w: np.ndarray) -> np.ndarray:
        """Noise-free linear images for K poses ``c2w`` [K, 4, 4]: float32 [K, H, W], ~[0, 1]."""
        import open3d as o3d

        cam, scene = self.lens, self.scene
        k, n = len(c2w), len(self._dirs)
        rot = c2w[:, :3, :3].astype(np.float32)
        dirs = np.einsum("kij,nj->kni", rot, self._dirs).reshape(-1, 3)
        origins = np.repeat(c2w[:, :3, 3].astype(np.float32), n, axis=0)
        hit = scene.raycaster.cast_rays(  # type: ignore[attr-defined]
            o3d.core.Tensor(np.concatenate([origins, dirs], 1))
        )
        t = hit["t_hit"].numpy()
        ok = np.isfinite(t)
        t = np.where(ok, t, np.float32(0))
        # Work on [3, M] arrays (one row per axis): row arithmetic is much faster than [M, 3].
        d, nrm = dirs.T, np.ascontiguousarray(hit["primitive_normals"].numpy().T)
        points = origins.T + d * t
        facing = _dot(nrm, d)
        nrm *= np.where(facing > 0, np.float32(-1), np.float32(1))  # towards the camera
        # Isotropic mip filtering of an anisotropic footprint: leaning to its short axis keeps
        # walls seen at grazing angles (where parallax is largest) sharp, at a little aliasing.
        footprint = t / np.float32(cam.fx) / np.maximum(np.abs(facing), np.float32(0.1)) ** 0.25
        ids = hit["geometry_ids"].numpy().astype(np.int64)
        ids[~ok] = len(scene.materials)
        order = np.argsort(ids, kind="stable")
        bounds = np.searchsorted(ids[order], np.arange(len(scene.materials) + 1))
        albedo = np.zeros(len(t), np.float32)
        for g, material in enumerate(scene.materials):
            sel = order[bounds[g] : bounds[g + 1]]
            if len(sel):
                albedo[sel] = material(points[:, sel], nrm[:, sel], footprint[sel])
        light = np.full(len(t), scene.ambient, np.float32)
        for lamp in scene.lights:
            to_l = np.asarray(lamp.position, np.float32)[:, None] - points
            d2 = np.maximum(_dot(to_l, to_l), np.float32(0.5))
            cos = _dot(nrm, to_l) / np.sqrt(d2)
            light += np.float32(lamp.intensity) * np.maximum(cos, np.float32(0)) / d2
        out = np.where(ok, albedo * light, np.float32(0))
        return out.reshape(k, cam.height, cam.width)

    def blur_pixels(self, c2w_open: np.ndarray, c2w_close: np.ndarray) -> float:
        """Rough image motion (pixels) between two poses [4, 4]: rotation plus translation seen
        at 1 m."""
        r = c2w_open[:3, :3].T @ c2w_close[:3, :3]
        angle = np.arccos(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))
        shift = np.linalg.norm(c2w_close[:3, 3] - c2w_open[:3, 3])
        return float((angle + shift / 1.0) * self.lens.fx)

    @staticmethod
    def subframes(blur_px: float, max_subframes: int) -> np.ndarray:
        """Offsets in [-0.5, 0.5] of the exposure at which to render sub-frames: float [K], K =
        the blur in pixels clipped to [1, ``max_subframes``]."""
        k = int(np.clip(np.ceil(blur_px), 1, max_subframes))
        return np.zeros(1) if k == 1 else np.linspace(-0.5, 0.5, k)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product of [3, M] arrays -> [M]."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
