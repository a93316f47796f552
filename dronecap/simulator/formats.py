"""Capture writers: a video, or a drone capture folder with onboard telemetry.

Layouts (the telemetry contract; ``dronecap ingest`` reads them):

- ``mp4``: ``flight.mp4`` (FFV1 by default) plus ``flight.json`` beside it;
- ``nanocockpit``: ``FOLDER/camera_raw/00000.png ...`` (one 8-bit gray PNG per received frame)
  and ``FOLDER/metadata.csv`` with ``filename, frame_id, frame_timestamp, state_timestamp, x, y,
  z, vx, vy, vz, qx, qy, qz, qw``: the 8-bit hardware frame counter (wraps 255 -> 0; dropped
  frames leave gaps), capture and state times in microseconds, the latest onboard estimate
  (millimetres, mm/s, body-to-world quaternion scalar last) at the state time;
- ``pulp-dronet``: ``FOLDER/images/<ticks>.jpeg`` (gray JPEG named by the capture time in
  microseconds) and ``FOLDER/state.csv`` at ~100 Hz with ``timeTicks, stateEstimate.x/y/z``
  (metres) and ``stateEstimate.qx/qy/qz/qw``.

Folder formats get ``FOLDER/flight.json`` (ground truth, see :mod:`dronecap.simulator.simulate`).
Every output appears under its final name only when complete.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from dronecap.errors import InputError
from dronecap.files import atomic_output
from dronecap.simulator.video import write_gray_video

FORMATS = ("mp4", "nanocockpit", "pulp-dronet")
BOOT_US = 2_000_000  # capture clock at the first frame: the drone booted two seconds earlier
PULP_JPEG_QUALITY = 95  # quality of PULP-Dronet's JPEG files when no --jpeg level is given
NANOCOCKPIT_COLUMNS = (
    "filename", "frame_id", "frame_timestamp", "state_timestamp",
    "x", "y", "z", "vx", "vy", "vz", "qx", "qy", "qz", "qw",
)  # fmt: skip
PULP_COLUMNS = (
    "timeTicks", "stateEstimate.x", "stateEstimate.y", "stateEstimate.z",
    "stateEstimate.qx", "stateEstimate.qy", "stateEstimate.qz", "stateEstimate.qw",
)  # fmt: skip


def ticks(seconds: np.ndarray) -> np.ndarray:
    """Capture-clock microseconds (int64) of flight times in seconds."""
    return BOOT_US + np.rint(np.asarray(seconds) * 1e6).astype(np.int64)


def frame_files(fmt: str, source_frames: list[int], fps: float) -> list[str]:
    """File name (relative to the capture folder) of each delivered frame, in order."""
    if fmt == "nanocockpit":
        return [f"camera_raw/{k:05d}.png" for k in range(len(source_frames))]
    if fmt == "pulp-dronet":
        return [f"images/{t}.jpeg" for t in ticks(np.asarray(source_frames) / fps)]
    raise ValueError(f"{fmt} has no frame files")


def write_video(
    path: Path, images: Iterable[np.ndarray], fps: float, codec: str, doc: dict
) -> tuple[Path, Path]:
    """``path`` (the video) and its ground truth ``path.with_suffix('.json')``."""
    gt = path.with_suffix(".json")
    for p in (path, gt):
        if p.is_dir():
            raise InputError("is a folder, expected a file to write", p)
    write_gray_video(path, images, fps, codec)
    with atomic_output(gt) as tmp:
        tmp.write_text(json.dumps(doc))
    return path, gt


def write_folder(
    folder: Path,
    fmt: str,
    images: Iterable[np.ndarray],
    doc: dict,
    states: dict[str, np.ndarray],
    jpeg_quality: int,
) -> tuple[Path, Path]:
    """A capture folder of format ``fmt`` (nanocockpit or pulp-dronet).

    Args:
        images: uint8 [H, W] delivered frames, in the order of ``doc["frames"]``.
        doc: the ground-truth document; its frames carry ``file``, ``source_frame``.
        states: the onboard estimate, ``times`` [S] s, ``position`` [S, 3] m, ``velocity``
            [S, 3] m/s, ``quaternion`` [S, 4] xyzw.
        jpeg_quality: quality of the pulp-dronet JPEG files.

    Returns:
        (folder, its flight.json).
    """
    import cv2

    if folder.exists() and not folder.is_dir():
        raise InputError("output exists and is not a folder", folder)
    frames = doc["frames"]
    with atomic_output(folder) as tmp:
        (tmp / ("camera_raw" if fmt == "nanocockpit" else "images")).mkdir(parents=True)
        for rec, image in zip(frames, images, strict=True):
            params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if fmt == "pulp-dronet" else []
            if not cv2.imwrite(str(tmp / rec["file"]), image, params):
                raise InputError("cannot write a frame image (disk full or read-only?)", folder)
        state_ticks = ticks(states["times"])
        if fmt == "nanocockpit":
            _write_metadata(tmp / "metadata.csv", frames, state_ticks, states)
        else:
            _write_states(tmp / "state.csv", state_ticks, states)
        (tmp / "flight.json").write_text(json.dumps(doc))
    return folder, folder / "flight.json"


def _write_metadata(
    path: Path, frames: list[dict], state_ticks: np.ndarray, states: dict[str, np.ndarray]
) -> None:
    """NanoCockpit metadata.csv: one row per received frame, the latest state at capture."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(NANOCOCKPIT_COLUMNS)
        for rec in frames:
            t = int(rec["frame_timestamp"])
            k = max(0, int(np.searchsorted(state_ticks, t, side="right")) - 1)
            p, v = states["position"][k] * 1e3, states["velocity"][k] * 1e3
            q = states["quaternion"][k]
            w.writerow(
                [rec["file"], rec["frame_id"], t, int(state_ticks[k])]
                + [f"{x:.2f}" for x in (*p, *v)]
                + [f"{x:.7f}" for x in q]
            )


def _write_states(path: Path, state_ticks: np.ndarray, states: dict[str, np.ndarray]) -> None:
    """PULP-Dronet state.csv: every state row (metres, quaternion xyzw)."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(PULP_COLUMNS)
        for t, p, q in zip(state_ticks, states["position"], states["quaternion"], strict=True):
            w.writerow([int(t)] + [f"{x:.5f}" for x in p] + [f"{x:.7f}" for x in q])
