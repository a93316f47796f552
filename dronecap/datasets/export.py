"""Export a dataset for nerfstudio, instant-ngp and COLMAP: ``transforms.json``, PNGs, a model.

The folder holds (everything in the dataset's own scene frame, so the files agree):

- ``images/00000.png`` ...: the stored images, RGBA when the dataset has alpha (straight colour),
  else RGB or 8-bit gray;
- ``transforms.json`` (nerfstudio 1.1.5's ``nerfstudio-data`` parser and instant-ngp):
  ``camera_model`` (PINHOLE, OPENCV or OPENCV_FISHEYE), ``fl_x``, ``fl_y``, ``cx``, ``cy``,
  ``w``, ``h`` (pixels; pixel centres at + 0.5 as in dronecap and both tools), the distortion
  (OPENCV: ``k1 k2 p1 p2`` and ``k3`` when non-zero; fisheye: ``k1..k4`` and instant-ngp's
  ``is_fisheye``), ``camera_angle_x`` for a centred pinhole, per frame ``file_path`` and
  ``transform_matrix`` (camera-to-world, OpenGL camera axes: x right, y up, z backwards);
  ``train_filenames`` / ``val_filenames`` / ``test_filenames`` (all three, as nerfstudio wants
  once one is present; ``val`` is the real val split, or the test split when there is none);
  ``applied_transform`` (3x4: the dataset's normalisation, source frame -> exported frame, so
  nerfstudio's ``dataparser_transform`` maps back to the SfM frame); instant-ngp's ``aabb``
  (the dataset's AABB, which instant-ngp fits into its unit cube) and ``aabb_scale`` 1;
  ``ply_file_path`` when there are sparse points;
- ``transforms_{train,val,test}.json``: the same keys with only that split's frames, for
  instant-ngp (``--scene transforms_train.json``: test frames never in the training file) and
  for NeRF codebases that read NeRF Synthetic scenes (``camera_angle_x`` is written only for a
  centred pinhole, which is what that layout can express);
- ``sparse_pc.ply``: the sparse points with their colours in the exported frame, and
  ``colmap/sparse/0`` (binary) and ``colmap/text`` (text): the COLMAP model of the exported
  images and poses (:mod:`dronecap.datasets.export_colmap`);
- ``trajectory_tum.txt``: the camera-to-world poses (OpenCV axes) as a TUM trajectory, stamped
  with the capture time (else the source frame index), for evo-style trajectory tools.

A camera neither tool can express (FULL_OPENCV with rational terms k4..k6) is refused; one that
only instant-ngp cannot express (non-zero k3) gets no per-split files, and the result says so.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.datasets.blender import opencv_to_opengl
from dronecap.datasets.format import SPLITS, Dataset, Intrinsics, open_dataset
from dronecap.datasets.trajectory import write_tum
from dronecap.errors import InputError
from dronecap.files import atomic_output

PLY_NAME = "sparse_pc.ply"  # nerfstudio's own name for the sparse cloud
COLMAP_BINARY = "colmap/sparse/0"
COLMAP_TEXT = "colmap/text"
TRAJECTORY = "trajectory_tum.txt"


@dataclass
class ExportResult:
    """What :func:`export_transforms` wrote."""

    out_dir: Path
    frames: int
    split_counts: dict[str, int]  # frames listed per split in transforms.json (empty: no split)
    split_files: list[str]  # transforms_<split>.json written
    points: int  # sparse points in the PLY and the COLMAP model (0: no PLY)
    observations: int  # 2D observations kept in the COLMAP model
    notes: list[str] = field(default_factory=list)  # what could not be written, and why


def frame_camera_keys(ds: Dataset) -> list[dict[str, Any]]:
    """Per-frame camera keys [N] (nerfstudio reads them over the top-level ones): each frame's
    own camera when the dataset has several, else nothing per frame."""
    if ds.cameras is None or len(ds.cameras) == 1:
        return [{} for _ in range(ds.n)]
    table = [nerfstudio_camera(k) for k in ds.cameras]
    return [table[int(c)] for c in ds.camera_index]


def nerfstudio_camera(k: Intrinsics) -> dict[str, Any]:
    """Camera keys of ``k`` as nerfstudio reads them (fl_x, fl_y, cx, cy, w, h, camera_model,
    k1..k4, p1, p2; pixels).

    Raises:
        InputError: a FULL_OPENCV camera with rational terms (k4..k6 != 0), which nerfstudio's
            polynomial lens cannot express.
    """
    cam: dict[str, Any] = {
        "camera_model": "PINHOLE",
        "fl_x": float(k.fx),
        "fl_y": float(k.fy),
        "cx": float(k.cx),
        "cy": float(k.cy),
        "w": int(k.width),
        "h": int(k.height),
    }
    if k.is_pinhole:
        return cam
    d = [float(x) for x in k.distortion]
    if k.is_fisheye:
        cam["camera_model"] = "OPENCV_FISHEYE"
        cam.update(zip(("k1", "k2", "k3", "k4"), d, strict=True))
        return cam
    if k.model == "FULL_OPENCV" and any(d[5:]):
        raise InputError(
            f"camera FULL_OPENCV has rational distortion terms k4..k6 = {d[5:]}, which "
            "nerfstudio and instant-ngp cannot express"
        )
    c = k.opencv_coeffs()  # (k1, k2, p1, p2[, k3, ...])
    cam["camera_model"] = "OPENCV"
    cam.update({"k1": float(c[0]), "k2": float(c[1]), "p1": float(c[2]), "p2": float(c[3])})
    if len(c) > 4 and c[4] != 0:
        cam["k3"] = float(c[4])
    return cam


def ngp_problem(cam: dict[str, Any]) -> str | None:
    """Why instant-ngp cannot read the camera ``cam`` (from :func:`nerfstudio_camera`), or None.

    instant-ngp's OpenCV lens has four slots: k1, k2 and then p1, p2 (k3 and k4 share them).
    """
    if cam["camera_model"] == "OPENCV" and "k3" in cam:
        return "instant-ngp's OpenCV lens has no k3 (non-zero here)"
    return None


def ngp_keys(cam: dict[str, Any], aabb: np.ndarray | None) -> dict[str, Any]:
    """instant-ngp's extra keys: ``is_fisheye``, ``aabb`` (mapped to its unit cube) and
    ``aabb_scale`` (1: the scene is that box)."""
    out: dict[str, Any] = {}
    if cam["camera_model"] == "OPENCV_FISHEYE":
        out["is_fisheye"] = True
    if aabb is not None:
        out["aabb"] = np.asarray(aabb, float).tolist()
        out["aabb_scale"] = 1
    return out


def nerfstudio_args(aabb: np.ndarray | None) -> str:
    """The ``nerfstudio-data`` dataparser options under which nerfstudio keeps the exported
    frame: no re-orientation, no re-centring, no rescaling (its defaults ``up``, ``poses`` and
    auto-scale move the poses), and a ``--scene-scale`` whose box [-s, s]^3 holds the AABB."""
    opts = "--orientation-method none --center-method none --auto-scale-poses False"
    if aabb is None:
        return opts
    s = float(np.abs(np.asarray(aabb, float)).max())
    return f"{opts} --scene-scale {np.ceil(s * 1000) / 1000:g}"


def centred_pinhole(k: Intrinsics) -> bool:
    """True when ``k`` is a Blender/NeRF Synthetic camera (camera_angle_x says it all)."""
    return k.is_pinhole and k.fx == k.fy and k.cx == k.width / 2 and k.cy == k.height / 2


def split_lists(ds: Dataset, files: list[str]) -> tuple[dict[str, list[str]], list[str]]:
    """``{train, val, test}`` file lists for nerfstudio (val: the val split, else test), and
    notes; empty when the dataset has no usable split."""
    if ds.split is None:
        return {}, ["no train/test split: nerfstudio picks its own, no per-split files"]
    idx = {s: np.flatnonzero(ds.split == v) for s, v in SPLITS.items()}
    notes = []
    if not len(idx["val"]):
        idx["val"] = idx["test"]
        notes.append("no val split: val_filenames lists the test frames")
    if not len(idx["train"]) or not len(idx["val"]):
        return {}, ["the split has no train or no test frame: no split lists written"]
    return {s: [files[i] for i in ix] for s, ix in idx.items()}, notes


def export_transforms(
    in_path: str | Path, out_dir: str | Path, sparse_model: str | Path | None = None
) -> ExportResult:
    """Write ``out_dir`` (atomically, replacing it): transforms files, images, PLY, COLMAP model.

    Args:
        in_path: a dronecap file with poses and intrinsics (kind posed, dataset or shard).
        out_dir: the folder to write.
        sparse_model: the SfM model the dataset's poses came from (``sfm/model``); its points,
            colours and observations go into the PLY and the COLMAP model. Without it, points
            stored in the dataset (``extra/points3d_xyz``, ``extra/points3d_rgb``) are used.

    Raises:
        InputError: unreadable input, no poses/intrinsics, an inexpressible camera, or a
            sparse model whose images do not match the dataset's poses.
    """
    from dronecap.datasets.export_colmap import scene_model

    in_path, out_dir = Path(in_path), Path(out_dir)
    ds = open_dataset(in_path, kinds=("posed", "dataset", "shard"))
    if ds.poses is None or (ds.intrinsics is None and ds.cameras is None):
        raise InputError("has no camera poses or intrinsics to export", in_path)
    k = ds.camera_of(0)
    cam = nerfstudio_camera(k)
    own = frame_camera_keys(ds)
    if centred_pinhole(k):
        cam["camera_angle_x"] = float(2 * np.arctan(k.width / (2 * k.fx)))
    files = [f"images/{i:05d}.png" for i in range(ds.n)]
    rec = scene_model(ds, [Path(f).name for f in files], sparse_model)
    norm = np.eye(4) if ds.normalization is None else np.asarray(ds.normalization, float)
    common: dict[str, Any] = {
        **cam,
        **ngp_keys(cam, ds.aabb),
        "applied_transform": norm[:3].tolist(),
    }
    if rec.num_points3D():
        common["ply_file_path"] = PLY_NAME
    gl = opencv_to_opengl(ds.poses)
    frames = [
        {"file_path": f, "transform_matrix": m.tolist(), "dronecap_name": ds.frame_name(i)} | own[i]
        for i, (f, m) in enumerate(zip(files, gl, strict=True))
    ]
    lists, notes = split_lists(ds, files)
    common["dronecap_nerfstudio_args"] = nerfstudio_args(ds.aabb)
    notes.append(
        f"nerfstudio keeps this frame and box with: ns-train nerfacto --data {out_dir} "
        f"nerfstudio-data {common['dronecap_nerfstudio_args']}"
    )
    meta = {**common, "frames": frames, **{f"{s}_filenames": v for s, v in lists.items()}}
    problem = ngp_problem(cam)
    if problem and lists:
        notes.append(f"no per-split files: {problem}")
    with atomic_output(out_dir) as tmp:
        split_files = _write_folder(
            tmp, ds, files, meta, frames, lists, None if problem else common, rec
        )
    return ExportResult(
        out_dir=out_dir,
        frames=ds.n,
        split_counts={s: len(v) for s, v in lists.items()},
        split_files=split_files,
        points=int(rec.num_points3D()),
        observations=int(rec.compute_num_observations()),
        notes=notes,
    )


def _write_folder(
    tmp: Path,
    ds: Dataset,
    files: list[str],
    meta: dict[str, Any],
    frames: list[dict[str, Any]],
    lists: dict[str, list[str]],
    common: dict[str, Any] | None,
    rec: Any,
) -> list[str]:
    """Fill the export folder ``tmp``: images, transforms.json, the per-split files (when
    ``common`` is given: the tools can read them), PLY, COLMAP models, TUM trajectory; returns
    the per-split file names written."""
    import cv2

    split_files = []
    (tmp / "images").mkdir(parents=True)
    for i, f in enumerate(files):
        # imencode + a plain write: a full disk raises (cv2.imwrite only returns False)
        (tmp / f).write_bytes(cv2.imencode(".png", _bgr(ds, i))[1].tobytes())
    (tmp / "transforms.json").write_text(json.dumps(meta, indent=1))
    if common is not None:
        by_file = dict(zip(files, frames, strict=True))
        for s, names in lists.items():
            part = {**common, "frames": [by_file[f] for f in names]}
            (tmp / f"transforms_{s}.json").write_text(json.dumps(part, indent=1))
            split_files.append(f"transforms_{s}.json")
    if rec.num_points3D():
        rec.export_PLY(str(tmp / PLY_NAME))
    for sub, write in ((COLMAP_BINARY, rec.write_binary), (COLMAP_TEXT, rec.write_text)):
        (tmp / sub).mkdir(parents=True)
        write(str(tmp / sub))
    write_tum(tmp / TRAJECTORY, _times(ds), ds.poses)
    return split_files


def _times(ds: Dataset) -> np.ndarray:
    """Per-frame TUM timestamps: the capture time, else the source index, else the position."""
    if ds.timestamps is not None:
        return ds.timestamps
    return np.arange(ds.n, dtype=float) if ds.source_index is None else ds.source_index * 1.0


def _bgr(ds: Dataset, i: int) -> np.ndarray:
    """Frame i as OpenCV wants to write it: gray, BGR, or BGRA when there is alpha."""
    im = ds.images[i]
    if ds.alpha is not None:
        rgb = np.repeat(im, 3, axis=2) if im.shape[2] == 1 else im
        return np.dstack([rgb[:, :, ::-1], ds.alpha[i]])
    return im[:, :, 0] if im.shape[2] == 1 else im[:, :, ::-1]
