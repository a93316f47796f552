"""Import an instant-ngp / nerfstudio ``transforms.json`` dataset into a dronecap dataset.

Accepted layouts: a folder with ``transforms.json`` (nerfstudio; split lists
``train_filenames`` / ``val_filenames`` / ``test_filenames`` when present), a folder with
``transforms_{train,val,test}.json`` (instant-ngp / NeRF Synthetic; the split is the file), or
one ``.json`` file. What is read, with the tools' own meanings:

- the camera: ``fl_x`` / ``fl_y`` (or ``camera_angle_x`` / ``camera_angle_y`` in radians, or
  instant-ngp's ``x_fov`` / ``y_fov`` in degrees; ``fl_y`` defaults to ``fl_x``), ``cx`` / ``cy``
  (default: the image centre), ``w`` / ``h`` (default: the image size), ``camera_model`` and the
  distortion ``k1 k2 k3 k4 p1 p2`` (nerfstudio's meaning: OPENCV_FISHEYE takes k1..k4, the
  perspective models an OpenCV lens k1 k2 p1 p2 k3; instant-ngp's ``is_fisheye`` means
  OPENCV_FISHEYE) — top-level or per frame; per-frame cameras must all be the same camera
  (a dronecap dataset has one);
- per frame ``file_path`` (relative to the JSON; the extension may be missing) and
  ``transform_matrix`` (camera-to-world, OpenGL camera axes), ``dronecap_name`` when present;
- ``ply_file_path``: sparse points (with colours) for the bounds; ``aabb`` (instant-ngp's scene
  box): when present the poses keep their frame and this is the AABB — so a dronecap export
  imports back unchanged; ``applied_transform`` is then kept as the dataset's normalisation.

Bounds otherwise as for a captured flight (:mod:`dronecap.datasets.import_scene`), carved from
the train views' alpha for an object capture with a pinhole camera. Without any split the frames
get the every-8th test split of ``dronecap split``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.datasets.blender import opengl_to_opencv
from dronecap.datasets.format import SPLITS, Intrinsics, provenance, write_dataset
from dronecap.datasets.import_scene import (
    check_options,
    imported_dataset,
    read_images,
    resized_camera,
    scene_bounds,
    visible_points,
)
from dronecap.datasets.safe_paths import check_frame_count, check_import_memory, inside_folder
from dronecap.errors import InputError
from dronecap.files import sha256_file

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".exr", ".pgm")
CAMERA_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y",
               "x_fov", "y_fov", "camera_model", "is_fisheye",
               "k1", "k2", "k3", "k4", "p1", "p2")  # fmt: skip
PERSPECTIVE = ("PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def find_transforms(src: Path) -> list[tuple[Path, str | None]]:
    """The JSON file(s) of a source and the split each one holds (None: the file says)."""
    if src.is_file():
        return [(src, None)]
    if not src.is_dir():
        raise InputError("no such file or folder", src)
    if (src / "transforms.json").exists():
        return [(src / "transforms.json", None)]
    parts = [(src / f"transforms_{s}.json", s) for s in SPLITS]
    parts = [(p, s) for p, s in parts if p.exists()]
    if not parts:
        raise InputError("no transforms.json or transforms_{train,val,test}.json here", src)
    return parts


def _load(path: Path) -> dict[str, Any]:
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(f"not a readable JSON file: {err}", path) from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise InputError("has no 'frames' list (not a transforms.json)", path)
    if not meta["frames"]:
        raise InputError("has no frames", path)
    return meta


def image_path(root: Path, file_path: str) -> Path:
    """The image a ``file_path`` names (instant-ngp and NeRF Synthetic omit the extension)."""
    p = root / file_path.replace("\\", "/")
    if p.suffix.lower() in IMAGE_SUFFIXES or p.exists():
        return p
    for suffix in IMAGE_SUFFIXES:
        if p.with_name(p.name + suffix).exists():
            return p.with_name(p.name + suffix)
    return p


def camera_of(keys: dict[str, Any], width: int, height: int) -> Intrinsics:
    """The dronecap camera of nerfstudio/instant-ngp camera ``keys`` for ``width x height``
    images (see the module docstring).

    Raises:
        ValueError: no focal length, a non-numeric value, or a lens dronecap cannot express.
    """
    w, h = int(keys.get("w", width)), int(keys.get("h", height))

    def focal(axis: str, size: int) -> float | None:
        if f"fl_{axis}" in keys:
            return float(keys[f"fl_{axis}"])
        if f"camera_angle_{axis}" in keys:
            return size / (2 * np.tan(float(keys[f"camera_angle_{axis}"]) / 2))
        if f"{axis}_fov" in keys:
            return size / (2 * np.tan(np.radians(float(keys[f"{axis}_fov"])) / 2))
        return None

    fx, fy = focal("x", w), focal("y", h)
    if fx is None and fy is None:
        raise ValueError("no focal length (fl_x, camera_angle_x or x_fov)")
    fx, fy = fx or fy, fy or fx
    cx, cy = float(keys.get("cx", w / 2)), float(keys.get("cy", h / 2))
    d = {n: float(keys.get(n, 0.0)) for n in ("k1", "k2", "k3", "k4", "p1", "p2")}
    model = str(keys.get("camera_model", "OPENCV_FISHEYE" if keys.get("is_fisheye") else "OPENCV"))
    if model == "OPENCV_FISHEYE":
        radial = (d["k1"], d["k2"], d["k3"], d["k4"])
        k = Intrinsics(fx, fy, cx, cy, w, h, "OPENCV_FISHEYE", radial)
    elif model in PERSPECTIVE:
        if d["k4"]:
            raise ValueError(f"k4 = {d['k4']} (nerfstudio's r^8 term) has no OpenCV equivalent")
        opencv = (d["k1"], d["k2"], d["p1"], d["p2"])
        if d["k3"]:
            k = Intrinsics(fx, fy, cx, cy, w, h, "FULL_OPENCV", (*opencv, d["k3"], 0.0, 0.0, 0.0))
        elif any(opencv):
            k = Intrinsics(fx, fy, cx, cy, w, h, "OPENCV", opencv)
        else:
            k = Intrinsics(fx, fy, cx, cy, w, h)
    else:
        raise ValueError(f"camera_model {model!r} is not supported (perspective or OPENCV_FISHEYE)")
    if (w, h) != (width, height):
        raise ValueError(f"the camera is for {w}x{h} images but the images are {width}x{height}")
    problems = k.problems()
    if problems:
        raise ValueError(problems[0])
    return k


def import_transforms(
    src: str | Path,
    out_path: str | Path,
    size: int = 160,
    color: str = "auto",
    progress: bool = True,
) -> Path:
    """Read a transforms.json dataset and write it as a dronecap dataset (kind "dataset").

    Args:
        src: a folder (see the module docstring) or a ``.json`` file.
        out_path, size, color, progress: as for every importer
            (:mod:`dronecap.datasets.import_scene`).
    """
    check_options(size, color)
    src = Path(src)
    sources = find_transforms(src)
    entries: list[tuple[dict, dict, Path, str | None]] = []  # frame, file meta, its JSON, split
    metas = {}
    for path, split in sources:
        meta = metas[path] = _load(path)
        entries += [(fr, meta, path, split) for fr in meta["frames"]]
    first_json = sources[0][0]
    check_frame_count(len(entries), first_json)
    paths, poses = [], []
    for i, (fr, _, jpath, _) in enumerate(entries):
        try:
            m = np.asarray(fr["transform_matrix"], float)
            if m.shape == (3, 4):
                m = np.vstack([m, [0, 0, 0, 1]])
            if m.shape != (4, 4) or not np.isfinite(m).all():
                raise ValueError("transform_matrix is not a finite 4x4 matrix")
            paths.append(
                inside_folder(jpath.parent, image_path(jpath.parent, str(fr["file_path"])))
            )
        except (KeyError, TypeError, ValueError) as err:
            raise InputError(f"frame {i}: {err}", jpath) from None
        poses.append(m)
    check_import_memory(paths, size, first_json)
    imgs = read_images(paths, size, color, progress)
    table, index = _frame_cameras(entries, *imgs.source_size)
    k = resized_camera(table[0], imgs.images)
    c2w = opengl_to_opencv(np.stack(poses))
    split = _split(entries, paths, first_json)
    top = metas[first_json]
    points, colors = _ply_points(top, first_json)
    declared = _declared_box(top, first_json)
    masks = None
    if imgs.alpha is not None and k.is_pinhole:  # an object capture: carve as import-blender
        views = np.flatnonzero(split == SPLITS["train"])
        masks = (imgs.alpha[views], k, views)
    outer = None if declared is not None else ngp_box(top, first_json)
    b = scene_bounds(c2w, points, visible_points(c2w, k, points), declared, masks, k, outer)
    norm = b.normalization
    if declared is not None and "applied_transform" in top:
        norm = np.vstack([np.asarray(top["applied_transform"], float), [0, 0, 0, 1]])
    names = [str(fr.get("dronecap_name", fr["file_path"])) for fr, *_ in entries]
    ds = imported_dataset(
        imgs,
        (table, index),  # nerfstudio's per-frame intrinsics: a camera per frame
        b,
        names,
        split,
        colors,
        provenance(
            "import-transforms",
            {"src": str(src), "size": size, "color": color},
            {p.name: sha256_file(p) for p, _ in sources},
        ),
        {"source": "transforms.json"},
        normalization=norm,
    )
    return write_dataset(out_path, ds)


def _frame_cameras(entries: list, width: int, height: int) -> tuple[list[Intrinsics], np.ndarray]:
    """The distinct cameras of the frames (top-level keys overridden per frame, nerfstudio's
    per-frame intrinsics) in order of first use, and each frame's index among them (int [N])."""
    table: list[Intrinsics] = []
    index = np.zeros(len(entries), np.int64)
    for i, (fr, meta, jpath, _) in enumerate(entries):
        keys = {**{c: meta[c] for c in CAMERA_KEYS if c in meta},
                **{c: fr[c] for c in CAMERA_KEYS if c in fr}}  # fmt: skip
        try:
            k = camera_of(keys, width, height)
        except (ValueError, TypeError) as err:
            raise InputError(f"frame {i}: {err}", jpath) from None
        if k not in table:
            table.append(k)
        index[i] = table.index(k)
    return table, index


