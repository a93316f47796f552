"""COLMAP cameras <-> dronecap cameras (:class:`dronecap.camera.Camera`).

Pixel conventions agree (pixel (u, v) is centred at (u + 0.5, v + 0.5) in both), so parameters
pass unchanged; only the parameter layout differs for COLMAP's one-focal models.
"""

from __future__ import annotations

from collections.abc import Sequence

from dronecap.camera.model import Camera

ONE_PARAM_FOCAL = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")  # COLMAP models with a single f


def colmap_camera(k: Camera) -> tuple[str, list[float]]:
    """(COLMAP model name, params) of a camera; a one-focal model with fx != fy becomes OPENCV
    (same maths, two focal lengths). Pixel conventions agree: no shift."""
    if k.model in ONE_PARAM_FOCAL and abs(k.fx - k.fy) > 1e-9 * k.fx:
        d = (list(k.distortion) + [0.0] * 4)[:4]
        return "OPENCV", [k.fx, k.fy, k.cx, k.cy, *d]
    if k.model in ONE_PARAM_FOCAL:
        return k.model, [k.fx, k.cx, k.cy, *k.distortion]
    return k.model, [k.fx, k.fy, k.cx, k.cy, *k.distortion]


def camera_from_colmap(model: str, params: Sequence[float], width: int, height: int) -> Camera:
    """dronecap Camera of a COLMAP camera (same pixel-centre convention, values unchanged)."""
    p = [float(x) for x in params]
    if model in ONE_PARAM_FOCAL:
        fx = fy = p[0]
        cx, cy, dist = p[1], p[2], tuple(p[3:])
    else:
        fx, fy, cx, cy, dist = p[0], p[1], p[2], p[3], tuple(p[4:])
    return Camera(fx, fy, cx, cy, int(width), int(height), model=model, distortion=dist)
