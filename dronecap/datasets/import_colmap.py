"""Import a COLMAP sparse model and its images folder into a dronecap dataset.

Every registered image of the model becomes a frame (sorted by image name), with its pose
(COLMAP's camera-from-world inverted: camera-to-world, OpenCV axes, which COLMAP uses too) and
the model's camera (COLMAP and dronecap both centre pixel (u, v) at (u + 0.5, v + 0.5), so the
parameters carry over; SIMPLE_PINHOLE becomes PINHOLE). All registered images must share one
camera. The sparse points (with their colours) and the images each one is seen in give the bounds
exactly as ``dronecap sfm`` does for a captured flight (:func:`datasets.normalize.normalize_scene`,
:func:`datasets.normalize.near_far`); the points kept by the outlier removal are stored in the
dataset (``extra/points3d_xyz``, ``extra/points3d_rgb``, scene frame) for exports. Frames get
the every-8th test split of ``dronecap split``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dronecap.datasets.format import Intrinsics, provenance, write_dataset
from dronecap.datasets.import_scene import (
    check_options,
    imported_dataset,
    read_images,
    scene_bounds,
)
from dronecap.datasets.safe_paths import inside_folder
from dronecap.errors import InputError


def read_model(model_dir: str | Path) -> Any:
    """pycolmap.Reconstruction of a sparse model folder (binary or text).

    Raises:
        InputError: not a model folder, unreadable, or no registered image.
    """
    import pycolmap

    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise InputError("no such folder (expected a COLMAP model, e.g. sparse/0)", model_dir)
    if not any((model_dir / f"images.{ext}").exists() for ext in ("bin", "txt")):
        raise InputError("not a COLMAP model folder (no images.bin or images.txt)", model_dir)
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as err:  # pycolmap raises plain RuntimeError/ValueError on bad files
        raise InputError(f"unreadable COLMAP model: {err}", model_dir) from None
    if rec.num_reg_images() == 0:
        raise InputError("the COLMAP model has no registered image", model_dir)
    return rec


def model_cameras(rec: Any, model_dir: Path) -> dict[int, Intrinsics]:
    """The cameras of the registered images (COLMAP camera id -> dronecap camera).

    Raises:
        InputError: a COLMAP model dronecap has no lens for, or cameras of different image
            sizes (a dataset's images share one size).
    """
    from dronecap.camera.colmap import camera_from_colmap

    used = {rec.images[i].camera_id for i in rec.reg_image_ids()}
    cams = {}
    for cid in sorted(used):
        c = rec.cameras[cid]
        model = "PINHOLE" if c.model.name == "SIMPLE_PINHOLE" else c.model.name
        params = list(c.params)
        if c.model.name == "SIMPLE_PINHOLE":
            params = [params[0], params[0], params[1], params[2]]
        k = camera_from_colmap(model, params, c.width, c.height)
        if k.problems():
            raise InputError(f"camera {cid}: {k.problems()[0]}", model_dir)
        cams[cid] = k
    if len({(k.width, k.height) for k in cams.values()}) > 1:
        raise InputError(
            f"the registered images use {len(cams)} cameras of different image sizes; a "
            "dronecap dataset holds one size (import the images of each size separately)",
            model_dir,
        )
    return cams


def import_colmap(
    model_dir: str | Path,
    images_dir: str | Path,
    out_path: str | Path,
    size: int = 160,
    color: str = "auto",
    progress: bool = True,
) -> Path:
    """Read a sparse model + images and write a dronecap dataset (kind "dataset").

    Args:
        model_dir: COLMAP model folder (cameras, images, points3D as .bin or .txt).
        images_dir: the folder the model's image names are relative to.
        out_path, size, color, progress: as for every importer
            (:mod:`dronecap.datasets.import_scene`).
    """
    from dronecap.datasets.colmap_model import model_arrays
    from dronecap.datasets.split import every_kth_split
    from dronecap.files import sha256_file

    check_options(size, color)
    model_dir, images_dir = Path(model_dir), Path(images_dir)
    rec = read_model(model_dir)
    cams = model_cameras(rec, model_dir)
    if not images_dir.is_dir():
        raise InputError("no such images folder", images_dir)
    names = sorted(rec.images[i].name for i in rec.reg_image_ids())
    table, index = camera_table(rec, cams, names)
    k0 = table[0]
    _, c2w, points, seen = model_arrays(rec, names)
    ids = sorted(rec.points3D.keys())
    colors = np.array([rec.points3D[p].color for p in ids], np.uint8).reshape(-1, 3)
    imgs = read_images(
        [inside_folder(images_dir, images_dir / n) for n in names], size, color, progress
    )
    if imgs.source_size != (k0.width, k0.height):
        raise InputError(
            f"images are {imgs.source_size[0]}x{imgs.source_size[1]} but the model's camera is "
            f"for {k0.width}x{k0.height}",
            images_dir,
        )
    b = scene_bounds(c2w, points, seen)
    model_files = sorted(p for p in model_dir.iterdir() if p.is_file())
    ds = imported_dataset(
        imgs,
        (table, index),  # COLMAP's several cameras: a camera per frame
        b,
        names,
        every_kth_split(np.arange(len(names))),
        colors,
        provenance(
            "import-colmap",
            {"model": str(model_dir), "images": str(images_dir), "size": size, "color": color},
            {p.name: sha256_file(p) for p in model_files},
        ),
        {
            "source": "colmap",
            "colmap_registered": len(names),
            "colmap_images": int(rec.num_images()),
            "colmap_points": int(len(points)),
        },
    )
    return write_dataset(out_path, ds)


def camera_table(
    rec: Any, cams: dict[int, Intrinsics], names: list[str]
) -> tuple[list[Intrinsics], np.ndarray]:
    """The distinct cameras of the images ``names`` [N] (in order of first use; equal cameras
    under two ids are one) and each image's index among them, int64 [N]."""
    by_name = {img.name: img.camera_id for img in rec.images.values()}
    table: list[Intrinsics] = []
    index = np.zeros(len(names), np.int64)
    for i, name in enumerate(names):
        k = cams[by_name[name]]
        if k not in table:
            table.append(k)
        index[i] = table.index(k)
    return table, index
