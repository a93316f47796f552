"""Which camera SfM starts from and what COLMAP may change: ``--camera fixed|refine|estimate``.

- **fixed**: the known camera (frames.h5 intrinsics from a calibration or the simulator's
  flight.json, or ``--camera-from`` an earlier posed.h5 of the same drone) is given to COLMAP
  with its distortion model and never changed. Known intrinsics are what make forward flights
  reconstructable (self-calibration scatters, see docs/sfm.md).
- **refine**: map with the known camera fixed, then one final bundle adjustment refines the focal
  length(s) and the distortion. The principal point stays where the calibration put it (on
  160-px frames COLMAP cannot pin it down; AI-deck calibrations put it 30-60 px off the centre
  row).
- **estimate**: self-calibration: mapping with one focal length and one radial term
  (SIMPLE_RADIAL), then a final bundle adjustment with a second radial term (RADIAL). With a
  known camera its principal point is kept (never assumed at the centre when it is known);
  without, COLMAP puts it at the image centre.
- **auto** (default): fixed when a camera is known (``camera_source`` "calibration" or
  "flight.json", a frames.h5 without the attribute but with intrinsics, or ``--camera-from``),
  estimate otherwise.

A swarm (frames.h5 with several drones) gets a camera per drone, all handled the same way: the
drone's own calibrated camera when every drone has one (fixed by default), otherwise estimated
per drone (shared by that drone's frames). ``--camera-from`` gives one drone's camera and is
refused for a swarm.

Pixel coordinates: dronecap cameras put the centre of pixel (u, v) at (u + 0.5, v + 0.5), as
COLMAP does, so parameters go to COLMAP unchanged.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.camera import Camera
from dronecap.camera.colmap import colmap_camera
from dronecap.datasets.format import Dataset, open_dataset
from dronecap.errors import InputError

ESTIMATE_FOCAL_FACTOR = 1.2  # COLMAP's first guess of f: 1.2 x the larger image side
# Self-calibration maps with one radial term: mapping with two from the first frames let k2 run
# away on the white lego orbit (k2 -4.1, 6 % registered). The final bundle adjustment adds the
# second term (REFINED_MODEL): with one alone the focal length absorbs the lens's k2 and came
# out +2 % on every drone of the simulated AI-deck swarm, with the second +0.5 %.
ESTIMATE_MODEL = "SIMPLE_RADIAL"
REFINED_MODEL = "RADIAL"
ASPECT_TOLERANCE = 0.01  # --camera-from: image aspect ratios may differ by this fraction


@dataclass(frozen=True)
class CameraPlan:
    """The camera handed to COLMAP and what bundle adjustment may refine."""

    mode: str  # "fixed" | "refine" | "estimate"
    camera: Camera | None  # start values; None: COLMAP guesses (ESTIMATE_MODEL, centred)
    source: str  # where the known camera came from ("calibration", a posed.h5 path, "none")
    others: tuple[Camera | None, ...] = ()  # a swarm: the cameras of drones 1, 2, ... (same mode)

    @property
    def cameras(self) -> tuple[Camera | None, ...]:
        """The start camera of every drone (one entry for a single flight)."""
        return (self.camera, *self.others)

    @property
    def refine(self) -> bool:
        """True when mapping refines focal length and distortion (estimate)."""
        return self.mode == "estimate"

    @property
    def refine_after(self) -> bool:
        """True when a final bundle adjustment refines them (refine, estimate). refine: mapping
        keeps the camera fixed, because refining a many-parameter model (OPENCV: 6 values) from
        the first few frames of a 160-px flight diverges (measured: fx 222 -> 458, k1 -0.15 ->
        -4.5); estimate: the final adjustment adds the second radial term (:func:`refined`)."""
        return self.mode in ("refine", "estimate")

    def colmap(self) -> tuple[str, list[float]] | None:
        """(COLMAP model name, params in COLMAP's order) or None (see ``camera.colmap``)."""
        return None if self.camera is None else colmap_camera(self.camera)

    def colmap_per_drone(self) -> list[tuple[str, list[float]] | None]:
        """:meth:`colmap` of every drone's camera."""
        return [None if k is None else colmap_camera(k) for k in self.cameras]


def camera_of_posed(path: Path, width: int, height: int) -> Camera:
    """The camera stored in an earlier reconstruction (posed.h5), scaled to ``width x height``.

    Raises:
        InputError: not a posed.h5 with intrinsics, or an image aspect that differs.
    """
    posed = open_dataset(path, kinds=("posed",))
    k = posed.intrinsics
    if k is None:
        raise InputError("--camera-from: this posed.h5 has no camera", path)
    aspect_a, aspect_b = k.width / k.height, width / height
    if abs(aspect_a / aspect_b - 1) > ASPECT_TOLERANCE:
        raise InputError(
            f"--camera-from: its camera is for {k.width}x{k.height} images, the frames are "
            f"{width}x{height} (different aspect ratio)",
            path,
        )
    return k if (k.width, k.height) == (width, height) else k.scaled_to(width, height)


def plan_camera(ds: Dataset, mode: str, camera_from: Path | None = None) -> CameraPlan:
    """Resolve ``--camera`` for the frames ``ds`` (see the module docstring).

    Raises:
        InputError: fixed/refine asked with no known camera, or a bad ``camera_from``.
    """
    h, w = ds.images.shape[1:3]
    drones = ds.drones()
    n_drones = int(drones.max()) + 1 if len(drones) else 1
    default = "calibration" if ds.intrinsics or ds.cameras else "none"
    source = str(ds.attrs.get("camera_source", default))
    if n_drones > 1:
        if camera_from is not None:
            raise InputError(
                "--camera-from gives one drone's camera; these frames come from "
                f"{n_drones} drones, each with its own camera in frames.h5"
            )
        firsts = [int(np.flatnonzero(drones == d)[0]) for d in range(n_drones)]
        known = [ds.camera_of(i) if source != "none" else None for i in firsts]
        if any(k is None for k in known):  # every drone estimated alike
            known = [None] * n_drones
        plans = [_plan(k, source, w, h, mode) for k in known]
        return dataclasses.replace(plans[0], others=tuple(p.camera for p in plans[1:]))
    known_one = ds.intrinsics if source != "none" else None
    if camera_from is not None:
        known_one, source = camera_of_posed(Path(camera_from), w, h), str(camera_from)
    return _plan(known_one, source, w, h, mode)


def _plan(known: Camera | None, source: str, w: int, h: int, mode: str) -> CameraPlan:
    """The plan of one camera (``known``: calibrated, or None) for ``w x h`` frames."""
    if mode == "auto":
        mode = "fixed" if known is not None else "estimate"
    if known is None:
        if mode != "estimate":
            raise InputError(
                f"--camera {mode} needs a known camera: ingest with --intrinsics (a calibration "
                "or flight.json) or give --camera-from an earlier posed.h5"
            )
        return CameraPlan("estimate", None, "none")
    if mode == "estimate":  # self-calibrate, but keep the known principal point
        f = ESTIMATE_FOCAL_FACTOR * max(w, h)
        start = Camera(f, f, known.cx, known.cy, w, h, ESTIMATE_MODEL, (0.0,))
        return CameraPlan("estimate", start, source)
    return CameraPlan(mode, dataclasses.replace(known), source)


def refined(rec: Any) -> Any:
    """``rec`` (a pycolmap Reconstruction) with every ``ESTIMATE_MODEL`` camera turned into a
    ``REFINED_MODEL`` one (the same f, cx, cy, k1 and k2 = 0), ready for the final adjustment."""
    import pycolmap

    one, two = (getattr(pycolmap.CameraModelId, m) for m in (ESTIMATE_MODEL, REFINED_MODEL))
    for cam in rec.cameras.values():
        if cam.model == one:
            params = [*cam.params, 0.0]
            cam.model = two
            cam.params = params
    return rec
