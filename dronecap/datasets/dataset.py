"""The in-memory dataset: :class:`Dataset` (frames, poses, the camera table, drones), its error
type and the provenance record every file carries.

The file layout it is stored in is :mod:`dronecap.datasets.format`'s docstring; reading and
writing are :mod:`dronecap.datasets.read` and :mod:`dronecap.datasets.write`.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dronecap.camera import Camera
from dronecap.datasets import checks
from dronecap.datasets.checks import SPLITS
from dronecap.errors import InputError

Intrinsics = Camera  # the stored camera: dronecap.camera.Camera (one camera type)


class DatasetError(InputError):
    """A dataset file that cannot be used: foreign, newer, truncated or inconsistent."""


@dataclass
class Dataset:
    """An in-memory dronecap dataset. Arrays are indexed by frame along their first axis."""

    images: np.ndarray  # uint8 [N, H, W, C]
    kind: str = "dataset"
    alpha: np.ndarray | None = None  # uint8 [N, H, W]
    poses: np.ndarray | None = None  # float64 [N, 4, 4] camera-to-world, OpenCV axes
    intrinsics: Intrinsics | None = None
    names: list[str] | None = None
    source_index: np.ndarray | None = None  # int64 [N]
    timestamps: np.ndarray | None = None  # float64 [N] seconds
    split: np.ndarray | None = None  # int8 [N]: 0 train, 1 val, 2 test, -1 unassigned
    near_far: np.ndarray | None = None  # float64 [N, 2]
    aabb: np.ndarray | None = None  # float64 [2, 3] (min, max) in scene units
    normalization: np.ndarray | None = None  # float64 [4, 4]: x_scene = M @ x_source
    background: tuple[float, ...] | None = None  # in [0, 1], C values; None: no alpha
    shards: dict[str, np.ndarray] = field(default_factory=dict)  # name -> int16 [N]
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    attrs: dict[str, Any] = field(default_factory=dict)  # small JSON-able stage metadata
    cameras: list[Camera] | None = None  # the table of cameras (one per drone or import)
    camera_index: np.ndarray | None = None  # int16 [N] index into cameras of every frame
    drone: np.ndarray | None = None  # int16 [N] drone (source position 0..D-1) of every frame
    drone_names: list[str] | None = None  # [D] a name per drone (its source's name)

    @property
    def n(self) -> int:
        """Number of frames."""
        return int(self.images.shape[0])

    @property
    def channels(self) -> int:
        """1 for gray, 3 for RGB."""
        return int(self.images.shape[3])

    @property
    def hw(self) -> tuple[int, int]:
        """(height, width) in pixels."""
        return int(self.images.shape[1]), int(self.images.shape[2])

    def frame_name(self, i: int) -> str:
        """Name of frame ``i``: its source name, or ``frame_000123`` when the file has none."""
        return self.names[i] if self.names is not None else f"frame_{i:06d}"

    def camera_of(self, i: int) -> Camera:
        """The camera of frame ``i``: ``cameras[camera_index[i]]``, or the single camera."""
        if self.cameras is None or self.camera_index is None:
            if self.intrinsics is None:
                raise DatasetError("has no camera intrinsics")
            return self.intrinsics
        return self.cameras[int(self.camera_index[i])]

    def frame_cameras(self) -> list[Camera]:
        """The camera of every frame, [N] (one object shared by the frames of a camera)."""
        return [self.camera_of(i) for i in range(self.n)]

    def drones(self) -> np.ndarray:
        """The drone of every frame, int64 [N] (all 0 for a single flight)."""
        if self.drone is None:
            return np.zeros(self.n, np.int64)
        return np.asarray(self.drone, np.int64)

    def drone_name(self, d: int) -> str:
        """Name of drone ``d``: its source's name, or ``drone_<d>`` when the file has none."""
        return self.drone_names[d] if self.drone_names is not None else f"drone_{d}"

    def set_cameras(self, cameras: list[Camera], camera_index: np.ndarray) -> None:
        """Give frames their own cameras: ``camera_index`` int [N] into ``cameras``; sets
        ``intrinsics`` to the camera when there is exactly one, None otherwise."""
        self.cameras = list(cameras)
        self.camera_index = np.asarray(camera_index, np.int16)
        self.intrinsics = self.cameras[0] if len(self.cameras) == 1 else None

    def indices(self, split: str) -> np.ndarray:
        """Frame indices of a split ("train", "val", "test"), int64 [M]."""
        if self.split is None:
            raise DatasetError(f"has no train/test split (run `dronecap split`) for {split!r}")
        return np.flatnonzero(self.split == SPLITS[split])

    def same_as(self, other: Dataset) -> bool:
        """Every field equal to ``other``'s (arrays exactly, NaN where NaN): a file read back is
        the same data."""
        for f in dataclasses.fields(Dataset):
            x, y = getattr(self, f.name), getattr(other, f.name)
            if isinstance(x, dict) and any(isinstance(v, np.ndarray) for v in x.values()):
                if x.keys() != y.keys() or any(not _same_array(x[k], y[k]) for k in x):
                    return False
            elif isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
                if x is None or y is None or not _same_array(x, y):
                    return False
            elif x != y:
                return False
        return True

    def subset(self, idx: np.ndarray) -> Dataset:
        """A new Dataset holding frames ``idx`` (every per-frame array is sliced)."""
        idx = np.asarray(idx, dtype=np.int64)

        def take(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[idx]

        return dataclasses.replace(
            self,
            images=self.images[idx],
            alpha=take(self.alpha),
            poses=take(self.poses),
            names=None if self.names is None else [self.names[i] for i in idx],
            source_index=take(self.source_index),
            timestamps=take(self.timestamps),
            split=take(self.split),
            near_far=take(self.near_far),
            shards={k: v[idx] for k, v in self.shards.items()},
            camera_index=take(self.camera_index),
            drone=take(self.drone),
            extra=dict(self.extra),
            provenance=dict(self.provenance),
            attrs=dict(self.attrs),
        )

    def validate(self, path: str | Path | None = None) -> None:
        """Raise :class:`DatasetError` naming ``path`` and the field for the first problem found:
        schema, dtypes, shapes, non-finite values, non-rigid poses, a bad camera, bounds,
        near/far or background out of range."""
        problem = self.problem()
        if problem is not None:
            raise DatasetError(problem, path if path is not None else "<dataset>")

    def problem(self) -> str | None:
        """The first thing wrong with this dataset ("<field>: <problem>"), or None."""
        return checks.problem(self)


def _same_array(a: np.ndarray, b: np.ndarray) -> bool:
    """Same shape and values; NaN equals NaN in float arrays (a score that was not measured)."""
    a, b = np.asarray(a), np.asarray(b)
    return np.array_equal(a, b, equal_nan=a.dtype.kind in "fc" and b.dtype.kind in "fc")


def provenance(stage: str, params: dict[str, Any], inputs: dict[str, str]) -> dict[str, Any]:
    """Provenance record: the stage, its parameters and its inputs' content hashes."""
    return {
        "stage": stage,
        "params": params,
        "inputs": inputs,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
