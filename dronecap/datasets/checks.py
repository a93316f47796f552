"""The checks behind ``Dataset.validate`` (every write and every read of a dronecap file).

:func:`problem` returns the first thing wrong with a dataset as "<field>: <problem>": schema,
dtypes and shapes, non-finite values, non-rigid camera poses (orthonormal within
:data:`ROTATION_TOL`, det +1, last row [0, 0, 0, 1]), the camera (``Camera.problems``), an AABB
that is finite with max > min and seen by some camera, 0 <= near < far, a background in [0, 1],
the camera table (every camera valid and sized like the images, every frame's index in range,
``intrinsics`` equal to the one camera or None when there are several) and the drones (>= 0,
a name for each when names are given).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from dronecap.camera import Camera

if TYPE_CHECKING:
    from dronecap.datasets.dataset import Dataset

KINDS = ("frames", "posed", "dataset", "shard")
SPLITS = {"train": 0, "val": 1, "test": 2}
ROTATION_TOL = 1e-4  # max |R^T R - I| entry of a camera rotation (float64 poses reach 1e-12)


def problem(ds: Dataset) -> str | None:
    """The first thing wrong with ``ds`` ("<field>: <problem>"), or None."""
    im = ds.images
    if not isinstance(im, np.ndarray) or im.dtype != np.uint8 or im.ndim != 4:
        return f"images: must be uint8 [N,H,W,1|3], found {describe(im)}"
    if im.shape[3] not in (1, 3) or min(im.shape[1:3]) < 1:
        return f"images: must be uint8 [N,H,W,1|3] with H, W >= 1, found {list(im.shape)}"
    if ds.kind not in KINDS:
        return f"kind: unknown kind {ds.kind!r}, expected one of {list(KINDS)}"
    n, h, w = im.shape[:3]
    per_frame = {
        "alpha": (ds.alpha, (n, h, w), "u"),
        "poses": (ds.poses, (n, 4, 4), "f"),
        "source_index": (ds.source_index, (n,), "iu"),
        "timestamps": (ds.timestamps, (n,), "fiu"),
        "split": (ds.split, (n,), "iu"),
        "near_far": (ds.near_far, (n, 2), "fiu"),
        "camera_index": (ds.camera_index, (n,), "iu"),
        "drone": (ds.drone, (n,), "iu"),
        **{f"shards/{k}": (v, (n,), "iu") for k, v in ds.shards.items()},
    }
    for name, (arr, shape, kinds) in per_frame.items():
        if arr is None:
            continue
        if not isinstance(arr, np.ndarray) or arr.dtype.kind not in kinds:
            return f"{name}: wrong type {describe(arr)}"
        if tuple(arr.shape) != shape:
            return f"{name}: has shape {list(arr.shape)}, expected {list(shape)}"
        if arr.dtype.kind == "f" and not np.isfinite(arr).all():
            return f"{name}: contains non-finite values (NaN or Inf)"
    if ds.alpha is not None and ds.alpha.dtype != np.uint8:
        return f"alpha: must be uint8, found {ds.alpha.dtype}"
    if ds.split is not None and not np.isin(ds.split, [-1, *SPLITS.values()]).all():
        found = sorted(set(ds.split.tolist()))[:8]
        return f"split: values must be -1, 0, 1 or 2, found {found}"
    for name, arr in ds.shards.items():
        if len(arr) and arr.min() < -1:
            return f"shards/{name}: client numbers must be >= -1, found {int(arr.min())}"
    if ds.names is not None:
        if len(ds.names) != n:
            return f"names: has {len(ds.names)} entries, expected {n}"
        if not all(isinstance(s, str) for s in ds.names):
            return "names: entries must be strings"
    if ds.poses is not None and (bad := _pose_problem(ds.poses)) is not None:
        return f"poses: {bad}"
    if ds.near_far is not None and n:
        nf = ds.near_far
        if not ((nf[:, 0] >= 0).all() and (nf[:, 1] > nf[:, 0]).all()):
            i = int(np.flatnonzero(~((nf[:, 0] >= 0) & (nf[:, 1] > nf[:, 0])))[0])
            return f"near_far: must satisfy 0 <= near < far, frame {i} has {nf[i].tolist()}"
    if ds.intrinsics is not None and (bad := _camera_problem(ds.intrinsics, w, h)) is not None:
        return f"intrinsics: {bad}"
    if (bad := _camera_table_problem(ds)) is not None:
        return bad
    if (bad := _drone_problem(ds)) is not None:
        return bad
    if ds.aabb is not None and (bad := _aabb_problem(ds)) is not None:
        return f"aabb: {bad}"
    if ds.normalization is not None:
        m = ds.normalization
        if not _float_array(m, (4, 4)):
            return f"normalization: must be a finite float [4, 4], found {describe(m)}"
    if ds.background is not None:
        bg = ds.background
        if len(bg) != im.shape[3]:
            return f"background: has {len(bg)} values for {im.shape[3]} channels"
        if not all(_real(x) and 0.0 <= float(x) <= 1.0 for x in bg):
            return f"background: values must be finite and in [0, 1], found {list(bg)}"
    for name in ("provenance", "attrs"):
        if not isinstance(getattr(ds, name), dict):
            return f"{name}: must be a JSON object, found {type(getattr(ds, name)).__name__}"
    return None


def _camera_problem(k: object, w: int, h: int) -> str | None:
    """What is wrong with camera ``k`` for w x h images (None when it is usable)."""
    if not isinstance(k, Camera):
        return f"must be a Camera, found {type(k).__name__}"
    for problem in k.problems():
        return problem
    if (k.width, k.height) != (w, h):
        return f"are for {k.width}x{k.height} but images are {w}x{h}"
    return None


def _camera_table_problem(ds: Dataset) -> str | None:
    """The camera table, the per-frame index into it and its agreement with ``intrinsics``."""
    cams, index = ds.cameras, ds.camera_index
    if cams is None:
        return "camera_index: given without a cameras table" if index is not None else None
    if not isinstance(cams, list) or not cams:
        return f"cameras: must be a non-empty list of cameras, found {describe(cams)}"
    h, w = ds.images.shape[1:3]
    for i, k in enumerate(cams):
        if (bad := _camera_problem(k, w, h)) is not None:
            return f"cameras[{i}]: {bad}"
    if index is None:
        if len(cams) > 1:
            return f"camera_index: missing, needed to choose among {len(cams)} cameras"
    elif len(index) and (index.min() < 0 or index.max() >= len(cams)):
        bad = int(index.min() if index.min() < 0 else index.max())
        return f"camera_index: {bad} is not a camera (the table has {len(cams)})"
    expected = cams[0] if len(cams) == 1 else None
    if ds.intrinsics != expected:
        if expected is None:
            return f"intrinsics: must be None when there are {len(cams)} cameras"
        return "intrinsics: must equal cameras[0] when there is one camera"
    return None


def _drone_problem(ds: Dataset) -> str | None:
    """Drone numbers >= 0, and a name for every drone when names are given."""
    names = ds.drone_names
    if names is not None and not (
        isinstance(names, list) and all(isinstance(s, str) for s in names)
    ):
        return "drone_names: must be a list of strings"
    if ds.drone is None or not len(ds.drone):
        return None
    if ds.drone.min() < 0:
        return f"drone: numbers must be >= 0, found {int(ds.drone.min())}"
    if names is not None and ds.drone.max() >= len(names):
        return f"drone: drone {int(ds.drone.max())} has no name (drone_names has {len(names)})"
    return None


def _aabb_problem(ds: Dataset) -> str | None:
    a = ds.aabb
    if not _float_array(a, (2, 3)) or not np.all(a[1] > a[0]):
        return f"must be finite [[min xyz], [max xyz]] with max > min, found {describe(a)}"
    if ds.poses is not None and ds.n and not _box_seen(np.asarray(a), ds.poses, ds):
        return f"{np.asarray(a).tolist()} is outside every camera's view"
    return None


def _box_seen(box: np.ndarray, poses: np.ndarray, ds: Dataset) -> bool:
    """Whether some camera sees part of ``box`` [2, 3]: a camera inside it, one of 5^3 points
    spread over it inside an image, or a ray through an image's centre or corners hitting it.
    Without intrinsics: some part of it lies in front of a camera."""
    t = np.linspace(0.0, 1.0, 5)
    pts = box[0] + (box[1] - box[0]) * np.stack(np.meshgrid(t, t, t), -1).reshape(-1, 3)
    cam = np.einsum("nji,nkj->nki", poses[:, :3, :3], pts[None] - poses[:, None, :3, 3])
    inside = ((poses[:, :3, 3] >= box[0]) & (poses[:, :3, 3] <= box[1])).all(1)
    if ds.intrinsics is None and ds.cameras is None:
        return bool(inside.any() or (cam[..., 2] > 0).any())
    ks = ds.frame_cameras()
    fx, fy, cx, cy = (
        np.array([getattr(k, a) for k in ks])[:, None] for a in ("fx", "fy", "cx", "cy")
    )
    w, h = ks[0].width, ks[0].height
    z = np.where(cam[..., 2] > 0, cam[..., 2], np.inf)
    u, v = fx * cam[..., 0] / z + cx, fy * cam[..., 1] / z + cy
    in_image = (cam[..., 2] > 0) & (u >= 0) & (u <= w) & (v >= 0) & (v <= h)
    if inside.any() or in_image.any():
        return True
    uv = np.array([[w / 2, h / 2], [0, 0], [w, 0], [0, h], [w, h]])  # [5, 2]
    d_cam = np.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy, np.ones((len(ks), 5))], -1)
    d = np.einsum("nij,nkj->nki", poses[:, :3, :3], d_cam)  # [N, 5, 3] world directions
    o = poses[:, None, :3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (box[0] - o) / d, (box[1] - o) / d  # 0/0: the ray runs in a slab's face
    t0, t1 = np.where(np.isnan(t0), -np.inf, t0), np.where(np.isnan(t1), np.inf, t1)
    near = np.minimum(t0, t1).max(-1)
    far = np.maximum(t0, t1).min(-1)
    return bool(((far >= near) & (far > 0)).any())


def _pose_problem(poses: np.ndarray) -> str | None:
    """What makes these camera-to-world poses [N, 4, 4] not rigid (None when they are)."""
    if not len(poses):
        return None
    bottom = np.abs(poses[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(1)
    if (bottom > 1e-9).any():
        i = int(np.argmax(bottom))
        return f"frame {i}: last row must be [0, 0, 0, 1], found {poses[i, 3].tolist()}"
    r = poses[:, :3, :3]
    err = np.abs(np.einsum("nji,njk->nik", r, r) - np.eye(3)).max((1, 2))
    if (err > ROTATION_TOL).any():
        i = int(np.argmax(err))
        return f"frame {i}: rotation is not orthonormal (|R^T R - I| = {err[i]:.3g})"
    det = np.linalg.det(r)
    if (det < 0).any():
        i = int(np.flatnonzero(det < 0)[0])
        return f"frame {i}: rotation is a reflection (det {det[i]:.3f}), not a rotation"
    return None


def _real(x: object) -> bool:
    """True for a finite int/float (numpy included), False for bools, strings and the rest."""
    if isinstance(x, bool | np.bool_) or not isinstance(x, int | float | np.integer | np.floating):
        return False
    return bool(np.isfinite(float(x)))


def _float_array(a: object, shape: tuple[int, ...]) -> bool:
    return (
        isinstance(a, np.ndarray)
        and a.dtype.kind in "fiu"
        and a.shape == shape
        and bool(np.isfinite(a).all())
    )


def describe(a: object) -> str:
    """A value in a few words for an error message (dtype and shape, or type and text)."""
    if isinstance(a, np.ndarray):
        if a.size <= 8 and a.dtype.kind in "fiub":
            return f"{a.dtype} {a.tolist()}"
        return f"{a.dtype} {list(a.shape)}"
    return f"{type(a).__name__} {str(a)[:60]!r}"
