"""The COLMAP model of an exported dataset, in the dataset's scene frame (pycolmap).

:func:`scene_model` builds a ``pycolmap.Reconstruction`` holding the dataset's camera (at the
stored resolution) and one registered image per frame, named as the exported PNGs, with the
dataset's poses (camera-from-world in OpenCV axes, which is COLMAP's convention). Its points:

- from the SfM model the poses came from (``sfm/model``, in COLMAP's own frame): the model is
  moved into the scene frame with the dataset's normalisation (``Reconstruction.transform``),
  each dataset frame is matched to the model image with the same pose, and every point seen by
  at least two of the dataset's frames is kept with its colour and its observations (keypoints
  rescaled when the model's camera has another resolution);
- else from points stored in the dataset (``extra/points3d_xyz`` float [P, 3] in the scene
  frame, ``extra/points3d_rgb`` uint8 [P, 3]), without observations;
- else none.

Points whose colours are all black (an SfM step that extracted no colour) take the frames'
colour (:func:`colour_from_frames`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dronecap.datasets.format import Dataset
from dronecap.errors import InputError

POSE_TOLERANCE = 1e-6  # a model image matches a frame when centres agree to this x scene size
POINTS_XYZ = "points3d_xyz"  # Dataset.extra names of stored sparse points (scene frame)
POINTS_RGB = "points3d_rgb"


def scene_model(ds: Dataset, names: list[str], sparse_model: str | Path | None) -> Any:
    """pycolmap.Reconstruction of ``ds`` (see the module docstring); ``names[i]`` is frame i's
    image name.

    Raises:
        InputError: an unreadable ``sparse_model``, or one in which some frame has no image
            with its pose (not the model this dataset came from).
    """
    import pycolmap

    from dronecap.camera.colmap import colmap_camera

    k = ds.camera_of(0)  # all cameras share the image size
    rec = pycolmap.Reconstruction()
    for c, cam in enumerate(ds.cameras or [k]):  # camera c + 1: one per camera of the table
        model, params = colmap_camera(cam)
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(
                model=model, width=k.width, height=k.height, params=params, camera_id=c + 1
            )
        )
    index = ds.camera_index if ds.camera_index is not None else np.zeros(ds.n, int)
    w2c = np.linalg.inv(ds.poses)
    src, match = (None, {}) if sparse_model is None else _matched_model(ds, sparse_model)
    for i, name in enumerate(names):
        keypoints = np.zeros((0, 2))
        if i in match:
            s_img = src.images[match[i]]
            s_cam = src.cameras[s_img.camera_id]
            scale = np.array([k.width / s_cam.width, k.height / s_cam.height])
            keypoints = np.array([p.xy for p in s_img.points2D]).reshape(-1, 2) * scale
        camera_id = int(index[i]) + 1
        image = pycolmap.Image(name=name, keypoints=keypoints, camera_id=camera_id, image_id=i + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[i, :3, :3]), w2c[i, :3, 3])
        rec.add_image_with_trivial_frame(image, pose)
    if src is not None:
        back = {img_id: i + 1 for i, img_id in match.items()}
        for point in src.points3D.values():
            track = pycolmap.Track()
            for el in point.track.elements:
                if el.image_id in back:
                    track.add_element(back[el.image_id], el.point2D_idx)
            if track.length() >= 2:
                rec.add_point3D(point.xyz, track, point.color)
    elif POINTS_XYZ in ds.extra:
        xyz = np.asarray(ds.extra[POINTS_XYZ], np.float64).reshape(-1, 3)
        rgb = np.asarray(ds.extra.get(POINTS_RGB, np.zeros_like(xyz)), np.uint8).reshape(-1, 3)
        for p, c in zip(xyz, rgb, strict=True):
            rec.add_point3D(p, pycolmap.Track(), c)
    if rec.num_points3D() and not any(pt.color.any() for pt in rec.points3D.values()):
        colour_from_frames(rec, ds)
    return rec


def colour_from_frames(rec: Any, ds: Dataset) -> None:
    """Give the points of ``rec`` (built by :func:`scene_model`, image i + 1 = frame i) the
    frames' colour (gray replicated to RGB): the median over the pixels that observe each point
    (its track's keypoints), or, for a point without observations, over the frames it projects
    into (in front of the camera, inside the image). Points no frame sees stay black."""
    k = ds.intrinsics
    h, w = ds.hw
    for pid, point in rec.points3D.items():
        samples = []
        for el in point.track.elements:
            uv = rec.images[el.image_id].points2D[el.point2D_idx].xy
            samples.append((el.image_id - 1, uv))
        if not samples:
            cam = (point.xyz - ds.poses[:, :3, 3])[:, None, :] @ ds.poses[:, :3, :3]  # [N, 1, 3]
            cam = cam[:, 0]
            front = np.flatnonzero(cam[:, 2] > 1e-9)
            uv = k.project(cam[front]) if len(front) else np.zeros((0, 2))
            samples = list(zip(front, uv, strict=True))
        vals = []
        for i, (u, v) in samples:
            if 0 <= u < w and 0 <= v < h:
                vals.append(ds.images[i][int(v), int(u)])
        if vals:
            c = np.median(np.stack(vals), 0).round().astype(np.uint8)
            rec.points3D[pid].color = np.repeat(c, 3) if c.size == 1 else c


def _matched_model(ds: Dataset, path: str | Path) -> tuple[Any, dict[int, int]]:
    """The SfM model moved into the scene frame, and {frame index: model image id}."""
    import pycolmap

    path = Path(path)
    if not (path / "images.bin").exists() and not (path / "images.txt").exists():
        raise InputError("not a COLMAP model folder (no images.bin or images.txt)", path)
    try:
        src = pycolmap.Reconstruction(str(path))
    except Exception as err:  # pycolmap raises plain RuntimeError/ValueError on bad files
        raise InputError(f"unreadable COLMAP model: {err}", path) from None
    if ds.normalization is not None:
        src.transform(pycolmap.Sim3d(np.asarray(ds.normalization, float)[:3]))
    ids = list(src.reg_image_ids())
    if not ids:
        raise InputError("the COLMAP model has no registered image", path)
    centres = np.array([src.images[i].projection_center() for i in ids])
    size = float(np.ptp(ds.poses[:, :3, 3], axis=0).max()) or 1.0
    match = {}
    for f in range(ds.n):
        d = np.linalg.norm(centres - ds.poses[f, :3, 3], axis=1)
        j = int(np.argmin(d))
        w2c = src.images[ids[j]].cam_from_world().matrix()[:, :3]
        rot_err = float(np.abs(w2c.T - ds.poses[f, :3, :3]).max())
        if d[j] > POSE_TOLERANCE * size or rot_err > POSE_TOLERANCE:
            raise InputError(
                f"frame {f} ({ds.frame_name(f)}) has no image with its pose in this COLMAP model "
                f"(nearest centre {d[j]:.3g} away): not the model this dataset came from",
                path,
            )
        match[f] = ids[j]
    return src, match
