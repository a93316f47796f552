"""Arrays of a COLMAP model (pycolmap.Reconstruction): registered frames, camera-to-world poses,
sparse points and which points each frame observes. Used by ``dronecap sfm`` and the COLMAP
importer alike.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def model_arrays(rec: Any, names: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """Registered frames of a pycolmap Reconstruction.

    Args:
        rec: pycolmap.Reconstruction.
        names: work-folder name of every input frame (flight order).

    Returns:
        frame indices int [R] (sorted), c2w float64 [R, 4, 4] (OpenCV axes, COLMAP units),
        points float64 [P, 3], and for each registered frame the int [P_i] row numbers (into
        ``points``) of the points it observes.
    """
    pos = {n: i for i, n in enumerate(names)}
    ids = sorted(rec.points3D.keys())
    row = {pid: r for r, pid in enumerate(ids)}
    points = np.array([rec.points3D[p].xyz for p in ids], dtype=np.float64).reshape(-1, 3)
    regs = sorted((pos[rec.images[i].name], i) for i in rec.reg_image_ids())
    idx = np.array([f for f, _ in regs], dtype=np.int64)
    c2w = np.zeros((len(regs), 4, 4))
    seen = []
    for k, (_, image_id) in enumerate(regs):
        image = rec.images[image_id]
        w2c = np.eye(4)
        w2c[:3] = image.cam_from_world().matrix()
        c2w[k] = np.linalg.inv(w2c)
        seen.append(np.array([row[p.point3D_id] for p in image.points2D if p.has_point3D()], int))
    return idx, c2w, points, seen
