"""Export a dataset to the nerfstudio / instant-ngp ``transforms.json`` layout, plus PNG images.

The folder holds:

- ``images/00000.png`` ...: the stored images, RGBA when the dataset has alpha (straight colour),
  else RGB or 8-bit gray;
- ``transforms.json``: ``camera_model`` (PINHOLE, or OPENCV with k1, k2, p1, p2), ``fl_x``,
  ``fl_y``, ``cx``, ``cy``, ``w``, ``h`` (pixels; pixel centres at + 0.5 as in dronecap),
  ``camera_angle_x``, and per frame ``file_path`` and ``transform_matrix`` (camera-to-world,
  OpenGL camera axes: x right, y up, z backwards), plus ``train_filenames`` /
  ``val_filenames`` / ``test_filenames`` for the non-empty splits;
- when the camera is a centred pinhole with square pixels, also Blender-layout
  ``transforms_{train,val,test}.json`` (``camera_angle_x`` + frames) for NeRF codebases that read
  NeRF Synthetic scenes — ``dronecap import-blender`` reads them back.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.datasets.blender import opencv_to_opengl
from dronecap.datasets.format import SPLITS, Dataset, Intrinsics, open_dataset
from dronecap.errors import InputError
from dronecap.files import atomic_output

# COLMAP model -> names of its extra parameters, in the order Intrinsics.distortion holds them
_DISTORTION = {
    "SIMPLE_PINHOLE": (),
    "PINHOLE": (),
    "SIMPLE_RADIAL": ("k1",),
    "RADIAL": ("k1", "k2"),
    "OPENCV": ("k1", "k2", "p1", "p2"),
}


def camera_json(k: Intrinsics) -> dict[str, Any]:
    """nerfstudio camera fields of ``k`` (fl_x, fl_y, cx, cy, w, h, camera_model, k1...)."""
    if k.model not in _DISTORTION or len(k.distortion) != len(_DISTORTION[k.model]):
        raise InputError(
            f"cannot export camera model {k.model} with {len(k.distortion)} distortion parameters"
        )
    cam: dict[str, Any] = {
        "camera_model": "OPENCV" if k.distortion else "PINHOLE",
        "fl_x": k.fx,
        "fl_y": k.fy,
        "cx": k.cx,
        "cy": k.cy,
        "w": k.width,
        "h": k.height,
        "camera_angle_x": float(2 * np.arctan(k.width / (2 * k.fx))),
    }
    if k.distortion:
        cam.update({name: 0.0 for name in ("k1", "k2", "p1", "p2")})
        cam.update(dict(zip(_DISTORTION[k.model], map(float, k.distortion), strict=True)))
    return cam


def export_transforms(in_path: str | Path, out_dir: str | Path) -> Path:
    """Write ``out_dir`` (atomically, replacing it) with transforms.json and the images.

    Args:
        in_path: a dronecap file with poses and intrinsics (kind posed, dataset or shard).
        out_dir: the folder to write.

    Raises:
        InputError: unreadable input, no poses/intrinsics, or an unexportable camera model.
    """
    import cv2

    in_path, out_dir = Path(in_path), Path(out_dir)
    ds = open_dataset(in_path, kinds=("posed", "dataset", "shard"))
    if ds.poses is None or ds.intrinsics is None:
        raise InputError("has no camera poses or intrinsics to export", in_path)
    cam = camera_json(ds.intrinsics)
    gl = opencv_to_opengl(ds.poses)
    files = [f"images/{i:05d}.png" for i in range(ds.n)]
    frames = [
        {"file_path": f, "transform_matrix": m.tolist(), "dronecap_name": ds.frame_name(i)}
        for i, (f, m) in enumerate(zip(files, gl, strict=True))
    ]
    meta: dict[str, Any] = {**cam, "frames": frames}
    splits = (
        {} if ds.split is None else {s: np.flatnonzero(ds.split == v) for s, v in SPLITS.items()}
    )
    for s, idx in splits.items():
        if len(idx):
            meta[f"{s}_filenames"] = [files[i] for i in idx]
    if ds.aabb is not None:
        meta["dronecap_aabb"] = np.asarray(ds.aabb).tolist()
    with atomic_output(out_dir) as tmp:
        (tmp / "images").mkdir(parents=True)
        for i, f in enumerate(files):
            cv2.imwrite(str(tmp / f), _bgr(ds, i))
        (tmp / "transforms.json").write_text(json.dumps(meta, indent=1))
        k = ds.intrinsics
        centred = k.fx == k.fy and k.cx == k.width / 2 and k.cy == k.height / 2
        if centred and not k.distortion:
            for s, idx in splits.items():
                if not len(idx):
                    continue
                blender = {
                    "camera_angle_x": cam["camera_angle_x"],
                    "frames": [frames[i] for i in idx],
                }
                (tmp / f"transforms_{s}.json").write_text(json.dumps(blender, indent=1))
    return out_dir


def _bgr(ds: Dataset, i: int) -> np.ndarray:
    """Frame i as OpenCV wants to write it: gray, BGR, or BGRA when there is alpha."""
    im = ds.images[i]
    if ds.alpha is not None:
        rgb = np.repeat(im, 3, axis=2) if im.shape[2] == 1 else im
        return np.dstack([rgb[:, :, ::-1], ds.alpha[i]])
    return im[:, :, 0] if im.shape[2] == 1 else im[:, :, ::-1]
