"""Repairs of a chosen model: frames whose pose jumps off the flight path registered again,
and a final bundle adjustment that refines the camera."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.sfm.camera_plan import refined
from dronecap.sfm.colmap_steps import incremental_map
from dronecap.sfm.flights import flight_of
from dronecap.sfm.options import SfmOptions
from dronecap.sfm.report import pose_jumps


def jump_frames(model: Path, names: list[str]) -> list[int]:
    """Frame indices (into ``names``) of ``model`` that :func:`pose_jumps` flags (each drone's
    flight on its own)."""
    import pycolmap

    rec = pycolmap.Reconstruction(model)
    pos = {n: i for i, n in enumerate(names)}
    regs = sorted((pos[rec.images[i].name], i) for i in rec.reg_image_ids())
    centres = np.array([rec.images[i].projection_center() for _, i in regs]).reshape(-1, 3)
    frames = np.array([f for f, _ in regs], dtype=np.int64)
    flights = np.array([flight_of(names[f]) for f in frames], dtype=np.int64)
    return pose_jumps(centres, frames, flights)


def remap_jumps(
    database: Path,
    image_dir: Path,
    work: Path,
    model: Path,
    jumps: list[int],
    names: list[str],
    opts: SfmOptions,
    refine_camera: bool,
    on_register: Callable[[int], None],
) -> tuple[str, dict[str, Any]]:
    """Deregister the ``jumps`` frames of ``model`` and resume mapping (the extension pass's
    relaxed thresholds) into ``work/unjumped``, so that they register again against the settled
    points.

    A frame registered early, against few points of distant structure, can take a pose that
    fits its points but not the flight (a sideways shift traded for a rotation); later the
    points are many and its PnP finds the right pose (Himax test_15: frame 19 re-registers on
    its neighbours' path). Returns the model folder to keep (the new one when it has as many
    frames and fewer jumps) and a record for the report.
    """
    import pycolmap

    rec = pycolmap.Reconstruction(model)
    size = rec.num_reg_images()
    for image_id in list(rec.reg_image_ids()):
        if names.index(rec.images[image_id].name) in jumps:
            rec.deregister_frame(rec.images[image_id].frame_id)
    start = work / "unjumped_start"
    start.mkdir(parents=True, exist_ok=True)
    rec.write(start)
    found = incremental_map(
        database, image_dir, work / "unjumped", opts, refine_camera, on_register, start
    )
    record: dict[str, Any] = {"frames": jumps, "kept": False}
    if found:
        k = max(found, key=lambda j: found[j]["frames"])
        left = jump_frames(Path(k), names)
        if found[k]["frames"] >= size and len(left) < len(jumps):
            record.update(kept=True, still_jumping=left)
            return k, record
    return str(model), record


def refine_camera_of(model: Path, out: Path, second_term: bool) -> str:
    """Bundle-adjust ``model`` refining focal length(s) and distortion (not the principal
    point); with ``second_term`` (a self-calibrated camera, ``--camera estimate``) its
    one-term cameras get a second radial term first (``camera_plan.refined``), while a
    calibrated camera (``--camera refine``) keeps its model. Written to ``out``, whose path is
    returned."""
    import pycolmap

    rec = pycolmap.Reconstruction(model)
    rec = refined(rec) if second_term else rec
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = True
    ba.refine_extra_params = True
    ba.refine_principal_point = False
    pycolmap.bundle_adjustment(rec, ba)
    out.mkdir(parents=True, exist_ok=True)
    rec.write(out)
    return str(out)