def _split(entries: list, paths: list[Path], first_json: Path) -> np.ndarray:
    """Per-frame split: the file's split, the *_filenames lists, or every 8th frame to test."""
    from dronecap.datasets.split import every_kth_split

    if entries[0][3] is not None:
        return np.array([SPLITS[s] for *_, s in entries], np.int8)
    meta = entries[0][1]
    lists = {s: meta.get(f"{s}_filenames") for s in SPLITS}
    if not any(v is not None for v in lists.values()):
        return every_kth_split(np.arange(len(entries)))
    index = {p.resolve(): i for i, p in enumerate(paths)}
    split = np.full(len(entries), -1, np.int8)
    for s in ("train", "val", "test"):  # later wins: a frame in val and test is a test frame
        for name in lists[s] or []:
            i = index.get(image_path(first_json.parent, str(name)).resolve())
            if i is None:
                raise InputError(f"{s}_filenames names {name!r}, which no frame has", first_json)
            if s != "train" and split[i] == SPLITS["train"]:
                raise InputError(f"{name!r} is in both train_filenames and {s}_filenames",
                                 first_json)  # fmt: skip
            split[i] = SPLITS[s]
    return split


def _ply_points(meta: dict, jpath: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Points [P, 3] (OpenGL world = the poses' world) and colours uint8 [P, 3] of the
    ``ply_file_path``, or empty."""
    if "ply_file_path" not in meta:
        return np.zeros((0, 3)), None
    import pycolmap

    path = jpath.parent / str(meta["ply_file_path"])
    if not path.exists():
        raise InputError("ply_file_path names a missing file", path)
    rec = pycolmap.Reconstruction()
    try:
        rec.import_PLY(str(path))
    except Exception as err:  # pycolmap raises plain RuntimeError on a bad PLY
        raise InputError(f"unreadable PLY: {err}", path) from None
    pts = list(rec.points3D.values())
    xyz = np.array([p.xyz for p in pts], float).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], np.uint8).reshape(-1, 3)
    return xyz, rgb


def _declared_box(meta: dict, jpath: Path) -> np.ndarray | None:
    if "aabb" not in meta:
        return None
    a = np.asarray(meta["aabb"], float)
    if a.shape != (2, 3) or not np.isfinite(a).all() or not (a[1] > a[0]).all():
        raise InputError(f"aabb must be [[min x,y,z], [max x,y,z]], found {meta['aabb']}", jpath)
    return a


NGP_SCALE, NGP_OFFSET = 0.33, (0.5, 0.5, 0.5)  # instant-ngp's defaults for "scale", "offset"


def ngp_box(meta: dict, jpath: Path) -> tuple[np.ndarray, str] | None:
    """instant-ngp's scene box in the file's frame, or None when ``aabb_scale`` is absent.

    instant-ngp maps a file position p to p' = P(p) * scale + offset, P the cyclic axis
    permutation (x, y, z) -> (y, z, x), and models the cube of side ``aabb_scale`` centred on
    (0.5, 0.5, 0.5) (the unit cube [0, 1]^3 when 1); ``colmap2nerf.py`` puts the cameras'
    look-at point at the origin and their mean distance at 4. So the box is centred on
    P^-1((0.5 - offset) / scale) with half side aabb_scale / (2 scale): [-6, 6]^3 for
    aabb_scale 4 with the defaults.
    """
    if "aabb_scale" not in meta:
        return None
    try:
        a = float(meta["aabb_scale"])
        scale = float(meta.get("scale", NGP_SCALE))
        offset = np.asarray(meta.get("offset", NGP_OFFSET), float).reshape(3)
    except (TypeError, ValueError) as err:
        raise InputError(f"aabb_scale / scale / offset: {err}", jpath) from None
    if not (a > 0 and scale > 0 and np.isfinite(offset).all()):
        raise InputError(f"aabb_scale {a} and scale {scale} must be positive", jpath)
    centre = np.roll((0.5 - offset) / scale, 1)  # ngp (y, z, x) back to the file's (x, y, z)
    half = a / (2 * scale)
    return np.stack([centre - half, centre + half]), f"the file's aabb_scale {a:g} box"
