"""A swarm's flights in COLMAP's work folder: one image folder per drone, so that each drone gets
its own camera (``CameraMode.PER_FOLDER``) and every image name says which flight it belongs to.
A single flight keeps flat names (00000.png, ...)."""

from __future__ import annotations

import numpy as np


def image_names(drones: np.ndarray) -> list[str]:
    """Zero-padded PNG names in flight order, one per frame (``drones``: int [N], the drone of
    every frame): 00000.png, 00001.png, ... for one drone; for a swarm, a folder per drone
    (COLMAP gives each folder its own camera): d00/00000.png, ..., d01/00072.png, ..."""
    n = len(drones)
    width = max(5, len(str(max(n - 1, 0))))
    if n == 0 or int(np.max(drones)) == 0:
        return [f"{i:0{width}d}.png" for i in range(n)]
    return [f"{flight_folder(int(d))}/{i:0{width}d}.png" for i, d in enumerate(drones)]


def flight_folder(drone: int) -> str:
    """The image folder of a swarm's drone ``drone``: d00, d01, ..."""
    return f"d{drone:02d}"


def flight_of(name: str) -> int:
    """The drone of a work-folder image name (0 without a folder): :func:`image_names`."""
    return int(name.split("/")[0][1:]) if "/" in name else 0
