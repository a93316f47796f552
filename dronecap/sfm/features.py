"""SIFT features of a flight's frames in a COLMAP database, with the cameras COLMAP maps them
with: one per drone, known or guessed (:func:`extract`); sparse footage again one octave finer
(:func:`extract_finer_when_sparse`); or the images and cameras alone (:func:`import_images`,
for features computed elsewhere: :mod:`dronecap.sfm.ray_front`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.sfm.camera_plan import ESTIMATE_MODEL
from dronecap.sfm.flights import flight_of
from dronecap.sfm.options import FINEST_OCTAVE, SfmOptions

MIN_KEYPOINTS = 16  # a frame with fewer SIFT keypoints cannot register (reported as textureless)


def extract(
    database: Path,
    image_dir: Path,
    names: list[str],
    opts: SfmOptions,
    cameras: list[tuple[str, list[float]] | None],
) -> dict[str, int]:
    """SIFT on CPU into ``database``: one camera shared by every image, or for a swarm (names
    in a folder per drone, ``reconstruct.image_names``) one camera per folder.

    Args:
        cameras: per drone, (COLMAP model name, params) when intrinsics are known (params in
            COLMAP's pixel convention), or None to let COLMAP guess a camera of
            ``ESTIMATE_MODEL`` from the image size.

    Returns:
        image name -> number of keypoints.
    """
    import pycolmap

    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = opts.num_threads
    ext.sift.max_num_features = opts.max_features
    ext.sift.first_octave = opts.first_octave
    ext.sift.peak_threshold = opts.peak_threshold
    mode, reader = _reader(cameras)
    pycolmap.extract_features(
        database,
        image_dir,
        image_names=names,
        camera_mode=mode,
        reader_options=reader,
        extraction_options=ext,
        device=pycolmap.Device.cpu,
    )
    with pycolmap.Database.open(database) as db:
        if len(cameras) > 1:
            _set_folder_cameras(db, cameras)
        return {im.name: db.num_keypoints_for_image(im.image_id) for im in db.read_all_images()}


def import_images(
    database: Path, image_dir: Path, names: list[str], cameras: list[tuple[str, list[float]] | None]
) -> None:
    """The images ``names`` and their cameras in a new ``database`` as :func:`extract` makes
    them, without features (:mod:`dronecap.sfm.ray_front` writes those)."""
    import pycolmap

    mode, reader = _reader(cameras)
    pycolmap.Database.open(database).close()  # import_images wants the file to exist
    pycolmap.import_images(database, image_dir, mode, names, reader)
    if len(cameras) > 1:
        with pycolmap.Database.open(database) as db:
            _set_folder_cameras(db, cameras)


def _reader(cameras: list[tuple[str, list[float]] | None]) -> tuple[Any, Any]:
    """COLMAP's camera mode and image reader options for ``cameras`` (per drone): one camera
    (known, or guessed as ``ESTIMATE_MODEL``) for one drone, one per folder for a swarm."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = ESTIMATE_MODEL
    if len(cameras) == 1 and cameras[0] is not None:
        reader.camera_model = cameras[0][0]
        reader.camera_params = ",".join(f"{v:.10g}" for v in cameras[0][1])
    mode = pycolmap.CameraMode.SINGLE if len(cameras) == 1 else pycolmap.CameraMode.PER_FOLDER
    return mode, reader


def _set_folder_cameras(db: Any, cameras: list[tuple[str, list[float]] | None]) -> None:
    """Give each drone's folder camera its known model and parameters (``cameras`` per drone;
    None: COLMAP's guess stays)."""
    import pycolmap

    done: set[int] = set()
    for im in db.read_all_images():
        known = cameras[flight_of(im.name)]
        if known is None or im.camera_id in done:
            continue
        old = db.read_camera(im.camera_id)
        cam = pycolmap.Camera(
            model=known[0],
            width=old.width,
            height=old.height,
            params=np.asarray(known[1], np.float64),
            camera_id=im.camera_id,
        )
        cam.has_prior_focal_length = True
        db.update_camera(cam)
        done.add(im.camera_id)


def extract_finer_when_sparse(
    database: Path,
    image_dir: Path,
    names: list[str],
    opts: SfmOptions,
    cameras: list[tuple[str, list[float]] | None],
) -> tuple[dict[str, int], int]:
    """:func:`extract` at ``opts.first_octave``; when the frames' median keypoint count is
    under ``opts.finer_below``, the database is built again one octave finer (never finer
    than :data:`FINEST_OCTAVE`) at the contrast threshold ``opts.finer_peak_threshold``.

    Returns:
        (image name -> number of keypoints, the first octave the database holds).
    """
    octave = opts.first_octave
    keypoints = extract(database, image_dir, names, opts, cameras)
    median = float(np.median(list(keypoints.values()))) if keypoints else 0.0
    if octave > FINEST_OCTAVE and median < opts.finer_below:
        database.unlink()
        octave -= 1
        finer = dataclasses.replace(
            opts, first_octave=octave, peak_threshold=opts.finer_peak_threshold
        )
        keypoints = extract(database, image_dir, names, finer, cameras)
    return keypoints, octave
